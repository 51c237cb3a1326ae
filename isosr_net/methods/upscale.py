"""A low-res ray cast upscaled by interpolation (no AO: an interpolator knows none)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from isosr_net.inference import (
    output_buffers,
)
from isosr_net.methods.base import FrameMethod, FrameRunner, LowResOptions, choice, register_runner
from isosr_net.metrics import INTERPOLATIONS, upscale_baseline
from isosr_net.reconnet import RayLimits
from isosr_net.timing import StageTimer
from isosr_render import FrameBuffers
from isosr_render.conventions import LOWRES_BUFFERS


@dataclass(frozen=True)
class UpscaleOptions(LowResOptions):
    """A low-res render's factor and how it is upscaled.

    Attributes:
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"``.
    """

    interpolation: str = choice("bilinear", INTERPOLATIONS)


@register_runner("upscale")
class ClassicUpscaleRunner(FrameRunner):
    """A low-res ray cast upscaled by interpolation, shaded without AO."""

    label = "classic upscaling"
    serve_bench_ao = (0,)
    plot_color = "C2"

    low_res = True
    options_type = UpscaleOptions

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """x2, x4, x8 by each interpolation (smoke: x2 bicubic, x4 nearest and bilinear)."""
        upscales = (((2, "bicubic"), (4, "nearest"), (4, "bilinear")) if smoke else
                    [(f, mode) for f in (2, 4, 8) for mode in INTERPOLATIONS])
        return [FrameMethod.of(cls.kind, factor=f, interpolation=mode) for f, mode in upscales]

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """Bilinear x4 and x2: the cheapest of all."""
        return (0, FrameMethod.of(cls.kind, factor=4)), (1, FrameMethod.of(cls.kind, factor=2))

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} {m.options.interpolation}"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("filter"):
            up = upscale_classic(rendered, self.method.factor, self.method.options.interpolation)
        up.ao = None  # no AO: shaded unoccluded
        return self.colored(up, timer, rendered)


def upscale_classic(low: FrameBuffers, factor: int, interpolation: str = "bilinear") -> FrameBuffers:
    """A low-res frame's mask, normal and depth upscaled by interpolation
    (:func:`isosr_net.metrics.upscale_baseline`), as the network's outputs are laid out; AO is 1
    everywhere: an interpolator knows no occlusion.

    Shape:
        low: mask, depth (h, w), normal (h, w, 3). Returns mask, depth, ao (H, W), normal (H, W, 3),
        ``H = h * factor``, ``W = w * factor``.
    """
    return output_buffers(upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], factor, interpolation))
