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

import functools
import math
import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from isosr_render import kernels, voxels
from isosr_render.brick_pool import BrickPool, MemoryStats
from isosr_render.buffers import FrameBuffers
from isosr_render.camera import Camera
from isosr_render.clip import MAX_PLANES, Clip
from isosr_render.color_field import ColorField
from isosr_render.conventions import AO_RADIUS, BUFFER_NAMES
from isosr_render.flow_fill import FILL_METHODS, fill_flow
from isosr_render.scan import BRICK
from isosr_render.shading import ShadingParams, composite, shade
from isosr_render.surfaces import MAX_SURFACES, Surfaces
from isosr_render.volume import Volume, native_integer
from isosr_render.voxels import VoxelSource, boxes, map_bounded

REFINE_METHODS = {"bisection": kernels.REFINE_BISECTION, "secant": kernels.REFINE_SECANT}
REQUESTABLE = BUFFER_NAMES + ("samples",)
# Largest image side and supersampling the renderer accepts (a bound against runaway requests).
MAX_SIDE = 16384
MAX_SPP = 256
MAX_AO_SAMPLES = 4096
# Cap of the brick distance grid: a ray leaps at most (2 MAX_LEAP - 1) bricks at once.
MAX_LEAP = 16
GRID_CACHE = 4
# Render plans that Renderer.render keeps (one per plan key, thread and CUDA stream; each holds
# one frame's buffers): a plan made per call cost 0.6-0.9 ms of host time on the GPU machine.
PLAN_CACHE = 4
# Pixels of the views one launch renders at most (Renderer.render_views): a plan of several views holds all their
# buffers, sixteen 1080p views' about 1.5 GB with AO, flow and positions; a larger batch renders in more launches.
MAX_LAUNCH_PIXELS = 16 * 1920 * 1080
# Without a limit, a CUDA renderer keeps a volume dense while it takes at most this share of free memory.
DENSE_SHARE = 0.5
# The voxels' Warp type on the device, per storage name (see isosr_render.volume).
STORE_TYPES = {"float32": wp.float32, "uint16": wp.uint16, "uint8": wp.uint8}
# surface_kernel's buffers in its argument order: OUT_* bit and Warp type.
KERNEL_BUFFERS = {"mask": (kernels.OUT_MASK, wp.float32), "normal": (kernels.OUT_NORMAL, wp.vec3),
                  "depth": (kernels.OUT_DEPTH, wp.float32), "position": (kernels.OUT_POSITION, wp.vec3),
                  "flow": (kernels.OUT_FLOW, wp.vec2), "ao": (kernels.OUT_AO, wp.float32),
                  "cap": (kernels.OUT_CAP, wp.vec2), "samples": (kernels.OUT_SAMPLES, wp.int32),
                  "surface": (kernels.OUT_SURFACE, wp.float32)}
# Host layout of kernels.FrameArgs (a numpy record with the ctypes struct's offsets).
FRAME_DTYPE = np.dtype(kernels.FrameArgs.numpy_dtype())
# Host layout of a clip's values (kernels.ClipArgs' two arrays, one record): its kernels.ClipRegion, then at a
# 16-byte boundary its plane rows.
_REGION = np.dtype(kernels.ClipRegion.numpy_dtype())
CLIP_DTYPE = np.dtype({"names": ["region", "planes"], "formats": [_REGION, (np.float32, (MAX_PLANES, 4))],
                       "offsets": [0, -(-_REGION.itemsize // 16) * 16],
                       "itemsize": -(-_REGION.itemsize // 16) * 16 + MAX_PLANES * 16})
CAP_SIGNS = {"none": 0, "above": 1, "below": -1}


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
        clip: clip planes, crop box and caps (:mod:`isosr_render.clip`); the default cuts nothing.
            With caps, ``color`` shows the cut faces in the volume's values (the ``cap`` buffer).
        coloring: colour the surface by a field (:class:`~isosr_render.color_field.ColorField`): the frame
            gets ``albedo`` (from ``position``, rendered for it) and ``color`` shades with it; None: no pass.
        surfaces: several isosurfaces (:mod:`isosr_render.surfaces`; ``iso`` must be their first): rays stop at
            the nearest of them, the frame gets ``surface`` and ``albedo`` (their colours) and ``color`` shades
            with it; with translucent ones also ``behind``, the second layer, and ``color`` composites both. Not
            with a coloring, nor on a sparse volume. None: the one ``iso``.
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
    clip: Clip = field(default_factory=Clip)
    coloring: ColorField | None = None
    surfaces: Surfaces | None = None

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
        if not math.isfinite(self.iso):
            raise ValueError(f"iso must be finite, got {self.iso}")
        if self.step is not None and not (math.isfinite(self.step) and self.step > 0):
            raise ValueError(f"step must be a positive length in world units, got {self.step}")
        if self.refine not in REFINE_METHODS:
            raise ValueError(f"refine must be one of {sorted(REFINE_METHODS)}, got {self.refine!r}")
        if not isinstance(self.refine_steps, (int, np.integer)) or not 0 <= self.refine_steps <= 32:
            raise ValueError(f"refine_steps must be an integer in [0, 32], got {self.refine_steps!r}")
        if not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed must be an integer in [0, 2^31), got {self.seed!r}")
        if not (math.isfinite(self.ao_radius) and self.ao_radius > 0):
            raise ValueError(f"ao_radius must be a positive length in world units, got {self.ao_radius}")
        if "flow" in self.outputs and self.prev_camera is None:
            raise ValueError("flow needs a previous camera (prev_camera); the first frame of a sequence has none")
        if self.flow_fill not in FILL_METHODS:
            raise ValueError(f"flow_fill must be one of {FILL_METHODS}, got {self.flow_fill!r}")
        if not isinstance(self.clip, Clip):
            raise ValueError(f"clip must be an isosr_render.clip.Clip, got {type(self.clip).__name__}")
        if self.coloring is not None and not isinstance(self.coloring, ColorField):
            raise ValueError(f"coloring must be an isosr_render.color_field.ColorField, got "
                             f"{type(self.coloring).__name__}")
        self._check_surfaces()
        if "albedo" in self.outputs and self.coloring is None and self.surfaces is None:
            raise ValueError("the albedo output needs a coloring or several surfaces")

    def _check_surfaces(self) -> None:
        """ValueError where ``surfaces`` is not :class:`Surfaces`, disagrees with ``iso`` or comes with a coloring,
        or ``surface`` is asked for without it."""
        if self.surfaces is None:
            if "surface" in self.outputs:
                raise ValueError("the surface output needs several surfaces (surfaces=...)")
            return
        if not isinstance(self.surfaces, Surfaces):
            raise ValueError(f"surfaces must be an isosr_render.surfaces.Surfaces, got {type(self.surfaces).__name__}")
        if self.iso != self.surfaces.iso:
            raise ValueError(f"iso must be the first surface's ({self.surfaces.iso}), got {self.iso}")
        if self.coloring is not None:
            raise ValueError("several surfaces colour the frame by their own colours: not with a coloring")

    def kernel_outputs(self) -> int:
        """The kernel's OUT_* bits: the asked buffers and the ones they are made from."""
        need = set(self.outputs)
        if "color" in need:
            need |= {"mask", "normal"} | ({"cap"} if self.clip.capped else set())
        if self.coloring is not None:
            need |= {"mask", "position"}
        if self.surfaces is not None:
            need |= {"mask", "surface"}
        if "flow" in need and self.flow_fill != "none":
            need.add("mask")
        return sum(KERNEL_BUFFERS[name][0] for name in need if name in KERNEL_BUFFERS)

    def plan_key(self) -> tuple:
        """What a :class:`RenderPlan` fixes: size, buffers, rays per pixel, and whether it clips (the kernels
        that clip are their own, :func:`isosr_render.kernels.frame_kernels`) and caps (a buffer of the kernels'
        for ``color``), whether it colours (``position`` rendered for it) and the layers of several surfaces (0:
        one iso; their kernels are their own); the rest may change per frame."""
        return (self.width, self.height, self.outputs, self.flow_fill, self.spp, self.clip.active, self.clip.capped,
                self.coloring is not None, 0 if self.surfaces is None else self.surfaces.layers)

    def launch_key(self) -> tuple:
        """What the views of one launch share (:meth:`RenderPlan.stage_views`): the plan key, the iso and its
        empty-space skipping, the clip and the surfaces; the rest (cameras, seed, step, AO rays...) is each view's."""
        return self.plan_key(), float(self.iso), self.skip, self.clip, self.surfaces


def warp_device(device: str):
    """The Warp device ``device`` names (``cpu``, ``cuda``, ``cuda:N``); a clear error without CUDA."""
    wp.init()
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError(f"device {device!r} asked for, but Warp finds no CUDA device on this machine")
    return wp.get_device(device)


def load_frame_kernels(device: wp.context.Devicelike, clipped: bool, several: bool = False) -> None:
    """Load the frame kernels that clip (``clipped``) and march several isos (``several``) on the Warp ``device``,
    compiled on their first use (some seconds on a CPU, unless the kernel cache has them): on
    any thread (a server loads them off its device thread), never while that thread captures a CUDA graph."""
    variant = kernels.frame_variant(clipped, several)
    wp.load_module(wp.get_module(kernels.VARIANT_MODULES[variant]), device=device)


def device_limit(device, max_device_bytes: int | None) -> int | None:
    """The bytes a volume's voxels may take on ``device`` before it renders sparse: the given
    limit, else ``DENSE_SHARE`` of the free memory on CUDA, none on the CPU."""
    if max_device_bytes is None and device.is_cuda:
        return int(DENSE_SHARE * device.free_memory)
    return max_device_bytes


def _fill_view(record: np.ndarray, camera: Camera, width: int, height: int) -> None:
    """Write a camera into a `kernels.View` record."""
    right, up, back = camera.basis()
    for name, value in (("eye", camera.eye), ("right", right), ("up", up), ("back", back),
                        ("tan_half_fov", camera.tan_half_fov()), ("width", width), ("height", height)):
        record[name] = value


def frame_args(camera: Camera, request: RenderRequest, step: float, out: np.ndarray | None = None) -> np.ndarray:
    """One frame's `kernels.FrameArgs` as a host record (:data:`FRAME_DTYPE`, shape (1,)): a new one,
    or ``out`` (such a record) written over, every field of it."""
    args = np.zeros(1, FRAME_DTYPE) if out is None else out
    _fill_view(args["view"], camera, request.width, request.height)
    _fill_view(args["prev"], request.prev_camera or camera, request.width, request.height)
    params = args["params"]
    for name, value in (("iso", request.iso), ("step", step), ("refine_mode", REFINE_METHODS[request.refine]),
                        ("refine_steps", request.refine_steps), ("spp", request.spp),
                        ("ao_samples", request.ao_samples), ("ao_radius", request.ao_radius),
                        ("seed", request.seed), ("outputs", request.kernel_outputs())):
        params[name] = value
    return args


def clip_args(clip: Clip, out: np.ndarray | None = None) -> np.ndarray:
    """A clip's values for the clipped kernels (`kernels.ClipArgs`) as a host record (:data:`CLIP_DTYPE`,
    shape (1,)): a new one, or ``out`` written over, every field of it."""
    args = np.zeros(1, CLIP_DTYPE) if out is None else out
    box = clip.box or ((0.0,) * 3,) * 2
    region = args["region"]
    for name, value in (("count", len(clip.planes)), ("boxed", clip.box is not None), ("lo", box[0]),
                        ("hi", box[1]), ("cap", CAP_SIGNS[clip.cap])):
        region[name] = value
    args["planes"] = clip.plane_rows()
    return args


# The texture filter's interpolation weights are 8-bit fractions: a sample may be off by up to
# 3/256 of its cell's value range; this margin over it also covers the float rounding of gain and bias.
FILTER_ERROR = 4 / 256


def filtered_layout(dense: wp.array, minmax: wp.array, unit: tuple[float, float], device) -> kernels.Filtered:
    """Dense voxels' :class:`~isosr_render.kernels.Filtered` layout: their texture (a copy) and its
    error bound, from the widest brick value range (each cell lies in a brick, overlap included)."""
    wp.synchronize_device(device)  # the voxels and their min-max grid were made on Warp's stream
    layout = kernels.Filtered()
    layout.tex = wp.Texture3D(dense, filter_mode=wp.TextureFilterMode.LINEAR,
                              address_mode=wp.TextureAddressMode.CLAMP, normalized_coords=False, device=device)
    texel = {wp.uint8: 255.0, wp.uint16: 65535.0, wp.float32: 1.0}[dense.dtype]  # raw value of a texel read as 1
    d0, a = unit
    layout.gain, layout.bias = texel * a, d0 * a
    ranges = wp.to_torch(minmax)
    layout.near = FILTER_ERROR * float((ranges[..., 1] - ranges[..., 0]).max()) + 1e-5
    return layout


def write_box(dense: wp.array, box: tuple[slice, slice, slice], values: np.ndarray) -> None:
    """Device values of a box into dense voxels: in place on the CPU (host memory already),
    else uploaded contiguous and copied into the box."""
    if dense.device.is_cpu:
        dense.numpy()[box] = values
    else:
        wp.copy(dense[box], wp.array(np.ascontiguousarray(values), device=dense.device))


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
        dense: the volume's voxels already on the device, dense (:meth:`load` makes them); None:
            streamed from the volume's source here.
        filtered: march dense voxels through a copy of them as a hardware-filtered texture
            (:class:`~isosr_render.kernels.Filtered`: the same hits, fewer loads; twice the
            voxels' bytes on the device). None: on CUDA where twice the voxels fit the limit;
            True: also on the CPU (Warp filters in software there), else ValueError; False: never.
    """

    def __init__(self, volume: Volume, device: str = "cpu", brick_size: int = 8, threads: int | None = None,
                 max_device_bytes: int | None = None, dense: wp.array | None = None, filtered: bool | None = None):
        if brick_size < 1:
            raise ValueError(f"brick_size must be positive, got {brick_size}")
        self.volume = volume
        self._default_step = 0.5 * volume.voxel_size_world()  # per frame staged: computed once
        self.device = warp_device(device)
        self.threads = 1 if self.device.is_cuda else (threads or os.cpu_count() or 1)
        wp.load_module(kernels, device=self.device)
        self.brick_size = brick_size
        self.max_device_bytes = max_device_bytes = device_limit(self.device, max_device_bytes)
        self._base = self._base_grid()
        self.pool: BrickPool | None = None
        if max_device_bytes is None or volume.device_bytes <= max_device_bytes:
            if dense is None:
                dense = self._upload_dense()
            elif dense.shape != volume.shape or dense.dtype != STORE_TYPES[volume.storage.name]:
                raise ValueError(f"dense voxels of shape {dense.shape} do not fit the volume {volume.shape} "
                                 f"of {volume.storage.name}")
            self._dense = dense
            bricks = tuple(max(1, -(-(n - 1) // brick_size)) for n in volume.shape)
            if brick_size == BRICK:  # the volume's bricks are what the kernel computes (normalized, overlap included)
                self.minmax = wp.array(volume.bricks, dtype=wp.vec2, device=self.device)
            else:
                self.minmax = wp.empty(bricks, dtype=wp.vec2, device=self.device)
                wp.launch(kernels.minmax_kernel, dim=bricks, inputs=[dense, self._base, self.minmax],
                          device=self.device)
            self.layout = self._dense_layout(dense, filtered)
            resident = volume.device_bytes * (2 if self.filtered else 1)
            total = int(np.prod(bricks))
            self._stats = MemoryStats("dense", volume.storage.name, volume.device_bytes, resident, resident,
                                      max_device_bytes or 0, total, total)
        else:
            if filtered:
                raise ValueError(f"filtered: the volume ({volume.device_bytes} bytes) renders sparse past "
                                 f"max_device_bytes={max_device_bytes}; only dense voxels march a texture")
            self.pool = BrickPool(volume, self.device, brick_size, max_device_bytes)
            self.minmax = self.pool.minmax
            self.layout = kernels.Sparse()
            self.layout.brick, self.layout.slots, self.layout.minmax = brick_size, self.pool.slots, self.minmax
        wp.synchronize_device(self.device)  # uploads ran on Warp's stream; renders run on torch's
        self._grids: OrderedDict[tuple[float, bool], kernels.Grid] = OrderedDict()
        self._plans: OrderedDict[tuple, RenderPlan] = OrderedDict()
        self._plans_lock = threading.Lock()
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        # 1x1 stand-ins for buffers a request does not ask for (and for the per-sample march counts).
        self._unused = {t: wp.empty((1, 1), dtype=t, device=self.device) for t in (wp.float32, wp.vec2, wp.vec3, wp.int32)}
        self._unused_counts = wp.empty((1, 1, 1), dtype=wp.int32, device=self.device)
        self._unused_hits = wp.empty((1, 1, 1), dtype=wp.float32, device=self.device)

    @property
    def filtered(self) -> bool:
        """Whether the march reads a filtered texture of the voxels (:class:`~isosr_render.kernels.Filtered`)."""
        return isinstance(self.layout, kernels.Filtered.cls)

    def _dense_layout(self, dense: wp.array, filtered: bool | None) -> kernels.Dense | kernels.Filtered:
        """Dense voxels' layout: :func:`filtered_layout` where asked (``filtered``, else
        ValueError), or by default on CUDA where twice the voxels fit the limit and the device
        makes the texture (its sides and memory allow); else :class:`~isosr_render.kernels.Dense`."""
        volume, limit = self.volume, self.max_device_bytes
        fits = limit is None or 2 * volume.device_bytes <= limit
        if filtered and not fits:
            raise ValueError(f"filtered: the voxels and their texture ({2 * volume.device_bytes} bytes) do not fit "
                             f"max_device_bytes={limit}")
        if filtered or (filtered is None and self.device.is_cuda and fits):
            try:
                return filtered_layout(dense, self.minmax, volume.unit, self.device)
            except RuntimeError as e:  # e.g. a side past the device's 3D texture extent
                if filtered:
                    raise ValueError(f"filtered: {self.device} cannot make the voxels' texture: {e}") from e
        layout = kernels.Dense()
        layout.brick = self.brick_size
        return layout

    def _base_grid(self) -> kernels.Grid:
        """The iso-independent part of the kernels' grid (a 1x1x1 stand-in for the distance grid)."""
        grid = kernels.Grid()
        grid.dist = wp.zeros((1, 1, 1), dtype=wp.uint8, device=self.device)
        grid.unit = wp.vec2(*self.volume.unit)
        grid.size = wp.vec3i(*self.volume.shape)
        grid.brick = self.brick_size
        scale, offset = self.volume.world_transform()
        grid.scale = wp.vec3(*scale)
        grid.offset = wp.vec3(*offset)
        return grid

    @property
    def voxels(self) -> wp.array:
        """The voxels on the device in their storage type: dense (the volume's shape) or the brick pool
        (which may grow as bricks page in), laid out as :attr:`layout` says."""
        return self._dense if self.pool is None else self.pool.pool

    @classmethod
    def load(cls, source: VoxelSource, device: str = "cpu", **kwargs) -> "Renderer":
        """Scan a voxel source and make its renderer, in one read of the source for 8/16-bit
        integers headed for a dense volume (each box goes to the device as the scan reads it);
        float and 32-bit data, and sparse volumes, read it again (see :mod:`isosr_render.scan`).

        Args:
            kwargs: as :class:`Renderer` (``brick_size``, ``threads``, ``max_device_bytes``).
        """
        target = warp_device(device)
        limit = device_limit(target, kwargs.get("max_device_bytes"))
        dtype = np.dtype(source.dtype)
        dense, sink = None, None
        if native_integer(dtype) and (limit is None or int(np.prod(source.shape)) * dtype.itemsize <= limit):
            kind = STORE_TYPES[f"uint{8 * dtype.itemsize}"]
            dense = wp.empty(tuple(source.shape), dtype=kind, device=target)

            def sink(box, values):
                write_box(dense, box, values)

        return cls(Volume.from_source(source, sink=sink), device, dense=dense, **kwargs)

    def _upload_dense(self) -> wp.array:
        """Stream the volume's source to a dense device array, box by box (host memory: a few boxes);
        float32 as stored where it may be, normalized there in one pass (:attr:`Volume.raw_float32`)."""
        volume = self.volume
        dense = wp.empty(volume.shape, dtype=STORE_TYPES[volume.storage.name], device=self.device)
        raw = volume.raw_float32

        def read(box):
            stored = np.asarray(volume.source.read(*box))
            return box, stored if raw else volume.device_box(stored)

        for box, values in map_bounded(read, boxes(volume.source), voxels.READ_THREADS):
            write_box(dense, box, values)
        if raw:  # after Warp's copies (its stream), before Warp reads the voxels again: torch's pass between syncs
            wp.synchronize_device(self.device)
            volume.normalize_float32_(wp.to_torch(dense))
            if self.device.is_cuda:
                torch.cuda.synchronize(self.torch_device)
        return dense

    @functools.cached_property
    def torch_device(self) -> torch.device:
        """The renderer's device as torch names it (``cpu``, ``cuda:N``): where its buffers live."""
        return torch.device(wp.device_to_torch(self.device))

    def memory(self) -> MemoryStats:
        """Where the voxels are (dense or sparse) and what paging cost so far."""
        return self._stats if self.pool is None else self.pool.stats

    def grid(self, iso: float | tuple[float, ...], skip: bool = True) -> kernels.Grid:
        """The kernels' view of the volume for one iso (or up to :data:`MAX_SURFACES`, a brick active for any):
        its shape and scale, and each brick's distance to an active brick.

        Built on the device from the min-max grid (a few small launches) and kept for the
        last few iso-values. A sparse volume first pages in the bricks the iso needs (one iso only).
        """
        isos = tuple(float(v) for v in np.atleast_1d(iso))
        key = (isos, bool(skip))
        if self.pool is not None:
            if len(isos) > 1:
                raise ValueError(f"{self.volume.name or 'volume'}: several surfaces need a dense volume; this one "
                                 f"renders sparse past max_device_bytes={self.max_device_bytes}")
            self.pool.ensure(isos[0])
        if key in self._grids:
            self._grids.move_to_end(key)
            return self._grids[key]
        shape = self.minmax.shape
        dist = wp.empty(shape, dtype=wp.uint8, device=self.device)
        spare = wp.empty(shape, dtype=wp.uint8, device=self.device)
        padded = wp.vec4(*(isos + (float(kernels.BIG),) * (MAX_SURFACES - len(isos))))
        wp.launch(kernels.occupancy_kernel, dim=shape, inputs=[self.minmax, padded, int(skip), MAX_LEAP, dist],
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
        return self._default_step

    def plan(self, request: RenderRequest, views: int = 1) -> "RenderPlan":
        """Buffers and a launch reused by frames of ``request``'s size and outputs, of up to ``views`` views at
        once (see :class:`RenderPlan`)."""
        return RenderPlan(self, request, views)

    def render(self, camera: Camera, request: RenderRequest, rows: tuple[int, int] | None = None) -> FrameBuffers:
        """Render one frame into new buffers; they come back as torch tensors on the renderer's device.

        A kept plan of the request's size and outputs renders it (one per thread and CUDA stream, the
        last :data:`PLAN_CACHE`), and its buffers are copied out: frames never share memory.

        Args:
            rows: render only the image rows ``[start, stop)`` (a focus region); the buffers keep
                the full image size and hold undefined values (possibly NaN) in the other rows.
        """
        plan = self._kept_plan(request)
        return plan.owned([plan.render(camera, request, rows)])[0]

    def render_views(self, frames: Sequence[tuple[Camera, RenderRequest]]) -> list[FrameBuffers]:
        """Several views in one launch, each into new buffers as :meth:`render` makes them and equal to its view
        rendered alone: ``(camera, request)`` each, the requests alike in what a launch shares
        (:meth:`RenderRequest.launch_key`). A kept plan of the next power of two of views renders them; more
        pixels than :data:`MAX_LAUNCH_PIXELS` render in several launches.

        Raises:
            ValueError: no views, or requests that one launch cannot render (:meth:`RenderPlan.stage_views`).
        """
        if not frames:
            raise ValueError("render_views: no views to render")
        request = frames[0][1]
        per_launch = max(1, MAX_LAUNCH_PIXELS // (request.width * request.height))
        out = []
        for start in range(0, len(frames), per_launch):
            views = frames[start:start + per_launch]
            plan = self._kept_plan(request, 1 << (len(views) - 1).bit_length())
            plan.stage_views(views)
            plan.launch()
            out += plan.owned(plan.view_buffers([r for _, r in views]))
        return out

    def _kept_plan(self, request: RenderRequest, views: int = 1) -> RenderPlan:
        """The kept plan for ``request`` and up to ``views`` views on this thread and CUDA stream (made on first
        use)."""
        stream = torch.cuda.current_stream(self.device.ordinal).cuda_stream if self.device.is_cuda else None
        key = (request.plan_key(), views, threading.get_ident(), stream)
        with self._plans_lock:
            plan = self._plans.get(key)
            if plan is None:
                plan = self._plans[key] = self.plan(request, views)
                if len(self._plans) > PLAN_CACHE:
                    self._plans.popitem(last=False)
            self._plans.move_to_end(key)
        return plan


def surface_albedo(surfaces: Surfaces, table_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``surface`` buffer (indices of ``surfaces.items``, -1 where none), ``albedo`` (their colours, 0 where
    none) and their opacities (1 where none) of the kernels' per-pixel indices into the iso table (ascending isos,
    :meth:`Surfaces.table`)."""
    order, colors, _ = _surface_tables(surfaces, table_index.device)
    # Rows a frame did not render hold anything (a focus region's, a band's yet to come): bounded first.
    index = torch.nan_to_num(table_index, nan=-1.0).clamp(-1.0, len(surfaces.items) - 1.0).long()
    surface = order[index]  # -1 indexes the last entry: none
    return surface, colors[surface.long()], surface_opacity(surfaces, surface)


def surface_opacity(surfaces: Surfaces, surface: torch.Tensor) -> torch.Tensor:
    """The opacity of each pixel's surface, of the ``surface`` buffer (indices of ``surfaces.items``; -1, none: 1)."""
    return _surface_tables(surfaces, surface.device)[2][surface.long()]


@functools.lru_cache(maxsize=16)
def _surface_tables(surfaces: Surfaces, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """On ``device`` (made once: a copy to a GPU stalls): the user's index of each table entry, each surface's
    colour and opacity, each followed by the entry of none (-1, black, 1)."""
    order = torch.tensor(surfaces.order() + [-1], dtype=torch.float32, device=device)
    colors = torch.tensor([s.color for s in surfaces.items] + [(0.0, 0.0, 0.0)], dtype=torch.float32, device=device)
    opacities = torch.tensor([s.opacity for s in surfaces.items] + [1.0], dtype=torch.float32, device=device)
    return order, colors, opacities


class RenderPlan:
    """Frames of one size and one set of outputs (:meth:`RenderRequest.plan_key`) on one renderer,
    rendered into buffers the plan owns.

        plan = renderer.plan(request)
        for camera, prev in sequence_cameras(path):
            frame = plan.render(camera, replace(request, prev_camera=prev))  # the plan's buffers

    The buffers are made once. Per frame, :meth:`stage` packs the camera, the previous camera and
    the ray parameters (iso, step, seed, AO rays...) into the plan's host record and copies it to
    the device (on CUDA from pinned memory, asynchronous on the current torch stream; a stage
    waits until the last one's copy has run);
    :meth:`launch` runs the two kernels that read them there: the first hit of each ray
    (:func:`~isosr_render.kernels.first_hit_kernel`), then the buffers from the hits
    (:func:`~isosr_render.kernels.surface_kernel`; for several rays per pixel
    ``surface_samples_kernel``). Neither allocates, so a launch captured in a CUDA graph
    (``torch.cuda.graph``) renders each frame staged before its replay.
    A captured launch keeps the iso's grid it was captured with: capture again for another iso.

    The tensors a frame returns are views of the plan's buffers, valid until its next frame:
    clone what must outlive it (:meth:`owned`).

    A plan of ``views`` views renders up to that many frames of one iso, clip and surfaces in one launch
    (:meth:`stage_views`, :meth:`launch`, :meth:`view_buffers`): their buffers lie one under the other
    (:func:`~isosr_render.kernels.view_of`), each view with its own record of camera and ray parameters, and
    each equals its frame rendered alone.
    """

    def __init__(self, renderer: Renderer, request: RenderRequest, views: int = 1):
        self.renderer, self.key, self.views = renderer, request.plan_key(), views
        device = renderer.device
        self.layers = 1 if request.surfaces is None else request.surfaces.layers
        if views < 1 or (views > 1 and self.layers == 2):
            raise ValueError(f"a render plan holds 1 view or more (translucent surfaces' two layers: one), not {views}")
        self.arrays, self.tensors, self._hits, self._counts, self._storage = self._layer(request)
        if self.layers == 2:  # translucent surfaces: the second layer's own
            self.behind_arrays, self.behind_tensors, self._behind_hits, self._behind_counts, _ = self._layer(request)
        # The staged FrameArgs in torch memory (stream-ordered copies), seen by Warp as one struct, and
        # after it a clipping plan's clip (CLIP_DTYPE, seen as kernels.ClipArgs' arrays) and a several-surface
        # plan's iso table (kernels.IsoSet's), copied from one host record (pinned on CUDA: written again once
        # its last copy has run).
        self.clipped, self.several = request.clip.active, request.surfaces is not None
        if self.several and renderer.pool is not None:
            renderer.grid((0.0, 1.0))  # the sparse volume's error, before anything is made
        records = FRAME_DTYPE.itemsize * views  # a view's record each
        at = -(-records // 16) * 16
        isos_at = at + (CLIP_DTYPE.itemsize if self.clipped else 0)
        size = isos_at + 8 * MAX_SURFACES if self.several else at + CLIP_DTYPE.itemsize if self.clipped else records
        self._args_bytes = torch.zeros(size, dtype=torch.uint8, device=renderer.torch_device)
        self._host_bytes = torch.zeros(size, dtype=torch.uint8, pin_memory=device.is_cuda)
        self._host_args = self._host_bytes.numpy()[:records].view(FRAME_DTYPE)
        self._copied = torch.cuda.Event() if device.is_cuda else None
        base = self._args_bytes.data_ptr()
        self._args = wp.array(ptr=base, dtype=kernels.FrameArgs, shape=(views,), device=device)
        self._clip = kernels.NoClip()
        self._host_clip = None
        if self.clipped:
            self._host_clip = self._host_bytes.numpy()[at:at + CLIP_DTYPE.itemsize].view(CLIP_DTYPE)
            self._clip = kernels.ClipArgs()
            self._clip.region = wp.array(ptr=base + at, dtype=kernels.ClipRegion, shape=(1,), device=device)
            self._clip.planes = wp.array(ptr=base + at + CLIP_DTYPE.fields["planes"][1], dtype=wp.vec4,
                                         shape=(MAX_PLANES,), device=device)
        self._isos = kernels.OneIso()
        self._host_isos = None
        if self.several:
            self._host_isos = self._host_bytes.numpy()[isos_at:].view(np.float32)
            table = wp.array(ptr=base + isos_at, dtype=wp.float32, shape=(2 * MAX_SURFACES,), device=device)
            self._isos = self._iso_set(table, 0, renderer._unused_hits)
            if self.layers == 2:
                self._behind_isos = self._iso_set(table, 1, self._hits)
        load_frame_kernels(device, self.clipped, self.several)  # not while a graph is captured
        self._grid: kernels.Grid | None = None
        # ((grid, voxels), {bands: launches}): the launches recorded over the grid and voxels of the last frame.
        self._launches: tuple[tuple, dict[tuple, list[tuple[wp.Launch, ...]]]] | None = None
        self._staged = 0  # views staged for the next launch

    def _layer(self, request: RenderRequest) -> tuple[dict, dict, wp.array, wp.array, torch.Tensor]:
        """One layer's kernel buffers by name (those not asked for the renderer's 1x1 stand-ins), the present ones
        as tensors (views of one storage, so that a frame's are copied out in one copy: :meth:`owned`), per ray of
        the first HIT_PLANES of each pixel (rays, rows, columns) the hit's ray parameter and its march's sample
        count, and that storage."""
        renderer, bits = self.renderer, request.kernel_outputs()
        h, w = self.views * request.height, request.width  # the views one under the other (kernels.view_of)
        asked = {name: dtype for name, (bit, dtype) in KERNEL_BUFFERS.items() if bits & bit}
        channels = {name: wp.types.type_size_in_bytes(dtype) // 4 for name, dtype in asked.items()}  # 4-byte scalars
        storage = torch.empty(sum(channels.values()) * h * w, dtype=torch.float32, device=renderer.torch_device)
        tensors, at = {}, 0
        for name, dtype in asked.items():  # int32 buffers viewed as such
            part = storage[at:at + channels[name] * h * w]
            part = part.view(h, w, channels[name]) if channels[name] > 1 else part.view(h, w)
            tensors[name], at = part.view(torch.int32) if dtype == wp.int32 else part, at + part.numel()
        arrays = {name: wp.from_torch(tensors[name], dtype=dtype) if name in asked else renderer._unused[dtype]
                  for name, (_, dtype) in KERNEL_BUFFERS.items()}
        planes = (min(request.spp, kernels.HIT_PLANES), h, w)
        hits = wp.empty(planes, dtype=wp.float32, device=renderer.device)
        counts = (wp.empty(planes, dtype=wp.int32, device=renderer.device)
                  if bits & kernels.OUT_SAMPLES else renderer._unused_counts)
        return arrays, tensors, hits, counts, storage

    def owned(self, frames: list[FrameBuffers]) -> list[FrameBuffers]:
        """``frames`` (this plan's :meth:`buffers`, or :meth:`view_buffers` of the views staged) with their buffers
        of the plan copied out: in one copy of its storage where they fill it, else one a buffer of the rows staged
        (the tensors a pass after the kernels made, and the second layer's, are their own already)."""
        mine, whole = self._storage.untyped_storage().data_ptr(), self._staged == self.views
        rows = self.key[1] * self._staged
        copies = {"": self._storage.clone()} if whole else {name: t[:rows].clone() for name, t in self.tensors.items()}
        typed: dict[torch.dtype, torch.Tensor] = {}  # the whole copy as each dtype, made once

        def own(name: str, t: torch.Tensor) -> torch.Tensor:
            if t.untyped_storage().data_ptr() != mine:
                return t
            if whole:
                if t.dtype not in typed:
                    typed[t.dtype] = copies[""].view(t.dtype)
                return typed[t.dtype].as_strided(t.shape, t.stride(), t.storage_offset())
            start = (t.storage_offset() - self.tensors[name].storage_offset()) // t.stride(0)
            return copies[name][start:start + t.shape[0]]
        return [FrameBuffers(**{name: own(name, getattr(frame, name)) for name in frame.present()},
                             behind=None if frame.behind is None else frame.behind.clone()) for frame in frames]

    @staticmethod
    def _iso_set(table: wp.array, layer: int, after: wp.array) -> kernels.IsoSet:
        """The kernels' :class:`~isosr_render.kernels.IsoSet` of ``layer`` (``after``: the first layer's hits)."""
        isos = kernels.IsoSet()
        isos.values, isos.layer, isos.after = table, layer, after
        return isos

    def check(self, request: RenderRequest) -> None:
        """ValueError unless ``request`` has the plan's size, outputs, flow fill and rays per pixel."""
        if request.plan_key() != self.key:
            w, h, outputs, fill, spp, clipped, capped, colors, several = self.key
            raise ValueError(f"this render plan renders {w}x{h} {outputs} (flow fill {fill!r}, spp {spp}, clipped "
                             f"{clipped}, capped {capped}, coloring {colors}, surfaces {several}), not "
                             f"{request.width}x{request.height} {request.outputs} (flow fill {request.flow_fill!r}, "
                             f"spp {request.spp}, clipped {request.clip.active}, capped {request.clip.capped}, coloring "
                             f"{request.coloring is not None}, surfaces {request.surfaces is not None}): make a plan "
                             f"for that request (Renderer.plan)")

    def stage(self, camera: Camera, request: RenderRequest) -> None:
        """Copy the frame's values to the device (ordered before later work on the torch stream) and
        select the grid of its iso (sparse volumes page its bricks in here)."""
        self.stage_views([(camera, request)])

    def stage_views(self, frames: Sequence[tuple[Camera, RenderRequest]]) -> None:
        """:meth:`stage` of up to the plan's ``views`` views, ``(camera, request)`` each, that the next
        :meth:`launch` renders together: their requests alike in what a launch shares
        (:meth:`RenderRequest.launch_key`), each view's record its own (cameras, seed, step, AO rays...).

        Raises:
            ValueError: more views than the plan holds, none, or requests a launch cannot share (naming why).
        """
        if not 0 < len(frames) <= self.views:
            raise ValueError(f"this render plan renders 1 to {self.views} views at once, not {len(frames)}")
        request = frames[0][1]
        for _, other in frames:
            self.check(other)
            if other.launch_key() != request.launch_key():
                raise ValueError("views rendered together share their iso, empty-space skipping, clip and surfaces: "
                                 f"render views of iso {other.iso:g} (skip {other.skip}) and iso {request.iso:g} "
                                 f"(skip {request.skip}), or of other clips or surfaces, apart")
        surfaces = request.surfaces
        self._grid = self.renderer.grid(request.iso if surfaces is None else tuple(s.iso for s in surfaces.items),
                                        request.skip)
        if self._copied is not None:
            self._copied.synchronize()  # the last frame's copy has read the host record (seldom a wait)
        for i, (camera, view) in enumerate(frames):
            frame_args(camera, view, view.step or self.renderer.default_step(), out=self._host_args[i:i + 1])
        self._staged = len(frames)
        if self._host_clip is not None:
            clip_args(request.clip, out=self._host_clip)
        if self._host_isos is not None:
            self._host_isos[:] = surfaces.table(float(kernels.BIG))
        self._args_bytes.copy_(self._host_bytes, non_blocking=self._copied is not None)
        if self._copied is not None:
            self._copied.record(torch.cuda.current_stream(self.renderer.torch_device))

    def launch(self, rows: tuple[int, int] | None = None) -> None:
        """Render the staged frame into the plan's buffers: on CUDA its two kernels on the current torch
        stream (capturable in a CUDA graph); on CPUs row bands over the renderer's threads.

        Args:
            rows: only the rows ``[start, stop)`` of the buffers (the image's, for one view staged; the views
                lie one under the other); the other rows keep what they held. None: every staged view's.
        """
        if self._grid is None:
            raise ValueError("render plan: stage a frame before launching it")
        h = self.key[1] * self._staged
        row0, row1 = (0, h) if rows is None else rows
        if not 0 <= row0 < row1 <= h:
            raise ValueError(f"rows must satisfy 0 <= start < stop <= height {h}, got {rows}")
        renderer = self.renderer
        if renderer.device.is_cuda:
            stream = wp.stream_from_torch(torch.cuda.current_stream(renderer.device.ordinal))
            for launch in self._recorded(((row0, row1 - row0),))[0]:
                launch.launch(stream)
            return
        bands = np.array_split(np.arange(row0, row1), min(row1 - row0, 4 * renderer.threads))
        launches = self._recorded(tuple((int(b[0]), len(b)) for b in bands if len(b)))

        def band(pair: tuple[wp.Launch, ...]) -> None:
            for launch in pair:
                launch.launch()

        if renderer._pool is None:
            for pair in launches:
                band(pair)
        else:
            list(renderer._pool.map(band, launches))

    def _recorded(self, bands: tuple[tuple[int, int], ...]) -> list[tuple[wp.Launch, ...]]:
        """The kernels' launches (first hit, surface; then the second layer's, with translucent surfaces) over row
        bands ``(row0, rows)``, recorded once per grid, voxel array and bands (the last few bands of a grid: a
        plan of several views launches over as many rows as views are staged)."""
        grid, voxels, renderer = self._grid, self.renderer.voxels, self.renderer
        if self._launches is None or self._launches[0] != (id(grid), voxels.ptr):
            self._launches = (id(grid), voxels.ptr), {}
        recorded = self._launches[1]
        if bands not in recorded:
            if len(recorded) > self.views + 2:
                del recorded[next(iter(recorded))]  # the oldest
            tiles_x, tile = -(-self.key[0] // kernels.TILE_W), kernels.TILE_W * kernels.TILE_H
            frame_kernels = kernels.frame_kernels(self.clipped, self.several)
            first_hit = frame_kernels["first_hit_kernel"]
            surface = frame_kernels["surface_kernel" if self.key[4] == 1 else "surface_samples_kernel"]
            layers = [(self._isos, self._hits, self._counts, self.arrays)]
            if self.layers == 2:
                layers.append((self._behind_isos, self._behind_hits, self._behind_counts, self.behind_arrays))

            def pair(row0: int, rows: int, isos, hits: wp.array, counts: wp.array, arrays: dict) -> tuple[wp.Launch, ...]:
                pixels = tiles_x * -(-rows // kernels.TILE_H) * tile  # threads: whole 8x4 tiles
                common = [voxels, renderer.layout, grid, self._args, self._clip, isos, row0, rows, hits, counts]
                return (wp.launch(first_hit, dim=hits.shape[0] * pixels, device=renderer.device, inputs=common,
                                  record_cmd=True),
                        wp.launch(surface, dim=pixels, device=renderer.device, record_cmd=True,
                                  inputs=[*common, *arrays.values()]))

            recorded[bands] = [sum((pair(row0, rows, *layer) for layer in layers), ()) for row0, rows in bands]
        return recorded[bands]

    def buffers(self, request: RenderRequest) -> FrameBuffers:
        """The rendered frame as ``request`` asks for it: the plan's buffers (views), plus the passes
        after the kernel that it names (flow fill, color), which make new tensors. A plan of one view's
        (several views': :meth:`view_buffers`)."""
        self.check(request)
        if self.views > 1:
            raise ValueError(f"this render plan holds {self.views} views: read them with view_buffers")
        frame, alpha = self._frame(request, self.tensors)
        if self.layers == 2:  # translucent surfaces: the second layer behind, the colours composited
            frame.behind = self._frame(request, self.behind_tensors, behind=True)[0]
            if "color" in request.outputs:
                frame.color = composite(frame.color, frame.behind.color, alpha)
        return frame

    def view_buffers(self, requests: Sequence[RenderRequest]) -> list[FrameBuffers]:
        """:meth:`buffers` of each view staged together (:meth:`stage_views`), in their order: views of the
        plan's buffers, and the passes after the kernel that each request names."""
        views = {name: t.split(self.key[1]) for name, t in self.tensors.items()}  # one call a buffer, not a view
        return [self._frame(request, {name: parts[i] for name, parts in views.items()})[0]
                for i, request in enumerate(requests)]

    @staticmethod
    def _frame(request: RenderRequest, tensors: dict, behind: bool = False) -> tuple[FrameBuffers, torch.Tensor | None]:
        """One layer's frame as ``request`` asks for it (:meth:`buffers`), and with several surfaces the opacity of
        each pixel's (1 where none). The layer ``behind`` is the last: its colour covers the background by its
        surfaces' opacity too."""
        frame, alpha = FrameBuffers(**{name: tensors[name] for name in request.outputs if name in tensors}), None
        if "flow" in request.outputs and request.flow_fill != "none":
            frame.flow = fill_flow(tensors["flow"], tensors["mask"], request.flow_fill)
        if request.coloring is not None:
            frame.albedo = request.coloring.albedo(tensors["position"], tensors["mask"])
        if request.surfaces is not None:
            frame.surface, frame.albedo, alpha = surface_albedo(request.surfaces, tensors["surface"])
            frame.surface = frame.surface if "surface" in request.outputs else None
        if "color" in request.outputs:
            frame.color = shade(tensors["mask"] * alpha if behind else tensors["mask"], tensors["normal"],
                                tensors.get("ao"), request.shading, tensors.get("cap"), frame.albedo)
        return frame, alpha

    def render(self, camera: Camera, request: RenderRequest, rows: tuple[int, int] | None = None) -> FrameBuffers:
        """One frame: :meth:`stage`, :meth:`launch`, :meth:`buffers`."""
        self.stage(camera, request)
        self.launch(rows)
        return self.buffers(request)
