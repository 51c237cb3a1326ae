"""isosr_server: the FastAPI frame-streaming service (floor 3)."""
