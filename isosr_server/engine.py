"""The engine: the one owner of the device.

All renderer, network and encoder work runs on one worker thread (a 1-thread executor), so
concurrent requests never race on the GPU or on a session's recurrent state, and GPU work
of different sessions is serialized in submission order (the executor's FIFO queue). A view
session asks for its next frame only after the last one is made, so the ready sessions are
served in turn (round robin), never the busiest first. The view frames asked for while the
device thread is busy are made together, as one job (a batch): those of one runner kind, volume
and size through the kind's ``make_batch``; a frame that runs in slices goes alone. The event loop awaits
:meth:`Engine.call`; everything named ``*_sync`` runs only on that thread. On GPUs that thread issues its
work on a CUDA stream of its own (:attr:`Engine.stream`): the encoder threads read a frame's colors once its
event has passed (:class:`ImageCodes`), never waiting for work the device thread issued after it (nvJPEG
synchronizes the legacy default stream before each image, which would make it wait for the next batch); a video
frame's I420 planes are converted and copied to the host on that stream too, so video encoders make no device call. The
device thread does not wait for the device either: a batch's input checks are read there too
(:attr:`~isosr_net.methods.FrameResult.checks`), so it goes on with the next batch while the GPU runs this one.
The render kernels that clip or march several isos are compiled on their first use on threads of their own
(:meth:`Engine.frame_kernels`): the sessions that need them wait, the others' frames keep coming.

Frames are made by isosr_net's frame methods through the view modes (:mod:`isosr_server.views`).
Networks are loaded once (:class:`isosr_net.methods.Networks`, in the server's precision:
fp16 on CUDA by default, fp32 on CPUs; NHWC and the fast layers on GPUs, no ``torch.compile``,
which would stall every session for seconds at each new frame size); every view session and
upscale stream gets its own copy that shares the weights and owns its recurrent state.
Renderers are cached per volume (a few, least recently used dropped).
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import suppress
from collections.abc import Awaitable, Callable, Generator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from isosr_net.methods import RUNNERS, Networks, finish_steps
from isosr_net.inference import RecurrentNetwork, default_precision
from isosr_net.reconnet import RayLimits
from isosr_net.reconstructor import Reconstructor, recon_limits
from isosr_net.timing import StageTimer, timed_steps
from isosr_net.upscaler import Upscaler
from isosr_render import FrameBuffers, Renderer, ShadingParams, Volume, orbit, parse_procedural, shade
from isosr_render.brick_pool import MemoryStats
from isosr_render.images import quantize
from isosr_render.picking import pick
from isosr_render.kernels import VARIANT_MODULES
from isosr_render.renderer import load_frame_kernels
from isosr_server.auto import AutoPolicy, ProbeCache
from isosr_server.core.config import Settings
from isosr_server.codecs.buffers import pack_view_buffers
from isosr_server.codecs.buffers_device import view_buffer_codes
from isosr_server.codecs import video as video_codecs
from isosr_server.encoding import CodedImage, device_jpeg, encode_image, encode_jpegs, encoder_name
from isosr_server.protocol import (IMAGE_ENCODINGS, AutoChoice, FocusMsg, ModeInfo, PickedMsg, PickMsg, ProtocolError,
                                   UpscaleRequest, ViewBuffers, ViewSettings, VolumeMemory)
from isosr_server.video import device_i420
from isosr_server.views import FrameJob, FramePlan, SessionFrames, ViewContext, ViewFrame, mode_infos

log = logging.getLogger("isosr.server")
RENDERER_CACHE = 4
# How frames name the server's networks (in their method's name: "x4 network fp16", "..., recon fp16").
MODEL_NAMES = {cls: cls.display_name for cls in (Upscaler, Reconstructor)}
# Low-res tile side of CPU upscaling: the largest upscale (960x540 to 3840x2160) in 12 tiles, its
# peak memory a sixth of the whole frame's (7.9 GB measured whole), the same result (see Upscaler).
CPU_UPSCALE_TILE = 240
# Window sizes whose classes the reconstruction tunes for at start-up on GPUs (pixels' bit length:
# 0.5-1 and 1-2 megapixels, 720p and 1080p among them); other sizes tune on their first frame.
WARM_RECON_SIZES = ((720, 1280), (1080, 1920))
# Threads that encode video frames, off the device thread: the sessions' encoders side by side (a session
# encodes one frame at a time; each encoder has threads of its own, isosr_server.video.video_threads).
VIDEO_ENCODER_THREADS = max(1, (os.cpu_count() or 1) // 2)
# Threads that encode images and buffers. Up to 4 cores, one: on 2 cores a second one cost a fast session
# beside a slow one 35% of its frames/s instead of 14% (tests/test_client.py), competing with the device
# thread. Beyond, a quarter of the cores (up to 8): with one, a plain server's 1080p JPEG frames stopped at
# 380-460 frames/s for 16-64 sessions on an H200 with the GPU 28-31% busy, one thread's rate at about 2.3 ms
# a frame (benchmarks/results/bench_cluster_*_1080p_cuda.json; more threads not yet measured there). A
# session's frames still go out in order: isosr_server.sessions._send_frame encodes each after the one before.
IMAGE_ENCODER_THREADS = 1 if (os.cpu_count() or 1) <= 4 else min(8, (os.cpu_count() or 1) // 4)
# A unit of the auto mode's background probe waits for a moment without view frames in the making,
# at most this long: frames first, and the probe still ends under a steady load.
PROBE_WAIT_S = 0.5
# A probe unit longer than this is logged (viewers saw their frames wait for it).
SLOW_PROBE_UNIT_S = 0.25


def serving_network(cls: type[RecurrentNetwork], model: Path, device: str, precision: str) -> RecurrentNetwork:
    """A network as the service runs it: the reconstruction as :meth:`Reconstructor.served` (the
    fused kernels where they apply, autotuned once per size class); the upscaler on GPUs NHWC with
    the fast layers, not compiled, on CPUs in tiles (bounded memory)."""
    if cls is Reconstructor:
        return Reconstructor.served(model, device, precision)
    cuda = torch.device(device).type == "cuda"
    net = cls(model, device, precision, channels_last=cuda, fast_layers=cuda)
    if isinstance(net, Upscaler) and not cuda:
        net.tile = CPU_UPSCALE_TILE
    return net


@dataclass(frozen=True)
class EncodedFrame:
    """A view frame ready for the wire: the coded image (or the coded buffers), server milliseconds
    per stage, the channel legend, the method's name, the frame whose camera the flow refers to,
    the volume's device memory after it, the time step it shows, the frames made together
    with it on the device (itself included), and what ``auto`` expects of the method it chose."""

    image: CodedImage | None
    buffers: ViewBuffers | None
    times: dict[str, float]
    legend: dict | None
    method: str
    prev_seq: int
    memory: VolumeMemory
    t: int = 0
    batch: int = 1
    choice: AutoChoice | None = None


@dataclass(frozen=True)
class AskedFrame:
    """A view frame asked for and not yet made (:meth:`Engine._batched`): the session's frames, its
    renderer and job, the future its result goes to, its deadline, the quality it is coded at as a
    JPEG, together with its batch mates' where the device encodes them (None: its session codes it), and
    the video encoding whose planes the device makes for it (:meth:`Engine.codes_sync`; None: not video)."""

    frames: SessionFrames
    renderer: Renderer
    job: FrameJob
    future: asyncio.Future
    deadline: float
    jpeg: int | None
    video: str | None


@dataclass(frozen=True)
class ImageCodes:
    """A made frame's quantized colors and, on a GPU, the event on the device thread's stream after which
    they hold them (None on CPUs), with the frame's checks left to read then (:meth:`FrameResult.checked`):
    a thread reads them through :meth:`wait`. A GPU's video frame also has its I420 planes at the encoder's
    coded size, converted on the device and copied to the host before the same event (None otherwise).

    Shape:
        rgb: (H, W, 3) uint8.
        i420: (coded height * 3 // 2, coded width) uint8, in pinned host memory.
    """

    rgb: torch.Tensor
    ready: torch.cuda.Event | None
    checked: Callable[[], None]
    i420: torch.Tensor | None = None

    def wait(self) -> torch.Tensor:
        """The colors, once the device has made them (blocks this thread until then, not longer).

        Raises:
            ValueError: the frame's input checks fail (its session's error)."""
        if self.ready is not None:
            self.ready.synchronize()
        self.checked()
        return self.rgb


class Engine:
    """Owns the device: networks, renderers, encoders, and the thread all their work runs on."""

    def __init__(self, config: Settings):
        self.config = config
        self.device = torch.device(config.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(f"device {config.device!r} asked for, but torch finds no CUDA device")
        self.precision = config.precision or default_precision(self.device)
        self.slice_ms = config.slice_ms or (8.0 if self.device.type == "cuda" else 100.0)
        # The device thread's own CUDA stream (module docstring), made current there as the thread starts.
        self.stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="isosr-device",
                                            initializer=self._enter_stream)
        # Image, video and buffers encoding: off the device thread, which goes on with the next frame meanwhile.
        self._encoder = ThreadPoolExecutor(max_workers=IMAGE_ENCODER_THREADS, thread_name_prefix="isosr-encoder")
        self._video = ThreadPoolExecutor(max_workers=VIDEO_ENCODER_THREADS, thread_name_prefix="isosr-video")
        # The render kernels that clip or march several isos, compiled on their first use (seconds on a CPU with a
        # cold kernel cache): on threads of their own, so that only the sessions whose frames need them wait
        # (:meth:`frame_kernels`); a thread per such set, so that none waits for another's compile.
        self._compiler = ThreadPoolExecutor(max_workers=len(VARIANT_MODULES) - 1, thread_name_prefix="isosr-compile")
        self._kernel_loads: dict[tuple, Future] = {}
        self._renderers: OrderedDict[str, Renderer] = OrderedDict()
        self.networks = Networks(serving_network)
        self._models = {Upscaler: (config.model, MODEL_NAMES[Upscaler]),
                        Reconstructor: (config.recon_model, MODEL_NAMES[Reconstructor])}
        self.context: ViewContext | None = None
        self.modes: list[ModeInfo] = []
        self.auto: AutoPolicy | None = None
        self._probes: set[asyncio.Task] = set()  # the auto mode's probes under way (background device work)
        self._framing = 0  # view frames in the making
        self._idle = asyncio.Event()  # set while none is
        self._idle.set()
        self._thread: threading.Thread | None = None
        # View frames asked for and not yet made, whether a batch job is queued to make them, and how long
        # a batch may wait for more (its condition notified at each one asked).
        self._pending: list[AskedFrame] = []
        self._batch_queued = False
        self._asked = threading.Condition()
        self.batch_wait_s = config.batch_wait_ms / 1e3
        # Seconds the device thread spent in its finished jobs (not a batch's wait for frames), and when its
        # job in progress began (None: none is): busy_seconds adds them up for GET /metrics.
        self._busy_s, self._job_began = 0.0, None
        self._busy_lock = threading.Lock()

    async def call(self, fn, *args):
        """Run ``fn(*args)`` on the device thread and await its result."""
        return await asyncio.get_running_loop().run_in_executor(self._executor, self._busy, fn, *args)

    def _busy(self, fn, *args):
        """``fn(*args)`` (device thread), its wall time counted in :meth:`busy_seconds`."""
        with self._busy_lock:
            self._job_began = time.monotonic()
        try:
            return fn(*args)
        finally:
            with self._busy_lock:
                self._busy_s += time.monotonic() - self._job_began
                self._job_began = None

    def busy_seconds(self) -> float:
        """Seconds the device thread has spent in jobs so far, the one in progress included: its frames' host
        work and its waits for the GPU, not a batch's wait for frames (any thread; a rate near 1 is the thread
        at its bound)."""
        with self._busy_lock:
            return self._busy_s + (0.0 if self._job_began is None else time.monotonic() - self._job_began)

    def _enter_stream(self) -> None:
        if self.stream is not None:
            torch.cuda.set_stream(self.stream)

    def _on_thread(self) -> None:
        if self._thread is None:
            self._thread = threading.current_thread()
        assert threading.current_thread() is self._thread, "engine work must run on the device thread"

    def network(self, cls: type[RecurrentNetwork]) -> RecurrentNetwork:
        """The server's loaded network of a class (its template: shared weights, no stream's state)."""
        return self.networks.get(cls, self._models[cls][0], str(self.device), self.precision)

    # ---- start-up ---------------------------------------------------------------------------

    def start_sync(self) -> None:
        """Load the networks and warm the device: one small frame of each kind that warms up
        (:attr:`FrameRunner.warm_up`: the network, the reconstruction, the plain render), shaded and encoded;
        on GPUs also the auto mode's candidates at the common window sizes and their probes' (:meth:`AutoPolicy.warm`)."""
        self._on_thread()
        factor = self.network(Upscaler).upscale_factor
        reconstructor = self.network(Reconstructor)
        if reconstructor.upscale_factor != 1:
            raise ValueError(f"{self.config.recon_model}: the service's reconstruct mode renders at full resolution; "
                             f"this model also upscales x{reconstructor.upscale_factor}")
        x2 = self.networks.get(Reconstructor, self.config.recon_x2_model, str(self.device), self.precision)
        if x2.upscale_factor != 2:
            raise ValueError(f"{self.config.recon_x2_model}: the auto mode's x2 reconstruction must upscale x2, "
                             f"this model upscales x{x2.upscale_factor}")
        if self.device.type == "cuda":  # tune the fused kernels for common windows before the first viewer
            reconstructor.warm(WARM_RECON_SIZES)
            x2.warm([(h // 2, w // 2) for h, w in WARM_RECON_SIZES])
        self.context = ViewContext(factor, self.precision, self._models)
        self.modes = mode_infos(self.context)  # what ready and GET /v1/modes list
        self.auto = AutoPolicy.for_server(str(self.device), self.precision, factor, self._models,
                                          self.config.target_fps, self.networks, self.config.recon_x2_model,
                                          ProbeCache(self.config.probe_cache, self.device_label()), self.slice_ms,
                                          self.config.gpu_share, self.config.resolved_min_fps)
        renderer = Renderer(parse_procedural("proc:sphere@16"), str(self.device))
        if self.device.type == "cuda":
            self.auto.warm(renderer, WARM_RECON_SIZES)
        frames = self.new_session_frames("proc:sphere@16")
        for mode in (kind for kind, runner in RUNNERS.items() if runner.warm_up):
            job = FrameJob(ViewSettings(mode=mode, width=8 * factor, height=8 * factor), orbit(30, 20, 1.8), 0.5,
                           FocusMsg(), 0, False, 1)
            pack_codes(self.codes_sync(finish_steps(frames.steps(renderer, job))),
                       lambda rgb, _: CodedImage(encode_image(rgb, "jpeg", 80), "jpeg"))

    @property
    def upscale_factor(self) -> int:
        return self.context.factor

    def model_info(self) -> dict:
        """The upscaling model's parameters for ``GET /v2/models/isosr`` (its folder's name only)."""
        cfg = self.network(Upscaler).net.config
        return {"upscale_factor": self.upscale_factor, "precision": self.precision, "device": str(self.device),
                "model": Path(self.config.model).name,
                "encoders": {e: encoder_name(str(self.device), e) for e in self.encodings()},
                "config": {k: v for k, v in vars(cfg).items() if isinstance(v, (int, float, str, bool, list, tuple))}}

    def encodings(self) -> list[str]:
        """The encodings view sessions can have now: the images, and the video codecs PyAV has."""
        return list(IMAGE_ENCODINGS + video_codecs.available())

    @property
    def recon_limits(self) -> RayLimits:
        """The reconstruction model's ray limits: what view sessions and requests may ask of it."""
        return recon_limits(self.config.recon_model)

    def recon_info(self) -> dict:
        """The reconstruction model's parameters for ``GET /v2/models/isosr-recon`` (its folder's name only)."""
        limits = self.recon_limits
        return {"model": Path(self.config.recon_model).name, "precision": self.precision, "device": str(self.device),
                "max_ao_rays": limits.max_ao_rays, "max_spp": limits.max_spp}

    def new_network(self, cls: type[RecurrentNetwork]) -> RecurrentNetwork:
        """A stream's own network of a class: shares the loaded weights, starts without recurrent state."""
        return self.network(cls).own()

    def new_session_frames(self, scene: str) -> SessionFrames:
        """A view session's own frame state (its own networks' recurrent state)."""
        return SessionFrames(scene, self.networks.fork(), self.context, self.auto)

    def gpu_memory(self) -> int | None:
        """Bytes of GPU memory torch holds now (None on the CPU)."""
        return torch.cuda.memory_allocated(self.device) if self.device.type == "cuda" else None

    def volume_memory(self) -> dict[str, MemoryStats]:
        """Per cached renderer's volume: where its voxels are and what paging cost (read per scrape)."""
        return {name: renderer.memory() for name, renderer in list(self._renderers.items())}

    def device_label(self) -> str:
        """The device's kind, as probe results are kept by (a GPU's name, or the CPU's core count)."""
        if self.device.type == "cuda":
            return torch.cuda.get_device_name(self.device)
        return f"cpu, {os.cpu_count()} cores"

    def start_probes(self) -> None:
        """Run the auto mode's waiting probes as background work on the device thread, a unit at a
        time, in turn with frames (event loop)."""
        while self.auto is not None and self.auto.pending:
            task = asyncio.get_running_loop().create_task(self._run_probe(self.auto.pending.pop()))
            self._probes.add(task)
            task.add_done_callback(self._probes.discard)

    async def _run_probe(self, steps: Generator) -> None:
        await self.run_steps(steps, self._wait_idle, self._log_slow_unit)

    @staticmethod
    def _log_slow_unit(seconds: float) -> None:
        """Say when a probe's unit held the device thread long enough for viewers to see it stall."""
        if seconds > SLOW_PROBE_UNIT_S:
            log.info("auto probe: one unit held the device thread for %.2f s (frames waited)", seconds)

    async def _wait_idle(self) -> None:
        """Until no view frame is in the making, or ``PROBE_WAIT_S`` at most."""
        with suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._idle.wait(), PROBE_WAIT_S)

    async def run_steps(self, steps: Generator, before_each: Callable[[], Awaitable[None]] | None = None,
                        took: Callable[[float], None] | None = None):
        """A generator of slices run to its end, each slice its own job on the device thread (other
        jobs interleave between them); its result. ``before_each`` is awaited before every slice,
        ``took`` told each slice's seconds on the device thread."""
        while True:
            if before_each is not None:
                await before_each()
            done, result, seconds = await self.call(_advance, steps)
            if took is not None:
                took(seconds)
            if done:
                return result

    def shutdown(self) -> None:
        """Stop: probes between two of their units, queued work dropped, the slice in progress ended."""
        for task in list(self._probes):
            task.cancel()
        self._executor.shutdown(wait=True, cancel_futures=True)
        self._compiler.shutdown(wait=True, cancel_futures=True)
        self._encoder.shutdown(wait=True, cancel_futures=True)
        self._video.shutdown(wait=True, cancel_futures=True)

    async def frame_kernels(self, renderer: Renderer, job: FrameJob) -> None:
        """Load the render kernels of ``job``'s frames and picks (those of its clip and surfaces) on a compile
        thread the first time a frame needs them, while the device thread goes on with other sessions' frames; the
        asks meanwhile share that one load, and one that failed is tried again at the next ask. The plain ones are
        loaded with the renderer."""
        key = (renderer.device.alias, job.settings.clip.clip().active, bool(job.settings.surfaces))
        if key[1:] == (False, False):
            return
        load = self._kernel_loads.get(key)
        if load is None:
            load = self._kernel_loads[key] = self._compiler.submit(load_frame_kernels, *key)
        try:
            if not load.done():  # a session that leaves meanwhile leaves the load to the others
                await asyncio.shield(asyncio.wrap_future(load))
            load.result()  # a load done long ago (every frame after the first): no wait, no future made
        except Exception:
            if self._kernel_loads.get(key) is load:
                del self._kernel_loads[key]
            raise

    async def pick(self, renderer: Renderer, job: FrameJob, msg: PickMsg) -> PickedMsg:
        """:meth:`pick_sync` on the device thread, once its render kernels are loaded."""
        await self.frame_kernels(renderer, job)
        return await self.call(self.pick_sync, renderer, job, msg)

    # ---- work (device thread only) ----------------------------------------------------------

    def pick_sync(self, renderer: Renderer, job: FrameJob, msg: PickMsg) -> PickedMsg:
        """What lies under ``msg``'s pixel of the view ``job`` shows (its camera, iso or surfaces, clip and size).

        Raises:
            ProtocolError: the pixel lies outside the view; surfaces the renderer cannot show (422).
        """
        self._on_thread()
        iso, surfaces = SessionFrames.surfaces(renderer, job)
        st = job.settings
        try:
            found = pick(renderer, job.camera, iso, st.width, st.height, msg.x, msg.y, st.clip.clip(), surfaces)
        except ValueError as e:
            raise ProtocolError(str(e)) from None
        return PickedMsg(msg.x, msg.y, msg.id, **asdict(found))

    def renderer_sync(self, name: str, volume: Volume) -> Renderer:
        """The cached renderer of a volume (uploads it on first use); a series' step is a volume of
        its own, named by :func:`isosr_server.sessions.step_name`."""
        self._on_thread()
        if name in self._renderers:
            self._renderers.move_to_end(name)
        else:
            self._renderers[name] = Renderer(volume, str(self.device), max_device_bytes=self.config.max_volume_bytes)
            while len(self._renderers) > RENDERER_CACHE:
                self._renderers.popitem(last=False)
        return self._renderers[name]

    async def view_frame(self, frames: SessionFrames, renderer: Renderer, job: FrameJob,
                         code: Callable[[torch.Tensor, torch.Tensor | None], CodedImage], video: str | None = None,
                         deadline: float | None = None, jpeg: int | None = None
                         ) -> Callable[[], Awaitable[EncodedFrame]]:
        """One view frame, made in slices of about ``slice_ms`` (:meth:`SessionFrames.steps`), each
        its own job on the device thread, so that other sessions' frames interleave with a heavy one;
        its codes made there too (:meth:`codes_sync`). Returns once the device is done with it: what
        it returns encodes it on an encoder thread (:func:`pack_codes`; ``code`` codes a shaded frame's
        colors and, on a GPU, its ``video`` planes; ``video``: the frame's video encoding, coded on a video
        encoder thread), while the device thread goes on with the next frame, this session's included
        (:func:`isosr_server.sessions.run_frames`).
        ``deadline`` (``time.monotonic()``; default: now) orders the batches (:meth:`_batch_sync`).
        ``jpeg``: the frame is coded as a JPEG of this quality, which lets a batch's JPEGs be coded
        together on a device that encodes them (:func:`device_jpeg`; ``code`` is not called then)."""
        start = time.perf_counter()
        await self.frame_kernels(renderer, job)
        self._framing += 1
        self._idle.clear()
        try:
            due = time.monotonic() if deadline is None else deadline
            made, codes, batch, thread_ms = await self._batched(frames, renderer, job, due, jpeg, video)
        finally:
            self._framing -= 1
            if not self._framing:
                self._idle.set()
        self.start_probes()
        pool = self._video if video else self._encoder
        memory = VolumeMemory(**renderer.memory().to_json())

        async def encode() -> EncodedFrame:
            began = time.perf_counter()
            if isinstance(codes, Future):  # its JPEG, coded in turn with its batch mates' (_shared_jpegs)
                image, buffers = CodedImage(await asyncio.wrap_future(codes), "jpeg"), None
            else:
                image, buffers = await asyncio.get_running_loop().run_in_executor(pool, pack_codes, codes, code)
            done = time.perf_counter()
            frames.served(job, made, thread_ms)
            times = made.result.times | {"encode": 1e3 * (done - began), "total": 1e3 * (done - start)}
            return EncodedFrame(image, buffers, times, made.legend, made.method.name, made.prev_seq, memory,
                                job.settings.t, batch, made.choice)
        return encode

    async def _batched(self, frames: SessionFrames, renderer: Renderer, job: FrameJob,
                       deadline: float, jpeg: int | None, video: str | None) -> tuple[ViewFrame, object, int, float]:
        """A view frame, its codes, the frames made together with it (itself included) and what it cost the
        device thread (ms; its share of its batch's wall time), made in the next batch (:meth:`_batch_sync`):
        the frames of every session that asked meanwhile, one device-thread job for them all. A frame that
        runs in slices comes back as its steps and is made here alone, a device-thread job per slice (its
        cost: its stages' device time, since other frames run between its slices)."""
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        with self._asked:
            self._pending.append(AskedFrame(frames, renderer, job, future, deadline, jpeg, video))
            start_batch, self._batch_queued = not self._batch_queued, True
            self._asked.notify()
        if start_batch:
            loop.run_in_executor(self._executor, self._busy, self._batch_sync, loop)
        out = await future
        if isinstance(out, Generator):
            made = await self.run_steps(out)
            return made, await self.call(self.codes_sync, made, video), 1, sum(made.result.times.values())
        return out

    def _batch_sync(self, loop: asyncio.AbstractEventLoop) -> None:
        """Make the frames asked for since the last batch (device thread): each planned
        (:meth:`SessionFrames.plan`); those of one slice grouped by their runners' ``batch_key`` and
        made by its ``make_batch``, the group with the earliest deadline first, then coded (its JPEGs
        together: :meth:`_shared_jpegs`); those that run in slices handed back as their steps. Each
        session's result or error goes to its own future only. A batch takes what is pending when
        the thread gets to it, after waiting up to :attr:`batch_wait_s` for the sessions that have
        not asked yet (:meth:`_fill_batch`): no frame is held past its deadline to fill one."""
        self._on_thread()
        with self._asked:
            self._fill_batch()
            pending, self._pending, self._batch_queued = self._pending, [], False
        groups: dict[tuple, list[tuple[AskedFrame, FramePlan]]] = {}
        for asked in sorted(pending, key=lambda a: a.deadline):
            try:
                plan = asked.frames.plan(asked.renderer, asked.job)
                if plan.runner.one_slice(self.slice_ms):
                    groups.setdefault(plan.runner.batch_key(), []).append((asked, plan))
                else:
                    _resolve(loop, asked.future, asked.frames.planned_steps(plan, self.slice_ms))
            except Exception as e:  # noqa: BLE001 - this session's error, not its batch mates'
                _resolve(loop, asked.future, error=e)
        for group in groups.values():  # in the order of their earliest deadlines (dicts keep insertion order)
            began = time.perf_counter()
            try:
                results = type(group[0][1].runner).make_batch([(p.runner, p.job.camera, p.prev_camera)
                                                               for _, p in group])
            except Exception as e:  # noqa: BLE001 - a kind's batch failed as a whole: its sessions' error
                results = [e] * len(group)
            made = []  # (asked, made frame, its codes) of the frames made
            for (asked, plan), result in zip(group, results):
                try:
                    if isinstance(result, Exception):
                        raise result
                    frame = asked.frames.made(plan, result)
                    made.append((asked, frame, self.codes_sync(frame, asked.video)))
                except Exception as e:  # noqa: BLE001 - as above
                    _resolve(loop, asked.future, error=e)
            thread_ms = 1e3 * (time.perf_counter() - began) / len(group)  # the clock auto's probes time by
            for (asked, frame, _), codes in zip(made, self._shared_jpegs(made)):
                _resolve(loop, asked.future, (frame, codes, len(group), thread_ms))

    def _fill_batch(self) -> None:
        """Wait (holding :attr:`_asked`) until every view session has asked for a frame, :attr:`batch_wait_s`
        has passed, or the earliest pending frame's deadline has come, whichever is first."""
        if self.batch_wait_s <= 0 or not self._pending:
            return
        sessions = max(asked.job.sessions for asked in self._pending)
        began = time.monotonic()
        until = min(began + self.batch_wait_s, min(asked.deadline for asked in self._pending))
        while len(self._pending) < sessions and (left := until - time.monotonic()) > 0:
            self._asked.wait(left)
        with self._busy_lock:
            self._busy_s -= time.monotonic() - began  # waiting for frames is not the device's work

    def _shared_jpegs(self, made: list[tuple[AskedFrame, ViewFrame, object]]) -> list[object]:
        """The codes of a batch's made frames, those coded as JPEGs of one quality on a device that encodes
        them (:func:`device_jpeg`) as the future of their bytes: one encoder-thread job codes them in turn
        (nvJPEG, off the device thread), each frame's bytes released as soon as they are made."""
        codes = [c for _, _, c in made]
        together: dict[int, list[int]] = {}
        for i, (asked, _, c) in enumerate(made):
            if asked.jpeg is not None and isinstance(c, ImageCodes) and device_jpeg(c.rgb.device):
                together.setdefault(asked.jpeg, []).append(i)
        for quality, indices in together.items():
            futures = [Future() for _ in indices]
            job = self._encoder.submit(code_jpegs_in_turn, [codes[i] for i in indices], quality, futures)

            def cancel_with(job: Future, futures: list[Future] = futures) -> None:
                if job.cancelled():  # the encoders shut down before it ran
                    for future in futures:
                        future.cancel()
            job.add_done_callback(cancel_with)
            for i, future in zip(indices, futures):
                codes[i] = future
        return codes

    def codes_sync(self, made: ViewFrame, video: str | None = None) -> ImageCodes | tuple:
        """A made frame's codes: its color quantized to uint8 on the device (the image to encode), with a
        GPU's ``video`` frame's I420 planes on the host (the video encoder thread then makes no device call,
        which would wait for the device thread's later work), or the ``buffers`` mode's low-res codes on the
        host (:func:`view_buffer_codes`)."""
        self._on_thread()
        if made.color is not None:
            rgb = quantize(made.color)
            ready = i420 = None
            if rgb.is_cuda:
                if video is not None:
                    coded = video_codecs.coded_size(video, rgb.shape[1], rgb.shape[0])
                    i420 = device_i420(rgb, *coded).to("cpu", non_blocking=True)  # pinned; done at the event
                ready = torch.cuda.Event(blocking=True)  # its waiters sleep, not spin
                ready.record()
            return ImageCodes(rgb, ready, made.result.checked, i420)
        made.result.checked()  # the host reads the buffers now (view_buffer_codes): their checks too
        b = made.result.buffers
        return view_buffer_codes(FrameBuffers(mask=b.mask, normal=b.normal, depth=b.depth,
                                              flow=b.flow if made.prev_seq >= 0 else None))

    async def upscale(self, upscaler: Upscaler, request: UpscaleRequest) -> tuple[bytes | None, dict | None, dict]:
        """One upscale request: ``(image bytes or None, float32 numpy buffers or None, times in ms)``;
        a tiled upscale in slices, one device-thread job per tile (:meth:`Upscaler.upscale_steps`).

        Raises:
            ValueError: the library refuses the frame (e.g. fp16 with depths beyond its range).
        """
        return await self.run_steps(self._upscale_steps(upscaler, request, time.perf_counter()))

    def _upscale_steps(self, upscaler: Upscaler, request: UpscaleRequest, start: float) -> Generator:
        timer = StageTimer(self.device)
        if request.reset:
            upscaler.reset()
        frame = FrameBuffers(**{n: torch.from_numpy(getattr(request, n).astype("float32"))
                                for n in ("mask", "normal", "depth", "flow") if getattr(request, n) is not None})
        high = yield from timed_steps(upscaler.upscale_steps(frame), timer, "network")
        _check_finite(upscaler, high)
        image = buffers = None
        if request.output == "buffers":
            with timer("encode"):
                buffers = {n: getattr(high, n).cpu().numpy() for n in ("mask", "normal", "depth", "ao")}
        else:
            with timer("shading"):
                color = shade(high.mask, high.normal, high.ao)
            with timer("encode"):
                image = encode_image(quantize(color), request.output, request.quality)
        return image, buffers, timer.ms() | {"total": 1e3 * (time.perf_counter() - start)}

    async def reconstruct(self, reconstructor: Reconstructor, inputs: dict[str, np.ndarray], ao_rays: int, spp: int,
                          outputs: tuple[str, ...], reset: bool) -> tuple[dict[str, np.ndarray], dict]:
        """One reconstruction request (:meth:`Reconstructor.reconstruct`, one device-thread job):
        ``(float32 numpy buffers named in outputs, times in ms)``; ``color`` is shaded with the
        default material, and only when ``outputs`` names it.

        Args:
            inputs: full-res mask, normal, depth, and ao and flow where given (float16/float32).
            reset: forget the recurrent state first.

        Raises:
            ValueError: the library refuses the frame (e.g. fp16 with depths beyond its range).
        """
        return await self.call(self._reconstruct_sync, reconstructor, inputs, ao_rays, spp, outputs, reset,
                               time.perf_counter())

    def _reconstruct_sync(self, reconstructor: Reconstructor, inputs: dict[str, np.ndarray], ao_rays: int, spp: int,
                          outputs: tuple[str, ...], reset: bool, start: float) -> tuple[dict[str, np.ndarray], dict]:
        self._on_thread()
        timer = StageTimer(self.device)
        if reset:
            reconstructor.reset()
        frame = FrameBuffers(**{n: torch.from_numpy(a.astype("float32")) for n, a in inputs.items()})
        with timer("network"):
            out = reconstructor.reconstruct(frame, ao_rays, spp, ShadingParams() if "color" in outputs else None)
        _check_finite(reconstructor, out)
        with timer("encode"):
            buffers = {n: getattr(out, n).cpu().numpy() for n in outputs}
        return buffers, timer.ms() | {"total": 1e3 * (time.perf_counter() - start)}


def _check_finite(network: RecurrentNetwork, out: FrameBuffers) -> None:
    """`ValueError` if a network's output holds NaN or Inf, its recurrent state reset first (a
    non-finite output must not feed the next frame)."""
    if not bool(torch.stack([torch.isfinite(getattr(out, n)).all() for n in out.present()]).all()):  # one sync
        network.reset()
        raise ValueError("the network gave non-finite values for this frame")


def code_jpegs_in_turn(codes: list[ImageCodes], quality: int, futures: list[Future]) -> None:
    """JPEGs of a batch's frames on the device (encoder thread), one after the other in the batch's order
    (its deadlines'), each frame's bytes (or its error) to its future as soon as they are made: nvJPEG codes
    one image at a time under one lock (torchvision), so a frame need not wait for its batch's last."""
    for c, future in zip(codes, futures):
        try:
            future.set_result(encode_jpegs([c.wait()], quality)[0])
        except Exception as e:  # noqa: BLE001 - this frame's error, not its batch mates'
            future.set_exception(e)


def _resolve(loop: asyncio.AbstractEventLoop, future: asyncio.Future, result: object = None,
             error: BaseException | None = None) -> None:
    """Settle an event-loop future from the device thread (unless its session stopped waiting)."""
    def settle() -> None:
        if future.done():
            return
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
    loop.call_soon_threadsafe(settle)


def pack_codes(codes: ImageCodes | tuple, code: Callable[[torch.Tensor, torch.Tensor | None], CodedImage]
               ) -> tuple[CodedImage | None, ViewBuffers | None]:
    """``(code(colors, video planes), None)`` of quantized colors, or ``(None, buffers)`` of the buffers codes
    (encoder thread)."""
    if isinstance(codes, tuple):
        return None, pack_view_buffers(*codes)
    return code(codes.wait(), codes.i420), None


def _advance(steps: Generator) -> tuple[bool, object, float]:
    """One slice of a generator of slices: ``(False, None, seconds)``, or ``(True, its result, seconds)`` at
    its end, with the seconds it took."""
    began = time.perf_counter()
    try:
        next(steps)
        return False, None, time.perf_counter() - began
    except StopIteration as done:
        return True, done.value, time.perf_counter() - began
