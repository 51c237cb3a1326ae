"""isosr_bench: timing and accuracy studies (floor 3); run as `python -m isosr_bench.<name>`."""
