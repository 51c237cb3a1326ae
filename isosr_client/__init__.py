"""isosr_client: thin clients that upscale and shade low-res buffers (floor 3)."""
