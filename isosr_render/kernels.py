"""Warp kernels: the min-max brick grid, its per-iso distance grid, and first-hit + AO ray casting.

One code path for ``cuda`` and ``cpu``, and for every way the voxels lie on the device: dense
float32 (normalized), uint16 or uint8 (normalized per sample, ``(v - d0) * a``), or sparse: a
pool of resident bricks, each stored with its one-voxel overlap as ``(B + 1)^3`` voxels, found
through a per-brick slot table (a brick without a slot can hold no surface for the current
iso: its samples read the brick's minimum, on the same side of the iso as all its voxels).
Dense voxels may come with a copy as a hardware-filtered 3D texture (:class:`Filtered`, on CUDA):
the march takes its lattice samples there (one fetch for eight loads and seven lerps) and every
sample it decides by, within the filter's error bound of the iso, exactly, so its hits stay
those of the exact march.

Rays march in voxel coordinates (voxel ``(i, j, k)`` at integer coordinates, the data spanning
``[0, n - 1]`` per axis) while the ray parameter ``t`` stays in world units, so step sizes and
AO radii mean the same on anisotropic grids. A brick is active when its value range (min-max grid) holds the
iso-value; the trilinear interpolant inside a brick is bounded by the brick's voxels (they
include the one-voxel overlap), so skipping inactive bricks never loses a hit. Rays leap
over inactive bricks by the Chebyshev distance to the nearest active one and march only
active bricks. Buffer conventions: :mod:`isosr_render.conventions`.

A frame is two kernels that read its values (:class:`FrameArgs`) from device memory, so that a
CUDA graph replays them for each frame staged after: the first hit of each ray
(:func:`first_hit_kernel`, one thread a ray, the march alone: 80 registers per thread on sm_90),
then per pixel the buffers made from its hits (:func:`surface_kernel`: normals, AO rays, flow).
The ray caster is latency-bound, so the warps an SM keeps in flight set its speed: the one kernel
that did both (166-168 registers, 12 warps an SM) took 1.3-1.5 times as long on an H100
(``docs/measurements.md``). The voxels are the kernels' own argument, typed per storage (one
compiled overload each), and the hot functions take the few values they read, never a whole
struct: each struct passed to a sampling function cost 70-80 registers.

Clipping (:mod:`isosr_render.clip`) is a compile-time variant too: the frame kernels take a clip
argument, :class:`NoClip` (this module's kernels: the plain path, compiled as without clipping) or
:class:`ClipArgs` (the same kernels in :data:`CLIPPED_MODULE`, built only when a frame clips), the
functions that cut overloaded on it (:func:`clipped_cast`, :func:`cut_face`, :func:`face_normal`).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from isosr_render.clip import MAX_PLANES
from isosr_render.surfaces import MAX_SURFACES

# The renderer needs no gradients (halves compile time); this module's option, not Warp's global one.
wp.set_module_options({"enable_backward": False})

# Bits of ``RayParams.outputs``: which buffers a launch writes (the rest are not computed).
OUT_MASK = wp.constant(1)
OUT_NORMAL = wp.constant(2)
OUT_DEPTH = wp.constant(4)
OUT_POSITION = wp.constant(8)
OUT_FLOW = wp.constant(16)
OUT_AO = wp.constant(32)
OUT_SAMPLES = wp.constant(64)
OUT_CAP = wp.constant(128)
OUT_SURFACE = wp.constant(256)

REFINE_BISECTION = wp.constant(0)
REFINE_SECANT = wp.constant(1)

# R2 low-discrepancy sequence (subpixel offsets for supersampling).
R2_A1 = wp.constant(0.7548776662466927)
R2_A2 = wp.constant(0.5698402909980532)
BIG = wp.constant(1.0e30)
# Pixel tile that one warp of threads renders.
TILE_W = wp.constant(8)
TILE_H = wp.constant(4)


@wp.struct
class Grid:
    """The volume's shape and value scale, its brick distance grid for one iso-value, and the voxel <->
    world transform (the voxels, in their device type, and how they lie, :class:`Dense`,
    :class:`Sparse` or :class:`Filtered`, are the kernels' arguments beside it)."""

    unit: wp.vec2  # (d0, a): normalized = (voxel - d0) * a
    size: wp.vec3i  # voxels per axis
    dist: wp.array3d(dtype=wp.uint8)  # per brick, for the current iso: Chebyshev distance to an active brick
    brick: int
    scale: wp.vec3  # world = voxel * scale + offset
    offset: wp.vec3


@wp.struct
class Dense:
    """Voxels of shape ``Grid.size``."""

    brick: int  # unused (a struct needs a field)


@wp.struct
class Sparse:
    """A pool of resident bricks, ``(slots * (brick + 1), brick + 1, brick + 1)`` voxels, each brick stored with
    its one-voxel overlap."""

    brick: int
    slots: wp.array3d(dtype=wp.int32)  # per brick, its pool slot, -1 if not resident
    minmax: wp.array3d(dtype=wp.vec2)  # per brick: normalized (min, max) of its voxels and overlap


@wp.struct
class Filtered:
    """Dense voxels of shape ``Grid.size``, and the same voxels as a 3D texture with linear
    filtering, unnormalized coordinates and clamped addressing (texel ``(i, j, k)`` at ``(k + 0.5,
    j + 0.5, i + 0.5)``), for the march's lattice samples: normalized ``texel * gain - bias``
    (8- and 16-bit texels read in [0, 1]). The filter weighs with 8-bit fractions, so a sample may
    be off by up to ``near`` (3/256 of a cell's value range, with a margin); one within ``near``
    of the iso is taken from the voxels."""

    tex: wp.Texture3D
    gain: float
    bias: float
    near: float


@wp.struct
class View:
    """A camera: position, world-space axes (right, up, backward) and projection."""

    eye: wp.vec3
    right: wp.vec3
    up: wp.vec3
    back: wp.vec3
    tan_half_fov: float
    width: int
    height: int


@wp.struct
class RayParams:
    """What to march for and which buffers to write."""

    iso: float
    step: float  # world units along the ray
    refine_mode: int
    refine_steps: int
    spp: int
    ao_samples: int
    ao_radius: float  # world units
    seed: int
    outputs: int  # OUT_* bits


@wp.struct
class FrameArgs:
    """One frame's values, read by the kernels from device memory: a launch recorded (or captured
    in a CUDA graph) once renders each new frame after a copy of this struct."""

    view: View
    prev: View  # the previous frame's camera (flow); ``view`` when there is none
    params: RayParams


@wp.struct
class NoClip:
    """The kernels' clip argument when nothing is cut: its overloads leave every ray's interval as it is, so
    the plain kernels compile as without clipping (the clipped ones take :class:`ClipArgs`)."""

    unused: int  # a struct needs a field


@wp.struct
class ClipRegion:
    """The kept region's values besides its planes (:class:`ClipArgs`), world units."""

    count: int  # planes
    boxed: int  # whether the box [lo, hi] cuts
    lo: wp.vec3
    hi: wp.vec3
    cap: int  # which side of the iso is solid for caps: 1 above, -1 below, 0 no caps


@wp.struct
class ClipArgs:
    """The kept region (:class:`isosr_render.clip.Clip`), read by the clipped kernels from device memory, as
    :class:`FrameArgs` (a recorded launch clips each frame as staged): ``region[0]`` (:class:`ClipRegion`), and
    its first ``count`` planes as rows ``(normal, offset)`` of ``planes`` (:data:`MAX_PLANES` rows), each
    keeping ``dot(normal, x) + offset >= 0``. A table in device memory, not in a struct: indexed by a
    variable, a table held in the frame's struct went to the stack (96 bytes in the first-hit kernel)."""

    region: wp.array(dtype=ClipRegion)
    planes: wp.array(dtype=wp.vec4)


@wp.struct
class OneIso:
    """The kernels' iso argument for one isosurface (``RayParams.iso``): its overloads compile the plain
    kernels as with a float iso (those for several take :class:`IsoSet`)."""

    unused: int  # a struct needs a field


@wp.struct
class IsoSet:
    """Several isosurfaces (:mod:`isosr_render.surfaces`), read from device memory as :class:`ClipArgs`:
    ``values`` their :data:`MAX_SURFACES` iso-values ascending (the unused ones :data:`BIG`), then their
    opacities in that order. A sample's band is the count of isos at or below it; a ray crosses a surface
    between two samples of different bands. ``layer`` 0 marches to each ray's first crossing; 1 to the next one
    after it (``after``: the first layer's hits, a plan's first planes) where that surface is translucent."""

    values: wp.array(dtype=wp.float32)
    layer: int
    after: wp.array3d(dtype=wp.float32)


# band, crossed_iso, near_iso and store_surface have an overload per iso type, as clipped_cast per clip type.
@wp.func
def band(isos: OneIso, iso: float, f: float) -> int:
    """Which side of ``iso`` the sample ``f`` lies on: 1 at or above, else 0."""
    return wp.where(f >= iso, 1, 0)


@wp.func
def band(isos: IsoSet, iso: float, f: float) -> int:
    """How many of the isos lie at or below the sample ``f``."""
    b = int(0)
    for k in range(MAX_SURFACES):
        if f >= isos.values[k]:
            b += 1
    return b


@wp.func
def crossed_iso(isos: OneIso, iso: float, f0: float, f1: float) -> float:
    """The iso crossed between samples ``f0`` and ``f1``: ``iso``."""
    return iso


@wp.func
def crossed_iso(isos: IsoSet, iso: float, f0: float, f1: float) -> float:
    """The iso first crossed going from ``f0`` to ``f1`` (of different bands): the next one from ``f0``'s side."""
    b = band(isos, iso, f0)
    if band(isos, iso, f1) > b:
        return isos.values[b]
    return isos.values[b - 1]


@wp.func
def near_iso(isos: OneIso, iso: float, v: float, near: float) -> bool:
    """Whether ``v`` lies within ``near`` of ``iso``."""
    return wp.abs(v - iso) < near


@wp.func
def near_iso(isos: IsoSet, iso: float, v: float, near: float) -> bool:
    """Whether ``v`` lies within ``near`` of any of the isos."""
    close = False
    for k in range(MAX_SURFACES):
        if wp.abs(v - isos.values[k]) < near:
            close = True
    return close


@wp.kernel
def minmax_kernel(voxels: wp.array3d(dtype=Any), grid: Grid, minmax: wp.array3d(dtype=wp.vec2)):
    """Per brick of dense voxels: min and max of its normalized voxels, including the shared face voxels."""
    bi, bj, bk = wp.tid()
    brick = grid.brick
    x1 = wp.min((bi + 1) * brick, grid.size[0] - 1)
    y1 = wp.min((bj + 1) * brick, grid.size[1] - 1)
    z1 = wp.min((bk + 1) * brick, grid.size[2] - 1)
    lo = float(BIG)
    hi = -float(BIG)
    for x in range(bi * brick, x1 + 1):
        for y in range(bj * brick, y1 + 1):
            for z in range(bk * brick, z1 + 1):
                v = (float(voxels[x, y, z]) - grid.unit[0]) * grid.unit[1]
                lo = wp.min(lo, v)
                hi = wp.max(hi, v)
    minmax[bi, bj, bk] = wp.vec2(lo, hi)


@wp.kernel
def occupancy_kernel(minmax: wp.array3d(dtype=wp.vec2), isos: wp.vec4, skip: int, empty: int,
                     dist: wp.array3d(dtype=wp.uint8)):
    """Distance 0 for bricks whose range holds one of ``isos`` (padded with :data:`BIG`; all bricks without
    ``skip``), else ``empty``."""
    i, j, k = wp.tid()
    mm = minmax[i, j, k]
    active = skip == 0
    for s in range(4):
        active = active or (mm[0] <= isos[s] and isos[s] <= mm[1])
    dist[i, j, k] = wp.uint8(wp.where(active, 0, empty))


@wp.func
def dist_at(dist: wp.array3d(dtype=wp.uint8), i: int, j: int, k: int, axis: int, offset: int, far: int) -> int:
    """``dist`` at the cell ``offset`` steps along ``axis``; ``far`` outside the grid."""
    c = wp.vec3i(i, j, k)
    c[axis] = c[axis] + offset
    if c[axis] < 0 or c[axis] >= dist.shape[axis]:
        return far
    return int(dist[c[0], c[1], c[2]])


@wp.kernel
def chebyshev_pass_kernel(src: wp.array3d(dtype=wp.uint8), axis: int, far: int, dst: wp.array3d(dtype=wp.uint8)):
    """One separable pass of the Chebyshev (L-inf) distance transform, capped at ``far``."""
    i, j, k = wp.tid()
    best = int(src[i, j, k])
    for s in range(1, far):
        if s >= best:
            break
        best = wp.min(best, wp.max(s, dist_at(src, i, j, k, axis, -s, far)))
        best = wp.min(best, wp.max(s, dist_at(src, i, j, k, axis, s, far)))
    dst[i, j, k] = wp.uint8(best)


@wp.func
def trilinear(a: wp.array3d(dtype=Any), i: int, j: int, k: int, d0: float, f: wp.vec3) -> float:
    """Trilinear interpolation of ``a[i:i+2, j:j+2, k:k+2] - d0`` at fractions ``f`` (d0 subtracted exactly first)."""
    c00 = wp.lerp(float(a[i, j, k]) - d0, float(a[i + 1, j, k]) - d0, f[0])
    c10 = wp.lerp(float(a[i, j + 1, k]) - d0, float(a[i + 1, j + 1, k]) - d0, f[0])
    c01 = wp.lerp(float(a[i, j, k + 1]) - d0, float(a[i + 1, j, k + 1]) - d0, f[0])
    c11 = wp.lerp(float(a[i, j + 1, k + 1]) - d0, float(a[i + 1, j + 1, k + 1]) - d0, f[0])
    return wp.lerp(wp.lerp(c00, c10, f[1]), wp.lerp(c01, c11, f[1]), f[2])


@wp.func
def normalized(a: wp.array3d(dtype=Any), grid: Grid, i: int, j: int, k: int, f: wp.vec3) -> float:
    """The normalized trilinear sample at fractions ``f`` of ``a``'s cell ``(i, j, k)``."""
    return trilinear(a, i, j, k, grid.unit[0], f) * grid.unit[1]


@wp.func
def lookup(voxels: wp.array3d(dtype=Any), layout: Dense, grid: Grid, i: int, j: int, k: int, f: wp.vec3) -> float:
    """The normalized trilinear sample at fractions ``f`` of the cell ``(i, j, k)`` of dense voxels."""
    return normalized(voxels, grid, i, j, k, f)


@wp.func
def lookup(voxels: wp.array3d(dtype=Any), layout: Sparse, grid: Grid, i: int, j: int, k: int, f: wp.vec3) -> float:
    """The normalized trilinear sample at fractions ``f`` of the cell ``(i, j, k)``, from the brick pool; a
    brick without a slot holds no surface for the current iso: its minimum (on the iso's side of all its voxels)."""
    b = layout.brick
    bi = i // b
    bj = j // b
    bk = k // b
    slot = layout.slots[bi, bj, bk]
    if slot < 0:
        return layout.minmax[bi, bj, bk][0]
    return normalized(voxels, grid, slot * (b + 1) + i - bi * b, j - bj * b, k - bk * b, f)


@wp.func
def lookup(voxels: wp.array3d(dtype=Any), layout: Filtered, grid: Grid, i: int, j: int, k: int, f: wp.vec3) -> float:
    """The normalized trilinear sample at fractions ``f`` of the cell ``(i, j, k)`` of dense voxels (exact)."""
    return normalized(voxels, grid, i, j, k, f)


@wp.func
def clamped(grid: Grid, p: wp.vec3) -> wp.vec3:
    """Voxel coordinates ``p`` clamped to the grid's ``[0, n - 1]`` per axis."""
    return wp.vec3(wp.clamp(p[0], 0.0, float(grid.size[0] - 1)), wp.clamp(p[1], 0.0, float(grid.size[1] - 1)),
                   wp.clamp(p[2], 0.0, float(grid.size[2] - 1)))


@wp.func
def sample_volume(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3) -> float:
    """Normalized trilinear sample at voxel coordinates ``p``, clamped to the grid."""
    q = clamped(grid, p)
    i = wp.min(int(q[0]), grid.size[0] - 2)
    j = wp.min(int(q[1]), grid.size[1] - 2)
    k = wp.min(int(q[2]), grid.size[2] - 2)
    return lookup(voxels, layout, grid, i, j, k, wp.vec3(q[0] - float(i), q[1] - float(j), q[2] - float(k)))


# march_sample and exact_sample have an overload per layout, not one for Any: through march's Any
# parameter Warp picked an Any overload over the Filtered one (measured: the exact march ran).
@wp.func
def march_sample(voxels: wp.array3d(dtype=Any), layout: Dense, grid: Grid, p: wp.vec3, isos: Any,
                 iso: float) -> float:
    """A march's sample at voxel coordinates ``p``: the exact trilinear one (:func:`sample_volume`)."""
    return sample_volume(voxels, layout, grid, p)


@wp.func
def march_sample(voxels: wp.array3d(dtype=Any), layout: Sparse, grid: Grid, p: wp.vec3, isos: Any,
                 iso: float) -> float:
    """A march's sample at voxel coordinates ``p``: the exact trilinear one (:func:`sample_volume`)."""
    return sample_volume(voxels, layout, grid, p)


@wp.func
def march_sample(voxels: wp.array3d(dtype=Any), layout: Filtered, grid: Grid, p: wp.vec3, isos: Any,
                 iso: float) -> float:
    """A march's sample at voxel coordinates ``p`` from the texture, exact within ``near`` of the isos
    (:func:`near_iso`): either way in the band that the exact sample is."""
    q = clamped(grid, p)
    v = wp.texture_sample(layout.tex, wp.vec3f(q[2] + 0.5, q[1] + 0.5, q[0] + 0.5), dtype=float) * layout.gain \
        - layout.bias
    if near_iso(isos, iso, v, layout.near):
        return sample_volume(voxels, layout, grid, p)
    return v


@wp.func
def exact_sample(voxels: wp.array3d(dtype=Any), layout: Dense, grid: Grid, p: wp.vec3, f: float) -> float:
    """The exact sample at ``p`` given the march's sample ``f`` there: ``f`` itself."""
    return f


@wp.func
def exact_sample(voxels: wp.array3d(dtype=Any), layout: Sparse, grid: Grid, p: wp.vec3, f: float) -> float:
    """The exact sample at ``p`` given the march's sample ``f`` there: ``f`` itself."""
    return f


@wp.func
def exact_sample(voxels: wp.array3d(dtype=Any), layout: Filtered, grid: Grid, p: wp.vec3, f: float) -> float:
    """The exact sample at ``p`` (the march's ``f`` may be the texture's)."""
    return sample_volume(voxels, layout, grid, p)


@wp.func
def gradient_world(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3) -> wp.vec3:
    """Central-difference gradient (one voxel apart) at voxel coordinates ``p``, world units."""
    ex = wp.vec3(1.0, 0.0, 0.0)
    ey = wp.vec3(0.0, 1.0, 0.0)
    ez = wp.vec3(0.0, 0.0, 1.0)
    dx = sample_volume(voxels, layout, grid, p + ex) - sample_volume(voxels, layout, grid, p - ex)
    dy = sample_volume(voxels, layout, grid, p + ey) - sample_volume(voxels, layout, grid, p - ey)
    dz = sample_volume(voxels, layout, grid, p + ez) - sample_volume(voxels, layout, grid, p - ez)
    return wp.cw_div(wp.vec3(dx, dy, dz), 2.0 * grid.scale)


@wp.func
def clip_to_grid(size: wp.vec3i, o: wp.vec3, d: wp.vec3) -> wp.vec2:
    """Ray-parameter interval ``(t0, t1)`` inside the voxel box; ``t0 > t1`` if missed."""
    t0 = -float(BIG)
    t1 = float(BIG)
    for a in range(3):
        hi = float(size[a] - 1)
        if d[a] == 0.0:
            if o[a] < 0.0 or o[a] > hi:
                t0 = float(BIG)
        else:
            ta = (0.0 - o[a]) / d[a]
            tb = (hi - o[a]) / d[a]
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec2(t0, t1)


@wp.func
def refine_crossing(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, o: wp.vec3, d: wp.vec3, iso: float,
                    t0: float, f0: float, t1: float, f1: float, mode: int, steps: int) -> float:
    """Narrow the bracket ``[t0, t1]`` around the iso crossing, then interpolate linearly."""
    ta = float(t0)
    fa = float(f0)
    tb = float(t1)
    fb = float(f1)
    for _ in range(steps):
        w = float(0.5)
        if mode == REFINE_SECANT and wp.abs(fb - fa) > 1.0e-12:
            w = (iso - fa) / (fb - fa)
            if w < 0.01 or w > 0.99:  # safeguard: a secant stuck at an end (e.g. a plateau) bisects
                w = 0.5
        tm = ta + w * (tb - ta)
        fm = sample_volume(voxels, layout, grid, o + d * tm)
        if (fm >= iso) == (fa >= iso):
            ta = tm
            fa = fm
        else:
            tb = tm
            fb = fm
    w_end = 0.5
    if wp.abs(fb - fa) > 1.0e-12:
        w_end = wp.clamp((iso - fa) / (fb - fa), 0.0, 1.0)
    return ta + w_end * (tb - ta)


@wp.func
def march(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, o: wp.vec3, d: wp.vec3, t_start: float, t_end: float,
          isos: Any, iso: float, h: float, refine_mode: int, refine_steps: int) -> wp.vec2:
    """First iso crossing (of any of ``isos``: :func:`band`) of the ray ``o + t d`` (voxel coordinates) within
    ``[t_start, t_end]``,
    its bracket narrowed by ``refine_steps``; ``refine_steps < 0``: only whether it crosses counts
    (AO rays), and ``t_hit`` is the bracket's start, unrefined.

    Empty bricks are leapt over a whole cube at a time: a brick at Chebyshev distance D >= 1
    from the nearest active brick sits in a cube of (2D - 1)^3 inactive bricks, and the ray
    jumps to that cube's exit. Active bricks (D = 0) are marched on the global sample lattice
    ``t_start + k h``, plus one sample at the brick's exit, so crossings between bricks
    are bracketed too. Returns ``(t_hit, samples)``, ``t_hit < 0`` when there is no crossing.
    """
    b = float(grid.brick)
    nb = wp.vec3i(grid.dist.shape[0], grid.dist.shape[1], grid.dist.shape[2])
    nudge = 1.0e-3 / wp.max(wp.abs(d[0]), wp.max(wp.abs(d[1]), wp.abs(d[2])))  # 1/1000 voxel
    samples = float(0.0)
    t = float(t_start)
    have_prev = int(0)  # whether (t_prev, f_prev) is the sample at t
    t_prev = float(t_start)
    f_prev = float(0.0)
    budget = 4 * (nb[0] + nb[1] + nb[2]) + 16  # a bound on cube steps; real rays need far fewer
    while t < t_end and budget > 0:
        budget -= 1
        p = o + d * (t + nudge)
        cell = wp.vec3i(wp.clamp(int(wp.floor(p[0] / b)), 0, nb[0] - 1),
                        wp.clamp(int(wp.floor(p[1] / b)), 0, nb[1] - 1),
                        wp.clamp(int(wp.floor(p[2] / b)), 0, nb[2] - 1))
        dist = int(grid.dist[cell[0], cell[1], cell[2]])
        reach = float(wp.max(dist - 1, 0))
        t_exit = t_end
        for a in range(3):
            if d[a] > 0.0:
                t_exit = wp.min(t_exit, ((float(cell[a]) + 1.0 + reach) * b - o[a]) / d[a])
            elif d[a] < 0.0:
                t_exit = wp.min(t_exit, ((float(cell[a]) - reach) * b - o[a]) / d[a])
        t_exit = wp.max(t_exit, t + nudge)
        if dist == 0:
            if have_prev == 0:
                t_prev = t
                f_prev = march_sample(voxels, layout, grid, o + d * t, isos, iso)
                samples += 1.0
                have_prev = 1
            k = wp.floor((t - t_start) / h) + 1.0
            t_s = t_start + k * h
            done = int(0)
            while done == 0:
                if t_s >= t_exit:
                    t_s = wp.min(t_exit, t_end)
                    done = 1
                f = march_sample(voxels, layout, grid, o + d * t_s, isos, iso)
                samples += 1.0
                if band(isos, iso, f) != band(isos, iso, f_prev):
                    if refine_steps < 0:
                        return wp.vec2(t_prev, samples)
                    f_prev = exact_sample(voxels, layout, grid, o + d * t_prev, f_prev)
                    f = exact_sample(voxels, layout, grid, o + d * t_s, f)
                    t_hit = refine_crossing(voxels, layout, grid, o, d, crossed_iso(isos, iso, f_prev, f), t_prev,
                                            f_prev, t_s, f, refine_mode, refine_steps)
                    return wp.vec2(t_hit, samples + float(refine_steps))
                t_prev = t_s
                f_prev = f
                k += 1.0
                t_s = t_start + k * h
        else:
            have_prev = 0
        t = t_exit
    return wp.vec2(-1.0, samples)


@wp.func
def voxel_from_world(grid: Grid, p: wp.vec3) -> wp.vec3:
    """World point to voxel coordinates."""
    return wp.cw_div(p - grid.offset, grid.scale)


@wp.func
def cast(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, origin: wp.vec3, direction: wp.vec3, t_near: float,
         t_far: float, isos: Any, iso: float, step: float, refine_mode: int, refine_steps: int) -> wp.vec2:
    """First crossing of a world-space ray (unit ``direction``) in ``[t_near, t_far]``, world units
    (the ray parameters as for :func:`march`)."""
    o = voxel_from_world(grid, origin)
    d = wp.cw_div(direction, grid.scale)
    span = clip_to_grid(grid.size, o, d)
    t0 = wp.max(span[0], t_near)
    t1 = wp.min(span[1], t_far)
    if t0 > t1:
        return wp.vec2(-1.0, 0.0)
    return march(voxels, layout, grid, o, d, t0, t1, isos, iso, step, refine_mode, refine_steps)


@wp.func
def kept_span(clip: ClipArgs, o: wp.vec3, d: wp.vec3, t_near: float, t_far: float) -> wp.vec3:
    """The part ``(t0, t1)`` of ``[t_near, t_far]`` where the world ray ``o + t d`` lies in the kept region
    (``t0 > t1``: none; one interval, the region being convex), and the face through which it enters at
    ``t0``: a plane's row, ``MAX_PLANES + axis`` for the box, -1 where the region does not bound ``t0``."""
    region = clip.region[0]
    t0 = float(t_near)
    t1 = float(t_far)
    face = float(-1.0)
    for i in range(region.count):
        row = clip.planes[i]
        n = wp.vec3(row[0], row[1], row[2])
        s = wp.dot(n, o) + row[3]  # >= 0 at a kept origin
        dn = wp.dot(n, d)
        if dn > 0.0:
            if -s / dn > t0:
                t0 = -s / dn
                face = float(i)
        elif dn < 0.0:
            t1 = wp.min(t1, -s / dn)
        elif s < 0.0:  # parallel to the plane, on its removed side
            t1 = -float(BIG)
    if region.boxed != 0:
        lo = region.lo
        hi = region.hi
        for a in range(3):
            if d[a] == 0.0:
                if o[a] < lo[a] or o[a] > hi[a]:
                    t1 = -float(BIG)
            else:
                ta = (lo[a] - o[a]) / d[a]
                tb = (hi[a] - o[a]) / d[a]
                if wp.min(ta, tb) > t0:
                    t0 = wp.min(ta, tb)
                    face = float(MAX_PLANES + a)
                t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec3(t0, t1, face)


@wp.func
def solid_at(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3, iso: float, cap: int) -> bool:
    """Whether the world point ``p`` lies in the grid and on the iso's solid side (``ClipRegion.cap``)."""
    q = voxel_from_world(grid, p)
    for a in range(3):
        if q[a] < 0.0 or q[a] > float(grid.size[a] - 1):
            return False
    return (sample_volume(voxels, layout, grid, q) >= iso) == (cap > 0)


# clipped_cast, cut_face and face_normal have an overload per clip type, as march_sample per layout: NoClip's
# are the plain path's (the plain kernels compile as without clipping), ClipArgs' cut.
@wp.func
def clipped_cast(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, clip: NoClip, origin: wp.vec3,
                 direction: wp.vec3, t_near: float, t_far: float, isos: Any, iso: float, step: float,
                 refine_mode: int, refine_steps: int) -> wp.vec2:
    """:func:`cast`: nothing is cut."""
    return cast(voxels, layout, grid, origin, direction, t_near, t_far, isos, iso, step, refine_mode, refine_steps)


@wp.func
def clipped_cast(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, clip: ClipArgs, origin: wp.vec3,
                 direction: wp.vec3, t_near: float, t_far: float, isos: Any, iso: float, step: float,
                 refine_mode: int, refine_steps: int) -> wp.vec2:
    """:func:`cast` over the kept part of ``[t_near, t_far]``; with caps, a ray that enters the kept region
    through a face at a solid point (and stays in it for a while) hits that face there."""
    span = kept_span(clip, origin, direction, t_near, t_far)
    cap = clip.region[0].cap
    if cap != 0 and span[2] >= 0.0 and span[0] < span[1]:  # a flat region has no faces
        if solid_at(voxels, layout, grid, origin + direction * span[0], iso, cap):
            return wp.vec2(span[0], 1.0)
    return cast(voxels, layout, grid, origin, direction, span[0], span[1], isos, iso, step, refine_mode,
                refine_steps)


@wp.func
def cut_face(clip: NoClip, o: wp.vec3, d: wp.vec3, t: float) -> float:
    """-1: no hit is on a cut face."""
    return -1.0


@wp.func
def cut_face(clip: ClipArgs, o: wp.vec3, d: wp.vec3, t: float) -> float:
    """The cut face (:func:`kept_span`) that the ray ``o + t d``'s hit at ``t`` (:func:`clipped_cast`) lies on,
    -1 where it is the surface's (a hit after the kept region's entry, or no caps)."""
    if clip.region[0].cap != 0:
        span = kept_span(clip, o, d, 0.0, float(BIG))
        if t <= span[0]:
            return span[2]
    return -1.0


@wp.func
def face_normal(clip: NoClip, face: int, d: wp.vec3) -> wp.vec3:
    """No faces (never called)."""
    return -d


@wp.func
def face_normal(clip: ClipArgs, face: int, d: wp.vec3) -> wp.vec3:
    """The unit normal, into the kept region, of the face ``face`` (:func:`kept_span`) that a ray of
    direction ``d`` enters through."""
    if face < MAX_PLANES:
        row = clip.planes[face]
        return wp.vec3(row[0], row[1], row[2])
    n = wp.vec3(0.0)
    n[face - MAX_PLANES] = wp.sign(d[face - MAX_PLANES])
    return n


@wp.func
def nearest_surface(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, isos: IsoSet, p: wp.vec3) -> int:
    """The table index of the iso nearest the volume's value at the world point ``p`` (a hit's: its surface)."""
    v = sample_volume(voxels, layout, grid, voxel_from_world(grid, p))
    nearest = int(0)
    best = float(BIG)
    for k in range(MAX_SURFACES):
        e = wp.abs(v - isos.values[k])
        if e < best:
            best = e
            nearest = k
    return nearest


@wp.func
def opacity_at(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, isos: IsoSet, p: wp.vec3) -> float:
    """The opacity of the surface hit at the world point ``p``."""
    return isos.values[MAX_SURFACES + nearest_surface(voxels, layout, grid, isos, p)]


# occlusion has an overload per iso type, as band.
@wp.func
def occlusion(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, isos: OneIso, p: wp.vec3) -> float:
    """How much an AO ray's hit near the world point ``p`` occludes: fully."""
    return 1.0


@wp.func
def occlusion(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, isos: IsoSet, p: wp.vec3) -> float:
    """How much an AO ray's hit near the world point ``p`` (past its crossing) occludes: its surface's opacity."""
    return opacity_at(voxels, layout, grid, isos, p)


@wp.func
def ambient_occlusion(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, clip: Any, p: wp.vec3, n: wp.vec3,
                      isos: Any, iso: float, step: float, rays: int, radius: float, state: wp.uint32) -> wp.vec2:
    """Fraction of ``rays`` cosine-weighted hemisphere rays around ``n`` that escape within ``radius``,
    counting only occluders in the kept region (``clip``), a translucent surface by its opacity (:func:`occlusion`).

    Returns ``(ao, samples)``.
    """
    # Orthonormal frame around n (Duff et al. 2017, branchless).
    sign = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    bb = n[0] * n[1] * a
    tx = wp.vec3(1.0 + sign * n[0] * n[0] * a, sign * bb, -sign * n[0])
    ty = wp.vec3(bb, sign + n[1] * n[1] * a, -n[1])
    origin = p + n * (0.5 * wp.min(grid.scale[0], wp.min(grid.scale[1], grid.scale[2])))
    hits = float(0.0)
    samples = float(0.0)
    for _ in range(rays):
        u1 = wp.randf(state)
        u2 = wp.randf(state)
        r = wp.sqrt(u1)
        phi = 2.0 * wp.pi * u2
        dir = tx * (r * wp.cos(phi)) + ty * (r * wp.sin(phi)) + n * wp.sqrt(wp.max(1.0 - u1, 0.0))
        # Whether the ray is blocked is settled when its crossing is bracketed: no refinement.
        res = clipped_cast(voxels, layout, grid, clip, origin, wp.normalize(dir), 0.0, radius, isos, iso, step,
                           REFINE_BISECTION, -1)
        samples += res[1]
        if res[0] >= 0.0:  # the bracket's start: half a step on, near the surface crossed
            hits += occlusion(voxels, layout, grid, isos, origin + wp.normalize(dir) * (res[0] + 0.5 * step))
    return wp.vec2(1.0 - hits / float(rays), samples)


@wp.func
def project_to_pixel(view: View, p: wp.vec3) -> wp.vec3:
    """World point to ``(x, y, depth)`` in ``view``'s pixels; depth <= 0 behind the camera."""
    q = p - view.eye
    depth = -wp.dot(q, view.back)
    safe = wp.where(wp.abs(depth) > 1.0e-12, depth, 1.0e-12)
    aspect = float(view.width) / float(view.height)
    ndc_x = wp.dot(q, view.right) / (safe * view.tan_half_fov * aspect)
    ndc_y = wp.dot(q, view.up) / (safe * view.tan_half_fov)
    return wp.vec3((ndc_x + 1.0) * 0.5 * float(view.width), (1.0 - ndc_y) * 0.5 * float(view.height), depth)


@wp.func
def band_pixel(width: int, rows: int, tid: int) -> wp.vec2i:
    """Thread ``tid``'s pixel ``(column, row in the band)`` of a band ``rows`` high; ``(-1, -1)`` past its
    edge. Threads walk the band in 8x4-pixel tiles, one tile per 32-thread warp, so that a warp's
    rays stay close together (coherent brick walks and cache lines)."""
    tile = tid // (TILE_W * TILE_H)
    lane = tid - tile * (TILE_W * TILE_H)
    tiles_x = (width + TILE_W - 1) // TILE_W
    c = (tile % tiles_x) * TILE_W + lane % TILE_W
    r = (tile // tiles_x) * TILE_H + lane // TILE_W
    if c >= width or r >= rows:
        return wp.vec2i(-1, -1)
    return wp.vec2i(c, r)


@wp.func
def view_of(frame: wp.array(dtype=FrameArgs), row: int) -> wp.vec2i:
    """``(view, its image row)`` of a row of the buffers, in which the views of ``frame`` (one size) lie one
    under the other: rows ``[v * height, (v + 1) * height)`` are view ``v``'s."""
    v = row // frame[0].view.height
    return wp.vec2i(v, row - v * frame[0].view.height)


@wp.func
def subpixel(c: int, row: int, s: int, spp: int) -> wp.vec2:
    """Image position of sample ``s`` of ``spp`` in pixel ``(c, row)``: its center, or an R2 offset."""
    if spp == 1:
        return wp.vec2(float(c) + 0.5, float(row) + 0.5)
    return wp.vec2(float(c) + wp.mod(0.5 + float(s) * R2_A1, 1.0), float(row) + wp.mod(0.5 + float(s) * R2_A2, 1.0))


@wp.func
def ray_direction(view: View, p: wp.vec2) -> wp.vec3:
    """World direction (unit) of the camera ray through image position ``p``."""
    aspect = float(view.width) / float(view.height)
    ndc_x = 2.0 * p[0] / float(view.width) - 1.0
    ndc_y = 1.0 - 2.0 * p[1] / float(view.height)
    return wp.normalize(view.right * (ndc_x * view.tan_half_fov * aspect) + view.up * (ndc_y * view.tan_half_fov)
                        - view.back)


# march_ray has an overload per iso type: one iso's plain march, and several isos' layers.
@wp.func
def march_ray(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs), clip: Any,
              isos: OneIso, v: int, c: int, y: int, row: int, s: int) -> wp.vec2:
    """Ray ``s`` of pixel ``(c, y)`` of view ``v`` (``row``: its row in the buffers, :func:`view_of`) to its first
    iso crossing: ``(t, volume samples)``, ``t < 0`` where none."""
    view = frame[v].view
    params = frame[v].params
    return clipped_cast(voxels, layout, grid, clip, view.eye, ray_direction(view, subpixel(c, y, s, params.spp)),
                        0.0, float(BIG), isos, params.iso, params.step, params.refine_mode, params.refine_steps)


@wp.func
def march_ray(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs), clip: Any,
              isos: IsoSet, v: int, c: int, y: int, row: int, s: int) -> wp.vec2:
    """Ray ``s`` of pixel ``(c, y)`` of view ``v`` (its buffers' ``row``) to its crossing of ``isos.layer``
    (:class:`IsoSet`): ``(t, volume samples)``,
    ``t < 0`` where none (in layer 1 also where the first crossing's surface is opaque). Layer 1 starts a
    quarter step past the first crossing (a crossing nearer than that is not seen)."""
    view = frame[v].view
    params = frame[v].params
    dir = ray_direction(view, subpixel(c, y, s, params.spp))
    first = wp.vec2(0.0)
    if isos.layer == 0 or s >= isos.after.shape[0]:
        first = clipped_cast(voxels, layout, grid, clip, view.eye, dir, 0.0, float(BIG), isos, params.iso, params.step,
                             params.refine_mode, params.refine_steps)
        if isos.layer == 0:
            return first
    else:
        first = wp.vec2(isos.after[s, row, c], 0.0)
    if first[0] < 0.0 or opacity_at(voxels, layout, grid, isos, view.eye + dir * first[0]) >= 1.0:
        return wp.vec2(-1.0, first[1])
    res = clipped_cast(voxels, layout, grid, clip, view.eye, dir, first[0] + 0.25 * params.step, float(BIG), isos,
                       params.iso, params.step, params.refine_mode, params.refine_steps)
    return wp.vec2(res[0], res[1] + first[1])


@wp.kernel
def first_hit_kernel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs),
                     clip: Any, isos: Any, row0: int, rows: int, hits: wp.array3d(dtype=wp.float32),
                     counts: wp.array3d(dtype=wp.int32)):
    """One thread per ray of the first ``hits.shape[0]`` of each pixel of the band ``[row0, row0 + rows)``
    (rays outermost) of the buffers' rows, where the views of ``frame`` lie one under the other (:func:`view_of`):
    the ray parameter of its first iso crossing (world units, -1 where none) into ``hits[ray, row, column]``; with
    ``OUT_SAMPLES``, the volume samples that took into ``counts`` alike.
    The march alone: few registers, so that many warps in flight hide its memory latency."""
    width = frame[0].view.width
    tid = wp.tid()
    tiles = ((width + TILE_W - 1) // TILE_W) * ((rows + TILE_H - 1) // TILE_H) * TILE_W * TILE_H
    s = tid // tiles
    px = band_pixel(width, rows, tid - s * tiles)
    if px[0] < 0:
        return
    row = px[1] + row0
    vy = view_of(frame, row)
    res = march_ray(voxels, layout, grid, frame, clip, isos, vy[0], px[0], vy[1], row, s)
    hits[s, row, px[0]] = res[0]
    if (frame[vy[0]].params.outputs & OUT_SAMPLES) != 0:
        counts[s, row, px[0]] = int(res[1])


# Rays per pixel whose first hits a render plan keeps (spp x H x W floats); surface_samples_kernel
# marches those past them itself, so a plan's memory stays bounded whatever the rays per pixel.
HIT_PLANES = 8
# The surface kernels' register cap (16 warps an SM on sm_90). Uncapped, surface_kernel takes 134 and
# surface_samples_kernel 168: its loop over rays keeps the frame's values live across the AO rays'
# march; capped, it kept some in ~120 bytes of stack and took 0.70-0.89 times as long on an H100
# (4 rays per pixel, 1080p and 4K); marching the rays past HIT_PLANES too, 232-240 bytes (not timed).
SURFACE_MAX_REGISTERS = 128


@wp.func
def hit_surface(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs), clip: Any,
                isos: Any, v: int, c: int, y: int, s: int, t: float):
    """What ray ``s`` of pixel ``(c, y)`` of view ``v``, its first hit at ``t``, gives the buffers that ``outputs`` asks
    for: ``(hit point (world), depth, normal (camera axes), flow (pixels), AO, AO's volume samples, cap)``,
    ``cap`` being ``(1, normalized value)`` where the hit is a cut face (:func:`clipped_cast`), else 0."""
    view = frame[v].view
    params = frame[v].params
    out = params.outputs
    p = subpixel(c, y, s, params.spp)
    dir = ray_direction(view, p)
    p_world = view.eye + dir * t
    face = cut_face(clip, view.eye, dir, t)
    n_view = wp.vec3(0.0)
    occ = wp.vec2(0.0)
    if (out & (OUT_NORMAL | OUT_AO)) != 0:
        n = -dir  # where the gradient vanishes: face the camera
        if face >= 0.0:
            n = -face_normal(clip, int(face), dir)  # the cut face, turned to the camera
        else:
            g = gradient_world(voxels, layout, grid, voxel_from_world(grid, p_world))
            if wp.length(g) > 1.0e-20:
                n = wp.normalize(g)
                if wp.dot(n, dir) > 0.0:
                    n = -n
        n_view = wp.vec3(wp.dot(n, view.right), wp.dot(n, view.up), wp.dot(n, view.back))
        if (out & OUT_AO) != 0:
            state = wp.rand_init(params.seed, (y * view.width + c) * params.spp + s)
            occ = ambient_occlusion(voxels, layout, grid, clip, p_world, n, isos, params.iso, params.step,
                                    params.ao_samples, params.ao_radius, state)
    flow = wp.vec2(0.0)
    if (out & OUT_FLOW) != 0:
        q = project_to_pixel(frame[v].prev, p_world)
        if q[2] > 0.0:
            flow = wp.vec2(q[0] - p[0], q[1] - p[1])
    cap = wp.vec2(0.0)
    if face >= 0.0 and (out & OUT_CAP) != 0:
        cap = wp.vec2(1.0, sample_volume(voxels, layout, grid, voxel_from_world(grid, p_world)))
    return p_world, -wp.dot(p_world - view.eye, view.back), n_view, flow, occ[0], occ[1], cap


@wp.func
def store_surface(isos: OneIso, voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3, hit: bool,
                  surface: wp.array2d(dtype=wp.float32), c: int, row: int):
    """Nothing: one surface."""
    return


@wp.func
def store_surface(isos: IsoSet, voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3, hit: bool,
                  surface: wp.array2d(dtype=wp.float32), c: int, row: int):
    """Pixel ``(c, row)``'s surface: where ``hit`` at ``p`` (world), the table index of the iso nearest the
    volume's value there (the crossing's, to the refinement's tolerance), else -1."""
    nearest = float(-1.0)
    if hit:
        nearest = float(nearest_surface(voxels, layout, grid, isos, p))
    surface[row, c] = nearest


@wp.func
def store_pixel(frame: wp.array(dtype=FrameArgs), v: int, c: int, row: int, hit_count: float, p_sum: wp.vec3,
                depth_sum: float, n_sum: wp.vec3, flow_sum: wp.vec2, ao_sum: float, cap_sum: wp.vec2,
                sample_count: float, mask: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                depth: wp.array2d(dtype=wp.float32), position: wp.array2d(dtype=wp.vec3),
                flow: wp.array2d(dtype=wp.vec2), ao: wp.array2d(dtype=wp.float32), cap: wp.array2d(dtype=wp.vec2),
                samples: wp.array2d(dtype=wp.int32)):
    """Write the asked buffers of view ``v`` at ``(c, row)`` from the sums over its pixel's rays that hit
    (``hit_count`` of them; ``cap_sum[0]`` of them on cut faces)."""
    params = frame[v].params
    out = params.outputs
    inv = 1.0 / wp.max(hit_count, 1.0)
    if (out & OUT_MASK) != 0:
        mask[row, c] = hit_count / float(params.spp)
    if (out & OUT_NORMAL) != 0:
        nv = wp.vec3(0.0)
        if wp.length(n_sum) > 1.0e-12:
            nv = wp.normalize(n_sum)
        elif hit_count > 0.0:
            nv = wp.vec3(0.0, 0.0, 1.0)  # subpixel normals cancelled out: face the camera
        normal[row, c] = nv
    if (out & OUT_DEPTH) != 0:
        depth[row, c] = depth_sum * inv
    if (out & OUT_POSITION) != 0:
        position[row, c] = p_sum * inv
    if (out & OUT_FLOW) != 0:
        flow[row, c] = flow_sum * inv
    if (out & OUT_AO) != 0:
        ao[row, c] = ao_sum * inv
    if (out & OUT_CAP) != 0:
        cap[row, c] = wp.vec2(cap_sum[0] / float(params.spp), cap_sum[1] / wp.max(cap_sum[0], 1.0))
    if (out & OUT_SAMPLES) != 0:
        samples[row, c] = int(sample_count)


@wp.kernel(enable_backward=False, cuda_max_registers=SURFACE_MAX_REGISTERS)
def surface_kernel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs),
                   clip: Any, isos: Any, row0: int, rows: int, hits: wp.array3d(dtype=wp.float32),
                   counts: wp.array3d(dtype=wp.int32), mask: wp.array2d(dtype=wp.float32),
                   normal: wp.array2d(dtype=wp.vec3), depth: wp.array2d(dtype=wp.float32),
                   position: wp.array2d(dtype=wp.vec3), flow: wp.array2d(dtype=wp.vec2),
                   ao: wp.array2d(dtype=wp.float32), cap: wp.array2d(dtype=wp.vec2),
                   samples: wp.array2d(dtype=wp.int32), surface: wp.array2d(dtype=wp.float32)):
    """One ray per pixel: per pixel of the band (of the buffers' rows: the views one under the other,
    :func:`view_of`), from its first hit (:func:`first_hit_kernel`), the asked buffers (``FrameArgs.params.outputs``),
    AO rays cast from the hit."""
    px = band_pixel(frame[0].view.width, rows, wp.tid())
    if px[0] < 0:
        return
    c = px[0]
    row = px[1] + row0
    vy = view_of(frame, row)
    v = vy[0]
    t = hits[0, row, c]
    sample_count = float(0.0)
    if (frame[v].params.outputs & OUT_SAMPLES) != 0:
        sample_count = float(counts[0, row, c])
    if t < 0.0:
        store_pixel(frame, v, c, row, 0.0, wp.vec3(0.0), 0.0, wp.vec3(0.0), wp.vec2(0.0), 0.0, wp.vec2(0.0),
                    sample_count, mask, normal, depth, position, flow, ao, cap, samples)
        store_surface(isos, voxels, layout, grid, wp.vec3(0.0), False, surface, c, row)
        return
    p_world, d, n_view, fl, occ, occ_samples, on_cap = hit_surface(voxels, layout, grid, frame, clip, isos, v, c,
                                                                   vy[1], 0, t)
    store_pixel(frame, v, c, row, 1.0, p_world, d, n_view, fl, occ, on_cap, sample_count + occ_samples, mask, normal,
                depth, position, flow, ao, cap, samples)
    store_surface(isos, voxels, layout, grid, p_world, True, surface, c, row)


@wp.kernel(enable_backward=False, cuda_max_registers=SURFACE_MAX_REGISTERS)
def surface_samples_kernel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs),
                           clip: Any, isos: Any, row0: int, rows: int, hits: wp.array3d(dtype=wp.float32),
                           counts: wp.array3d(dtype=wp.int32), mask: wp.array2d(dtype=wp.float32),
                           normal: wp.array2d(dtype=wp.vec3), depth: wp.array2d(dtype=wp.float32),
                           position: wp.array2d(dtype=wp.vec3), flow: wp.array2d(dtype=wp.vec2),
                           ao: wp.array2d(dtype=wp.float32), cap: wp.array2d(dtype=wp.vec2),
                           samples: wp.array2d(dtype=wp.int32), surface: wp.array2d(dtype=wp.float32)):
    """:func:`surface_kernel` for several rays per pixel: the buffers averaged over the rays that hit. Rays past
    the first ``hits.shape[0]`` (the planes a plan keeps, :data:`HIT_PLANES`) are marched here."""
    px = band_pixel(frame[0].view.width, rows, wp.tid())
    if px[0] < 0:
        return
    c = px[0]
    row = px[1] + row0
    vy = view_of(frame, row)
    v = vy[0]
    count_samples = (frame[v].params.outputs & OUT_SAMPLES) != 0
    hit_count = float(0.0)
    p_sum = wp.vec3(0.0)
    depth_sum = float(0.0)
    n_sum = wp.vec3(0.0)
    flow_sum = wp.vec2(0.0)
    ao_sum = float(0.0)
    cap_sum = wp.vec2(0.0)
    sample_count = float(0.0)
    p_first = wp.vec3(0.0)  # the first hitting ray's hit: the pixel's surface
    for s in range(frame[v].params.spp):
        t = float(-1.0)
        if s < hits.shape[0]:
            t = hits[s, row, c]
            if count_samples:
                sample_count += float(counts[s, row, c])
        else:
            res = march_ray(voxels, layout, grid, frame, clip, isos, v, c, vy[1], row, s)
            t = res[0]
            sample_count += res[1]
        if t >= 0.0:
            p_world, d, n_view, fl, occ, occ_samples, on_cap = hit_surface(voxels, layout, grid, frame, clip, isos, v,
                                                                           c, vy[1], s, t)
            if hit_count == 0.0:
                p_first = p_world
            hit_count += 1.0
            p_sum += p_world
            depth_sum += d
            n_sum += n_view
            flow_sum += fl
            ao_sum += occ
            cap_sum += on_cap
            sample_count += occ_samples
    store_pixel(frame, v, c, row, hit_count, p_sum, depth_sum, n_sum, flow_sum, ao_sum, cap_sum, sample_count, mask,
                normal, depth, position, flow, ao, cap, samples)
    store_surface(isos, voxels, layout, grid, p_first, hit_count > 0.0, surface, c, row)


# The voxels' device types and layouts: one compiled overload of each voxel-reading kernel per pair.
VOXEL_TYPES = (wp.float32, wp.uint16, wp.uint8)
LAYOUTS = (Dense, Sparse, Filtered)
# The kernels that render a frame, by name.
FRAME_KERNELS = ("first_hit_kernel", "surface_kernel", "surface_samples_kernel")
# The Warp modules of the frame kernels that clip (ClipArgs), march several isos (IsoSet) or both, beside this
# module's plain ones (NoClip, OneIso): each compiled and loaded only when a frame needs it, so that a feature
# unused builds and runs nothing of it.
CLIPPED_MODULE = f"{__name__}.clipped"
SURFACES_MODULE = f"{__name__}.surfaces"
CLIPPED_SURFACES_MODULE = f"{__name__}.clipped_surfaces"
VARIANT_MODULES = {(NoClip, OneIso): __name__, (ClipArgs, OneIso): CLIPPED_MODULE, (NoClip, IsoSet): SURFACES_MODULE,
                   (ClipArgs, IsoSet): CLIPPED_SURFACES_MODULE}
for _module in VARIANT_MODULES.values():
    wp.set_module_options({"enable_backward": False}, module=_module)
# The renderer's Warp modules (isosr_net.warp_modules lists the project's).
RENDER_MODULES = tuple(VARIANT_MODULES.values())


def _variant(kernel: wp.Kernel, module: str) -> wp.Kernel:
    """``kernel``'s code (and options) in the Warp module ``module``, under the same name."""
    if module == __name__:
        return kernel
    return wp.Kernel(kernel.func, key=kernel.key, module=wp.get_module(module), options=dict(kernel.options))


# Per (clip type, iso type), the frame kernels by name (one compiled overload each per voxel type and layout).
FRAME_KERNEL_SETS = {variant: {name: _variant(globals()[name], module) for name in FRAME_KERNELS}
                     for variant, module in VARIANT_MODULES.items()}
for _dtype in VOXEL_TYPES:
    wp.overload(minmax_kernel, {"voxels": wp.array3d(dtype=_dtype)})
    for _layout in LAYOUTS:
        for (_clip, _isos), _kernels in FRAME_KERNEL_SETS.items():
            for _kernel in _kernels.values():
                wp.overload(_kernel, {"voxels": wp.array3d(dtype=_dtype), "layout": _layout, "clip": _clip,
                                      "isos": _isos})


def frame_variant(clipped: bool, several: bool = False) -> tuple[type, type]:
    """The frame kernels' (clip type, iso type): :class:`ClipArgs` (``clipped``) or :class:`NoClip`, and
    :class:`IsoSet` (``several`` isos) or :class:`OneIso`."""
    return ClipArgs if clipped else NoClip, IsoSet if several else OneIso


def frame_kernels(clipped: bool, several: bool = False) -> dict[str, wp.Kernel]:
    """The frame kernels by name of :func:`frame_variant`."""
    return FRAME_KERNEL_SETS[frame_variant(clipped, several)]
