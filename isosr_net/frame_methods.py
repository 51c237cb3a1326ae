"""Every way to make a frame: one contract, one class per way, a registry by name.

A :class:`FrameMethod` names a way and its knobs (a frozen, hashable spec); a
:class:`FrameRunner` makes one stream's frames with it. Each way is one `FrameRunner` subclass
registered under its kind (:func:`register_runner`), as diffusers' schedulers share one
``step()`` contract. The registry, :data:`RUNNERS`:

    full         ray cast at full resolution with N AO rays (0: none) and M rays per pixel
    atrous       full resolution, few AO rays smoothed by the a-trous filter (:mod:`isosr_net.atrous`)
    svgf         full resolution, few AO rays accumulated over frames along the flow and filtered
                 (SVGF, :mod:`isosr_net.svgf`)
    oidn         full resolution, few AO rays shaded and denoised by Intel Open Image Denoise
                 (optional: where ``pyoidn`` is installed, :mod:`isosr_net.oidn`)
    reconstruct  full resolution, few (or no) AO rays reconstructed by a trained network
                 (:mod:`isosr_net.reconnet`: converged AO, antialiased edges)
    upscale      a low-res ray cast upscaled by interpolation (no AO: an interpolator knows none)
    network      a low-res ray cast upscaled by a trained network (which infers AO)
    buffers      the low-res ray cast itself, unshaded (for a client that upscales)

Every runner computes only the buffers its method needs (plus those a caller asks to ``keep``)
and reports per-stage times:

    runner = make_runner(FrameMethod("reconstruct", ao_rays=1, precision="fp16"), renderer, iso, 1920, 1080)
    result = runner.frame(camera, prev_camera)  # FrameResult: buffers (color, mask, normal, ...), times
    result.buffers.color                         # (H, W, 3) in [0, 1]

``prev_camera=None`` starts a new sequence (a recurrent network forgets its previous output).
A new method is one class and its registration; the Pareto benchmark, the budget policy,
``isosr render`` and the service run them all through this contract. A kind that needs an optional
package says why it cannot run where it is missing (:func:`unavailable_kinds`); making its runner
raises that reason.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import ClassVar

import torch

from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest
from isosr_render.conventions import AO_RADIUS, LOWRES_BUFFERS
from isosr_render.renderer import MAX_AO_SAMPLES, MAX_SPP
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import ShadingParams, shade, shade_on
from isosr_render.shapes import check_int
from isosr_net.atrous import ATrousConfig, atrous_filter
from isosr_net.inference import PRECISIONS, RecurrentNetwork, finish_steps, output_buffers
from isosr_net.metrics import INTERPOLATIONS, upscale_baseline
from isosr_net import oidn
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor, recon_config, recon_limits
from isosr_net.reconnet import UPSCALES
from isosr_net.svgf import SVGFConfig, SVGFHistory, svgf_filter
from isosr_net.timing import StageTimer
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler

# Upscaling factors a low-res method takes.
MAX_FACTOR = 16
# The AO seed of a temporal method's first frame, one more per frame: other methods cast with
# seed 0 and the quality reference with 1 (isosr_net.budget.REFERENCE_SEED), so no frame's rays
# are the reference's.
FIRST_TEMPORAL_SEED = 2


@dataclass(frozen=True)
class FrameMethod:
    """One way to make frames: a registered kind and its knobs (each kind reads the ones it needs
    and refuses the others' non-default values).

    Attributes:
        kind: a name of :data:`RUNNERS` (module docstring).
        ao_rays: AO rays per hit (0: no AO).
        spp: rays per pixel.
        factor: upscaling factor (low-res kinds; 1 for the others).
        interpolation: ``"nearest"``, ``"bilinear"`` or ``"bicubic"`` (``upscale``).
        model: the network's model folder (learned kinds; None: the shipped default).
        model_name: the network's name in :attr:`name`.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (learned kinds).
        quality: ``"fast"``, ``"balanced"`` or ``"high"`` (``oidn``).
    """

    kind: str = "full"
    ao_rays: int = 0
    spp: int = 1
    factor: int = 1
    interpolation: str = "bilinear"
    model: str | None = None
    model_name: str = "network"
    precision: str = "fp32"
    quality: str = "high"

    def __post_init__(self):
        if self.kind not in RUNNERS:
            raise ValueError(f"frame method kind must be one of {tuple(RUNNERS)}, got {self.kind!r}")
        self.runner.check(self)

    @property
    def runner(self) -> type[FrameRunner]:
        """The registered class that runs this method."""
        return RUNNERS[self.kind]

    @property
    def name(self) -> str:
        """``full, AO 8, spp 1``, ``full, AO 2, a-trous``, ``full, AO 2, svgf``, ``full, AO 2, oidn high``,
        ``full, AO 2, spp 1, recon fp16``, ``x4 bilinear``, ``x4 network bf16``, ``x4 buffers``."""
        return self.runner.describe(self)

    @property
    def learned(self) -> bool:
        """Whether a trained network takes part."""
        return self.runner.network_class is not None


@dataclass
class FrameResult:
    """One frame of a runner.

    Attributes:
        buffers: the frame's buffers: ``color`` (the final frame; None for unshaded kinds) and
            what the method makes of mask, normal, depth, ao, plus the buffers asked to keep.
            At the frame size, except an unshaded low-res kind's (``buffers``), at the render's.
            Valid until the runner's next frame (a runner may reuse their memory, as one CUDA
            graph per frame does): :meth:`FrameBuffers.clone` keeps a frame longer.
        timers: the frame's stage timers (:attr:`times` reads them).
        continued: whether the frame continued the stream from the previous camera (its flow
            refers to it); False on a sequence's first frame.
    """

    buffers: FrameBuffers
    timers: list[StageTimer]
    continued: bool

    @property
    def times(self) -> dict[str, float]:
        """Milliseconds per stage (render, filter, network, shading, and what later timers add). Read
        when needed: on CUDA reading waits for the frame's last event, so the device thread may
        queue the next frame's work before the GPU has finished this one."""
        out: dict[str, float] = {}
        for timer in self.timers:
            for stage, ms in timer.ms().items():
                out[stage] = out.get(stage, 0.0) + ms
        return out


class Networks:
    """Loaded frame networks by (class, model folder, precision, device): each loaded once.

    A root cache hands out its loaded networks themselves (runners that run one after another,
    such as the benchmarks', share them; a new runner resets the state). :meth:`fork` gives a
    stream of its own: the same weights, its own recurrent state per network.

    Args:
        load: ``load(cls, model, device, precision)`` makes a network (default: ``cls.fastest``).
    """

    def __init__(self, load: Callable[[type[RecurrentNetwork], Path, str, str], RecurrentNetwork] | None = None):
        self._load = load or (lambda cls, model, device, precision: cls.fastest(model, device, precision))
        self._loaded: dict[tuple, RecurrentNetwork] = {}
        self._own: dict[tuple, RecurrentNetwork] | None = None

    @classmethod
    def eager(cls) -> Networks:
        """A cache that loads networks plainly (no compilation, no layout change): for a frame or
        two, where compiling costs more than it saves, and for references."""
        return cls(lambda net, model, device, precision: net(model, device, precision))

    def get(self, cls: type[RecurrentNetwork], model: Path, device: str, precision: str) -> RecurrentNetwork:
        """The network of this class, folder, device and precision (loaded on first use)."""
        key = (cls, str(Path(model).resolve()), str(device), precision)
        if key not in self._loaded:
            self._loaded[key] = self._load(cls, Path(model), str(device), precision)
        if self._own is None:
            return self._loaded[key]
        if key not in self._own:
            self._own[key] = self._loaded[key].own()
        return self._own[key]

    def fork(self) -> Networks:
        """A cache for one stream: shares what is loaded (and what it loads later), owns its state."""
        twin = Networks.__new__(Networks)
        twin._load, twin._loaded, twin._own = self._load, self._loaded, {}
        return twin


RUNNERS: dict[str, type[FrameRunner]] = {}


def unavailable_kinds() -> dict[str, str]:
    """The registered kinds that cannot run in this installation, each with why (an optional package
    missing); the others are available."""
    return {kind: reason for kind, cls in RUNNERS.items() if (reason := cls.unavailable()) is not None}


def register_runner(kind: str):
    """Class decorator: register a `FrameRunner` subclass under ``kind``."""
    def register(cls: type[FrameRunner]) -> type[FrameRunner]:
        if kind in RUNNERS:
            raise ValueError(f"frame method kind {kind!r} is registered already")
        cls.kind = kind
        RUNNERS[kind] = cls
        return cls
    return register


class FrameRunner(ABC):
    """Makes one stream's frames with one method: the contract every way of making frames shares.

    Class attributes (a kind's traits):
        kind: its name in :data:`RUNNERS`.
        low_res: renders at 1/factor of the frame size.
        recurrent: reads the previous frame (through the renderer's flow).
        shaded: makes a final color.
        fresh_rays: casts new AO rays each frame (another seed), to accumulate them over frames.
        network_class: the trained network it runs (None: none), with its default model.
        knobs: the spec's fields it reads; the others must keep their defaults.
        ao_rays, spp, factor: the ``(low, high)`` bounds of the spec's counts (:meth:`bounds`).
        label: a menu's words for it.
        view_mode: a viewer may ask for it by name (a service mode).
        default_ao_rays: the AO rays a viewer starts it with.

    Args:
        method: the way to make frames.
        renderer: the volume's renderer (its device is where everything runs).
        iso: normalized iso-value.
        width, height: the frame's size; a low-res method's factor must divide both.
        shading: material and light.
        ao_radius: AO ray length, world units.
        networks: where learned kinds get their network (see :class:`Networks`); None: a private cache.
        atrous: the a-trous filter's knobs (see :func:`atrous_filter`).
        keep: buffers to make and return besides what the method needs (e.g. a channel view's
            ``depth`` or ``flow``), at the frame size.
        shade: make the final color; off (a channel view shows one kept buffer instead), a method
            computes only what its kept buffers need (a full-resolution render: only them).
    """

    kind: ClassVar[str]
    low_res: ClassVar[bool] = False
    recurrent: ClassVar[bool] = False
    shaded: ClassVar[bool] = True
    fresh_rays: ClassVar[bool] = False
    network_class: ClassVar[type[RecurrentNetwork] | None] = None
    default_model: ClassVar[Path | None] = None
    knobs: ClassVar[tuple[str, ...]] = ()
    ao_rays: ClassVar[tuple[int, int]] = (0, 0)
    spp: ClassVar[tuple[int, int]] = (1, 1)
    factor: ClassVar[tuple[int, int]] = (1, 1)
    label: ClassVar[str] = ""
    view_mode: ClassVar[bool] = True
    default_ao_rays: ClassVar[int] = 0

    def __init__(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                 shading: ShadingParams = ShadingParams(), ao_radius: float = AO_RADIUS,
                 networks: Networks | None = None, atrous: ATrousConfig = ATrousConfig(), keep: tuple[str, ...] = (),
                 shade: bool = True):
        check_int(width, "width", 1, where="frame")
        check_int(height, "height", 1, where="frame")
        if (reason := self.unavailable()) is not None:
            raise RuntimeError(f"{method.name} cannot run here: {reason}")
        if width % method.factor or height % method.factor:
            raise ValueError(f"{method.name}: the factor {method.factor} must divide the frame size {width}x{height}")
        self.method, self.renderer, self.iso = method, renderer, float(iso)
        self.width, self.height = width, height
        self.shading, self.ao_radius, self.atrous, self.keep = shading, ao_radius, atrous, tuple(keep)
        self.shade = shade
        self.device = str(renderer.device)
        self._last_timer: StageTimer | None = None  # the previous frame's (read lazily: no sync per frame)
        self.frames = 0  # frames made: with fresh_rays, the next frame's AO seed
        self.net: RecurrentNetwork | None = None
        if self.network_class is not None:
            networks = Networks() if networks is None else networks
            self.net = networks.get(self.network_class, Path(method.model or self.default_model), self.device,
                                    method.precision)
            if self.net.upscale_factor != method.factor:
                raise ValueError(f"{method.name}: the model upscales x{self.net.upscale_factor}, not x{method.factor}")
            self.net.reset()

    @classmethod
    def check(cls, method: FrameMethod) -> None:
        """ValueError for knobs out of bounds or not this kind's (the spec's ``__post_init__`` calls it)."""
        for f in fields(method):
            if f.name not in cls.knobs and f.name not in ("kind", "model_name") and getattr(method, f.name) != f.default:
                raise ValueError(f"{method.kind} frame method: takes no {f.name} (only {', '.join(cls.knobs)})")
        for name, (low, high) in cls.bounds(method).items():
            check_int(getattr(method, name), name, low, high, where=f"{method.kind} frame method")
        if method.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {method.interpolation!r}")
        if method.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {method.precision!r}")
        if method.quality not in oidn.QUALITIES:
            raise ValueError(f"quality must be one of {oidn.QUALITIES}, got {method.quality!r}")

    @classmethod
    def bounds(cls, method: FrameMethod) -> dict[str, tuple[int, int]]:
        """The ``(low, high)`` bounds of ``method``'s counts ``ao_rays``, ``spp``, ``factor``."""
        return {"ao_rays": cls.ao_rays, "spp": cls.spp, "factor": cls.factor}

    @classmethod
    def unavailable(cls) -> str | None:
        """Why this kind cannot run in this installation (an optional package missing), or None."""
        return None

    @classmethod
    @abstractmethod
    def describe(cls, method: FrameMethod) -> str:
        """The method's display name (:attr:`FrameMethod.name`)."""

    @abstractmethod
    def outputs(self) -> tuple[str, ...]:
        """The buffers the method ray casts (flow aside: recurrent kinds get it after a previous camera)."""

    @classmethod
    @abstractmethod
    def makes(cls, method: FrameMethod) -> tuple[str, ...]:
        """The buffers a frame's result holds besides color (those kept come on top)."""

    @abstractmethod
    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        """The work after the render: the frame's buffers with ``color`` (unshaded kinds: without)."""

    def render_request(self, prev_camera: Camera | None = None) -> RenderRequest:
        """The ray cast a frame starts with: only the buffers the method reads and those kept, at the
        size it renders (flow only against a previous camera)."""
        flow = prev_camera is not None and (self.recurrent or "flow" in self.keep)
        outputs = self.outputs() + tuple(k for k in self.keep if k not in self.makes(self.method) and k != "flow")
        outputs += ("flow",) if flow else ()
        m = self.method
        seed = {"seed": (FIRST_TEMPORAL_SEED + self.frames) % 2 ** 31} if self.fresh_rays else {}
        return RenderRequest(self.width // m.factor, self.height // m.factor, self.iso, outputs,
                             ao_radius=self.ao_radius, prev_camera=prev_camera if flow else None,
                             shading=self.shading, spp=m.spp, ao_samples=max(1, m.ao_rays), **seed)

    def frame(self, camera: Camera, prev_camera: Camera | None = None) -> FrameResult:
        """The next frame of the stream; ``prev_camera=None`` starts a new sequence.

        Shape:
            buffers.color, normal: (H, W, 3). mask, depth, ao: (H, W). flow: (H, W, 2).
        """
        return finish_steps(self.steps(camera, prev_camera))

    @torch.no_grad()
    def steps(self, camera: Camera, prev_camera: Camera | None = None,
              slice_ms: float | None = None) -> Generator[None, None, FrameResult]:
        """:meth:`frame` in slices, for a scheduler that interleaves other work between them (a
        generator: it yields between slices and returns the `FrameResult`).

        With ``slice_ms``, a ray cast that may take longer (the runner's first, or one after a
        frame whose ray cast took longer) runs in row bands of about ``slice_ms`` each: the first
        band has 1/32 of the rows and is timed (a device sync), the next ones are sized from it.
        Without, or when the last ray cast took less, the frame is one slice.
        """
        timer = StageTimer(self.device)
        request = self.render_request(prev_camera)
        if slice_ms is None or (self._last_timer is not None and self._last_timer.ms()["render"] < slice_ms):
            rendered, buffers = self.render_finish(camera, request, timer)
        else:
            rendered = yield from self._render_bands(camera, request, slice_ms, timer)
            buffers = self.finish(rendered, timer)
        for name in self.keep:
            if getattr(buffers, name) is None and getattr(rendered, name) is not None:
                setattr(buffers, name, self._to_frame_size(name, getattr(rendered, name)))
        self._last_timer = timer
        self.frames += 1
        return FrameResult(buffers, [timer], prev_camera is not None and self.recurrent)

    def render_finish(self, camera: Camera, request: RenderRequest,
                      timer: StageTimer) -> tuple[FrameBuffers, FrameBuffers]:
        """A frame in one slice: ``(rendered, finished)``, the ray cast then :meth:`finish`."""
        with timer("render"):
            rendered = self.renderer.render(camera, request)
        return rendered, self.finish(rendered, timer)

    def _render_bands(self, camera: Camera, request: RenderRequest, slice_ms: float,
                      timer: StageTimer) -> Generator[None, None, FrameBuffers]:
        """The ray cast in row bands of about ``slice_ms`` each, yielding between them: each band
        renders its rows into one plan of this frame's own, whose buffers the frame keeps."""
        plan = self.renderer.plan(request)
        height, start, rows, out = request.height, 0, max(1, request.height // 32), None
        while start < height:
            stop = min(height, start + rows)
            began = time.perf_counter()
            with timer("render"):
                out = plan.render(camera, request, rows=(start, stop))
            if self.renderer.device.is_cuda:
                torch.cuda.synchronize(self.renderer.torch_device)
            took_ms = 1e3 * (time.perf_counter() - began)
            rows = max(1, int((stop - start) * slice_ms / max(took_ms, 1e-3)))
            start = stop
            if start < height:
                yield
        return out

    def colored(self, buffers: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        """``buffers`` with the final color (unless the runner does not shade)."""
        if self.shade:
            with timer("shading"):
                buffers.color = shade_on(buffers.mask.device.type)(buffers.mask, buffers.normal, buffers.ao,
                                                                  self.shading)
        return buffers

    def _to_frame_size(self, name: str, t: torch.Tensor) -> torch.Tensor:
        """A rendered buffer at the frame size: nearest upsampling of low-res ones (flow in frame pixels)."""
        f = self.method.factor
        if f == 1 or not self.shaded:
            return t
        up = torch.repeat_interleave(torch.repeat_interleave(t, f, 0), f, 1)
        return up * f if name == "flow" else up


@register_runner("full")
class FullRunner(FrameRunner):
    """Full resolution, AO from ``ao_rays`` rays per hit (0: none)."""

    label = "full resolution"

    knobs = ("ao_rays", "spp")
    ao_rays = (0, MAX_AO_SAMPLES)
    spp = (1, MAX_SPP)

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, spp {m.spp}"

    def outputs(self) -> tuple[str, ...]:
        if not self.shade:  # a buffer view: the mask and what is kept
            return ("mask",) + tuple(k for k in self.keep if k != "flow")
        return ("mask", "normal") + (("ao",) if self.method.ao_rays else ())

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal") + (("ao",) if m.ao_rays else ())

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        return self.colored(FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=rendered.ao), timer)

    def rows(self, camera: Camera, start: int, stop: int) -> torch.Tensor:
        """Rows ``[start, stop)`` of the frame's color only (a focus lens's region).

        Shape:
            Returns (stop - start, W, 3).
        """
        rendered = self.renderer.render(camera, self.render_request(), rows=(start, stop))
        ao = None if rendered.ao is None else rendered.ao[start:stop]
        return shade(rendered.mask[start:stop], rendered.normal[start:stop], ao, self.shading)


@register_runner("atrous")
class ATrousRunner(FrameRunner):
    """Full resolution, AO from 1-4 (or more) rays per hit smoothed by the edge-avoiding a-trous filter."""

    label = "filtered AO (a-trous)"
    default_ao_rays = 4

    knobs = ("ao_rays", "spp")
    ao_rays = (1, MAX_AO_SAMPLES)
    spp = (1, MAX_SPP)

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
        return self.colored(FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=ao), timer)


@register_runner("svgf")
class SVGFRunner(FrameRunner):
    """Full resolution, AO from 1-4 (or more) rays per hit, a new set of rays each frame, accumulated
    along the flow and filtered by SVGF (:func:`isosr_net.svgf.svgf_filter`); a frame without a
    previous camera starts the history anew."""

    label = "filtered AO (SVGF)"
    default_ao_rays = 1

    recurrent = True
    fresh_rays = True
    knobs = ("ao_rays", "spp")
    ao_rays = (1, MAX_AO_SAMPLES)
    spp = (1, MAX_SPP)
    config: ClassVar[SVGFConfig] = SVGFConfig()  # the temporal knobs (the a-trous ones: the runner's atrous)

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.history: SVGFHistory | None = None
        self._prev_camera: Camera | None = None

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, svgf" + (f", spp {m.spp}" if m.spp > 1 else "")

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "depth", "position", "ao")

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal", "ao")

    def steps(self, camera: Camera, prev_camera: Camera | None = None,
              slice_ms: float | None = None) -> Generator[None, None, FrameResult]:
        self._prev_camera = prev_camera  # the view the history is reprojected from
        return (yield from super().steps(camera, prev_camera, slice_ms))

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        flow = None if rendered.flow is None else rendered.flow.permute(2, 0, 1)[None]
        with timer("filter"):
            ao, self.history = svgf_filter(rendered.ao[None, None], rendered.mask[None, None],
                                           rendered.normal.permute(2, 0, 1)[None], rendered.depth[None, None],
                                           rendered.position.permute(2, 0, 1)[None], flow, self._prev_camera,
                                           self.history, self.config, self.atrous)
        return self.colored(FrameBuffers(mask=rendered.mask, normal=rendered.normal, ao=ao[0, 0]), timer)


@register_runner("oidn")
class OIDNRunner(FrameRunner):
    """Full resolution, 1-4 (or more) AO rays per hit shaded, the noisy color denoised by Intel Open
    Image Denoise with the AO-free shading as albedo and the normals as clean auxiliary images
    (:func:`isosr_net.oidn.denoise`). Its frames hold a color but no AO."""

    label = "denoised AO (OIDN)"
    default_ao_rays = 1

    knobs = ("ao_rays", "spp", "quality")
    ao_rays = (1, MAX_AO_SAMPLES)
    spp = (1, MAX_SPP)

    @classmethod
    def unavailable(cls) -> str | None:
        return oidn.unavailable()

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"full, AO {m.ao_rays}, oidn {m.quality}" + (f", spp {m.spp}" if m.spp > 1 else "")

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "ao")

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal")

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        buffers = FrameBuffers(mask=rendered.mask, normal=rendered.normal)
        if self.shade:
            with timer("shading"):
                noisy = shade_on(rendered.mask.device.type)(rendered.mask, rendered.normal, rendered.ao, self.shading)
                albedo = shade_on(rendered.mask.device.type)(rendered.mask, rendered.normal, None, self.shading)
            with timer("filter"):
                buffers.color = oidn.denoise(noisy, albedo, rendered.normal, self.method.quality)
        return buffers


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
    default_ao_rays = 2

    recurrent = True
    fresh_rays = True  # accumulated along the flow before the network (isosr_net.ray_history)
    network_class = Reconstructor
    default_model = DEFAULT_RECON_MODEL
    knobs = ("ao_rays", "spp", "factor", "model", "precision")
    ao_rays = (0, MAX_AO_SAMPLES)
    factor = (1, max(UPSCALES))

    @classmethod
    def bounds(cls, m: FrameMethod) -> dict[str, tuple[int, int]]:
        return super().bounds(m) | {"spp": (1, recon_limits(m.model or cls.default_model).max_spp)}

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"{'full' if m.factor == 1 else f'x{m.factor}'}, AO {m.ao_rays}, spp {m.spp}, {m.model_name} {m.precision}"

    def outputs(self) -> tuple[str, ...]:
        return ("mask", "normal", "depth") + (("ao", "position") if self.method.ao_rays else ())

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return ("mask", "normal", "depth", "ao")

    @property
    def read_rays(self) -> int:
        """The AO rays per hit the network reads the frame's mean as (at most its ``max_ao_rays``)."""
        return self.net.limits.read(self.method.ao_rays)

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("network"):  # shading included: one call
            return self.net.reconstruct(rendered, self.read_rays, self.method.spp,
                                        self.shading if self.shade else None)

    def render_finish(self, camera: Camera, request: RenderRequest,
                      timer: StageTimer) -> tuple[FrameBuffers, FrameBuffers]:
        if not self.net.graphable(self.renderer, request):
            return super().render_finish(camera, request, timer)
        with timer("render"):  # the network and the shading included: one graph
            rendered, out = self.net.render_reconstruct(self.renderer, camera, request, self.read_rays,
                                                        self.method.spp, self.shading if self.shade else None)
        return rendered, out


def reconstruct_method(model: str | None = None, **knobs) -> FrameMethod:
    """The ``reconstruct`` method of ``model`` (None: the shipped one) at the model's own upscale
    (:attr:`~isosr_net.reconnet.ReconNetConfig.upscale`: an x2 model renders at half the sides);
    ``knobs``: the method's others."""
    return FrameMethod("reconstruct", factor=recon_config(model or DEFAULT_RECON_MODEL).upscale, model=model, **knobs)


@register_runner("upscale")
class ClassicUpscaleRunner(FrameRunner):
    """A low-res ray cast upscaled by interpolation, shaded without AO."""

    label = "classic upscaling"

    low_res = True
    knobs = ("factor", "interpolation")
    factor = (2, MAX_FACTOR)

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} {m.interpolation}"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("filter"):
            up = upscale_classic(rendered, self.method.factor, self.method.interpolation)
        up.ao = None  # no AO: shaded unoccluded
        return self.colored(up, timer)


@register_runner("network")
class NetworkRunner(FrameRunner):
    """A low-res ray cast upscaled by the trained network (which infers AO), shaded."""

    label = "network upscaling"

    low_res = True
    recurrent = True
    network_class = Upscaler
    default_model = DEFAULT_MODEL
    knobs = ("factor", "model", "precision")
    factor = (2, MAX_FACTOR)

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} {m.model_name} {m.precision}"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS + ("ao",)

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("network"):
            high = self.net.upscale(rendered)
        return self.colored(high, timer)


@register_runner("buffers")
class BuffersRunner(FrameRunner):
    """The low-res ray cast itself (mask, normal, depth; flow after a previous camera), unshaded:
    for a client that upscales and shades them."""

    label = "low-res buffers (the client upscales)"

    low_res = True
    recurrent = True
    shaded = False
    knobs = ("factor",)
    factor = (2, MAX_FACTOR)

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} buffers"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS + ("flow",)

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        return rendered


def make_runner(method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                **options) -> FrameRunner:
    """The registered runner of ``method`` (arguments and options: :class:`FrameRunner`)."""
    return method.runner(method, renderer, iso, width, height, **options)


def upscale_classic(low: FrameBuffers, factor: int, interpolation: str = "bilinear") -> FrameBuffers:
    """A low-res frame's mask, normal and depth upscaled by interpolation
    (:func:`isosr_net.metrics.upscale_baseline`), as the network's outputs are laid out; AO is 1
    everywhere: an interpolator knows no occlusion.

    Shape:
        low: mask, depth (h, w), normal (h, w, 3). Returns mask, depth, ao (H, W), normal (H, W, 3),
        ``H = h * factor``, ``W = w * factor``.
    """
    return output_buffers(upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], factor, interpolation))


def run_sequence(runner: FrameRunner, cameras: list[Camera]) -> list[FrameBuffers]:
    """A new sequence along ``cameras``: each frame's buffers (copies: the runner may reuse its memory)."""
    return [runner.frame(camera, prev).buffers.clone() for camera, prev in sequence_cameras(cameras)]


@dataclass
class FrameStream:
    """One viewer's frames whatever it asks for next: the runner of the current method, iso, size
    and AO radius, made anew when any of them changes. The one place the recurrent reset is
    decided for a stream: a new runner starts without state (so a change of settings or size is a
    cut), and so does a frame without a previous camera.

    Args:
        networks: the stream's own networks (:meth:`Networks.fork`).
        shading: material and light.
    """

    networks: Networks
    shading: ShadingParams = field(default_factory=ShadingParams)
    runner: FrameRunner | None = None
    _key: tuple | None = None

    def frame(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int, camera: Camera,
              prev_camera: Camera | None, ao_radius: float = AO_RADIUS, keep: tuple[str, ...] = (),
              shade: bool = True) -> FrameResult:
        """The next frame; ``prev_camera`` counts only while the runner stays the same."""
        return finish_steps(self.steps(method, renderer, iso, width, height, camera, prev_camera, ao_radius, keep,
                                       shade))

    def steps(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int, camera: Camera,
              prev_camera: Camera | None, ao_radius: float = AO_RADIUS, keep: tuple[str, ...] = (),
              shade: bool = True, slice_ms: float | None = None) -> Generator[None, None, FrameResult]:
        """:meth:`frame` in slices (:meth:`FrameRunner.steps`)."""
        key = (method, renderer, float(iso), width, height, float(ao_radius), tuple(keep), shade)
        if key != self._key:
            self.runner = make_runner(method, renderer, iso, width, height, shading=self.shading,
                                      ao_radius=ao_radius, networks=self.networks, keep=keep, shade=shade)
            self._key, prev_camera = key, None
        return (yield from self.runner.steps(camera, prev_camera, slice_ms))
