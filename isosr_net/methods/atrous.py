"""Full resolution, few AO rays smoothed by the edge-avoiding a-trous filter (:mod:`isosr_net.filters.atrous`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from isosr_net.filters.atrous import atrous_filter
from isosr_net.methods.base import FrameMethod, FrameRunner, RayOptions, count, register_runner
from isosr_net.reconnet import RayLimits
from isosr_net.timing import StageTimer
from isosr_render import FrameBuffers
from isosr_render.renderer import MAX_AO_SAMPLES


@dataclass(frozen=True)
class ATrousOptions(RayOptions):
    """The rays the a-trous filter smooths: at least one AO ray per hit."""

    ao_rays: int = count(4, 1, MAX_AO_SAMPLES)


@register_runner("atrous")
class ATrousRunner(FrameRunner):
    """Full resolution, AO from 1-4 (or more) rays per hit smoothed by the edge-avoiding a-trous filter."""

    label = "filtered AO (a-trous)"
    serve_bench_ao = (2,)
    plot_color = "C1"

    options_type = ATrousOptions

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """1, 2, 4 AO rays (smoke: 2)."""
        return [FrameMethod.of(cls.kind, ao_rays=n) for n in ((2,) if smoke else (1, 2, 4))]

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """1, 2, 4 AO rays."""
        return tuple((rank, FrameMethod.of(cls.kind, ao_rays=n)) for rank, n in ((6, 1), (11, 2), (15, 4)))

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, a-trous" + (f", spp {m.spp}" if m.spp > 1 else "")

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "depth", "ao")

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal", "ao")

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("filter"):
            ao = atrous_filter(rendered.ao[None, None], rendered.mask[None, None],
                               rendered.normal.permute(2, 0, 1)[None], rendered.depth[None, None], self.atrous)[0, 0]
        return self.colored(FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=ao), timer, rendered)
