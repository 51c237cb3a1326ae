"""Every way to make a frame's final color, and the stateful runner that makes it.

A :class:`FrameMethod` names one way: ray cast at full resolution with N AO rays and M rays
per pixel; full resolution with few AO rays and the a-trous filter (:mod:`isosr_net.atrous`);
full resolution with few (or no) AO rays reconstructed by a trained network
(:mod:`isosr_net.reconnet`: converged AO, antialiased edges); a low-res ray cast upscaled
classically (no AO: a classic upscaler knows none); or a low-res ray cast upscaled by a trained
network (which infers AO). A :class:`FrameRunner` makes one
stream's frames with it, camera after camera, computing only the buffers the method needs:

    runner = FrameRunner(FrameMethod("network", factor=4, precision="bf16"), renderer, iso, 1920, 1080)
    frame = runner.frame(camera, prev_camera)  # FrameBuffers: color (H, W, 3) in [0, 1], mask, normal[, ao]

``prev_camera=None`` starts a new sequence (the network forgets its previous output).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_render.renderer import MAX_AO_SAMPLES, MAX_SPP
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import ShadingParams, shade
from isosr_net.atrous import ATrousConfig, atrous_filter
from isosr_net.metrics import upscale_baseline
from isosr_net.reconnet import MAX_RECON_AO_RAYS, MAX_RECON_SPP
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor
from isosr_net.upscaler import DEFAULT_MODEL, PRECISIONS, Upscaler, highres_frame

KINDS = ("full", "atrous", "reconstruct", "upscale", "network")
LEARNED = ("reconstruct", "network")
INTERPOLATIONS = ("nearest", "bilinear", "bicubic")
# AO ray length in world units, as the training data and the benchmarks use it.
AO_RADIUS = 0.05


@dataclass(frozen=True)
class FrameMethod:
    """One way to make the final frame.

    Attributes:
        kind: ``"full"`` (full-resolution ray cast), ``"atrous"`` (full resolution, AO filtered),
            ``"reconstruct"`` (full resolution, trained reconstruction), ``"upscale"`` (low-res
            ray cast, classic interpolation), ``"network"`` (low-res ray cast, trained network).
        ao_rays: AO rays per hit (full: 0 for none; atrous: at least 1; reconstruct: 0 to
            :data:`isosr_net.reconnet.MAX_RECON_AO_RAYS`, 0 infers AO; upscalers: 0).
        spp: rays per pixel (full resolution only; reconstruct: at most
            :data:`isosr_net.reconnet.MAX_RECON_SPP`).
        factor: upscaling factor (upscale and network: at least 2; others: 1).
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"`` (upscale).
        model: the network's model folder (learned kinds; None: the shipped default).
        model_name: the network's name in :attr:`name`.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (learned kinds).
    """

    kind: str = "full"
    ao_rays: int = 0
    spp: int = 1
    factor: int = 1
    interpolation: str = "bilinear"
    model: str | None = None
    model_name: str = "network"
    precision: str = "fp32"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"frame method kind must be one of {KINDS}, got {self.kind!r}")
        low_res = self.kind in ("upscale", "network")
        recon = self.kind == "reconstruct"
        most_rays = 0 if low_res else MAX_RECON_AO_RAYS if recon else MAX_AO_SAMPLES
        most_spp = 1 if low_res else MAX_RECON_SPP if recon else MAX_SPP
        for name, value, low, high in (("ao_rays", self.ao_rays, 1 if self.kind == "atrous" else 0, most_rays),
                                       ("spp", self.spp, 1, most_spp),
                                       ("factor", self.factor, 2 if low_res else 1, 16 if low_res else 1)):
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{self.kind} frame method: {name} must be an integer in [{low}, {high}], "
                                 f"got {value!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {self.interpolation!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {self.precision!r}")

    @property
    def name(self) -> str:
        """``full, AO 8, spp 1``, ``full, AO 2, a-trous``, ``full, AO 2, spp 1, recon fp16``,
        ``x4 bilinear``, ``x4 network bf16``."""
        if self.kind == "full":
            return f"full, AO {self.ao_rays}, spp {self.spp}"
        if self.kind == "atrous":
            return f"full, AO {self.ao_rays}, a-trous" + (f", spp {self.spp}" if self.spp > 1 else "")
        if self.kind == "reconstruct":
            return f"full, AO {self.ao_rays}, spp {self.spp}, {self.model_name} {self.precision}"
        if self.kind == "upscale":
            return f"x{self.factor} {self.interpolation}"
        return f"x{self.factor} {self.model_name} {self.precision}"

    @property
    def learned(self) -> bool:
        """Whether a trained network takes part."""
        return self.kind in LEARNED

    def upscaler_key(self, device: str) -> tuple[str, str, str]:
        """What identifies this method's `Upscaler` (shared between runners of one device)."""
        default = DEFAULT_RECON_MODEL if self.kind == "reconstruct" else DEFAULT_MODEL
        return str(Path(self.model or default).resolve()), self.precision, str(device)


class FrameRunner:
    """Makes one stream's frames with one method.

    Args:
        method: the way to make frames.
        renderer: the volume's renderer (its device is where everything runs).
        iso: normalized iso-value.
        width, height: the final frame's size; an upscaling method's factor must divide both.
        shading: material and light.
        ao_radius: AO ray length, world units.
        upscalers: a cache of `Upscaler` by :meth:`FrameMethod.upscaler_key`, shared by runners
            that run one after another (a compiled network is built once); None: a private one.
        atrous: the a-trous filter's knobs (see :func:`atrous_filter`).
    """

    def __init__(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                 shading: ShadingParams = ShadingParams(), ao_radius: float = AO_RADIUS,
                 upscalers: dict | None = None, atrous: ATrousConfig = ATrousConfig()):
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"frame {name} must be a positive integer, got {value!r}")
        if width % method.factor or height % method.factor:
            raise ValueError(f"{method.name}: the factor {method.factor} must divide the frame size "
                             f"{width}x{height}")
        self.method, self.renderer, self.iso = method, renderer, float(iso)
        self.width, self.height = width, height
        self.shading, self.ao_radius, self.atrous = shading, ao_radius, atrous
        self.device = str(renderer.device)
        self.upscaler = None
        if method.learned:
            upscalers = {} if upscalers is None else upscalers
            key = method.upscaler_key(self.device)
            if key not in upscalers:
                kind = Reconstructor if method.kind == "reconstruct" else Upscaler
                upscalers[key] = kind.fastest(key[0], self.device, method.precision)
            self.upscaler = upscalers[key]
            if self.upscaler.upscale_factor != method.factor:
                raise ValueError(f"{method.name}: the model upscales x{self.upscaler.upscale_factor}, "
                                 f"not x{method.factor}")
            self.upscaler.reset()

    def render_request(self, prev_camera: Camera | None = None) -> RenderRequest:
        """The ray cast a frame of this method starts with: only the buffers the method reads, at
        the size it renders (flow only after a previous camera, for the learned kinds)."""
        m = self.method
        flow = ("flow",) if prev_camera is not None and m.learned else ()
        outputs = {"full": ("mask", "normal", "color") + (("ao",) if m.ao_rays else ()),
                   "atrous": ("mask", "normal", "depth", "ao"),
                   "reconstruct": ("mask", "normal", "depth") + (("ao",) if m.ao_rays else ()) + flow,
                   "upscale": LOWRES_BUFFERS,
                   "network": LOWRES_BUFFERS + flow}[m.kind]
        return RenderRequest(self.width // m.factor, self.height // m.factor, self.iso, outputs,
                             ao_radius=self.ao_radius, prev_camera=prev_camera if flow else None,
                             shading=self.shading, spp=m.spp, ao_samples=max(1, m.ao_rays))

    @torch.no_grad()
    def frame(self, camera: Camera, prev_camera: Camera | None = None) -> FrameBuffers:
        """The next frame of the stream; ``prev_camera=None`` starts a new sequence.

        Returns:
            FrameBuffers at the frame size with ``color`` (the final frame), ``mask``, ``normal``,
            and ``ao`` where the method makes AO.

        Shape:
            color, normal: (H, W, 3). mask, ao: (H, W).
        """
        m = self.method
        out = self.renderer.render(camera, self.render_request(prev_camera))
        if m.kind == "full":
            return FrameBuffers(mask=out.mask, normal=out.normal, ao=out.ao, color=out.color)
        if m.kind == "atrous":
            ao = atrous_filter(out.ao[None, None], out.mask[None, None], out.normal.permute(2, 0, 1)[None],
                               out.depth[None, None], self.atrous)[0, 0]
            return FrameBuffers(mask=out.mask, normal=out.normal, ao=ao,
                                color=shade(out.mask, out.normal, ao, self.shading))
        if m.kind == "upscale":
            up = upscale_classic(out, m.factor, m.interpolation)
            return FrameBuffers(mask=up.mask, normal=up.normal,  # no AO: shaded unoccluded (AO 1)
                                color=shade(up.mask, up.normal, up.ao, self.shading))
        if m.kind == "reconstruct":  # shaded within the reconstruction's one (compiled) call
            return self.upscaler.reconstruct(out, m.ao_rays, m.spp, self.shading)
        high = self.upscaler.upscale(out)
        high.color = shade(high.mask, high.normal, high.ao, self.shading)
        return high


def upscale_classic(low: FrameBuffers, factor: int, interpolation: str = "bilinear") -> FrameBuffers:
    """A low-res frame's mask, normal and depth upscaled by interpolation
    (:func:`isosr_net.metrics.upscale_baseline`), as the network's outputs are laid out; AO is 1
    everywhere: an interpolator knows no occlusion.

    Shape:
        low: mask, depth (h, w), normal (h, w, 3). Returns mask, depth, ao (H, W), normal (H, W, 3),
        ``H = h * factor``, ``W = w * factor``.
    """
    return highres_frame(upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], factor, interpolation))


def run_sequence(runner: FrameRunner, cameras: list[Camera]) -> list[FrameBuffers]:
    """A new sequence along ``cameras``: one frame per camera."""
    return [runner.frame(camera, prev) for camera, prev in sequence_cameras(cameras)]
