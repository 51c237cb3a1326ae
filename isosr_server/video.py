"""A view session's frame coding: images, or a video stream whose bitrate and frame rate follow
the link (issue 21; the codecs: :mod:`isosr_server.codecs.video`).

Rate control (`RateControl`, on the event loop). The target bitrate is the client's cap
(``bitrate_kbps`` > 0), or, with 0, the server's own choice: it starts at ``max_bitrate_kbps``
(the encoders' constant quality decides the bytes while the link keeps up) and follows the
link. The link's throughput is estimated from acknowledged frames (``received``): a frame's
bytes over the time the link was busy with it (from its send, or the previous acknowledgment
if later, to its acknowledgment), the largest such sample of the last `WINDOW_S`. When the
frame loop has a frame to make but no credit (the link or the client lags), the target drops
to `HEADROOM` of that estimate; after `PROBE_S` without waiting it rises by `PROBE_STEP`, up
to the ceiling. The frame rate steps down (`FPS_STEPS`) before the bits per pixel of a frame
fall below `MIN_BITS_PER_PIXEL`; the encoder's share of the bitrate per frame follows the frame
rate the session really has (frames sent in the last WINDOW_S, when slower), with a margin of
`FPS_HYSTERESIS` before it changes (each change reopens the encoder: a keyframe). Credit-based flow
control stays: a slow link drops frames (latest wins), never queues them.

Coding (`SessionCoder`, on the engine's video encoder threads; one frame of a session at a time). Image
encodings encode each frame alone. A video session keeps one encoder, opened anew (its first
frame a keyframe) on a new encoding, size or quality, when its rate is off the target by more
than `REOPEN_DOWN` / `REOPEN_UP` (up only while the cap binds), and forces a keyframe at the
client's request and after a refined frame (which goes out as a lossless ``png``). An encoder
that cannot be made (PyAV or the codec missing, settings refused) gives a ``jpeg`` frame and a
notice; the session then stays on jpeg until the client asks for another encoding.
"""

from __future__ import annotations

import functools
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from isosr_server.codecs.video import VideoEncoder, VideoUnavailable, check_available
from isosr_server.encoding import CodedImage, encode_image
from isosr_server.protocol import VIDEO_ENCODINGS

# The link estimate: the largest throughput sample of the last WINDOW_S seconds.
WINDOW_S = 2.0
# A lagging link gets this share of its estimate; PROBE_S seconds without lag raise the target PROBE_STEP times.
HEADROOM, PROBE_S, PROBE_STEP = 0.8, 1.0, 1.25
# The lowest target the estimate sets (a stalled client must not drive it to nothing).
MIN_KBPS = 50
# Frame rates a session steps through; below MIN_BITS_PER_PIXEL a frame's quality drops too far.
FPS_STEPS = (60.0, 30.0, 20.0, 15.0, 10.0, 5.0)
MIN_BITS_PER_PIXEL = 0.03
# The encoder's frame rate moves to the step of the rate frames are sent at only once that rate lies this
# share beyond the band of its current step (up: above it by this share; down: below the lower step by it):
# without it a session sent at about 30 frames/s under a max_fps of 60 flipped between 30 and 60 and
# reopened its encoder, a keyframe, every 4-5 frames (measured on a 625 kbit/s loopback link, 480x270).
FPS_HYSTERESIS = 0.1
# A running encoder is reopened when the target falls below 1/REOPEN_DOWN of its rate, or rises
# above REOPEN_UP times it while its frames fill at least CAP_BINDS of their share.
REOPEN_DOWN, REOPEN_UP, CAP_BINDS = 1.2, 1.5, 0.6
# Frames whose size the encoder remembers (does the cap bind?); frames in flight the estimate tracks.
RECENT_FRAMES = 8


class RateControl:
    """A video session's target bitrate and frame rate (module docstring).

    Args:
        cap_kbps: the client's cap (0: estimate the link).
        ceiling_kbps: ``max_bitrate_kbps``.
        max_fps: ``max_fps``.
    """

    def __init__(self, cap_kbps: int, ceiling_kbps: int, max_fps: float):
        self.ceiling, self.max_fps = ceiling_kbps, max_fps
        self.cap = cap_kbps
        self.target = float(cap_kbps or ceiling_kbps)
        self._inflight: deque[tuple[int, int, float]] = deque(maxlen=64)  # (seq, bytes, sent at)
        self._sent: deque[float] = deque(maxlen=64)  # when the last frames were sent
        self._samples: deque[tuple[float, float]] = deque(maxlen=64)  # (when, kbit/s)
        self._last_ack = -float("inf")
        self._encoder_fps: float | None = None  # the encoder's frame rate of the last measured one
        self._changed = time.monotonic()

    def set_cap(self, cap_kbps: int) -> None:
        """A new ``bitrate_kbps`` (0: estimate)."""
        if cap_kbps != self.cap:
            self.cap, self.target, self._changed = cap_kbps, float(cap_kbps or self.target), time.monotonic()

    def sent(self, seq: int, nbytes: int, now: float) -> None:
        self._inflight.append((seq, nbytes, now))
        self._sent.append(now)

    def acknowledged(self, seq: int, now: float) -> None:
        """Frames up to ``seq`` arrived: one throughput sample."""
        nbytes, began = 0, None
        while self._inflight and self._inflight[0][0] <= seq:
            _, n, sent = self._inflight.popleft()
            nbytes, began = nbytes + n, sent if began is None else began
        if began is not None:
            busy = now - max(began, self._last_ack)
            if busy > 0:
                self._samples.append((now, 8e-3 * nbytes / busy))
        self._last_ack = now

    def estimate(self, now: float) -> float | None:
        """The link's throughput in kbit/s (None: no sample of the last WINDOW_S)."""
        recent = [kbps for when, kbps in self._samples if now - when <= WINDOW_S]
        return max(recent) if recent else None

    def lagging(self, now: float) -> None:
        """The frame loop waits on credit: with no cap of the client's, aim below the link's estimate."""
        estimate = self.estimate(now)
        if self.cap == 0 and estimate is not None and self.target > HEADROOM * estimate:
            self.target, self._changed = max(float(MIN_KBPS), HEADROOM * estimate), now

    def bitrate_kbps(self, now: float) -> int:
        """The target now (probing upwards after PROBE_S without lag)."""
        if self.cap == 0 and self.target < self.ceiling and now - self._changed >= PROBE_S:
            self.target, self._changed = min(float(self.ceiling), self.target * PROBE_STEP), now
        return max(1, round(self.target))

    def fps(self, width: int, height: int, bitrate_kbps: int) -> float:
        """The frame rate to keep: the highest of ``max_fps`` and the lower `FPS_STEPS` whose frames
        get MIN_BITS_PER_PIXEL."""
        return next((f for f in self._steps() if 1e3 * bitrate_kbps / (f * width * height) >= MIN_BITS_PER_PIXEL),
                    self._steps()[-1])

    def encoder_fps(self, fps: float, now: float) -> float:
        """The frame rate the encoder shares the bitrate by: ``fps``, or the step at or above the rate
        of the frames sent in the last WINDOW_S where that is lower (a render-bound session); it
        changes steps only beyond FPS_HYSTERESIS (module docstring)."""
        recent = [t for t in self._sent if now - t <= WINDOW_S]
        if len(recent) < 3 or recent[-1] <= recent[0]:
            self._encoder_fps = None
            return fps
        made = (len(recent) - 1) / (recent[-1] - recent[0])
        step, now_at = min((f for f in self._steps() if f >= made), default=self._steps()[0]), self._encoder_fps
        if now_at is None or (step > now_at and made > (1 + FPS_HYSTERESIS) * now_at) or \
                (step < now_at and made < (1 - FPS_HYSTERESIS) * step):
            self._encoder_fps = step
        return min(fps, self._encoder_fps)

    def _steps(self) -> list[float]:
        return [self.max_fps] + [f for f in FPS_STEPS if f < self.max_fps]


@dataclass(frozen=True)
class CodePlan:
    """How one frame is coded: the session's encoding (``png`` for a refined frame), quality,
    and for video the target bitrate, frame rate, timestamp and whether a keyframe is asked for."""

    encoding: str
    quality: int
    bitrate_kbps: int = 0
    fps: float = 30.0
    timestamp_us: int = 0
    keyframe: bool = False
    refined: bool = False


class SessionCoder:
    """One view session's coding of its frames (module docstring); thread-safe (a lock).

    Args:
        cores: the CPU cores encoders may use (`video_threads`).
    """

    def __init__(self, cores: int):
        self.cores = cores
        self._lock = threading.Lock()
        self.encoder: VideoEncoder | None = None
        self._sizes: deque[int] = deque(maxlen=RECENT_FRAMES)
        self._after_still = False

    def code(self, rgb: torch.Tensor, plan: CodePlan, i420: torch.Tensor | None = None) -> CodedImage:
        """One frame's bytes as ``plan`` says (a jpeg frame with a notice where video fails); a video frame
        from ``i420`` where given (:func:`device_i420` of ``rgb`` at the encoder's coded size, on the host).

        Shape:
            rgb: (H, W, 3) uint8, on any device.
            i420: (coded height * 3 // 2, coded width) uint8, on the host.
        """
        with self._lock:
            return self._code(rgb, plan, i420)

    def _code(self, rgb: torch.Tensor, plan: CodePlan, i420: torch.Tensor | None) -> CodedImage:
        if plan.refined and plan.encoding in VIDEO_ENCODINGS:
            self._after_still = True
            return CodedImage(encode_image(rgb, "png", plan.quality), "png")
        if plan.encoding not in VIDEO_ENCODINGS:
            return CodedImage(encode_image(rgb, plan.encoding, plan.quality), plan.encoding)
        try:
            encoder = self._encoder(int(rgb.shape[1]), int(rgb.shape[0]), plan)
        except VideoUnavailable as e:
            self._close()
            return CodedImage(encode_image(rgb, "jpeg", plan.quality), "jpeg", notice=f"{e}; sending jpeg")
        data, key = encode_frame(encoder, rgb, plan.timestamp_us, plan.keyframe or self._after_still, i420)
        self._after_still = False
        self._sizes.append(len(data))
        return CodedImage(data, plan.encoding, key, encoder.codec, encoder.bitrate_kbps)

    def _encoder(self, width: int, height: int, plan: CodePlan) -> VideoEncoder:
        """The running encoder, or a new one where the plan differs from it (module docstring)."""
        e = self.encoder
        if e is not None and (e.encoding, e.width, e.height, e.quality) == (plan.encoding, width, height,
                                                                            plan.quality):
            share = 125.0 * e.bitrate_kbps / e.fps  # bytes of a frame's share of the rate
            binds = len(self._sizes) > 1 and np.mean(list(self._sizes)[1:]) >= CAP_BINDS * share
            if plan.fps == e.fps and not (plan.bitrate_kbps * REOPEN_DOWN < e.bitrate_kbps or
                                          (binds and plan.bitrate_kbps > REOPEN_UP * e.bitrate_kbps)):
                return e
        self._close()
        self.encoder = VideoEncoder(plan.encoding, width, height, plan.quality, plan.bitrate_kbps, plan.fps,
                                    video_threads(width, height, self.cores))
        return self.encoder

    def close(self) -> None:
        """Free the video encoder (the next video frame opens one, a keyframe)."""
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self.encoder is not None:
            self.encoder.close()
        self.encoder = None
        self._sizes.clear()


# BT.709 RGB -> Y'CbCr, limited range (Y 16-235, Cb and Cr 16-240 about 128): the matrix the streams signal
# (isosr_server.codecs.video), which their decoders invert.
_KR, _KB = 0.2126, 0.0722
BT709_LIMITED = torch.tensor([[_KR, 1 - _KR - _KB, _KB],
                              [-_KR / (2 - 2 * _KB), -(1 - _KR - _KB) / (2 - 2 * _KB), 0.5],
                              [0.5, -(1 - _KR - _KB) / (2 - 2 * _KR), -_KB / (2 - 2 * _KR)]]
                             ) * torch.tensor([[219 / 255], [224 / 255], [224 / 255]])


def device_i420(rgb: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """A frame as a video encoder's I420 planes (BT.709, limited range), made on its device: padded to the
    coded ``width`` x ``height`` by repeating its last column and row, chroma the mean of each 2x2 block.

    Shape:
        rgb: (H, W, 3) uint8, H <= height and W <= width (both even).
        Returns: (height * 3 // 2, width) uint8: Y, then Cb, then Cr.
    """
    h, w = rgb.shape[:2]
    if rgb.dtype != torch.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or not (h <= height and w <= width):
        raise ValueError(f"device_i420: takes (H, W, 3) uint8 within {height}x{width}, got {tuple(rgb.shape)} "
                         f"{rgb.dtype}")
    if height % 2 or width % 2:
        raise ValueError(f"device_i420: 4:2:0 needs even coded sides, got {width}x{height}")
    x = torch.nn.functional.pad(rgb.permute(2, 0, 1).float()[None], (0, width - w, 0, height - h), mode="replicate")
    matrix = _bt709_on(x.device)
    luma = torch.einsum("j,njhw->hw", matrix[0], x) + 16
    # the chroma of each block's mean RGB: the mean of its chroma (the conversion is linear), a quarter of the work
    chroma = torch.einsum("ij,njhw->ihw", matrix[1:], torch.nn.functional.avg_pool2d(x, 2)) + 128
    return torch.cat([luma.flatten(), chroma.flatten()]).round_().clamp_(0, 255).to(torch.uint8).view(-1, width)


@functools.cache
def _bt709_on(device: torch.device) -> torch.Tensor:
    return BT709_LIMITED.to(device)


def encode_frame(encoder: VideoEncoder, rgb: torch.Tensor, timestamp_us: int, keyframe: bool = False,
                 i420: torch.Tensor | None = None) -> tuple[bytes, bool]:
    """:meth:`VideoEncoder.encode` of a frame where it is: its ``i420`` planes where given (made on the device
    thread: :meth:`isosr_server.engine.Engine.codes_sync`), a CUDA frame converted to I420 there
    (:func:`device_i420`: half the bytes to copy, no conversion on the host), a host frame by FFmpeg's
    swscale (its SIMD conversion took 5 ms of a core a 1080p frame, torch's 27).

    Shape:
        rgb: (H, W, 3) uint8, the encoder's size, on any device.
        i420: (coded height * 3 // 2, coded width) uint8, on the host.
    """
    if i420 is not None:
        return encoder.encode_i420(i420.numpy(), timestamp_us, keyframe)
    if rgb.is_cuda:
        return encoder.encode_i420(device_i420(rgb, *encoder.coded_size).cpu().numpy(), timestamp_us, keyframe)
    return encoder.encode(rgb.cpu().numpy(), timestamp_us, keyframe)


def video_threads(width: int, height: int, cores: int) -> int:
    """Threads of a video encoder of this size: one per half megapixel, 1 to ``cores`` // 2.

    Alone, sliced threads cut a frame's latency for few bytes (an H200 host, 1080p h264 at matched PSNR, 1 / 2 / 4 /
    8 / 16 threads: 27 / 15.2 / 12.6 / 9.1 / 7.0 ms a frame, 23 ms of cores at 4 and 25 at 8, bytes +0.7 % from 4 to
    8), but in service 8 did not beat 4 (16 sessions of 4 replicas: encode stage 20.6-21.3 ms against 19-21, frame
    rates 400 / 307 against 414 / 321, replicas' cores 16.4 against 13.6-15.2): ``bench_video_threads_1080p_cuda.json``,
    ``bench_cluster_haproxy_h264_1080p_cuda.json``."""
    return max(1, min(max(1, cores // 2), width * height // 500_000))


def fallback_notice(encoding: str) -> str | None:
    """Why ``encoding`` cannot be made here (None: it can, or it is an image encoding)."""
    if encoding not in VIDEO_ENCODINGS:
        return None
    try:
        check_available(encoding)
    except VideoUnavailable as e:
        return f"{e}; sending jpeg"
    return None

