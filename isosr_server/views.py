"""The view modes: how a view session's settings become frames (on the engine's device thread).

Every frame method of isosr_net's registry (:data:`isosr_net.methods.RUNNERS`) that is a
view mode and can run here is a mode of that name, run by the session's `FrameStream` with the
knobs its settings name. Two more are compositions only a viewer has:

    auto    the budget policy's method for this session's share of the device (:mod:`isosr_server.auto`)
    focus   ``network`` frames with a full-resolution lens (``ao_rays`` AO rays) inside the focus
            region, blended in by a weight that ramps from 0 at its border to 1 ``focus_blend_px`` inside

A still camera's refined frame is the ``full`` method with ``refine_ao_rays``, made outside the
stream (its recurrent state is kept for the next moving frame). A channel view (``channel`` other
than ``shaded``) false-colors one buffer of the mode's frame instead of its color
(:mod:`isosr_server.channels`); the method makes that buffer too, and nothing else besides.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from isosr_net.methods import RUNNERS, FrameMethod, FrameResult, FrameRunner, FrameStream, Networks, make_runner
from isosr_net.timing import StageTimer
from isosr_render import Camera, Renderer
from isosr_server.auto import AutoPolicy, served_factor
from isosr_server.channels import false_color
from isosr_net.metrics import INTERPOLATIONS
from isosr_render.renderer import MAX_AO_SAMPLES
from isosr_server.protocol import MAX_VIEW_SPP, FocusMsg, ModeInfo, OptionInfo, ProtocolError, ViewSettings


@dataclass(frozen=True)
class ViewContext:
    """What the server's configuration fixes for every view: the networks' upscale factor,
    precision, and model folders with their display names by network class (None: the shipped one)."""

    factor: int
    precision: str
    models: dict = field(default_factory=dict)  # network class -> (folder or None, name)


def method_for(kind: str, settings: ViewSettings, ctx: ViewContext) -> FrameMethod:
    """The frame method ``kind`` with the knobs it reads from the settings and the server (the
    others, e.g. OIDN's quality, at the method's defaults).

    Raises:
        ValueError: the settings are outside what the method takes (e.g. 9 AO rays to reconstruct).
    """
    runner = RUNNERS[kind]
    values = {"ao_rays": settings.ao_rays, "spp": settings.spp, "interpolation": settings.interpolation,
              "factor": served_factor(runner, ctx.factor), "precision": ctx.precision}
    model, name = ctx.models.get(runner.network_class, (None, "network"))
    values["model"] = None if model is None else str(model)
    return FrameMethod(kind, model_name=name, **{k: values[k] for k in runner.knobs if k in values})


@dataclass(frozen=True)
class FrameJob:
    """One frame a view session asks for (made on the device thread)."""

    settings: ViewSettings
    camera: Camera
    iso: float
    focus: FocusMsg
    seq: int
    refined: bool
    sessions: int  # view sessions the device serves now (the auto mode's share)


@dataclass
class ViewFrame:
    """A made view frame: the color to encode (None: ``buffers``, whose low-res buffers travel
    coded), the method's result, the channel legend, and the frame whose camera the flow refers to."""

    color: torch.Tensor | None
    result: FrameResult
    method: FrameMethod
    legend: dict | None = None
    prev_seq: int = -1


class View(ABC):
    """One view mode: which method makes the next frame, and what is composed on top."""

    name: ClassVar[str]
    label: ClassVar[str]

    @abstractmethod
    def info(self, ctx: ViewContext) -> ModeInfo:
        """What a viewer shows of this mode: its label and the settings it reads with their bounds."""

    @abstractmethod
    def method(self, settings: ViewSettings, ctx: ViewContext, frames: SessionFrames, renderer: Renderer,
               job: FrameJob) -> FrameMethod:
        """The method of this frame."""

    def sample(self, settings: ViewSettings, ctx: ViewContext) -> FrameMethod | None:
        """The method the settings name, to check them once (None: it is chosen per frame)."""
        return self.method(settings, ctx, None, None, None)

    def compose(self, result: FrameResult, renderer: Renderer, job: FrameJob, timer: StageTimer) -> torch.Tensor:
        """The final color of a shaded frame."""
        return result.buffers.color


@dataclass(frozen=True)
class MethodView(View):
    """A mode that is a registered frame method."""

    name: str

    @property
    def label(self) -> str:
        return RUNNERS[self.name].label

    def info(self, ctx: ViewContext) -> ModeInfo:
        runner = RUNNERS[self.name]
        return ModeInfo(self.name, self.label, method_options(runner, ctx), runner.shaded, runner.low_res)

    def method(self, settings, ctx, frames, renderer, job) -> FrameMethod:
        return method_for(self.name, settings, ctx)


def method_options(runner: type[FrameRunner], ctx: ViewContext) -> list[OptionInfo]:
    """The view settings a method reads, with its bounds where the server's models set them
    (the knobs the server fixes, factor, model and precision, are not the viewer's)."""
    bounds = runner.bounds(method_for(runner.kind, ViewSettings(ao_rays=runner.default_ao_rays), ctx))
    options = {"ao_rays": OptionInfo("ao_rays", *bounds["ao_rays"], default=runner.default_ao_rays),
               "spp": OptionInfo("spp", bounds["spp"][0], min(bounds["spp"][1], MAX_VIEW_SPP), default=1),
               "interpolation": OptionInfo("interpolation", default="bilinear", choices=list(INTERPOLATIONS))}
    return [options[k] for k in runner.knobs if k in options]


class FocusView(View):
    """``network`` frames with a full-resolution lens inside the focus region (module docstring)."""

    name = "focus"
    label = "focus + context (lens)"

    def info(self, ctx: ViewContext) -> ModeInfo:
        return ModeInfo(self.name, self.label, [OptionInfo("ao_rays", 0, MAX_AO_SAMPLES, default=0)], low_res=True,
                        focus=True)

    def method(self, settings, ctx, frames, renderer, job) -> FrameMethod:
        return method_for("network", settings, ctx)

    def compose(self, result, renderer, job, timer) -> torch.Tensor:
        color, st = result.buffers.color, job.settings
        with timer("shading"):
            weight = focus_weight(job.focus, st.width, st.height, st.focus_blend_px, color.device)
            covered = weight.amax(dim=1).nonzero()
        if len(covered) == 0:
            return color
        start, stop = int(covered[0]), int(covered[-1]) + 1
        lens = make_runner(FrameMethod("full", ao_rays=st.ao_rays, spp=st.spp), renderer, job.iso, st.width,
                           st.height, ao_radius=st.ao_radius, clip=st.clip.clip())
        with timer("render"):
            sharp = lens.rows(job.camera, start, stop)
        with timer("shading"):
            w = weight[start:stop, :, None]
            color[start:stop] = color[start:stop] * (1.0 - w) + sharp * w
        return color


class AutoView(View):
    """The budget policy's method for this session's share of the device (:class:`AutoPolicy`)."""

    name = "auto"
    label = "auto (the server chooses)"

    def info(self, ctx: ViewContext) -> ModeInfo:
        return ModeInfo(self.name, self.label, [])

    def sample(self, settings, ctx) -> None:
        return None

    def method(self, settings, ctx, frames, renderer, job) -> FrameMethod:
        return frames.auto.choose(renderer, frames.scene, job.iso, settings.width, settings.height, job.camera,
                                  job.sessions, settings.ao_radius).method


# auto, the registered view-mode methods that can run here (in the registry's order), focus.
VIEWS: dict[str, View] = {v.name: v for v in [AutoView()] + [MethodView(k) for k, cls in RUNNERS.items()
                                                             if cls.view_mode and cls.unavailable() is None]
                          + [FocusView()]}


def mode_infos(ctx: ViewContext) -> list[ModeInfo]:
    """The modes this server offers, as ``ready`` and ``GET /v1/modes`` list them."""
    return [view.info(ctx) for view in VIEWS.values()]


def check(settings: ViewSettings, ctx: ViewContext) -> None:
    """`ProtocolError` for settings no frame can be made of: knobs outside the method's bounds, a size
    a low-res method's factor does not divide, a channel the mode does not make, a mode this server
    does not offer."""
    if settings.mode not in VIEWS:
        raise ProtocolError(f"unknown mode {settings.mode!r}; this server offers {', '.join(VIEWS)}")
    try:
        method = VIEWS[settings.mode].sample(settings, ctx)
    except ValueError as e:
        raise ProtocolError(f"{settings.mode} mode: {e}") from None
    if method is None:
        return
    runner = method.runner
    if runner.low_res and (settings.width % method.factor or settings.height % method.factor):
        raise ProtocolError(f"size {settings.width}x{settings.height} must be a multiple of the upscale factor "
                            f"{method.factor} in {settings.mode} mode")
    if settings.channel != "shaded" and not runner.shaded:
        raise ProtocolError(f"{settings.mode} mode has no channel view: its buffers travel themselves")
    if settings.channel == "ao" and "ao" not in runner.makes(method):
        raise ProtocolError(f"{settings.mode} mode makes no AO to show"
                            + (" (give ao_rays > 0)" if runner.bounds(method)["ao_rays"][1] else ""))


def refined_method(settings: ViewSettings) -> FrameMethod:
    """The still camera's refined frame: full resolution with ``refine_ao_rays``."""
    return FrameMethod("full", ao_rays=settings.refine_ao_rays, spp=settings.spp)


def refines(settings: ViewSettings, ctx: ViewContext) -> bool:
    """Whether a still camera gets a refined frame: refine is on and the mode's own frames are not
    already a full-resolution render with at least as many AO rays (auto's choice varies: always)."""
    if not settings.refine:
        return False
    method, refined = VIEWS[settings.mode].sample(settings, ctx), refined_method(settings)
    return method is None or method.runner is not refined.runner or method.ao_rays < refined.ao_rays


class SessionFrames:
    """A view session's device-side state: its frame stream (own networks and recurrent state), the
    previous moving frame's camera and seq, and the frames it makes.

    Args:
        scene: the volume's name (the auto mode's probe cache key).
        networks: the session's own networks (:meth:`Networks.fork`).
        ctx: the server's view context.
        auto: the server's auto policy.
    """

    def __init__(self, scene: str, networks: Networks, ctx: ViewContext, auto: AutoPolicy):
        self.scene, self.ctx, self.auto = scene, ctx, auto
        self.stream = FrameStream(networks)
        self._prev: tuple[Camera, int] | None = None

    def steps(self, renderer: Renderer, job: FrameJob,
              slice_ms: float | None = None) -> Generator[None, None, ViewFrame]:
        """Make one frame of ``job`` (device thread) in slices of about ``slice_ms``
        (:meth:`isosr_net.methods.FrameRunner.steps`): a generator that returns the frame."""
        st = job.settings
        shaded = st.channel == "shaded"
        keep = () if shaded else (st.channel,)
        timer = StageTimer(str(renderer.device))
        clip = st.clip.clip()
        if job.refined:
            method = refined_method(st)
            runner = make_runner(method, renderer, job.iso, st.width, st.height, ao_radius=st.ao_radius, keep=keep,
                                 shade=shaded, clip=clip)
            result = yield from runner.steps(job.camera, None, slice_ms)
            prev_seq = -1
        else:
            view = VIEWS[st.mode]
            method = view.method(st, self.ctx, self, renderer, job)
            prev_camera, prev_seq = self._prev or (None, -1)
            result = yield from self.stream.steps(method, renderer, job.iso, st.width, st.height, job.camera,
                                                  prev_camera, st.ao_radius, keep, shaded, slice_ms, clip)
            self._prev = (job.camera, job.seq)
            prev_seq = prev_seq if result.continued else -1
        if not shaded:
            with timer("shading"):
                color, legend = false_color(result.buffers, st.channel)
        elif not method.runner.shaded:
            color, legend = None, None
        else:
            color = result.buffers.color if job.refined else view.compose(result, renderer, job, timer)
            legend = None
        result.timers.append(timer)
        return ViewFrame(color, result, method, legend, prev_seq)


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
