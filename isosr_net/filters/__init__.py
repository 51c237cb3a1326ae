"""Classic filters the frame methods run: a-trous, SVGF, OIDN."""
