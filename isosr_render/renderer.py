"""The renderer's Python API: a `RenderRequest` in, `FrameBuffers` out.

    volume = load_volume("head.nii.gz")            # or procedural.parse_procedural("proc:sphere")
    renderer = Renderer(volume, device="cuda")     # streams the volume to the device, builds the min-max grid
    request = RenderRequest(480, 270, iso=volume.normalized_iso(300.0), outputs=("mask", "normal"))
    frame = renderer.render(orbit(30, 20, 1.8), request)
    frame.normal                                   # torch tensor (270, 480, 3), no copy

A request computes only what it names: AO rays only when ``ao`` is asked, flow only with a
previous camera, normals only for ``normal``, ``ao`` or ``color``.

Voxels go to the device in their narrow type (see :mod:`isosr_render.volume`), streamed box
by box from the volume's source. A volume whose dense size exceeds ``max_device_bytes`` is
rendered sparse: only the bricks each iso needs are resident (:mod:`isosr_render.brick_pool`).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from isosr_render import kernels
from isosr_render.brick_pool import BrickPool, MemoryStats
from isosr_render.buffers import FrameBuffers
from isosr_render.camera import Camera
from isosr_render.conventions import AO_RADIUS, BUFFER_NAMES
from isosr_render.flow_fill import FILL_METHODS, fill_flow
from isosr_render.shading import ShadingParams, shade
from isosr_render.volume import Volume
from isosr_render.voxels import boxes, map_bounded

REFINE_METHODS = {"bisection": kernels.REFINE_BISECTION, "secant": kernels.REFINE_SECANT}
REQUESTABLE = BUFFER_NAMES + ("samples",)
# Largest image side and supersampling the renderer accepts (a bound against runaway requests).
MAX_SIDE = 16384
MAX_SPP = 256
MAX_AO_SAMPLES = 4096
# Cap of the brick distance grid: a ray leaps at most (2 MAX_LEAP - 1) bricks at once.
MAX_LEAP = 16
GRID_CACHE = 4
# Without a limit, a CUDA renderer keeps a volume dense while it takes at most this share of free memory.
DENSE_SHARE = 0.5
STORE_KINDS = {"float32": (kernels.STORE_F32, wp.float32), "uint16": (kernels.STORE_U16, wp.uint16),
               "uint8": (kernels.STORE_U8, wp.uint8)}


@dataclass(frozen=True)
class RenderRequest:
    """One frame to render and the buffers to compute.

    Attributes:
        width, height: image size in pixels.
        iso: iso-value on the normalized [0, 1] scale (``Volume.normalized_iso`` converts).
            Outside the data range the image is empty.
        outputs: buffer names (see conventions), plus ``samples`` for the per-pixel count of
            volume samples.
        step: ray-marching step in world units; ``None`` means half the smallest voxel.
        refine: ``"secant"`` or ``"bisection"``, for ``refine_steps`` steps, each followed by a
            final linear interpolation in the bracket (0 steps: interpolation only).
        spp: rays per pixel (supersampling; the mask becomes coverage).
        ao_samples: hemisphere rays per hit for ``ao``.
        ao_radius: AO ray length in world units.
        seed: seed of the AO rays (deterministic per pixel).
        prev_camera: the previous frame's camera; needed for ``flow``.
        flow_fill: ``"none"``, ``"ns"`` (OpenCV Navier-Stokes) or ``"pushpull"``: fill the
            flow of pixels without a hit.
        skip: use the min-max grid to skip bricks (off only to measure what it saves).
        shading: material and light for ``color``.
    """

    width: int
    height: int
    iso: float
    outputs: tuple[str, ...] = ("mask", "normal", "depth")
    step: float | None = None
    refine: str = "secant"
    refine_steps: int = 4
    spp: int = 1
    ao_samples: int = 64
    ao_radius: float = AO_RADIUS
    seed: int = 0
    prev_camera: Camera | None = None
    flow_fill: str = "none"
    skip: bool = True
    shading: ShadingParams = field(default_factory=ShadingParams)

    def __post_init__(self):
        object.__setattr__(self, "outputs", tuple(dict.fromkeys(self.outputs)))
        unknown = [o for o in self.outputs if o not in REQUESTABLE]
        if unknown:
            raise ValueError(f"unknown outputs {unknown}; choose from {', '.join(REQUESTABLE)}")
        if not self.outputs:
            raise ValueError("a render request needs at least one output")
        for name, value, top in (("width", self.width, MAX_SIDE), ("height", self.height, MAX_SIDE),
                                 ("spp", self.spp, MAX_SPP), ("ao_samples", self.ao_samples, MAX_AO_SAMPLES)):
            if not isinstance(value, (int, np.integer)) or not 1 <= value <= top:
                raise ValueError(f"{name} must be an integer in [1, {top}], got {value!r}")
        if not np.isfinite(self.iso):
            raise ValueError(f"iso must be finite, got {self.iso}")
        if self.step is not None and not (np.isfinite(self.step) and self.step > 0):
            raise ValueError(f"step must be a positive length in world units, got {self.step}")
        if self.refine not in REFINE_METHODS:
            raise ValueError(f"refine must be one of {sorted(REFINE_METHODS)}, got {self.refine!r}")
        if not isinstance(self.refine_steps, (int, np.integer)) or not 0 <= self.refine_steps <= 32:
            raise ValueError(f"refine_steps must be an integer in [0, 32], got {self.refine_steps!r}")
        if not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed must be an integer in [0, 2^31), got {self.seed!r}")
        if not (np.isfinite(self.ao_radius) and self.ao_radius > 0):
            raise ValueError(f"ao_radius must be a positive length in world units, got {self.ao_radius}")
        if "flow" in self.outputs and self.prev_camera is None:
            raise ValueError("flow needs a previous camera (prev_camera); the first frame of a sequence has none")
        if self.flow_fill not in FILL_METHODS:
            raise ValueError(f"flow_fill must be one of {FILL_METHODS}, got {self.flow_fill!r}")

    def kernel_outputs(self) -> int:
        """The kernel's OUT_* bits: the asked buffers and the ones they are made from."""
        need = set(self.outputs)
        if "color" in need:
            need |= {"mask", "normal"}
        if "flow" in need and self.flow_fill != "none":
            need.add("mask")
        bits = {"mask": kernels.OUT_MASK, "normal": kernels.OUT_NORMAL, "depth": kernels.OUT_DEPTH,
                "position": kernels.OUT_POSITION, "flow": kernels.OUT_FLOW, "ao": kernels.OUT_AO,
                "samples": kernels.OUT_SAMPLES}
        return sum(bits[name] for name in need if name in bits)


def _view(camera: Camera, width: int, height: int) -> kernels.View:
    """The kernel's camera struct."""
    right, up, back = camera.basis()
    v = kernels.View()
    v.eye = wp.vec3(*camera.eye)
    v.right = wp.vec3(*right)
    v.up = wp.vec3(*up)
    v.back = wp.vec3(*back)
    v.tan_half_fov = camera.tan_half_fov()
    v.width = width
    v.height = height
    return v


class Renderer:
    """Renders isosurfaces of one volume on one device.

    Args:
        volume: the volume; uploaded once, with its min-max grid (independent of the iso).
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        brick_size: voxels per min-max brick edge (a multiple of 8 for sparse volumes).
        threads: CPU only: threads over which the image is split in row bands
            (Warp's CPU kernels run on one thread each); default: all cores.
        max_device_bytes: the most bytes the volume's voxels may take on the device; a volume
            whose dense size is larger is rendered sparse. Default: none on CPU, half of the
            free memory on CUDA.
    """

    def __init__(self, volume: Volume, device: str = "cpu", brick_size: int = 8, threads: int | None = None,
                 max_device_bytes: int | None = None):
        wp.init()
        if device.startswith("cuda") and not wp.is_cuda_available():
            raise RuntimeError(f"device {device!r} asked for, but Warp finds no CUDA device on this machine")
        if brick_size < 1:
            raise ValueError(f"brick_size must be positive, got {brick_size}")
        self.volume = volume
        self.device = wp.get_device(device)
        self.threads = 1 if self.device.is_cuda else (threads or os.cpu_count() or 1)
        wp.load_module(kernels, device=self.device)
        self.brick_size = brick_size
        if max_device_bytes is None and self.device.is_cuda:
            max_device_bytes = int(DENSE_SHARE * self.device.free_memory)
        self.max_device_bytes = max_device_bytes
        self._base = self._base_grid()
        self.pool: BrickPool | None = None
        if max_device_bytes is None or volume.device_bytes <= max_device_bytes:
            self._upload_dense()
            bricks = tuple(max(1, -(-(n - 1) // brick_size)) for n in volume.shape)
            self.minmax = wp.empty(bricks, dtype=wp.vec2, device=self.device)
            wp.launch(kernels.minmax_kernel, dim=bricks, inputs=[self._base, self.minmax], device=self.device)
            total = int(np.prod(bricks))
            self._stats = MemoryStats("dense", volume.storage.name, volume.device_bytes, volume.device_bytes,
                                      volume.device_bytes, max_device_bytes or 0, total, total)
        else:
            self.pool = BrickPool(volume, self.device, brick_size, max_device_bytes)
            self.minmax = self.pool.minmax
            self._base.sparse = 1
            self._base.slots = self.pool.slots
        self._base.minmax = self.minmax
        self._grids: OrderedDict[tuple[float, bool], kernels.Grid] = OrderedDict()
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        # 1x1 stand-ins for buffers a request does not ask for.
        self._unused = {t: wp.empty((1, 1), dtype=t, device=self.device) for t in (wp.float32, wp.vec2, wp.vec3, wp.int32)}

    def _base_grid(self) -> kernels.Grid:
        """The iso-independent part of the kernels' grid, with 1x1x1 stand-ins for the arrays."""
        grid = kernels.Grid()
        for name, dtype in (("data", wp.float32), ("data16", wp.uint16), ("data8", wp.uint8), ("slots", wp.int32)):
            setattr(grid, name, wp.zeros((1, 1, 1), dtype=dtype, device=self.device))
        grid.kind = STORE_KINDS[self.volume.storage.name][0]
        grid.unit = wp.vec2(*self.volume.unit)
        grid.size = wp.vec3i(*self.volume.shape)
        grid.sparse = 0
        grid.brick = self.brick_size
        scale, offset = self.volume.world_transform()
        grid.scale = wp.vec3(*scale)
        grid.offset = wp.vec3(*offset)
        return grid

    def _set_voxels(self, grid: kernels.Grid, voxels: wp.array) -> None:
        """Point ``grid``'s field of the volume's device type at ``voxels``."""
        field = {kernels.STORE_F32: "data", kernels.STORE_U16: "data16", kernels.STORE_U8: "data8"}[grid.kind]
        setattr(grid, field, voxels)

    def _upload_dense(self) -> None:
        """Stream the volume's source to a dense device array, box by box (host memory: a few boxes)."""
        volume = self.volume
        voxels = wp.empty(volume.shape, dtype=STORE_KINDS[volume.storage.name][1], device=self.device)

        def read(box):
            return box, volume.device_box(np.asarray(volume.source.read(*box)))

        for box, values in map_bounded(read, boxes(volume.source), min(os.cpu_count() or 1, 8)):
            wp.copy(voxels[box], wp.array(np.ascontiguousarray(values), device=self.device))
        self._set_voxels(self._base, voxels)

    def memory(self) -> MemoryStats:
        """Where the voxels are (dense or sparse) and what paging cost so far."""
        return self._stats if self.pool is None else self.pool.stats

    def grid(self, iso: float, skip: bool = True) -> kernels.Grid:
        """The kernels' view of the volume for one iso: data plus each brick's distance to an active brick.

        Built on the device from the min-max grid (a few small launches) and kept for the
        last few iso-values. A sparse volume first pages in the bricks the iso needs.
        """
        key = (float(iso), bool(skip))
        if self.pool is not None:
            self.pool.ensure(iso)
            self._set_voxels(self._base, self.pool.pool)  # the pool may have grown
        if key in self._grids:
            self._grids.move_to_end(key)
            grid = self._grids[key]
            if self.pool is not None:
                self._set_voxels(grid, self.pool.pool)
            return grid
        shape = self.minmax.shape
        dist = wp.empty(shape, dtype=wp.uint8, device=self.device)
        spare = wp.empty(shape, dtype=wp.uint8, device=self.device)
        wp.launch(kernels.occupancy_kernel, dim=shape, inputs=[self.minmax, float(iso), int(skip), MAX_LEAP, dist],
                  device=self.device)
        for axis in range(3):
            wp.launch(kernels.chebyshev_pass_kernel, dim=shape, inputs=[dist, axis, MAX_LEAP, spare], device=self.device)
            dist, spare = spare, dist
        grid = kernels.Grid()
        for name in kernels.Grid.vars:
            if name != "dist":
                setattr(grid, name, getattr(self._base, name))
        grid.dist = dist
        self._grids[key] = grid
        if len(self._grids) > GRID_CACHE:
            self._grids.popitem(last=False)
        return grid

    def default_step(self) -> float:
        """Half the smallest voxel edge, in world units."""
        return 0.5 * self.volume.voxel_size_world()

    def render(self, camera: Camera, request: RenderRequest, rows: tuple[int, int] | None = None) -> FrameBuffers:
        """Render one frame; buffers come back as torch tensors on the renderer's device.

        Args:
            rows: render only the image rows ``[start, stop)`` (a focus region); the buffers keep
                the full image size and hold undefined values (possibly NaN) in the other rows.
        """
        w, h = request.width, request.height
        row0, row1 = (0, h) if rows is None else rows
        if not 0 <= row0 < row1 <= h:
            raise ValueError(f"rows must satisfy 0 <= start < stop <= height {h}, got {rows}")
        bits = request.kernel_outputs()
        params = kernels.RayParams()
        params.iso = float(request.iso)
        params.step = float(request.step or self.default_step())
        params.refine_mode = REFINE_METHODS[request.refine]
        params.refine_steps = request.refine_steps
        params.spp = request.spp
        params.ao_samples = request.ao_samples
        params.ao_radius = float(request.ao_radius)
        params.seed = request.seed
        params.outputs = bits
        grid = self.grid(request.iso, request.skip)

        def buffer(bit: int, dtype) -> wp.array:
            # The kernel writes every pixel of an asked buffer.
            return wp.empty((h, w), dtype=dtype, device=self.device) if bits & bit else self._unused[dtype]

        arrays = {
            "mask": buffer(kernels.OUT_MASK, wp.float32),
            "normal": buffer(kernels.OUT_NORMAL, wp.vec3),
            "depth": buffer(kernels.OUT_DEPTH, wp.float32),
            "position": buffer(kernels.OUT_POSITION, wp.vec3),
            "flow": buffer(kernels.OUT_FLOW, wp.vec2),
            "ao": buffer(kernels.OUT_AO, wp.float32),
            "samples": buffer(kernels.OUT_SAMPLES, wp.int32),
        }
        view = _view(camera, w, h)
        prev = view if request.prev_camera is None else _view(request.prev_camera, w, h)

        tiles_x = -(-w // kernels.TILE_W)

        def launch(row0: int, rows: int):
            threads = tiles_x * -(-rows // kernels.TILE_H) * kernels.TILE_W * kernels.TILE_H
            wp.launch(kernels.render_kernel, dim=threads,
                      inputs=[grid, view, prev, params, row0, rows, *arrays.values()], device=self.device)

        if self.device.is_cuda:
            with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(self.device.ordinal))):
                launch(row0, row1 - row0)
        else:
            bands = np.array_split(np.arange(row0, row1), min(row1 - row0, 4 * self.threads))
            jobs = [(int(b[0]), len(b)) for b in bands if len(b)]
            if self._pool is None:
                for job in jobs:
                    launch(*job)
            else:
                list(self._pool.map(lambda job: launch(*job), jobs))

        tensors = {name: wp.to_torch(a) for name, a in arrays.items() if a.shape == (h, w)}
        frame = FrameBuffers()
        for name in request.outputs:
            if name == "color":
                continue
            setattr(frame, name, tensors[name])
        if "flow" in request.outputs and request.flow_fill != "none":
            frame.flow = fill_flow(tensors["flow"], tensors["mask"], request.flow_fill)
        if "color" in request.outputs:
            ao = tensors["ao"] if bits & kernels.OUT_AO else None
            frame.color = shade(tensors["mask"], tensors["normal"], ao, request.shading)
        return frame
