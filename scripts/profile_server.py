"""Where a server's time goes under many view sessions: py-spy samples of `isosr serve`'s threads.

    python scripts/profile_server.py --device cuda --volume bonsai --mode reconstruct --ao 1 --sessions 16 --out DIR

Starts the server (:class:`isosr_bench.bench_server.ServerProcess`), drives ``--sessions`` closed-loop
view sessions (1080p unless ``--size``; :func:`isosr_bench.sessions.run_sessions`), and once
they are warm samples the server with py-spy three times, ``--seconds`` each: every thread that is
not idle (where each thread spends its CPU), only the thread that holds the GIL (who owns the
interpreter), then every thread idle or not (where each waits). Threads are told apart by what their
stacks run: the device thread (the engine's frames), the event loop, the encoder pool. Writes
``DIR/profile_server_<mode>_<sessions>_<device>.json``: per thread its share of the span active,
holding the GIL and in all, and its 20 functions with the most samples, inclusive (anywhere on the
stack; those on 90% of the thread's stacks left out) and self (the innermost frame, all kept), as
shares of the span; its ``waiting``: each innermost frame's share in all less its share active; with
``--native``, a fourth sampling with C and driver frames (``native``: where a blocked call blocks,
the server paused for each sample; ``native_waits``: its share running, waiting for the GIL, in a device
sync, idle); with the sessions' frames/s over the run. py-spy must be on PATH
(a dev tool, not a dependency); it attaches with ptrace, so the server runs as a child of this
script.
"""

from __future__ import annotations

import argparse
import collections
import json
import subprocess
import threading
import time
from pathlib import Path

from isosr_bench.bench_server import SIZES, ServerProcess, room_options
from isosr_bench.common import commit, device_name
from isosr_bench.sessions import run_sessions

RATE_HZ = 100
# A thread is named by the first of these functions found in its stacks.
THREAD_KINDS = (("_advance", "device"), ("_batch_sync", "device"), ("codes_sync", "device"),
                ("pack_codes", "encoder"), ("encode_image", "encoder"), ("encode_jpegs", "encoder"),
                ("Server.run", "event loop"), ("_run_once", "event loop"),
                ("RenderPlan.launch.<locals>.band", "CPU render bands"))
TOP = 20


# The samplings: the threads' stacks while active, the GIL holder's only, and every thread's idle or not;
# with --native a fourth, every thread's with its C and driver frames (py-spy pauses the process for each sample).
SAMPLINGS = {"active": [], "gil": ["--gil"], "all": ["--idle"]}
NATIVE = {"native": ["--idle", "--native"]}


def sample(pid: int, seconds: float, path: Path, options: list[str]) -> None:
    """py-spy's collapsed stacks of ``pid``'s threads over ``seconds``, as ``options`` (:data:`SAMPLINGS`) take them."""
    command = ["py-spy", "record", "--pid", str(pid), "--duration", str(int(seconds)), "--rate", str(RATE_HZ),
               "--format", "raw", "--threads", "--function", "-o", str(path)]
    paused = "--native" in options  # py-spy reads native stacks only from a paused process
    subprocess.run(command + options + ([] if paused else ["--nonblocking"]), check=True, capture_output=True)


def read_stacks(path: Path) -> dict[str, list[tuple[list[str], int]]]:
    """Stacks by thread id: ``[(frames outermost first, samples)]``."""
    threads: dict[str, list] = collections.defaultdict(list)
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        frames = stack.split(";")
        tid = next((f for f in frames if f.startswith("thread (")), "thread (?)")
        threads[tid].append(([f.split(" (")[0] for f in frames if not f.startswith(("thread (", "process "))],
                             int(count)))
    return threads


def thread_kind(stacks: list[tuple[list[str], int]]) -> str:
    """The thread's kind by a function on its stacks (py-spy names a method with or without its class)."""
    names = {f for frames, _ in stacks for f in frames}
    names |= {f.rpartition(".")[2] for f in names}
    return next((kind for fn, kind in THREAD_KINDS if fn in names), "other")


def summarize(stacks: list[tuple[list[str], int]], span_samples: int) -> dict:
    inclusive, own = collections.Counter(), collections.Counter()
    for frames, n in stacks:
        for f in set(frames):
            inclusive[f] += n
        if frames:
            own[frames[-1]] += n
    total = sum(n for _, n in stacks)
    everywhere = {f for f, n in inclusive.items() if n >= 0.9 * total}  # the thread's own frames (its loop)

    def share(c: collections.Counter, left_out: set[str]) -> dict[str, float]:
        return {f: round(n / span_samples, 4) for f, n in c.most_common(TOP + len(left_out)) if f not in left_out}
    # an innermost frame is where the thread is, even on most of its stacks (a wait): only inclusive leaves them out
    return {"share": round(total / span_samples, 4), "inclusive": share(inclusive, everywhere),
            "self": share(own, set())}


def waiting(row: dict) -> dict[str, float]:
    """Where a thread waits: each innermost frame's share of the span idle included less its share active
    (two samplings of the same length, so a share is within a few samples' noise)."""
    everything, active = row.get("all", {}).get("self", {}), row.get("active", {}).get("self", {})
    shares = {f: round(share - active.get(f, 0.0), 4) for f, share in everything.items()}
    return {f: share for f, share in sorted(shares.items(), key=lambda kv: -kv[1]) if share > 0}


# What a native stack waits in, by its frames (py-spy --native names C functions; the GIL's own are often inlined
# into the call that released it, so a condition wait outside these is read as the GIL's).
WAITS = (("device sync", ("ynchronize",)),  # cudaStreamSynchronize, cuEventSynchronize, torch's synchronize
         ("idle", ("PyThread_acquire_lock", "epoll", "select", "Condition.wait", "Event.wait", "Queue.get")),
         ("GIL", ("pthread_cond_timedwait", "pthread_cond_wait")))


def native_waits(stacks: list[tuple[list[str], int]], span_samples: int) -> dict[str, float]:
    """A thread's native samples as shares of the span: in a device sync, idle (a lock, queue or socket wait), waiting
    for the GIL (a condition wait otherwise: a C call released the GIL and waits to take it back), or running."""
    counts = collections.Counter()
    for frames, n in stacks:
        counts[next((kind for kind, marks in WAITS if any(m in f for f in frames[-6:] for m in marks)), "running")] += n
    return {kind: round(counts[kind] / span_samples, 4) for kind in ("running", "GIL", "device sync", "idle")}


def profile(args) -> dict:
    size, samplings = SIZES[args.size], SAMPLINGS | (NATIVE if args.native else {})
    with ServerProcess(args.device, room_options(args.sessions)) as server:
        result: dict = {}
        timed = threading.Event()  # every session has its warm-up frames
        drive = threading.Thread(target=lambda: result.update(run_sessions(
            server.url, args.volume, args.sessions, len(samplings) * args.seconds + 4, args.mode, size,
            {"ao_rays": args.ao}, processes=args.client_processes, on_start=timed.set)))
        drive.start()
        while not timed.wait(1.0):
            if not drive.is_alive():
                raise RuntimeError(f"the sessions ended before their timed span: {result.get('errors')}")
        out = {}
        for name, options in samplings.items():
            path = Path(args.out) / f"pyspy_{name}.txt"
            sample(server.pid, args.seconds, path, options)
            span = int(args.seconds * RATE_HZ)
            for tid, stacks in read_stacks(path).items():
                row = out.setdefault(tid, {"thread": thread_kind(stacks)})
                row[name] = summarize(stacks, span)
                if name == "native":
                    row["native_waits"] = native_waits(stacks, span)
        drive.join()
    for row in out.values():
        row["waiting"] = waiting(row)
    return {"threads": sorted(out.values(), key=lambda r: -r.get("active", {}).get("share", 0)),
            "fps": result.get("fps"), "fps_per_session": result.get("fps_per_session"),
            "latency_p99_ms": result.get("latency_p99_ms"), "methods": result.get("methods"),
            "errors": result.get("errors")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--volume", default="bonsai")
    parser.add_argument("--mode", default="reconstruct")
    parser.add_argument("--ao", type=int, default=1)
    parser.add_argument("--sessions", type=int, default=16)
    parser.add_argument("--size", choices=tuple(SIZES), default="1080p")
    parser.add_argument("--seconds", type=float, default=8.0, help="seconds of each of the three samplings (default 8)")
    parser.add_argument("--client-processes", type=int, default=4)
    parser.add_argument("--native", action="store_true",
                        help="a fourth sampling with native frames (CUDA driver, torch's C++): what a waiting thread "
                             "waits in; py-spy pauses the server for each of its samples (default off)")
    parser.add_argument("--out", default="bench-out")
    args = parser.parse_args()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    report = {"benchmark": "profile_server", "device": device_name(args.device), "commit": commit(),
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "command": "python scripts/profile_server.py " + " ".join(
                  f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
              "mode": args.mode, "ao": args.ao, "sessions": args.sessions, "rate_hz": RATE_HZ} | profile(args)
    path = Path(args.out) / f"profile_server_{args.mode}_{args.sessions}_{args.device}.json"
    path.write_text(json.dumps(report, indent=1))
    print(json.dumps({k: report[k] for k in ("fps", "latency_p99_ms", "methods", "errors")}))
    for t in report["threads"]:
        print(t["thread"], "active", t.get("active", {}).get("share"), "gil", t.get("gil", {}).get("share"))
        print("   inclusive:", list(t.get("active", {}).get("inclusive", {}).items())[:12])
        print("   waiting:", list(t["waiting"].items())[:8])


if __name__ == "__main__":
    main()
