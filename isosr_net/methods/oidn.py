"""Full resolution, few AO rays denoised by Intel Open Image Denoise (optional: where ``pyoidn`` is installed)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from isosr_net.filters import oidn
from isosr_net.methods.base import FrameMethod, FrameRunner, RayOptions, choice, count, register_runner
from isosr_net.timing import StageTimer
from isosr_render import FrameBuffers
from isosr_render.renderer import MAX_AO_SAMPLES
from isosr_render.shading import shade_on


@dataclass(frozen=True)
class OIDNOptions(RayOptions):
    """The rays OIDN denoises (at least one AO ray per hit) and its quality.

    Attributes:
        quality: ``"fast"``, ``"balanced"`` or ``"high"``.
    """

    ao_rays: int = count(1, 1, MAX_AO_SAMPLES)
    quality: str = choice("high", oidn.QUALITIES)


@register_runner("oidn")
class OIDNRunner(FrameRunner):
    """Full resolution, 1-4 (or more) AO rays per hit shaded, the noisy color denoised by Intel Open
    Image Denoise with the AO-free shading as albedo and the normals as clean auxiliary images
    (:func:`isosr_net.filters.oidn.denoise`). Its frames hold a color but no AO."""

    label = "denoised AO (OIDN)"
    plot_color = "C6"

    options_type = OIDNOptions

    @classmethod
    def unavailable(cls) -> str | None:
        return oidn.unavailable()

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """1, 2, 4 AO rays, each at the fast and the high quality (smoke: 2, fast)."""
        rays, qualities = ((2,), ("fast",)) if smoke else ((1, 2, 4), ("fast", "high"))
        return [FrameMethod.of(cls.kind, ao_rays=n, quality=q) for n in rays for q in qualities]

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, oidn {m.options.quality}" + (f", spp {m.spp}" if m.spp > 1 else "")

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "ao")

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal")

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        buffers = FrameBuffers(mask=rendered.mask, normal=rendered.normal, cap=rendered.cap, albedo=rendered.albedo)
        if self.shade:
            with timer("shading"):
                shade, mask = shade_on(rendered.mask.device.type), self.coverage(rendered.mask, rendered)
                noisy = shade(mask, rendered.normal, rendered.ao, self.shading, rendered.cap, rendered.albedo)
                albedo = shade(mask, rendered.normal, None, self.shading, rendered.cap, rendered.albedo)
            with timer("filter"):
                denoised = oidn.denoise(noisy, albedo, rendered.normal, self.method.options.quality)
                # OIDN filters the background too: where nothing was hit, the background (the albedo's) stays.
                buffers.color = torch.where(rendered.mask[..., None] > 0, denoised, albedo)
        return buffers
