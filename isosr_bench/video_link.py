"""A slow link on loopback, and one viewer of a real server over it (bench_video's link run).

`Throttle` is a TCP proxy on a free loopback port that forwards each connection to the server,
the server's bytes to the client paced at ``rate_bps`` (a link of that throughput and no
propagation delay: add a real link's round trip to the latencies measured), the client's
unpaced (camera updates and acknowledgments are a few hundred bytes a second). Its buffers are
bounded: it holds one chunk of `CHUNK` bytes at a time and reads the server's socket with a
receive buffer of `RECEIVE_BUFFER` bytes, so what the link has not carried waits in the
server's socket, where a real link's would queue, and the server's flow control (frames in
flight within ``max_unacked_frames``) is what bounds it.

`link_run` drives one view session through it open loop, as a user dragging the camera: a new
camera every ``1 / input_hz`` seconds along an orbit whatever has arrived, and frames taken as
they come (:meth:`isosr_client.view.ViewSession.receive`; video decoded as it arrives, JPEG
decoded here). A frame's latency is the client's: from sending the newest camera it includes
to its arrival; ``display`` adds this side's decode.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from isosr_client.drive import Orbit
from isosr_client.view import connect

# Bytes the proxy forwards at a time (3.3 ms at 10 Mbit/s) and the receive buffer of its socket to the server.
CHUNK = 4096
RECEIVE_BUFFER = 65536
# How late the pacing thread may wake (the GIL, the scheduler) and still make the time up: the link
# bursts at most this long.
SLACK_S = 0.005


class Throttle:
    """A loopback TCP proxy to ``target_port`` whose server-to-client bytes go at ``rate_bps``
    (module docstring); a context manager (``url``: its address as an http URL).

    Args:
        target_port: the server's port on 127.0.0.1.
        rate_bps: the link's throughput in bits per second.
    """

    def __init__(self, target_port: int, rate_bps: float):
        if not rate_bps > 0:
            raise ValueError(f"throttle: rate_bps must be positive, got {rate_bps!r}")
        self.target_port, self.rate_bps = target_port, float(rate_bps)
        self.carried = 0  # bytes carried to clients
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._listener.getsockname()[1]}"
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []

    def __enter__(self) -> "Throttle":
        threading.Thread(target=self._accept, daemon=True).start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for s in [self._listener, *self._sockets]:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            upstream = socket.socket()
            upstream.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)  # before connect: the window
            upstream.connect(("127.0.0.1", self.target_port))
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._sockets += [client, upstream]
            threading.Thread(target=self._pump, args=(upstream, client, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(client, upstream, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, paced: bool) -> None:
        """Forward ``src`` to ``dst``; paced, a chunk leaves once the link has carried it (the link
        is free again at ``free_at``; a late wake-up within SLACK_S is made up)."""
        free_at = 0.0
        try:
            while chunk := src.recv(CHUNK):
                if paced:
                    free_at = max(time.perf_counter() - SLACK_S, free_at) + 8 * len(chunk) / self.rate_bps
                    while (wait := free_at - time.perf_counter()) > 0:
                        time.sleep(wait)
                    self.carried += len(chunk)
                dst.sendall(chunk)
        except OSError:
            pass
        try:
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            pass


def link_run(url: str, rate_bps: float, volume: str, mode: str, size: tuple[int, int], settings: dict,
             seconds: float, input_hz: float, path: Orbit, warmup_frames: int = 3) -> dict:
    """One view session through a `Throttle` of ``rate_bps`` to the server at ``url`` for ``seconds``
    after ``warmup_frames`` closed-loop frames (module docstring).

    Returns:
        frames, frames/s, latency and display latency p50/p99 (ms), payload bytes per frame and
        kbit/s, the link's kbit/s (the proxy's count), keyframes, the server's mean ms per stage (render
        to encode: made one after the other, they bound a session's frame rate), the server's targets (kbit/s; 0 for
        images), frames that could not be decoded (left out of the rest), the encodings and methods
        of the frames, decode ms and the session's notices.
    """
    port = int(url.rsplit(":", 1)[1])
    with Throttle(port, rate_bps) as link, connect(link.url, volume, mode, size, settings=dict(settings, refine=False),
                                                   local_upscale=False, timeout=120) as view:
        for i in range(warmup_frames):
            view.set_camera(**path.camera(i))
            view.frame()
        stats, undecodable, tick, carried = [], 0, 1.0 / input_hz, link.carried
        start = time.perf_counter()
        for i in range(warmup_frames, warmup_frames + round(seconds * input_hz)):
            view.set_camera(**path.camera(i))
            due = start + (i - warmup_frames + 1) * tick
            while (left := due - time.perf_counter()) > 0:
                frame = view.receive(left)
                if frame is None:
                    continue
                if frame.error is None:
                    frame.rgb()  # a viewer shows it (video: decoded on arrival)
                    stats.append(frame.stats)
                else:
                    undecodable += 1
        elapsed = time.perf_counter() - start
        carried = link.carried - carried
        notices = list(view.notices)
    if not stats:
        return {"frames": 0, "undecodable": undecodable, "notices": notices}
    latency = np.array([s.latency_ms for s in stats])
    display = latency + np.array([s.client_ms.get("decode", 0.0) for s in stats])
    payload, targets = sum(s.nbytes for s in stats), [s.bitrate_kbps for s in stats]
    return {"frames": len(stats), "fps": len(stats) / elapsed,
            "latency_p50_ms": float(np.percentile(latency, 50)), "latency_p99_ms": float(np.percentile(latency, 99)),
            "display_latency_p50_ms": float(np.percentile(display, 50)),
            "display_latency_p99_ms": float(np.percentile(display, 99)),
            "bytes_per_frame": payload / len(stats), "payload_kbps": 8e-3 * payload / elapsed,
            "link_kbps": 8e-3 * carried / elapsed, "keyframes": sum(s.keyframe for s in stats),
            "target_kbps_min": min(targets), "target_kbps_median": float(np.median(targets)),
            "target_kbps_max": max(targets),
            "server_ms": {k: float(np.mean([s.server_ms.get(k, 0.0) for s in stats])) for k in stats[-1].server_ms}, "undecodable": undecodable, "encodings": sorted({s.encoding for s in stats}),
            "methods": sorted({s.method for s in stats}),
            "decode_ms": float(np.mean([s.client_ms.get("decode", 0.0) for s in stats])), "notices": notices}
