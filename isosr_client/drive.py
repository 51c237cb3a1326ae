"""Driving a view session along a camera path, closed or open loop, and summarizing what it cost.

Closed loop (:func:`drive`): send a camera, wait for the frame that includes it, send the next. So a
frame's latency is the round trip of one camera change (network, queueing on the server's device,
render, network, encode, transfer), and frames/s is what one viewer gets when it asks for the next
frame as soon as it has one: one frame in flight, its whole round trip a frame's interval.

Open loop (:func:`drag`): send a camera at a fixed rate and take the frames as they come, as a
browser viewer does while its user drags (the server makes the newest state whenever the flow
control's credit allows, several frames in flight). A frame's latency is from the newest camera it
includes; frames/s is bounded by the rate, the server and the link, not by one round trip.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from isosr_client.view import FrameStats, ViewFrame, ViewSession


@dataclass(frozen=True)
class Orbit:
    """An orbit path: frame ``i`` looks from ``yaw + i * yaw_step``, ``pitch``, ``distance`` (degrees,
    world units) at the volume's center."""

    yaw: float = 30.0
    pitch: float = 20.0
    distance: float = 1.8
    yaw_step: float = 2.0

    @classmethod
    def parse(cls, text: str) -> "Orbit":
        """``YAW,PITCH,DIST[,YAWSTEP]``; ValueError for anything else."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            values = []
        if len(values) not in (3, 4) or not all(np.isfinite(values)):
            raise ValueError(f"--orbit must be YAW,PITCH,DIST[,YAWSTEP] (finite numbers), got {text!r}")
        return cls(*values)

    def camera(self, i: int) -> dict:
        """Frame ``i``'s camera as `ViewSession.set_camera` keywords."""
        return {"yaw": self.yaw + i * self.yaw_step, "pitch": self.pitch, "distance": self.distance}


def drive(session: ViewSession, path: Orbit, frames: int, rgb: bool = True,
          on_frame: Callable[[int, ViewFrame], None] | None = None,
          stop_at: float | None = None) -> tuple[list[FrameStats], float]:
    """Show ``frames`` frames of ``path`` closed loop (or fewer, once ``time.monotonic()`` passes
    ``stop_at``).

    Args:
        session: the view session.
        path: the cameras.
        frames: how many.
        rgb: get each frame as RGB (decode the image, or shade the upscaled buffers) inside the
            timed loop, as a viewer would; off, frames stay coded (timing the server).
        on_frame: ``on_frame(i, frame)`` sees each frame outside the timed loop (writing files).
        stop_at: a deadline on ``time.monotonic()``.

    Returns:
        ``(stats per frame, seconds spent in the timed loop)``.
    """
    stats, busy = [], 0.0
    for i in range(frames):
        if stop_at is not None and time.monotonic() >= stop_at:
            break
        start = time.perf_counter()
        session.set_camera(**path.camera(i))
        frame = session.latest()
        if rgb:
            frame.rgb()
        busy += time.perf_counter() - start
        stats.append(frame.stats)
        if on_frame is not None:
            on_frame(i, frame)
    return stats, busy


def drag(session: ViewSession, path: Orbit, frames: int, rate_hz: float,
         stop_at: float | None = None) -> tuple[list[FrameStats], float]:
    """Send ``path``'s first ``frames`` cameras at ``rate_hz`` (open loop) and take every frame as it comes, until
    they are sent and the last is shown, or ``time.monotonic()`` passes ``stop_at``.

    Returns:
        ``(stats per frame received, seconds from the first camera to the end)``.

    Raises:
        ValueError: ``rate_hz`` is not a positive finite number.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be a positive finite number, got {rate_hz!r}")
    stats: list[FrameStats] = []
    start = time.monotonic()
    end = float("inf") if stop_at is None else stop_at
    sent = -1
    for i in range(frames):
        tick = start + i / rate_hz
        if tick >= end:
            break
        while (left := min(tick, end) - time.monotonic()) > 0:  # frames arriving before this camera is due
            frame = session.receive(left)
            if frame is not None:
                stats.append(frame.stats)
        sent = session.set_camera(**path.camera(i))
    while sent >= 0 and (not stats or stats[-1].ack < sent) and (left := end - time.monotonic()) > 0:  # its frame
        frame = session.receive(min(left, session.timeout))
        if frame is None and left > session.timeout:
            raise TimeoutError(f"no frame with update {sent} within {session.timeout:g} s")
        if frame is not None:
            stats.append(frame.stats)
    return stats, time.monotonic() - start


def summarize(stats: list[FrameStats], seconds: float) -> dict:
    """frames, frames/s, latency mean, p50 and p99 (ms), mean bytes per frame, mean server and
    client milliseconds per stage."""
    if not stats:
        raise ValueError("no frames to summarize")
    latency = np.array([s.latency_ms for s in stats])
    server = {k: float(np.mean([s.server_ms.get(k, 0.0) for s in stats]))
              for k in sorted({k for s in stats for k in s.server_ms})}
    client = {k: float(np.mean([s.client_ms.get(k, 0.0) for s in stats]))
              for k in sorted({k for s in stats for k in s.client_ms})}
    return {"frames": len(stats), "fps": len(stats) / seconds if seconds > 0 else float("nan"),
            "latency_mean_ms": float(latency.mean()), "latency_p50_ms": float(np.percentile(latency, 50)),
            "latency_p99_ms": float(np.percentile(latency, 99)),
            "bytes_per_frame": float(np.mean([s.nbytes for s in stats])), "server_ms": server, "client_ms": client}
