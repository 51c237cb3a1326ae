"""Inference: the `Reconstructor`, a trained ReconNet with one stream's recurrent state.

    reconstructor = Reconstructor()                    # the shipped reconstruction model, CPU, fp32
    for frame in frames:                               # full-res FrameBuffers: mask, normal, depth,
        out = reconstructor.reconstruct(frame, 2, 1)   #   ao (2 rays), flow; rendered with spp 1
    reconstructor.reset()                              # on a camera cut

``out`` holds mask (an antialiased alpha), normal, depth and converged-looking AO. Frames that
carry a ``position`` buffer (and AO rays) have their rays accumulated along the flow first
(:mod:`isosr_net.ray_history`): each frame should cast new ones (another seed). Every stream
needs its own `Reconstructor` (:meth:`~isosr_net.inference.RecurrentNetwork.own`): the previous
output and the ray history are its state.
"""

from __future__ import annotations

import copy
import functools
import math
import os
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import torch

from isosr_render.buffers import FrameBuffers, stacked
from isosr_render.conventions import AO, MASK, NORMAL
from isosr_render.shading import ShadingParams, shade
from isosr_net.fused_recon import FusedReconNet, fusable, fused_reconnet, fused_runs_on, triton_imports
from isosr_net.reconnet import OUTPUTS, RayLimits, ReconNet, ReconNetConfig
from isosr_net.inference import (AO_MESSAGE, PRECISIONS, InputChecks, LateChecks, RecurrentNetwork, ao_in_range,
                                 buffer_stack, check_buffer, check_surface, frames_flags, own_streams, stack_buffers,
                                 surface_tensors)
from isosr_net.model import read_config
from isosr_net.ray_history import RayHistory, histories_join, joined_histories, network_inputs

if TYPE_CHECKING:  # types only: render_reconstruct takes what a renderer made
    from isosr_render.camera import Camera
    from isosr_render.renderer import Renderer, RenderPlan, RenderRequest

DEFAULT_RECON_MODEL = Path(__file__).resolve().parent / "recon_model"
RECON_X2_MODEL = DEFAULT_RECON_MODEL.parent / "recon_x2_model"  # the shipped model that also upscales x2
# Captured CUDA graphs kept per Reconstructor (frame sizes x samplings x first frame or not), at
# most this many and of frames of this many output pixels in all: a graph keeps its frame's
# buffers (1-2 GB at 4K; 18 samplings x 2 sizes of three models took an H100's 80 GB). Four 4K
# graphs, sixteen 1080p ones.
MAX_GRAPHS = 32
MAX_GRAPH_PIXELS = 4 * 3840 * 2160
# The batched network calls' graphs (``batch_graphs``), shared by a network's streams: one per chunk of a
# batch (:func:`graph_chunks`: powers of two up to MAX_GRAPH_BATCH, and up to half of MAX_BATCH_GRAPH_PIXELS,
# so that all of a frame size's chunks stay: 16 at 1080p, 4 at 4K, 1 at 8K), frame size, sampling and
# shading, of output pixels in all at most MAX_BATCH_GRAPH_PIXELS (a graph's own inputs and outputs take ~92
# bytes a pixel, fp32, and the largest chunk's activations stay in the pool: the chunks 1-16 of 1080p frames,
# ~8 GB).
MAX_GRAPH_BATCH = 16
MAX_BATCH_GRAPH_PIXELS = 32 * 1920 * 1080
T = TypeVar("T")


def graph_chunks(batch: int, largest: int = MAX_GRAPH_BATCH) -> list[int]:
    """The sizes in which a batch of ``batch`` frames replays captured graphs: as many of ``largest`` (a
    power of two) as fit, then the rest's binary digits, largest first (41 -> [16, 16, 8, 1]): a graph
    per power of two, no frame padded."""
    if batch < 1 or largest < 1 or largest & (largest - 1):
        raise ValueError(f"graph_chunks: a batch >= 1 and a largest chunk that is a power of two, got {batch}, "
                         f"{largest}")
    full, rest = divmod(batch, largest)
    return [largest] * full + [1 << b for b in reversed(range(rest.bit_length())) if rest >> b & 1]


def recon_limits(model: str | os.PathLike = DEFAULT_RECON_MODEL) -> RayLimits:
    """The ray limits of a reconstruction model folder (:func:`recon_config`): the views check
    each frame's method against them."""
    return recon_config(model).limits


def recon_config(model: str | os.PathLike = DEFAULT_RECON_MODEL) -> ReconNetConfig:
    """The config of a reconstruction model folder, read from its ``config.json`` (not its
    weights) once per version of that file.

    Raises:
        FileNotFoundError, ValueError: not a readable model folder (:func:`~isosr_net.model.read_config`),
            or not a ReconNet's.
    """
    try:
        version = os.stat(Path(model) / "config.json").st_mtime_ns
    except OSError:
        version = None  # read_config says what is wrong
    return _read_config(str(model), version)


@functools.lru_cache(maxsize=16)
def _read_config(model: str, version: int | None) -> ReconNetConfig:
    config = read_config(model)["model"]
    if config.get("type") != "ReconNet":
        raise ValueError(f"{model}: a {config.get('type')} model, not a reconstruction network (ReconNet)")
    try:
        return ReconNetConfig(**config)
    except TypeError as e:
        raise ValueError(f"{model}: bad model config: {e}") from None


def recon_inputs(frame: FrameBuffers, ao_rays: int, spp: int, limits: RayLimits, checks: InputChecks | None = None,
                 history: RayHistory | None = None) -> tuple[torch.Tensor, torch.Tensor | None, RayHistory | None]:
    """A full-resolution frame as ReconNet's inputs: ``(inputs, flow or None, ray history or
    None)``, the inputs in the channel order :data:`isosr_render.conventions.RECON_CHANNELS`,
    the AO and sampling channels as :func:`sampled_rays` makes them (as at inference).

    Args:
        frame: mask, normal, depth, and ``ao`` when ``ao_rays > 0``, rendered with ``spp`` rays
            per pixel and ``ao_rays`` AO rays per hit; ``position`` to accumulate the rays.
        ao_rays: AO rays per hit, 0 to ``limits.max_ao_rays`` (0: no AO input).
        spp: rays per pixel, 1 to ``limits.max_spp``.
        limits: the model's :class:`~isosr_net.reconnet.RayLimits` (the sampling channels' scale).
        checks: where to queue the checks of the buffers' values; None checks at once (a host sync).
        history: the ray history of the sequence's previous frames (None: a first frame).

    Raises:
        ValueError: counts out of range, a buffer missing or misshapen, and (without ``checks``)
            a buffer not finite or AO outside [0, 1].

    Shape:
        Returns inputs (1, 8, H, W) and flow (1, 2, H, W), float32.
    """
    now = checks is None
    checks = InputChecks() if now else checks
    _check_frame(frame, ao_rays, spp, limits)
    surface, flow = surface_tensors(frame, checks)
    if ao_rays:
        checks.add(ao_in_range(frame.ao.float()), bool, AO_MESSAGE)
    if now:
        checks.raise_first()
    _, _, h, w = surface.shape
    ao, sampling, history = sampled_rays(frame, ao_rays, spp, limits, history,
                                         limits.channels(ao_rays, spp, surface[:, :1, :1, :1]))
    ao = surface.new_zeros(1, 1, h, w) if ao is None else ao.float()[None, None]
    return torch.cat([surface, ao, sampling.expand(1, 2, h, w)], dim=1), flow, history


def sampled_rays(frame: FrameBuffers, ao_rays: int, spp: int, limits: RayLimits, history: RayHistory | None,
                 constant: torch.Tensor, out: RayHistory | None = None
                 ) -> tuple[torch.Tensor | None, torch.Tensor, RayHistory | None]:
    """The AO and sampling channels a network of ``limits`` reads of a frame: ``(ao, sampling,
    new history)``, with no host sync. A frame with AO rays and ``position`` has them
    accumulated with ``history`` (None: anew) into ``out`` (None: new tensors), and its
    sampling's AO plane counts, per pixel, the rays behind the mean; else the frame's own AO
    (None without rays), the ``constant`` sampling, and no history.

    Shape:
        constant: (1, 2, 1, 1), :meth:`RayLimits.channels` of the sampling. Returns ao (H, W);
        sampling (1, 2, H, W), or ``constant``.
    """
    if not accumulates(ao_rays, frame.position is not None):
        return frame.ao if ao_rays else None, constant, None
    ao, sampling, history = network_inputs([frame], history, ao_rays, spp, limits, out)
    return ao[0], sampling, history


def accumulates(ao_rays: int, positions: bool) -> bool:
    """Whether a frame's AO rays join the ray history: it has some, and their hit points."""
    return bool(ao_rays) and positions


def _check_frame(frame: FrameBuffers, ao_rays: int, spp: int, limits: RayLimits) -> None:
    """The host's checks of a frame (counts within ``limits``, buffers present, shapes, dtypes);
    its values are the frame work's to check (:data:`~isosr_net.inference.FRAME_FLAGS`)."""
    limits.check(ao_rays, spp, "reconstruction")
    dims = check_surface(frame)
    if ao_rays:
        if frame.ao is None:
            raise ValueError(f"reconstruction from {ao_rays} AO rays needs the frame's ao buffer")
        check_buffer(frame.ao, "(H, W)", "ao", "recon_inputs", dims)


def _check_ray_factor(ray_factor: float) -> None:
    """A ray factor (the rays behind a frame's AO mean per ray its sampling counts) is a finite number >= 1."""
    if isinstance(ray_factor, bool) or not isinstance(ray_factor, (int, float)) or not 1 <= ray_factor < math.inf:
        raise ValueError(f"ray_factor must be a finite number >= 1 (the rays behind the AO mean per ray the model "
                         f"reads), got {ray_factor!r}")


def recon_frame(net: ReconNet, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                sampling: torch.Tensor, flow: torch.Tensor | None, previous: torch.Tensor | None,
                shading: ShadingParams | None, ray_factor: float = 1.0, precision: torch.dtype = torch.float32
                ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One frame's work after the render, with no host sync: inputs laid out and checked, the
    previous output warped (or the first frame's stand-in), the network, the output as buffers,
    shading. :meth:`~isosr_net.fused_recon.FusedReconNet.frame` does the same in fused kernels.

    Args:
        mask, normal, depth, ao: the frame's buffers (``ao`` None: no AO rays).
        sampling: the sampling channels' two values, or planes.
        flow: the frame's flow or None; warps ``previous`` where that is given, else checked only.
        previous: the previous frame's buffers' stack, or None on a sequence's first frame.
        shading: material and light for ``color``; None makes none.
        ray_factor: the rays behind ``ao``'s mean per ray ``sampling`` counts (:meth:`ReconNet.forward`).
        precision: the network's autocast dtype.

    Returns:
        ``(stack, color or None, flags)``: the output buffers' stack (:func:`buffer_stack`; the
        next frame's previous), the shaded color, the input checks' :data:`FRAME_FLAGS`.

    Shape:
        mask, depth, ao: (H, W). normal: (H, W, 3). sampling: (1, 2, 1, 1) or (1, 2, H, W). flow: (H, W, 2).
        previous: (1, 6, H, W). Returns stack (1, 6, H, W), color (H, W, 3), flags (6,).
    """
    one = (None if t is None else t[None] for t in (mask, normal, depth, ao, flow))
    stack, color, flags = recon_frames(net, *one, sampling=sampling, previous=previous, shading=shading,
                                       ray_factor=ray_factor, precision=precision)
    return stack, None if color is None else color[0], flags[0]


def recon_frames(net: ReconNet, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                 ao: torch.Tensor | None, flow: torch.Tensor | None, *, sampling: torch.Tensor,
                 previous: torch.Tensor | None, shading: ShadingParams | None, ray_factor: float = 1.0,
                 precision: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """:func:`recon_frame` of a batch of frames of several streams in one call (each its own
    ``previous`` and ``flow``; all with or all without them).

    Shape:
        mask, depth, ao: (B, H, W). normal: (B, H, W, 3). flow: (B, H, W, 2). sampling: (1 or B, 2, 1 or
        H, 1 or W). previous: (B, 6, H, W). Returns stack (B, 6, H, W), color (B, H, W, 3), flags (B, 6).
    """
    b, h, w = mask.shape
    surface = torch.cat([mask[:, None], normal.permute(0, 3, 1, 2), depth[:, None]], dim=1).float()
    sampled = surface.new_zeros(b, 1, h, w) if ao is None else ao[:, None].float()
    inputs = torch.cat([surface, sampled, sampling.expand(b, 2, h, w)], dim=1)
    carried = None if previous is None else flow.permute(0, 3, 1, 2).float()
    with torch.autocast(surface.device.type, dtype=precision, enabled=precision != torch.float32):
        output = net.step(inputs, carried, previous, ray_factor)[0]
    stack = buffer_stack(output)
    color = None if shading is None else shade(stack[:, MASK.start], stack[:, NORMAL].permute(0, 2, 3, 1),
                                               stack[:, AO.start], shading)
    return stack, color, frames_flags(mask, normal, depth, ao, flow)


class GraphCache(OrderedDict):
    """Captured graphs by key, the least recently used dropped past ``max_graphs`` entries or
    ``max_pixels`` output pixels in all (the newest is always kept). With ``capture_at`` 2, a key is
    captured at its second use (:meth:`due`): values that change every frame (a material's slider
    dragged) run without capturing a graph each."""

    def __init__(self, max_graphs: int = MAX_GRAPHS, max_pixels: int = MAX_GRAPH_PIXELS, capture_at: int = 1):
        super().__init__()
        self.max_graphs, self.max_pixels, self.capture_at = max_graphs, max_pixels, capture_at
        self._pixels: dict[tuple, int] = {}
        self._uses: OrderedDict[tuple, int] = OrderedDict()  # of keys not captured, the most recent max_graphs

    def due(self, key: tuple) -> bool:
        """Count a use of ``key``, not captured: whether to capture it now."""
        self._uses[key] = self._uses.pop(key, 0) + 1
        while len(self._uses) > self.max_graphs:
            self._uses.popitem(last=False)
        return self._uses[key] >= self.capture_at

    def use(self, key: tuple):
        """The entry of ``key``, marked most recently used; None if there is none."""
        if key not in self:
            return None
        self.move_to_end(key)
        return self[key]

    def add(self, key: tuple, entry, pixels: int) -> None:
        """Keep ``entry`` (a graph of frames of ``pixels`` output pixels), dropping the oldest past the bounds."""
        self[key], self._pixels[key] = entry, pixels
        self._uses.pop(key, None)
        self.move_to_end(key)
        while len(self) > 1 and (len(self) > self.max_graphs or sum(self._pixels.values()) > self.max_pixels):
            oldest, _ = self.popitem(last=False)
            del self._pixels[oldest]


@dataclass
class FrameGraph:
    """One captured frame (render, reconstruction, shading): its graph, the render plan whose
    staged values it reads, its input checks' flags, the state tensors it reads and writes (the
    output stack, the pair of ray histories or None), held while it lives, and what a frame
    returns as views of them: the rendered buffers and the reconstruction (color the graph's own)."""

    graph: torch.cuda.CUDAGraph
    plan: RenderPlan
    flags: torch.Tensor
    state: torch.Tensor
    histories: tuple[RayHistory, RayHistory] | None
    rendered: FrameBuffers
    reconstructed: FrameBuffers


class Reconstructor(RecurrentNetwork):
    """A trained reconstruction network and one stream's recurrent state.

    Args:
        model: a ReconNet model folder; default the shipped one.
        device, precision, channels_last, autotune, fast_layers: as for
            :class:`~isosr_net.inference.RecurrentNetwork`.
        compile: a ``torch.compile`` mode for the whole frame's work after the render
            (:func:`recon_frame`: inputs, checks, warp, network, output, shading fused where inductor can);
            None runs it eagerly.
        graphs: on CUDA, replay that work as one CUDA graph per frame size and sampling, captured
            on first use (no launch or Python overhead per frame; with ``compile``, its
            mode must not be ``"reduce-overhead"``, which brings graphs of its own);
            :meth:`render_reconstruct` replays the render with it, in one graph.
        fused: the frame's work after the render as the network's fused Triton kernels alone
            (:meth:`isosr_net.fused_recon.FusedReconNet.frame`: the inputs' layout and checks, the
            previous output's warp, the output buffers and shading among them): fp16, on CUDA
            with Triton, without ``fast_layers`` (whose layers it replaces) or ``compile``.
        batch_graphs: on CUDA, replay :meth:`reconstruct_batch`'s network calls from CUDA graphs that the
            network's streams share (:func:`graph_chunks`): one host call a chunk of frames instead of a
            launch a pass, and a graph's memory per batch size, not per stream.
    """

    display_name = "recon"  # in a method's name: "full, AO 2, spp 1, recon fp16"

    def __init__(self, model: str | Path = DEFAULT_RECON_MODEL, device: str = "cpu", precision: str = "fp32",
                 channels_last: bool = False, compile: str | None = None, autotune: bool = False,
                 graphs: bool = False, fast_layers: bool = False, fused: bool = False, batch_graphs: bool = False):
        if fused and (precision != "fp16" or fast_layers or compile or not fused_runs_on(device)):
            raise ValueError(f"fused: the fused kernels need precision fp16 on a CUDA device with Triton, without "
                             f"fast_layers or compile; got {precision} on {device}, fast_layers={fast_layers}, "
                             f"compile={compile}, Triton {'imports' if triton_imports() else 'missing'}")
        super().__init__(model, device, precision, channels_last=channels_last, fast_layers=fast_layers,
                         autotune=autotune)
        if not isinstance(self.net, ReconNet):
            raise ValueError(f"{model}: a {type(self.net).__name__}, not a reconstruction network (ReconNet)")
        self.upscale_factor = self.net.config.upscale
        if (graphs or batch_graphs) and (self.device.type != "cuda" or compile == "reduce-overhead"):
            raise ValueError("graphs, batch_graphs: CUDA graphs need a CUDA device and a compile mode other than "
                             "reduce-overhead")
        if fused:
            self.net = fused_reconnet(self.net)
            self._frame, self._frames = self.net.frame, self.net.frames
        else:
            frame_fn = functools.partial(recon_frame, self.net, precision=PRECISIONS[precision])
            self._frame = torch.compile(frame_fn, mode=compile, dynamic=False) if compile else frame_fn
            self._frames = functools.partial(recon_frames, self.net, precision=PRECISIONS[precision])
        self.graphs, self.batch_graphs = graphs, batch_graphs
        # The batch graphs: the streams' twins share these (own() keeps them).
        self._batch_captured = GraphCache(MAX_GRAPHS, MAX_BATCH_GRAPH_PIXELS, capture_at=2)
        self._batch_pool = torch.cuda.graph_pool_handle() if batch_graphs else None
        self._sampling: dict[tuple[int, int], torch.Tensor] = {}
        self.history: RayHistory | None = None
        self._deferred: list[tuple] | None = None  # checks queued by defer_checks, or None: read at once
        self._late: list[LateChecks] = []  # frames' checks read late, not yet read here (settle_checks_later)
        self._own_graphs()

    def reset(self) -> None:
        """Forget the previous output and the ray history (a camera cut, a new sequence)."""
        super().reset()
        self.history, self._late = None, []

    def state_bytes(self) -> int:
        """Bytes the stream's state holds: the previous output and the ray history."""
        return super().state_bytes() + (0 if self.history is None else self.history.nbytes)

    def _own_graphs(self) -> None:
        """Empty caches of graphs (network and whole-frame), of the previous outputs they read, and
        a memory pool for them: a stream's own, so that streams neither share a graph's tensors
        nor replay into each other's pool."""
        self._captured = GraphCache()
        self._frame_graphs = GraphCache()
        # Per frame size, while a cached graph or the stream holds them (_drop_unheld_states).
        self._states: dict[tuple[int, int], torch.Tensor] = {}
        self._history_states: dict[tuple[int, int], tuple[RayHistory, RayHistory]] = {}
        self._pool = torch.cuda.graph_pool_handle() if self.graphs else None

    def drop_graphs(self) -> None:
        """As :meth:`RecurrentNetwork.drop_graphs`: the whole-frame and network graphs, their state tensors and
        pool (at 4K each graph holds gigabytes; the batch graphs, which the streams share, stay)."""
        self._own_graphs()

    def own(self) -> "Reconstructor":
        """As :meth:`RecurrentNetwork.own`; whole-frame graphs hold a stream's state, so the twin
        captures its own."""
        twin = super().own()
        twin._own_graphs()
        twin._deferred, twin._late = None, []  # its own checks, read at once until it defers them
        return twin

    def warm(self, sizes: Iterable[tuple[int, int]], ao_rays: int = 1, shading: ShadingParams | None = ShadingParams()
             ) -> None:
        """Make two frames (a first one, then one carrying it) of each ``(height, width)`` from empty
        buffers, then forget them: on CUDA the fused kernels compile and tune for those sizes'
        classes (:mod:`isosr_net.fused_kernels`) before a viewer's first frame waits for them."""
        for h, w in sizes:
            empty = torch.zeros(h, w, device=self.device)
            frame = FrameBuffers(mask=empty, normal=torch.zeros(h, w, 3, device=self.device), depth=empty,
                                 ao=empty if ao_rays else None, flow=torch.zeros(h, w, 2, device=self.device),
                                 position=torch.zeros(h, w, 3, device=self.device))
            for _ in range(2):
                self.reconstruct(frame, ao_rays, 1, shading)
        self.reset()

    @classmethod
    def fastest(cls, model: str | Path = DEFAULT_RECON_MODEL, device: str = "cuda",
                precision: str | None = None) -> "Reconstructor":
        """The variant for interactive use on ``device``: on CUDA, fp16 (``precision`` overrides),
        NHWC, the network as fused Triton kernels (``fused``, where Triton imports and in fp16;
        else its channel-padded layers compiled) and, through :meth:`render_reconstruct`, render,
        network and shading replayed as one CUDA graph; eager fp32 NHWC elsewhere. On an H100
        (``python -m isosr_bench.bench_recon_path``, ct_pitch, 1 AO ray, commit 4e442cc) the fused
        graph makes a 1080p frame in 2.62 ms and a 4K frame in 7.93 ms through the runner (at
        5fb514d the compiled one took 4.14 and 12.7 ms)."""
        if torch.device(device).type == "cuda":
            precision = precision or "fp16"
            if cls.fuses(model, device, precision):
                return cls(model, device, precision, channels_last=True, fused=True, graphs=True)
            return cls(model, device, precision, channels_last=True, compile="default", autotune=True,
                       fast_layers=True, graphs=True)
        return cls(model, device, precision or "fp32", channels_last=True)

    @classmethod
    def served(cls, model: str | Path, device: str, precision: str) -> "Reconstructor":
        """The variant a service runs on ``device`` (one per stream, :meth:`own`): NHWC on GPUs, the
        fused kernels where they apply (:meth:`fuses`), their batches' calls replayed from graphs the streams
        share (``batch_graphs``), else the fast layers; nothing compiled; no graphs per stream (their memory
        is per stream)."""
        cuda = torch.device(device).type == "cuda"
        if cls.fuses(model, device, precision):
            return cls(model, device, precision, channels_last=True, fused=True, batch_graphs=True)
        return cls(model, device, precision, channels_last=cuda, fast_layers=cuda)

    @staticmethod
    def fuses(model: str | Path, device: str, precision: str) -> bool:
        """Whether the fused kernels run ``model`` on ``device`` in ``precision``: fp16 on CUDA with
        Triton, and a model the kernels take (:func:`~isosr_net.fused_recon.fusable`)."""
        return (precision == "fp16" and torch.device(device).type == "cuda" and fused_runs_on(device)
                and fusable(recon_config(model)))

    @property
    def limits(self) -> RayLimits:
        """The most AO rays per hit and rays per pixel the model takes."""
        return self.net.config.limits

    def reconstruct(self, frame: FrameBuffers, ao_rays: int, spp: int = 1,
                    shading: ShadingParams | None = None, ray_factor: float = 1.0) -> FrameBuffers:
        """Reconstruct one frame; with ``shading``, shade it too (``color``).

        Args:
            frame: as for :func:`recon_inputs`; ``flow`` except after a cut; ``position`` to
                accumulate the AO rays along the flow (:mod:`isosr_net.ray_history`).
            ao_rays, spp: how the frame was sampled.
            shading: material and light for ``color``; None makes no color.
            ray_factor: the rays behind the frame's AO mean per ray ``ao_rays`` and ``spp`` count, >= 1
                (a frame of more AO rays than the model reads, :meth:`RayLimits.read`): a "blend" model
                weighs the mean by them.

        Raises:
            ValueError: as :func:`recon_inputs`, a ray_factor under 1, or fp16 and depths beyond
                :data:`isosr_net.inference.FP16_MAX_DEPTH`; the state is then left as it was.

        Shape:
            Returns mask, depth, ao (H, W); normal, color (H, W, 3).
        """
        _check_frame(frame, ao_rays, spp, self.limits)
        _check_ray_factor(ray_factor)
        self._settle_late()
        frame = frame.to(self.device)
        carry = self.carries(*frame.mask.shape, frame.flow is not None)
        with torch.no_grad():
            ao, sampling, history = self._rays(frame, ao_rays, spp, self.history if carry else None)
            args = (frame.mask, frame.normal, frame.depth, ao, sampling, frame.flow, self.previous if carry else None,
                    shading, ray_factor)
            stack, color, flags = self._replay(self._frame, args, self._captured, self._pool) if self.graphs \
                else self._frame(*args)
        if self.graphs:  # the graph's own tensors: the next replay overwrites them
            stack, color = stack.clone(), None if color is None else color.clone()
        self._checked(flags, lambda: self._keep(stack, history), output=stack)
        return stack_buffers(stack, color)

    @staticmethod
    def reconstruct_batch(nets: list[Reconstructor], frames: list[FrameBuffers], ao_rays: int, spp: int = 1,
                          shading: ShadingParams | None = None, ray_factor: float = 1.0
                          ) -> list[FrameBuffers | Exception]:
        """:meth:`reconstruct` of one frame of each of several streams (``nets[k]`` the stream of
        ``frames[k]``: twins of one network, :meth:`~isosr_net.inference.RecurrentNetwork.own`, none
        graphed) in one network call for those that carry their previous output and one for those
        that do not: each pass one launch for all. Each result equals the frame its stream makes
        alone (within the kernels' rounding at another batch size); a frame that fails its checks is
        that stream's error (its state kept as it was); the checks are read as :meth:`reconstruct`
        reads them (deferred: at :meth:`settle_checks`).

        Shape:
            As :meth:`reconstruct`, each frame of the same size.
        """
        template, results = nets[0], [None] * len(frames)
        if any(net.graphs or net._frame is not template._frame for net in nets):
            raise ValueError("reconstruct_batch: the streams must be ungraphed twins of one network")
        _check_ray_factor(ray_factor)
        settling = [net for net in nets if net._deferred is None]  # the others' caller settles them
        for net in settling:
            net.defer_checks()
        groups: dict[tuple[bool, bool], list] = {}
        for k, (net, frame) in enumerate(zip(nets, frames)):
            try:
                _check_frame(frame, ao_rays, spp, net.limits)
            except ValueError as e:
                results[k] = e
                continue
            net._settle_late()
            frame = frame.to(net.device)
            carry = net.carries(*frame.mask.shape, frame.flow is not None)
            groups.setdefault((carry, frame.flow is not None), []).append((k, net, frame, carry))
        with torch.no_grad():
            for group in groups.values():
                for (k, _, _, _), out in zip(group, template._batch_frames(group, ao_rays, spp, shading, ray_factor)):
                    results[k] = out
        for k, net in enumerate(nets):
            if net in settling:
                try:
                    net.settle_checks()
                except ValueError as e:
                    results[k] = e
        return results

    def _batch_frames(self, group: list[tuple], ao_rays: int, spp: int, shading: ShadingParams | None,
                      ray_factor: float) -> list[FrameBuffers]:
        """The frames of ``group`` (``(index, net, frame, carry)``, one ``carry`` for all) in one call."""
        frames = [frame for _, _, frame, _ in group]
        carry = group[0][3]
        ao, sampling, histories = self._batch_rays(group, ao_rays, spp)
        previous = torch.cat([net.previous for _, net, _, _ in group]) if carry else None
        mask, normal, depth, flow = (stacked(frames, n) for n in ("mask", "normal", "depth", "flow"))
        stack, color, flags = self._network_frames(mask, normal, depth, ao, flow, sampling, previous, shading,
                                                   ray_factor)
        # each stream keeps its own output, and its frame is views of that (none holds the batch's memory)
        outputs, each_flags = own_streams(stack), flags.unbind(0)
        colors = [None] * len(group) if color is None else color.unbind(0)
        out = []
        for j, (_, net, _, _) in enumerate(group):
            net._checked(each_flags[j], lambda net=net, j=j: net._keep(outputs[j], histories[j]), output=outputs[j])
            out.append(stack_buffers(outputs[j], colors[j]))
        return out

    def _batch_rays(self, group: list[tuple], ao_rays: int, spp: int
                    ) -> tuple[torch.Tensor | None, torch.Tensor, list[RayHistory | None]]:
        """:meth:`_rays` of the frames of ``group`` (as :meth:`_batch_frames`): ``(ao or None, sampling, each
        stream's new history)``. Their rays accumulate in one launch where their histories join (all or none
        present, of one size: :func:`histories_join`), else stream by stream.

        Shape:
            Returns ao (B, H, W); sampling (B, 2, H, W), or the constant (1, 2, 1, 1).
        """
        frames = [frame for _, _, frame, _ in group]
        histories = [net.history if carry else None for _, net, _, carry in group]
        if accumulates(ao_rays, frames[0].position is not None) and histories_join(histories):
            ao, sampling, history = network_inputs(frames, joined_histories(histories), ao_rays, spp, self.limits)
            return ao, sampling, history.streams()
        rays = [net._rays(frame, ao_rays, spp, history) for (_, net, frame, _), history in zip(group, histories)]
        ao = None if rays[0][0] is None else torch.stack([r[0] for r in rays])
        sampling = torch.cat([r[1] for r in rays]) if rays[0][1].shape[-1] > 1 else rays[0][1]
        return ao, sampling, [r[2] for r in rays]

    def _rays(self, frame: FrameBuffers, ao_rays: int, spp: int, history: RayHistory | None,
              out: RayHistory | None = None) -> tuple[torch.Tensor | None, torch.Tensor, RayHistory | None]:
        """:func:`sampled_rays` of the model, its constant sampling made once per sampling."""
        return sampled_rays(frame, ao_rays, spp, self.limits, history, self._sampling_tensor(ao_rays, spp), out)

    def defer_checks(self) -> None:
        """Until :meth:`settle_checks`, a frame's input checks are queued instead of read (a host sync
        each), and its state is kept only once they pass: the frames of several streams then issue
        their device work back to back, and the host waits for the device once, after the last."""
        self._deferred = []

    def settle_checks(self) -> None:
        """Read the checks queued since :meth:`defer_checks` and keep each frame's state, or raise the
        first that fails (that frame's state not kept, as :meth:`reconstruct` says); checks are read
        at once again after."""
        deferred, self._deferred = self._deferred or [], None
        for checks, keep, refused in deferred:
            self._settle(checks, keep, refused)

    def settle_checks_later(self) -> LateChecks | None:
        """:meth:`settle_checks` without waiting for the device: each frame queued since :meth:`defer_checks`
        keeps its state now and its checks travel to the host behind its work (None: none queued). Where
        they fail (:meth:`LateChecks.error`, that frame's error to whoever reads it), the stream starts over,
        as after a cut, at its first frame made once the device has reached them: a frame asked for sooner
        (a session with frames in flight) does not wait for them."""
        return self.settle_checks_later_each([self])[0]

    @staticmethod
    def settle_checks_later_each(nets: Sequence[Reconstructor]) -> list[LateChecks | None]:
        """:meth:`settle_checks_later` of each of several streams on one device, their checks copied to the
        host together (:meth:`InputChecks.read_later_each`: one copy and one event a batch)."""
        pending: list[tuple[int, InputChecks]] = []
        for k, net in enumerate(nets):
            deferred, net._deferred = net._deferred or [], None
            for _, keep, _ in deferred:
                keep()
            if deferred:
                pending.append((k, InputChecks.joined([checks for checks, _, _ in deferred])))
        late: list[LateChecks | None] = [None] * len(nets)
        for (k, _), checks in zip(pending, InputChecks.read_later_each([c for _, c in pending]) if pending else []):
            nets[k]._late.append(checks)
            late[k] = checks
        return late

    def _settle_late(self) -> None:
        """Before a frame: start the stream over where the checks read late that the device has reached
        failed; those it has not reached yet wait for a later frame (no wait here)."""
        reached = [late.reached() for late in self._late]
        failed = any(late.error() is not None for late, done in zip(self._late, reached) if done)
        self._late = [late for late, done in zip(self._late, reached) if not done]
        if failed:
            self.reset()

    def _checked(self, flags: torch.Tensor, keep: Callable[[], None], refused: Callable[[], None] | None = None,
                 output: torch.Tensor | None = None) -> None:
        """``keep()`` the frame's state once its checks pass (now, or at :meth:`settle_checks`); where
        they fail, ``refused()`` and raise. Its checks: the input ``flags`` and, while earlier frames' checks
        read late are not yet reached (the state may hold what they refuse), ``output`` finite."""
        checks = InputChecks()
        checks.add_flags(flags, self.precision == "fp16")
        if output is not None and self._late:
            checks.add_finite("the output, over a state kept before its frames' checks were read,", output)
        if self._deferred is not None:
            self._deferred.append((checks, keep, refused))
            return
        self._settle(checks, keep, refused)

    def _settle(self, checks: InputChecks, keep: Callable[[], None], refused: Callable[[], None] | None) -> None:
        """Read a frame's checks (one host sync): ``keep()``, or ``refused()`` and raise the first that fails."""
        try:
            checks.raise_first()
        except ValueError:
            if refused is not None:
                refused()
            raise
        keep()

    def _keep(self, previous: torch.Tensor, history: RayHistory | None) -> None:
        self.previous, self.history = previous, history

    def _sampling_tensor(self, ao_rays: int, spp: int) -> torch.Tensor:
        """The sampling channels' two values (1, 2, 1, 1) on the device, made once per sampling."""
        key = (ao_rays, spp)
        if key not in self._sampling:
            self._sampling[key] = self.limits.channels(ao_rays, spp, torch.zeros(1, 1, 1, 1, device=self.device))
        return self._sampling[key]

    def _network_frames(self, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                        flow: torch.Tensor | None, sampling: torch.Tensor, previous: torch.Tensor | None,
                        shading: ShadingParams | None, ray_factor: float
                        ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """The network's call over a batch (:func:`recon_frames`' arguments, results and shapes); with
        ``batch_graphs`` replayed from the shared graphs chunk by chunk (:func:`graph_chunks`), the
        results copied out of the graphs' own."""
        args = (mask, normal, depth, ao, flow, sampling, previous, shading, ray_factor)
        largest = MAX_BATCH_GRAPH_PIXELS // (2 * mask[0].numel() * self.upscale_factor ** 2)
        if not self.batch_graphs or largest < 1:
            return self._batch_call(*args)
        batch, start, results = mask.shape[0], 0, None
        for size in graph_chunks(batch, min(MAX_GRAPH_BATCH, 1 << (largest.bit_length() - 1))):
            part = tuple(a[start:start + size] if torch.is_tensor(a) and a.shape[0] == batch else a for a in args)
            outs = self._replay(self._batch_call, part, self._batch_captured, self._batch_pool)
            if results is None:
                results = tuple(None if o is None else o.new_empty((batch, *o.shape[1:])) for o in outs)
            for result, out in zip(results, outs):
                if result is not None:
                    result[start:start + size].copy_(out)
            start += size
        return results

    def _batch_call(self, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                    flow: torch.Tensor | None, sampling: torch.Tensor, previous: torch.Tensor | None,
                    shading: ShadingParams | None, ray_factor: float
                    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        return self._frames(mask, normal, depth, ao, flow, sampling=sampling, previous=previous, shading=shading,
                            ray_factor=ray_factor)

    def _replay(self, work: Callable[..., tuple], args: tuple, cache: GraphCache, pool: tuple | None
                ) -> tuple[torch.Tensor, ...]:
        """``work(*args)`` replayed from a CUDA graph of ``cache`` (captured into ``pool`` per shapes of the
        tensors among ``args`` and the other values, when :meth:`GraphCache.due`; until then run as it is),
        its inputs copied into the graph's own, its outputs the graph's (valid until its next replay)."""
        key = tuple(None if a is None else tuple(a.shape) if torch.is_tensor(a) else a for a in args)
        entry = cache.use(key)
        if entry is None and not cache.due(key):
            return work(*args)
        if entry is None:
            static = tuple(a.clone() if torch.is_tensor(a) else a for a in args)
            entry = (*self._capture(lambda: work(*static), pool), static)
            cache.add(key, entry, args[0].numel() * self.upscale_factor ** 2)
        graph, outs, static = entry
        for target, source in zip(static, args):
            if torch.is_tensor(source) and target is not source:
                target.copy_(source)
        graph.replay()
        return outs

    def _capture(self, work: Callable[[], T], pool: tuple | None, restore: Callable[[], None] | None = None
                 ) -> tuple[torch.cuda.CUDAGraph, T]:
        """``work`` captured as a CUDA graph into the memory ``pool``, after two warm-up calls on a side
        stream (they compile and autotune; ``restore``, after each, puts back what they wrote of what
        they read), and what the capture returned (the graph's tensors)."""
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(2):
                work()
                if restore is not None:
                    restore()
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        # thread_local: the encoders' CUDA calls on their own threads go on during a capture
        with torch.cuda.graph(graph, pool=pool, stream=torch.cuda.Stream(self.device),
                              capture_error_mode="thread_local"):
            out = work()
        return graph, out

    def graphable(self, renderer: Renderer, request: RenderRequest) -> bool:
        """Whether :meth:`render_reconstruct` makes ``request``'s frames in one CUDA graph: with
        ``graphs``, a dense volume on this device, and no pass after the render kernel (color,
        flow fill, coloring, several surfaces). Sparse volumes page bricks per frame on the host: they render
        ungraphed."""
        here = self.device if self.device.index is not None or self.device.type != "cuda" else \
            torch.device("cuda", torch.cuda.current_device())
        return (self.graphs and renderer.pool is None and renderer.torch_device == here
                and "color" not in request.outputs and request.flow_fill == "none" and request.coloring is None
                and request.surfaces is None)

    def render_reconstruct(self, renderer: Renderer, camera: Camera, request: RenderRequest, ao_rays: int,
                           spp: int = 1, shading: ShadingParams | None = None, ray_factor: float = 1.0
                           ) -> tuple[FrameBuffers, FrameBuffers]:
        """Render ``request`` and reconstruct it: ``(rendered, reconstructed)``.

        Where :meth:`graphable`, the render, the network and the shading replay as one CUDA graph
        per renderer, request size and buffers, iso, sampling, shading and first frame or not
        (captured on first use; a new iso or size captures anew): the frame's values go in by the
        render plan's copy; the graph reads the previous output and ray history from the stream's
        state tensors of the frame size and writes the new ones there (no copy after it: the
        output in place, the history into the other of a pair, in turn). Both
        results are then the plan's, the state's and the graph's tensors: valid until this
        stream's next frame (copy what you keep longer, :meth:`FrameBuffers.clone`). Elsewhere:
        :meth:`Renderer.render` then :meth:`reconstruct`.

        Raises:
            ValueError: as :meth:`reconstruct`; a graphed frame has then overwritten the state, so
                the stream starts anew (as after a cut).
        """
        if not self.graphable(renderer, request):
            rendered = renderer.render(camera, request)
            return rendered, self.reconstruct(rendered, ao_rays, spp, shading, ray_factor)
        _check_ray_factor(ray_factor)
        self._settle_late()
        size = (request.height, request.width)
        carry = self.carries(*size, request.prev_camera is not None)
        state = self._state(size, self.previous if carry else None)
        accumulating = accumulates(ao_rays, "position" in request.outputs)
        continued = carry and accumulating and self.history is not None
        histories = self._history_pair(size) if accumulating else None
        read, written = self._history_turn(histories, self.history if continued else None)
        key = (id(renderer), request.plan_key(), float(request.iso), request.skip, ao_rays, spp, shading, ray_factor,
               carry, continued, written is not None and written is histories[1])
        entry = self._frame_graphs.use(key)
        plan = renderer.plan(request) if entry is None else entry.plan
        plan.stage(camera, request)
        if entry is None:
            graph, (color, flags) = self._capture(lambda: self._graph_work(plan, request, ao_rays, spp, shading,
                                                                           ray_factor, carry, state, read, written),
                                                  self._pool, self._restorer(state))
            entry = FrameGraph(graph, plan, flags, state, histories, plan.buffers(request), stack_buffers(state, color))
            self._frame_graphs.add(key, entry, request.height * request.width * self.upscale_factor ** 2)
            self._drop_unheld_states(state, histories)
        entry.graph.replay()
        self._checked(entry.flags, lambda: self._keep(state, written), refused=self.reset,  # the graph wrote the state
                      output=state)
        # Copies of the views made at capture: what a caller sets on a frame's buffers stays its own.
        return copy.copy(entry.rendered), copy.copy(entry.reconstructed)

    def _state(self, size: tuple[int, int], previous: torch.Tensor | None) -> torch.Tensor:
        """The output stack of frames of input ``size`` that the graphs read (the previous output) and
        write (their own), made once per size, holding ``previous`` where given (copied unless it is
        that tensor already)."""
        state = self._states.get(size)
        if state is None:
            s = self.upscale_factor
            state = self._states[size] = torch.empty((1, OUTPUTS, s * size[0], s * size[1]), device=self.device)
        if previous is not None and previous is not state:
            state.copy_(previous)
        return state

    def _drop_unheld_states(self, *current: torch.Tensor | tuple[RayHistory, RayHistory] | None) -> None:
        """Forget the state tensors of sizes that no cached graph holds (nor ``current``, the frame's):
        a viewer resizing through many sizes keeps only those of the graphs' bounded cache."""
        held = {id(t) for e in self._frame_graphs.values() for t in (e.state, e.histories)} | {id(t) for t in current}
        for states in (self._states, self._history_states):
            for size in [size for size, t in states.items() if id(t) not in held]:
                del states[size]

    @staticmethod
    def _restorer(state: torch.Tensor) -> Callable[[], None]:
        """What puts ``state`` back as it holds now (a graph's warm-up frames write the output they
        read; the ray history they read they do not write)."""
        saved = state.clone()
        return lambda: state.copy_(saved)

    def _history_pair(self, size: tuple[int, int]) -> tuple[RayHistory, RayHistory]:
        """The two ray histories of frames of ``size`` that the graphs read and write in turn (a
        pixel's accumulation reads its neighbours' history: not in place), made once per size."""
        pair = self._history_states.get(size)
        if pair is None:
            pair = self._history_states[size] = (RayHistory.empty(1, *size, self.device),
                                                  RayHistory.empty(1, *size, self.device))
        return pair

    @staticmethod
    def _history_turn(pair: tuple[RayHistory, RayHistory] | None, history: RayHistory | None
                      ) -> tuple[RayHistory | None, RayHistory | None]:
        """``(read, written)`` of a frame: the one of ``pair`` holding ``history`` (copied into the
        first unless it is one of them; None without a history) and the other (None without a pair)."""
        if pair is None:
            return None, None
        if history is None:
            return None, pair[0]
        if history is pair[1]:
            return pair[1], pair[0]
        if history is not pair[0]:
            pair[0].copy_(history)
        return pair[0], pair[1]

    def _graph_work(self, plan: RenderPlan, request: RenderRequest, ao_rays: int, spp: int,
                    shading: ShadingParams | None, ray_factor: float, carry: bool, state: torch.Tensor,
                    read: RayHistory | None, written: RayHistory | None) -> tuple[torch.Tensor | None, torch.Tensor]:
        """A staged frame's render and its reconstruction (as :meth:`reconstruct`'s frame work), with
        no host sync: the previous output read from ``state`` where the frame ``carry``-s it, the
        new one written there; the ray history (where the frame makes one) continued from
        ``read`` (None: anew) into ``written``. Returns ``(color, flags)``."""
        plan.launch()
        rendered = plan.buffers(request)
        _check_frame(rendered, ao_rays, spp, self.limits)
        ao, sampling, _ = self._rays(rendered, ao_rays, spp, read, written)
        args = (rendered.mask, rendered.normal, rendered.depth, ao, sampling, rendered.flow, state if carry else None,
                shading, ray_factor)
        if isinstance(self.net, FusedReconNet):  # its tail writes the state after its pack read it
            _, color, flags = self._frame(*args, out=state)
        else:
            stack, color, flags = self._frame(*args)
            state.copy_(stack)
        return color, flags
