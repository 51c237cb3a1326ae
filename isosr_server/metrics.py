"""Prometheus metrics of one server, in the app's own registry (``GET /metrics``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from isosr_render.brick_pool import MemoryStats

# Stage latencies from 0.5 ms to 10 s.
BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)


class ServerMetrics:
    """Frames, per-stage latency, bytes sent, sessions, errors, GPU memory and volume residency.

    Args:
        gpu_memory: returns the bytes of GPU memory in use (None on the CPU); read per scrape.
        volume_memory: returns each loaded volume's `MemoryStats` by name; read per scrape.
        device_busy: returns the seconds the device thread has spent in jobs so far; read per scrape
            (``isosr_device_busy_seconds_total``: its rate near 1 is a device thread at its bound).

    Attributes:
        const_labels: labels every series carries in `text` and `collect` (behind replicas
            ``{"replica": name}``, so that scrapes of several replicas keep their series apart
            and ``sum`` gives the totals); none on a single server.
    """

    def __init__(self, gpu_memory: Callable[[], int | None],
                 volume_memory: Callable[[], dict[str, MemoryStats]] = dict, device_busy: Callable[[], float] = float):
        self.const_labels: dict[str, str] = {}
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames = Counter("isosr_frames", "Frames sent", ["kind", "mode", "refined"], registry=r)
        self.stage_seconds = Histogram("isosr_stage_seconds", "Server time per frame and stage", ["mode", "stage"],
                                       buckets=BUCKETS_S, registry=r)
        self.batch_frames = Histogram("isosr_batch_frames", "View frames made together on the device, per frame",
                                      buckets=(1, 2, 4, 8, 16, 32, 64), registry=r)
        self.bytes_sent = Counter("isosr_bytes_sent", "Payload bytes sent (images, buffers)", ["mode"], registry=r)
        self.sessions = Gauge("isosr_sessions", "Live sessions", ["kind"], registry=r)
        self.errors = Counter("isosr_errors", "Requests and sessions ended by an error", ["kind", "code"],
                              registry=r)
        gpu = Gauge("isosr_gpu_memory_bytes", "GPU memory allocated by torch (0 on the CPU)", registry=r)
        gpu.set_function(lambda: float(gpu_memory() or 0))
        r.register(_VolumeMemory(volume_memory))
        r.register(_DeviceBusy(device_busy))

    def frame(self, kind: str, mode: str, refined: bool, times_ms: dict[str, float], nbytes: int,
              batch: int = 1) -> None:
        """Count one frame (kind: view, upscale, reconstruct) with its stage times, payload bytes and (view
        frames) the frames made together with it."""
        self.frames.labels(kind, mode, str(refined).lower()).inc()
        if kind == "view":
            self.batch_frames.observe(batch)
        for stage, ms in times_ms.items():
            self.stage_seconds.labels(mode, stage).observe(ms / 1e3)
        self.bytes_sent.labels(mode).inc(nbytes)

    def error(self, kind: str, code: int) -> None:
        self.errors.labels(kind, str(code)).inc()

    def collect(self) -> Iterator[Metric]:
        """The registry's metric families, each sample with `const_labels` added."""
        for family in self.registry.collect():
            if self.const_labels:
                family.samples = [s._replace(labels={**s.labels, **self.const_labels}) for s in family.samples]
            yield family

    def text(self) -> bytes:
        """The Prometheus text exposition of `collect`."""
        return generate_latest(self)


class _VolumeMemory:
    """Per loaded volume (label ``volume``, and ``mode`` dense/sparse): resident and dense bytes,
    bricks resident/needed/total, page-ins and the last page-in's time."""

    GAUGES = (("resident_bytes", "Bytes of the volume's voxels on the device"),
              ("dense_bytes", "Bytes the whole volume takes on the device in its type"),
              ("bricks_resident", "Bricks on the device"), ("bricks_needed", "Bricks the last iso needs"),
              ("bricks_total", "Bricks of the volume"), ("page_ins", "Iso changes that paged bricks in"),
              ("last_page_in_s", "Seconds the last page-in took"))

    def __init__(self, volume_memory: Callable[[], dict[str, MemoryStats]]):
        self.volume_memory = volume_memory

    def collect(self) -> Iterator[Metric]:
        stats = self.volume_memory()
        for field, doc in self.GAUGES:
            family = GaugeMetricFamily(f"isosr_volume_{field}", doc, labels=["volume", "mode"])
            for name, s in stats.items():
                family.add_metric([name, s.mode], float(getattr(s, field)))
            yield family


class _DeviceBusy:
    """The seconds the device thread has spent in jobs (a counter read from the engine per scrape)."""

    def __init__(self, device_busy: Callable[[], float]):
        self.device_busy = device_busy

    def collect(self) -> Iterator[Metric]:
        yield CounterMetricFamily("isosr_device_busy_seconds", "Seconds the device thread spent in jobs (frames' "
                                  "host work and waits for the GPU)", value=self.device_busy())
