"""The frame pipelines of the view modes, one function each, and the per-stage timer.

Every function here runs on the engine's device thread (:mod:`isosr_server.engine`) and
computes only what its mode needs:

    full      full-res render (mask, normal, AO only with ao_rays > 0) -> shading
    network   low-res render (mask, normal, depth, flow) -> network (Upscaler) -> shading
    upscale   low-res render (mask, normal, depth) -> classic upscaling (``interpolation``) -> shading (no AO)
    buffers   low-res render (mask, normal, depth, flow) -> buffers coding (isosr_server.codecs, on the device)
    focus     ``network``, plus a full-res render of the rows the focus region covers, blended in
              by a weight that ramps from 0 at the region's border to 1 ``blend`` pixels inside
    reconstruct  full-res render (mask, normal, depth, flow, AO of ``ao_rays`` rays per hit)
              -> reconstruction network (Reconstructor) -> shading, all one
              :class:`isosr_net.frame_methods.FrameRunner` step (:class:`ReconStream`), which
              times no stages of its own: its frames report ``total`` and ``encode`` only
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch

from isosr_net.frame_methods import FrameMethod, FrameRunner, upscale_classic
from isosr_net.reconstructor import Reconstructor
from isosr_net.upscaler import Upscaler
from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_render.shading import shade
from isosr_server.codecs.buffers_device import encode_view_buffers
from isosr_server.protocol import FocusMsg, ViewBuffers

# Rays per pixel of reconstruct-mode renders: one, as full mode renders.
RECON_SPP = 1


class StageTimer:
    """Milliseconds per stage; on CUDA each stage ends with a synchronize, so a stage's time
    is its own GPU work (the price: no overlap between stages)."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.ms: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        yield
        if self.cuda:
            torch.cuda.synchronize()
        self.ms[stage] = self.ms.get(stage, 0.0) + 1e3 * (time.perf_counter() - start)


@dataclass(frozen=True)
class FrameSpec:
    """One view frame to make.

    Attributes:
        mode: a view mode (protocol.MODES).
        camera: this frame's camera; ``prev_camera`` the previous frame's of the stream (flow:
            low-res modes and ``reconstruct``), or None.
        iso: normalized iso-value.
        width, height: output size; low-res frames are ``factor`` times smaller.
        ao_samples, ao_radius: AO rays per hit of full-res renders (0: no AO); in ``reconstruct``
            mode the AO rays per hit the network gets (0: it infers AO).
        focus: the focus region (``focus`` mode).
        blend: focus border blend width in pixels.
        channel: ``shaded`` or the buffer a channel view shows (:mod:`isosr_server.channels`).
        interpolation: ``upscale`` mode's classic upscaling (nearest, bilinear, bicubic).
    """

    mode: str
    camera: Camera
    prev_camera: Camera | None
    iso: float
    width: int
    height: int
    ao_samples: int
    ao_radius: float
    focus: FocusMsg
    blend: int
    channel: str = "shaded"
    interpolation: str = "bilinear"


def lowres_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """The low-res size of an output size; ValueError unless both sides divide by ``factor``."""
    if width % factor or height % factor:
        raise ValueError(f"size {width}x{height} must be a multiple of the upscale factor {factor} in this mode")
    return width // factor, height // factor


def render_full(renderer: Renderer, spec: FrameSpec, timer: StageTimer,
                rows: tuple[int, int] | None = None) -> torch.Tensor:
    """The plain full-resolution shaded render (rows ``[start, stop)`` only, if given).

    Shape:
        Returns (H, W, 3) float, or (stop - start, W, 3) with ``rows``.
    """
    outputs = ("mask", "normal") + (("ao",) if spec.ao_samples else ())
    request = RenderRequest(spec.width, spec.height, spec.iso, outputs, ao_samples=max(spec.ao_samples, 1),
                            ao_radius=spec.ao_radius)
    start, stop = rows or (0, spec.height)
    with timer("render"):
        frame = renderer.render(spec.camera, request, rows=rows)
    with timer("shading"):
        ao = None if frame.ao is None else frame.ao[start:stop]
        return shade(frame.mask[start:stop], frame.normal[start:stop], ao)


def render_lowres(renderer: Renderer, spec: FrameSpec, factor: int, timer: StageTimer,
                  flow: bool = True) -> FrameBuffers:
    """The network's low-res inputs: mask, normal, depth, and flow when asked and a previous camera exists."""
    w, h = lowres_size(spec.width, spec.height, factor)
    with_flow = flow and spec.prev_camera is not None
    request = RenderRequest(w, h, spec.iso, LOWRES_BUFFERS + (("flow",) if with_flow else ()),
                            prev_camera=spec.prev_camera if with_flow else None)
    with timer("render"):
        return renderer.render(spec.camera, request)


def render_sr(renderer: Renderer, upscaler: Upscaler, spec: FrameSpec, timer: StageTimer) -> torch.Tensor:
    """Low-res render, network upscaling (recurrent: ``spec.prev_camera`` None resets), shading.

    Shape:
        Returns (H, W, 3) float.
    """
    low = render_lowres(renderer, spec, upscaler.upscale_factor, timer)
    with timer("network"):
        high = upscaler.upscale(low)
    with timer("shading"):
        return shade(high.mask, high.normal, high.ao)


def render_bilinear(renderer: Renderer, factor: int, spec: FrameSpec, timer: StageTimer) -> torch.Tensor:
    """Low-res render, classic upscaling of its buffers (``spec.interpolation``), shading without AO
    (the non-learned baseline)."""
    low = render_lowres(renderer, spec, factor, timer, flow=False)
    with timer("network"):
        high = upscale_classic(low, factor, spec.interpolation)
    with timer("shading"):
        return shade(high.mask, high.normal, high.ao)


def render_buffers(renderer: Renderer, factor: int, spec: FrameSpec, timer: StageTimer) -> ViewBuffers:
    """Low-res buffers in the buffers coding (flow relative to ``spec.prev_camera``), quantized on the device."""
    low = render_lowres(renderer, spec, factor, timer)
    with timer("encode"):
        return encode_view_buffers(low)


def focus_weight(focus: FocusMsg, width: int, height: int, blend: int, device: torch.device) -> torch.Tensor:
    """Per-pixel weight of the full-res render: 1 deeper than ``blend`` pixels inside the region,
    ramping to 0 at its border, 0 outside (pixel centers at ``+0.5``, x right, y down).

    Shape:
        Returns (H, W) float32.
    """
    y, x = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32) + 0.5,
                          torch.arange(width, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    if focus.shape == "circle":
        inside = focus.radius - torch.hypot(x - focus.center[0], y - focus.center[1])
    elif focus.shape == "box":
        x0, y0, x1, y1 = focus.box
        inside = torch.minimum(torch.minimum(x - x0, x1 - x), torch.minimum(y - y0, y1 - y))
    else:
        return torch.zeros(height, width, device=device)
    return (inside / blend).clamp(0.0, 1.0) if blend > 0 else (inside >= 0).float()


def render_focus(renderer: Renderer, upscaler: Upscaler, spec: FrameSpec, timer: StageTimer) -> torch.Tensor:
    """``network`` around the focus region, full resolution (with the asked AO) inside it, blended at the border."""
    color = render_sr(renderer, upscaler, spec, timer)
    with timer("shading"):
        weight = focus_weight(spec.focus, spec.width, spec.height, spec.blend, color.device)
        covered = weight.amax(dim=1).nonzero()
    if len(covered) == 0:
        return color
    start, stop = int(covered[0]), int(covered[-1]) + 1
    sharp = render_full(renderer, spec, timer, rows=(start, stop))
    with timer("shading"):
        w = weight[start:stop, :, None]
        color[start:stop] = color[start:stop] * (1.0 - w) + sharp * w
    return color


class ReconStream:
    """A view session's ``reconstruct`` frames: the session's own `Reconstructor` (its recurrent
    state) run by the `FrameRunner` of the current AO rays, iso, size and AO radius. A change of
    any of them makes a new runner, which starts without state, as a cut (``prev_camera`` None) does.

    Args:
        reconstructor: the session's own (:meth:`isosr_server.engine.Engine.new_recon_stream`).
        model: the folder it was loaded from.
    """

    def __init__(self, reconstructor: Reconstructor, model: Path):
        self.reconstructor, self.model = reconstructor, str(model)
        self.runner: FrameRunner | None = None

    def frame(self, renderer: Renderer, spec: FrameSpec) -> FrameBuffers:
        """The frame of ``spec``: full-res render with ``spec.ao_samples`` AO rays per hit,
        reconstruction (recurrent: ``spec.prev_camera`` None resets), shading.

        Raises:
            ValueError: ``spec.ao_samples`` beyond what the reconstruction takes.

        Shape:
            Returns color, normal (H, W, 3); mask, depth, ao (H, W).
        """
        method = FrameMethod("reconstruct", ao_rays=spec.ao_samples, spp=RECON_SPP, model=self.model,
                             precision=self.reconstructor.precision)
        r = self.runner
        if r is None or r.renderer is not renderer or (r.method, r.iso, r.width, r.height, r.ao_radius) != \
                (method, spec.iso, spec.width, spec.height, spec.ao_radius):
            self.runner = FrameRunner(method, renderer, spec.iso, spec.width, spec.height, ao_radius=spec.ao_radius,
                                      upscalers={method.upscaler_key(str(renderer.device)): self.reconstructor})
        return self.runner.frame(spec.camera, spec.prev_camera)
