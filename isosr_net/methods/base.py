"""The frame contract: a :class:`FrameMethod` names a way to make frames and its options (a frozen,
hashable value of the kind's :class:`MethodOptions`); a :class:`FrameRunner` makes one stream's
frames with it; :data:`RUNNERS` is the registry by kind (:func:`register_runner`), as diffusers' schedulers
share one ``step()`` contract; :class:`FrameStream` is one viewer's frames whatever it asks for next. The methods
themselves are one module each in this package (:mod:`isosr_net.methods`).
"""

from __future__ import annotations

import os
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Generator, Iterable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, get_type_hints

import torch

from isosr_net.filters.atrous import ATrousConfig
from isosr_net.inference import PRECISIONS, LateChecks, RecurrentNetwork
from isosr_net.reconnet import RayLimits
from isosr_net.timing import StageTimer
from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest
from isosr_render.clip import Clip
from isosr_render.color_field import ColorField
from isosr_render.conventions import AO_RADIUS
from isosr_render.renderer import MAX_AO_SAMPLES, MAX_SPP, surface_opacity
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import ShadingParams, composite, shade_on
from isosr_render.shapes import check_int
from isosr_render.steps import finish_steps
from isosr_render.surfaces import Surfaces

# Upscaling factors a low-res method takes.
MAX_FACTOR = 16
# The AO seed of a temporal method's first frame, one more per frame: other methods cast with
# seed 0 and the quality reference with 1 (isosr_net.budget.REFERENCE_SEED), so no frame's rays
# are the reference's.
FIRST_TEMPORAL_SEED = 2
# Another draw of the same frames' rays (FrameRunner's ``draw``) shifts every seed by this many (a temporal
# stream's seeds wrap within its draw's): no draw meets another's seeds, nor the reference's.
DRAW_SEEDS = 2 ** 20


def count(default: int, low: int, high: int) -> Any:
    """An options field that counts: an integer in ``[low, high]`` (its bounds, in the field's metadata)."""
    return field(default=default, metadata={"bounds": (low, high)})


def choice(default: str, choices: Iterable[str]) -> Any:
    """An options field that names one of ``choices`` (in the field's metadata)."""
    return field(default=default, metadata={"choices": tuple(choices)})


@dataclass(frozen=True)
class MethodOptions:
    """A kind's knobs, a frozen and hashable value: each method module subclasses it (its runner's
    ``options_type``), declaring counts by :func:`count` with their bounds and named choices by
    :func:`choice`. Making one refuses a value outside them, naming the field."""

    def __post_init__(self):
        for name, (low, high) in self.bounds().items():
            check_int(getattr(self, name), name, low, high)
        for f in fields(self):
            choices, value = f.metadata.get("choices"), getattr(self, f.name)
            if choices is not None and value not in choices:
                raise ValueError(f"{f.name} must be one of {', '.join(choices)}, got {value!r}")

    @classmethod
    def of(cls, **knobs) -> MethodOptions:
        """Options with ``knobs``, the others at their defaults.

        Raises:
            ValueError: a knob this type does not take (naming those it takes), or one out of bounds.
        """
        names = [f.name for f in fields(cls)]
        for key in knobs:
            if key not in names:
                raise ValueError(f"takes no {key} (only {', '.join(names)})")
        return cls(**knobs)

    def bounds(self) -> dict[str, tuple[int, int]]:
        """The ``(low, high)`` bounds of the counts (a subclass may narrow them by its other fields)."""
        return {f.name: f.metadata["bounds"] for f in fields(self) if "bounds" in f.metadata}


@dataclass(frozen=True)
class RayOptions(MethodOptions):
    """The rays of a full-resolution render.

    Attributes:
        ao_rays: AO rays per hit (0: no AO).
        spp: rays per pixel.
    """

    ao_rays: int = count(0, 0, MAX_AO_SAMPLES)
    spp: int = count(1, 1, MAX_SPP)


@dataclass(frozen=True)
class LowResOptions(MethodOptions):
    """A render at 1/factor of the frame's sides.

    Attributes:
        factor: the upscaling factor.
    """

    factor: int = count(2, 2, MAX_FACTOR)


@dataclass(frozen=True)
class ModelOptions(MethodOptions):
    """A trained network's.

    Attributes:
        model: the network's model folder (None: the kind's shipped one).
        model_name: the network's name in the method's name.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"``.
    """

    model: str | None = None
    model_name: str = "network"
    precision: str = choice("fp32", PRECISIONS)


@dataclass(frozen=True)
class FrameMethod:
    """One way to make frames: a registered kind and its options, a frozen, hashable value. Made
    from knobs by :meth:`of` (from text by :func:`parse_method`). Its counts read as :attr:`ao_rays`,
    :attr:`spp` and :attr:`factor` (neutral where the kind has none), its other knobs as ``options``'.

    Attributes:
        kind: a name of :data:`RUNNERS` (module docstring).
        options: the kind's knobs, of its runner's ``options_type``.
    """

    kind: str
    options: MethodOptions

    def __post_init__(self):
        if type(self.options) is not self.runner.options_type:
            raise TypeError(f"{self.kind} frame method: its options are a {self.runner.options_type.__name__}, "
                            f"not a {type(self.options).__name__}")

    @classmethod
    def of(cls, kind: str, **knobs) -> FrameMethod:
        """The method ``kind`` with ``knobs``, the others at its options' defaults.

        Raises:
            ValueError: an unknown kind, a knob the kind does not take or one out of bounds (naming them).
        """
        options_type = registered_runner(kind).options_type
        try:
            return cls(kind, options_type.of(**knobs))
        except ValueError as e:
            raise ValueError(f"{kind} frame method: {e}") from None

    def replace(self, **knobs) -> FrameMethod:
        """This method with ``knobs`` changed (checked as :meth:`of` checks them)."""
        return FrameMethod.of(self.kind, **(asdict(self.options) | knobs))

    @property
    def ao_rays(self) -> int:
        """AO rays per hit (0 for a kind without: none cast)."""
        return getattr(self.options, "ao_rays", 0)

    @property
    def spp(self) -> int:
        """Rays per pixel (1 for a kind without)."""
        return getattr(self.options, "spp", 1)

    @property
    def factor(self) -> int:
        """The upscaling factor (1 for a kind without: full resolution)."""
        return getattr(self.options, "factor", 1)

    @property
    def runner(self) -> type[FrameRunner]:
        """The registered class that runs this method."""
        return registered_runner(self.kind)

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
        checks: the frame's input checks where they were left to read later (a batch's,
            :meth:`FrameRunner.make_batch`): its taker reads them (:meth:`checked`) once it needs the frame.
    """

    buffers: FrameBuffers
    timers: list[StageTimer]
    continued: bool
    checks: LateChecks | None = None

    def checked(self) -> None:
        """Raise where the frame's checks read late fail (waits for the device to reach them, not longer)."""
        error = None if self.checks is None else self.checks.error()
        if error is not None:
            raise error

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


def registered_runner(kind: str) -> type[FrameRunner]:
    """The runner registered as ``kind``; ValueError naming the registered ones where none is."""
    if kind not in RUNNERS:
        raise ValueError(f"unknown frame method {kind!r}; registered: {', '.join(RUNNERS)}")
    return RUNNERS[kind]


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
        options_type: its knobs with their defaults and bounds (a :class:`MethodOptions`).
        label: a menu's words for it.
        view_mode: a viewer may ask for it by name (a service mode).
        warm_up: the service makes a frame of it at start, before the first viewer's (what its
            first frame compiles: shading with and without AO, its network).
        serve_bench_ao: the AO rays the server benchmark runs its view mode at, one case each
            (:mod:`isosr_bench.bench_server`; empty: none).
        plot_color: its matplotlib color in the Pareto plots (:mod:`isosr_bench.report`; None: not plotted).

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
        clip: clip planes, crop box and caps of every ray cast (:mod:`isosr_render.clip`); with caps,
            the color shows the cut faces in the volume's values.
        coloring: colour the surface by a field (:class:`~isosr_render.color_field.ColorField`): the render
            makes its ``albedo``, which the shading uses at the frame size; None: the material's colour.
        surfaces: several isosurfaces (:mod:`isosr_render.surfaces`; ``iso`` must be their first): every ray
            cast stops at the nearest, the render's ``albedo`` (their colours) as a coloring's; None: ``iso``.
            With translucent ones the render makes two layers: a ``layered`` kind composites them itself; another
            shaded kind runs its :meth:`finish` on each layer apart, the second by :attr:`behind`, and composites
            the colours (:meth:`finish_layers`); an unshaded kind refuses them (ValueError).
        layer: 0, the stream's runner; 1, the :attr:`behind` twin of one (translucent surfaces' second layer).
        draw: which draw of the AO rays: 0 (the service's), or another, whose seeds are all another's
            (:data:`DRAW_SEEDS`): a study scores a method over several draws of the same frames.
        layered: composites the two layers of translucent surfaces itself (the render's ``color``).

    Attributes:
        behind: with translucent surfaces on a shaded kind that is not ``layered``, the twin that finishes the second
            layer: the same method and settings, its own state (filter history, a copy of the network sharing the
            weights: :meth:`RecurrentNetwork.own`). None otherwise: opaque surfaces cost nothing more.
        prev_camera: the camera the frame being made continues from (None: a cut).
    """

    kind: ClassVar[str]
    low_res: ClassVar[bool] = False
    recurrent: ClassVar[bool] = False
    shaded: ClassVar[bool] = True
    fresh_rays: ClassVar[bool] = False
    network_class: ClassVar[type[RecurrentNetwork] | None] = None
    default_model: ClassVar[Path | None] = None
    options_type: ClassVar[type[MethodOptions]]
    label: ClassVar[str] = ""
    view_mode: ClassVar[bool] = True
    warm_up: ClassVar[bool] = False
    serve_bench_ao: ClassVar[tuple[int, ...]] = ()
    plot_color: ClassVar[str | None] = None
    layered: ClassVar[bool] = False

    def __init__(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                 shading: ShadingParams = ShadingParams(), ao_radius: float = AO_RADIUS,
                 networks: Networks | None = None, atrous: ATrousConfig = ATrousConfig(), keep: tuple[str, ...] = (),
                 shade: bool = True, clip: Clip = Clip(), coloring: ColorField | None = None,
                 surfaces: Surfaces | None = None, layer: int = 0, draw: int = 0):
        check_int(width, "width", 1, where="frame")
        check_int(height, "height", 1, where="frame")
        check_int(layer, "layer", 0, 1, where="frame")
        check_int(draw, "draw", 0, 2 ** 31 // DRAW_SEEDS - 1, where="frame")
        if (reason := self.unavailable()) is not None:
            raise RuntimeError(f"{method.name} cannot run here: {reason}")
        if width % method.factor or height % method.factor:
            raise ValueError(f"{method.name}: the factor {method.factor} must divide the frame size {width}x{height}")
        self.method, self.renderer, self.iso = method, renderer, float(iso)
        self.width, self.height = width, height
        self.shading, self.ao_radius, self.atrous, self.keep = shading, ao_radius, atrous, tuple(keep)
        self.shade, self.clip, self.coloring, self.surfaces = shade, clip, coloring, surfaces
        if surfaces is not None and self.iso != surfaces.iso:
            raise ValueError(f"{method.name}: iso must be the first surface's ({surfaces.iso}), got {self.iso}")
        translucent = surfaces is not None and surfaces.layers > 1
        if translucent and not self.shaded:
            raise ValueError(f"{method.name}: surfaces: translucent ones (an opacity below 1) need a shaded method "
                             f"(this kind sends one layer's buffers unshaded): make them opaque or pick another")
        self.device = str(renderer.device)
        self._last_timer: StageTimer | None = None  # the previous frame's (read lazily: no sync per frame)
        self.frames = 0  # frames made: with fresh_rays, the next frame's AO seed
        self.draw = draw
        self.layer, self.prev_camera = layer, None
        networks = Networks() if networks is None else networks
        self.net: RecurrentNetwork | None = None
        if self.network_class is not None:
            options = method.options
            self.net = networks.get(self.network_class, Path(options.model or self.default_model), self.device,
                                    options.precision)
            if self.net.upscale_factor != method.factor:
                raise ValueError(f"{method.name}: the model upscales x{self.net.upscale_factor}, not x{method.factor}")
            self.net = self.net.own() if layer else self.net
            self.net.reset()
        self.behind: FrameRunner | None = None
        if translucent and shade and not self.layered and not layer:
            self.behind = type(self)(method, renderer, iso, width, height, shading, ao_radius, networks, atrous,
                                     shade=shade, clip=clip, coloring=coloring, surfaces=surfaces, layer=1,
                                     draw=draw)

    @classmethod
    def unavailable(cls) -> str | None:
        """Why this kind cannot run in this installation (an optional package missing), or None."""
        return None

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """The settings of this kind the Pareto study measures (:mod:`isosr_bench.bench_pareto`),
        fewer with ``smoke``, learned ones in the precisions that are fast on ``device``. A learned kind's
        are of ``model``, ``(name, folder)`` (none where the folder holds another kind's model);
        the others' are asked for without one. Default: none."""
        return []

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """The settings of this kind the budget policy considers (:func:`isosr_net.budget.default_candidates`,
        whose arguments these are), each with its rank: its place in the policy's order, roughly
        cheapest first (the order breaks ties in quality; equal ranks keep the registry's order).
        Default: none."""
        return ()

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
        outputs += ("cap",) if self.shade and self.clip.capped else ()
        outputs += ("surface",) if self.behind is not None else ()  # the layers' opacities (finish_layers)
        m = self.method
        fresh = FIRST_TEMPORAL_SEED + self.frames % (DRAW_SEEDS - FIRST_TEMPORAL_SEED) if self.fresh_rays else 0
        seed = self.draw * DRAW_SEEDS + fresh
        return RenderRequest(self.width // m.factor, self.height // m.factor, self.iso, outputs,
                             ao_radius=self.ao_radius, prev_camera=prev_camera if flow else None,
                             shading=self.shading, spp=m.spp, ao_samples=max(1, m.ao_rays), clip=self.clip,
                             coloring=self.coloring if self.shade else None, surfaces=self.surfaces, seed=seed)

    def frame(self, camera: Camera, prev_camera: Camera | None = None) -> FrameResult:
        """The next frame of the stream; ``prev_camera=None`` starts a new sequence.

        Shape:
            buffers.color, normal: (H, W, 3). mask, depth, ao: (H, W). flow: (H, W, 2).
        """
        return finish_steps(self.steps(camera, prev_camera))

    def one_slice(self, slice_ms: float | None) -> bool:
        """Whether :meth:`steps` makes the next frame in one slice: without ``slice_ms``, or when the
        last frame's ray cast took less (reading it waits for that frame's render on a GPU)."""
        return slice_ms is None or (self._last_timer is not None and self._last_timer.ms()["render"] < slice_ms)

    def batch_key(self) -> tuple:
        """What runners share to make their frames together (:meth:`make_batch`): the kind, the
        renderer and the frame size (a kind that batches more narrowly adds to it)."""
        return type(self), id(self.renderer), self.width, self.height

    @classmethod
    def make_batch(cls, frames: list[tuple[FrameRunner, Camera, Camera | None]]) -> list[FrameResult | Exception]:
        """The next frame of several streams of this kind with equal :meth:`batch_key`, each
        ``(runner, camera, prev_camera)`` as :meth:`frame` takes them; each in one slice. A
        stream's error is its result (``asyncio.gather(return_exceptions=True)``): the others'
        frames are made, and each equals the frame its runner makes alone (the shared
        contract test checks it). Default: one after the other; a kind that shares launches
        across streams (one render over all cameras, one network call over the batch) overrides it,
        and may leave a frame's input checks to read later (:attr:`FrameResult.checks`: its taker calls
        :meth:`FrameResult.checked`).
        """
        results: list[FrameResult | Exception] = []
        for runner, camera, prev_camera in frames:
            try:
                results.append(runner.frame(camera, prev_camera))
            except Exception as e:  # noqa: BLE001 - the stream's own failure, returned as its result
                results.append(e)
        return results

    @staticmethod
    def render_together(frames: list[tuple[FrameRunner, Camera, Camera | None]]
                        ) -> list[tuple[FrameBuffers, StageTimer] | Exception]:
        """The ray cast of each frame, ``(runner, camera, prev_camera)`` as :meth:`make_batch` takes them, as its
        :meth:`steps` makes it in one slice (its request, its previous camera kept): those that one launch renders
        (one renderer, alike in :meth:`RenderRequest.launch_key`) in one (:meth:`Renderer.render_views`), each
        with the launch's timer (its ``render`` stage the frame's share). A launch of several views that fails is
        made again view by view: a frame's failure stays its own.
        """
        results: list[tuple[FrameBuffers, StageTimer] | Exception | None] = [None] * len(frames)
        # per launch (renderer, launch key): a runner of it, its frames' indices and their views
        launches: dict[tuple, tuple[FrameRunner, list[int], list[tuple[Camera, RenderRequest]]]] = {}
        for k, (runner, camera, prev_camera) in enumerate(frames):
            try:
                request = runner.render_request(prev_camera)
            except Exception as e:  # noqa: BLE001 - the stream's own failure, returned as its result
                results[k] = e
                continue
            runner.prev_camera = prev_camera
            _, indices, views = launches.setdefault((id(runner.renderer), request.launch_key()), (runner, [], []))
            indices.append(k)
            views.append((camera, request))
        for runner, indices, views in launches.values():
            timer = StageTimer(runner.device, share=len(views))
            try:
                with torch.no_grad(), timer("render"):
                    rendered = runner.renderer.render_views(views)
            except Exception as e:  # noqa: BLE001 - the launch failed: alone, its frame's error; else each alone
                for k in indices:
                    results[k] = e if len(indices) == 1 else FrameRunner.render_together([frames[k]])[0]
                continue
            for k, frame in zip(indices, rendered):
                results[k] = frame, timer
        return results

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
        self.prev_camera = prev_camera
        if self.one_slice(slice_ms):
            rendered, buffers = self.render_finish(camera, request, timer)
        else:
            rendered = yield from self._render_bands(camera, request, slice_ms, timer)
            buffers = self.finish_layers(rendered, timer)
        return self._made(rendered, buffers, [timer], prev_camera)

    def _made(self, rendered: FrameBuffers, buffers: FrameBuffers, timers: list[StageTimer],
              prev_camera: Camera | None) -> FrameResult:
        """A frame's result, its kept buffers added (at the frame size); the runner counts it."""
        for name in self.keep:
            if getattr(buffers, name) is None and getattr(rendered, name) is not None:
                setattr(buffers, name, self._to_frame_size(name, getattr(rendered, name)))
        self._last_timer = timers[0]
        self.frames += 1
        return FrameResult(buffers, timers, prev_camera is not None and self.recurrent)

    def render_finish(self, camera: Camera, request: RenderRequest,
                      timer: StageTimer) -> tuple[FrameBuffers, FrameBuffers]:
        """A frame in one slice: ``(rendered, finished)``, the ray cast then :meth:`finish_layers`."""
        with timer("render"):
            rendered = self.renderer.render(camera, request)
        return rendered, self.finish_layers(rendered, timer)

    def finish_layers(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        """:meth:`finish`; with a :attr:`behind` twin, also the twin's on the second layer (``rendered.behind``),
        the frame's ``color`` then both composited front to back by the front surface's opacity as the renderer
        composites them (:func:`~isosr_render.shading.composite`), its ``behind`` the twin's buffers."""
        front = self.finish(rendered, timer)
        if self.behind is None:
            return front
        self.behind.prev_camera = self.prev_camera
        front.behind = self.behind.finish(rendered.behind, timer)
        with timer("shading"):
            front.color = composite(front.color, front.behind.color, self.opacity(rendered))
        return front

    def opacity(self, rendered: FrameBuffers) -> torch.Tensor:
        """The opacity of each pixel's surface in a layer ``rendered`` with its ``surface`` (1 where none), at the
        frame size.

        Shape:
            Returns (H, W).
        """
        return self._to_frame_size("opacity", surface_opacity(self.surfaces, rendered.surface))

    def coverage(self, mask: torch.Tensor, rendered: FrameBuffers) -> torch.Tensor:
        """The ``mask`` (at the frame size) the colour is shaded with: the second layer's covers the background by
        its surface's opacity too (what lies behind it is not seen, as the renderer's); the first's as it is."""
        return mask * self.opacity(rendered) if self.layer else mask

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

    @property
    def shades_after(self) -> bool:
        """Whether the color needs the render's ``cap`` or ``albedo`` (cut faces, a coloring, several surfaces): a
        learned kind shades after its network then (:meth:`colored`), not in its call."""
        return self.shade and (self.clip.capped or self.coloring is not None or self.surfaces is not None)

    def colored(self, buffers: FrameBuffers, timer: StageTimer, rendered: FrameBuffers) -> FrameBuffers:
        """``buffers`` with the final color (unless the runner does not shade), with the ``rendered``
        frame's (at the render's size) ``cap``, the cut faces coloured by the volume's values, and
        ``albedo``, a coloring's or the surfaces' colour, brought to the frame size."""
        if self.shade:
            for name in ("cap", "albedo"):
                if getattr(rendered, name) is not None:
                    setattr(buffers, name, self._to_frame_size(name, getattr(rendered, name)))
            with timer("shading"):
                buffers.color = shade_on(buffers.mask.device.type)(self.coverage(buffers.mask, rendered),
                                                                  buffers.normal, buffers.ao, self.shading, buffers.cap,
                                                                  buffers.albedo)
        return buffers

    def _to_frame_size(self, name: str, t: torch.Tensor) -> torch.Tensor:
        """A rendered buffer at the frame size: nearest upsampling of low-res ones (flow in frame pixels)."""
        f = self.method.factor
        if f == 1 or not self.shaded:
            return t
        up = torch.repeat_interleave(torch.repeat_interleave(t, f, 0), f, 1)
        return up * f if name == "flow" else up


def parse_method(text: str) -> FrameMethod:
    """A method from ``NAME[:key=value,...]`` (``reconstruct:ao_rays=2,precision=bf16``): a
    registered kind and its knobs, typed as its options' fields.

    Raises:
        ValueError: an unknown kind or knob, a count that is not an integer, or knobs the kind
            does not take or outside its bounds (naming them).
    """
    kind, _, rest = text.partition(":")
    types = get_type_hints(registered_runner(kind).options_type)
    knobs = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"{text!r}: {item!r} is not KEY=VALUE with KEY one of {', '.join(types)}")
        try:
            knobs[key] = int(value) if types.get(key) is int else value
        except ValueError:
            raise ValueError(f"{text!r}: {key} must be an integer, got {value!r}") from None
    return FrameMethod.of(kind, **knobs)


def make_runner(method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                **options) -> FrameRunner:
    """The registered runner of ``method`` (arguments and options: :class:`FrameRunner`)."""
    return method.runner(method, renderer, iso, width, height, **options)


def run_sequence(runner: FrameRunner, cameras: list[Camera]) -> list[FrameBuffers]:
    """A new sequence along ``cameras``: each frame's buffers (copies: the runner may reuse its memory)."""
    return [runner.frame(camera, prev).buffers.clone() for camera, prev in sequence_cameras(cameras)]


@dataclass
class FrameStream:
    """One viewer's frames whatever it asks for next: the runner of the current method, iso, size
    and AO radius, made anew when any of them changes. The one place the recurrent reset is
    decided for a stream: a new runner starts without state (so a change of settings or size is a
    cut), and so does a frame without a previous camera. The key holds the renderer: another
    volume, or another time step of a series (each step is a renderer of its own), is a cut too,
    the simplest rule under which no history crosses from one step into the next.

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
              shade: bool = True, clip: Clip = Clip(), coloring: ColorField | None = None,
              surfaces: Surfaces | None = None) -> FrameResult:
        """The next frame; ``prev_camera`` counts only while the runner stays the same."""
        return finish_steps(self.steps(method, renderer, iso, width, height, camera, prev_camera, ao_radius, keep,
                                       shade, clip=clip, coloring=coloring, surfaces=surfaces))

    def steps(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int, camera: Camera,
              prev_camera: Camera | None, ao_radius: float = AO_RADIUS, keep: tuple[str, ...] = (),
              shade: bool = True, slice_ms: float | None = None,
              clip: Clip = Clip(), coloring: ColorField | None = None,
              surfaces: Surfaces | None = None) -> Generator[None, None, FrameResult]:
        """:meth:`frame` in slices (:meth:`FrameRunner.steps`)."""
        runner, prev_camera = self.runner_for(method, renderer, iso, width, height, prev_camera, ao_radius, keep, shade,
                                              clip, coloring, surfaces)
        return (yield from runner.steps(camera, prev_camera, slice_ms))

    def runner_for(self, method: FrameMethod, renderer: Renderer, iso: float, width: int, height: int,
                   prev_camera: Camera | None, ao_radius: float = AO_RADIUS, keep: tuple[str, ...] = (),
                   shade: bool = True, clip: Clip = Clip(),
                   coloring: ColorField | None = None,
                   surfaces: Surfaces | None = None) -> tuple[FrameRunner, Camera | None]:
        """The runner of the next frame and the previous camera it continues from (None where the
        runner is new: a cut; a new ``clip``, ``coloring`` or ``surfaces`` is one, as a new iso). Its frame is
        then :meth:`FrameRunner.steps` or part of a :meth:`FrameRunner.make_batch`."""
        key = (method, renderer, float(iso), width, height, float(ao_radius), tuple(keep), shade, clip, coloring,
               surfaces)
        if key != self._key:
            self.runner = make_runner(method, renderer, iso, width, height, shading=self.shading,
                                      ao_radius=ao_radius, networks=self.networks, keep=keep, shade=shade, clip=clip,
                                      coloring=coloring, surfaces=surfaces)
            self._key, prev_camera = key, None
        return self.runner, prev_camera
