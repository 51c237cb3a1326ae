"""``WS /v1/view``: a view session (the protocol module's docstring): ``open`` -> ``ready`` and
frames; then camera, iso, settings and focus updates, each answered by a frame the client acknowledges."""

from __future__ import annotations

import asyncio
import logging
import os
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace

import msgspec
from msgspec import UNSET
from fastapi import APIRouter, WebSocket

from isosr_server.api.deps import AuthorizedDep, CatalogDep, EngineDep, LimitsDep, MetricsDep, ViewSessionsDep
from isosr_server.api.ws import accept, end_ws, rate_limiter, receive
from isosr_server.engine import EncodedFrame, Engine
from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import (CLIENT_VIEW_MESSAGES, CLOSE_IDLE, VIDEO_ENCODINGS, FocusMsg, FrameMsg, Limits,
                                   Message, NoticeMsg, OpenMsg, PickMsg, ProtocolError, ReadyMsg, SettingRefused,
                                   SettingsMsg, ViewSettings, VolumeSummary, encode, parse, surfaces_of)
from isosr_server.sessions import (DEFAULT_CAMERA, SessionCounter, StepView, ViewJob, ViewSession, ViewState,
                                   run_frames, to_camera, watch_acks)
from isosr_server.video import SessionCoder
from isosr_server.views import FrameJob
from isosr_server.volumes import VolumeCatalog, coloring_field, load_volume, session_iso

log = logging.getLogger("isosr.server")

router = APIRouter(tags=["view"])


@router.websocket("/v1/view")
async def view(ws: WebSocket, authorized: AuthorizedDep, engine: EngineDep, catalog: CatalogDep, limits: LimitsDep,
               metrics: MetricsDep, view_sessions: ViewSessionsDep):
    if not await accept(ws, authorized, metrics):
        return
    limiter = rate_limiter(ws, limits)
    counted, tasks = False, []
    coder = SessionCoder(os.cpu_count() or 1)
    try:
        # A slot is taken only once a valid open arrived: a silent connection holds none.
        opened = parse(await receive(ws, limiter, limits), limits, (OpenMsg,))
        view_sessions.acquire("view sessions")
        counted = True
        metrics.sessions.labels("view").set(view_sessions.count)
        session, shown = await open_view(ws, opened, limits, catalog, engine, view_sessions)
        link = ViewLink(ws, engine, metrics, limits, session, shown, coder)
        tasks = [asyncio.create_task(run_frames(session, link.make, link.send)),
                 asyncio.create_task(take_updates(ws, limiter, limits, session, link.answer, catalog, shown)),
                 asyncio.create_task(watch_acks(session))]
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            task.result()  # raises what ended the session
    except Exception as e:
        await end_ws(ws, "view", e, metrics)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await asyncio.get_running_loop().run_in_executor(None, coder.close)  # after a frame still encoding
        if counted:
            view_sessions.release()
            metrics.sessions.labels("view").set(view_sessions.count)


class ViewLink:
    """An open view session's traffic: its frames made on the engine and coded by its coder, messages
    sent within the idle timeout (frames counted in the metrics), and picks answered."""

    def __init__(self, ws: WebSocket, engine: Engine, metrics: ServerMetrics, limits: Limits, session: ViewSession,
                 shown: StepView, coder: SessionCoder):
        self.ws, self.engine, self.metrics, self.limits = ws, engine, metrics, limits
        self.session, self.shown, self.coder = session, shown, coder
        self.frames = engine.new_session_frames(session.volume_name)

    async def make(self, job: ViewJob) -> Callable[[], Awaitable[EncodedFrame]]:
        """Make ``job``'s frame on the step it shows (:func:`run_frames`' maker); returns its encoding."""
        plan, shown = job.plan, self.shown
        await shown.show(job.frame.settings.t)
        frame = replace(shown.job(job.frame), field=shown.field)
        video = plan.encoding if plan.encoding in VIDEO_ENCODINGS and not plan.refined else None
        return await self.engine.view_frame(self.frames, shown.renderer, frame,
                                            lambda rgb, i420: self.coder.code(rgb, plan, i420), video,
                                            deadline=time.monotonic() + self.session.interval,
                                            jpeg=plan.quality if plan.encoding == "jpeg" else None)

    async def send(self, msg: Message) -> None:
        """Send ``msg``; a client that reads nothing for ``idle_timeout_s`` ends the session (CLOSE_IDLE)."""
        timeout = self.limits.idle_timeout_s
        try:
            async with asyncio.timeout(timeout):  # no task a send, as wait_for makes on Python 3.11
                await self.ws.send_bytes(encode(msg))
        except TimeoutError:
            raise ProtocolError(f"the client read no frame for {timeout:g} s", CLOSE_IDLE, 408) from None
        if isinstance(msg, FrameMsg):
            self.metrics.frame("view", msg.mode, msg.refined, msg.times, msg.nbytes, msg.batch)

    async def answer(self, msg: PickMsg) -> None:
        """A pick, at once, between frames, on the current view (its step)."""
        s = self.session.state
        job = self.shown.job(FrameJob(s.settings, s.camera, s.iso, s.focus, 0, False, 1))
        await self.send(await self.engine.pick(self.shown.renderer, job, msg))


async def take_updates(ws: WebSocket, limiter, limits: Limits, session: ViewSession,
                       answer: Callable[[PickMsg], Awaitable[None]], catalog: VolumeCatalog, shown: StepView) -> None:
    """A view session's client messages, until the connection ends: picks answered (``answer``),
    the rest applied to the session's state (a coloring's field volume resolved into ``shown``); a
    `SettingRefused` leaves the state as it was (:meth:`ViewSession.refuse`)."""
    while True:
        data, field = await receive(ws, limiter, limits), shown.field
        try:
            msg = parse(data, limits, CLIENT_VIEW_MESSAGES)
            if isinstance(msg, SettingsMsg) and msg.settings.coloring is not UNSET:  # its field resolved first
                field = await coloring_field(catalog, session.state.settings.updated(msg.settings, limits, msg.seq),
                                             session.volume, msg.seq)
            if isinstance(msg, SettingsMsg) and msg.settings.surfaces is not UNSET:  # checked on the volume first
                surfaces_of(session.state.settings.updated(msg.settings, limits, msg.seq).surfaces,
                            session.volume.normalized_iso, msg.seq)
        except SettingRefused as e:
            session.refuse(e)
            continue
        if isinstance(msg, PickMsg):
            await answer(msg)
        else:
            session.apply(msg)
            shown.field = field


async def open_view(ws: WebSocket, msg: OpenMsg, limits: Limits, catalog: VolumeCatalog,
                    engine: Engine, view_sessions: SessionCounter) -> tuple[ViewSession, StepView]:
    """Load the volume ``open`` names, answer ``ready``: the new session and the step it shows."""
    volume, info = await load_volume(catalog, msg.volume)
    settings = ViewSettings().updated(msg.settings, limits)
    given = msg.iso is not None
    normalized = session_iso(volume, msg.volume, msg.iso if given else info.iso, given and msg.iso_normalized,
                             "open.iso" if given else "open.volume")
    try:
        camera = to_camera(msg.camera or DEFAULT_CAMERA)
    except ValueError as e:
        raise ProtocolError(f"open.camera: {e}") from None
    state = ViewState(settings, camera, normalized, FocusMsg("none"),
                      msg.camera.seq if msg.camera and msg.camera.seq is not None else -1)
    session = ViewSession(secrets.token_hex(8), msg.volume, volume, state, engine.context, limits,
                          lambda: view_sessions.count, info.steps)
    renderer = await engine.call(engine.renderer_sync, msg.volume, volume)
    shown = StepView(session, catalog.series(msg.volume) if info.steps > 1 else None, renderer,
                     lambda name, step: engine.call(engine.renderer_sync, name, step))
    shown.field = await coloring_field(catalog, session.state.settings, volume)
    summary = msgspec.convert(info.to_json() | {"iso_normalized": normalized}, VolumeSummary)
    ready = ReadyMsg(session.id, summary, session.state.settings,
                     engine.upscale_factor, engine.recon_limits.max_ao_rays, limits, engine.modes,
                     engine.encodings())
    await ws.send_bytes(encode(ready))
    while session.notices:  # why the encoding is not the one asked for
        await ws.send_bytes(encode(NoticeMsg(session.notices.popleft())))
    log.info("view session %s opened on %s (%s %dx%d, %s)", session.id, msg.volume, settings.mode, settings.width,
             settings.height, session.state.settings.encoding)
    return session, shown
