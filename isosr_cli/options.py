"""Option types the commands share."""

from __future__ import annotations

import argparse


def frame_size(text: str) -> tuple[int, int]:
    """``WxH`` as ``(width, height)``, both positive (an argparse type)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 640x480, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"a frame's sides must be positive, got {text!r}")
    return w, h
