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

A coloring (``settings.coloring``) is a :class:`~isosr_render.color_field.ColorField` of the frame's
renderer, made on the device thread once per renderer, coloring and field volume (the job's
``field``, which the session resolved from the catalog), kept while they stay: a new one is a cut.
A shaded frame's legend is then the coloring's.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Generator
from dataclasses import dataclass, field, fields
from typing import ClassVar

import torch

from isosr_net.budget import BudgetChoice
from isosr_net.methods import RUNNERS, FrameMethod, FrameResult, FrameRunner, FrameStream, Networks, make_runner
from isosr_net.timing import StageTimer
from isosr_render import Camera, Renderer, Volume
from isosr_render.color_field import ColorField
from isosr_render.surfaces import Surfaces
from isosr_server.auto import AutoPolicy, served_factor
from isosr_server.channels import false_color
from isosr_render.renderer import MAX_AO_SAMPLES
from isosr_server.protocol import (CLOSE_POLICY, MAX_VIEW_SPP, AutoChoice, FocusMsg, ModeInfo, OptionInfo,
                                   ProtocolError, ViewSettings, surfaces_of)


@dataclass(frozen=True)
class ViewContext:
    """What the server's configuration fixes for every view: the networks' upscale factor,
    precision, and model folders with their display names by network class (None: the shipped one)."""

    factor: int
    precision: str
    models: dict = field(default_factory=dict)  # network class -> (folder or None, name)


# The knobs a view session's settings give a method, each with the most a session may ask for
# (None: the method's own bound); the server fixes the others (factor, model, precision).
VIEW_KNOBS = {"ao_rays": None, "spp": MAX_VIEW_SPP, "interpolation": None}


def method_for(kind: str, settings: ViewSettings, ctx: ViewContext) -> FrameMethod:
    """The frame method ``kind`` with the knobs it takes from the settings and the server (the
    others, e.g. OIDN's quality, at the method's defaults).

    Raises:
        ValueError: the settings are outside what the method takes (e.g. 9 AO rays to reconstruct).
    """
    runner = RUNNERS[kind]
    model, name = ctx.models.get(runner.network_class, (None, "network"))
    values = {k: getattr(settings, k) for k in VIEW_KNOBS} | {
        "factor": served_factor(runner, ctx.factor), "precision": ctx.precision,
        "model": None if model is None else str(model), "model_name": name}
    takes = {f.name for f in fields(runner.options_type)}
    return FrameMethod.of(kind, **{k: v for k, v in values.items() if k in takes})


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
    field: Volume | None = None  # the volume settings.coloring names (None: none, or the gradient)


@dataclass
class ViewFrame:
    """A made view frame: the color to encode (None: ``buffers``, whose low-res buffers travel
    coded), the method's result, the channel legend, the frame whose camera the flow refers to, and
    what ``auto`` expects of the method it chose."""

    color: torch.Tensor | None
    result: FrameResult
    method: FrameMethod
    legend: dict | None = None
    prev_seq: int = -1
    choice: AutoChoice | None = None


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

    def choose(self, settings: ViewSettings, ctx: ViewContext, frames: SessionFrames, renderer: Renderer,
               job: FrameJob) -> tuple[FrameMethod, AutoChoice | None]:
        """The method of this frame and what is expected of it where the server chose it (``auto``)."""
        return self.method(settings, ctx, frames, renderer, job), None

    def sample(self, settings: ViewSettings, ctx: ViewContext) -> FrameMethod | None:
        """The method the settings name, to check them once (None: it is chosen per frame)."""
        return self.method(settings, ctx, None, None, None)

    def compose(self, result: FrameResult, renderer: Renderer, job: FrameJob, timer: StageTimer,
                runner: FrameRunner) -> torch.Tensor:
        """The final color of a shaded frame (``runner``: the one that made it)."""
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
    """The view settings a method takes (:data:`VIEW_KNOBS`), from its options type: each with its
    default and its bounds (where the server's models set them) or its choices."""
    knobs = [f for f in fields(runner.options_type) if f.name in VIEW_KNOBS]
    defaults = ViewSettings(**{f.name: f.default for f in knobs})
    bounds = method_for(runner.kind, defaults, ctx).options.bounds()
    out = []
    for f in knobs:
        if f.name in bounds:
            low, high = bounds[f.name]
            most = VIEW_KNOBS[f.name]
            out.append(OptionInfo(f.name, low, high if most is None else min(high, most), default=f.default))
        else:
            out.append(OptionInfo(f.name, default=f.default, choices=list(f.metadata["choices"])))
    return out


class FocusView(View):
    """``network`` frames with a full-resolution lens inside the focus region (module docstring)."""

    name = "focus"
    label = "focus + context (lens)"

    def info(self, ctx: ViewContext) -> ModeInfo:
        return ModeInfo(self.name, self.label, [OptionInfo("ao_rays", 0, MAX_AO_SAMPLES, default=0)], low_res=True,
                        focus=True)

    def method(self, settings, ctx, frames, renderer, job) -> FrameMethod:
        return method_for("network", settings, ctx)

    def compose(self, result, renderer, job, timer, runner) -> torch.Tensor:
        color, st = result.buffers.color, job.settings
        with timer("shading"):
            weight = focus_weight(job.focus, st.width, st.height, st.focus_blend_px, color.device)
            covered = weight.amax(dim=1).nonzero()
        if len(covered) == 0:
            return color
        start, stop = int(covered[0]), int(covered[-1]) + 1
        lens = make_runner(FrameMethod.of("full", ao_rays=st.ao_rays, spp=st.spp), renderer, runner.iso, st.width,
                           st.height, ao_radius=st.ao_radius, clip=runner.clip, coloring=runner.coloring,
                           surfaces=runner.surfaces)
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
        return self.choose(settings, ctx, frames, renderer, job)[0]

    def choose(self, settings, ctx, frames, renderer, job) -> tuple[FrameMethod, AutoChoice]:
        choice = frames.auto.choose(renderer, frames.scene, job.iso, settings.width, settings.height, job.camera,
                                    job.sessions, settings.ao_radius, settings.clip.clip())
        return choice.method, expected(choice)


def expected(choice: BudgetChoice) -> AutoChoice:
    """What a frame says of the policy's choice: from the probe (its table of candidates), the cost table
    (a predicted time) or the prior (nothing measured). A time or PSNR not measured, or not finite (a
    candidate equal to the reference scores an infinite PSNR), travels as None."""
    known = (lambda v: float(v) if math.isfinite(v) else None)
    source = "probe" if choice.table else "prior" if math.isnan(choice.ms) else "table"
    return AutoChoice(choice.budget_ms, known(choice.ms), known(choice.expected_psnr), choice.fits, source)


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
                            + (" (give ao_rays > 0)" if "ao_rays" in method.options.bounds() else ""))


def refined_method(settings: ViewSettings) -> FrameMethod:
    """The still camera's refined frame: full resolution with ``refine_ao_rays``."""
    return FrameMethod.of("full", ao_rays=settings.refine_ao_rays, spp=settings.spp)


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
        self._coloring: tuple[tuple, ColorField] | None = None  # (renderer, settings, field), its ColorField

    def steps(self, renderer: Renderer, job: FrameJob,
              slice_ms: float | None = None) -> Generator[None, None, ViewFrame]:
        """Make one frame of ``job`` (device thread) in slices of about ``slice_ms``
        (:meth:`isosr_net.methods.FrameRunner.steps`): a generator that returns the frame."""
        return self.planned_steps(self.plan(renderer, job), slice_ms)

    def plan(self, renderer: Renderer, job: FrameJob) -> FramePlan:
        """The runner of ``job``'s frame and what it continues from (device thread): made next by
        :meth:`planned_steps`, or with other sessions' frames by the runner's ``make_batch``, then
        finished by :meth:`made`."""
        st = job.settings
        shaded = st.channel == "shaded"
        keep = () if shaded else (st.channel,)
        clip, coloring = st.clip.clip(), self.coloring(renderer, job)
        iso, surfaces = self.surfaces(renderer, job)
        if job.refined:
            method = refined_method(st)
            runner = make_runner(method, renderer, iso, st.width, st.height, ao_radius=st.ao_radius, keep=keep,
                                 shade=shaded, clip=clip, coloring=coloring, surfaces=surfaces)
            return FramePlan(job, renderer, method, runner, None, -1, None)
        view = VIEWS[st.mode]
        method, choice = view.choose(st, self.ctx, self, renderer, job)
        if surfaces is not None and surfaces.layers > 1 and not method.runner.shaded:
            method = FrameMethod.of("full", ao_rays=st.ao_rays, spp=st.spp)  # buffers: one layer sent unshaded
        prev_camera, prev_seq = self._prev or (None, -1)
        runner, prev_camera = self.stream.runner_for(method, renderer, iso, st.width, st.height, prev_camera,
                                                     st.ao_radius, keep, shaded, clip, coloring, surfaces)
        return FramePlan(job, renderer, method, runner, prev_camera, prev_seq, view, choice)

    def served(self, job: FrameJob, made: ViewFrame, thread_ms: float) -> None:
        """What an ``auto`` frame cost the device thread in service, for the policy that chose it
        (:meth:`AutoPolicy.served`; event loop)."""
        if made.choice is not None and self.auto is not None:
            st = job.settings
            self.auto.served(self.scene, job.iso, st.width, st.height, job.sessions, st.ao_radius, st.clip.clip(),
                             made.method, thread_ms)

    def coloring(self, renderer: Renderer, job: FrameJob) -> ColorField | None:
        """The job's coloring on the renderer's device (module docstring).

        Raises:
            ProtocolError: the field's grid is not the renderer's volume's (naming both shapes).
        """
        settings = job.settings.coloring
        if settings is None:
            return None
        key = (id(renderer), settings, id(job.field))
        if self._coloring is None or self._coloring[0] != key:
            try:
                made = ColorField.of(settings.coloring(), renderer.volume, job.field, renderer.torch_device)
            except ValueError as e:
                raise ProtocolError(f"settings.coloring: {e}", CLOSE_POLICY, 422) from None
            self._coloring = key, made
        return self._coloring[1]

    @staticmethod
    def surfaces(renderer: Renderer, job: FrameJob) -> tuple[float, Surfaces | None]:
        """The normalized iso the job's view renders and its surfaces, their isos normalized for the renderer's
        volume (None: the one ``job.iso``; else the iso is their first's). A frame's and a pick's.

        Raises:
            ProtocolError: two isos equal once normalized, or a volume rendered sparse (422).
        """
        surfaces = surfaces_of(job.settings.surfaces, renderer.volume.normalized_iso)
        if surfaces is not None and renderer.pool is not None:
            raise ProtocolError("settings.surfaces: several surfaces need a volume held dense on the device; this one "
                                "renders sparse", CLOSE_POLICY, 422)
        return (job.iso if surfaces is None else surfaces.iso), surfaces

    def planned_steps(self, plan: FramePlan, slice_ms: float | None = None) -> Generator[None, None, ViewFrame]:
        """A planned frame made alone, in slices of about ``slice_ms``."""
        result = yield from plan.runner.steps(plan.job.camera, plan.prev_camera, slice_ms)
        return self.made(plan, result)

    def made(self, plan: FramePlan, result: FrameResult) -> ViewFrame:
        """A planned frame's result as a view frame: its mode's composition, or a channel's false colors."""
        job, st = plan.job, plan.job.settings
        timer = StageTimer(str(plan.renderer.device))
        prev_seq = -1
        if plan.view is not None:  # a moving frame: the next one continues from it
            self._prev = (job.camera, job.seq)
            prev_seq = plan.prev_seq if result.continued else -1
        if st.channel != "shaded":
            with timer("shading"):
                color, legend = false_color(result.buffers, st.channel)
        elif not plan.method.runner.shaded:
            color, legend = None, None
        else:
            coloring = plan.runner.coloring
            color = result.buffers.color if plan.view is None else plan.view.compose(result, plan.renderer, job, timer,
                                                                                     plan.runner)
            legend = None if coloring is None else coloring_legend(coloring)
        result.timers.append(timer)
        return ViewFrame(color, result, plan.method, legend, prev_seq, plan.choice)


@dataclass(frozen=True)
class FramePlan:
    """A view frame about to be made (:meth:`SessionFrames.plan`): its job, the runner that makes it
    from ``camera`` after ``prev_camera`` (None: a cut), the previous frame's seq, its view mode
    (None: the still camera's refined frame) and what ``auto`` expects of the method it chose."""

    job: FrameJob
    renderer: Renderer
    method: FrameMethod
    runner: FrameRunner
    prev_camera: Camera | None
    prev_seq: int
    view: View | None
    choice: AutoChoice | None = None


def coloring_legend(coloring: ColorField) -> dict:
    """A coloring's legend as a shaded frame carries it (``protocol.Legend``: channel ``shaded``, ``unit``
    what colours it, the colour map's name and stops)."""
    c = coloring.legend()
    return {"channel": "shaded", "lo": c["lo"], "hi": c["hi"], "unit": c["by"], "colormap": c["colormap"],
            "stops": c["stops"]}


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
