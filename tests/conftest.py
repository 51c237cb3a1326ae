"""Shared helpers for the renderer tests: analytic fields on the world grid and pinhole rays.

Everything here follows :mod:`isosr_render.conventions` written out independently of the
renderer (world grid from ``world_from_voxel``, OpenGL-style view space, pixel centers at
``(col + 0.5, row + 0.5)``), so the tests compare the renderer with analytic references.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from isosr_render.conventions import world_from_voxel
from isosr_render.volume import Volume

# The device the renderer tests run on: CI runs them on the CPU; on a GPU machine
# `ISOSR_TEST_DEVICE=cuda pytest tests/test_renderer.py` runs the same tests there.
DEVICE = os.environ.get("ISOSR_TEST_DEVICE", "cpu")
# ISOSR_TEST_SHARD=K/N: this process runs every N-th collected test from the K-th (0-based), so that
# N processes share a slow file's tests (tests/test_fused_recon.py: the interpreter's, one per core).
SHARD_ENV = "ISOSR_TEST_SHARD"


def pytest_collection_modifyitems(config, items):
    shard = os.environ.get(SHARD_ENV)
    if not shard:
        return
    k, n = (int(part) for part in shard.split("/"))
    config.hook.pytest_deselected(items=[item for i, item in enumerate(items) if i % n != k])
    items[:] = items[k::n]


def world_grid(shape, spacing=(1.0, 1.0, 1.0)):
    """World coordinates ``(x, y, z)`` of every voxel, each of shape ``shape`` (float64)."""
    scale, offset = world_from_voxel(tuple(shape), tuple(spacing))
    axes = [np.arange(n, dtype=np.float64) * scale[a] + offset[a] for a, n in enumerate(shape)]
    return np.meshgrid(*axes, indexing="ij")


def sphere_sdf(p, radius=0.3):
    """Signed distance to a sphere at the origin; ``p`` has shape (..., 3)."""
    return np.linalg.norm(p, axis=-1) - radius


def torus_sdf(p, major=0.3, minor=0.1):
    """Signed distance to a torus around the z axis; ``p`` has shape (..., 3)."""
    q = np.hypot(p[..., 0], p[..., 1]) - major
    return np.hypot(q, p[..., 2]) - minor


def torus_normal(p, major=0.3):
    """Analytic outward unit normal of the torus around z at points ``p`` (..., 3)."""
    rho = np.hypot(p[..., 0], p[..., 1])
    core = np.stack([p[..., 0] * major / rho, p[..., 1] * major / rho, np.zeros_like(rho)], axis=-1)
    d = p - core
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def field_volume(fn, shape=(64, 64, 64), spacing=(1.0, 1.0, 1.0)) -> Volume:
    """``Volume.from_array`` of ``fn(p)`` sampled at the world position of every voxel."""
    x, y, z = world_grid(shape, spacing)
    p = np.stack([x, y, z], axis=-1)
    return Volume.from_array(fn(p).astype(np.float32), spacing=spacing)


def pixel_rays(camera, width: int, height: int):
    """Eye and unit world-space ray directions (H, W, 3) through the pixel centers (float64)."""
    right, up, back = camera.basis()
    t = camera.tan_half_fov()
    aspect = width / height
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    ndc_x, ndc_y = np.meshgrid(x, y)
    d = (ndc_x[..., None] * t * aspect) * right + (ndc_y[..., None] * t) * up - back
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.asarray(camera.eye, dtype=np.float64), d


def ray_sphere(eye, dirs, radius):
    """Analytic first hit of rays with a sphere at the origin.

    Returns:
        ``(hit, t, miss_distance)``: hit mask (H, W), ray parameter of the first hit in front of
        the eye (nan where none) and ``|distance(center, ray line) - radius|``, the distance of
        the ray from the silhouette.
    """
    b = dirs @ eye
    c = eye @ eye - radius * radius
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t_near, t_far = -b - root, -b + root
    t = np.where(t_near > 0, t_near, t_far)
    hit = (disc > 0) & (t > 0)
    line_dist = np.sqrt(np.maximum(eye @ eye - b * b, 0.0))
    return hit, np.where(hit, t, np.nan), np.abs(line_dist - radius)


def ray_march_sdf(sdf, eye, dirs, t0, t1, dt, near_band):
    """First hit of rays with the zero set of an exact SDF by dense sampling (float64).

    Samples ``sdf`` every ``dt`` in ``[t0, t1]``, takes the first + to - sign change and bisects
    it to machine precision. A ray counts as grazing (near a silhouette) when, before it gets
    deeper than ``near_band`` inside the surface, the SDF along it has a local minimum within
    ``near_band`` of 0.

    Returns:
        ``(hit, t, grazing)``, each of shape dirs.shape[:-1]; ``t`` is nan where there is no hit.
    """
    shape = dirs.shape[:-1]
    d = dirs.reshape(-1, 3)
    n = d.shape[0]
    t_hit = np.full(n, np.nan)
    lo = np.zeros(n)
    grazing = np.zeros(n, dtype=bool)
    active = np.ones(n, dtype=bool)  # not yet deeper than near_band
    s2 = np.full(n, np.inf)
    t_prev = t0
    s1 = sdf(eye + t0 * d)
    for t in np.arange(t0 + dt, t1, dt):
        s = sdf(eye + t * d)
        local_min = (s1 < s2) & (s1 <= s) & (np.abs(s1) < near_band)
        grazing |= active & local_min
        new = np.isnan(t_hit) & (s1 > 0) & (s <= 0)
        t_hit[new] = t
        lo[new] = t_prev
        active &= s > -near_band
        s2, s1, t_prev = s1, s, t
    hit = ~np.isnan(t_hit)
    a, b = lo[hit], t_hit[hit]
    for _ in range(60):
        m = 0.5 * (a + b)
        inside = sdf(eye + m[:, None] * d[hit]) <= 0
        b = np.where(inside, m, b)
        a = np.where(inside, a, m)
    t_hit[hit] = 0.5 * (a + b)
    return hit.reshape(shape), t_hit.reshape(shape), grazing.reshape(shape)


def render_np(renderer, camera, request) -> dict:
    """Render and return the present buffers as numpy arrays."""
    return renderer.render(camera, request).to_numpy()


def view_to_world(camera, n_view):
    """View-space vectors (..., 3) to world space: ``world = basis.T @ view``."""
    return n_view @ camera.basis()


def angle_deg(a, b):
    """Angle in degrees between unit vectors along the last axis."""
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@pytest.fixture(scope="session")
def sphere_volume() -> Volume:
    """Sphere SDF, radius 0.3 world units, 64^3."""
    return field_volume(lambda p: sphere_sdf(p, 0.3))


@pytest.fixture(scope="session")
def torus_volume() -> Volume:
    """Torus SDF around z, R = 0.3, r = 0.1, 64^3."""
    return field_volume(torus_sdf)


def record_make_batch(monkeypatch, record) -> None:
    """Have ``record(frames)`` called with the frames of each batch a frame kind's ``make_batch`` is given
    from outside (``(runner, camera, prev_camera)`` each): every kind's own make_batch wrapped, the calls
    one makes of its base's not recorded."""
    import threading

    from isosr_net.methods import RUNNERS, FrameRunner

    inner = threading.local()

    def recording(make_batch):
        def recorded(cls, frames):
            depth = getattr(inner, "depth", 0)
            if not depth:
                record(frames)
            inner.depth = depth + 1
            try:
                return make_batch(cls, frames)
            finally:
                inner.depth = depth
        return classmethod(recorded)
    for cls in {FrameRunner, *RUNNERS.values()}:
        if "make_batch" in vars(cls):
            monkeypatch.setattr(cls, "make_batch", recording(vars(cls)["make_batch"].__func__))
