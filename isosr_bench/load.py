"""What a timed span costs the machine: each GPU's busy fraction and the CPU cores that each
part of the service used, so that a throughput short of its goal names its bottleneck.

    load = LoadSampler({"proxy": titled(b"ray::ProxyActor")}, gpus=True)
    load.start(seconds=3.0)          # at the start of the span; returns at once
    ...                              # the work
    load.result()                    # {"gpu_busy": [0.93, 0.91], "cpu_cores": {"proxy": 1.0, ...}}

GPU busy: NVML's utilization (the share of each sample period in which a kernel ran), read by
``nvidia-smi`` every 100 ms over the span, averaged per GPU; ``None`` where there is no
``nvidia-smi``. CPU: the user and system time of each group's processes (``/proc/PID/stat``)
over the span, in cores (1.0: one core busy throughout); ``busiest`` is the group's busiest
process, which a single interpreter's lock bounds near 1.0; ``machine`` is every process.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable

TICKS_S = os.sysconf("SC_CLK_TCK")


def titled(prefix: bytes) -> Callable[[], list[int]]:
    """The processes whose command line starts with ``prefix`` (Ray titles its actors so)."""
    def pids() -> list[int]:
        found = []
        for entry in os.scandir("/proc"):
            try:
                with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                    if f.read().startswith(prefix):
                        found.append(int(entry.name))
            except (OSError, ValueError):  # not a process, or gone
                continue
        return found
    return pids


def cpu_ticks(pid: int) -> int | None:
    """A process's user + system clock ticks so far (None: gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
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
    """

    def __init__(self, groups: dict[str, Callable[[], list[int]]], gpus: bool) -> None:
        self.groups = groups
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
        machine_before, started = machine_ticks(), time.monotonic()
        time.sleep(seconds)
        after = {pid: cpu_ticks(pid) for pid in before}
        wall = time.monotonic() - started
        machine = (machine_ticks() - machine_before) / TICKS_S / wall
        cores = {}
        for name, pids in members.items():
            used = [(after[p] - before[p]) / TICKS_S / wall for p in pids if None not in (before[p], after[p])]
            cores[name] = {"processes": len(used), "cores": sum(used), "busiest": max(used, default=0.0)}
        self._result = {"cpu_cores": cores, "machine_cores": machine, "gpu_busy": self._gpu_busy(smi)}
        self._done.set()

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
