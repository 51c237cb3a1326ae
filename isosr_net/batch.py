"""`SequenceBatch`: sequences of network inputs and ground truth, as datagen renders them, the
dataset holds them, and training and evaluation consume them.

Channel orders: :data:`isosr_render.conventions.LOWRES_CHANNELS` / ``HIGHRES_CHANNELS``. The
first frame of a sequence has no previous frame: its flow slot is stored as zeros (a
sequence is one tensor per buffer) and never read; :meth:`SequenceBatch.flow_at` gives None.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from isosr_render.conventions import HIGHRES_CHANNELS, LOWRES_CHANNELS, RECON_CHANNELS
from isosr_render.shapes import check_shape

FIELDS = ("lowres", "flow", "highres")


@dataclass
class SequenceBatch:
    """One sequence, or a batch of them (a leading batch axis).

    Attributes:
        lowres: the network's input per frame: low-res mask, normal, depth (an upscaler's), or
            full-resolution buffers with sampled AO and its sampling (a reconstruction
            network's, :data:`isosr_render.conventions.RECON_CHANNELS`).
        flow: backward flow to the previous frame, low-res pixels; frame 0's slot is unused.
        highres: ground-truth mask, normal, depth, AO per frame.

    Shape:
        lowres: (*, T, 5 or 8, h, w). flow: (*, T, 2, h, w). highres: (*, T, 6, H, W); ``*`` is
        empty for one sequence and (B,) for a batch, the same for all three.
    """

    lowres: torch.Tensor
    flow: torch.Tensor
    highres: torch.Tensor

    def __post_init__(self) -> None:
        dims = check_shape(self.lowres, f"(*, T, {len(LOWRES_CHANNELS)}|{len(RECON_CHANNELS)}, h, w)", "lowres",
                           "SequenceBatch")
        check_shape(self.flow, "(*, T, 2, h, w)", "flow", "SequenceBatch", dims)
        check_shape(self.highres, f"(*, T, {len(HIGHRES_CHANNELS)}, H, W)", "highres", "SequenceBatch", dims)
        lead = {name: tuple(getattr(self, name).shape[:-4]) for name in FIELDS}
        if len(set(lead.values())) != 1:
            raise ValueError(f"SequenceBatch: lowres, flow and highres need the same leading dims, got {lead}")

    @property
    def frames(self) -> int:
        """Frames per sequence, T."""
        return self.lowres.shape[-4]

    def flow_at(self, t: int) -> torch.Tensor | None:
        """Frame ``t``'s flow, None on the first frame (no previous frame). Shape: (*, 2, h, w)."""
        return None if t == 0 else self.flow[..., t, :, :, :]

    def apply(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> SequenceBatch:
        """A batch of ``fn`` applied to each tensor (a dtype, a device, an index)."""
        return SequenceBatch(*(fn(getattr(self, name)) for name in FIELDS))

    def float(self) -> SequenceBatch:
        return self.apply(lambda t: t.float())

    def to(self, device: str | torch.device) -> SequenceBatch:
        return self.apply(lambda t: t.to(device))

    def __getitem__(self, index) -> SequenceBatch:
        """Sequences of a batch by index, slice or index tensor."""
        if self.lowres.ndim != 5:
            raise ValueError("SequenceBatch: only a batch (with a leading batch axis) can be indexed")
        return self.apply(lambda t: t[index])

    def __len__(self) -> int:
        """Sequences in a batch."""
        if self.lowres.ndim != 5:
            raise ValueError("SequenceBatch: one sequence has no length; frames counts its frames")
        return self.lowres.shape[0]

    def tensors(self) -> dict[str, torch.Tensor]:
        """The tensors by name (the keys of a datagen shard)."""
        return {name: getattr(self, name) for name in FIELDS}

    @classmethod
    def cat(cls, batches: Sequence[SequenceBatch]) -> SequenceBatch:
        """Batches joined along the batch axis."""
        return cls(*(torch.cat([getattr(b, name) for b in batches]) for name in FIELDS))
