"""Shape and integer checks: the helpers every stage uses to refuse tensors of the wrong shape
and counts out of range.

    dims = check_shape(pred, "(B, C, H, W)", "pred", "masked_psnr")
    check_shape(mask, "(B, 1, H, W)", "mask", "masked_psnr", dims)   # B, H, W as pred's

A spec is written as in the Shape sections of the docstrings: integers must match exactly,
names bind a size (a name used twice, or given in ``dims``, must have the same size each
time), ``5|6`` accepts any of those sizes, and a leading ``*`` any number of leading dims.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping


def _parse(spec: str) -> list[str]:
    tokens = [t.strip() for t in spec.strip().removeprefix("(").removesuffix(")").split(",")]
    tokens = [t for t in tokens if t]
    if not tokens or "*" in tokens[1:]:
        raise ValueError(f"check_shape: bad spec {spec!r} (a '*' may only lead)")
    return tokens


def check_shape(x, spec: str, name: str, where: str, dims: Mapping[str, int] | None = None) -> dict[str, int]:
    """Raise ValueError unless ``x.shape`` matches ``spec``; return the sizes its names bound.

    Args:
        x: anything with a ``shape`` (torch tensor, numpy array).
        spec: the expected shape, e.g. ``"(B, 5, H, W)"``, ``"(*, H, W, 3)"``, ``"(B, 5|6, H, W)"``.
        name: the argument's name, for the message.
        where: the function or class that checks, for the message.
        dims: sizes already bound by other arguments (the result of an earlier check).

    Returns:
        ``dims`` updated with the sizes of this shape's names.

    Raises:
        ValueError: ``"{where}: {name} must be {spec}[ with B=2, ...], got (…)"``.
    """
    tokens = _parse(spec)
    shape = tuple(int(s) for s in x.shape)
    known = dict(dims or {})
    bound = dict(known)
    leading = tokens[0] == "*"
    fixed = tokens[1:] if leading else tokens
    ok = len(shape) >= len(fixed) if leading else len(shape) == len(fixed)
    if ok:
        for token, size in zip(fixed, shape[len(shape) - len(fixed):]):
            if all(part.isdigit() for part in token.split("|")):
                ok = size in {int(part) for part in token.split("|")}
            elif token in bound:
                ok = bound[token] == size
            else:
                bound[token] = size
            if not ok:
                break
    if not ok:
        given = [f"{k}={v}" for k, v in known.items() if k in fixed]
        spec_text = "(" + ", ".join(tokens) + ")"
        raise ValueError(f"{where}: {name} must be {spec_text}{' with ' + ', '.join(given) if given else ''}, "
                         f"got {shape}")
    return bound


def check_int(value, name: str, low: int, high: int | None = None, where: str = "") -> int:
    """Raise ValueError unless ``value`` is an integer (not a bool) in ``[low, high]`` (``high``
    None: no upper bound); returns it. The one integer check of every stage's settings."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
        span = f"[{low}, {high}]" if high is not None else f">= {low}"
        raise ValueError(f"{where + ': ' if where else ''}{name} must be an integer {'in ' if high is not None else ''}"
                         f"{span}, got {value!r}")
    return value


def frame_size(text: str) -> tuple[int, int]:
    """``WxH`` as ``(width, height)``, both positive (an argparse type)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 640x480, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"a frame's sides must be positive, got {text!r}")
    return w, h
