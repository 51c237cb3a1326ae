"""What a timed span costs the machine: each GPU's busy fraction and the CPU cores that each
part of the service used, so that a throughput short of its goal names its bottleneck.

    load = LoadSampler({"proxy": titled(b"ray::ProxyActor")}, gpus=True)
    load.start(seconds=3.0)          # at the start of the span; returns at once
    ...                              # the work
    load.result()                    # {"gpu_busy": [0.93, 0.91], "cpu_cores": {"proxy": 1.0, ...}, "counters": {}}

Counters: a server's own, from its ``GET /metrics`` (:func:`metric_total`), as their rate over the span
(``device_thread``: the seconds its device thread spent in jobs per second, 1.0 at its bound).

GPU busy: NVML's utilization (the share of each sample period in which a kernel ran), read by
``nvidia-smi`` every 100 ms over the span, averaged per GPU; ``None`` where there is no
``nvidia-smi``. CPU: the user and system time of each group's processes (``/proc/PID/stat``)
over the span, in cores (1.0: one core busy throughout); ``busiest`` is the group's busiest
process, which a single interpreter's lock bounds near 1.0; ``machine`` is every process.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import threading
import time
import urllib.request
from collections.abc import Callable

from prometheus_client.parser import text_string_to_metric_families

TICKS_S = os.sysconf("SC_CLK_TCK")


def titled(prefix: bytes) -> Callable[[], list[int]]:
    """The processes whose command line starts with ``prefix`` (Ray titles its actors so)."""
    return _processes(lambda cmdline: cmdline.startswith(prefix))


def executable(name: bytes) -> Callable[[], list[int]]:
    """The processes of the program ``name`` (their command line's first word ends in ``/name``), e.g. HAProxy."""
    return _processes(lambda cmdline: cmdline.split(b"\0", 1)[0].rsplit(b"/", 1)[-1] == name)


def _processes(match: Callable[[bytes], bool]) -> Callable[[], list[int]]:
    """A reader of the ids of the processes whose command line (NUL-separated words) ``match`` accepts."""
    def pids() -> list[int]:
        found = []
        for entry in os.scandir("/proc"):
            try:
                with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                    if match(f.read()):
                        found.append(int(entry.name))
            except (OSError, ValueError):  # not a process, or gone
                continue
        return found
    return pids


def haproxy_backend(stats_port: int, backend: str = "http-isosr") -> dict[str, int]:
    """The current connections of each server of HAProxy's ``backend`` (Serve's, for the isosr app; ``BACKEND``: all
    of them; replicas are ``SERVE_REPLICA_...``, Serve's proxy, the backup until they join, ``SERVE_PROXY_...``),
    from HAProxy's statistics on ``stats_port`` (Ray's ``RAY_SERVE_HAPROXY_STATS_PORT``, default 8404)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{stats_port}/stats;csv", timeout=10) as r:
        rows = csv.DictReader(r.read().decode().lstrip("# ").splitlines())
        return {row["svname"]: int(row["scur"]) for row in rows if row["pxname"] == backend}


def metric_total(url: str, name: str) -> Callable[[], float | None]:
    """A reader of a server's counter: the sum of the samples named ``name`` in ``url``'s ``GET /metrics``
    (Prometheus text; over every label set); None where the server does not answer or has no such sample."""
    def read() -> float | None:
        try:
            with urllib.request.urlopen(url + "/metrics", timeout=5) as reply:
                text = reply.read().decode()
        except OSError:
            return None
        values = [s.value for family in text_string_to_metric_families(text) for s in family.samples if s.name == name]
        return sum(values) if values else None
    return read


def proc_stat(pid: int) -> list[str]:
    """The fields of ``/proc/PID/stat`` after the command's name (field 3 of proc(5), the state, first).

    Raises:
        OSError: no such process.
    """
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()


def proc_status(pid: int | str) -> dict[str, str]:
    """The fields of ``/proc/PID/status`` by name (``pid`` "self": this process), as written (``VmRSS``: "123 kB").

    Raises:
        OSError: no such process.
    """
    with open(f"/proc/{pid}/status") as f:
        return dict(line.rstrip("\n").split(":\t", 1) for line in f if ":\t" in line)


def cpu_ticks(pid: int) -> int | None:
    """A process's user + system clock ticks so far (None: gone)."""
    try:
        fields = proc_stat(pid)
    except OSError:
        return None
    return int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of proc(5))


def machine_ticks() -> int:
    """Every CPU's busy ticks so far (``/proc/stat``: all but idle and iowait)."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    return sum(values) - values[3] - values[4]


class LoadSampler:
    """GPU busy fractions and CPU cores per process group over one span (module docstring).

    Args:
        groups: name -> the function that lists the group's processes (looked up at the start).
        gpus: sample the GPUs with ``nvidia-smi``.
        counters: name -> a reader of a counter (:func:`metric_total`), read at the start and the end.
    """

    def __init__(self, groups: dict[str, Callable[[], list[int]]], gpus: bool,
                 counters: dict[str, Callable[[], float | None]] | None = None) -> None:
        self.groups = groups
        self.counters = counters or {}
        self.gpus = gpus and shutil.which("nvidia-smi") is not None
        self._done = threading.Event()
        self._result: dict = {}
        self._thread: threading.Thread | None = None

    def start(self, seconds: float) -> None:
        """Sample the next ``seconds`` in a thread; :meth:`result` waits for it."""
        self._thread = threading.Thread(target=self._sample, args=(seconds,), daemon=True)
        self._thread.start()

    def _sample(self, seconds: float) -> None:
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")  # the GPUs this process and its children may use
        smi = subprocess.Popen(["nvidia-smi", "--query-gpu=index,utilization.gpu", "--format=csv,noheader,nounits",
                                "-lms", "100", *(["-i", visible] if visible else [])],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) if self.gpus else None
        members = {name: list_pids() for name, list_pids in self.groups.items()}
        before = {pid: cpu_ticks(pid) for pids in members.values() for pid in pids}
        counted, counted_at = self._read_counters()
        machine_before, started = machine_ticks(), time.monotonic()
        time.sleep(seconds)
        after = {pid: cpu_ticks(pid) for pid in before}
        wall = time.monotonic() - started
        final, final_at = self._read_counters()
        counted = {name: None if None in (value, final[name]) else (final[name] - value) / (final_at - counted_at)
                   for name, value in counted.items()}
        machine = (machine_ticks() - machine_before) / TICKS_S / wall
        cores = {}
        for name, pids in members.items():
            used = [(after[p] - before[p]) / TICKS_S / wall for p in pids if None not in (before[p], after[p])]
            cores[name] = {"processes": len(used), "cores": sum(used), "busiest": max(used, default=0.0)}
        self._result = {"cpu_cores": cores, "machine_cores": machine, "gpu_busy": self._gpu_busy(smi),
                        "counters": counted}
        self._done.set()

    def _read_counters(self) -> tuple[dict[str, float | None], float]:
        """Each counter's value, and when they were read (the middle of their reads: a server answers in its
        request's time)."""
        began = time.monotonic()
        values = {name: read() for name, read in self.counters.items()}
        return values, (began + time.monotonic()) / 2

    @staticmethod
    def _gpu_busy(smi: subprocess.Popen | None) -> list[float] | None:
        if smi is None:
            return None
        smi.terminate()
        out, _ = smi.communicate(timeout=10)
        samples: dict[int, list[float]] = {}
        for line in out.splitlines():
            index, _, busy = line.partition(",")
            if busy.strip().isdigit():
                samples.setdefault(int(index), []).append(int(busy) / 100.0)
        return [sum(v) / len(v) for _, v in sorted(samples.items())] or None

    def result(self, timeout: float = 60.0) -> dict:
        """The span's figures; empty if the span was never started or did not end in ``timeout``."""
        if self._thread is None or not self._done.wait(timeout):
            return {}
        return self._result
