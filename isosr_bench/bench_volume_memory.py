"""Volume memory benchmark: native voxel types, streaming loads and the sparse brick pool.

    python -m isosr_bench.bench_volume_memory --device cuda          # full sizes, on a GPU
    python -m isosr_bench.bench_volume_memory --device cpu --smoke  # tiny sizes, CPU (CI)

Volumes come from `SpheresSource` (the distance to a few spheres, computed box by box: nothing
held; a stand-in for a chunked store on disk, whose reads it replaces by computation):

- ``ct``: 512x512x1000 int16 with a rescale (a DICOM series' size and type): the native
  path (``Renderer.load``: one read that scans and streams, uint16 on the device) against today's (whole array on the
  host, float32 normalized on the host, float32 on the device), load time, peak host and
  device memory, 1080p first-hit time of both.
- ``big``: 2048^3 uint16 (16 GiB on the device): the native path only. Today's path needs
  about 14 bytes a voxel on the host (the array, its float32 copy, a float32 temporary and
  the normalized result: ~120 GB) and 32 GiB on the device: it is not run (``legacy`` says why).
- ``huge``: ``--huge`` voxels a side of uint16 (default 2816: 45 GB in uint16, 89 GB in dense
  float32, more than an 80 GB GPU) under ``--limit-gb`` of device memory for voxels: the
  sparse brick pool: resident bytes and bricks, 1080p first hit with and without AO, the
  page-in time of the first iso, of an iso change, and of a fast camera move (residency
  depends on the iso only: a camera move pages nothing).

Peak host memory is the process's resident set high-water mark during each phase (reset
through ``/proc/self/clear_refs``); device memory is sampled every 5 ms from
``cudaMemGetInfo`` (whole device) during each phase. Writes
``OUT/bench_volume_memory_<device>.json``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import warp as wp

from isosr_bench.load import proc_status
from isosr_render import Renderer, RenderRequest, Volume, orbit
from isosr_render.procedural import SpheresSource
from isosr_render.voxels import ArraySource

from .common import bench_parser, mean_ms, print_table, time_frames, write_result

GB = 1e9
SIZES = {"ct": (512, 512, 1000), "big": (2048, 2048, 2048)}
SMOKE_SIZES = {"ct": (40, 40, 64), "big": (128, 128, 128), "huge": 128}
SMOKE_LIMIT = 0.7  # smoke: the sparse cases' limit as a share of their dense size
CT_RESCALE_NOTE = "int16, rescale (slope, intercept) to world units as DICOM would"


class Peak:
    """Peak host RSS (kernel high-water mark) and peak device memory in use (sampled) over a block."""

    def __init__(self, device: str):
        self.cuda = device.startswith("cuda")
        self.host_gb = self.host_added_gb = self.device_gb = 0.0

    @staticmethod
    def _status_gb(key: str) -> float:
        return int(proc_status("self")[key].split()[0]) * 1024 / GB

    def __enter__(self):
        try:
            Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
        except OSError:  # not allowed here: the peak is then the process's since its start
            pass
        self._rss = self._status_gb("VmRSS")
        self._stop = threading.Event()
        self._base = self._device_used()
        self._peak = self._base
        if self.cuda:
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _device_used(self) -> int:
        if not self.cuda:
            return 0
        free, total = torch.cuda.mem_get_info()
        return total - free

    def _sample(self):
        while not self._stop.wait(0.005):
            self._peak = max(self._peak, self._device_used())

    def __exit__(self, *exc):
        self._stop.set()
        if self.cuda:
            self._thread.join()
            self._peak = max(self._peak, self._device_used())
        self.host_gb = self._status_gb("VmHWM")
        self.host_added_gb = self.host_gb - self._rss
        self.device_gb = (self._peak - self._base) / GB
        return False


def _sync(device: str) -> None:
    wp.synchronize_device(device)


def legacy_volume(source: SpheresSource) -> Volume:
    """Today's path step by step: the whole array read, scaled to float32 and normalized on the
    host (as ``Volume.from_array`` did), then a float32 volume (uploaded dense by the renderer)."""
    values = source.read(*(slice(0, n) for n in source.shape))
    slope, intercept = source.rescale
    values = values.astype(np.float32) * np.float32(slope) + np.float32(intercept)
    lo, hi = float(values.min()), float(values.max())
    data = ((values - lo) * (1.0 / (hi - lo))).astype(np.float32)
    np.clip(data, 0.0, 1.0, out=data)
    del values
    return Volume.from_source(ArraySource(data, source.spacing, f"{source.name} (float32)", (hi - lo, lo)))


def _first_hit(renderer: Renderer, iso: float, device: str, frames: int, ao_samples: int = 0) -> float:
    """Mean 1080p first-hit time (ms; GPU time on CUDA) over an orbit (AO with ``ao_samples`` rays;
    ``frames`` 1 is the smoke run: 240x135)."""
    outputs = ("mask", "normal", "depth") + (("ao",) if ao_samples else ())
    size = (240, 135) if frames == 1 else (1920, 1080)
    request = RenderRequest(*size, iso=iso, outputs=outputs, ao_samples=max(1, ao_samples))
    t = time_frames(lambda i: renderer.render(orbit(30 + 7 * i, 20, 1.8), request), frames, device, warmup=1)
    return mean_ms(t)


def _limit(limit_gb: float | None, source) -> int:
    """The sparse cases' device limit in bytes (smoke: a share of the dense size)."""
    dense = int(np.prod(source.shape)) * source.dtype.itemsize
    return int(SMOKE_LIMIT * dense) if limit_gb is None else int(limit_gb * GB)


def load_native(source, device: str, limit: int | None = None) -> tuple[dict, Volume, Renderer]:
    """``Renderer.load``: one read of the source that scans it and streams it to the device (dense
    8/16-bit), or scans it and sets up the brick pool (sparse): time and peaks."""
    row = {"path": "native", "stored": source.dtype.name}
    with Peak(device) as peak:
        start = time.perf_counter()
        renderer = Renderer.load(source, device, max_device_bytes=limit)
        _sync(device)
        row["load_s"] = time.perf_counter() - start
    stats = renderer.memory()
    row.update(storage=renderer.volume.storage.name, mode=stats.mode, host_peak_gb=peak.host_gb,
               host_added_gb=peak.host_added_gb, device_peak_gb=peak.device_gb,
               resident_gb=stats.resident_bytes / GB, dense_gb=stats.dense_bytes / GB)
    return row, renderer.volume, renderer


def case_ct(shape, device: str, frames: int) -> list[dict]:
    """512x512x1000 int16: native against today's float32 path."""
    source = SpheresSource(shape, "int16", seed=1, chunks=(shape[0], shape[1], 1))
    row, volume, renderer = load_native(source, device)
    iso = volume.normalized_iso(0.0)
    row["first_hit_ms"] = _first_hit(renderer, iso, device, frames)
    del renderer
    legacy = {"path": "today (float32)", "stored": "int16", "storage": "float32", "mode": "dense",
              "note": "load_s includes a scan of the float32 array (the old code ran a device min-max kernel)"}
    with Peak(device) as peak:
        start = time.perf_counter()
        flat = legacy_volume(source)
        renderer = Renderer(flat, device)
        _sync(device)
        legacy["load_s"] = time.perf_counter() - start
    legacy.update(host_peak_gb=peak.host_gb, host_added_gb=peak.host_added_gb, device_peak_gb=peak.device_gb,
                  resident_gb=renderer.memory().resident_bytes / GB, dense_gb=renderer.memory().dense_bytes / GB,
                  first_hit_ms=_first_hit(renderer, iso, device, frames))
    return [dict(row, case="ct", shape=list(shape), note=CT_RESCALE_NOTE), dict(legacy, case="ct", shape=list(shape))]


def case_big(shape, device: str, limit_gb: float | None, frames: int) -> list[dict]:
    """2048^3 uint16: native dense, then the same volume sparse (the slot lookup's cost)."""
    source = SpheresSource(shape, "uint16", seed=2)
    row, volume, renderer = load_native(source, device)
    iso = volume.normalized_iso(0.0)
    row.update(case="big", shape=list(shape), first_hit_ms=_first_hit(renderer, iso, device, frames),
               legacy=f"not run: today's path needs ~{14 * np.prod(shape) / GB:.0f} GB of host memory and "
                      f"{4 * np.prod(shape) / GB:.0f} GB on the device")
    del renderer
    sparse = Renderer(volume, device, brick_size=16, max_device_bytes=_limit(limit_gb, source))
    start = time.perf_counter()
    sparse.grid(iso)
    _sync(device)
    stats = sparse.memory()
    return [row, {"case": "big", "shape": list(shape), "path": "native sparse", "stored": "uint16",
                  "storage": "uint16", "mode": stats.mode, "page_in_s": time.perf_counter() - start,
                  "resident_gb": stats.resident_bytes / GB, "dense_gb": stats.dense_bytes / GB,
                  "bricks": f"{stats.bricks_resident}/{stats.bricks_total}",
                  "first_hit_ms": _first_hit(sparse, iso, device, frames)}]


def case_huge(side: int, device: str, limit_gb: float | None, frames: int, ao_samples: int,
              iso_step: float) -> list[dict]:
    """A volume larger than the GPU in dense float32, rendered sparse under the limit: the first
    iso's page-in, an iso change's, and a fast camera move's (residency follows the iso only)."""
    shape = (side,) * 3
    source = SpheresSource(shape, "uint16", seed=3)
    row, volume, renderer = load_native(source, device, _limit(limit_gb, source))
    rows = []
    for label, value in (("first iso", 0.0), ("iso change", iso_step)):
        iso = volume.normalized_iso(value)
        before = replace(renderer.memory())
        start = time.perf_counter()
        renderer.grid(iso)
        _sync(device)
        page_in = time.perf_counter() - start
        stats = replace(renderer.memory())
        renderer.render(orbit(200, -40, 1.5), RenderRequest(64, 64, iso=iso))  # a fast camera move
        _sync(device)
        rows.append(dict(row, case="huge", shape=list(shape), step=label, iso_world=value, page_in_s=page_in,
                         bricks_paged=stats.bricks_paged - before.bricks_paged,
                         bytes_read_gb=(stats.bytes_read - before.bytes_read) / GB,
                         bricks=f"{stats.bricks_resident}/{stats.bricks_total}",
                         needed_fraction=stats.bricks_needed / stats.bricks_total,
                         resident_gb=stats.resident_bytes / GB, limit_gb=stats.limit_bytes / GB,
                         dense_float32_gb=4 * np.prod(shape) / GB,
                         camera_move_bricks_paged=renderer.memory().bricks_paged - stats.bricks_paged,
                         first_hit_ms=_first_hit(renderer, iso, device, frames),
                         first_hit_ao_ms=_first_hit(renderer, iso, device, frames, ao_samples), ao_samples=ao_samples))
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--cases", default="ct,big,huge", help="comma-separated: ct, big, huge")
    parser.add_argument("--huge", type=int, default=2816,
                        help="voxels a side of the sparse case (2816: 89 GB in dense float32)")
    parser.add_argument("--limit-gb", type=float, default=20.0, help="device memory for voxels in the sparse cases")
    parser.add_argument("--ao-samples", type=int, default=16)
    parser.add_argument("--iso-step", type=float, default=0.003, help="the iso change, world units")
    args = parser.parse_args(argv)
    cases = args.cases.split(",")
    wp.config.quiet = True
    wp.init()
    sizes, limit_gb, frames = dict(SIZES, huge=args.huge), args.limit_gb, 5
    if args.smoke:
        sizes, limit_gb, frames = SMOKE_SIZES, None, 1
    rows = []
    if "ct" in cases:
        rows += case_ct(sizes["ct"], args.device, frames)
    if "big" in cases:
        rows += case_big(sizes["big"], args.device, limit_gb, frames)
    if "huge" in cases:
        rows += case_huge(sizes["huge"], args.device, limit_gb, frames, args.ao_samples, args.iso_step)
    print_table(rows, ["case", "path", "step", "storage", "mode", "load_s", "host_added_gb", "device_peak_gb",
                       "resident_gb", "bricks", "page_in_s", "first_hit_ms", "first_hit_ao_ms"])
    print(f"wrote {write_result('bench_volume_memory', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
