"""The wire protocol of `isosr serve` (version 6): the one module the server and every client share.

Every message is declared once below as a frozen `msgspec.Struct`: its fields, their types and
their static bounds. Imports only numpy, msgspec, the standard library and the array codec
(:mod:`isosr_server.codecs.arrays`): clients need neither FastAPI nor torch.

Coding
    Every message is one msgpack map (never pickle) whose ``type`` names it. :func:`parse` takes
    one: bounded in size first, then decoded and validated by msgspec against the message
    classes allowed at that point (unknown fields, wrong types, values out of bounds, NaN and
    Inf, extension types and trailing bytes are errors, each reason naming the field, e.g.
    ``Expected `int` >= 1 - at `$.settings.width```), then checked against the receiver's
    `Limits` (:meth:`Message.check`). :func:`encode` writes one. Arrays travel as
    ``{dtype, shape, data[, zlib]}`` (:mod:`isosr_server.codecs.arrays`).

View session (``WS /v1/view``)
    client -> ``open`` (version, volume name, settings incl. mode and size, optional camera
    and iso); server -> ``ready`` (session id, volume summary, effective settings, upscale
    factor, the reconstruction's AO ray bound, limits, the encodings it can make) and a first
    frame. Then the client sends ``camera``, ``iso``, ``settings`` and ``focus`` at any rate;
    each carries an optional ``seq``. The server keeps only the newest state (latest wins) and answers ``frame``
    messages whose ``ack`` is the highest ``seq`` they include and whose ``method`` names the
    frame method that made them; an ``auto`` frame's ``choice`` says what the policy expects of
    that method (its frame time against the session's budget, its PSNR). A still camera gets one
    extra frame with ``refined: true``.
    Frames carry the volume's device memory and paging (``device``) when it changed.
    Bad input ends the session with an ``error`` message and a close code (``CLOSE_*``);
    non-fatal news (an encoding the server cannot make, so it sends jpeg) comes as ``notice``.
    A ``settings`` message whose clip, coloring or surfaces are bad (`NOTICED_SETTINGS`: 7 planes, a zero
    normal, NaN, an unknown colour map, a field of another grid, 5 surfaces) is refused whole with a ``notice``
    naming the field; the settings stay as they were, the next frame (of them) acknowledges its
    ``seq``, and the session goes on.
    ``pick`` asks what lies under a pixel of the current view; ``picked`` answers it (the
    isosurface point, its voxel, physical position and value, and which of several surfaces) between frames.

Encodings (``settings.encoding``)
    Images (`IMAGE_ENCODINGS`: jpeg, png, webp): each frame stands alone. Video
    (`VIDEO_ENCODINGS`: h264, vp9, av1; ``ready.encoders`` says which this server can make):
    a frame's ``image`` is one access unit of the session's stream (h264 Annex B with SPS/PPS
    in every keyframe; vp9 a raw frame; av1 a temporal unit of low-overhead OBUs), ``codec``
    its WebCodecs codec string, ``keyframe`` whether it decodes alone. The stream is coded at
    even width and height, av1 at sides of at least 64 (padded by repeating the last column /
    row): the client shows the top-left ``width`` x ``height``. Keyframes come on start (a new session,
    e.g. after a reconnect), on a new size or encoding, and when the client asks (``keyframe``,
    e.g. after a decoder error). A still camera's refined frame goes out as a lossless ``png``
    frame; the next moving frame is a video keyframe. The bitrate follows ``bitrate_kbps`` (the
    client's cap), or with 0 the link's throughput the server estimates from ``received``; the
    frame rate steps down before the quality gets too low. An encoding the server cannot make
    falls back to jpeg (``ready`` and the frames say so) with a ``notice`` saying why.

View modes (``settings.mode``)
    The server's frame methods that a viewer may ask for by name, with ``auto`` (the server's
    budget policy chooses the method per session) and ``focus`` (``network``, with a ``full``
    render inside the focus region). ``ready`` (and ``GET /v1/modes``) lists them as
    :class:`ModeInfo`: each mode's label, the settings it reads with their bounds, whether it
    makes a shaded image, upscales, or follows a focus point; a mode that is not listed is
    refused naming those that are. The usual ones:
    full         ray cast at the output size, ``ao_rays`` AO rays per hit (0: none), ``spp``
                 rays per pixel.
    atrous, svgf, oidn   as ``full``, the AO of few rays filtered or denoised.
    reconstruct  ray cast at the output size with few AO rays per hit, reconstructed by a
                 network to converged-looking AO and antialiased edges.
    network      ray cast at 1/factor of the output size, upscaled by the network (which infers
                 AO), shaded.
    upscale      as ``network`` with classic ``interpolation`` (nearest, bilinear, bicubic; no AO).
    buffers      the low-res buffers themselves (:mod:`isosr_server.codecs.buffers`): the client
                 upscales.
    ``network``, ``focus`` and ``reconstruct`` carry a recurrent state per session; a new iso, size or
    mode (``reconstruct``: or ``ao_rays``) starts it afresh.

Time series
    A volume with a time axis (:mod:`isosr_render.series`) lists its ``steps`` (``ready.volume``;
    1 for others); ``settings.t`` picks the step shown (0 to ``steps - 1``; beyond is refused),
    and each frame says the step it shows (``t``). A client plays a series by sending ``t`` at
    its rate. A step change is a cut: recurrent modes start afresh on the new step. A step that
    cannot be read (a file gone mid-playback) leaves the view on the last step shown, with a
    ``notice`` naming the step and why; the session goes on.

Flow control
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
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable, Mapping
from functools import lru_cache
from typing import Annotated, Any, ClassVar, Literal, Union

import msgspec
import numpy as np
from msgspec import UNSET, Meta, UnsetType

from isosr_render.clip import CAP_MODES, MAX_PLANES, Clip
from isosr_render.coloring import COLORMAPS, Coloring
from isosr_render.conventions import AO_RADIUS, MATERIAL_RGB
from isosr_render.surfaces import MAX_SURFACES, Surface, Surfaces
from isosr_server.codecs.arrays import ArrayTooBig, WireArray, decode_array, encode_array

# 12: frame.choice (what auto expects of the method it chose);
# 11: picked.surface (which of several surfaces a pick hit);
# 10: several isosurfaces (settings.surfaces);
# 9: frame.batch (the frames made together on the device);
# 8: colour by a field (settings.coloring; a shaded frame's legend);
# 7: time series (volume.steps, settings.t, frame.t);
# 6: clip planes, a crop box and caps (settings.clip);
# 5: modes named by the server (ready.modes), ready's limits on messages and acknowledgements;
# 3: the v3 vocabulary (modes auto/network/upscale/..., ao_rays, spp, interpolation, frame methods);
# 2 (acknowledged frames, flow control) and earlier are refused with a reason.
PROTOCOL_VERSION = 12

# Largest magnitude of any float field (camera coordinates, iso, ...): beyond it is hostile input.
MAX_ABS_FLOAT = 1e9
MAX_SEQ = 2**53
# Flow, in the buffers coding and in upscale requests, lies within +-FLOW_CLIP pixels (float16 ends at 65504).
FLOW_CLIP = 60000.0

MAX_VIEW_SPP = 4  # rays per pixel a view session may ask for
MAX_STEPS = 2**24  # time steps of a series, the static bound of ``t`` (a session checks its volume's count)
Step = Annotated[int, Meta(ge=0, lt=MAX_STEPS)]
# A view mode's name: the server lists its modes (``ready.modes``) and refuses others naming them.
ModeName = Annotated[str, Meta(pattern="^[a-z][a-z0-9_]{0,31}$")]
# What a shaded-mode frame shows: the shaded image or one buffer in false color (isosr_server.channels).
CHANNELS = ("shaded", "mask", "normal", "depth", "ao", "flow")
IMAGE_ENCODINGS = ("jpeg", "png", "webp")
VIDEO_ENCODINGS = ("h264", "vp9", "av1")
# A view session's encodings; upscale outputs are images.
ENCODINGS = IMAGE_ENCODINGS + VIDEO_ENCODINGS
INTERPOLATIONS = ("nearest", "bilinear", "bicubic")
UPSCALE_OUTPUTS = ("buffers",) + IMAGE_ENCODINGS
FOCUS_SHAPES = ("none", "circle", "box")
# Stages a frame's ``times`` may name (server milliseconds; each optional).
STAGES = ("render", "filter", "network", "shading", "encode", "total")
SESSION_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
# Volume names: a catalog name or a procedural spec; never a path.
VOLUME_NAME = re.compile(r"^(proc:[a-z]+(:\d{1,9})?(@\d{1,4})?|[A-Za-z0-9_][A-Za-z0-9_.-]{0,127})$")

# Authentication, when the server has a token: HTTP requests send ``Authorization: Bearer TOKEN``
# or the header below; WebSocket clients may instead offer the subprotocols ``SUBPROTOCOL`` and
# ``TOKEN_SUBPROTOCOL_PREFIX + TOKEN`` (browsers cannot set headers; tokens stay out of URLs and logs).
TOKEN_HEADER = "x-isosr-token"
SUBPROTOCOL = "isosr.v1"
TOKEN_SUBPROTOCOL_PREFIX = "isosr-token."
MSGPACK_MEDIA_TYPE = "application/msgpack"
# Behind replicas (`isosr serve --replicas N`) every HTTP answer and WebSocket handshake names its replica;
# an upscale session's requests carry its id in SESSION_HEADER (Ray Serve routes on it: its
# RAY_SERVE_SESSION_ID_HEADER_KEY default), and the first answer on a replica that did not hold the
# session's recurrent state says RESTARTED_HEADER: 1.
REPLICA_HEADER = "x-isosr-replica"
SESSION_HEADER = "x-session-id"
RESTARTED_HEADER = "x-isosr-session-restarted"

# WebSocket close codes (RFC 6455 where one fits, 4xxx mirror HTTP statuses).
CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001  # server shutting down
CLOSE_BAD_MESSAGE = 1007  # malformed msgpack, wrong field, dtype, shape, NaN/Inf
CLOSE_POLICY = 1008  # message rate above the limit; data the volume refuses (an iso outside its value range)
CLOSE_TOO_BIG = 1009  # message above max_message_bytes, image above the size limits
CLOSE_INTERNAL = 1011  # a server fault (logged at ERROR on the server)
CLOSE_UNAUTHORIZED = 4401  # missing or wrong token
CLOSE_NOT_FOUND = 4404  # unknown volume
CLOSE_IDLE = 4408  # no message for idle_timeout_s (or no open for open_timeout_s)
CLOSE_TOO_MANY = 4429  # session limit reached; try later

# Field types with their static bounds.
Finite = Annotated[float, Meta(ge=-MAX_ABS_FLOAT, le=MAX_ABS_FLOAT)]
Vec2 = tuple[Finite, Finite]
Vec3 = tuple[Finite, Finite, Finite]
Unit = Annotated[float, Meta(ge=0.0, le=1.0)]
Seq = Annotated[int, Meta(ge=0, le=MAX_SEQ)]
Version = Annotated[int, Meta(ge=0, le=2**31)]
Side = Annotated[int, Meta(ge=1)]
Millis = Annotated[float, Meta(ge=0.0, le=MAX_ABS_FLOAT)]
Times = dict[Literal[STAGES], Millis]
SessionId = Annotated[str, Meta(pattern=SESSION_ID.pattern)]
Factor = Annotated[int, Meta(ge=1, le=64)]


class ProtocolError(ValueError):
    """A client's message broke the protocol: what is wrong, the close code and HTTP status to answer."""

    def __init__(self, reason: str, close_code: int = CLOSE_BAD_MESSAGE, http_status: int = 400):
        super().__init__(reason)
        self.reason = reason
        self.close_code = close_code
        self.http_status = http_status


# The settings a live view refuses with a notice rather than an end: what users edit while exploring.
NOTICED_SETTINGS = ("clip", "coloring", "surfaces")
_NOTICED_PATH = re.compile(r"`\$\.settings\.(" + "|".join(NOTICED_SETTINGS) + r")\b")


class SettingRefused(ProtocolError):
    """A ``settings`` message refused for one of `NOTICED_SETTINGS`: a view session sends the reason
    as a ``notice`` and keeps its settings (elsewhere it is the `ProtocolError` it derives from);
    ``seq``: the refused message's, where it had a valid one."""

    def __init__(self, reason: str, close_code: int = CLOSE_BAD_MESSAGE, http_status: int = 400,
                 seq: int | None = None):
        super().__init__(reason, close_code, http_status)
        self.seq = seq


class _SeqOnly(msgspec.Struct):
    """A message read for its ``seq`` alone (a refused one's, which the session acknowledges)."""

    seq: Seq | None = None


def _seq_of(data: bytes) -> int | None:
    """The ``seq`` of a message that failed validation, if it has a valid one."""
    try:
        return msgspec.msgpack.decode(data, type=_SeqOnly, ext_hook=_no_ext).seq
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
        return None


class Limits(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Bounds the server enforces (and announces in ``ready``); all configurable by `isosr serve`.

    Attributes:
        max_message_bytes: largest message a client may send.
        max_side: largest output image side in pixels.
        max_pixels: largest output image area in pixels.
        max_fps: most frames a view session gets per second.
        max_messages_per_s: most messages a client may send per second (averaged over 1 s).
        max_sessions: most concurrent view sessions; the same again for upscale sessions.
        idle_timeout_s: a session without messages for this long is closed / expired.
        max_ao_rays: most AO rays per hit a client may ask for (refined frames included).
        max_unacked_frames: most frames a view session has sent (or is making) that its client
            has not acknowledged with ``received``; the server renders the next one only below it.
        open_timeout_s: a WebSocket that sends no ``open`` within this is closed (CLOSE_IDLE)
            and holds no session slot.
        max_sessions_per_client: most view sessions of one client address.
        body_timeout_s: an HTTP body must arrive within this.
        max_connections: most open connections.
        max_connections_per_client: most open connections of one client address.
        max_upscale_bytes: most memory the upscale sessions may hold together.
        max_bitrate_kbps: the highest video bitrate a view session may ask for (``bitrate_kbps``),
            and the ceiling of the server's own choice.
        max_first_message_bytes: largest WebSocket frame or message of a view session before its
            ``open`` (:mod:`isosr_server.ws_transport`).
        ack_timeout_s: a view session whose oldest unacknowledged frame went out this long ago is
            closed.
        max_header_bytes, max_header_count: largest HTTP request head in bytes, and most header
            fields (more: 431 and a close; :mod:`isosr_server.transport`).
        header_timeout_s: a request's head must be complete within this of its connection or of
            the previous response.
        max_open_connections: most open connections (fewer where the descriptor limit leaves less
            room); those that sent no complete request yet are closed first to make room.
        max_mesh_jobs: most mesh extractions under way at once, server-wide (more: 429); each runs
            a slab at a time on the device thread, so a view frame waits behind at most this many slabs.
    """

    max_message_bytes: int = 32 * 2**20
    max_side: int = 4096
    max_pixels: int = 3840 * 2160
    max_fps: float = 60.0
    max_messages_per_s: float = 1000.0
    max_sessions: int = 32
    idle_timeout_s: float = 300.0
    max_ao_rays: int = 256
    max_unacked_frames: int = 2
    open_timeout_s: float = 10.0
    max_sessions_per_client: int = 8
    body_timeout_s: float = 30.0
    max_connections: int = 256
    max_connections_per_client: int = 32
    max_upscale_bytes: int = 2 * 2**30
    max_bitrate_kbps: int = 100_000
    max_first_message_bytes: int = 64 * 2**10
    ack_timeout_s: float = 30.0
    max_header_bytes: int = 64 * 2**10
    max_header_count: int = 100
    header_timeout_s: float = 10.0
    max_open_connections: int = 4096
    max_mesh_jobs: int = 1

    def __post_init__(self):
        for f in msgspec.structs.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
                raise ValueError(f"limit {f.name} must be a positive number, got {value!r}")
            if isinstance(f.default, int) and not isinstance(value, int):
                raise ValueError(f"limit {f.name} must be an integer, got {value!r}")

    def check_size(self, width: int, height: int, what: str = "image") -> None:
        """Raise `ProtocolError` (CLOSE_TOO_BIG, HTTP 413) for an image over the size limits."""
        if width > self.max_side or height > self.max_side or width * height > self.max_pixels:
            raise ProtocolError(f"{what} {width}x{height} exceeds the limits (side <= {self.max_side}, "
                                f"pixels <= {self.max_pixels})", CLOSE_TOO_BIG, 413)

    def downscaled(self, factor: int) -> Limits:
        """These limits for a frame that is upscaled ``factor`` times: the largest side and area
        divided by ``factor`` and its square, the rest the same. Parsing an upscale request with
        them refuses the arrays of a frame too big to upscale before they inflate."""
        return msgspec.structs.replace(self, max_side=max(self.max_side // factor, 1),
                                       max_pixels=max(self.max_pixels // factor**2, 1))

    def array_bounds(self) -> tuple[int, int]:
        """The most elements and the longest side a wire array may declare: 4 channels of the largest image."""
        return 4 * self.max_pixels, self.max_side

    def check_rays(self, rays: int, path: str) -> None:
        """Raise `ProtocolError` (CLOSE_BAD_MESSAGE) for more AO rays than ``max_ao_rays``;
        ``path`` names the field (``$.settings.ao_rays``)."""
        if rays > self.max_ao_rays:
            raise ProtocolError(f"Expected `int` <= {self.max_ao_rays} (max_ao_rays) - at `{path}`")


# ---------------------------------------------------------------------------------------------
# settings


class ClipPlane(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A clip plane, world units: it keeps the half-space its (nonzero) normal points into."""

    point: Vec3
    normal: Vec3


class ClipSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Clip planes, a crop box ``(lo, hi)`` and caps, world units, as :class:`isosr_render.clip.Clip`
    checks them (its message names the field: ``clip.planes[0].normal must be a nonzero vector``)."""

    planes: Annotated[tuple[ClipPlane, ...], Meta(max_length=MAX_PLANES)] = ()
    box: tuple[Vec3, Vec3] | None = None
    cap: Literal[CAP_MODES] = "none"

    def __post_init__(self):
        self.clip()

    def clip(self) -> Clip:
        """The renderer's clip."""
        return Clip(tuple((p.point, p.normal) for p in self.planes), self.box, self.cap)


def clip_query(text: str) -> ClipSettings:
    """`ClipSettings` from JSON text (the ``clip`` query parameter of ``GET /v1/volumes/NAME/mesh``, as
    ``settings.clip`` spells it); `ProtocolError` naming the field."""
    try:
        return msgspec.json.decode(text, type=ClipSettings)
    except msgspec.ValidationError as e:
        raise ProtocolError(_short(f"clip: {_relative(e)}")) from None
    except msgspec.DecodeError as e:
        raise ProtocolError(_short(f"clip: not JSON: {e}")) from None


class ColoringSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Colour the surface by ``gradient`` (the volume's gradient magnitude) or by another volume of the
    same grid, named as in ``GET /v1/volumes`` (the server refuses an unknown one or another grid,
    naming both shapes), through a colour map over ``range`` (None: the values' own), as
    :class:`isosr_render.coloring.Coloring` checks them."""

    by: Annotated[str, Meta(pattern=VOLUME_NAME.pattern)]
    colormap: Literal[tuple(COLORMAPS)] = "viridis"
    range: Vec2 | None = None

    def __post_init__(self):
        self.coloring()

    def coloring(self) -> Coloring:
        """The renderer's coloring."""
        return Coloring(self.by, self.colormap, self.range)


class SurfaceSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One of several isosurfaces: its iso-value in data units, its colour (RGB in [0, 1]; default: the
    material's) and opacity (below 1 translucent: the ray goes on to the next surface, two layers composited)."""

    iso: Finite
    color: tuple[Unit, Unit, Unit] = MATERIAL_RGB
    opacity: Unit = 1.0


def surfaces_of(settings: tuple[SurfaceSettings, ...], normalize: Callable[[float], float],
                seq: int | None = None) -> Surfaces | None:
    """The renderer's surfaces of ``settings.surfaces`` (None where empty), their isos through ``normalize`` (a
    volume's ``normalized_iso``), checked by :class:`isosr_render.surfaces.Surfaces`.

    Raises:
        SettingRefused: (of the update ``seq``; CLOSE_POLICY, 422) what ``Surfaces`` refuses (two equal isos),
            naming the field.
    """
    if not settings:
        return None
    try:
        return Surfaces(tuple(Surface(normalize(s.iso), s.color, s.opacity) for s in settings))
    except ValueError as e:
        raise SettingRefused(f"settings.{e}", CLOSE_POLICY, 422, seq) from None


class ViewSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A view session's settings (``ready`` carries them whole; ``open`` and ``settings`` send
    a `SettingsUpdate` of any of them).

    Attributes:
        mode: a view mode (module docstring; ``ready.modes`` lists the server's).
        width, height: output image size; for the low-res modes (network, upscale, buffers,
            focus) a multiple of the network's upscale factor (``ready`` announces it).
        ao_rays: AO rays per hit of full-resolution renders (0 = no AO); in ``reconstruct`` the
            rays the network gets (0: it infers AO; past ``max_recon_ao_rays`` their mean is read
            as that many).
        spp: rays per pixel of full-resolution renders.
        interpolation: ``upscale`` mode's classic upscaling.
        ao_radius: AO ray length in world units.
        encoding, quality: coding of shaded frames (`ENCODINGS`, module docstring); quality 1-100
            for jpeg/webp, and the video codecs' constant quality (capped by the bitrate).
        bitrate_kbps: video only: the client's cap on the bitrate in kbit/s (at most
            ``max_bitrate_kbps``); 0: the server estimates the link from ``received``.
        refine: send one refined frame (full resolution, ``refine_ao_rays``) once the camera and
            settings were still for ``refine_after_s``.
        focus_blend_px: width of the blend at the focus region's border, full-res pixels.
        channel: ``shaded``, or a buffer shown in false color (:mod:`isosr_server.channels`).
        clip: clip planes, crop box and caps of every frame (:class:`ClipSettings`).
        coloring: colour the surface by a field (:class:`ColoringSettings`); None: the material's colour.
            A shaded frame's ``legend`` then names its colour map and range.
        t: a series' time step (module docstring), below ``ready.volume.steps``.
        surfaces: up to 4 isosurfaces shown together (:class:`SurfaceSettings`, distinct isos), each ray
            stopping at the nearest, each in its colour; empty: the session's one iso (``iso``), as before.
            With a translucent one every shaded mode runs its method on both layers and composites them;
            ``buffers`` mode (one layer, unshaded) sends full-resolution renders then (the frame's ``method``
            says so). Not with a coloring, nor on a volume rendered sparse (refused: 422).
    """

    mode: ModeName = "auto"
    width: Side = 640
    height: Side = 480
    ao_rays: Annotated[int, Meta(ge=0)] = 0
    spp: Annotated[int, Meta(ge=1, le=MAX_VIEW_SPP)] = 1
    interpolation: Literal[INTERPOLATIONS] = "bilinear"
    ao_radius: Annotated[float, Meta(gt=0.0, le=1.0)] = AO_RADIUS
    encoding: Literal[ENCODINGS] = "jpeg"
    quality: Annotated[int, Meta(ge=1, le=100)] = 85
    bitrate_kbps: Annotated[int, Meta(ge=0)] = 0
    refine: bool = True
    refine_after_s: Annotated[float, Meta(ge=0.0, le=3600.0)] = 0.5
    refine_ao_rays: Annotated[int, Meta(ge=0)] = 64
    focus_blend_px: Annotated[int, Meta(ge=0, le=256)] = 4
    channel: Literal[CHANNELS] = "shaded"
    clip: ClipSettings = ClipSettings()
    coloring: ColoringSettings | None = None
    t: Step = 0
    surfaces: Annotated[tuple[SurfaceSettings, ...], Meta(max_length=MAX_SURFACES)] = ()

    def updated(self, update: SettingsUpdate | Mapping[str, Any], limits: Limits,
                seq: int | None = None) -> ViewSettings:
        """These settings with ``update`` applied (a `SettingsUpdate`, or a map validated as one),
        checked against ``limits``.

        Raises:
            ProtocolError: an unknown field or a value out of its bounds (CLOSE_BAD_MESSAGE), a
                size over the limits (CLOSE_TOO_BIG).
            SettingRefused: (of the update ``seq``, which its frame acknowledges) surfaces with a coloring.
        """
        if not isinstance(update, SettingsUpdate):
            update = convert(update, SettingsUpdate, "settings")
        update.check(limits)
        new = msgspec.structs.replace(self, **update.given())
        limits.check_size(new.width, new.height)
        if new.surfaces and new.coloring is not None:
            raise SettingRefused("settings.surfaces: several surfaces show their own colours, not with "
                                 "settings.coloring (set one of them to its default)", seq=seq)
        return new


def check_step(t: int, steps: int, volume: str) -> None:
    """`ProtocolError` (CLOSE_POLICY, 422) for a time step ``t`` past a volume's ``steps`` (the
    server checks ``settings.t`` with it, a client before sending)."""
    if t >= steps:
        raise ProtocolError(f"settings.t: no time step {t} in {volume!r}, which has {steps} (0 to {steps - 1})",
                            CLOSE_POLICY, 422)


class _SettingsUpdateBase(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    def given(self) -> dict[str, Any]:
        """The fields this update sets."""
        return {name: v for name in self.__struct_fields__ if (v := getattr(self, name)) is not UNSET}

    def check(self, limits: Limits) -> None:
        """AO ray counts within ``limits.max_ao_rays``, the bitrate within ``max_bitrate_kbps``
        (sizes: `ViewSettings.updated`)."""
        for name in ("ao_rays", "refine_ao_rays"):
            rays = getattr(self, name)
            if rays is not UNSET:
                limits.check_rays(rays, f"$.settings.{name}")
        if self.bitrate_kbps is not UNSET and self.bitrate_kbps > limits.max_bitrate_kbps:
            raise ProtocolError(f"Expected `int` <= {limits.max_bitrate_kbps} (max_bitrate_kbps) - at "
                                f"`$.settings.bitrate_kbps`")


SettingsUpdate = msgspec.defstruct(
    "SettingsUpdate", [(f.name, Union[f.type, UnsetType], UNSET) for f in msgspec.structs.fields(ViewSettings)],
    bases=(_SettingsUpdateBase,), module=__name__,
    namespace={"__doc__": "A partial `ViewSettings` (``open.settings``, ``settings.settings``): each of its fields "
                          "optional (absent: unchanged; only the given ones travel), with the same bounds; unknown "
                          "fields are refused."})


# ---------------------------------------------------------------------------------------------
# messages


class _Tag:
    """``Message.TYPE``: the class's ``type`` tag, on the class and its instances."""

    def __get__(self, obj: Any, cls: type) -> str:
        return cls.__struct_config__.tag


class Message(msgspec.Struct, frozen=True, forbid_unknown_fields=True, tag_field="type"):
    """Base of the messages: the ``type`` tag is each class's ``TYPE``."""

    TYPE: ClassVar[str] = _Tag()

    def check(self, limits: Limits) -> None:
        """The checks that depend on the receiver's limits, run by :func:`parse` after decoding
        (none unless a message says otherwise)."""


def _check_version(version: int) -> None:
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {version} is not supported; this server speaks {PROTOCOL_VERSION}: "
                            f"update the client")


class CameraMsg(Message, tag="camera"):
    """A camera: look-at (``eye``, ``target``, ``up``, default +y) or orbit (``yaw``, ``pitch``,
    ``distance`` around ``target``, degrees, world +y up, as ``isosr_render.orbit``); ``fov_y`` in degrees."""

    eye: Vec3 | None = None
    target: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 | None = None
    yaw: Annotated[float, Meta(ge=-1e6, le=1e6)] | None = None
    pitch: Annotated[float, Meta(ge=-89.9, le=89.9)] | None = None
    distance: Annotated[float, Meta(ge=1e-6, le=1e6)] | None = None
    fov_y: Annotated[float, Meta(ge=1.0, le=170.0)] = 40.0
    seq: Seq | None = None

    def __post_init__(self):
        orbit = (self.yaw, self.pitch, self.distance)
        if self.eye is None and None in orbit:
            raise ProtocolError("camera: give eye (look-at) or yaw, pitch and distance (orbit)")
        if self.eye is not None and any(v is not None for v in orbit):
            raise ProtocolError("camera: give either eye or yaw/pitch/distance, not both")
        if self.eye is None and self.up is not None:
            raise ProtocolError("camera: an orbit camera has world +y up; up is for look-at cameras (eye)")
        if self.eye is not None:
            forward, up = np.subtract(self.target, self.eye), np.asarray(self.look_up(), np.float64)
            if np.linalg.norm(forward) < 1e-9:
                raise ProtocolError("camera: eye and target coincide")
            # <=: a zero up gives 0 <= 0 (isosr_render.Camera's strict < lets it through to a NaN basis).
            if np.linalg.norm(np.cross(forward, up)) <= 1e-6 * np.linalg.norm(forward) * np.linalg.norm(up):
                raise ProtocolError("camera: up is zero or parallel to the viewing direction")

    def look_up(self) -> tuple[float, float, float]:
        """The look-at camera's up direction."""
        return (0.0, 1.0, 0.0) if self.up is None else self.up


class OpenMsg(Message, tag="open"):
    """Client -> server, first message of a view session.

    Attributes:
        volume: a name from ``GET /v1/volumes`` or a procedural spec, never a path.
        settings: what differs from the `ViewSettings` defaults.
        camera: the first camera (None: the server's default).
        iso: data units unless ``iso_normalized``; None: the volume's suggested iso.
    """

    volume: Annotated[str, Meta(pattern=VOLUME_NAME.pattern)]
    settings: SettingsUpdate = msgspec.field(default_factory=SettingsUpdate)
    camera: CameraMsg | None = None
    iso: Finite | None = None
    iso_normalized: bool = False
    version: Version = PROTOCOL_VERSION

    def __post_init__(self):
        _check_version(self.version)

    def check(self, limits: Limits) -> None:
        self.settings.check(limits)


class IsoMsg(Message, tag="iso"):
    """Client -> server: a new iso-value (data units unless ``normalized``)."""

    value: Finite
    normalized: bool = False
    seq: Seq | None = None


class SettingsMsg(Message, tag="settings"):
    """Client -> server: a partial settings update."""

    settings: SettingsUpdate
    seq: Seq | None = None

    def check(self, limits: Limits) -> None:
        self.settings.check(limits)


class FocusMsg(Message, tag="focus"):
    """Client -> server: the focus region in output pixels (x right, y down): a circle
    (``center``, ``radius``), a box (``box`` = x0, y0, x1, y1) or ``none``."""

    shape: Literal[FOCUS_SHAPES] = "none"
    center: Vec2 | None = None
    radius: Annotated[float, Meta(ge=0.0, le=MAX_ABS_FLOAT)] | None = None
    box: tuple[Finite, Finite, Finite, Finite] | None = None
    seq: Seq | None = None

    def __post_init__(self):
        given = {name for name in ("center", "radius", "box") if getattr(self, name) is not None}
        needed = {"none": set(), "circle": {"center", "radius"}, "box": {"box"}}[self.shape]
        if given != needed:
            raise ProtocolError(f"focus: a {self.shape} region takes exactly {sorted(needed) or 'no fields'}")
        if self.box is not None and not (self.box[0] < self.box[2] and self.box[1] < self.box[3]):
            raise ProtocolError("focus: box must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1")


class PickMsg(Message, tag="pick"):
    """Client -> server: what lies under pixel ``(x, y)`` of the session's current view (x right,
    y down, pixel centres at +0.5); answered by ``picked`` with the same ``x``, ``y`` and ``id``."""

    x: Annotated[float, Meta(ge=0.0, le=MAX_ABS_FLOAT)]
    y: Annotated[float, Meta(ge=0.0, le=MAX_ABS_FLOAT)]
    id: Seq = 0


class ReceivedMsg(Message, tag="received"):
    """Client -> server: the client has taken frame ``frame`` (the frame's ``seq``) and every
    earlier one off the wire: credit for more (flow control, module docstring)."""

    frame: Seq


class KeyframeMsg(Message, tag="keyframe"):
    """Client -> server: make the next video frame a keyframe (e.g. after a decoder error)."""


class LevelSummary(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One level of a multiscale volume: its dataset path, voxels (x, y, z) and stored bytes."""

    level: Annotated[str, Meta(max_length=200)]
    shape: tuple[Side, Side, Side]
    nbytes: Annotated[int, Meta(ge=0)] = msgspec.field(name="bytes")


class VolumeSummary(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``ready.volume``: the volume a session views (:class:`isosr_server.volumes.VolumeInfo`).

    Attributes:
        name, shape, value_range: its name, voxels (x, y, z) and data range.
        iso: the suggested iso-value in data units; ``iso_normalized`` the session's, in [0, 1].
        histogram: voxel counts in ``histogram_bins`` equal bins over ``value_range``.
        level, levels: a multiscale volume's level served and all its levels, finest first
            (:mod:`isosr_server.volumes` says which is served); None for others.
        steps: a series' time steps (``settings.t`` picks one); 1 for a volume.
    """

    name: str
    shape: tuple[Side, Side, Side] | None
    value_range: tuple[float, float] | None
    iso: float | None
    histogram: list[Annotated[int, Meta(ge=0)]] | None
    histogram_bins: Side
    iso_normalized: Finite
    level: Annotated[str, Meta(max_length=200)] | None = None
    levels: list[LevelSummary] | None = None
    steps: Annotated[int, Meta(ge=1, le=MAX_STEPS)] = 1


class OptionInfo(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A setting a mode reads: an integer within ``[low, high]`` starting at ``default``, or one
    of ``choices``."""

    name: Annotated[str, Meta(max_length=32)]
    low: int | None = None
    high: int | None = None
    default: int | str | None = None
    choices: list[str] | None = None


class ModeInfo(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A view mode the server offers: its name and label, the settings it reads, whether its
    frames are shaded images (else buffers for the client), are upscaled by the server's factor
    (``low_res``: the size a multiple of it), and follow a ``focus`` point."""

    name: ModeName
    label: Annotated[str, Meta(max_length=100)]
    options: list[OptionInfo]
    shaded: bool = True
    low_res: bool = False
    focus: bool = False


class ReadyMsg(Message, tag="ready"):
    """Server -> client, the answer to ``open``: the session, its volume, its effective
    settings (``encoding``: the one it sends, jpeg where the asked one cannot be made), the
    network's upscale factor, the reconstruction's AO ray bound, the limits, and the encodings
    this server can make now (video codecs only where PyAV and the codec are present), and the
    view modes it offers."""

    session: SessionId
    volume: VolumeSummary
    settings: ViewSettings
    upscale_factor: Factor
    max_recon_ao_rays: Annotated[int, Meta(ge=0)]
    limits: Limits
    modes: list[ModeInfo]
    encoders: list[Literal[ENCODINGS]] = msgspec.field(default_factory=lambda: list(IMAGE_ENCODINGS))
    version: Version = PROTOCOL_VERSION


class PickedMsg(Message, tag="picked"):
    """Server -> client, the answer to ``pick``: whether the pixel's ray hits the isosurface and, if
    it does, the point in world units, its nearest voxel, its position in the volume's physical
    units (voxel coordinates times the spacing) and the volume's value there in data units
    (:class:`isosr_render.picking.Pick`); the distance between two picks is that of their
    ``position``. The view's clip holds: ``cap`` where the point lies on a capped cut face. With
    ``settings.surfaces``, the pick lands on the nearest of them (a translucent one too, not what shows
    through it) and ``surface`` is its index in that list (None without them, on a miss or a cut face)."""

    x: Finite
    y: Finite
    id: Seq
    hit: bool
    world: Vec3 | None = None
    voxel: tuple[int, int, int] | None = None
    position: Vec3 | None = None
    value: Finite | None = None
    depth: Finite | None = None
    cap: bool = False
    surface: Annotated[int, Meta(ge=0, lt=MAX_SURFACES)] | None = None


class NoticeMsg(Message, tag="notice"):
    """Server -> client: non-fatal news, e.g. ``h264 is not available on this server (PyAV
    missing); sending jpeg``."""

    text: Annotated[str, Meta(max_length=1000)]


class Legend(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The false colors of a channel-view frame (:mod:`isosr_server.channels`), or a coloring's on a
    shaded one (channel ``shaded``, ``unit`` what colours it): the values ``lo`` to ``hi`` in ``unit``, by
    ``colormap`` (``stops``: its RGB stops, where it has them)."""

    channel: Literal[CHANNELS]
    lo: float
    hi: float
    unit: Annotated[str, Meta(max_length=64)]
    colormap: Annotated[str, Meta(max_length=32)]
    stops: list[Vec3] | None = None


class ViewBuffers(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A ``buffers`` frame's low-res buffers in the buffers coding (:mod:`isosr_server.codecs.buffers`):
    coded mask, and what was sent of normal, depth (with its ``depth_range``: near, far) and flow."""

    mask: WireArray
    normal: WireArray | None = None
    depth: WireArray | None = None
    depth_range: Vec2 | None = None
    flow: WireArray | None = None

    def __post_init__(self):
        if (self.depth is None) != (self.depth_range is None):
            raise ProtocolError("buffers: depth and depth_range travel together")
        if self.depth_range is not None and self.depth_range[0] > self.depth_range[1]:
            raise ProtocolError("buffers: depth_range must be [near, far] with near <= far")

    @property
    def nbytes(self) -> int:
        """Payload bytes: the arrays' data as sent."""
        return sum(len(a.data) for a in (self.mask, self.normal, self.depth, self.flow) if a is not None)


class VolumeMemory(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Where a volume's voxels are on the server's device and what paging cost
    (:class:`isosr_render.brick_pool.MemoryStats`, field for field).

    Attributes:
        mode: ``dense`` (the whole volume on the device) or ``sparse`` (the bricks an iso needs).
        storage: the voxels' type on the device.
        dense_bytes, resident_bytes, pool_bytes, limit_bytes: the whole volume's bytes, those on
            the device now (dense: with the march's filtered texture where it has one), those
            allocated for the brick pool, the limit (0: none).
        bricks_total, bricks_resident, bricks_needed: bricks of the volume, resident, needed by
            the last iso.
        page_ins, bricks_paged, bytes_read: paging so far; ``last_page_in_s`` the last one's seconds.
    """

    mode: Literal["dense", "sparse"]
    storage: Annotated[str, Meta(max_length=16)]
    dense_bytes: Annotated[int, Meta(ge=0)]
    resident_bytes: Annotated[int, Meta(ge=0)]
    pool_bytes: Annotated[int, Meta(ge=0)]
    limit_bytes: Annotated[int, Meta(ge=0)]
    bricks_total: Annotated[int, Meta(ge=0)]
    bricks_resident: Annotated[int, Meta(ge=0)]
    bricks_needed: Annotated[int, Meta(ge=0)] = 0
    page_ins: Annotated[int, Meta(ge=0)] = 0
    bricks_paged: Annotated[int, Meta(ge=0)] = 0
    bytes_read: Annotated[int, Meta(ge=0)] = 0
    last_page_in_s: Annotated[float, Meta(ge=0, le=MAX_ABS_FLOAT)] = 0.0


class AutoChoice(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What the ``auto`` mode expects of the method it chose for a frame (``frame.method`` names it).

    Attributes:
        budget_ms: the frame's share of the device: ``1000 S / (N F)`` ms for N sessions at F frames
            a second on a share S of the device (`isosr_server.auto`).
        ms: the method's expected frame time on the device (None: not measured yet).
        psnr_db: its expected color PSNR against the reference, dB (None: not measured yet, or not
            finite: a candidate equal to its reference).
        fits: ``ms`` lies within the budget's headroom (False: nothing fit, the fastest was taken).
        source: where the expectation comes from: ``probe`` (this scene measured on this server),
            ``table`` (the device's cost table, scaled by this scene's first-hit time) or ``prior`` (no
            measurement yet: the cheapest method).
    """

    budget_ms: Millis
    ms: Millis | None
    psnr_db: Finite | None
    fits: bool
    source: Literal["probe", "table", "prior"]


class FrameMsg(Message, tag="frame"):
    """Server -> client: one view frame.

    Attributes:
        seq: the server's frame number in this session (from 0).
        ack: the highest client ``seq`` this frame includes (-1: none yet).
        mode: the mode that made it (``full`` for refined frames).
        method: the display name of the frame method that made it (e.g. ``full, AO 2, spp 1``).
        width, height: the output size (buffers travel at low resolution: width / factor; video
            is coded larger, at even sides: show its top-left width x height).
        encoding: an image or video encoding (`ENCODINGS`: ``image`` holds the bytes, module
            docstring) or ``buffers``.
        times: server milliseconds per stage (`STAGES`).
        nbytes: payload bytes (image, or the buffers' data); ``bytes`` on the wire.
        refined: the still-camera refined frame.
        image: the encoded image.
        buffers: the low-res buffers in the buffers coding.
        prev_seq: ``buffers`` only: the frame whose camera the flow refers to (-1: no flow,
            a cut: reset the recurrent state).
        legend: the channel view's false colors, or a coloring's colour map and range.
        keyframe: the frame decodes alone (every image frame; video: a keyframe).
        timestamp_us: video: when the frame was made, microseconds since the session began
            (increasing; the decoder's timestamp).
        codec: video only: the WebCodecs codec string (``avc1.64001f``, ``vp09.00.40.08``,
            ``av01.0.08M.08``).
        bitrate_kbps: video only: the encoder's target bitrate when it made the frame.
        device: the volume's device memory and paging (:class:`VolumeMemory`), on a session's
            first frame and on each frame after which it changed (e.g. an iso change paged
            bricks in); None: as last sent.
        t: the time step shown: ``settings.t``, or the last step shown where that one cannot be
            read (a ``notice`` says why).
        batch: the frames the server's device made together with this one, itself included (1:
            alone; many sessions' frames are made together under load).
        choice: ``auto`` frames: what the policy expects of the method it chose (:class:`AutoChoice`);
            None for other modes and refined frames.
    """

    seq: Seq
    ack: Annotated[int, Meta(ge=-1, le=MAX_SEQ)]
    mode: ModeName
    method: Annotated[str, Meta(max_length=200)]
    width: Side
    height: Side
    encoding: Literal[ENCODINGS + ("buffers",)]
    times: Times
    nbytes: Annotated[int, Meta(ge=0)] = msgspec.field(name="bytes")
    refined: bool = False
    image: bytes | None = None
    buffers: ViewBuffers | None = None
    prev_seq: Annotated[int, Meta(ge=-1, le=MAX_SEQ)] = -1
    legend: Legend | None = None
    keyframe: bool = True
    timestamp_us: Annotated[int, Meta(ge=0, le=MAX_SEQ)] = 0
    codec: Annotated[str, Meta(max_length=64)] | None = None
    bitrate_kbps: Annotated[int, Meta(ge=0)] = 0
    device: VolumeMemory | None = None
    t: Step = 0
    batch: Annotated[int, Meta(ge=1, le=MAX_SEQ)] = 1
    choice: AutoChoice | None = None

    def __post_init__(self):
        if (self.encoding == "buffers") != (self.buffers is not None) or (self.image is None) == (self.buffers is None):
            raise ProtocolError("frame: an encoded frame carries image bytes, a buffers frame carries buffers")
        if (self.encoding in VIDEO_ENCODINGS) != (self.codec is not None):
            raise ProtocolError("frame: a video frame carries its codec string, other frames none")
        if not self.keyframe and self.encoding not in VIDEO_ENCODINGS:
            raise ProtocolError("frame: only a video frame can be a delta frame (keyframe false)")

    def check(self, limits: Limits) -> None:
        limits.check_size(self.width, self.height, "frame")


class ErrorMsg(Message, tag="error"):
    """Server -> client before a close (or as an HTTP body): the close code / status and why."""

    code: Annotated[int, Meta(ge=0, le=9999)]
    reason: str


LOWRES_INPUTS = ("mask", "normal", "depth", "flow")
# Ranges of the low-res inputs (conventions: coverage, unit normals, depth in world units where the
# volume's box has side 1, flow in pixels). Far beyond them the network's activations overflow to
# NaN (depth 3e38 did, in fp32), so they are refused with a reason instead.
MAX_DEPTH = 1e6
LOWRES_BOUNDS = {"mask": (0.0, 1.0), "normal": (-1.001, 1.001), "depth": (0.0, MAX_DEPTH),
                 "flow": (-FLOW_CLIP, FLOW_CLIP)}
HIGHRES_OUTPUTS = ("mask", "normal", "depth", "ao")


def _check_arrays(arrays: dict[str, np.ndarray], dtypes: tuple[str, ...], height: int, width: int,
                  bounds: dict[str, tuple[float, float]] | None = None) -> None:
    """Each array a numpy array of one of ``dtypes``, (height, width[, 3 normal / 2 flow]),
    within ``bounds``; ProtocolError naming the first that is not."""
    for name, a in arrays.items():
        if not isinstance(a, np.ndarray) or a.dtype.name not in dtypes:
            raise ProtocolError(f"{name}: must be a numpy array of {' or '.join(dtypes)}, got "
                                f"{getattr(a, 'dtype', type(a).__name__)}")
        want = (height, width) + {"normal": (3,), "flow": (2,)}.get(name, ())
        if a.shape != want:
            raise ProtocolError(f"{name}: shape must be {want}, got {a.shape}")
        if bounds is not None and a.size:
            # Compared as Python floats: a bound beyond float16's range (MAX_DEPTH) cast to a
            # float16 array's dtype would overflow to inf.
            lo, hi = bounds[name]
            low, high = float(a.min()), float(a.max())
            if low < lo or high > hi:
                raise ProtocolError(f"{name}: values must lie in [{lo:g}, {hi:g}], got [{low:g}, {high:g}]")


class UpscaleRequest(Message, tag="upscale"):
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

    mask: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    flow: np.ndarray | None = None
    output: Literal[UPSCALE_OUTPUTS] = "buffers"
    quality: Annotated[int, Meta(ge=1, le=100)] = 85
    session: SessionId | None = None
    reset: bool = False
    version: Version = PROTOCOL_VERSION

    def __post_init__(self):
        _check_version(self.version)
        if not isinstance(self.mask, np.ndarray) or self.mask.ndim != 2:
            got = getattr(self.mask, "shape", self.mask)
            raise ProtocolError(_short(f"mask: must be a 2-D numpy array, got {got!r}"))
        arrays = {n: getattr(self, n) for n in LOWRES_INPUTS if getattr(self, n) is not None}
        _check_arrays(arrays, ("float16", "float32"), *self.mask.shape, LOWRES_BOUNDS)


class HighresBuffers(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``upscaled.buffers``: the network's high-res output, float32.

    Shape:
        mask, depth, ao: (H, W). normal: (H, W, 3).
    """

    mask: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    ao: np.ndarray


class UpscaleResponse(Message, tag="upscaled"):
    """Server -> client: the upscaled frame (``buffers``) or the shaded image (``image``)."""

    seq: Seq
    width: Side
    height: Side
    output: Literal[UPSCALE_OUTPUTS]
    times: Times
    nbytes: Annotated[int, Meta(ge=0)] = msgspec.field(name="bytes")
    buffers: HighresBuffers | None = None
    image: bytes | None = None

    def __post_init__(self):
        if (self.output == "buffers") != (self.buffers is not None) or (self.image is None) == (self.buffers is None):
            raise ProtocolError("upscaled: buffers output carries buffers, an image output carries image bytes")
        if self.buffers is not None:
            _check_arrays({n: getattr(self.buffers, n) for n in HIGHRES_OUTPUTS}, ("float32",), self.height,
                          self.width)

    def check(self, limits: Limits) -> None:
        limits.check_size(self.width, self.height, "upscaled frame")


CLIENT_VIEW_MESSAGES: dict[str, type[Message]] = {m.TYPE: m for m in (CameraMsg, IsoMsg, SettingsMsg, FocusMsg,
                                                                        PickMsg, ReceivedMsg, KeyframeMsg)}
SERVER_VIEW_MESSAGES: dict[str, type[Message]] = {m.TYPE: m for m in (ReadyMsg, FrameMsg, PickedMsg, NoticeMsg,
                                                                        ErrorMsg)}


# ---------------------------------------------------------------------------------------------
# coding


def _enc_hook(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return encode_array(obj)
    raise NotImplementedError(f"{type(obj).__name__} cannot travel")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)


def encode(msg: Message) -> bytes:
    """The msgpack bytes of a message (numpy arrays as uncompressed wire arrays)."""
    return _ENCODER.encode(msg)


def _relative(e: msgspec.ValidationError) -> str:
    """A nested validation error's reason with its path made relative (msgspec appends the outer one)."""
    m = re.fullmatch(r"(.*) - at `\$\.?(.*)`", str(e), re.DOTALL)
    return f"{m[1]} in `{m[2]}`" if m else str(e)


def _short(reason: str, limit: int = 200) -> str:
    """``reason`` within ``limit`` characters, its trailing field path (`` - at `$.x` `` or `` in `x` ``) kept
    whole where it fits: a long echoed value is what gets cut, not the field's name."""
    m = re.fullmatch(r"(.*)( (?:- at|in) `[^`]*`)", reason, re.DOTALL)
    if m is None or len(reason) <= limit:
        return reason[:limit]
    return (m[1][:max(limit - len(m[2]) - 3, 0)] + "..." + m[2])[:limit]


def _no_ext(code: int, data: memoryview) -> Any:
    raise ValueError(f"msgpack extension type {code} is not part of the protocol")


# Decoders are built one at a time: msgspec fills a Struct's type information (its annotations
# resolved in Python code, where threads switch) while it builds a decoder, and client processes
# whose 32 view threads opened at once died in it (a segfault in `parse` under `connect`, in three
# benchmark runs on a 32-core host). Decoding itself is thread-safe and takes no lock.
_BUILDING = threading.Lock()


def _decoder(types: tuple[type, ...], limits: Limits) -> msgspec.msgpack.Decoder:
    """A decoder of any of ``types``, its arrays bounded by ``limits`` (built once per pair)."""
    with _BUILDING:
        return _build_decoder(types, limits)


@lru_cache(maxsize=64)
def _build_decoder(types: tuple[type, ...], limits: Limits) -> msgspec.msgpack.Decoder:
    max_elements, max_side = limits.array_bounds()

    def dec_hook(kind: type, obj: Any) -> Any:
        if kind is not np.ndarray:
            raise NotImplementedError(f"{kind} is not part of the protocol")
        try:
            wire = msgspec.convert(obj, WireArray, builtin_types=(bytes,))  # bytes only, never base64 text
        except msgspec.ValidationError as e:
            raise ValueError(_relative(e)) from None
        return decode_array(wire, max_elements, max_side)

    return msgspec.msgpack.Decoder(Union[types], dec_hook=dec_hook, ext_hook=_no_ext)


def convert(obj: Any, kind: type, where: str) -> Any:
    """``obj`` (plain Python values, e.g. keyword arguments) validated as ``kind`` as if it had
    come over the wire; `ProtocolError` naming the field (``where`` prefixes the path)."""
    try:
        return msgspec.convert(obj, kind, builtin_types=(bytes,))
    except msgspec.ValidationError as e:
        raise ProtocolError(_short(f"{where}: {e}")) from None


def parse(data: bytes, limits: Limits, expected: Mapping[str, type[Message]] | tuple[type[Message], ...]) -> Message:
    """Decode and validate one message whose ``type`` is among ``expected``.

    Args:
        data: the msgpack bytes.
        limits: the receiver's limits (``max_message_bytes`` bounds ``data``, checked first).
        expected: the message classes allowed here (a tuple, or a TYPE -> class map).

    Raises:
        ProtocolError: what is wrong (the field's path where one is to blame), with the close
            code and HTTP status to answer: CLOSE_TOO_BIG / 413 for sizes over the limits,
            CLOSE_BAD_MESSAGE / 400 for everything else.
    """
    types = tuple(expected.values()) if isinstance(expected, Mapping) else tuple(expected)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("messages must be binary msgpack")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}",
                            CLOSE_TOO_BIG, 413)
    try:
        msg = _decoder(types, limits).decode(data)
    except ArrayTooBig as e:
        raise ProtocolError(_short(f"array {e}"), CLOSE_TOO_BIG, 413) from None
    except msgspec.ValidationError as e:
        reason = str(e)
        if reason.endswith("`$.type`") or reason == "Object missing required field `type`":
            reason = f"message type must be one of {', '.join(t.TYPE for t in types)}: {reason}"
        if _NOTICED_PATH.search(reason):
            raise SettingRefused(_short(reason), seq=_seq_of(data)) from None
        raise ProtocolError(_short(reason)) from None
    except (msgspec.DecodeError, ValueError) as e:  # not msgpack, truncated, trailing bytes, extension types
        raise ProtocolError(_short(f"malformed msgpack: {e}")) from None
    except RecursionError:  # arrays / maps nested past msgspec's depth bound: the client's mistake, not a fault
        raise ProtocolError("malformed msgpack: nested too deeply") from None
    msg.check(limits)
    return msg
