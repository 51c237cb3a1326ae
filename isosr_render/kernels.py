"""Warp kernels: the min-max brick grid, its per-iso distance grid, and first-hit + AO ray casting.

One code path for ``cuda`` and ``cpu``, and for every way the voxels lie on the device: dense
float32 (normalized), uint16 or uint8 (normalized per sample, ``(v - d0) * a``), or sparse: a
pool of resident bricks, each stored with its one-voxel overlap as ``(B + 1)^3`` voxels, found
through a per-brick slot table (a brick without a slot can hold no surface for the current
iso: its samples read the brick's minimum, on the same side of the iso as all its voxels).

Rays march in voxel coordinates (voxel ``(i, j, k)`` at integer coordinates, the data spanning
``[0, n - 1]`` per axis) while the ray parameter ``t`` stays in world units, so step sizes and
AO radii mean the same on anisotropic grids. A brick is active when its value range (min-max grid) holds the
iso-value; the trilinear interpolant inside a brick is bounded by the brick's voxels (they
include the one-voxel overlap), so skipping inactive bricks never loses a hit. Rays leap
over inactive bricks by the Chebyshev distance to the nearest active one and march only
active bricks. Buffer conventions: :mod:`isosr_render.conventions`.

The voxels are the kernels' own argument, typed per storage (one compiled overload each), and the
hot functions take the few values they read, never a whole struct: on CUDA each struct passed to
a sampling function, or copied from device memory and live across the march, cost the render
kernel 70-80 registers (178 -> 255 per thread on sm_90) and a third of its speed.
"""

from __future__ import annotations

from typing import Any

import warp as wp

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
    world transform (the voxels, in their device type, and how they lie, :class:`Dense` or
    :class:`Sparse`, are the kernels' arguments beside it)."""

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
    """One frame's values, read by the kernel from device memory: a launch recorded (or captured
    in a CUDA graph) once renders each new frame after a copy of this struct."""

    view: View
    prev: View  # the previous frame's camera (flow); ``view`` when there is none
    params: RayParams


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
def occupancy_kernel(minmax: wp.array3d(dtype=wp.vec2), iso: float, skip: int, empty: int,
                     dist: wp.array3d(dtype=wp.uint8)):
    """Distance 0 for bricks whose range holds ``iso`` (all bricks without ``skip``), else ``empty``."""
    i, j, k = wp.tid()
    mm = minmax[i, j, k]
    active = skip == 0 or (mm[0] <= iso and iso <= mm[1])
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
def lookup(voxels: wp.array3d(dtype=Any), layout: Dense, grid: Grid, i: int, j: int, k: int, f: wp.vec3) -> float:
    """The normalized trilinear sample at fractions ``f`` of the cell ``(i, j, k)`` of dense voxels."""
    return trilinear(voxels, i, j, k, grid.unit[0], f) * grid.unit[1]


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
    return trilinear(voxels, slot * (b + 1) + i - bi * b, j - bj * b, k - bk * b, grid.unit[0], f) * grid.unit[1]


@wp.func
def sample_volume(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3) -> float:
    """Normalized trilinear sample at voxel coordinates ``p``, clamped to the grid."""
    x = wp.clamp(p[0], 0.0, float(grid.size[0] - 1))
    y = wp.clamp(p[1], 0.0, float(grid.size[1] - 1))
    z = wp.clamp(p[2], 0.0, float(grid.size[2] - 1))
    i = wp.min(int(x), grid.size[0] - 2)
    j = wp.min(int(y), grid.size[1] - 2)
    k = wp.min(int(z), grid.size[2] - 2)
    return lookup(voxels, layout, grid, i, j, k, wp.vec3(x - float(i), y - float(j), z - float(k)))


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
          iso: float, h: float, refine_mode: int, refine_steps: int) -> wp.vec2:
    """First iso crossing of the ray ``o + t d`` (voxel coordinates) within ``[t_start, t_end]``,
    its bracket narrowed by ``refine_steps`` (0 where only whether it crosses counts).

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
                f_prev = sample_volume(voxels, layout, grid, o + d * t)
                samples += 1.0
                have_prev = 1
            k = wp.floor((t - t_start) / h) + 1.0
            t_s = t_start + k * h
            done = int(0)
            while done == 0:
                if t_s >= t_exit:
                    t_s = wp.min(t_exit, t_end)
                    done = 1
                f = sample_volume(voxels, layout, grid, o + d * t_s)
                samples += 1.0
                if (f >= iso) != (f_prev >= iso):
                    t_hit = refine_crossing(voxels, layout, grid, o, d, iso, t_prev, f_prev, t_s, f, refine_mode,
                                            refine_steps)
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
         t_far: float, iso: float, step: float, refine_mode: int, refine_steps: int) -> wp.vec2:
    """First crossing of a world-space ray (unit ``direction``) in ``[t_near, t_far]``, world units
    (the ray parameters as for :func:`march`)."""
    o = voxel_from_world(grid, origin)
    d = wp.cw_div(direction, grid.scale)
    span = clip_to_grid(grid.size, o, d)
    t0 = wp.max(span[0], t_near)
    t1 = wp.min(span[1], t_far)
    if t0 > t1:
        return wp.vec2(-1.0, 0.0)
    return march(voxels, layout, grid, o, d, t0, t1, iso, step, refine_mode, refine_steps)


@wp.func
def ambient_occlusion(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, p: wp.vec3, n: wp.vec3, iso: float,
                      step: float, rays: int, radius: float, state: wp.uint32) -> wp.vec2:
    """Fraction of ``rays`` cosine-weighted hemisphere rays around ``n`` that escape within ``radius``.

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
        res = cast(voxels, layout, grid, origin, wp.normalize(dir), 0.0, radius, iso, step, REFINE_BISECTION, 0)
        samples += res[1]
        if res[0] >= 0.0:
            hits += 1.0
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
def trace_pixel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, args: FrameArgs, row0: int, rows: int, tid: int,
                mask: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                depth: wp.array2d(dtype=wp.float32), position: wp.array2d(dtype=wp.vec3),
                flow: wp.array2d(dtype=wp.vec2), ao: wp.array2d(dtype=wp.float32),
                samples: wp.array2d(dtype=wp.int32)):
    """Thread ``tid``'s pixel of the band ``[row0, row0 + rows)``: first hit per subpixel sample, then the
    asked buffers.

    Threads walk the band in 8x4-pixel tiles, one tile per 32-thread warp, so that a warp's
    rays stay close together (coherent brick walks and cache lines).
    """
    view = args.view
    params = args.params
    tile = tid // (TILE_W * TILE_H)
    lane = tid - tile * (TILE_W * TILE_H)
    tiles_x = (view.width + TILE_W - 1) // TILE_W
    c = (tile % tiles_x) * TILE_W + lane % TILE_W
    r = (tile // tiles_x) * TILE_H + lane // TILE_W
    if c >= view.width or r >= rows:
        return
    row = r + row0
    aspect = float(view.width) / float(view.height)
    out = params.outputs
    hits = float(0.0)
    n_acc = wp.vec3(0.0)
    depth_acc = float(0.0)
    pos_acc = wp.vec3(0.0)
    flow_acc = wp.vec2(0.0)
    ao_acc = float(0.0)
    sample_count = float(0.0)
    for s in range(params.spp):
        jx = 0.5
        jy = 0.5
        if params.spp > 1:
            jx = wp.mod(0.5 + float(s) * R2_A1, 1.0)
            jy = wp.mod(0.5 + float(s) * R2_A2, 1.0)
        px = float(c) + jx
        py = float(row) + jy
        ndc_x = 2.0 * px / float(view.width) - 1.0
        ndc_y = 1.0 - 2.0 * py / float(view.height)
        dir = wp.normalize(view.right * (ndc_x * view.tan_half_fov * aspect)
                           + view.up * (ndc_y * view.tan_half_fov) - view.back)
        res = cast(voxels, layout, grid, view.eye, dir, 0.0, float(BIG), params.iso, params.step, params.refine_mode,
                   params.refine_steps)
        sample_count += res[1]
        if res[0] >= 0.0:
            hits += 1.0
            p_world = view.eye + dir * res[0]
            if (out & (OUT_NORMAL | OUT_AO)) != 0:
                g = gradient_world(voxels, layout, grid, voxel_from_world(grid, p_world))
                n = -dir  # where the gradient vanishes: face the camera
                if wp.length(g) > 1.0e-20:
                    n = wp.normalize(g)
                    if wp.dot(n, dir) > 0.0:
                        n = -n
                n_acc += wp.vec3(wp.dot(n, view.right), wp.dot(n, view.up), wp.dot(n, view.back))
                if (out & OUT_AO) != 0:
                    state = wp.rand_init(params.seed, (row * view.width + c) * params.spp + s)
                    occ = ambient_occlusion(voxels, layout, grid, p_world, n, params.iso, params.step,
                                            params.ao_samples, params.ao_radius, state)
                    ao_acc += occ[0]
                    sample_count += occ[1]
            depth_acc += -wp.dot(p_world - view.eye, view.back)
            pos_acc += p_world
            if (out & OUT_FLOW) != 0:
                q = project_to_pixel(args.prev, p_world)
                if q[2] > 0.0:
                    flow_acc += wp.vec2(q[0] - px, q[1] - py)

    inv = 1.0 / wp.max(hits, 1.0)
    if (out & OUT_MASK) != 0:
        mask[row, c] = hits / float(params.spp)
    if (out & OUT_NORMAL) != 0:
        nv = wp.vec3(0.0)
        if wp.length(n_acc) > 1.0e-12:
            nv = wp.normalize(n_acc)
        elif hits > 0.0:
            nv = wp.vec3(0.0, 0.0, 1.0)  # subpixel normals cancelled out: face the camera
        normal[row, c] = nv
    if (out & OUT_DEPTH) != 0:
        depth[row, c] = depth_acc * inv
    if (out & OUT_POSITION) != 0:
        position[row, c] = pos_acc * inv
    if (out & OUT_FLOW) != 0:
        flow[row, c] = flow_acc * inv
    if (out & OUT_AO) != 0:
        ao[row, c] = ao_acc * inv
    if (out & OUT_SAMPLES) != 0:
        samples[row, c] = int(sample_count)


@wp.kernel
def render_kernel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, args: FrameArgs, row0: int, rows: int,
                  mask: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                  depth: wp.array2d(dtype=wp.float32), position: wp.array2d(dtype=wp.vec3),
                  flow: wp.array2d(dtype=wp.vec2), ao: wp.array2d(dtype=wp.float32),
                  samples: wp.array2d(dtype=wp.int32)):
    """The frame's pixels (:func:`trace_pixel`), its values ``args`` a launch parameter."""
    trace_pixel(voxels, layout, grid, args, row0, rows, wp.tid(), mask, normal, depth, position, flow, ao, samples)


# As many registers as render_kernel takes: what the copy of the frame's values adds (about 30) the
# compiler then keeps in the stack (136 bytes, read once per ray) instead of costing occupancy (254 registers).
STAGED_MAX_REGISTERS = 168


@wp.kernel(enable_backward=False, cuda_max_registers=STAGED_MAX_REGISTERS, module=f"{__name__}.staged")
def render_staged_kernel(voxels: wp.array3d(dtype=Any), layout: Any, grid: Grid, frame: wp.array(dtype=FrameArgs),
                         row0: int, rows: int, mask: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                         depth: wp.array2d(dtype=wp.float32), position: wp.array2d(dtype=wp.vec3),
                         flow: wp.array2d(dtype=wp.vec2), ao: wp.array2d(dtype=wp.float32),
                         samples: wp.array2d(dtype=wp.int32)):
    """:func:`render_kernel` with the frame's values read from device memory (``frame`` holds one `FrameArgs`):
    a launch captured in a CUDA graph renders each frame staged after. Its own module, loaded only where
    graphs may be captured (CUDA): the copy stays live through the march (the kernel's writes might alias
    it), so launches that are not captured take the values as a parameter."""
    trace_pixel(voxels, layout, grid, frame[0], row0, rows, wp.tid(), mask, normal, depth, position, flow, ao, samples)


# The voxels' device types and layouts: one compiled overload of each voxel-reading kernel per pair.
VOXEL_TYPES = (wp.float32, wp.uint16, wp.uint8)
LAYOUTS = (Dense, Sparse)
for _dtype in VOXEL_TYPES:
    wp.overload(minmax_kernel, {"voxels": wp.array3d(dtype=_dtype)})
    for _layout in LAYOUTS:
        for _kernel in (render_kernel, render_staged_kernel):
            wp.overload(_kernel, {"voxels": wp.array3d(dtype=_dtype), "layout": _layout})
