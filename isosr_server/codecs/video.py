"""Video coding of a view session's frames (h264, vp9, av1) with FFmpeg's encoders and decoders
through PyAV (``pip install av``, the ``video`` extra; its wheels bundle libx264, libvpx,
SVT-AV1 and dav1d). numpy and PyAV only: the server encodes, clients decode with the same module.

Encoders run in low-latency settings, one per session (:class:`VideoEncoder`): no B-frames and
no lookahead, so each frame's access unit comes out of ``encode`` at once.

    h264  libx264, preset ``veryfast`` (`X264_PRESET`), adaptive quantization off, tune
          ``zerolatency``, Annex B with SPS/PPS in every keyframe; constant quality (CRF from
          ``quality``) capped by the bitrate (VBV).
    vp9   libvpx-vp9, deadline ``realtime``, ``cpu-used`` 8, ``lag-in-frames`` 0, row
          multithreading; CBR at the bitrate, its best quantizer bounded by ``quality``.
    av1   SVT-AV1 (libsvtav1), real-time mode (``rtc=1``: low-delay prediction), preset 10;
          CBR at the bitrate, its best quantizer bounded by ``quality``.

The rate cap is a VBV of `VBV_FRAMES` frames at the target bitrate and the nominal frame rate,
so no frame, a keyframe included, is much larger than that many frames' share of the bitrate:
the time a frame takes on a link running at the target stays bounded. FFmpeg's wrappers cannot
change a running encoder's rate, so a new bitrate or frame rate opens a new encoder (its first
frame a keyframe): :class:`isosr_server.video.SessionVideo` does that sparingly.

Colors: BT.709, limited range, 4:2:0, signalled in the stream; decoders convert back with the
same matrix. yuv420p needs even sides, and SVT-AV1's rate control sides of 64 pixels or more:
a frame is coded at `coded_size` (each side rounded up to even, at least the codec's
``min_side``), its last column or row repeated, and the decoder crops it off again.

SVT-AV1 prints its configuration to stderr at every open unless ``SVT_LOG`` says otherwise: the
first AV1 encoder sets ``SVT_LOG=1`` (errors only) where it is unset.
"""

from __future__ import annotations

import fractions
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from isosr_server.protocol import VIDEO_ENCODINGS

# libx264's preset (with tune zerolatency: no B-frames, no lookahead, sliced threads). Measured on
# bonsai orbits at JPEG 85's PSNR (2-core dev machine, 1 thread; smooth full:0 / noisy full:8 frames):
# bytes over JPEG's and CPU ms per 1080p frame: ultrafast 0.37 / 0.51, 22 ms; superfast 0.31 / 0.44,
# 25 ms; veryfast 0.26 / 0.41, 29 ms; faster 0.23 / 0.38, 36 ms. veryfast is the cheapest under a third
# of JPEG on smooth frames (ultrafast drops CABAC and motion search) at under a core per 1080p session
# at 30 frames/s; at 4K it costs 77 ms a frame against ultrafast's 66 for 0.21 of JPEG against 0.32.
# Adaptive quantization off (as ultrafast has it): 3% fewer bytes at matched PSNR (0.258 against 0.265,
# noisy 0.400 against 0.408), and a CRF keeps ultrafast's PSNR (quality 85 near JPEG 85's; with AQ on,
# 1.9 dB lower at the same CRF, 35.4 dB on tests/test_video.py's small frames).
X264_PRESET, X264_AQ_MODE = "veryfast", "0"
# Frames of the target bitrate the rate cap's buffer holds: the largest frame is about this many
# frames' share of the bitrate (2: a keyframe after a cut stays within two frame intervals on the link).
VBV_FRAMES = 2


@dataclass(frozen=True)
class Codec:
    """One video encoding: FFmpeg's encoder and decoder names, the quantizer range ``quality``
    maps onto (``quality`` 100 -> ``best``, 1 -> ``worst``) and the smallest side it codes."""

    encoding: str
    encoder: str
    decoder: str
    best: int
    worst: int
    min_side: int = 2

    def quantizer(self, quality: int) -> int:
        """The CRF (h264) or lowest quantizer (vp9, av1) of a quality 1-100."""
        if not 1 <= quality <= 100:
            raise ValueError(f"quality must lie in [1, 100], got {quality}")
        return round(self.best + (self.worst - self.best) * (100 - quality) / 99)


# Quantizer ranges: quality 85 (the protocol's default) lands near JPEG 85's PSNR on shaded frames
# (isosr_bench/bench_video.py matches them).
CODECS = {c.encoding: c for c in (Codec("h264", "libx264", "h264", 12, 51),
                                  Codec("vp9", "libvpx-vp9", "vp9", 4, 63),
                                  Codec("av1", "libsvtav1", "libdav1d", 8, 63, 64))}
assert tuple(CODECS) == VIDEO_ENCODINGS


class VideoUnavailable(RuntimeError):
    """This machine cannot make (or decode) an encoding: why, in words for a notice."""


@lru_cache(maxsize=1)
def _av():
    """PyAV, imported on first use (None where it is not installed)."""
    try:
        import av
    except ImportError:
        return None
    return av


def check_available(encoding: str, decode: bool = False) -> None:
    """Raise `VideoUnavailable` saying why ``encoding`` cannot be encoded (or decoded) here."""
    if encoding not in CODECS:
        raise VideoUnavailable(f"{encoding} is not a video encoding ({', '.join(CODECS)})")
    av = _av()
    if av is None:
        raise VideoUnavailable(f"{encoding} is not available here (PyAV missing: pip install av)")
    name = CODECS[encoding].decoder if decode else CODECS[encoding].encoder
    if name not in av.codecs_available:
        raise VideoUnavailable(f"{encoding} is not available here (PyAV {av.__version__} has no {name})")


def available(decode: bool = False) -> tuple[str, ...]:
    """The video encodings this machine can encode (or decode)."""
    out = []
    for encoding in CODECS:
        try:
            check_available(encoding, decode)
        except VideoUnavailable:
            continue
        out.append(encoding)
    return tuple(out)


def describe(encoding: str) -> str:
    """The encoder of a video encoding, for reports (``libx264 (PyAV 18.1.0, cpu)``)."""
    check_available(encoding)
    return f"{CODECS[encoding].encoder} (PyAV {_av().__version__}, cpu)"


def coded_size(encoding: str, width: int, height: int) -> tuple[int, int]:
    """The coded size of a ``width`` x ``height`` frame: each side rounded up to even, at least
    the codec's ``min_side``."""
    low = CODECS[encoding].min_side
    return max(low, width + width % 2), max(low, height + height % 2)


def _options(codec: Codec, quality: int, bitrate_kbps: int, fps: float) -> dict[str, str]:
    """FFmpeg's options of a low-latency encoder at ``quality`` capped at ``bitrate_kbps``."""
    q = str(codec.quantizer(quality))
    rate, buffer = f"{bitrate_kbps}k", f"{max(1, round(VBV_FRAMES * bitrate_kbps / fps))}k"
    if codec.encoding == "h264":
        return {"preset": X264_PRESET, "aq-mode": X264_AQ_MODE, "tune": "zerolatency", "crf": q, "maxrate": rate, "bufsize": buffer,
                "bf": "0", "forced-idr": "1"}
    if codec.encoding == "vp9":
        return {"deadline": "realtime", "cpu-used": "8", "lag-in-frames": "0", "row-mt": "1", "qmin": q,
                "qmax": "63", "b": rate, "minrate": rate, "maxrate": rate, "bufsize": buffer}
    return {"preset": "10", "b": rate, "bufsize": buffer, "qmin": q, "qmax": "63",
            "svtav1-params": "rtc=1:rc=2"}


class VideoEncoder:
    """One session's encoder of one codec, size, quality, bitrate and nominal frame rate.

    Args:
        encoding: ``h264``, ``vp9`` or ``av1``.
        width, height: the frames' size (coded at `coded_size`).
        quality: 1-100 (`Codec.quantizer`).
        bitrate_kbps: the rate cap in kbit/s (module docstring).
        fps: the nominal frame rate: the bitrate's share of a frame is ``bitrate_kbps / fps``.
        threads: the encoder's threads (0: FFmpeg's choice).
        options: FFmpeg options over the defaults (benchmarks; bad ones fail here).

    Raises:
        VideoUnavailable: the encoding cannot be made here, or the encoder refused its settings.
    """

    def __init__(self, encoding: str, width: int, height: int, quality: int, bitrate_kbps: int, fps: float,
                 threads: int = 0, options: dict[str, str] | None = None):
        check_available(encoding)
        if width < 1 or height < 1 or bitrate_kbps < 1 or not 0 < fps <= 1000:
            raise ValueError(f"video encoder: need a positive size, bitrate and fps, got {width}x{height}, "
                             f"{bitrate_kbps} kbit/s, {fps} fps")
        av, codec = _av(), CODECS[encoding]
        if encoding == "av1":
            os.environ.setdefault("SVT_LOG", "1")
        self.encoding, self.width, self.height = encoding, width, height
        self.quality, self.bitrate_kbps, self.fps = quality, bitrate_kbps, fps
        self.coded_size = coded_size(encoding, width, height)
        cc = av.CodecContext.create(codec.encoder, "w")
        cc.width, cc.height = self.coded_size
        cc.pix_fmt = "yuv420p"
        cc.time_base = fractions.Fraction(1, 1_000_000)
        cc.framerate = fractions.Fraction(fps).limit_denominator(1001)
        cc.bit_rate = bitrate_kbps * 1000
        cc.gop_size = 2**30 if encoding != "av1" else -1  # keyframes only when asked for (SVT: -1 = none)
        cc.max_b_frames = 0
        cc.thread_count = threads
        cc.color_primaries = cc.color_trc = cc.colorspace = 1  # BT.709
        cc.color_range = 1  # limited ("MPEG")
        cc.options = _options(codec, quality, bitrate_kbps, fps) | (options or {})
        try:
            cc.open()
        except av.FFmpegError as e:
            raise VideoUnavailable(f"the {encoding} encoder ({codec.encoder}) refused its settings: {e}") from None
        self._cc, self.codec = cc, None
        self._last_pts = -1

    def encode(self, rgb: np.ndarray, timestamp_us: int, keyframe: bool = False) -> tuple[bytes, bool]:
        """Encode one frame: ``(access unit, is a keyframe)``; ``keyframe`` forces one.
        ``timestamp_us`` must increase from frame to frame. FFmpeg's swscale converts it to 4:2:0.

        Shape:
            rgb: (height, width, 3) uint8.
        """
        if rgb.dtype != np.uint8 or rgb.shape != (self.height, self.width, 3):
            raise ValueError(f"video encoder: takes ({self.height}, {self.width}, 3) uint8, got {rgb.shape} "
                             f"{rgb.dtype}")
        pad = ((0, self.coded_size[1] - self.height), (0, self.coded_size[0] - self.width), (0, 0))
        frame = host_i420(np.pad(rgb, pad, mode="edge") if any(p[1] for p in pad) else rgb)
        return self._encode(frame, timestamp_us, keyframe)

    def encode_i420(self, planes: np.ndarray, timestamp_us: int, keyframe: bool = False) -> tuple[bytes, bool]:
        """:meth:`encode` of a frame already converted (BT.709, limited range, 4:2:0, at the coded size:
        :func:`isosr_server.video.device_i420` makes it where the frame is).

        Shape:
            planes: (coded height * 3 // 2, coded width) uint8: Y, then Cb, then Cr, each row-major.
        """
        width, height = self.coded_size
        if planes.dtype != np.uint8 or planes.shape != (height * 3 // 2, width):
            raise ValueError(f"video encoder: takes I420 planes ({height * 3 // 2}, {width}) uint8, got "
                             f"{planes.shape} {planes.dtype}")
        return self._encode(_av().VideoFrame.from_ndarray(planes, format="yuv420p"), timestamp_us, keyframe)

    def _encode(self, frame, timestamp_us: int, keyframe: bool) -> tuple[bytes, bool]:
        if timestamp_us <= self._last_pts:
            raise ValueError(f"video encoder: timestamps must increase, got {timestamp_us} after {self._last_pts}")
        av = _av()
        frame.pts, self._last_pts = timestamp_us, timestamp_us
        frame.pict_type = av.video.frame.PictureType.I if keyframe else av.video.frame.PictureType.NONE
        packets = self._cc.encode(frame)
        if len(packets) != 1:  # low-latency settings: one access unit per frame, at once
            raise RuntimeError(f"the {self.encoding} encoder gave {len(packets)} packets for one frame")
        data, key = bytes(packets[0]), bool(packets[0].is_keyframe)
        if key:
            self.codec = codec_string(self.encoding, data, *self.coded_size, self.fps)
        return data, key

    def close(self) -> None:
        """Flush and free the encoder (idempotent)."""
        if self._cc is not None:
            try:
                self._cc.encode(None)
            except _av().FFmpegError:
                pass
            self._cc = None


def host_i420(rgb: np.ndarray):
    """A host frame as an I420 ``av.VideoFrame`` by FFmpeg's swscale (BT.709, limited range): how
    :meth:`VideoEncoder.encode` converts it.

    Shape:
        rgb: (H, W, 3) uint8, H and W even.
    """
    frame = _av().VideoFrame.from_ndarray(rgb, format="rgb24")
    return frame.reformat(format="yuv420p", dst_colorspace="ITU709", dst_color_range="MPEG")


def rgb_of(frame) -> np.ndarray:
    """A decoded (or I420) ``av.VideoFrame`` as (H, W, 3) uint8 RGB, by the matrix the streams signal."""
    return frame.to_ndarray(format="rgb24", src_colorspace="ITU709", src_color_range="MPEG")


def codec_string(encoding: str, keyframe: bytes, width: int, height: int, fps: float) -> str:
    """The WebCodecs codec string of a stream, from its keyframe (h264: the SPS; av1: the sequence
    header) or its size and rate (vp9's level)."""
    if encoding == "h264":
        return _avc_string(keyframe)
    if encoding == "vp9":
        pixels = width * height
        level = next((lv for size, lv in _VP9_LEVELS if pixels <= size), 62)
        return f"vp09.00.{level + (fps > 30 and level >= 40):02d}.08"
    if encoding == "av1":
        return _av1_string(keyframe)
    raise ValueError(f"{encoding} is not a video encoding")


# VP9 levels by their largest picture (luma samples): 1, 1.1, 2, 2.1, 3, 3.1, 4, 5, 6 (x.1: above 30 fps from 4 on).
_VP9_LEVELS = ((36864, 10), (73728, 11), (122880, 20), (245760, 21), (552960, 30), (983040, 31), (2228224, 40),
               (8912896, 50), (35651584, 60))


def _avc_string(annexb: bytes) -> str:
    """``avc1.PPCCLL`` from the first SPS (NAL type 7) of an Annex B access unit."""
    at = 0
    while (at := annexb.find(b"\x00\x00\x01", at)) >= 0 and at + 6 < len(annexb):
        at += 3
        if annexb[at] & 0x1F == 7:
            return "avc1." + annexb[at + 1:at + 4].hex()
    raise ValueError("h264 keyframe without an SPS")


class _Bits:
    def __init__(self, data: bytes):
        self.data, self.at = data, 0

    def read(self, n: int) -> int:
        v = 0
        for _ in range(n):
            v = (v << 1) | (self.data[self.at >> 3] >> (7 - (self.at & 7))) & 1
            self.at += 1
        return v

    def uvlc(self) -> int:
        zeros = 0
        while not self.read(1):
            zeros += 1
        return (1 << zeros) - 1 + self.read(zeros)


def _av1_string(unit: bytes) -> str:
    """``av01.P.LLT.08`` from the sequence header OBU of a temporal unit (8-bit: this module codes 8-bit)."""
    at = 0
    while at < len(unit):
        header, at = unit[at], at + 1 + (unit[at] >> 2 & 1)  # skip the extension byte
        size, shift = 0, 0
        while True:  # leb128 (every OBU here has its size)
            byte, at = unit[at], at + 1
            size |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
        if header >> 3 & 0xF == 1:  # OBU_SEQUENCE_HEADER
            b = _Bits(unit[at:at + size])
            profile, _still, reduced = b.read(3), b.read(1), b.read(1)
            if reduced:
                return f"av01.{profile}.{b.read(5):02d}M.08"
            decoder_model = False
            if b.read(1):  # timing_info
                b.read(64)
                if b.read(1):
                    b.uvlc()
                decoder_model = bool(b.read(1))
                if decoder_model:
                    b.read(5 + 32 + 5 + 5)
            b.read(1 + 5 + 12)  # initial_display_delay_present, operating_points_cnt_minus_1, idc of op 0
            level = b.read(5)
            tier = b.read(1) if level > 7 else 0
            return f"av01.{profile}.{level:02d}{'H' if tier else 'M'}.08"
        at += size
    raise ValueError("av1 keyframe without a sequence header")


class VideoDecoder:
    """A client's decoder of one session's stream of one encoding (frames in order, from a keyframe).

    Raises:
        VideoUnavailable: the encoding cannot be decoded here (PyAV or the decoder missing).
    """

    def __init__(self, encoding: str):
        check_available(encoding, decode=True)
        av = _av()
        self.encoding = encoding
        self._cc = av.CodecContext.create(CODECS[encoding].decoder, "r")
        self._cc.thread_type = "SLICE"  # frame threads would hold frames back
        self._cc.flags |= av.codec.context.Flags.low_delay

    def decode(self, data: bytes, width: int, height: int) -> np.ndarray:
        """One access unit -> the frame as (height, width, 3) uint8 RGB (the coded padding cropped).

        Raises:
            ValueError: the decoder failed or gave no frame (ask the server for a keyframe).
        """
        av = _av()
        try:
            frames = self._cc.decode(av.Packet(data))
        except av.FFmpegError as e:
            raise ValueError(f"{self.encoding} decoder: {e}") from None
        if not frames:
            raise ValueError(f"{self.encoding} decoder: no frame from this access unit (missing keyframe?)")
        rgb = rgb_of(frames[-1])
        if rgb.shape[0] < height or rgb.shape[1] < width:
            raise ValueError(f"{self.encoding} decoder: frame {rgb.shape[1]}x{rgb.shape[0]} smaller than "
                             f"{width}x{height}")
        return np.ascontiguousarray(rgb[:height, :width])
