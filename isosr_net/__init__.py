"""isosr_net: the super-resolution network, flow warping, losses, training and inference (floor 2)."""
