"""The engine: the one owner of the device.

All renderer, network and encoder work runs on one worker thread (a 1-thread executor), so
concurrent requests never race on the GPU or on a session's recurrent state, and GPU work
of different sessions is serialized in submission order (the executor's FIFO queue). A view
session queues its next frame only after the last one is sent, so the ready sessions are
served in turn (round robin), never the busiest first. The event loop awaits
:meth:`Engine.call`; everything named ``*_sync`` runs only on that thread.

Renderers are cached per volume (a few, least recently used dropped); every stream gets its
own `Upscaler` made by :meth:`Engine.new_upscaler`, and every view session its own
`Reconstructor` (:meth:`Engine.new_recon_stream`): shallow copies of one loaded model each that
share its weights and own their recurrent state.
"""

from __future__ import annotations

import asyncio
import copy
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeVar

import torch

from isosr_net.reconstructor import DEFAULT_RECON_MODEL, MAX_RECON_AO_RAYS, Reconstructor
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import FrameBuffers, Renderer, Volume, orbit, parse_procedural, shade
from isosr_render.images import quantize
from isosr_server import channels, pipeline
from isosr_server.encoding import encode_image, encoder_name
from isosr_server.protocol import ENCODINGS, UpscaleRequest, ViewBuffers

RENDERER_CACHE = 4
Net = TypeVar("Net", bound=Upscaler)


@dataclass(frozen=True)
class EngineConfig:
    """Where and how the engine runs.

    Attributes:
        model: the upscaling model folder (``config.json`` + ``model.safetensors``).
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        precision: the networks' ``fp32``, ``bf16`` or ``fp16`` (upscaling and reconstruction).
        recon_model: the reconstruction model folder (``reconstruct`` mode).
    """

    model: Path = DEFAULT_MODEL
    device: str = "cpu"
    precision: str = "fp32"
    recon_model: Path = DEFAULT_RECON_MODEL


class Engine:
    """Owns the device: model, renderers, encoders, and the thread all their work runs on."""

    def __init__(self, config: EngineConfig):
        self.config = config
        self.device = torch.device(config.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(f"device {config.device!r} asked for, but torch finds no CUDA device")
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="isosr-device")
        self._renderers: OrderedDict[str, Renderer] = OrderedDict()
        self._template: Upscaler | None = None
        self._recon_template: Reconstructor | None = None
        self._thread: threading.Thread | None = None

    async def call(self, fn, *args):
        """Run ``fn(*args)`` on the device thread and await its result."""
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    def _on_thread(self) -> None:
        if self._thread is None:
            self._thread = threading.current_thread()
        assert threading.current_thread() is self._thread, "engine work must run on the device thread"

    # ---- start-up ---------------------------------------------------------------------------

    def start_sync(self) -> None:
        """Load the models and warm the device: one small render, upscale, reconstruction, shading and encode."""
        self._on_thread()
        # GPUs: NHWC and the rewritten layers (the same function,
        # isosr_net/fastpath.py); no torch.compile (the `fastest` variants), which would stall
        # every session for seconds at each new frame size.
        cuda = self.device.type == "cuda"
        self._template = Upscaler(self.config.model, str(self.device), self.config.precision,
                                  channels_last=cuda, fast_layers=cuda)
        self._recon_template = Reconstructor(self.config.recon_model, str(self.device), self.config.precision,
                                             channels_last=cuda, fast_layers=cuda)
        factor = self.upscale_factor
        renderer = Renderer(parse_procedural("proc:sphere@16"), str(self.device))
        spec = pipeline.FrameSpec("network", orbit(30, 20, 1.8), None, 0.5, 8 * factor, 8 * factor, 1, 0.05, None, 0)
        color = pipeline.render_sr(renderer, self.new_upscaler(), spec, pipeline.StageTimer(self.device))
        encode_image(quantize(color), "jpeg", 80)
        self.new_recon_stream().frame(renderer, replace(spec, mode="reconstruct"))

    @property
    def upscale_factor(self) -> int:
        return self._template.upscale_factor

    def model_info(self) -> dict:
        """Model metadata for ``GET /v2/models/isosr``."""
        cfg = self._template.net.config
        return {"upscale_factor": self.upscale_factor, "precision": self.config.precision,
                "device": str(self.device), "model": str(self.config.model),
                "encoders": {e: encoder_name(str(self.device), e) for e in ENCODINGS},
                "config": {k: v for k, v in vars(cfg).items() if isinstance(v, (int, float, str, bool, list, tuple))},
                "reconstruction": {"model": str(self.config.recon_model), "max_ao_rays": MAX_RECON_AO_RAYS,
                                   "spp": pipeline.RECON_SPP}}

    def new_upscaler(self) -> Upscaler:
        """A stream's own upscaler: shares the loaded weights, starts without recurrent state."""
        return _own(self._template)

    def new_recon_stream(self) -> pipeline.ReconStream:
        """A view session's own reconstruction: shares the loaded weights, starts without recurrent state."""
        return pipeline.ReconStream(_own(self._recon_template), self.config.recon_model)

    def gpu_memory(self) -> int | None:
        """Bytes of GPU memory torch holds now (None on the CPU)."""
        return torch.cuda.memory_allocated(self.device) if self.device.type == "cuda" else None

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    # ---- work (device thread only) ----------------------------------------------------------

    def renderer_sync(self, name: str, volume: Volume) -> Renderer:
        """The cached renderer of a volume (uploads it on first use)."""
        self._on_thread()
        if name in self._renderers:
            self._renderers.move_to_end(name)
        else:
            self._renderers[name] = Renderer(volume, str(self.device))
            while len(self._renderers) > RENDERER_CACHE:
                self._renderers.popitem(last=False)
        return self._renderers[name]

    def view_frame_sync(self, renderer: Renderer, upscaler: Upscaler, recon: pipeline.ReconStream,
                        spec: pipeline.FrameSpec, encoding: str,
                        quality: int) -> tuple[bytes | None, ViewBuffers | None, dict[str, float], dict | None]:
        """One view frame: ``(image bytes or None, coded buffers or None, times in ms, channel legend or None)``.

        Args:
            renderer: the session's volume's renderer.
            upscaler, recon: the session's own networks (network and focus; reconstruct).
            spec: the frame.
            encoding, quality: the image coding of shaded frames.
        """
        self._on_thread()
        timer = pipeline.StageTimer(self.device)
        with timer("total"):
            buffers, color, legend = None, None, None
            if spec.channel != "shaded" and spec.mode != "buffers":
                color, legend = channels.render_channel(renderer, upscaler, self.upscale_factor, spec, timer, recon)
            elif spec.mode == "full":
                color = pipeline.render_full(renderer, spec, timer)
            elif spec.mode == "network":
                color = pipeline.render_sr(renderer, upscaler, spec, timer)
            elif spec.mode == "reconstruct":
                color = recon.frame(renderer, spec).color
            elif spec.mode == "upscale":
                color = pipeline.render_bilinear(renderer, self.upscale_factor, spec, timer)
            elif spec.mode == "focus":
                color = pipeline.render_focus(renderer, upscaler, spec, timer)
            elif spec.mode == "buffers":
                buffers = pipeline.render_buffers(renderer, self.upscale_factor, spec, timer)
            else:
                raise ValueError(f"unknown mode {spec.mode!r}")
            image = None
            if color is not None:
                with timer("encode"):
                    image = encode_image(quantize(color), encoding, quality)
        return image, buffers, timer.ms, legend

    def upscale_sync(self, upscaler: Upscaler, request: UpscaleRequest) -> tuple[bytes | None, dict | None, dict]:
        """One upscale request: ``(image bytes or None, float32 numpy buffers or None, times in ms)``.

        Raises:
            ValueError: the library refuses the frame (e.g. fp16 with depths beyond its range).
        """
        self._on_thread()
        timer = pipeline.StageTimer(self.device)
        if request.reset:
            upscaler.reset()
        frame = FrameBuffers(**{n: torch.from_numpy(getattr(request, n).astype("float32"))
                                for n in ("mask", "normal", "depth", "flow") if getattr(request, n) is not None})
        with timer("total"):
            with timer("network"):
                high = upscaler.upscale(frame)
                if not all(bool(torch.isfinite(getattr(high, n)).all()) for n in high.present()):
                    upscaler.reset()  # a non-finite output must not feed the next frame
                    raise ValueError("the network gave non-finite values for this frame")
            if request.output == "buffers":
                with timer("encode"):
                    buffers = {n: getattr(high, n).cpu().numpy() for n in ("mask", "normal", "depth", "ao")}
                return None, buffers, timer.ms
            with timer("shading"):
                color = shade(high.mask, high.normal, high.ao)
            with timer("encode"):
                image = encode_image(quantize(color), request.output, request.quality)
        return image, None, timer.ms


def _own(template: Net) -> Net:
    """A stream's own copy of a loaded network: shares its weights, starts without recurrent state."""
    net = copy.copy(template)
    net.reset()
    return net
