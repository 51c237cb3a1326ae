"""The wire protocol of `isosr serve`: the one module the server and every client share.

Imports only numpy, msgpack and the standard library (clients need neither FastAPI nor torch).

Coding
    Every message is one msgpack map (never pickle) with a ``type`` key. Unpacking is strict:
    ``raw=False``, string map keys only, no extension types, bounded buffer / bin / str /
    array / map sizes, no trailing bytes. Unknown keys are errors (a typo is not silently
    ignored). Arrays travel as ``{dtype, shape, data}`` (plus ``zlib: true`` when ``data`` is
    zlib-compressed): dtype one of float16, float32, uint8, uint16, little-endian, C order;
    ``data`` must hold exactly ``prod(shape) * itemsize`` bytes; floats must be finite.

View session (``WS /v1/view``)
    client -> ``open`` (version, volume name, settings incl. mode and size, optional camera
    and iso); server -> ``ready`` (session id, volume info, effective settings, upscale
    factor, limits) and a first frame. Then the client sends ``camera``, ``iso``,
    ``settings`` and ``focus`` at any rate; each carries an optional ``seq``. The server keeps
    only the newest state (latest wins) and answers ``frame`` messages whose ``ack`` is the
    highest ``seq`` they include. A still camera gets one extra frame with ``refined: true``.
    Bad input ends the session with an ``error`` message and a close code (``CLOSE_*``).

View modes (``settings.mode``; :mod:`isosr_server.pipeline` makes each)
    full         ray cast at the output size, AO of ``ao_samples`` rays per pixel (0: none).
    sr           ray cast at 1/factor of the output size, upscaled by the network (which
                 infers AO), shaded.
    bilinear     as ``sr`` with bilinear upscaling instead of the network (no AO).
    buffers      the low-res buffers themselves (coding below): the client upscales.
    focus        ``sr``, with a ``full`` render inside the focus region.
    reconstruct  ray cast at the output size with few AO rays per hit (``ao_samples``: 0 to the
                 reconstruction model's bound, ``reconstruction.max_ao_rays`` of
                 ``GET /v2/models/isosr``, 8 for the shipped model; more are refused with
                 CLOSE_BAD_MESSAGE), reconstructed by a network to converged-looking AO and
                 antialiased edges, shaded. Added within version 2: servers without it refuse
                 the mode by name.
    ``sr``, ``focus`` and ``reconstruct`` carry a recurrent state per session; a new iso, size or
    mode (``reconstruct``: or ``ao_samples``) starts it afresh.

Flow control (version 2)
    The client answers each frame it has taken off the wire with ``received`` (``frame``: the
    frame's ``seq``; cumulative: it covers every frame before it too). The server renders a
    frame only while fewer than ``max_unacked_frames`` frames are unacknowledged, so a slow
    client gets frames at the rate it takes them, each of the newest state, and a stalled one
    costs nothing after ``max_unacked_frames`` frames. A ``received`` for a frame not yet sent
    ends the session (CLOSE_BAD_MESSAGE); one for an older frame than the newest acknowledged
    changes nothing. A session waiting on credit for ``idle_timeout_s`` is closed (CLOSE_IDLE).

Upscaling (``POST /v1/upscale``, ``WS /v1/upscale/stream``)
    ``upscale`` request (low-res mask, normal, depth, optional flow in the conventions of
    :mod:`isosr_render.conventions`, float16/float32) -> ``upscaled`` (high-res mask, normal,
    depth, ao as float32 arrays, or one encoded image).

Buffers mode coding (:func:`encode_view_buffers` / :func:`decode_view_buffers`)
    mask   uint8 coverage ``round(255 m)``, at least 1 where ``m > 0`` (so "no hit" survives
           exactly); error <= 1/255.
    normal octahedral, 2 x uint16 per pixel; angular error < 1e-3 rad (float16 xyz: 6 bytes
           a pixel instead of 4, and 37% more after zlib); 0 where the mask is 0.
    depth  uint16, linear between the frame's nearest and farthest hit (``depth_range``);
           error <= (far - near) / 131070 (float16: relative 4.9e-4, 1e-3 at depth 2, about a
           voxel of a 1024^3 volume; 30% fewer bytes, but the network reads depth edges).
    flow   float16 pixels, clipped to +-FLOW_CLIP; error <= |flow| * 2^-11.
    Each array zlib level 1 (stdlib; zstd is not in 3.12's; level 6 saved only 4% more).
    Measured on a 480x270 low-res frame of bonsai (1080p / 4, 10% covered, Otsu iso, orbit
    30/20/1.8): 147 KB against 3.63 MB of float32 (mask 3.1 KB, normal 59 KB, depth 30 KB,
    flow 54 KB); encode 11 ms, decode 9 ms on one CPU core. A bit-packed mask would save
    1.6 KB (1%) and lose coverage, so the mask stays uint8.
"""

from __future__ import annotations

import math
import re
import zlib
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, ClassVar

import msgpack
import numpy as np

# 2: view clients acknowledge frames (``received``, flow control); 1 is refused with a reason.
PROTOCOL_VERSION = 2

# dtype names allowed on the wire, always little-endian.
WIRE_DTYPES = {"float16": np.dtype("<f2"), "float32": np.dtype("<f4"), "uint8": np.dtype("u1"),
               "uint16": np.dtype("<u2")}
MAX_NDIM = 3
MAX_STR = 4096
# Largest magnitude of any float field (camera coordinates, iso, ...): beyond it is hostile input.
MAX_ABS_FLOAT = 1e9
# Flow in the buffers coding is clipped to this many pixels (float16 ends at 65504).
FLOW_CLIP = 60000.0
ZLIB_LEVEL = 1

MODES = ("full", "sr", "bilinear", "buffers", "focus", "reconstruct")
# What a shaded-mode frame shows: the shaded image or one buffer in false color (isosr_server.channels).
CHANNELS = ("shaded", "mask", "normal", "depth", "ao", "flow")
ENCODINGS = ("jpeg", "png", "webp")
UPSCALE_OUTPUTS = ("buffers",) + ENCODINGS
FOCUS_SHAPES = ("none", "circle", "box")
SESSION_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
MAX_SEQ = 2**53

# Authentication, when the server has a token: HTTP requests send ``Authorization: Bearer TOKEN``
# or the header below; WebSocket clients may instead offer the subprotocols ``SUBPROTOCOL`` and
# ``TOKEN_SUBPROTOCOL_PREFIX + TOKEN`` (browsers cannot set headers; tokens stay out of URLs and logs).
TOKEN_HEADER = "x-isosr-token"
SUBPROTOCOL = "isosr.v1"
TOKEN_SUBPROTOCOL_PREFIX = "isosr-token."
MSGPACK_MEDIA_TYPE = "application/msgpack"

# WebSocket close codes (RFC 6455 where one fits, 4xxx mirror HTTP statuses).
CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001  # server shutting down
CLOSE_BAD_MESSAGE = 1007  # malformed msgpack, wrong field, dtype, shape, NaN/Inf
CLOSE_POLICY = 1008  # message rate above the limit
CLOSE_TOO_BIG = 1009  # message above max_message_bytes, image above the size limits
CLOSE_INTERNAL = 1011  # a server fault (logged at ERROR on the server)
CLOSE_UNAUTHORIZED = 4401  # missing or wrong token
CLOSE_NOT_FOUND = 4404  # unknown volume
CLOSE_IDLE = 4408  # no message for idle_timeout_s
CLOSE_TOO_MANY = 4429  # session limit reached; try later


@dataclass(frozen=True)
class Limits:
    """Bounds the server enforces (and announces in ``ready``); all configurable by `isosr serve`.

    Attributes:
        max_message_bytes: largest message a client may send.
        max_side: largest output image side in pixels.
        max_pixels: largest output image area in pixels.
        max_fps: most frames a view session gets per second.
        max_messages_per_s: most messages a client may send per second (averaged over 1 s).
        max_sessions: most concurrent view sessions; the same again for upscale sessions.
        idle_timeout_s: a session without messages for this long is closed / expired.
        max_ao_samples: most AO rays per pixel a client may ask for (refined frames included).
        max_unacked_frames: most frames a view session has sent (or is making) that its client
            has not acknowledged with ``received``; the server renders the next one only below it.
        open_timeout_s: a WebSocket that sends no first message (``open``) within it is closed
            with CLOSE_IDLE and holds no session slot.
        max_sessions_per_client: most WebSocket sessions (past their first message) one client
            address holds.
        body_timeout_s: an HTTP request body must arrive within it (HTTP 408 after).
        max_connections: most HTTP requests and WebSockets in progress.
        max_connections_per_client: most HTTP requests and WebSockets in progress from one client
            address.
    """

    max_message_bytes: int = 32 * 2**20
    max_side: int = 4096
    max_pixels: int = 3840 * 2160
    max_fps: float = 60.0
    max_messages_per_s: float = 1000.0
    max_sessions: int = 32
    idle_timeout_s: float = 300.0
    max_ao_samples: int = 256
    max_unacked_frames: int = 2
    open_timeout_s: float = 10.0
    max_sessions_per_client: int = 8
    body_timeout_s: float = 30.0
    max_connections: int = 256
    max_connections_per_client: int = 32

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 \
                    or not math.isfinite(value):
                raise ValueError(f"limit {f.name} must be a positive number, got {value!r}")
            if isinstance(f.default, int) and not isinstance(value, int):
                raise ValueError(f"limit {f.name} must be an integer, got {value!r}")

    def check_size(self, width: int, height: int, what: str = "image") -> None:
        """Raise `ProtocolError` (CLOSE_TOO_BIG, HTTP 413) for an image over the size limits."""
        if width > self.max_side or height > self.max_side or width * height > self.max_pixels:
            raise ProtocolError(f"{what} {width}x{height} exceeds the limits (side <= {self.max_side}, "
                                f"pixels <= {self.max_pixels})", CLOSE_TOO_BIG, 413)


class ProtocolError(ValueError):
    """A client's message broke the protocol: what is wrong, the close code and HTTP status to answer."""

    def __init__(self, reason: str, close_code: int = CLOSE_BAD_MESSAGE, http_status: int = 400):
        super().__init__(reason)
        self.reason = reason
        self.close_code = close_code
        self.http_status = http_status


# ---------------------------------------------------------------------------------------------
# msgpack


def pack(message: dict) -> bytes:
    """msgpack bytes of a wire dict (``Message.to_wire()``)."""
    return msgpack.packb(message, use_bin_type=True)


def _no_ext(code: int, data: bytes):
    raise ValueError(f"msgpack extension type {code} is not part of the protocol")


def unpack(data: bytes, max_bytes: int) -> dict:
    """Decode one message; a `ProtocolError` for anything but one size-bounded msgpack map.

    Raises:
        ProtocolError: too big (CLOSE_TOO_BIG / 413), malformed or truncated (CLOSE_BAD_MESSAGE / 400).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("messages must be binary msgpack")
    if len(data) > max_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds the limit of {max_bytes}", CLOSE_TOO_BIG, 413)
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, ext_hook=_no_ext, timestamp=0,
                                max_buffer_size=max(max_bytes, 1), max_bin_len=max_bytes, max_str_len=MAX_STR,
                                max_array_len=4096, max_map_len=64, max_ext_len=0, use_list=True)
    try:
        unpacker.feed(data)
        obj = unpacker.unpack()
        trailing = unpacker.tell() != len(data)
    except (ValueError, msgpack.UnpackException) as e:  # FormatError, StackError, OutOfData, ext types
        raise ProtocolError(f"malformed msgpack: {type(e).__name__}: {e}"[:200]) from None
    if trailing:
        raise ProtocolError("malformed msgpack: bytes after the message")
    if not isinstance(obj, dict):
        raise ProtocolError(f"a message must be a msgpack map, got {type(obj).__name__}")
    return obj


# ---------------------------------------------------------------------------------------------
# field validation


class _Reader:
    """Reads the fields of one wire map, checks their types and ranges, and rejects leftovers."""

    def __init__(self, d: Any, where: str):
        if not isinstance(d, dict):
            raise ProtocolError(f"{where} must be a map, got {type(d).__name__}")
        self.d, self.where, self.used = d, where, set()

    def _raw(self, key: str, required: bool):
        self.used.add(key)
        if key not in self.d or self.d[key] is None:
            if required:
                raise ProtocolError(f"{self.where}: missing field {key!r}")
            return None
        return self.d[key]

    def int(self, key: str, lo: int, hi: int, default: int | None = None, required: bool = False) -> int | None:
        v = self._raw(key, required)
        if v is None:
            return default
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ProtocolError(f"{self.where}: {key} must be an integer in [{lo}, {hi}], got {v!r}"[:200])
        return v

    def float(self, key: str, lo: float = -MAX_ABS_FLOAT, hi: float = MAX_ABS_FLOAT, default: float | None = None,
              required: bool = False, open_lo: bool = False) -> float | None:
        v = self._raw(key, required)
        if v is None:
            return default
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi \
            and not (open_lo and v == lo)
        if not ok:
            span = f"({lo}, {hi}]" if open_lo else f"[{lo}, {hi}]"
            raise ProtocolError(f"{self.where}: {key} must be a finite number in {span}, got {v!r}"[:200])
        return float(v)

    def bool(self, key: str, default: bool | None = None, required: bool = False) -> bool | None:
        v = self._raw(key, required)
        if v is None:
            return default
        if not isinstance(v, bool):
            raise ProtocolError(f"{self.where}: {key} must be true or false, got {v!r}"[:200])
        return v

    def choice(self, key: str, options: tuple[str, ...], default: str | None = None, required: bool = False):
        v = self._raw(key, required)
        if v is None:
            return default
        if v not in options or not isinstance(v, str):
            raise ProtocolError(f"{self.where}: {key} must be one of {', '.join(options)}, got {v!r}"[:200])
        return v

    def str(self, key: str, pattern: re.Pattern, default: str | None = None, required: bool = False):
        v = self._raw(key, required)
        if v is None:
            return default
        if not isinstance(v, str) or not pattern.match(v):
            raise ProtocolError(f"{self.where}: {key} must match {pattern.pattern}, got {v!r}"[:200])
        return v

    def vec(self, key: str, n: int, required: bool = False) -> tuple[float, ...] | None:
        v = self._raw(key, required)
        if v is None:
            return None
        if not isinstance(v, list) or len(v) != n:
            raise ProtocolError(f"{self.where}: {key} must be a list of {n} numbers, got {v!r}"[:200])
        sub = _Reader({str(i): x for i, x in enumerate(v)}, f"{self.where}.{key}")
        return tuple(sub.float(str(i), required=True) for i in range(n))

    def map(self, key: str, required: bool = False) -> dict | None:
        v = self._raw(key, required)
        if v is not None and not isinstance(v, dict):
            raise ProtocolError(f"{self.where}: {key} must be a map, got {type(v).__name__}")
        return v

    def done(self):
        extra = set(self.d) - self.used
        if extra:
            raise ProtocolError(f"{self.where}: unknown fields {sorted(map(str, extra))}"[:200])


def _seq(r: _Reader) -> int | None:
    return r.int("seq", 0, MAX_SEQ)


def _version(r: _Reader, where: str) -> int:
    """The message's protocol version; `ProtocolError` for any but `PROTOCOL_VERSION`."""
    version = r.int("version", 0, 2**31, required=True)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"{where}: protocol version {version} is not supported; this server speaks "
                            f"{PROTOCOL_VERSION}: update the client")
    return version


# ---------------------------------------------------------------------------------------------
# arrays


def encode_array(a: np.ndarray, compress: bool = False) -> dict:
    """An array as ``{dtype, shape, data[, zlib]}`` (little-endian, C order)."""
    a = np.asarray(a)
    name = next((n for n, dt in WIRE_DTYPES.items() if a.dtype == dt or a.dtype == dt.newbyteorder("=")), None)
    if name is None:
        raise ValueError(f"dtype {a.dtype} cannot travel; use one of {', '.join(WIRE_DTYPES)}")
    data = np.ascontiguousarray(a, dtype=WIRE_DTYPES[name]).tobytes()
    wire = {"dtype": name, "shape": list(a.shape), "data": zlib.compress(data, ZLIB_LEVEL) if compress else data}
    if compress:
        wire["zlib"] = True
    return wire


def decode_array(wire: Any, where: str, limits: Limits, dtypes: tuple[str, ...] = tuple(WIRE_DTYPES),
                 shape: tuple[int | None, ...] | None = None, bounds: tuple[float, float] | None = None) -> np.ndarray:
    """Validate and decode a wire array (a read-only view of the message bytes when uncompressed).

    Args:
        wire: the ``{dtype, shape, data[, zlib]}`` map.
        where: the field's name, for error messages.
        limits: bounds the element count (``max_pixels * 4``) and side (``max_side``).
        dtypes: dtype names accepted here.
        shape: the expected shape, ``None`` entries free.
        bounds: the range every value must lie in.

    Raises:
        ProtocolError: unknown dtype, bad shape, byte count mismatch, corrupt zlib data, NaN/Inf,
            values out of ``bounds``.
    """
    r = _Reader(wire, where)
    dtype_name = r.choice("dtype", dtypes, required=True)
    dims = r._raw("shape", True)
    data = r._raw("data", True)
    compressed = r.bool("zlib", False)
    r.done()
    if not isinstance(dims, list) or not 1 <= len(dims) <= MAX_NDIM \
            or any(isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= limits.max_side for n in dims):
        raise ProtocolError(f"{where}: shape must be 1 to {MAX_NDIM} sides in [1, {limits.max_side}], got {dims!r}"[:200])
    if shape is not None and (len(dims) != len(shape) or any(s is not None and s != n for s, n in zip(shape, dims))):
        want = tuple("*" if s is None else s for s in shape)
        raise ProtocolError(f"{where}: shape must be {want}, got {tuple(dims)}")
    count = math.prod(dims)
    if count > 4 * limits.max_pixels:
        raise ProtocolError(f"{where}: {count} elements exceed the limit", CLOSE_TOO_BIG, 413)
    if not isinstance(data, bytes):
        raise ProtocolError(f"{where}: data must be msgpack bin bytes")
    dtype = WIRE_DTYPES[dtype_name]
    nbytes = count * dtype.itemsize
    if compressed:
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(data, nbytes + 1)
        except zlib.error as e:
            raise ProtocolError(f"{where}: corrupt zlib data ({e})") from None
        if len(raw) != nbytes or not inflater.eof:
            raise ProtocolError(f"{where}: zlib data does not inflate to {nbytes} bytes for shape {tuple(dims)}")
        data = raw
    if len(data) != nbytes:
        raise ProtocolError(f"{where}: {len(data)} data bytes, but {dtype_name} {tuple(dims)} needs {nbytes}")
    a = np.frombuffer(data, dtype=dtype).reshape(dims)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ProtocolError(f"{where}: holds NaN or Inf values")
    if bounds is not None and a.size and (a.min() < bounds[0] or a.max() > bounds[1]):
        raise ProtocolError(f"{where}: values must lie in [{bounds[0]:g}, {bounds[1]:g}], got "
                            f"[{float(a.min()):g}, {float(a.max()):g}]")
    return a


# ---------------------------------------------------------------------------------------------
# buffers mode coding


def _octahedral_encode(normal: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) -> (..., 2) uint16 octahedral codes."""
    n = normal.astype(np.float64)
    n = n / np.maximum(np.abs(n).sum(-1, keepdims=True), 1e-30)
    xy = n[..., :2]
    sign = np.where(xy >= 0, 1.0, -1.0)
    folded = (1.0 - np.abs(xy[..., ::-1])) * sign
    xy = np.where(n[..., 2:3] < 0, folded, xy)
    return np.round((np.clip(xy, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint16)


def _octahedral_decode(code: np.ndarray) -> np.ndarray:
    """(..., 2) uint16 octahedral codes -> unit vectors (..., 3) float32."""
    xy = code.astype(np.float64) / 65535 * 2 - 1
    z = 1.0 - np.abs(xy).sum(-1, keepdims=True)
    sign = np.where(xy >= 0, 1.0, -1.0)
    xy = np.where(z < 0, (1.0 - np.abs(xy[..., ::-1])) * sign, xy)
    n = np.concatenate([xy, z], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def encode_view_buffers(mask: np.ndarray, normal: np.ndarray | None, depth: np.ndarray | None,
                        flow: np.ndarray | None) -> dict:
    """Low-res buffers (float32 numpy, conventions of isosr_render) in the buffers-mode coding.

    Shape:
        mask, depth: (h, w). normal: (h, w, 3). flow: (h, w, 2).
    """
    covered = mask > 0
    wire: dict[str, Any] = {"mask": encode_array(
        np.where(covered, np.maximum(np.round(np.clip(mask, 0, 1) * 255), 1), 0).astype(np.uint8), True)}
    if normal is not None:
        wire["normal"] = encode_array(np.where(covered[..., None], _octahedral_encode(normal), 0).astype(np.uint16),
                                      True)
    if depth is not None:
        hits = depth[covered]
        near, far = (float(hits.min()), float(hits.max())) if hits.size else (0.0, 0.0)
        scale = 65535.0 / (far - near) if far > near else 0.0
        q = np.where(covered, np.round((depth.astype(np.float64) - near) * scale), 0)
        wire["depth"] = encode_array(q.astype(np.uint16), True)
        wire["depth_range"] = [near, far]
    if flow is not None:
        wire["flow"] = encode_array(np.clip(flow, -FLOW_CLIP, FLOW_CLIP).astype(np.float16), True)
    return wire


def decode_view_buffers(wire: Any, limits: Limits) -> dict[str, np.ndarray]:
    """The inverse of :func:`encode_view_buffers`: float32 buffers (mask, and what was sent of
    normal, depth, flow), within the tolerances in the module docstring; 0 where the mask is 0."""
    r = _Reader(wire, "buffers")
    mask_u8 = decode_array(r._raw("mask", True), "buffers.mask", limits, ("uint8",), (None, None))
    h, w = mask_u8.shape
    covered = mask_u8 > 0
    out = {"mask": mask_u8.astype(np.float32) / 255}
    code = r._raw("normal", False)
    if code is not None:
        n = _octahedral_decode(decode_array(code, "buffers.normal", limits, ("uint16",), (h, w, 2)))
        out["normal"] = np.where(covered[..., None], n, 0).astype(np.float32)
    q = r._raw("depth", False)
    near_far = r.vec("depth_range", 2, required=q is not None)
    if q is not None:
        q = decode_array(q, "buffers.depth", limits, ("uint16",), (h, w))
        near, far = near_far
        if far < near:
            raise ProtocolError("buffers: depth_range must be [near, far] with near <= far")
        out["depth"] = np.where(covered, near + q.astype(np.float64) * ((far - near) / 65535), 0).astype(np.float32)
    fl = r._raw("flow", False)
    if fl is not None:
        out["flow"] = decode_array(fl, "buffers.flow", limits, ("float16",), (h, w, 2)).astype(np.float32)
    r.done()
    return out


# ---------------------------------------------------------------------------------------------
# messages


class Message:
    """Base of the typed messages: ``to_wire()`` gives a msgpack-ready map, ``from_wire()`` validates one."""

    TYPE: ClassVar[str]

    def to_wire(self) -> dict:
        raise NotImplementedError

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "Message":
        raise NotImplementedError


def _drop_none(d: dict) -> dict:
    return {k: v for k, v in d.items() if v is not None}


@dataclass(frozen=True)
class ViewSettings:
    """A view session's settings. In ``open`` and ``settings`` messages every field is optional
    (absent: unchanged, or the default here).

    Attributes:
        mode: ``full``, ``sr``, ``bilinear``, ``buffers``, ``focus`` or ``reconstruct``
            (module docstring).
        width, height: output image size; for every mode but ``full`` and ``reconstruct`` a
            multiple of the network's upscale factor (``ready`` announces it).
        ao_samples: AO rays per pixel of full-resolution renders (``full``, inside ``focus``;
            0 = no AO); in ``reconstruct`` the AO rays per hit the network gets, 0 to its bound
            (0: it infers AO).
        ao_radius: AO ray length in world units.
        encoding, quality: image coding of shaded frames; quality 1-100 for jpeg/webp.
        refine: send one refined frame (full resolution, ``refine_ao_samples``) once the
            camera and settings were still for ``refine_after_s``.
        focus_blend_px: width of the blend at the focus region's border, full-res pixels.
        channel: ``shaded``, or a buffer shown in false color (:mod:`isosr_server.channels`).
    """

    mode: str = "sr"
    width: int = 640
    height: int = 480
    ao_samples: int = 0
    ao_radius: float = 0.05
    encoding: str = "jpeg"
    quality: int = 85
    refine: bool = True
    refine_after_s: float = 0.5
    refine_ao_samples: int = 64
    focus_blend_px: int = 4
    channel: str = "shaded"

    @staticmethod
    def read_update(d: Any, limits: Limits, where: str = "settings") -> dict:
        """Validate a partial settings map; returns the fields present (for ``dataclasses.replace``)."""
        r = _Reader(d, where)
        update = {
            "mode": r.choice("mode", MODES),
            "width": r.int("width", 1, limits.max_side),
            "height": r.int("height", 1, limits.max_side),
            "ao_samples": r.int("ao_samples", 0, limits.max_ao_samples),
            "ao_radius": r.float("ao_radius", 0.0, 1.0, open_lo=True),
            "encoding": r.choice("encoding", ENCODINGS),
            "quality": r.int("quality", 1, 100),
            "refine": r.bool("refine"),
            "refine_after_s": r.float("refine_after_s", 0.0, 3600.0),
            "refine_ao_samples": r.int("refine_ao_samples", 0, limits.max_ao_samples),
            "focus_blend_px": r.int("focus_blend_px", 0, 256),
            "channel": r.choice("channel", CHANNELS),
        }
        r.done()
        return _drop_none(update)

    def updated(self, update: dict, limits: Limits) -> "ViewSettings":
        """These settings with ``update`` (from :meth:`read_update`) applied and the size checked."""
        new = replace(self, **update)
        limits.check_size(new.width, new.height)
        return new


@dataclass(frozen=True)
class CameraMsg(Message):
    """A camera: look-at (``eye``, ``target``, ``up``, default +y) or orbit (``yaw``, ``pitch``,
    ``distance`` around ``target``, degrees, world +y up, as ``isosr_render.orbit``); ``fov_y`` in degrees."""

    TYPE: ClassVar[str] = "camera"
    eye: tuple[float, float, float] | None = None
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] | None = None
    yaw: float | None = None
    pitch: float | None = None
    distance: float | None = None
    fov_y: float = 40.0
    seq: int | None = None

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "seq": self.seq, "eye": _list(self.eye), "target": list(self.target),
                           "up": _list(self.up), "yaw": self.yaw, "pitch": self.pitch, "distance": self.distance,
                           "fov_y": self.fov_y})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits, where: str = "camera") -> "CameraMsg":
        r = _Reader(d, where)
        r.choice("type", (cls.TYPE,))
        msg = cls(eye=r.vec("eye", 3), target=r.vec("target", 3) or (0.0, 0.0, 0.0),
                  up=r.vec("up", 3), yaw=r.float("yaw", -1e6, 1e6),
                  pitch=r.float("pitch", -89.9, 89.9), distance=r.float("distance", 1e-6, 1e6),
                  fov_y=r.float("fov_y", 1.0, 170.0, default=40.0), seq=_seq(r))
        r.done()
        orbit = (msg.yaw, msg.pitch, msg.distance)
        if msg.eye is None and None in orbit:
            raise ProtocolError(f"{where}: give eye (look-at) or yaw, pitch and distance (orbit)")
        if msg.eye is not None and any(v is not None for v in orbit):
            raise ProtocolError(f"{where}: give either eye or yaw/pitch/distance, not both")
        if msg.eye is None and msg.up is not None:
            raise ProtocolError(f"{where}: an orbit camera has world +y up; up is for look-at cameras (eye)")
        if msg.eye is not None:
            forward, up = np.subtract(msg.target, msg.eye), msg.look_up()
            if np.linalg.norm(forward) < 1e-9:
                raise ProtocolError(f"{where}: eye and target coincide")
            # <=: a zero up gives 0 <= 0 (isosr_render.Camera's strict < lets it through to a NaN basis).
            if np.linalg.norm(np.cross(forward, up)) <= 1e-6 * np.linalg.norm(forward) * np.linalg.norm(up):
                raise ProtocolError(f"{where}: up is zero or parallel to the viewing direction")
        return msg

    def look_up(self) -> tuple[float, float, float]:
        """The look-at camera's up direction."""
        return (0.0, 1.0, 0.0) if self.up is None else self.up


def _list(v):
    return None if v is None else list(v)


@dataclass(frozen=True)
class OpenMsg(Message):
    """Client -> server, first message of a view session."""

    TYPE: ClassVar[str] = "open"
    volume: str
    settings: dict = field(default_factory=dict)  # a partial ViewSettings update
    camera: CameraMsg | None = None
    iso: float | None = None  # data units unless iso_normalized; None: the volume's suggested iso
    iso_normalized: bool = False
    version: int = PROTOCOL_VERSION

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "version": self.version, "volume": self.volume,
                           "settings": self.settings, "camera": None if self.camera is None else self.camera.to_wire(),
                           "iso": self.iso, "iso_normalized": self.iso_normalized})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "OpenMsg":
        r = _Reader(d, "open")
        r.choice("type", (cls.TYPE,))
        version = _version(r, "open")
        camera = r.map("camera")
        msg = cls(volume=r.str("volume", VOLUME_NAME, required=True),
                  settings=ViewSettings.read_update(r.map("settings") or {}, limits, "open.settings"),
                  camera=None if camera is None else CameraMsg.from_wire(camera, limits, "open.camera"),
                  iso=r.float("iso"), iso_normalized=r.bool("iso_normalized", False), version=version)
        r.done()
        return msg


# Volume names: a catalog name or a procedural spec; never a path.
VOLUME_NAME = re.compile(r"^(proc:[a-z]+(:\d{1,9})?(@\d{1,4})?|[A-Za-z0-9_][A-Za-z0-9_.-]{0,127})$")


@dataclass(frozen=True)
class IsoMsg(Message):
    """Client -> server: a new iso-value (data units unless ``normalized``)."""

    TYPE: ClassVar[str] = "iso"
    value: float
    normalized: bool = False
    seq: int | None = None

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "seq": self.seq, "value": self.value, "normalized": self.normalized})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "IsoMsg":
        r = _Reader(d, "iso")
        r.choice("type", (cls.TYPE,))
        msg = cls(value=r.float("value", required=True), normalized=r.bool("normalized", False), seq=_seq(r))
        r.done()
        return msg


@dataclass(frozen=True)
class SettingsMsg(Message):
    """Client -> server: a partial settings update (see `ViewSettings`)."""

    TYPE: ClassVar[str] = "settings"
    settings: dict
    seq: int | None = None

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "seq": self.seq, "settings": self.settings})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "SettingsMsg":
        r = _Reader(d, "settings message")
        r.choice("type", (cls.TYPE,))
        msg = cls(settings=ViewSettings.read_update(r.map("settings", required=True), limits), seq=_seq(r))
        r.done()
        return msg


@dataclass(frozen=True)
class FocusMsg(Message):
    """Client -> server: the focus region in output pixels (x right, y down): a circle
    (``center``, ``radius``), a box (``box`` = x0, y0, x1, y1) or ``none``."""

    TYPE: ClassVar[str] = "focus"
    shape: str = "none"
    center: tuple[float, float] | None = None
    radius: float | None = None
    box: tuple[float, float, float, float] | None = None
    seq: int | None = None

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "seq": self.seq, "shape": self.shape, "center": _list(self.center),
                           "radius": self.radius, "box": _list(self.box)})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "FocusMsg":
        r = _Reader(d, "focus")
        r.choice("type", (cls.TYPE,))
        msg = cls(shape=r.choice("shape", FOCUS_SHAPES, required=True), center=r.vec("center", 2),
                  radius=r.float("radius", 0.0, MAX_ABS_FLOAT), box=r.vec("box", 4), seq=_seq(r))
        r.done()
        given = {"center": msg.center is not None, "radius": msg.radius is not None, "box": msg.box is not None}
        needed = {"none": set(), "circle": {"center", "radius"}, "box": {"box"}}[msg.shape]
        if {k for k, v in given.items() if v} != needed:
            raise ProtocolError(f"focus: a {msg.shape} region takes exactly {sorted(needed) or 'no fields'}")
        if msg.box is not None and not (msg.box[0] < msg.box[2] and msg.box[1] < msg.box[3]):
            raise ProtocolError("focus: box must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1")
        return msg


@dataclass(frozen=True)
class ReceivedMsg(Message):
    """Client -> server: the client has taken frame ``frame`` (the frame's ``seq``) and every
    earlier one off the wire: credit for more (flow control, module docstring)."""

    TYPE: ClassVar[str] = "received"
    frame: int

    def to_wire(self) -> dict:
        return {"type": self.TYPE, "frame": self.frame}

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "ReceivedMsg":
        r = _Reader(d, "received")
        r.choice("type", (cls.TYPE,))
        msg = cls(frame=r.int("frame", 0, MAX_SEQ, required=True))
        r.done()
        return msg


@dataclass(frozen=True)
class ReadyMsg(Message):
    """Server -> client, the answer to ``open``."""

    TYPE: ClassVar[str] = "ready"
    session: str
    volume: dict  # name, shape, value_range, iso (suggested, data units), iso_normalized
    settings: dict  # the effective ViewSettings
    upscale_factor: int
    limits: dict
    version: int = PROTOCOL_VERSION

    def to_wire(self) -> dict:
        return {"type": self.TYPE, "version": self.version, "session": self.session, "volume": self.volume,
                "settings": self.settings, "upscale_factor": self.upscale_factor, "limits": self.limits}

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "ReadyMsg":
        r = _Reader(d, "ready")
        r.choice("type", (cls.TYPE,))
        msg = cls(version=r.int("version", 0, 2**31, required=True), session=r.str("session", SESSION_ID, required=True),
                  volume=r.map("volume", required=True), settings=r.map("settings", required=True),
                  upscale_factor=r.int("upscale_factor", 1, 64, required=True), limits=r.map("limits", required=True))
        r.done()
        return msg

    def view_settings(self) -> ViewSettings:
        return ViewSettings(**self.settings)


STAGES = ("render", "network", "shading", "encode", "total")


def _read_times(r: _Reader) -> dict[str, float]:
    times = r.map("times", required=True)
    t = _Reader(times, "times")
    out = {s: t.float(s, 0.0, 1e9) for s in STAGES}
    t.done()
    return _drop_none(out)


@dataclass(frozen=True)
class FrameMsg(Message):
    """Server -> client: one view frame.

    Attributes:
        seq: the server's frame number in this session (from 0).
        ack: the highest client ``seq`` this frame includes (-1: none yet).
        mode: the mode that made it (``full`` for refined frames).
        width, height: the output size (buffers travel at low resolution: width / factor).
        encoding: ``jpeg``, ``png``, ``webp`` (``image`` holds the bytes) or ``buffers``.
        image: the encoded image.
        buffers: the low-res buffers in the buffers-mode coding (:func:`decode_view_buffers`).
        prev_seq: ``buffers`` only: the frame whose camera the flow refers to (-1: no flow,
            a cut: reset the recurrent state).
        times: server milliseconds per stage (render, network, shading, encode, total).
        nbytes: payload bytes (image, or the buffers' data).
        refined: the still-camera refined frame.
        legend: channel view only: ``channel, lo, hi, unit, colormap[, stops]`` of the false colors.
    """

    TYPE: ClassVar[str] = "frame"
    seq: int
    ack: int
    mode: str
    width: int
    height: int
    encoding: str
    times: dict
    nbytes: int
    refined: bool = False
    image: bytes | None = None
    buffers: dict | None = None
    prev_seq: int = -1
    legend: dict | None = None

    def to_wire(self) -> dict:
        return _drop_none({"type": self.TYPE, "seq": self.seq, "ack": self.ack, "mode": self.mode, "width": self.width,
                           "height": self.height, "encoding": self.encoding, "times": self.times,
                           "bytes": self.nbytes, "refined": self.refined, "image": self.image,
                           "buffers": self.buffers, "prev_seq": self.prev_seq, "legend": self.legend})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "FrameMsg":
        r = _Reader(d, "frame")
        r.choice("type", (cls.TYPE,))
        msg = cls(seq=r.int("seq", 0, MAX_SEQ, required=True), ack=r.int("ack", -1, MAX_SEQ, required=True),
                  mode=r.choice("mode", MODES, required=True), width=r.int("width", 1, limits.max_side, required=True),
                  height=r.int("height", 1, limits.max_side, required=True),
                  encoding=r.choice("encoding", ENCODINGS + ("buffers",), required=True), times=_read_times(r),
                  nbytes=r.int("bytes", 0, 2**40, required=True), refined=r.bool("refined", False),
                  image=r._raw("image", False), buffers=r.map("buffers"), prev_seq=r.int("prev_seq", -1, MAX_SEQ, -1),
                  legend=r.map("legend"))
        r.done()
        if (msg.encoding == "buffers") != (msg.buffers is not None) or (msg.image is None) == (msg.buffers is None):
            raise ProtocolError("frame: an encoded frame carries image bytes, a buffers frame carries buffers")
        if msg.image is not None and not isinstance(msg.image, bytes):
            raise ProtocolError("frame: image must be bytes")
        return msg


@dataclass(frozen=True)
class ErrorMsg(Message):
    """Server -> client before a close (or as an HTTP body): the close code / status and why."""

    TYPE: ClassVar[str] = "error"
    code: int
    reason: str

    def to_wire(self) -> dict:
        return {"type": self.TYPE, "code": self.code, "reason": self.reason}

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "ErrorMsg":
        r = _Reader(d, "error")
        r.choice("type", (cls.TYPE,))
        msg = cls(code=r.int("code", 0, 9999, required=True), reason=r._raw("reason", True))
        r.done()
        if not isinstance(msg.reason, str):
            raise ProtocolError("error: reason must be a string")
        return msg


LOWRES_INPUTS = ("mask", "normal", "depth", "flow")
# Ranges of the low-res inputs (conventions: coverage, unit normals, depth in world units where the
# volume's box has side 1, flow in pixels). Far beyond them the network's activations overflow to
# NaN (depth 3e38 did, in fp32), so they are refused with a reason instead.
MAX_DEPTH = 1e6
LOWRES_BOUNDS = {"mask": (0.0, 1.0), "normal": (-1.001, 1.001), "depth": (0.0, MAX_DEPTH),
                 "flow": (-FLOW_CLIP, FLOW_CLIP)}
HIGHRES_OUTPUTS = ("mask", "normal", "depth", "ao")


@dataclass(frozen=True)
class UpscaleRequest(Message):
    """Client -> server: one low-res frame to upscale (``POST /v1/upscale``, ``WS /v1/upscale/stream``).

    Attributes:
        mask, normal, depth, flow: low-res buffers (float16/float32 numpy) in the conventions of
            :mod:`isosr_render.conventions`, within ``LOWRES_BOUNDS``; flow optional (without it
            the recurrent state resets).
        output: ``buffers`` (float32 high-res mask, normal, depth, ao) or ``png``/``jpeg``/``webp``
            (the shaded image).
        quality: jpeg/webp quality 1-100.
        session: POST only: an id whose consecutive frames keep the recurrent state.
        reset: forget the recurrent state before this frame.

    Shape:
        mask, depth: (h, w). normal: (h, w, 3). flow: (h, w, 2).
    """

    TYPE: ClassVar[str] = "upscale"
    mask: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    flow: np.ndarray | None = None
    output: str = "buffers"
    quality: int = 85
    session: str | None = None
    reset: bool = False
    version: int = PROTOCOL_VERSION

    def to_wire(self) -> dict:
        arrays = {n: encode_array(getattr(self, n)) for n in LOWRES_INPUTS if getattr(self, n) is not None}
        return _drop_none({"type": self.TYPE, "version": self.version, **arrays, "output": self.output,
                           "quality": self.quality, "session": self.session, "reset": self.reset})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "UpscaleRequest":
        r = _Reader(d, "upscale")
        r.choice("type", (cls.TYPE,))
        version = _version(r, "upscale")
        floats, b = ("float16", "float32"), LOWRES_BOUNDS
        mask = decode_array(r._raw("mask", True), "mask", limits, floats, (None, None), b["mask"])
        h, w = mask.shape
        normal = decode_array(r._raw("normal", True), "normal", limits, floats, (h, w, 3), b["normal"])
        depth = decode_array(r._raw("depth", True), "depth", limits, floats, (h, w), b["depth"])
        flow = r._raw("flow", False)
        flow = None if flow is None else decode_array(flow, "flow", limits, floats, (h, w, 2), b["flow"])
        msg = cls(mask=mask, normal=normal, depth=depth, flow=flow,
                  output=r.choice("output", UPSCALE_OUTPUTS, "buffers"), quality=r.int("quality", 1, 100, 85),
                  session=r.str("session", SESSION_ID), reset=r.bool("reset", False), version=version)
        r.done()
        return msg


@dataclass(frozen=True)
class UpscaleResponse(Message):
    """Server -> client: the upscaled frame (``buffers``: float32 mask, normal, depth, ao) or image."""

    TYPE: ClassVar[str] = "upscaled"
    seq: int
    width: int
    height: int
    output: str
    times: dict
    nbytes: int
    buffers: dict[str, np.ndarray] | None = None
    image: bytes | None = None

    def to_wire(self) -> dict:
        buffers = None if self.buffers is None else {n: encode_array(a) for n, a in self.buffers.items()}
        return _drop_none({"type": self.TYPE, "seq": self.seq, "width": self.width, "height": self.height,
                           "output": self.output, "times": self.times, "bytes": self.nbytes, "buffers": buffers,
                           "image": self.image})

    @classmethod
    def from_wire(cls, d: dict, limits: Limits) -> "UpscaleResponse":
        r = _Reader(d, "upscaled")
        r.choice("type", (cls.TYPE,))
        width = r.int("width", 1, limits.max_side, required=True)
        height = r.int("height", 1, limits.max_side, required=True)
        buffers = r.map("buffers")
        if buffers is not None:
            b = _Reader(buffers, "upscaled.buffers")
            shapes = {"mask": (height, width), "normal": (height, width, 3), "depth": (height, width),
                      "ao": (height, width)}
            buffers = {n: decode_array(b._raw(n, True), n, limits, ("float32",), s) for n, s in shapes.items()}
            b.done()
        msg = cls(seq=r.int("seq", 0, MAX_SEQ, required=True), width=width, height=height,
                  output=r.choice("output", UPSCALE_OUTPUTS, required=True), times=_read_times(r),
                  nbytes=r.int("bytes", 0, 2**40, required=True), buffers=buffers, image=r._raw("image", False))
        r.done()
        if (msg.output == "buffers") != (buffers is not None) or (msg.image is None) == (buffers is None):
            raise ProtocolError("upscaled: buffers output carries buffers, an image output carries image bytes")
        return msg


CLIENT_VIEW_MESSAGES: dict[str, type[Message]] = {m.TYPE: m for m in (CameraMsg, IsoMsg, SettingsMsg, FocusMsg,
                                                                        ReceivedMsg)}
SERVER_VIEW_MESSAGES: dict[str, type[Message]] = {m.TYPE: m for m in (ReadyMsg, FrameMsg, ErrorMsg)}


def parse(data: bytes, limits: Limits, expected: dict[str, type[Message]] | tuple[type[Message], ...]) -> Message:
    """Unpack and validate one message whose ``type`` is among ``expected``.

    Args:
        data: the msgpack bytes.
        limits: size bounds (``max_message_bytes`` bounds ``data``).
        expected: the message classes allowed here (a tuple, or a TYPE -> class map).

    Raises:
        ProtocolError: what is wrong, with the close code and HTTP status to answer.
    """
    if isinstance(expected, tuple):
        expected = {m.TYPE: m for m in expected}
    d = unpack(data, limits.max_message_bytes)
    kind = d.get("type")
    if not isinstance(kind, str) or kind not in expected:
        raise ProtocolError(f"message type must be one of {', '.join(expected)}, got {kind!r}"[:200])
    return expected[kind].from_wire(d, limits)


def limits_to_wire(limits: Limits) -> dict:
    return asdict(limits)
