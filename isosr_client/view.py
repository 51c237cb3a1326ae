"""A view session on `isosr serve` (``WS /v1/view``) for notebooks and scripts.

    from isosr_client import connect

    with connect("http://127.0.0.1:8000", volume="proc:cloud:0", mode="buffers", size=(640, 480)) as view:
        view.set_camera(yaw=40, pitch=20, distance=1.8)
        rgb = view.frame()                 # numpy (480, 640, 3) uint8, includes the camera above
        print(view.stats)                  # latency, bytes, frame method, server stage times, refined flag

Synchronous (``websockets.sync.client``). In ``buffers`` mode the server sends the low-res
buffers and this side decodes them (:mod:`isosr_server.codecs.buffers`, numpy), upscales them
with the network on ``device`` and shades them (:mod:`isosr_client.local`, loaded with torch at
the first such frame), keeping the network's recurrent state across frames; every other mode
arrives as an encoded image, or as video (h264, vp9, av1: decoded here with PyAV, the ``video``
extra, as each frame arrives, since each needs the ones before it; a decoder error asks the
server for a keyframe). ``prefer`` picks the encoding: the first this side can decode and the
server offers (``ready.encoders``); an encoding this side cannot decode falls back to jpeg, and
why, like the server's own notices, lands in ``notices``. Of the server, only the protocol and
its codecs are imported.

With ``reconnect=True`` a session whose connection is lost (the server's process died, or it
went away or failed: `RECONNECT_CODES`) opens itself again, on any replica behind
``isosr serve --replicas``, with its current camera, iso, settings and focus, and goes on;
``reconnects`` counts how often, and each frame's stats name the replica that made it.
"""

from __future__ import annotations

import json
import ssl
import time
import urllib.error
import urllib.request
import warnings
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit, urlunsplit

import msgspec
import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from isosr_render.image_codec import decode_image
from isosr_server.codecs import video
from isosr_server.codecs.buffers import decode_view_buffers
from isosr_server.protocol import (CLIENT_VIEW_MESSAGES, CLOSE_GOING_AWAY, CLOSE_INTERNAL, ENCODINGS, REPLICA_HEADER,
                                   SERVER_VIEW_MESSAGES, TOKEN_HEADER, VIDEO_ENCODINGS, AutoChoice, CameraMsg, ErrorMsg,
                                   FocusMsg, FrameMsg, IsoMsg, KeyframeMsg, Limits, NoticeMsg, OpenMsg, PickedMsg,
                                   PickMsg, ProtocolError, ReadyMsg, ReceivedMsg, SettingsMsg, SettingsUpdate,
                                   ViewSettings, VolumeMemory, check_step, convert, encode, parse)

if TYPE_CHECKING:
    from isosr_client.local import LocalUpscaler
    from isosr_render.buffers import FrameBuffers

# What this client accepts from a server: frames up to 256 MiB (a 4096^2 PNG fits).
CLIENT_LIMITS = Limits(max_message_bytes=2**28)
# Close codes after which a session with ``reconnect`` opens itself again: the connection was lost
# without a close (1006: as when the server's process dies), the server went away, failed, restarts
# or is overloaded (1012, 1013).
RECONNECT_CODES = (1006, CLOSE_GOING_AWAY, CLOSE_INTERNAL, 1012, 1013)
# How long a lost session keeps trying to open again; the pauses between tries (doubling from the first).
RECONNECT_WINDOW_S, RECONNECT_PAUSE_S, RECONNECT_PAUSE_MAX_S = 10.0, 0.05, 0.25
# Notices a session keeps (the newest).
MAX_NOTICES = 32


def decodable(encoding: str) -> str | None:
    """Why this side cannot decode ``encoding`` (None: it can)."""
    if encoding not in VIDEO_ENCODINGS:
        return None
    try:
        video.check_available(encoding, decode=True)
    except video.VideoUnavailable as e:
        return str(e)
    return None


def choose_encoding(prefer: Sequence[str], offered: Sequence[str] = ENCODINGS) -> tuple[str, list[str]]:
    """The first of ``prefer`` that this side can decode and ``offered`` holds (jpeg if none), and
    why the ones before it were passed over.

    Raises:
        ValueError: ``prefer`` names something that is no encoding.
    """
    unknown = [e for e in prefer if e not in ENCODINGS]
    if unknown:
        raise ValueError(f"prefer: {unknown[0]!r} is not an encoding ({', '.join(ENCODINGS)})")
    passed = []
    for encoding in prefer:
        why = decodable(encoding) or (None if encoding in offered else f"the server offers no {encoding}")
        if why is None:
            return encoding, passed
        passed.append(why)
    return "jpeg", passed


class ServerError(RuntimeError):
    """The server refused a request or ended the session: its close code / HTTP status and reason."""

    def __init__(self, code: int, reason: str):
        super().__init__(f"server error {code}: {reason}")
        self.code, self.reason = code, reason


def endpoint(url: str, path: str, websocket: bool) -> str:
    """``url`` (``http(s)://`` or ``ws(s)://`` host and port, any path dropped) with ``path``, in
    the scheme asked for.

    Raises:
        ValueError: not an http, https, ws or wss URL with a host.
    """
    parts = urlsplit(url)
    secure = {"http": False, "ws": False, "https": True, "wss": True}.get(parts.scheme)
    if secure is None or not parts.netloc:
        raise ValueError(f"server URL must look like http://HOST:PORT or ws://HOST:PORT, got {url!r}")
    scheme = ("wss" if secure else "ws") if websocket else ("https" if secure else "http")
    return urlunsplit((scheme, parts.netloc, path, "", ""))


def tls_context(where: str, cafile: str | Path | None) -> ssl.SSLContext | None:
    """How a connection to ``where`` (from `endpoint`) checks the server's certificate: None (the
    system's certificate authorities; nothing for plain http and ws) without ``cafile``, else a
    context that trusts the PEM certificates in ``cafile`` (e.g. a self-signed server's own).

    Raises:
        ValueError: ``cafile`` with a plain http or ws URL, or it is missing or holds no certificate.
    """
    if cafile is None:
        return None
    if not where.startswith(("https:", "wss:")):
        raise ValueError(f"cafile {cafile} goes with an https or wss URL, not {where}")
    try:
        return ssl.create_default_context(cafile=cafile)
    except ssl.SSLError:
        raise ValueError(f"cafile {cafile}: no PEM certificate in it") from None
    except OSError as e:
        raise ValueError(f"cafile {cafile}: {e.strerror}") from None


def auth_headers(token: str | None) -> dict[str, str]:
    """The headers that carry the server's token (none without one)."""
    return {} if token is None else {"Authorization": f"Bearer {token}", TOKEN_HEADER: token}


def http_call(url: str, path: str, token: str | None = None, cafile: str | Path | None = None, timeout: float = 60.0,
              body: bytes | None = None, headers: Mapping[str, str] | None = None) -> tuple[Mapping[str, str], bytes]:
    """One HTTP request to ``path`` of the server at ``url`` (POST with a ``body``, else GET): the
    reply's headers and bytes.

    Raises:
        ServerError: the server refused it (its status and reason).
        ValueError: a bad URL or ``cafile`` (see `endpoint`, `tls_context`).
    """
    where = endpoint(url, path, websocket=False)
    request = urllib.request.Request(where, data=body, method="GET" if body is None else "POST",
                                     headers={**(headers or {}), **auth_headers(token)})
    try:
        with urllib.request.urlopen(request, timeout=timeout, context=tls_context(where, cafile)) as reply:
            return reply.headers, reply.read()
    except urllib.error.HTTPError as e:
        detail = e.read()
        try:
            reason = json.loads(detail)["error"]
        except (ValueError, KeyError, TypeError):
            reason = detail.decode(errors="replace")[:200]
        raise ServerError(e.code, reason) from None


@dataclass
class FrameStats:
    """What one frame cost.

    Attributes:
        seq, ack: the server's frame number and the newest client update it includes (-1: none).
        mode: the mode that made it (``full`` for refined frames).
        method: the display name of the frame method that made it.
        refined: the still-camera refined frame.
        latency_ms: from sending the newest update it includes (or ``open``) to its arrival; for
            a refined frame this includes the still time before the server refines.
        nbytes: payload bytes (image, or the coded buffers).
        wire_bytes: the whole message.
        server_ms: the server's milliseconds per stage (render, network, shading, encode, total).
        client_ms: this side's milliseconds: ``decode`` (image, video or buffers), ``network`` (local
            upscaling), ``shading``; filled as they happen.
        replica: the server replica that made it (``isosr serve --replicas``; None: a single server).
        encoding: the frame's encoding; ``keyframe``, ``bitrate_kbps``: a video frame's.
        device: the volume's device memory and paging on the server, as of this frame (frames
            carry it when it changed; :class:`isosr_server.protocol.VolumeMemory`).
        batch: the frames the server made together with this one, itself included (1: alone).
        choice: ``auto`` frames: what the server's policy expects of the method it chose (its time
            against the session's budget, its PSNR: :class:`isosr_server.protocol.AutoChoice`).
    """

    seq: int
    ack: int
    mode: str
    method: str
    refined: bool
    latency_ms: float
    nbytes: int
    wire_bytes: int
    server_ms: dict[str, float]
    client_ms: dict[str, float] = field(default_factory=dict)
    replica: str | None = None
    encoding: str = "jpeg"
    keyframe: bool = True
    bitrate_kbps: int = 0
    device: VolumeMemory | None = None
    batch: int = 1
    choice: AutoChoice | None = None


@dataclass
class ViewFrame:
    """One received frame; the RGB image is decoded (or shaded) only when asked for.

    Attributes:
        message: the validated frame message.
        stats: its costs.
        highres: ``buffers`` frames upscaled here: the network's high-res buffers, else None.
        error: a video frame that could not be decoded: why (a keyframe was asked for).
    """

    message: FrameMsg
    stats: FrameStats
    highres: FrameBuffers | None = None
    error: str | None = None
    _rgb: np.ndarray | None = None

    def rgb(self) -> np.ndarray:
        """The frame as (H, W, 3) uint8 RGB (decoded or shaded on first call)."""
        if self.error is not None:
            raise ValueError(f"frame {self.message.seq}: {self.error}")
        if self._rgb is None:
            start = time.perf_counter()
            if self.message.image is not None:
                self._rgb = decode_image(self.message.image)
                stage = "decode"
            elif self.highres is not None:
                from isosr_client.local import shade_rgb  # loaded already: it made highres

                self._rgb = shade_rgb(self.highres)
                stage = "shading"
            else:
                raise ValueError("this buffers frame was not upscaled here (connect(..., local_upscale=True))")
            self.stats.client_ms[stage] = self.stats.client_ms.get(stage, 0.0) + 1e3 * (time.perf_counter() - start)
        return self._rgb


class ViewSession:
    """A connected view session. Made by :func:`connect`; close it (or use ``with``).

    Updates (:meth:`set_camera`, :meth:`set_iso`, :meth:`set_settings`, :meth:`set_focus`)
    are sent at once, each with a new ``seq``; the server renders the newest state (latest
    wins). :meth:`latest` / :meth:`frame` return the newest frame that includes every update
    sent so far, waiting for it when needed.

    Flow control: each frame is acknowledged (``received``) as it is taken off the wire here,
    and the server sends at most ``limits.max_unacked_frames`` frames ahead; so frames are made
    only as fast as this side asks for them, and the next one shows the newest state.
    """

    def __init__(self, ws, ready: ReadyMsg, opened_at: float, opened: OpenMsg, device: str, model: str | Path | None,
                 local_upscale: bool, timeout: float, reopen: Callable[[OpenMsg], tuple] | None = None):
        self._ws, self.ready, self.timeout = ws, ready, timeout
        self.replica: str | None = ws.response.headers.get(REPLICA_HEADER)
        self._opened, self._reopen, self.reconnects = opened, reopen, 0
        self._camera, self._iso, self._focus = opened.camera, None, None  # the state a reopened session restores
        first_seq = -1 if opened.camera is None else 0
        self.settings: ViewSettings = ready.settings
        self.limits: Limits = ready.limits
        self.upscale_factor = ready.upscale_factor
        self.device, self.model, self.local_upscale = device, model, local_upscale
        self._local: LocalUpscaler | None = None
        self._last_buffers_seq = -1
        self._seq = first_seq  # the newest update sent: the open's camera (0), else none (-1)
        self._sent_at: dict[int, float] = {-1: opened_at, first_seq: opened_at}
        self._latest: ViewFrame | None = None
        self._pick_id, self._picked = 0, None  # the last pick asked, the last answer
        self.stats: FrameStats | None = None
        self.volume_memory: VolumeMemory | None = None  # the newest the frames carried
        self.closed = False
        self.notices: deque[str] = deque(maxlen=MAX_NOTICES)
        self._decoder: video.VideoDecoder | None = None  # the video stream's, from its last keyframe

    def _notice(self, text: str) -> None:
        """News about the session (an encoding that cannot be had): kept and warned of."""
        self.notices.append(text)
        warnings.warn(text, stacklevel=3)

    # ---- updates -------------------------------------------------------------------------------

    def _send(self, msg) -> int | None:
        """Validate an update (or a pick) as the server would, send it, and return its seq."""
        self._check_open()
        data = encode(msg)
        parse(data, self.limits, CLIENT_VIEW_MESSAGES)  # a bad update fails here, clearly
        if isinstance(msg, CameraMsg):  # the state a reopened session restores
            self._camera = msg
        elif isinstance(msg, IsoMsg):
            self._iso = msg
        elif isinstance(msg, FocusMsg):
            self._focus = msg
        elif isinstance(msg, SettingsMsg):
            self.settings = self.settings.updated(msg.settings, self.limits)
        seq = getattr(msg, "seq", None)  # a pick carries none: it asks, it changes no state
        if seq is not None:
            self._sent_at[seq] = time.perf_counter()
        try:
            self._ws.send(data)
        except ConnectionClosed as e:
            self._connection_closed(e)
            return self._seq  # the reopened session's open carries this update
        return seq

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def set_camera(self, yaw: float | None = None, pitch: float | None = None, distance: float | None = None, *,
                   eye: tuple[float, float, float] | None = None, target: tuple[float, float, float] = (0, 0, 0),
                   up: tuple[float, float, float] | None = None, fov_y: float = 40.0) -> int:
        """Orbit (``yaw``, ``pitch``, ``distance`` around ``target``, degrees, world +y up) or
        look-at (``eye``, ``target``, ``up``, default +y); returns the update's seq.

        Raises:
            ProtocolError: an incomplete or degenerate camera (eye on the target, up along the view).
        """
        return self._send(CameraMsg(eye=_floats(eye), target=_floats(target), up=_floats(up), yaw=yaw, pitch=pitch,
                                    distance=distance, fov_y=fov_y, seq=self._next_seq()))

    def set_iso(self, value: float, normalized: bool = False) -> int:
        """A new iso-value (data units unless ``normalized``); returns the update's seq."""
        return self._send(IsoMsg(value, normalized, self._next_seq()))

    def set_settings(self, **settings) -> int:
        """Change settings (`ViewSettings` fields: mode, width, height, ao_rays, encoding, ...);
        returns the update's seq.

        Raises:
            ProtocolError: an unknown field or a value out of range (nothing is sent then).
        """
        update = convert(settings, SettingsUpdate, "settings")
        self.settings.updated(update, self.limits)  # refused here, before a seq is taken
        why = decodable(settings.get("encoding", "jpeg"))
        if why is not None:
            self._notice(f"{why}; asking for jpeg")
            update = msgspec.structs.replace(update, encoding="jpeg")
        return self._send(SettingsMsg(update, self._next_seq()))

    def set_clip(self, planes: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
                 box: tuple[Sequence[float], Sequence[float]] | None = None, cap: str = "none") -> int:
        """Clip every frame, world units: planes ``(point, normal)``, each keeping the side its normal
        points into, a crop box ``(lo, hi)``, and caps of the cut faces where they cut the solid
        (``"above"``: values at or above the iso are solid; ``"below"``; ``"none"``); no arguments: no
        clipping. Returns the update's seq.

        Raises:
            ProtocolError: a bad plane or box, naming it (nothing is sent then).
        """
        return self.set_settings(clip={"planes": [{"point": _floats(p), "normal": _floats(n)} for p, n in planes],
                                       "box": None if box is None else [_floats(c) for c in box], "cap": cap})

    @property
    def steps(self) -> int:
        """The volume's time steps (a series; 1 for a volume)."""
        return self.ready.volume.steps

    @property
    def step(self) -> int:
        """The time step asked for last (a frame's ``message.t`` is the one it shows)."""
        return self.settings.t

    def set_step(self, t: int) -> int:
        """Show time step ``t`` of a series (0 to ``steps - 1``); returns the update's seq. Playing a
        series is setting the next step at the rate wanted.

        Raises:
            ProtocolError: ``t`` past the series (nothing is sent then).
        """
        check_step(t, self.steps, self.ready.volume.name)
        return self.set_settings(t=t)

    def set_coloring(self, by: str | None, colormap: str = "viridis",
                     range: tuple[float, float] | None = None) -> int:
        """Colour the surface by ``"gradient"`` (the volume's gradient magnitude) or by another volume of its
        grid (a name of ``GET /v1/volumes``), through ``colormap`` over ``range`` in the values' units (None:
        their own range); ``by=None``: the material's colour. Frames then carry the legend (``frame.legend``:
        colour map, ``lo``, ``hi``). Returns the update's seq.

        Raises:
            ProtocolError: an unknown colour map or a bad range, naming it (nothing is sent then). The
                server refuses an unknown volume or another grid with a notice naming it (:attr:`notices`,
                and a warning) and a frame of the settings as they were; the session goes on.
        """
        coloring = None if by is None else {"by": by, "colormap": colormap,
                                            "range": None if range is None else _floats(range)}
        return self.set_settings(coloring=coloring)

    def set_surfaces(self, surfaces: Sequence[tuple] = ()) -> int:
        """Show up to 4 isosurfaces together, each ``(iso in data units, (r, g, b) in [0, 1][, opacity])``: each
        ray stops at the nearest, shaded in its colour; one of opacity below 1 lets the ray go on to the next,
        the two layers composited (the frames then full-resolution renders); no arguments: the session's one iso
        again. Returns the update's seq.

        Raises:
            ProtocolError: more than 4, or a colour or opacity outside [0, 1], naming the field (nothing is sent
                then); the
                server refuses equal isos, a coloring beside them or a volume rendered sparse (the session ends
                with its reason).
        """
        return self.set_settings(surfaces=[{"iso": float(iso), "color": _floats(color), "opacity": float(opacity)}
                                           for iso, color, opacity in ((*s, 1.0)[:3] for s in surfaces)])

    def set_focus(self, shape: str = "none", center: tuple[float, float] | None = None, radius: float | None = None,
                  box: tuple[float, float, float, float] | None = None) -> int:
        """The ``focus`` mode's region in output pixels (x right, y down): ``circle`` (center,
        radius), ``box`` (x0, y0, x1, y1) or ``none``; returns the update's seq."""
        return self._send(FocusMsg(shape, _floats(center), radius, _floats(box), self._next_seq()))

    def pick(self, x: float, y: float, timeout: float | None = None) -> PickedMsg:
        """What lies under pixel ``(x, y)`` of the current view (x right, y down, pixel centres at
        +0.5): whether it hits the isosurface and where (world, voxel, physical ``position``) with
        the volume's ``value`` there; the distance between two picks is that of their positions.
        With several surfaces set, ``surface`` is the index of the one hit. Frames arriving
        meanwhile are taken as usual.

        Raises:
            TimeoutError: no answer within ``timeout`` seconds (default: the session's).
            ServerError: the server ended the session (e.g. a point outside the view).
        """
        self._pick_id += 1
        self._send(PickMsg(float(x), float(y), self._pick_id))
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while self._picked is None or self._picked.id != self._pick_id:
            left = deadline - time.monotonic()
            if left <= 0 or not self._receive(left):
                raise TimeoutError(f"no answer to pick {self._pick_id} in time")
        return self._picked

    # ---- frames --------------------------------------------------------------------------------

    def latest(self, refined: bool = False, timeout: float | None = None) -> ViewFrame:
        """The newest frame that includes every update sent so far (and is the refined one, if
        ``refined``), waiting for it up to ``timeout`` seconds (default: the session's).

        Raises:
            TimeoutError: no such frame in time (a refined frame never comes with ``refine`` off).
            ServerError: the server ended the session.
        """
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while self._receive(0.0):  # take what has arrived already
            pass
        while not self._current(refined):
            left = deadline - time.monotonic()
            if left <= 0 or not self._receive(left):
                raise TimeoutError(f"no {'refined ' if refined else ''}frame with update {self._seq} within "
                                   f"{self.timeout if timeout is None else timeout:g} s")
        return self._latest

    def frame(self, refined: bool = False, timeout: float | None = None) -> np.ndarray:
        """:meth:`latest` as (H, W, 3) uint8 RGB; its costs in :attr:`stats`."""
        return self.latest(refined, timeout).rgb()

    def receive(self, timeout: float) -> ViewFrame | None:
        """The next frame to arrive within ``timeout`` seconds, whatever update it includes (None:
        none came): for a viewer that sends updates at its own pace and shows frames as they come
        (open loop), where :meth:`latest` waits for the newest update.

        Raises:
            ServerError: the server ended the session.
        """
        deadline = time.monotonic() + timeout
        before = self._latest
        while self._latest is before:
            left = deadline - time.monotonic()
            if left <= 0 or not self._receive(left):
                return None
        return self._latest

    def _current(self, refined: bool) -> bool:
        f = self._latest
        return f is not None and f.message.ack >= self._seq and (f.message.refined or not refined)

    def _receive(self, timeout: float) -> bool:
        """Receive and process one server message; False if none came within ``timeout``."""
        self._check_open()
        try:
            data = self._ws.recv(timeout=timeout)
        except TimeoutError:
            return False
        except ConnectionClosed as e:
            self._connection_closed(e)
            return True
        arrived = time.perf_counter()
        msg = parse(data, CLIENT_LIMITS, SERVER_VIEW_MESSAGES)
        if isinstance(msg, ErrorMsg):
            self.close()
            raise ServerError(msg.code, msg.reason)
        if isinstance(msg, NoticeMsg):
            self._notice(f"server: {msg.text}")
            return True
        if isinstance(msg, PickedMsg):
            self._picked = msg
            return True
        if not isinstance(msg, FrameMsg):
            raise ProtocolError(f"expected a frame, got a {msg.TYPE} message")
        self._acknowledge(msg.seq)
        sent = max((t for s, t in self._sent_at.items() if s <= msg.ack), default=self._sent_at[-1])
        for s in [s for s in self._sent_at if -1 < s < msg.ack]:
            del self._sent_at[s]  # bounded: the newest acknowledged update and those after it stay
        self.volume_memory = msg.device or self.volume_memory
        stats = FrameStats(msg.seq, msg.ack, msg.mode, msg.method, msg.refined, 1e3 * (arrived - sent), msg.nbytes,
                           len(data), dict(msg.times), replica=self.replica, encoding=msg.encoding,
                           keyframe=msg.keyframe, bitrate_kbps=msg.bitrate_kbps, device=self.volume_memory,
                           batch=msg.batch, choice=msg.choice)
        frame = ViewFrame(msg, stats)
        if msg.encoding in VIDEO_ENCODINGS:
            self._decode_video(frame)
        elif msg.buffers is not None and self.local_upscale:
            frame.highres = self._upscale(msg, stats)
        self._latest, self.stats = frame, stats
        return True

    def _decode_video(self, frame: ViewFrame) -> None:
        """Decode a video frame now (the next needs it): its RGB, or its error after which a
        keyframe is asked for and delta frames are passed over until one comes."""
        msg, start = frame.message, time.perf_counter()
        if msg.keyframe and (self._decoder is None or self._decoder.encoding != msg.encoding):
            self._decoder = video.VideoDecoder(msg.encoding)  # the encoding was decodable when asked for
        if self._decoder is None or self._decoder.encoding != msg.encoding:
            frame.error = "a delta frame without its keyframe"
            return
        try:
            frame._rgb = self._decoder.decode(msg.image, msg.width, msg.height)
        except ValueError as e:
            frame.error = f"{e}; a keyframe was asked for"
            self._decoder = None
            try:
                self._ws.send(encode(KeyframeMsg()))
            except ConnectionClosed:
                pass  # the next receive reports the close
        frame.stats.client_ms["decode"] = 1e3 * (time.perf_counter() - start)

    def _acknowledge(self, frame_seq: int) -> None:
        """Tell the server this frame was taken: credit for the next (flow control)."""
        try:
            self._ws.send(encode(ReceivedMsg(frame_seq)))
        except ConnectionClosed:
            pass  # the next receive reports the close with the server's code and reason

    def _upscale(self, msg: FrameMsg, stats: FrameStats) -> FrameBuffers:
        """Decode a buffers frame and upscale it, continuing the recurrent state when the server's
        flow refers to the last frame upscaled here (``prev_seq``), else starting afresh."""
        start = time.perf_counter()
        arrays = decode_view_buffers(msg.buffers, CLIENT_LIMITS)
        stats.client_ms["decode"] = 1e3 * (time.perf_counter() - start)
        if self._local is None:
            from isosr_client.local import LocalUpscaler  # torch and the network: only where frames are upscaled here

            self._local = LocalUpscaler(self.model, self.device, self.upscale_factor)
        continues = msg.prev_seq >= 0 and msg.prev_seq == self._last_buffers_seq and "flow" in arrays
        if not continues:
            arrays.pop("flow", None)  # the network's state resets without flow
        start = time.perf_counter()
        high = self._local.upscale(arrays)
        stats.client_ms["network"] = 1e3 * (time.perf_counter() - start)
        self._last_buffers_seq = msg.seq
        return high

    def _connection_closed(self, e: ConnectionClosed) -> None:
        """Reopen the session after a lost connection (``reconnect``), else raise the close as a `ServerError`."""
        code = e.rcvd.code if e.rcvd else 1006
        if self._reopen is not None and code in RECONNECT_CODES:
            self._reconnect()
            return
        self.closed = True
        raise ServerError(code, e.rcvd.reason if e.rcvd else "connection lost") from None

    def _reconnect(self) -> None:
        """Open the session again with its current camera, iso, settings and focus; tries for
        RECONNECT_WINDOW_S while the server cannot be reached or fails.

        Raises:
            ServerError, ConnectionError: the server refused (not a failure of its own), or no try succeeded.
        """
        camera = None if self._camera is None else msgspec.structs.replace(self._camera, seq=0)
        iso = (self._opened.iso, self._opened.iso_normalized) if self._iso is None else (self._iso.value,
                                                                                         self._iso.normalized)
        opened = OpenMsg(self._opened.volume, SettingsUpdate(**msgspec.structs.asdict(self.settings)), camera, *iso)
        deadline, pause = time.monotonic() + RECONNECT_WINDOW_S, RECONNECT_PAUSE_S
        while True:
            try:
                ws, ready, opened_at = self._reopen(opened)
                break
            except (ServerError, ConnectionError) as e:
                if (isinstance(e, ServerError) and e.code not in RECONNECT_CODES and e.code < 500) or \
                        time.monotonic() + pause > deadline:
                    self.closed = True
                    raise
            time.sleep(pause)
            pause = min(2 * pause, RECONNECT_PAUSE_MAX_S)
        self._ws, self.ready, self.replica = ws, ready, ws.response.headers.get(REPLICA_HEADER)
        self._seq = -1 if camera is None else 0
        self._sent_at = {-1: opened_at, self._seq: opened_at}
        self._latest, self._last_buffers_seq = None, -1  # the local network starts afresh too
        self._decoder = None  # the new session's stream starts with a keyframe
        self.reconnects += 1
        if self._focus is not None:
            self._send(msgspec.structs.replace(self._focus, seq=self._next_seq()))

    # ---- lifetime ------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self.closed:
            raise ServerError(1000, "the session is closed")

    def close(self) -> None:
        """End the session (idempotent)."""
        if not self.closed:
            self.closed = True
            self._ws.close()

    def __enter__(self) -> "ViewSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _floats(v):
    return None if v is None else tuple(float(x) for x in v)


def connect(url: str, volume: str, mode: str = "auto", size: tuple[int, int] = (640, 480), *,
            token: str | None = None, settings: dict | None = None, camera: dict | None = None,
            iso: float | None = None, iso_normalized: bool = False, device: str = "cpu",
            model: str | Path | None = None, local_upscale: bool = True, timeout: float = 60.0,
            reconnect: bool = False, prefer: Sequence[str] | None = None,
            cafile: str | Path | None = None, compression: str | None = None) -> ViewSession:
    """Open a view session on ``volume`` (a name from ``GET /v1/volumes``, or ``proc:...``).

    Args:
        url: the server, ``http(s)://HOST:PORT`` or ``ws(s)://HOST:PORT``.
        volume: the volume's name.
        mode: a view mode the server offers (``ready.modes``, ``GET /v1/modes``: e.g. ``auto``,
            ``full``, ``network``, ``upscale``, ``buffers``, ``focus``, ``reconstruct`` with
            ``settings["ao_rays"]`` AO rays per hit within the mode's bounds).
        size: output (width, height); a multiple of the upscale factor in the low-res modes
            (``network``, ``upscale``, ``buffers``, ``focus``).
        token: the server's token, if it has one.
        settings: more `ViewSettings` fields (ao_rays, interpolation, encoding, quality, refine, ...).
        camera: the first camera as `set_camera` keywords (default: the server's).
        iso, iso_normalized: the first iso-value (default: the volume's suggested one).
        device, model: where and with which model (None: the shipped one) ``buffers`` frames are
            upscaled here.
        local_upscale: upscale ``buffers`` frames here (off: keep them coded, e.g. to time the server).
        timeout: seconds to wait for the connection and for each frame.
        reconnect: open the session again when its connection is lost (module docstring).
        prefer: encodings best first (e.g. ``("av1", "h264", "jpeg")``): the session opens with the
            first this side decodes and switches to the first of those ``ready.encoders`` offers
            (over ``settings["encoding"]``).
        cafile: PEM certificates to trust for an https/wss server instead of the system's (e.g. the
            server's self-signed certificate).
        compression: ``"deflate"`` offers the WebSocket's permessage-deflate, as browsers do (frames
            are coded images: a server that accepts it spends CPU on every frame for ~nothing); None: off.

    Raises:
        ServerError: the server refused (unknown volume, bad settings, session limit, token).
        ProtocolError: bad settings or camera, found before anything is sent.
    """
    width, height = size
    settings, passed = dict(settings or {}), []
    if prefer is not None:
        settings["encoding"], passed = choose_encoding(prefer)
    why = decodable(settings.get("encoding", "jpeg"))
    if why is not None:
        settings["encoding"] = "jpeg"
        passed.append(why)
    wanted = convert(dict(settings, mode=mode, width=width, height=height), SettingsUpdate, "settings")
    first_camera = None if camera is None else CameraMsg(**{k: _floats(v) if isinstance(v, (list, tuple)) else v
                                                             for k, v in camera.items()}, seq=0)
    open_msg = OpenMsg(volume, wanted, first_camera, iso, iso_normalized)
    data = encode(open_msg)
    parse(data, CLIENT_LIMITS, (OpenMsg,))  # bad input fails here, before any connection
    where, headers = endpoint(url, "/v1/view", websocket=True), auth_headers(token)
    context = tls_context(where, cafile)
    ws, ready, opened_at = _open(where, headers, open_msg, timeout, context, compression)
    reopen = (lambda msg: _open(where, headers, msg, timeout, context, compression)) if reconnect else None
    view = ViewSession(ws, ready, opened_at, open_msg, device, model, local_upscale, timeout, reopen)
    for why in passed:
        view._notice(f"{why}; asking for {wanted.encoding}")
    if prefer is not None:
        best, _ = choose_encoding(prefer, ready.encoders)
        if best != ready.settings.encoding:
            view.set_settings(encoding=best)
    return view


def _open(where: str, headers: dict[str, str], open_msg: OpenMsg, timeout: float,
          context: ssl.SSLContext | None, compression: str | None = None) -> tuple:
    """Connect to ``where`` and open a session: ``(websocket, ready, when the open was sent)``.

    Raises:
        ServerError: the server refused (its close code or HTTP status and reason).
        ConnectionError: nothing answered.
    """
    data = encode(open_msg)
    try:
        # Entered: websockets 17.1 deprecates using connect()'s result without `with`; the
        # session's close() ends it.
        ws = ws_connect(where, additional_headers=headers,
                        max_size=CLIENT_LIMITS.max_message_bytes, compression=compression,
                        open_timeout=timeout, proxy=None, ssl=context).__enter__()
    except Exception as e:  # handshake refused (401), nothing listening, ...
        status = getattr(getattr(e, "response", None), "status_code", None)
        if status is not None:
            body = getattr(e.response, "body", b"") or b""
            raise ServerError(status, body.decode(errors="replace") or str(e)) from None
        raise ConnectionError(f"cannot reach {where}: {e}") from None
    opened_at = time.perf_counter()
    try:
        ws.send(data)
        reply = parse(ws.recv(timeout=timeout), CLIENT_LIMITS, SERVER_VIEW_MESSAGES)
    except ConnectionClosed as e:
        ws.close()
        raise ServerError(e.rcvd.code if e.rcvd else 1006, e.rcvd.reason if e.rcvd else "connection lost") from None
    except BaseException:
        ws.close()
        raise
    if isinstance(reply, ErrorMsg):
        ws.close()
        raise ServerError(reply.code, reply.reason)
    if not isinstance(reply, ReadyMsg):
        ws.close()
        raise ProtocolError(f"expected ready, got a {reply.TYPE} message")
    return ws, reply, opened_at
