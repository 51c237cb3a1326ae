"""Intel Open Image Denoise 2.5 (``pyoidn``, optional): the pretrained denoiser a learned method is
measured against.

Fed as issue 19's measurement fed it: the noisy color of a few-ray render, the AO-free shading
as albedo and the view-space normals, both noise-free (``clean_aux``), LDR. Runs on the tensors'
device: OIDN's CPU device for CPU tensors, its CUDA device for CUDA tensors (where the
installed OIDN has the CUDA library; ``shared/gpu/oidn`` carries one to the GPU machine).
"""

from __future__ import annotations

import functools
import importlib.util

import torch

# OIDN's quality modes, fastest first.
QUALITIES = ("fast", "balanced", "high")


@functools.cache
def unavailable() -> str | None:
    """Why OIDN cannot run in this installation (``pyoidn`` not installed, or its library not
    loading), or None."""
    if importlib.util.find_spec("pyoidn") is None:
        return ("the pyoidn package is not installed (`pip install pyoidn`, or the isosr[oidn] extra; "
                "shared/gpu/oidn/README.md for the GPU machine)")
    try:
        import pyoidn  # noqa: F401
    except (ImportError, OSError) as e:
        return f"the pyoidn package does not load: {e}"
    return None


def denoise(color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, quality: str = "high") -> torch.Tensor:
    """The denoised color, clamped to [0, 1].

    Args:
        color: the noisy color in [0, 1].
        albedo: the noise-free AO-free shading in [0, 1].
        normal: noise-free normals in [-1, 1] (0 where nothing was hit).
        quality: one of :data:`QUALITIES`.

    Raises:
        RuntimeError: pyoidn is not installed, or OIDN fails (e.g. no CUDA device in its build).
        ValueError: a quality not of :data:`QUALITIES`, or shapes that differ.

    Shape:
        color, albedo, normal: (H, W, 3). Returns (H, W, 3) float32 on ``color``'s device.
    """
    if (reason := unavailable()) is not None:
        raise RuntimeError(f"oidn: {reason}")
    if quality not in QUALITIES:
        raise ValueError(f"oidn: quality must be one of {QUALITIES}, got {quality!r}")
    for name, t in (("albedo", albedo), ("normal", normal)):
        if t.shape != color.shape or color.ndim != 3 or color.shape[-1] != 3:
            raise ValueError(f"oidn: color must be (H, W, 3) and {name} its shape, got {tuple(color.shape)} "
                             f"and {tuple(t.shape)}")
    import pyoidn

    out = pyoidn.denoise(color.float().contiguous(), albedo=albedo.float().contiguous(),
                         normal=normal.float().contiguous(), clean_aux=True, quality=quality)
    return out.clamp_(0.0, 1.0)
