"""Sessions: view sessions (latest-frame-wins state, credit-based flow control, the frame loop,
the still-camera refine) and upscale sessions (a network's recurrent state per id: the upscaler's,
the reconstructor's; idle expiry, a bounded count).

Latest frame wins. A view session holds only the newest state the client asked for: every
``camera``/``iso``/``settings``/``focus`` message overwrites it and bumps a version, so stale
updates are coalesced, never queued. The frame loop renders the newest state and only then
looks at the state again: at most one frame per session is on the device, and a frame is never
rendered for a state already superseded before its render began. Its encoding and sending run
beside the next frame's render (in frame order), so a session's frame rate is bounded by the
slower of the two, not their sum (at 1080p on an H100: about 25 ms of rendering in auto mode and
14-26 ms of h264 encoding; made one after the other, one h264 session got 23 frames/s).

Flow control. A frame counts as sent when the client acknowledges it (``received``), not when
the kernel takes it (loopback send buffers hold megabytes: hundreds of frames). The loop makes
a frame only while fewer than ``Limits.max_unacked_frames`` are unacknowledged; otherwise it
waits on the session's event (set by every update and acknowledgment; no polling), updates
coalescing meanwhile. So a slow client gets frames at the rate it takes them, each of the
newest state, and a stalled one costs no device time or memory after that many frames; a
session that waits on credit for ``idle_timeout_s`` is closed with CLOSE_IDLE, as one that
sends nothing for that long is; and a frame not acknowledged within ``ack_timeout_s`` of its
sending ends the session (`watch_acks`), so no party holds session slots by never acknowledging.
Sessions waiting on credit queue no device work, so the device thread (FIFO, one job per
session at most) serves the ready sessions in turn.

Video. A session in a video encoding codes its frames as one stream (:mod:`isosr_server.video`):
its bitrate follows the client's cap or the link's throughput estimated from the
acknowledgments, its frame rate steps down (the loop's pause between frames grows) before its
quality drops too far, and a ``keyframe`` request renders the current state again as a keyframe.
An encoding that cannot be made falls back to jpeg with a ``notice``.

Time series. A session on a series (:class:`StepView`) shows the step its settings name (``t``):
each step is a volume of its own with its own renderer, read off the device thread (the series'
cache, the next steps prefetched), so that a step change is a cut for the recurrent methods (the
frame stream's key holds the renderer). A step that cannot be read leaves the last one shown,
with a notice.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace

import msgspec

from isosr_net.inference import RecurrentNetwork
from isosr_net.upscaler import Upscaler
from isosr_render import Camera, Renderer, Volume, VolumeError, orbit
from isosr_render.series import VolumeSeries, step_iso
from isosr_server import views
from isosr_server.engine import EncodedFrame
from isosr_server.protocol import (CLOSE_IDLE, CLOSE_TOO_MANY, VIDEO_ENCODINGS, CameraMsg, FocusMsg, FrameMsg, IsoMsg,
                                   KeyframeMsg, Legend, Limits, Message, NoticeMsg, ProtocolError, ReceivedMsg,
                                   SettingRefused, SettingsMsg, ViewSettings, VolumeMemory, check_step)
from isosr_server.video import CodePlan, RateControl, fallback_notice
from isosr_server.views import FrameJob, ViewContext
from isosr_server.volumes import session_iso

DEFAULT_CAMERA = CameraMsg(yaw=30.0, pitch=20.0, distance=1.8)


def to_camera(msg: CameraMsg) -> Camera:
    """The renderer's camera for a camera message (look-at or orbit)."""
    if msg.eye is None:
        return orbit(msg.yaw, msg.pitch, msg.distance, msg.target, msg.fov_y)
    return Camera(msg.eye, msg.target, msg.look_up(), msg.fov_y)


class RateLimiter:
    """A token bucket: ``rate`` messages a second on average, bursts of up to ``rate``."""

    def __init__(self, rate: float):
        self.rate, self.tokens, self.stamp = rate, rate, time.monotonic()

    def allow(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.rate, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class SessionCounter:
    """A bounded count of live sessions of one kind."""

    def __init__(self, limit: int):
        self.limit, self.count = limit, 0

    def acquire(self, what: str) -> None:
        """Count one more; `ProtocolError` (CLOSE_TOO_MANY / 429) at the limit."""
        if self.count >= self.limit:
            raise ProtocolError(f"the server already serves {what} (at most {self.limit}); try later", CLOSE_TOO_MANY,
                                429)
        self.count += 1

    def release(self) -> None:
        self.count -= 1


@dataclass(frozen=True)
class ViewState:
    """What the client asked for last."""

    settings: ViewSettings
    camera: Camera
    iso: float  # normalized
    focus: FocusMsg
    ack: int = -1


@dataclass(frozen=True)
class ViewJob:
    """A frame the loop should make now, and how it is coded."""

    frame: FrameJob
    ack: int
    plan: CodePlan


class ViewSession:
    """One viewer's newest state and the bookkeeping of its frames (flow continuity, refine).

    Args:
        session_id: the id announced in ``ready``.
        volume_name, volume: what it views.
        state: the initial state (from ``open``).
        context: the server's view context (upscale factor, precision, models).
        limits: the server's limits.
        sessions: how many view sessions the server serves now (the auto mode's share).
        steps: the volume's time steps (a series: :class:`StepView`; 1 for a volume).
    """

    def __init__(self, session_id: str, volume_name: str, volume: Volume, state: ViewState, context: ViewContext,
                 limits: Limits, sessions: Callable[[], int] = lambda: 1, steps: int = 1):
        self.id, self.volume_name, self.volume = session_id, volume_name, volume
        self.context, self.limits, self.sessions, self.steps = context, limits, sessions, steps
        self.check_settings(state.settings)
        self.notices: deque[str] = deque(maxlen=8)  # to send before the next frame
        self.state = replace(state, settings=self._makeable(state.settings))
        self.rate = RateControl(state.settings.bitrate_kbps, limits.max_bitrate_kbps, limits.max_fps)
        self.interval = 1.0 / limits.max_fps  # the pause between frame starts (video: its frame rate's)
        self.keyframe_asked = False
        self.started = time.monotonic()
        self.sent_memory: VolumeMemory | None = None  # the device memory the last frame carried
        self._timestamp_us = -1
        self.version, self.changed_at = 0, time.monotonic()
        self.changed = asyncio.Event()
        self.changed.set()
        self.rendered_version = self.refined_version = -1
        self.next_seq = 0
        # Flow control: the newest frame whose sending began, and the newest the client acknowledged.
        self.sent_seq = self.received_seq = -1
        self.unacked_sent: deque[tuple[int, float]] = deque()  # (seq, when its sending began), oldest first

    def check_settings(self, settings: ViewSettings) -> None:
        """`ProtocolError` for settings no frame can be made of (:func:`isosr_server.views.check`), or
        a time step past the volume's."""
        views.check(settings, self.context)
        check_step(settings.t, self.steps, self.volume_name)

    def _makeable(self, settings: ViewSettings) -> ViewSettings:
        """``settings``, in jpeg (with a notice) where their encoding cannot be made here."""
        notice = fallback_notice(settings.encoding)
        if notice is None:
            return settings
        self.notices.append(notice)
        return msgspec.structs.replace(settings, encoding="jpeg")

    def fall_back(self, notice: str) -> None:
        """The encoder failed: jpeg from now on (the client's next encoding tries again), and a notice."""
        self.notices.append(notice)
        self.state = replace(self.state, settings=msgspec.structs.replace(self.state.settings, encoding="jpeg"))

    def refuse(self, refused: SettingRefused) -> None:
        """A settings update refused: its reason as a notice before a frame of the settings as they were,
        which acknowledges its ``seq``."""
        self.notices.append(f"settings refused, kept as they were: {refused.reason}"[:1000])
        if refused.seq is not None:
            self.state = replace(self.state, ack=max(self.state.ack, refused.seq))
        self._changed()

    def apply(self, msg: Message) -> None:
        """Take a client update (latest wins), acknowledgment or keyframe request; `ProtocolError`
        if it does not fit this session."""
        if isinstance(msg, ReceivedMsg):
            self.acknowledge(msg.frame)
            return
        s = self.state
        if isinstance(msg, KeyframeMsg):  # the current state again, as a keyframe
            self.keyframe_asked = True
            self._changed()
            return
        if isinstance(msg, CameraMsg):
            try:
                s = replace(s, camera=to_camera(msg))
            except ValueError as e:
                raise ProtocolError(f"camera: {e}") from None
        elif isinstance(msg, IsoMsg):
            s = replace(s, iso=session_iso(self.volume, self.volume_name, msg.value, msg.normalized, "iso.value"))
        elif isinstance(msg, SettingsMsg):
            settings = s.settings.updated(msg.settings, self.limits, msg.seq)
            self.check_settings(settings)
            s = replace(s, settings=self._makeable(settings))
            self.rate.set_cap(settings.bitrate_kbps)
        elif isinstance(msg, FocusMsg):
            s = replace(s, focus=msg)
        else:
            raise ProtocolError(f"a view session takes camera, iso, settings, focus and received messages, "
                                f"not {msg.TYPE}")
        if msg.seq is not None:
            s = replace(s, ack=max(s.ack, msg.seq))
        self.state = s
        self._changed()

    def _changed(self) -> None:
        self.version += 1
        self.changed_at = time.monotonic()
        self.changed.set()

    def acknowledge(self, frame: int) -> None:
        """The client took frame ``frame`` and those before it: credit for more.

        Raises:
            ProtocolError: (CLOSE_BAD_MESSAGE) ``frame`` was never sent.
        """
        if frame > self.sent_seq:
            sent = "no frame was sent yet" if self.sent_seq < 0 else f"the newest sent is {self.sent_seq}"
            raise ProtocolError(f"received: frame {frame} was never sent ({sent})")
        while self.unacked_sent and self.unacked_sent[0][0] <= frame:
            self.unacked_sent.popleft()
        if frame > self.received_seq:
            self.received_seq = frame
            self.rate.acknowledged(frame, time.monotonic())
            self.changed.set()

    def unacknowledged(self) -> int:
        """Frames made (sent, or being made) that the client has not acknowledged."""
        return self.next_seq - 1 - self.received_seq

    def has_credit(self) -> bool:
        """Whether the next frame may be made: fewer than ``max_unacked_frames`` unacknowledged."""
        return self.unacknowledged() < self.limits.max_unacked_frames

    def refine_in(self, now: float) -> float | None:
        """Seconds until the refined frame of the current state is due (None: none is)."""
        if self.refined_version == self.version or not views.refines(self.state.settings, self.context):
            return None
        return max(0.0, self.changed_at + self.state.settings.refine_after_s - now)

    def next_job(self, now: float) -> ViewJob | None:
        """The frame to make now: the newest state if not yet rendered, else a due refined frame."""
        s, st = self.state, self.state.settings
        if self.rendered_version != self.version:
            self.rendered_version, refined = self.version, False
        elif self.refine_in(now) == 0.0:
            self.refined_version, refined = self.version, True
        else:
            return None
        job = ViewJob(FrameJob(st, s.camera, s.iso, s.focus, self.next_seq, refined, self.sessions()), s.ack,
                      self._plan(st, refined, now))
        self.next_seq += 1
        return job

    def _plan(self, st: ViewSettings, refined: bool, now: float) -> CodePlan:
        """How the next frame is coded: for video at the rate control's bitrate and frame rate."""
        self._timestamp_us = max(self._timestamp_us + 1, round(1e6 * (now - self.started)))
        if st.encoding not in VIDEO_ENCODINGS:
            return CodePlan(st.encoding, st.quality, timestamp_us=self._timestamp_us, refined=refined)
        bitrate = self.rate.bitrate_kbps(now)
        fps = self.rate.fps(st.width, st.height, bitrate)
        self.interval = 1.0 / fps
        plan = CodePlan(st.encoding, st.quality, bitrate, self.rate.encoder_fps(fps, now), self._timestamp_us,
                        self.keyframe_asked, refined)
        self.keyframe_asked = False
        return plan


def step_name(name: str, t: int) -> str:
    """The engine's name of a series' step (its renderer's cache key); a volume's own name for step 0."""
    return name if t == 0 else f"{name}@t{t}"


class StepView:
    """The step of a series a view session shows, with its volume and renderer (a volume: step 0 only).

    Every step is a volume of its own (its own value range): a frame's iso, normalized for the
    session's volume (step 0), is normalized again for the step (:func:`step_iso`). The step's
    renderer is the engine's for that step: a new step is a new renderer, so the session's
    frame stream starts without history on it (the stream's key holds the renderer), the simplest
    rule under which nothing of one step ghosts into the next.

    Args:
        session: the view session (its volume is step 0).
        series: the series, or None for a volume.
        renderer: step 0's renderer.
        upload: ``await upload(name, volume)``: a step's renderer (the engine's, on its device thread).
    """

    def __init__(self, session: ViewSession, series: VolumeSeries | None, renderer: Renderer,
                 upload: Callable[[str, Volume], Awaitable[Renderer]]):
        self.session, self.series, self.upload = session, series, upload
        self.t, self.volume, self.renderer = 0, session.volume, renderer
        self.field: Volume | None = None  # the volume settings.coloring colours by (None: none, the gradient)

    async def show(self, t: int) -> None:
        """Make step ``t`` the one shown: read (or from the cache) off the event loop, its renderer
        from the engine; the next steps prefetched. A step that cannot be read keeps the one
        shown and queues a notice naming it."""
        if self.series is None:
            return
        if t != self.t:
            try:
                volume = await asyncio.to_thread(self.series.step, t)
            except (VolumeError, OSError) as e:
                self.session.notices.append(f"time step {t} ({self.series.labels[t]}) cannot be read: "
                                            f"{' '.join(str(e).split())}; showing step {self.t}"[:1000])
            else:
                self.renderer = await self.upload(step_name(self.session.volume_name, t), volume)
                self.t, self.volume = t, volume
        self.series.prefetch(self.t)

    def job(self, frame: FrameJob) -> FrameJob:
        """``frame`` for the step shown: its iso normalized for the step, its settings' ``t`` the step's."""
        if self.series is None:
            return frame
        settings = msgspec.structs.replace(frame.settings, t=self.t)
        return replace(frame, settings=settings, iso=step_iso(frame.iso, self.session.volume, self.volume))


# Makes a frame on the device; what it returns encodes it (engine.view_frame).
FrameMaker = Callable[[ViewJob], Awaitable[Callable[[], Awaitable[EncodedFrame]]]]


async def run_frames(session: ViewSession, make: FrameMaker, send: Callable[[Message], Awaitable[None]]) -> None:
    """The session's frame loop (runs until cancelled): wait for a new state or a due refine,
    then for credit (`ViewSession.has_credit`), keep at most ``max_fps`` (video: its frame rate),
    make the frame (``make``, on the device thread), then encode and send it (after the notices
    due) in a task of its own, one frame after the other, while the loop goes on.

    Raises:
        ProtocolError: (CLOSE_IDLE) the client acknowledged no frame for ``idle_timeout_s``
            while the session had a frame to make; or what ended the sending.
    """
    last_start = -float("inf")
    stalled_since: float | None = None
    sender: asyncio.Task | None = None
    try:
        while True:
            if sender is not None and sender.done():
                sender.result()  # raises what ended the sending
            session.changed.clear()
            now = time.monotonic()
            if session.rendered_version == session.version:
                wait = session.refine_in(now)
                if wait is None or wait > 0:
                    await _wait(session.changed, wait, sender)
                    continue
            if not session.has_credit():
                session.rate.lagging(now)
                stalled_since = now if stalled_since is None else stalled_since
                left = stalled_since + session.limits.idle_timeout_s - now
                if left <= 0:
                    raise ProtocolError(f"the client acknowledged no frame for {session.limits.idle_timeout_s:g} s "
                                        f"({session.unacknowledged()} unacknowledged)", CLOSE_IDLE, 408)
                await _wait(session.changed, left, sender)  # updates coalesce meanwhile; an acknowledgment wakes it
                continue
            stalled_since = None
            pause = last_start + session.interval - now
            if pause > 0:
                await asyncio.sleep(pause)  # updates arriving meanwhile coalesce into the state
            job = session.next_job(time.monotonic())
            if job is None:
                continue
            last_start = time.monotonic()
            encode = await make(job)
            sender = asyncio.create_task(_send_frame(session, job, encode, sender, send))
    finally:
        if sender is not None:
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)


async def _send_frame(session: ViewSession, job: ViewJob, encode: Callable[[], Awaitable[EncodedFrame]],
                      before: asyncio.Task | None, send: Callable[[Message], Awaitable[None]]) -> None:
    """Encode and send one frame once the frame ``before`` it is sent (frames go out in order)."""
    if before is not None:
        await before
    made = await encode()
    coded = made.image
    if coded is not None and coded.notice is not None:
        session.fall_back(coded.notice)
    while session.notices:
        await send(NoticeMsg(session.notices.popleft()))
    f, st = job.frame, job.frame.settings
    image = {"encoding": "buffers"} if coded is None else {
        "image": coded.data, "encoding": coded.encoding, "keyframe": coded.keyframe, "codec": coded.codec,
        "bitrate_kbps": coded.bitrate_kbps}
    msg = FrameMsg(seq=f.seq, ack=job.ack, mode="full" if f.refined else st.mode, width=st.width,
                   height=st.height, times=made.times, nbytes=frame_bytes(made),
                   refined=f.refined, buffers=made.buffers, prev_seq=made.prev_seq,
                   legend=None if made.legend is None else Legend(**made.legend), method=made.method,
                   timestamp_us=job.plan.timestamp_us,
                   device=None if made.memory == session.sent_memory else made.memory, t=made.t,
                   batch=made.batch, choice=made.choice, **image)
    session.sent_memory = made.memory
    session.sent_seq = f.seq  # before sending: the client may acknowledge it before send returns
    session.unacked_sent.append((f.seq, time.monotonic()))
    session.rate.sent(f.seq, msg.nbytes, time.monotonic())
    await send(msg)


async def watch_acks(session: ViewSession) -> None:
    """Runs until cancelled, beside the frame loop: a frame the client has not acknowledged within
    ``ack_timeout_s`` of its sending ends the session, whatever else the client sends (a party that
    never acknowledges holds no session slot for longer).

    Raises:
        ProtocolError: (CLOSE_IDLE) the oldest unacknowledged frame went out ``ack_timeout_s`` ago.
    """
    timeout = session.limits.ack_timeout_s
    while True:
        if not session.unacked_sent:
            await asyncio.sleep(timeout)  # a frame sent meanwhile is due after this wakes
            continue
        seq, sent_at = session.unacked_sent[0]
        left = sent_at + timeout - time.monotonic()
        if left <= 0:
            raise ProtocolError(f"frame {seq} was not acknowledged (received) within {timeout:g} s "
                                f"(ack_timeout_s)", CLOSE_IDLE, 408)
        await asyncio.sleep(left)


def frame_bytes(made: EncodedFrame) -> int:
    """Payload bytes of a frame: the image, or the coded buffers' data."""
    return len(made.image.data) if made.image is not None else made.buffers.nbytes


async def _wait(event: asyncio.Event, timeout: float | None, sender: asyncio.Task | None = None) -> None:
    """Wait until ``event`` is set, ``timeout`` seconds (None: no limit) have passed, or ``sender``
    (the frame being sent) is done."""
    waits = [asyncio.ensure_future(event.wait())] + ([sender] if sender is not None and not sender.done() else [])
    try:
        await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waits[0].cancel()


@dataclass
class _IdSession:
    network: RecurrentNetwork
    client: str
    used: float


class UpscaleSessions:
    """Recurrent networks by network class and session id (``POST /v1/upscale``'s ``session``, the
    infer endpoints' ``sequence_id``: each model its own state per id) plus open upscale streams.

    Bounded in number (``max_sessions`` together; at most ``max_sessions_per_client`` ids per
    client address, 429 past it), and in the memory their recurrent states hold
    (``max_upscale_bytes``). Past either server-wide bound the least recently used ids are
    dropped, so no client holds slots the others need: a dropped id restarts its recurrence on
    its next request (as after ``idle_timeout_s`` without one, when ids expire). Streams are
    connections: they are refused (429) when every slot is a stream's.
    """

    def __init__(self, limits: Limits, make: Callable[[type[RecurrentNetwork]], RecurrentNetwork]):
        self.limits, self.make = limits, make
        self._by_id: OrderedDict[tuple[type[RecurrentNetwork], str], _IdSession] = OrderedDict()
        self._streams: list[Upscaler] = []
        self.streams = SessionCounter(limits.max_sessions)

    def __len__(self) -> int:
        return len(self._by_id) + self.streams.count

    def held_bytes(self) -> int:
        """Bytes the sessions' recurrent states hold."""
        nets = [s.network for s in self._by_id.values()] + self._streams
        return sum(u.state_bytes() for u in nets)

    def trim(self, keep: RecurrentNetwork | None = None) -> int:
        """Drop the least recently used ids (never the one of ``keep``) while the states hold more
        than ``max_upscale_bytes``; returns how many."""
        dropped = 0
        for k in [k for k, s in self._by_id.items() if s.network is not keep]:
            if self.held_bytes() <= self.limits.max_upscale_bytes:
                break
            del self._by_id[k]
            dropped += 1
        return dropped

    def expire(self, now: float) -> int:
        """Drop sessions idle longer than the timeout; returns how many."""
        stale = [k for k, s in self._by_id.items() if now - s.used > self.limits.idle_timeout_s]
        for k in stale:
            del self._by_id[k]
        return len(stale)

    def get(self, session_id: str, client: str, cls: type[RecurrentNetwork] = Upscaler) -> RecurrentNetwork:
        """The id's network of ``cls`` (a new one for a new id: `ProtocolError` 429 when ``client``
        holds its bound already; the least recently used id dropped when the server is full)."""
        now = time.monotonic()
        self.expire(now)
        key = (cls, session_id)
        if key not in self._by_id:
            held = sum(s.client == client for s in self._by_id.values())
            if held >= self.limits.max_sessions_per_client:
                raise ProtocolError(f"this client holds {held} upscale sessions already, the most one address may; "
                                    f"reuse one or let one expire", CLOSE_TOO_MANY, 429)
            self._make_room()
            self._by_id[key] = _IdSession(self.make(cls), client, now)
        session = self._by_id[key]
        session.used = now
        self._by_id.move_to_end(key)
        return session.network

    def _make_room(self) -> None:
        """One free slot: drop the least recently used id if every slot is taken; 429 if all are streams'."""
        if len(self) < self.limits.max_sessions:
            return
        if not self._by_id:
            raise ProtocolError(f"the server already holds {self.limits.max_sessions} upscale sessions; try later",
                                CLOSE_TOO_MANY, 429)
        self._by_id.popitem(last=False)

    def open_stream(self) -> Upscaler:
        """Count a stream (`ProtocolError` 429 when every slot is a stream's) and give it its own upscaler."""
        self.expire(time.monotonic())
        self._make_room()
        self.streams.acquire("upscale streams")
        self._streams.append(self.make(Upscaler))
        return self._streams[-1]

    def close_stream(self, upscaler: Upscaler) -> None:
        self._streams.remove(upscaler)
        self.streams.release()
