"""Volumes larger than the device: only the bricks an iso-value needs, paged in from the voxel source.

The min-max bricks say which bricks can hold the surface for an iso (their range holds it);
those and their 26 neighbours (read by normals at brick faces and by samples on brick
exits) are resident in a pool on the device. Each pool slot holds one brick with its
one-voxel overlap, ``(B + 1)^3`` voxels in the volume's device type, so that a trilinear
sample reads a single slot; a per-brick table gives the slot (-1: not resident, the kernels
then read the brick's minimum, which lies on the same side of the iso as all its voxels).

An iso change pages in only the bricks it needs that are not resident, reading the voxel
source chunk by chunk (on threads) and scattering each chunk's bricks to their slots. Bricks no
longer needed stay until the pool is full, then the least recently needed go. The pool grows
geometrically up to ``max_bytes``; an iso needing more is refused with a clear error. A
request with ``skip=False`` (a measurement knob) also marches non-resident bricks and reads
their minimum there.

Why a pool of our own rather than ``wp.Volume`` (NanoVDB): NanoVDB in Warp holds float32,
int32 or vec3 voxels, not uint8/uint16, so it would double or quadruple the resident bytes of
the scans this is for; its topology is built once (``allocate_by_tiles``), so an iso change
rebuilds it instead of paging the difference; and its CPU sampling measured 3x slower than a
plain array here (``../shared/notes/warp.md``). The pool keeps one kernel code path (a slot
lookup per sample) for dense and sparse, tested on CPU.
"""

from __future__ import annotations

import threading
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import warp as wp

from isosr_render import voxels
from isosr_render.scan import BRICK
from isosr_render.volume import Volume
from isosr_render.voxels import box_extent, map_bounded


class DeviceMemoryError(RuntimeError):
    """An iso-value needs more resident bricks than the device memory limit allows."""


@dataclass
class MemoryStats:
    """Where a renderer's voxels are and what paging cost (for ``/metrics`` and the viewer).

    Attributes:
        mode: ``"dense"`` (the whole volume on the device) or ``"sparse"`` (a brick pool).
        storage: the voxels' type on the device.
        dense_bytes: bytes of the whole volume in that type.
        resident_bytes: bytes of voxels on the device now (dense array, with its filtered
            texture where the march reads one, or the pool's used slots).
        pool_bytes: bytes allocated for the pool (sparse), else equal to ``resident_bytes``.
        limit_bytes: the device memory limit for voxels (0: none).
        bricks_total, bricks_resident, bricks_needed: bricks of the volume, resident, needed
            by the last iso (active and neighbours).
        page_ins, bricks_paged, bytes_read: paging so far; ``last_page_in_s`` the last one's time.
    """

    mode: str
    storage: str
    dense_bytes: int
    resident_bytes: int
    pool_bytes: int
    limit_bytes: int
    bricks_total: int
    bricks_resident: int
    bricks_needed: int = 0
    page_ins: int = 0
    bricks_paged: int = 0
    bytes_read: int = 0
    last_page_in_s: float = 0.0

    def to_json(self) -> dict:
        return asdict(self)


def coarsen(bricks: np.ndarray, factor: int) -> np.ndarray:
    """Min-max bricks of ``factor`` times the edge from ``BRICK``-voxel ones (a coarse brick's
    voxels and overlap are its fine bricks' ones).

    Shape:
        bricks: (a, b, c, 2) -> (ceil(a / factor), ceil(b / factor), ceil(c / factor), 2)
    """
    if factor == 1:
        return bricks
    pad = [(0, -n % factor) for n in bricks.shape[:3]]
    lo = np.pad(bricks[..., 0], pad, constant_values=np.inf)
    hi = np.pad(bricks[..., 1], pad, constant_values=-np.inf)
    shape = tuple(n // factor for n in lo.shape)
    split = (shape[0], factor, shape[1], factor, shape[2], factor)
    return np.stack([lo.reshape(split).min(axis=(1, 3, 5)), hi.reshape(split).max(axis=(1, 3, 5))], axis=-1)


class BrickPool:
    """The resident bricks of one volume on one device.

    Args:
        volume: the volume (its source is read while paging).
        device: the Warp device.
        brick: voxels per brick edge, a multiple of ``BRICK``.
        max_bytes: the most bytes of voxels the pool may hold.
        threads: threads reading the source while paging (default ``voxels.READ_THREADS``).
    """

    def __init__(self, volume: Volume, device, brick: int, max_bytes: int, threads: int | None = None):
        if brick % BRICK:
            raise ValueError(f"a sparse volume's brick size must be a multiple of {BRICK}, got {brick}")
        self.volume, self.device, self.brick, self.max_bytes = volume, device, brick, int(max_bytes)
        self.threads = threads or voxels.READ_THREADS
        self.dtype = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}[volume.storage.name]
        self.brick_bytes = (brick + 1) ** 3 * volume.storage.itemsize
        self.capacity = self.max_bytes // self.brick_bytes
        minmax = np.ascontiguousarray(coarsen(volume.bricks, brick // BRICK), dtype=np.float32)
        self.shape = minmax.shape[:3]
        self.minmax = wp.array(minmax, dtype=wp.vec2, device=device)
        self.slots_host = np.full(self.shape, -1, np.int32)
        self.slots = wp.array(self.slots_host, dtype=wp.int32, device=device)
        self.last_needed = np.zeros(self.shape, np.int64)  # per brick: the page-in that last needed it
        self.pool = wp.empty((0, brick + 1, brick + 1), dtype=self.dtype, device=device)
        self.free: list[int] = []
        self.satisfied: set[float] = set()
        self.lock = threading.Lock()
        self.stats = MemoryStats("sparse", volume.storage.name, volume.device_bytes, 0, 0, self.max_bytes,
                                 int(np.prod(self.shape)), 0)

    def _needed(self, iso: float) -> torch.Tensor:
        """Bricks whose range holds ``iso``, dilated by one brick (bool, on the device)."""
        mm = wp.to_torch(self.minmax)
        active = ((mm[..., 0] <= iso) & (iso <= mm[..., 1])).float()[None, None]
        return torch.nn.functional.max_pool3d(active, 3, stride=1, padding=1)[0, 0] > 0

    def ensure(self, iso: float) -> None:
        """Make every brick ``iso`` needs resident (a no-op when the last paging already did)."""
        iso = float(np.float32(iso))
        if iso in self.satisfied:
            return
        with self.lock:
            if iso not in self.satisfied:
                self._page(iso)

    def _page(self, iso: float) -> None:
        start = time.perf_counter()
        needed = self._needed(iso).cpu().numpy()
        count = int(needed.sum())
        if count > self.capacity:
            raise DeviceMemoryError(
                f"{self.volume.name or 'volume'}: iso {iso:g} (normalized) needs {count} bricks "
                f"of {self.brick_bytes} bytes, "
                f"{count * self.brick_bytes / 2**30:.2f} GiB, more than the limit of {self.max_bytes / 2**30:.2f} GiB "
                f"({self.capacity} bricks): raise max_device_bytes or choose another iso")
        self.stats.page_ins += 1
        self.last_needed[needed] = self.stats.page_ins
        missing = np.argwhere(needed & (self.slots_host < 0))
        if len(missing):
            self._make_room(len(missing))
            slots = np.array([self.free.pop() for _ in range(len(missing))], np.int32)
            self._page_in(missing, slots)
            self.slots_host[tuple(missing.T)] = slots
            wp.copy(self.slots, wp.array(self.slots_host, dtype=wp.int32, device="cpu"))
            wp.synchronize_device(self.device)  # renders run on torch's stream, not Warp's
        self.satisfied.add(iso)
        self.stats.bricks_needed = count
        self.stats.bricks_resident = int((self.slots_host >= 0).sum())
        self.stats.resident_bytes = self.stats.bricks_resident * self.brick_bytes
        self.stats.pool_bytes = self.pool.shape[0] // (self.brick + 1) * self.brick_bytes
        self.stats.last_page_in_s = time.perf_counter() - start

    def _make_room(self, count: int) -> None:
        """Free slots for ``count`` bricks: grow the pool (x2, up to the limit), then evict the
        bricks needed longest ago (never those of the current page-in)."""
        slots = self.pool.shape[0] // (self.brick + 1)
        if len(self.free) < count and slots < self.capacity:
            grown = min(self.capacity, max(2 * slots, slots + count - len(self.free) + slots // 4, 64))
            pool = wp.empty((grown * (self.brick + 1), self.brick + 1, self.brick + 1), dtype=self.dtype,
                            device=self.device)
            if slots:
                wp.copy(pool, self.pool, count=self.pool.size)
            self.pool = pool
            self.free.extend(range(grown - 1, slots - 1, -1))
        if len(self.free) < count:
            resident = np.argwhere(self.slots_host >= 0)
            age = self.last_needed[tuple(resident.T)]
            evict = resident[np.argsort(age, kind="stable")[: count - len(self.free)]]
            self.free.extend(self.slots_host[tuple(evict.T)].tolist())
            self.slots_host[tuple(evict.T)] = -1
            self.satisfied.clear()
        wp.synchronize_device(self.device)

    def _page_in(self, bricks: np.ndarray, slots: np.ndarray) -> None:
        """Read ``bricks`` (brick coordinates) from the source and write them to pool ``slots``.

        Shape:
            bricks: (n, 3); slots: (n,)
        """
        source, b = self.volume.source, self.brick
        # Group by the smallest chunk-aligned box (whole chunks, whole bricks): each group's read
        # is the bounding box of its bricks there, plus the overlap plane.
        extent = np.maximum(1, -(-np.array(box_extent(source, b, 1)) // b))  # bricks per box and axis
        keys = bricks // extent
        order = np.lexsort(keys.T[::-1])
        bricks, slots, keys = bricks[order], slots[order], keys[order]
        cuts = np.flatnonzero(np.any(np.diff(keys, axis=0), axis=1)) + 1
        groups = list(zip(np.split(bricks, cuts), np.split(slots, cuts)))

        def read(group):
            members, where = group
            lo = members.min(axis=0) * b
            hi = np.minimum((members.max(axis=0) + 1) * b + 1, source.shape)
            stored = np.asarray(source.read(*(slice(int(l), int(h)) for l, h in zip(lo, hi))))
            values = self.volume.device_box(stored)
            span = (members.max(axis=0) - members.min(axis=0) + 1) * b + 1
            values = np.pad(values, [(0, int(s - n)) for s, n in zip(span, values.shape)], mode="edge")
            st = values.strides
            windows = np.lib.stride_tricks.as_strided(
                values, tuple(span // b) + (b + 1,) * 3, tuple(s * b for s in st) + st, writeable=False)
            local = members - members.min(axis=0)
            return windows[tuple(local.T)], where, stored.nbytes

        pool = wp.to_torch(self.pool)
        if pool.dtype == torch.uint16:
            pool = pool.view(torch.int16)  # index_put has no uint16 kernels
        pool = pool.view(-1, (b + 1) ** 3)
        for staged, where, nbytes in map_bounded(read, groups, self.threads):
            staged = np.ascontiguousarray(staged).reshape(len(where), -1)
            if staged.dtype == np.uint16:
                staged = staged.view(np.int16)
            pool[torch.from_numpy(where.astype(np.int64)).to(pool.device)] = torch.from_numpy(staged).to(pool.device)
            self.stats.bytes_read += nbytes
        if pool.is_cuda:
            torch.cuda.synchronize(pool.device)
        self.stats.bricks_paged += len(slots)
