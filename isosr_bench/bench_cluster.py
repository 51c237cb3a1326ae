"""What Ray Serve costs and what it buys: `isosr serve` against `isosr serve --replicas N`.

    python -m isosr_bench.bench_cluster --device cuda --volume bonsai      # 1920x1080, one GPU
    python -m isosr_bench.bench_cluster --device cuda --volume bonsai --gpus-per-replica 1 \
        --replicas 0,1,2,4 --sessions 16,32,64 --failover-sessions 32      # one replica per GPU
    CUDA_VISIBLE_DEVICES=0 python -m isosr_bench.bench_cluster --device cuda --volume bonsai \
        --gpus-per-replica split --replicas 1,2,4 --sessions 16            # N replicas on one GPU
    (with `nvidia-cuda-mps-control -d` started before: the same under MPS)
    python -m isosr_bench.bench_cluster --smoke                            # small, CPU

Results: ``OUT/bench_cluster_<size>_<device>.json`` (``--gpus-per-replica`` of 1
or more: ``bench_cluster_gpus_<size>_<device>.json``; ``split``, each server's replicas sharing
one GPU: ``bench_cluster_one_gpu_<size>_<device>.json``), written after every case; a later run
keeps the rows of the servers it does not measure in its ``--lease`` and of other leases (one run per
server fits a time-limited call); scaling compares rows of one lease.
Per server (``--replicas``: 0 is the plain single process, N > 0 is N replicas of
``--gpus-per-replica`` each behind Serve's proxy, on a local Ray started by the server), case
(``full`` without AO, ``reconstruct`` at 1 AO ray, ``auto``) and session count: frames/s in
total and per session and latency p50/p99, as :func:`isosr_bench.sessions.run_sessions`
measures them (sessions dealt to ``--client-processes``), the methods the frames name (``auto``: what it
chose; with replicas, their ``auto mode`` log lines of the case, ``auto_log``: why), which replicas made them,
the GPUs the server holds (``gpus``), whether an MPS daemon ran (``mps``: replicas sharing a GPU run their
kernels together under it), and over the timed span (:class:`isosr_bench.load.LoadSampler`) each GPU's busy
fraction, the CPU cores of the server's process, Serve's proxy and the replicas, and the plain server's device
thread's share of the span in jobs (``device_thread_busy``, from its ``GET /metrics``): a replica's
interpreter near one core, the proxy's, or a device thread near 1, is the bound where the GPUs idle.
``--client-deflate``: the sessions offer permessage-deflate as a browser does (``client_deflate``);
Serve's proxy takes it and deflates every frame, the plain server declines it.
``--drag-hz HZ``: the sessions send cameras at HZ and take frames as they come, as a browser viewer while its
user drags (``client``; results ``..._drag_<device>.json``), where by default each is closed loop.
Then scaling: each N-replica row against the 1-replica row of its case, frames/s over N times
its frames/s at the same sessions, and p99 latency against its p99 at 1/N of the sessions.
Failover, on the first server of 2 or more replicas: ``--failover-sessions`` closed-loop
sessions with ``reconnect=True``; one replica's process is killed (SIGKILL); for each session
that was on it (the sessions that reconnect), the time from the kill to its first frame from
another replica; for the others, errors and their longest gap between frames; and whether
``/v2/health/ready`` stayed 200 throughout.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np

from isosr_bench.bench_server import (SIZES, ServerProcess, case_row, check_offered, device_thread, room_options,
                                      server_load)
from isosr_bench.common import bench_parser, commit, device_name, kept_rows, print_table, write_result
from isosr_bench.load import LoadSampler, executable, haproxy_backend, titled
from isosr_bench.sessions import add_drag_argument, choices_line, client_model, result_suffix, run_sessions
from isosr_client.drive import Orbit
from isosr_client.view import connect
from isosr_server.core.config import ENV_PREFIX, INGRESSES, TOKEN_ENV
from isosr_server.protocol import IMAGE_ENCODINGS, VIDEO_ENCODINGS
from isosr_server.replica import mps_running
from isosr_server.views import VIEWS

CASES = (("full", 0), ("reconstruct", 1), ("auto", 0))
PLAIN = "plain"  # the server without replicas: one process, one device thread
# Where the local Ray the servers start keeps its processes' logs (the replicas' among them).
RAY_LOGS = Path(os.environ.get("RAY_TMPDIR", "/tmp/ray")) / "session_latest" / "logs"
# The most of the replicas' auto log lines an auto row keeps (the last ones).
AUTO_LOG_LINES = 60


def parse_cases(text: str) -> tuple[tuple[str, int], ...]:
    """``MODE:AO_RAYS,...`` (``full:0,reconstruct:1``) as (mode, AO rays) cases.

    Raises:
        ValueError: a mode the server does not offer, or AO rays that are not a count.
    """
    cases = []
    for item in text.split(","):
        mode, _, ao = item.partition(":")
        if mode not in VIEWS or not ao.isdigit():
            raise ValueError(f"{item!r} is not MODE:AO_RAYS with MODE one of {', '.join(VIEWS)}")
        cases.append((mode, int(ao)))
    return tuple(cases)


def replica_pids() -> list[int]:
    """The process ids of this machine's isosr replicas (Ray titles them ``ray::ServeReplica:...``)."""
    pids = []
    for entry in os.scandir("/proc"):
        try:
            title = open(f"/proc/{entry.name}/cmdline", "rb").read()
        except OSError:  # not a process, or gone
            continue
        if title.startswith(b"ray::ServeReplica") and b"IsosrReplica" in title:
            pids.append(int(entry.name))
    return sorted(pids)


def wait_for_replicas_in_haproxy(replicas: int, stats_port: int | None = None, timeout_s: float = 120.0) -> None:
    """Until HAProxy's backend holds every replica (a server is ready a few seconds before: until then HAProxy
    sends requests to Serve's proxy, its backup, and a session opened then stays on that path); ``stats_port``:
    HAProxy's statistics (default: ``RAY_SERVE_HAPROXY_STATS_PORT``, else Ray's 8404).

    Raises:
        RuntimeError: not within ``timeout_s``, naming the servers HAProxy holds.
    """
    port = stats_port or int(os.environ.get("RAY_SERVE_HAPROXY_STATS_PORT", "8404"))
    deadline = time.monotonic() + timeout_s
    while True:
        servers = haproxy_backend(port)
        if sum(name.startswith("SERVE_REPLICA") for name in servers) >= replicas:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"HAProxy holds {sorted(servers)}, not {replicas} replicas, {timeout_s:g} s after ready")
        time.sleep(0.5)


def stop_ray() -> None:
    """Stop what the server's local Ray may leave behind when its process is killed."""
    subprocess.run([sys.executable, "-m", "ray.scripts.scripts", "stop", "--force"], capture_output=True, timeout=120)


def failover(url: str, volume: str, size: tuple[int, int], sessions: int, before_s: float, after_s: float) -> dict:
    """Kill one of the replicas under ``sessions`` reconnecting sessions (module docstring)."""
    frames: list[list[tuple[float, str | None]]] = [[] for _ in range(sessions)]
    reconnects = [0] * sessions
    errors: list[str] = []
    stop_at = time.monotonic() + before_s + after_s
    opened = threading.Barrier(sessions + 1)

    def viewer(k: int) -> None:
        path = Orbit(yaw=30.0 + 360.0 * k / sessions)
        with connect(url, volume, "full", size, settings={"refine": False}, local_upscale=False, timeout=60,
                     reconnect=True) as view:
            opened.wait()
            i = 0
            while time.monotonic() < stop_at:
                try:
                    view.set_camera(**path.camera(i))
                    frame = view.latest()
                    frames[k].append((time.monotonic(), frame.stats.replica))
                except Exception as e:  # counted: no session may see one but the killed replica's
                    errors.append(f"session {k} at {time.monotonic():.3f}: {type(e).__name__}: {e}")
                i += 1
            reconnects[k] = view.reconnects

    threads = [threading.Thread(target=viewer, args=(k,), daemon=True) for k in range(sessions)]
    for t in threads:
        t.start()
    opened.wait(timeout=120)
    time.sleep(before_s)
    pids = replica_pids()
    seen = sorted({r for got in frames for _, r in got})
    os.kill(pids[0], signal.SIGKILL)
    killed = time.monotonic()
    health = []
    while time.monotonic() < killed + min(after_s, 5.0):
        try:
            with urllib.request.urlopen(url + "/v2/health/ready", timeout=2) as r:
                health.append(r.status)
        except urllib.error.HTTPError as e:
            health.append(e.code)
        except OSError as e:
            health.append(type(e).__name__)
        time.sleep(0.1)
    for t in threads:
        t.join(timeout=after_s + 60)
    moved, others, doomed = [], [], set()
    for got, reconnected in zip(frames, reconnects):
        if reconnected:
            doomed |= {r for t, r in got if t < killed}
            after = [t for t, r in got if t > killed and r not in doomed]
            moved.append(after[0] - killed if after else None)
        else:
            times = [t for t, _ in got]
            others.append(float(max(np.diff(times))) if len(times) > 1 else None)
    return {"study": "failover", "sessions": sessions, "replicas": seen, "killed": sorted(doomed),
            "moved_sessions": len(moved), "failover_s": moved,
            "failover_max_s": max((m for m in moved if m is not None), default=None),
            "unmoved": sum(m is None for m in moved),
            "other_sessions": len(others), "other_max_gap_s": max((g for g in others if g), default=None),
            "errors": errors, "health_ready": sorted({str(h) for h in health})}


def replica_share(gpus: str, replicas: int) -> float:
    """One replica's GPU share: ``--gpus-per-replica`` as a number, or ``split`` (1/N of one GPU)."""
    return 1.0 / replicas if gpus == "split" else float(gpus)


def servers(replicas: list[int], gpus: str, device: str, ingress: str = "serve"
            ) -> list[tuple[str, int, float, tuple[str, ...]]]:
    """(name, replicas, GPUs held, extra `isosr serve` options) per server measured: 0 replicas
    is the plain server (one GPU on CUDA); replicas behind ``ingress`` (`isosr serve --ingress`)."""
    cuda = device.startswith("cuda")
    out = []
    for n in replicas:
        if n == 0:
            out.append((PLAIN, 0, float(cuda), ()))
            continue
        share = replica_share(gpus, n) if cuda else 0.0
        ray_options = ("--gpus-per-replica", f"{share:g}") if cuda else ()
        out.append((f"ray{n}", n, n * share, ("--replicas", str(n), "--ingress", ingress, *ray_options)))
    return out


def scaling(rows: list[dict]) -> list[dict]:
    """Each N-replica case row (N > 1) against the 1-replica server: ``efficiency`` is its
    frames/s over N times the 1-replica frames/s at the same sessions; ``p99_ratio`` its p99
    latency over the 1-replica p99 at 1/N of the sessions (where measured). Rows name their
    server's ``replicas`` (0: the plain server); rows are compared within their ``lease`` only."""
    one = {(r.get("lease"), r["mode"], r["ao"], r["sessions"]): r
           for r in rows if r.get("replicas") == 1 and "fps" in r}
    out = []
    for r in rows:
        n = r.get("replicas", 0) if "fps" in r else 0
        base = one.get((r.get("lease"), r.get("mode"), r.get("ao"), r.get("sessions")))
        if n < 2 or base is None:
            continue
        fewer = (one.get((r.get("lease"), r["mode"], r["ao"], r["sessions"] // n))
                 if r["sessions"] % n == 0 else None)
        out.append({"study": "scaling", "lease": r.get("lease"), "server": r["server"], "replicas": n, "mode": r["mode"], "ao": r["ao"],
                    "sessions": r["sessions"], "fps": r["fps"], "fps_one": base["fps"],
                    "efficiency": r["fps"] / (n * base["fps"]),
                    "p99_ms": r["latency_p99_ms"], "p99_one_at_1_over_n_ms": fewer and fewer["latency_p99_ms"],
                    "p99_ratio": fewer and r["latency_p99_ms"] / fewer["latency_p99_ms"]})
    return out


def merge(path: Path, rows: list[dict], measured: set[tuple[str, str]]) -> list[dict]:
    """The rows of an existing result at ``path`` for (server, lease) pairs other than ``measured``
    (each with its file's device, commit and lease), then ``rows``; scaling rows are recomputed after."""
    kept = kept_rows(path, lambda r: r.get("study") != "scaling", stamp=("device", "commit", "lease"))
    return [r for r in kept if (r.get("server"), r.get("lease")) not in measured] + rows


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--volume", default="proc:cloud:0@128", help="a volume the server offers")
    parser.add_argument("--size", choices=("1080p", "4k"), default="1080p", help="the view sessions' frame size")
    parser.add_argument("--seconds", type=float, help="timed seconds per case (default 5; smoke 1)")
    parser.add_argument("--settle", type=float, default=0.0,
                        help="untimed seconds of every case's sessions before its timed span: auto's probes and "
                             "re-choices under the case's load (its steady state; default 0: its first seconds)")
    parser.add_argument("--sessions", help="concurrent sessions per case, comma-separated (default 1,16,32)")
    parser.add_argument("--replicas", default="0,1,2", help="servers by replica count, comma-separated (0: plain)")
    parser.add_argument("--cases", default=",".join(f"{m}:{ao}" for m, ao in CASES),
                        help="MODE:AO_RAYS per case, comma-separated")
    parser.add_argument("--encoding", choices=IMAGE_ENCODINGS + VIDEO_ENCODINGS, default="jpeg",
                        help="the view sessions' frame encoding (default jpeg; video: the server's cores encode)")
    parser.add_argument("--gpus-per-replica", default="0.5",
                        help="each replica's GPU share (CUDA), or 'split': each server's replicas share one GPU")
    parser.add_argument("--failover-sessions", type=int, default=8, help="sessions of the failover study (0: none)")
    parser.add_argument("--lease", default=time.strftime("%Y-%m-%d %H:00", time.gmtime()),
                        help="the machine's lease, the same for every call in it: rows are compared (scaling) "
                             "and replaced within one lease (default: this hour, UTC)")
    parser.add_argument("--client-deflate", action="store_true",
                        help="the sessions offer permessage-deflate, as a browser's viewer does (rows: client_deflate)")
    parser.add_argument("--ingress", choices=INGRESSES, default="serve",
                        help="what carries the replicas' requests (isosr serve --ingress; rows: ingress)")
    parser.add_argument("--client-processes", type=int, default=max(1, min(8, (os.cpu_count() or 2) // 4)),
                        help="processes the client sessions are dealt to")
    add_drag_argument(parser)
    args = parser.parse_args(argv)
    size_name = "smoke" if args.smoke else args.size
    size, seconds = SIZES[size_name], args.seconds or (1.0 if args.smoke else 5.0)
    counts = [int(n) for n in (args.sessions or ("1,4" if args.smoke else "1,16,32")).split(",")]
    volume = "proc:cloud:0@32" if args.smoke and args.volume == parser.get_default("volume") else args.volume
    try:
        check_offered(volume)
    except ValueError as e:
        parser.error(f"--volume: {e}")
    replicas = [int(n) for n in args.replicas.split(",") if n]
    if not replicas or min(replicas) < 0:
        parser.error(f"--replicas: one or more replica counts of 0 or more (0: the plain server), got {args.replicas!r}")
    if not (math.isfinite(args.settle) and args.settle >= 0):
        parser.error(f"--settle: untimed seconds, 0 or more, got {args.settle!r}")
    try:
        modes = parse_cases(args.cases)
    except ValueError as e:
        parser.error(f"--cases: {e}")
    try:
        if args.gpus_per_replica != "split" and float(args.gpus_per_replica) < 0:
            raise ValueError
    except ValueError:
        parser.error(f"--gpus-per-replica: a share of 0 or more, or 'split', got {args.gpus_per_replica!r}")
    # at info: a replica's auto probes, choices and re-choices reach its Ray worker's log
    options = room_options(max(counts + [args.failover_sessions])) + ("--log-level", "info")
    failover_on = next((f"ray{n}" for n in replicas if n >= 2), None)
    measured = servers(replicas, args.gpus_per_replica, args.device, args.ingress)
    kind = "_one_gpu" if args.gpus_per_replica == "split" else "_gpus" if float(args.gpus_per_replica) >= 1 else ""
    name = (f"bench_cluster{kind}_{size_name}" + ("" if args.encoding == "jpeg" else f"_{args.encoding}")
            + result_suffix(args.drag_hz))
    path = args.out / f"{name}_{'cuda' if args.device.startswith('cuda') else 'cpu'}.json"
    stamp = {"device": device_name(args.device), "commit": commit(), "lease": args.lease}
    compression = "deflate" if args.client_deflate else None
    mps = args.device.startswith("cuda") and mps_running()  # replicas sharing a GPU: together, or taking turns
    merged = merge(path, [], {(server, args.lease) for server, *_ in measured})  # the other servers' rows of earlier runs
    for server_name, server_replicas, gpus, extra in measured:
        cases = [(mode, ao, n) for mode, ao in modes for n in counts]
        failover_sessions = args.failover_sessions if server_name == failover_on else 0
        ingress = args.ingress if server_replicas else None
        for row in measure_server(server_name, args.device, options + extra, cases, failover_sessions,
                                  volume, size, seconds, args.client_processes, args.encoding, compression, ingress,
                                  server_replicas, args.settle, args.drag_hz):
            merged.append(dict(row, replicas=server_replicas, gpus=gpus, encoding=args.encoding, mps=mps,
                               client=client_model(args.drag_hz),
                               client_deflate=args.client_deflate, ingress=ingress, **stamp))
            # Written after every row: a run cut off (a device call's time limit) keeps what it measured.
            scaled = scaling(merged)
            written = write_result(name, args.device, merged + scaled, args.out)
    print_table([r for r in merged if "mode" in r],
                ["server", "gpus", "mode", "ao", "sessions", "fps", "fps_per_session", "latency_p50_ms",
                 "latency_p99_ms", "errors", "methods", "gpu_busy", "proxy_cores", "replica_cores_max",
                 "server_cores"])
    print_table(scaled, ["server", "mode", "ao", "sessions", "fps", "fps_one", "efficiency", "p99_ms",
                         "p99_one_at_1_over_n_ms", "p99_ratio"])
    print(f"wrote {written}")


def load_fields(load: dict) -> dict:
    """A case row's share of a :class:`LoadSampler` result (rounded: they are read, not computed on)."""
    if not load:
        return {}
    cores = load["cpu_cores"]
    return server_load(load) | {
        "machine_cores": round(load["machine_cores"], 2), "server_cores": round(cores["server"]["cores"], 2),
        "proxy_cores": round(cores["proxy"]["cores"], 2), "replica_cores": round(cores["replica"]["cores"], 2),
        "replica_cores_max": round(cores["replica"]["busiest"], 2)}


def server_environment() -> dict[str, str]:
    """The settings the servers take from this process's environment (``ISOSR_*``; the token left out)."""
    return {k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIX) and k != TOKEN_ENV}


def log_sizes(logs: Path = RAY_LOGS) -> dict[Path, int]:
    """Each log file's size now (none where ``logs`` is missing): where a case's lines start (:func:`auto_log`)."""
    return {p: p.stat().st_size for p in logs.rglob("*") if p.is_file()} if logs.is_dir() else {}


def auto_log(before: dict[Path, int], logs: Path = RAY_LOGS, most: int = AUTO_LOG_LINES) -> list[str]:
    """The ``auto mode`` lines the replicas logged since ``before`` (:func:`log_sizes`), each after its file's
    name, the last ``most``: what each replica probed and chose under the case's load, and why it traded rate
    for AO or did not."""
    lines: list[str] = []
    for path, size in sorted(log_sizes(logs).items()):
        start = before.get(path, 0)
        if size > start:
            with open(path, "rb") as f:
                f.seek(start)
                lines += [f"{path.name}: {line.strip()}" for line in f.read().decode(errors="replace").splitlines()
                          if "auto mode" in line]
    return lines[-most:]


def measure_server(name: str, device: str, options: tuple[str, ...], cases: list[tuple[str, int, int]],
                   failover_sessions: int, volume: str, size: tuple[int, int], seconds: float, processes: int,
                   encoding: str, compression: str | None = None, ingress: str | None = None, replicas: int = 0,
                   settle_s: float = 0.0, drag_hz: float = 0.0):
    """Start one server and yield a row per (mode, AO rays, sessions) case (frames coded as ``encoding``,
    the sessions' WebSocket compression ``compression``; its ``replicas`` behind ``ingress``, whose processes are
    the rows' proxy; timed after ``settle_s`` untimed seconds; the sessions dragging at ``drag_hz``, 0: closed
    loop), then its failover row."""
    started = time.monotonic()
    try:
        with ServerProcess(device, options) as server:
            if ingress == "haproxy":
                wait_for_replicas_in_haproxy(replicas)
            ready_s = time.monotonic() - started
            proxy = executable(b"haproxy") if ingress == "haproxy" else titled(b"ray::ProxyActor")
            groups = {"server": lambda: [server.pid], "proxy": proxy,
                      "replica": titled(b"ray::ServeReplica")}
            # One device thread's counter behind the plain server's /metrics; a replica's answers for itself only.
            counters = device_thread(server.url) if name == PLAIN else {}
            for mode, ao, n in cases:
                load = LoadSampler(groups, gpus=device.startswith("cuda"), counters=counters)
                settings = {"ao_rays": ao, "encoding": encoding}
                logged = log_sizes() if mode == "auto" and name != PLAIN else None
                result = run_sessions(server.url, volume, n, seconds, mode, size, settings, processes=processes,
                                      on_start=lambda: load.start(seconds), compression=compression,
                                      settle_s=settle_s, drag_hz=drag_hz)
                row = dict(case_row(mode, ao, result), server=name, ready_s=ready_s, settle_s=settle_s,
                           replicas_seen=len(result.get("replicas", [])), server_environment=server_environment(),
                           **load_fields(load.result()))
                if logged is not None:  # why each replica chose what it did
                    row["auto_log"] = auto_log(logged)
                print(f"{name:<6} {mode:<5} AO {ao:<2} x{n:<3} {row.get('fps', 0):7.1f} fps "
                      f"({row.get('fps_per_session', 0):6.1f}/session) p50 {row.get('latency_p50_ms', 0):6.1f} "
                      f"p99 {row.get('latency_p99_ms', 0):6.1f} ms errors {row['errors']} (ready in {ready_s:.0f} s) "
                      f"{row.get('methods')} GPU busy {row.get('gpu_busy')} cores: server {row.get('server_cores')} "
                      f"proxy {row.get('proxy_cores')} replica max {row.get('replica_cores_max')} "
                      f"device thread {row.get('device_thread_busy')}", flush=True)
                if row.get("choices"):  # auto: what each replica expected of what it chose
                    print(f"       auto expected: {choices_line(row['choices'])}", flush=True)
                yield row
            if failover_sessions:
                row = dict(failover(server.url, volume, size, failover_sessions, 3.0, 6.0), server=name)
                print(row, flush=True)
                yield row
    finally:
        if name != PLAIN:
            stop_ray()


if __name__ == "__main__":
    main()
