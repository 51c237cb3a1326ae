"""`FrameBuffers`: the typed structure in which a rendered frame travels between stages."""

from __future__ import annotations

import os
from collections.abc import Sequence
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
        mask, depth, ao: (H, W). normal, position, color, albedo: (H, W, 3). flow, cap: (H, W, 2).
        surface: (H, W), the index of the isosurface shown (several surfaces), -1 where none.
        samples: (H, W) int32, volume samples taken per pixel (a diagnostic).

    ``behind``, not a buffer: with translucent surfaces (:mod:`isosr_render.surfaces`), the second layer's
    buffers (where the rays go on past a translucent first hit); :meth:`clone` and :meth:`to` carry it, a frame
    file holds the first layer only.
    """

    mask: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    position: torch.Tensor | None = None
    flow: torch.Tensor | None = None
    ao: torch.Tensor | None = None
    color: torch.Tensor | None = None
    cap: torch.Tensor | None = None
    albedo: torch.Tensor | None = None
    surface: torch.Tensor | None = None
    samples: torch.Tensor | None = None
    behind: FrameBuffers | None = None

    def present(self) -> list[str]:
        """Names of the buffers this frame holds, in field order (``behind`` is none of them)."""
        return [f.name for f in fields(self) if f.name != "behind" and getattr(self, f.name) is not None]

    def channels_first(self, names: tuple[str, ...]) -> torch.Tensor:
        """The named buffers stacked channels-first in that order: (C, H, W). With
        ``LOWRES_BUFFERS`` / ``HIGHRES_BUFFERS`` this is the network's channel order.

        Raises:
            ValueError: a named buffer is missing.
        """
        parts = []
        for name in names:
            t = getattr(self, name)
            if t is None:
                raise ValueError(f"the frame lacks its {name} buffer")
            parts.append(t[None] if t.ndim == 2 else t.permute(2, 0, 1))
        return torch.cat(parts)

    def clone(self) -> FrameBuffers:
        """A copy of the present buffers (to keep a frame whose maker reuses its memory)."""
        return FrameBuffers(**{name: getattr(self, name).clone() for name in self.present()},
                            behind=None if self.behind is None else self.behind.clone())

    def to(self, device: torch.device | str) -> FrameBuffers:
        """The present buffers on ``device`` (the same tensors where they are there already)."""
        return FrameBuffers(**{name: getattr(self, name).to(device) for name in self.present()},
                            behind=None if self.behind is None else self.behind.to(device))

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
        return cls(**{k: torch.from_numpy(v) for k, v in _read_checked(path, time_axis=False).items()})


def stacked(frames: Sequence[FrameBuffers], name: str) -> torch.Tensor | None:
    """The buffer ``name`` of several frames of one size, stacked (a batch's); None where the first has none.

    Shape:
        Returns (B, *the buffer's).
    """
    return None if getattr(frames[0], name) is None else torch.stack([getattr(f, name) for f in frames])


def save_sequence(frames: list[FrameBuffers], path: str | os.PathLike) -> None:
    """Write frames as one ``.npz`` with a leading time axis per buffer (atomically).

    Every frame must hold the same buffers; shapes become (T, H, W[, C]).
    """
    if not frames:
        raise ValueError("save_sequence needs at least one frame")
    names = frames[0].present()
    if any(f.present() != names for f in frames):
        raise ValueError("every frame of a sequence must hold the same buffers")
    arrays = {n: np.stack([getattr(f, n).detach().cpu().numpy() for f in frames]) for n in names}
    atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load_sequence(path: str | os.PathLike) -> list[FrameBuffers]:
    """Read a sequence file (buffers with a leading time axis), checking names and shapes."""
    arrays = _read_checked(path, time_axis=True)
    length = next(iter(arrays.values())).shape[0]
    return [FrameBuffers(**{k: torch.from_numpy(np.ascontiguousarray(a[t])) for k, a in arrays.items()})
            for t in range(length)]


def _read_checked(path: str | os.PathLike, time_axis: bool) -> dict[str, np.ndarray]:
    """The arrays of a frame or sequence file, after checking their names and shapes."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if not arrays:
        raise ValueError(f"{path}: holds no buffers")
    unknown = set(arrays) - {f.name for f in fields(FrameBuffers)}
    if unknown:
        raise ValueError(f"{path}: unknown buffers {sorted(unknown)}; expected some of {BUFFER_NAMES}")
    lead = "T, " if time_axis else ""
    for name, a in arrays.items():
        channels = BUFFER_CHANNELS.get(name, 1)
        want = (2 if channels == 1 else 3) + time_axis
        if a.ndim != want or (channels > 1 and a.shape[-1] != channels):
            raise ValueError(f"{path}: buffer {name} has shape {a.shape}, expected ({lead}H, W"
                             + (f", {channels})" if channels > 1 else ")"))
    if len({a.shape[:2 + time_axis] for a in arrays.values()}) != 1:
        raise ValueError(f"{path}: buffers disagree in size: { {k: a.shape for k, a in arrays.items()} }")
    return arrays
