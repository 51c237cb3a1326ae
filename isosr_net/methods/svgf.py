"""Full resolution, few AO rays accumulated along the flow and filtered (SVGF, :mod:`isosr_net.filters.svgf`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from isosr_net.filters.svgf import SVGFConfig, SVGFHistory, svgf_filter
from isosr_net.methods.base import FrameMethod, FrameRunner, RayOptions, count, register_runner
from isosr_net.timing import StageTimer
from isosr_render import FrameBuffers
from isosr_render.renderer import MAX_AO_SAMPLES


@dataclass(frozen=True)
class SVGFOptions(RayOptions):
    """The rays SVGF accumulates and filters: at least one AO ray per hit."""

    ao_rays: int = count(1, 1, MAX_AO_SAMPLES)


@register_runner("svgf")
class SVGFRunner(FrameRunner):
    """Full resolution, AO from 1-4 (or more) rays per hit, a new set of rays each frame, accumulated
    along the flow and filtered by SVGF (:func:`isosr_net.filters.svgf.svgf_filter`); a frame without a
    previous camera starts the history anew."""

    label = "filtered AO (SVGF)"
    plot_color = "C5"

    recurrent = True
    fresh_rays = True
    options_type = SVGFOptions
    config: ClassVar[SVGFConfig] = SVGFConfig()  # the temporal knobs (the a-trous ones: the runner's atrous)

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.history: SVGFHistory | None = None

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """1, 2, 4 AO rays (smoke: 2)."""
        return [FrameMethod.of(cls.kind, ao_rays=n) for n in ((2,) if smoke else (1, 2, 4))]

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, svgf" + (f", spp {m.spp}" if m.spp > 1 else "")

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "depth", "position", "ao")

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal", "ao")

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        flow = None if rendered.flow is None else rendered.flow.permute(2, 0, 1)[None]
        with timer("filter"):
            ao, self.history = svgf_filter(rendered.ao[None, None], rendered.mask[None, None],
                                           rendered.normal.permute(2, 0, 1)[None], rendered.depth[None, None],
                                           rendered.position.permute(2, 0, 1)[None], flow, self.prev_camera,
                                           self.history, self.config, self.atrous)
        return self.colored(FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=ao[0, 0]), timer, rendered)
