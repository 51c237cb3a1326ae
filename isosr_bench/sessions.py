"""View sessions against a running server, closed loop or dragging (open loop), for the service benchmarks.

The client side of :mod:`isosr_bench.bench_server` and :mod:`isosr_bench.bench_cluster`. It imports
the client alone (no torch): the client processes that sessions are dealt to start in well under
a second, so a case's set-up is not the spawn of several interpreters importing the network stack.
"""

from __future__ import annotations

import argparse
import faulthandler
import math
import multiprocessing
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait

import numpy as np

from isosr_client.drive import Orbit, drag, drive, summarize
from isosr_client.view import FrameStats, connect


def run_sessions(url: str, volume: str, sessions: int, seconds: float, mode: str, size: tuple[int, int],
                 settings: dict, focus: tuple[float, float, float] | None = None, warmup_frames: int = 2,
                 max_frames: int = 100_000, processes: int = 1, on_start: Callable[[], None] | None = None,
                 compression: str | None = None, settle_s: float = 0.0, drag_hz: float = 0.0) -> dict:
    """``sessions`` concurrent view sessions (one thread each) for ``seconds`` after
    ``warmup_frames`` untimed frames each, then ``settle_s`` untimed seconds (``auto``'s probes and re-choices
    under the load: its steady state, where 0 times its first seconds); every session orbits from its own start
    yaw.
    ``focus``: the focus circle (x, y, radius in pixels) of ``focus`` mode. ``processes``: client
    processes the sessions are dealt to (one process's threads share one interpreter lock, which
    must not bound what several GPUs serve); the timed span starts together in all, and
    ``on_start`` is called as it starts. ``compression``: the sessions' WebSocket compression
    (`isosr_client.view.connect`; ``"deflate"`` as browsers offer it). ``drag_hz``: 0, each session closed loop
    (`isosr_client.drive.drive`: one frame in flight); else its cameras sent at that rate and its frames taken as
    they come (`isosr_client.drive.drag`, as a browser viewer while its user drags), the settling too.

    Returns:
        `isosr_client.drive.summarize` of all frames with ``fps`` summed over the sessions,
        plus ``fps_per_session``, ``errors`` (exception texts), ``sessions``, the ``methods``, the
        frames' mean ``batch`` (frames the server made together) as ``batch_mean``, and the
        ``replicas`` (``isosr serve --replicas``) that made the frames, and ``auto``'s ``choices``
        (:func:`auto_choices`).
    """
    processes = max(1, min(processes, sessions))
    job = (url, volume, sessions, seconds, mode, size, settings, focus, warmup_frames, max_frames, compression,
           settle_s, drag_hz)
    if processes == 1:
        opened = threading.Barrier(sessions + 1)
        waiter = threading.Thread(target=_wait_opened, args=(opened, on_start), daemon=True)
        waiter.start()
        parts = [drive_sessions(job, range(sessions), opened)]
    else:
        context = multiprocessing.get_context("spawn")  # a fork would copy this process's torch and threads
        with context.Manager() as manager, ProcessPoolExecutor(processes, mp_context=context,
                                                                initializer=faulthandler.enable) as pool:
            opened = manager.Barrier(sessions + 1)
            futures = [pool.submit(drive_sessions, job, range(p, sessions, processes), opened)
                       for p in range(processes)]
            threading.Thread(target=_wait_opened, args=(opened, on_start), daemon=True).start()
            done, _ = wait(futures, return_when=FIRST_EXCEPTION)
            if any(f.exception() for f in done):  # a process died: the others' sessions stop at the barrier
                opened.abort()
            parts = [f.result() for f in futures]
    stats = [s for part in parts for s in part[0]]
    busy = [b for part in parts for b in part[1]]
    errors = [e for part in parts for e in part[2]]
    frames = [s for per in stats for s in per]
    if not frames:
        return {"sessions": sessions, "errors": errors or ["no frames"]}
    result = summarize(frames, 1.0)
    per_session_fps = [len(s) / b for s, b in zip(stats, busy) if b > 0]
    result.update(sessions=sessions, errors=errors, fps=float(sum(per_session_fps)),
                  fps_per_session=float(np.mean(per_session_fps)), methods=sorted({s.method for s in frames}),
                  choices=auto_choices(stats, busy),
                  batch_mean=float(np.mean([s.batch for s in frames])),
                  replicas=sorted({s.replica for s in frames if s.replica is not None}))
    return result


def add_drag_argument(parser) -> None:
    """The service benchmarks' ``--drag-hz``: their sessions' client model (:func:`run_sessions`' ``drag_hz``)."""
    def rate(text: str) -> float:
        value = float(text)
        if not (math.isfinite(value) and value >= 0):
            raise argparse.ArgumentTypeError(f"a rate in Hz, 0 or more (0: closed loop), got {text!r}")
        return value
    parser.add_argument("--drag-hz", type=rate, default=0.0, metavar="HZ",
                        help="each session sends its cameras at HZ and takes frames as they come, as a browser viewer "
                             "while its user drags (default 0: closed loop, one frame in flight)")


def client_model(drag_hz: float) -> str:
    """A row's name for its sessions' client model."""
    return f"drag {drag_hz:g} Hz" if drag_hz else "closed loop"


def result_suffix(drag_hz: float) -> str:
    """What a result file's name adds for dragging sessions (their rows kept apart from closed-loop ones)."""
    return "_drag" if drag_hz else ""


def auto_choices(stats: list[list[FrameStats]], busy: list[float]) -> dict[str, dict]:
    """What ``auto`` expected of each method it chose, over the frames that say (by method name): its
    frames, mean expected PSNR and time, mean budget, and where the expectations came from; and what the
    viewers got of it: its frames a second over all sessions (``fps``), the ``sessions`` that made most of
    their frames with it and those sessions' frames a second (``session_fps_mean``, ``session_fps_min``;
    None where no session did). ``stats`` and ``busy``: each session's frames and timed seconds."""
    by_method: dict[str, list] = {}
    rate: dict[str, float] = {}
    mostly: dict[str, list[float]] = {}
    for frames, seconds in zip(stats, busy):
        chosen = [s for s in frames if s.choice is not None]
        for s in chosen:
            by_method.setdefault(s.method, []).append(s.choice)
        if not chosen or seconds <= 0:
            continue
        counts = Counter(s.method for s in chosen)
        for method, n in counts.items():
            rate[method] = rate.get(method, 0.0) + n / seconds
        mostly.setdefault(counts.most_common(1)[0][0], []).append(len(frames) / seconds)
    mean = (lambda values: float(np.mean(values)) if values else None)
    return {method: {"frames": len(cs), "psnr_db": mean([c.psnr_db for c in cs if c.psnr_db is not None]),
                     "ms": mean([c.ms for c in cs if c.ms is not None]), "budget_ms": mean([c.budget_ms for c in cs]),
                     "sources": sorted({c.source for c in cs}), "fps": rate.get(method, 0.0),
                     "sessions": len(mostly.get(method, [])), "session_fps_mean": mean(mostly.get(method, [])),
                     "session_fps_min": min(mostly[method]) if mostly.get(method) else None}
            for method, cs in sorted(by_method.items())}


def choices_line(choices: dict[str, dict]) -> str:
    """:func:`auto_choices` in one line for a console: each method, its expected PSNR and time against
    the budget, where the expectation came from, its rate and the sessions that mostly made it."""
    def number(value: float | None, digits: int) -> str:
        return "?" if value is None else f"{value:.{digits}f}"
    return "; ".join(f"{method}: {number(c['psnr_db'], 1)} dB, {number(c['ms'], 2)} of {c['budget_ms']:.2f} ms "
                     f"({'/'.join(c['sources'])}, {c['frames']} frames, {c['fps']:.1f}/s; mostly in {c['sessions']} "
                     f"sessions at {number(c['session_fps_min'], 1)}-{number(c['session_fps_mean'], 1)}/s)"
                     for method, c in choices.items())


def _wait_opened(opened, on_start: Callable[[], None] | None) -> None:
    """The timed span starts once every session is warm (or one failed: it aborts the barrier)."""
    try:
        opened.wait(timeout=300)
    except threading.BrokenBarrierError:
        return
    if on_start is not None:
        on_start()


def drive_sessions(job: tuple, ks: range, opened) -> tuple[list[list[FrameStats]], list[float], list[str]]:
    """Sessions ``ks`` of :func:`run_sessions`' ``job``, one thread each, in this process: their
    frames' stats, their busy seconds and the errors. They wait at ``opened`` after warming up."""
    (url, volume, sessions, seconds, mode, size, settings, focus, warmup_frames, max_frames, compression, settle_s,
     drag_hz) = job
    stats: dict[int, list[FrameStats]] = {k: [] for k in ks}
    busy = dict.fromkeys(ks, 0.0)
    errors: list[str] = []

    def timed(view, path: Orbit, stop_at: float) -> tuple[list[FrameStats], float]:
        if drag_hz:
            return drag(view, path, max_frames, drag_hz, stop_at)
        return drive(view, path, max_frames, rgb=False, stop_at=stop_at)

    def viewer(k: int) -> None:
        path = Orbit(yaw=30.0 + 360.0 * k / sessions)
        try:
            with connect(url, volume, mode, size, settings=dict(settings, refine=False), local_upscale=False,
                         timeout=120, compression=compression) as view:
                if focus is not None:
                    view.set_focus("circle", focus[:2], focus[2])
                drive(view, path, warmup_frames, rgb=False)
                if settle_s > 0:
                    timed(view, path, stop_at=time.monotonic() + settle_s)
                opened.wait()
                stats[k], busy[k] = timed(view, Orbit(path.yaw + 10, path.pitch, path.distance),
                                          stop_at=time.monotonic() + seconds)
        except threading.BrokenBarrierError:
            pass
        except Exception as e:  # reported in the result: a load test counts them
            errors.append(f"session {k}: {type(e).__name__}: {e}")
            opened.abort()

    threads = {k: threading.Thread(target=viewer, args=(k,), daemon=True) for k in ks}
    for t in threads.values():
        t.start()
    for t in threads.values():
        t.join(settle_s + seconds + 420)
    errors += [f"session {k}: did not finish" for k, t in threads.items() if t.is_alive()]
    return [stats[k] for k in ks], [busy[k] for k in ks], errors
