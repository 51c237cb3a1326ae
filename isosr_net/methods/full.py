"""Full resolution: the plain ray cast with AO rays per hit and rays per pixel."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from isosr_net.methods.base import FrameMethod, FrameResult, FrameRunner, RayOptions, register_runner
from isosr_net.reconnet import RayLimits
from isosr_net.timing import StageTimer
from isosr_render import Camera, FrameBuffers
from isosr_render.buffers import stacked
from isosr_render.shading import ShadingParams, shade, shade_on


@dataclass(frozen=True)
class FullOptions(RayOptions):
    """A full-resolution render's rays: any AO rays per hit (0: none), rays per pixel."""


@register_runner("full")
class FullRunner(FrameRunner):
    """Full resolution, AO from ``ao_rays`` rays per hit (0: none); translucent surfaces' two layers composited by
    the renderer."""

    label = "full resolution"
    layered = True
    warm_up = True
    serve_bench_ao = (0, 8)
    plot_color = "C0"

    options_type = FullOptions

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """0-128 AO rays at 1, 2, 4 rays per pixel (smoke: 0, 2, 8 at 1, 2)."""
        spps, rays = ((1, 2), (0, 2, 8)) if smoke else ((1, 2, 4), (0, 1, 2, 4, 8, 16, 32, 64, 128))
        return [FrameMethod.of(cls.kind, ao_rays=n, spp=s) for s in spps for n in rays]

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """0-64 AO rays at spp 1, 0 and 8 at spp 2, 0 and 16 at spp 4."""
        return tuple((rank, FrameMethod.of(cls.kind, ao_rays=n, spp=s)) for rank, n, s in (
            (2, 0, 1), (4, 1, 1), (9, 2, 1), (14, 4, 1), (20, 8, 1), (21, 0, 2), (24, 16, 1), (25, 8, 2), (26, 0, 4),
            (32, 32, 1), (33, 64, 1), (34, 16, 4)))

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, spp {m.spp}"

    def outputs(self) -> tuple[str, ...]:
        if not self.shade:  # a buffer view: the mask and what is kept
            return ("mask",) + tuple(k for k in self.keep if k != "flow")
        return ("mask", "normal") + (("ao",) if self.method.ao_rays else ()) + (("color",) if self._layers else ())

    @property
    def _layers(self) -> bool:
        """Whether the render makes two layers and their colour (translucent surfaces, shaded)."""
        return self.shade and self.surfaces is not None and self.surfaces.layers > 1

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal") + (("ao",) if m.ao_rays else ())

    @classmethod
    def make_batch(cls, frames: list[tuple[FrameRunner, Camera, Camera | None]]) -> list[FrameResult | Exception]:
        """As :meth:`FrameRunner.make_batch`, the frames that shade alike in one call: rendered together
        (:meth:`FrameRunner.render_together`), then those of one material and the same buffers (AO, cut faces,
        colours) stacked and shaded together
        (:func:`~isosr_render.shading.shade_on`: on GPUs one compiled call, whose host work the batch shares;
        each frame's ``shading`` stage its share of the call). Two layers, or none shaded: each frame as alone."""
        results: list[FrameResult | Exception | None] = [None] * len(frames)
        together = [k for k, (runner, _, _) in enumerate(frames)
                    if runner.shade and not runner._layers and runner.behind is None]
        for k in range(len(frames)):
            if k not in together:
                results[k] = super().make_batch([frames[k]])[0]
        alike: dict[tuple, list[tuple[int, FullRunner, FrameBuffers, FrameBuffers, StageTimer, Camera | None]]] = {}
        for k, made in zip(together, cls.render_together([frames[k] for k in together])):
            if isinstance(made, Exception):
                results[k] = made
                continue
            (runner, _, prev_camera), (rendered, timer) = frames[k], made
            buffers = FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=rendered.ao, cap=rendered.cap,
                                   albedo=rendered.albedo)
            key = (runner.shading,) + tuple(getattr(buffers, n) is None for n in ("ao", "cap", "albedo"))
            alike.setdefault(key, []).append((k, runner, rendered, buffers, timer, prev_camera))
        for group in alike.values():
            try:
                colors, shading = cls._shade_together([buffers for _, _, _, buffers, _, _ in group], group[0][1].shading)
            except Exception as e:  # noqa: BLE001 - the group's shading failed: its streams' error
                colors, shading = [e] * len(group), None
            for (k, runner, rendered, buffers, timer, prev_camera), color in zip(group, colors):
                if isinstance(color, Exception):
                    results[k] = color
                    continue
                buffers.color = color
                results[k] = runner._made(rendered, buffers, [timer, shading], prev_camera)
        return results

    @staticmethod
    def _shade_together(frames: list[FrameBuffers], params: ShadingParams) -> tuple[list[torch.Tensor], StageTimer]:
        """The colors of single-layer frames of one size, stacked and shaded in one call, and its timer (each
        frame's share)."""
        device = frames[0].mask.device
        timer = StageTimer(device, share=len(frames))
        with torch.no_grad(), timer("shading"):
            mask, normal, ao, cap, albedo = (stacked(frames, n) for n in ("mask", "normal", "ao", "cap", "albedo"))
            colors = shade_on(device.type)(mask, normal, ao, params, cap, albedo)
        return list(colors.unbind(0)), timer

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        buffers = FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=rendered.ao)
        if self._layers:
            buffers.color, buffers.albedo, buffers.behind = rendered.color, rendered.albedo, rendered.behind
            return buffers
        return self.colored(buffers, timer, rendered)

    def rows(self, camera: Camera, start: int, stop: int) -> torch.Tensor:
        """Rows ``[start, stop)`` of the frame's color only (a focus lens's region).

        Shape:
            Returns (stop - start, W, 3).
        """
        rendered = self.renderer.render(camera, self.render_request(), rows=(start, stop))
        if self._layers:
            return rendered.color[start:stop]
        ao, cap, albedo = (None if t is None else t[start:stop] for t in (rendered.ao, rendered.cap, rendered.albedo))
        return shade(rendered.mask[start:stop], rendered.normal[start:stop], ao, self.shading, cap, albedo)
