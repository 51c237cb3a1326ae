"""Full resolution (or x2), few AO rays reconstructed by a trained network (:mod:`isosr_net.reconnet`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from isosr_net.inference import default_precision
from isosr_net.methods.base import (FrameMethod, FrameResult, FrameRunner, ModelOptions, RayOptions, count,
                                   register_runner)
from isosr_net.model import read_config
from isosr_net.reconnet import UPSCALES, RayLimits
from isosr_net.reconstructor import (
    DEFAULT_RECON_MODEL,
    Reconstructor,
    recon_config,
    recon_limits,
)
from isosr_net.timing import StageTimer
from isosr_render import Camera, FrameBuffers, RenderRequest
from isosr_render.renderer import MAX_AO_SAMPLES
from isosr_render.shading import ShadingParams

# The x2 reconstruction's name in its methods' names (``x2, AO 1, spp 1, recon_x2 fp16``).
X2_MODEL_NAME = "recon_x2"
# Where make_batch runs the network once over a batch's frames: on GPUs, where a frame's network is many
# small launches (the service's fused kernels, ungraphed) whose host work a batch shares; on CPUs the
# network's arithmetic dominates, and each stream's frame stays its own call.
BATCHED_NETWORK_DEVICES = ("cuda",)
# The shipped reconstruction's name in the budget policy's candidates and the recon-path study's
# rows (``full, AO 1, spp 1, network fp16``): their probe caches and results know them by it.
CANDIDATE_MODEL_NAME = "network"


@dataclass(frozen=True)
class ReconstructOptions(ModelOptions, RayOptions):
    """The rays a reconstruction model reads, the model and its upscale.

    Attributes:
        spp: rays per pixel, at most the model's ``max_spp``.
        factor: the model's upscale (:attr:`~isosr_net.reconnet.ReconNetConfig.upscale`: an x2
            model renders at half the sides).
    """

    ao_rays: int = count(2, 0, MAX_AO_SAMPLES)
    factor: int = count(1, 1, max(UPSCALES))
    model_name: str = Reconstructor.display_name

    @classmethod
    def of(cls, **knobs) -> ReconstructOptions:
        """As :meth:`MethodOptions.of`, the factor the model's own unless given."""
        knobs.setdefault("factor", recon_config(knobs.get("model") or DEFAULT_RECON_MODEL).upscale)
        return super().of(**knobs)

    def bounds(self) -> dict[str, tuple[int, int]]:
        return super().bounds() | {"spp": (1, recon_limits(self.model or DEFAULT_RECON_MODEL).max_spp)}


@register_runner("reconstruct")
class ReconstructRunner(FrameRunner):
    """Full resolution (or 1/factor of it, for a model that upscales: ``ReconNetConfig.upscale``),
    1 ray per pixel to the model's ``max_spp`` and any AO rays per hit (past its ``max_ao_rays`` the
    network reads their mean as that many: :meth:`~isosr_net.reconnet.RayLimits.read`),
    reconstructed (and shaded, in one compiled call on GPUs) by the trained reconstruction
    network. With a `Reconstructor` made with ``graphs`` on CUDA, a frame in one slice (render,
    network, shading) is one CUDA graph (:meth:`Reconstructor.render_reconstruct`), timed as the
    ``render`` stage."""

    label = "reconstruction (full res, few AO rays)"
    warm_up = True
    serve_bench_ao = (1,)
    plot_color = "C4"

    recurrent = True
    fresh_rays = True  # accumulated along the flow before the network (isosr_net.ray_history)
    network_class = Reconstructor
    default_model = DEFAULT_RECON_MODEL
    options_type = ReconstructOptions

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """A reconstruction model (a ReconNet's folder) at its upscale over 0-16 AO rays at 1, 2, 4 rays
        per pixel, to its limits, and past its AO rays (read as its ``max_ao_rays``) 32 and 64 at its
        most rays per pixel: the top (smoke: 0 and 2 AO rays at spp 1); fp16 on CUDA, fp32 elsewhere."""
        if model is None:
            return []
        name, folder = model
        if read_config(folder)["model"].get("type") != "ReconNet":
            return []
        limits = recon_limits(folder)
        sampling = [(1, 0), (1, 2)] if smoke else [(s, n) for s in (1, 2, 4) for n in (0, 1, 2, 4, 8, 16)
                                                   if s <= limits.max_spp and n <= limits.max_ao_rays]
        if not smoke:
            sampling += [(limits.max_spp, n) for n in (32, 64) if n > limits.max_ao_rays]
        shipped = None if folder == cls.default_model else str(folder)
        return [FrameMethod.of(cls.kind, model=shipped, ao_rays=n, spp=s, precision=default_precision(device),
                               model_name=name) for s, n in sampling]

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """Over 1-4 AO rays at 1-4 rays per pixel, and over 8 (spp 2, 4), 16, 32 and 64 (spp 4) where
        its model takes the rays per pixel (``limits``; None: the shipped model's; past its
        ``max_ao_rays`` it reads their mean as that many): a model over the input rays passes the
        plain render there. And the reconstruction that also upscales x2 (``x2_model``; None:
        none) over 1-16 AO rays at spp 1 and 4 at spp 2, to its model's limits: a quarter of the
        pixels rendered, so many AO rays cost little, the best there is below about twice the
        cheapest full frame (H100, 73dd70b: 1.5-2.7 ms at 1080p, 4.4-7.2 ms at 4K). In
        ``precision`` (None: fp16 on CUDA, fp32 elsewhere)."""
        limits = limits or recon_limits(cls.default_model)
        precision = precision or default_precision(device)
        out = [(rank, FrameMethod.of(cls.kind, ao_rays=n, spp=s, precision=precision,
                                     model_name=CANDIDATE_MODEL_NAME)) for rank, n, s in (
            (8, 1, 1), (12, 2, 1), (17, 4, 1), (19, 1, 2), (22, 2, 2), (23, 4, 2), (27, 1, 4), (28, 2, 4), (29, 4, 4),
            (30, 8, 2), (31, 8, 4), (35, 16, 4), (36, 32, 4), (37, 64, 4)) if s <= limits.max_spp]
        if x2_model is not None:
            x2 = recon_limits(x2_model)
            out += [(rank, FrameMethod.of(cls.kind, model=str(x2_model), ao_rays=n, spp=s, model_name=X2_MODEL_NAME,
                                          precision=precision))
                    for rank, n, s in ((5, 1, 1), (7, 2, 1), (10, 4, 1), (13, 8, 1), (16, 4, 2), (18, 16, 1))
                    if n <= x2.max_ao_rays and s <= x2.max_spp]
        return tuple(out)

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        sides = "full" if m.factor == 1 else f"x{m.factor}"
        return f"{sides}, AO {m.ao_rays}, spp {m.spp}, {m.options.model_name} {m.options.precision}"

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "depth") + (("ao", "position") if self.method.ao_rays else ())

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal", "depth", "ao")

    @property
    def read_rays(self) -> int:
        """The AO rays per hit the network reads the frame's mean as (at most its ``max_ao_rays``)."""
        return self.net.limits.read(self.method.ao_rays)

    @property
    def ray_factor(self) -> float:
        """The rays behind the frame's AO mean per ray the network reads (:meth:`Reconstructor.reconstruct`)."""
        return self.method.ao_rays / self.read_rays if self.read_rays else 1.0

    @property
    def fused_shading(self) -> ShadingParams | None:
        """The shading the network's call makes too: none where the runner does not shade, or where it
        shades after it (:attr:`FrameRunner.shades_after`)."""
        return self.shading if self.shade and not self.shades_after else None

    def batch_key(self) -> tuple:
        """As :meth:`FrameRunner.batch_key`, and what the network's call takes alike: the method (its
        model, rays and precision) and the shading the call makes."""
        return super().batch_key() + (self.method, self.fused_shading)

    @classmethod
    def make_batch(cls, frames: list[tuple[FrameRunner, Camera, Camera | None]]) -> list[FrameResult | Exception]:
        """As :meth:`FrameRunner.make_batch`, without waiting for the device: each stream's frame issues its
        work and its input checks travel to the host behind it, read by whoever takes the frame
        (:attr:`FrameResult.checks`; on a GPU the host's work for the next batch overlaps the device's for
        this one). On the devices in :data:`BATCHED_NETWORK_DEVICES`, streams whose networks run ungraphed
        (the service's), on one layer (opaque surfaces), render their frames together
        (:meth:`FrameRunner.render_together`: one launch where they share it), then the network runs once
        over them all (:meth:`Reconstructor.reconstruct_batch`; the frames' ``network`` stage is their
        batch's). A frame whose checks fail is its stream's error, and its stream starts over at its first
        frame made once the device has reached them (:meth:`Reconstructor.settle_checks_later`)."""
        for runner, _, _ in frames:
            runner.net.defer_checks()
        if len(frames) > 1 and torch.device(frames[0][0].device).type in BATCHED_NETWORK_DEVICES and \
                not any(runner.net.graphs or runner.behind is not None for runner, _, _ in frames):
            results = cls._network_batch(frames)
        else:
            results = super().make_batch(frames)
        for result, checks in zip(results, Reconstructor.settle_checks_later_each([r.net for r, _, _ in frames])):
            if isinstance(result, FrameResult):
                result.checks = checks
        return results

    @classmethod
    def _network_batch(cls, frames: list[tuple[ReconstructRunner, Camera, Camera | None]]
                       ) -> list[FrameResult | Exception]:
        """The streams' renders (one launch where they share one, :meth:`FrameRunner.render_together`), then one
        network call for them all (checks deferred by the caller)."""
        rendered: list[tuple[int, ReconstructRunner, StageTimer, FrameBuffers, Camera | None]] = []
        results: list[FrameResult | Exception | None] = [None] * len(frames)
        for k, ((runner, _, prev_camera), made) in enumerate(zip(frames, cls.render_together(frames))):
            if isinstance(made, Exception):
                results[k] = made
            else:
                rendered.append((k, runner, made[1], made[0], prev_camera))
        if not rendered:
            return results
        first = rendered[0][1]
        network = StageTimer(first.device)
        with network("network"):  # shading included: one call
            outs = Reconstructor.reconstruct_batch([r.net for _, r, _, _, _ in rendered],
                                                   [f for _, _, _, f, _ in rendered], first.read_rays,
                                                   first.method.spp, first.fused_shading, first.ray_factor)
        for (k, runner, timer, frame, prev_camera), out in zip(rendered, outs):
            try:
                if isinstance(out, Exception):
                    raise out
                buffers = runner.colored(out, timer, frame) if runner.shades_after else out
                results[k] = runner._made(frame, buffers, [timer, network], prev_camera)
            except Exception as e:  # noqa: BLE001 - as above
                results[k] = e
        return results

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("network"):  # shading included: one call
            out = self.net.reconstruct(rendered, self.read_rays, self.method.spp, self.fused_shading, self.ray_factor)
        return self.colored(out, timer, rendered) if self.shades_after else out

    def render_finish(self, camera: Camera, request: RenderRequest,
                      timer: StageTimer) -> tuple[FrameBuffers, FrameBuffers]:
        if not self.net.graphable(self.renderer, request):
            return super().render_finish(camera, request, timer)
        with timer("render"):  # the network and the shading included: one graph
            rendered, out = self.net.render_reconstruct(self.renderer, camera, request, self.read_rays,
                                                        self.method.spp, self.fused_shading, self.ray_factor)
        return rendered, self.colored(out, timer, rendered) if self.shades_after else out

