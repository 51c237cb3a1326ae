"""`FrameBuffers`: the typed structure in which a rendered frame travels between stages."""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

import numpy as np
import torch

from isosr_render.atomic import atomic_write
from isosr_render.conventions import BUFFER_CHANNELS, BUFFER_NAMES


@dataclass
class FrameBuffers:
    """One frame's buffers as torch tensors, ``None`` where a buffer was not asked for.

    Conventions (units, frames, ranges): :mod:`isosr_render.conventions`.

    Shape:
        mask, depth, ao: (H, W). normal, position, color: (H, W, 3). flow: (H, W, 2).
        samples: (H, W) int32, volume samples taken per pixel (a diagnostic).
    """

    mask: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    position: torch.Tensor | None = None
    flow: torch.Tensor | None = None
    ao: torch.Tensor | None = None
    color: torch.Tensor | None = None
    samples: torch.Tensor | None = None

    def present(self) -> list[str]:
        """Names of the buffers this frame holds, in field order."""
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]

    def to_numpy(self) -> dict[str, np.ndarray]:
        """The present buffers as numpy arrays (a copy only where they live on a GPU)."""
        return {name: getattr(self, name).detach().cpu().numpy() for name in self.present()}

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write the frame file atomically (all buffers or no file)."""
        arrays = self.to_numpy()
        atomic_write(path, lambda f: np.savez_compressed(f, **arrays))

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> "FrameBuffers":
        """Read a frame file written by :meth:`save_npz`, checking names and shapes."""
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        unknown = set(arrays) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"{path}: unknown buffers {sorted(unknown)}; expected some of {BUFFER_NAMES}")
        for name, a in arrays.items():
            channels = BUFFER_CHANNELS.get(name, 1)
            want = 2 if channels == 1 else 3
            if a.ndim != want or (channels > 1 and a.shape[-1] != channels):
                raise ValueError(f"{path}: buffer {name} has shape {a.shape}, expected (H, W"
                                 + (f", {channels})" if channels > 1 else ")"))
        return cls(**{k: torch.from_numpy(v) for k, v in arrays.items()})
