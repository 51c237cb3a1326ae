"""Tests for isosr_render.renderer against analytic references.

Every expected value comes from geometry written out in the tests (ray-sphere intersection,
dense float64 marching of an exact SDF, planes, pinhole projection from the conventions),
never from the renderer's own code. Scenes are small (<= 128 x 96 pixels, <= 64^3 voxels)
so the file runs in seconds on a 2-core CPU.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from conftest import (DEVICE, angle_deg, field_volume, pixel_rays, ray_march_sdf, ray_sphere, render_np,
                      sphere_sdf, torus_normal, torus_sdf, view_to_world, world_grid)
from isosr_render.camera import Camera, orbit
from isosr_render.renderer import Renderer, RenderRequest
from isosr_render.shading import shade
from isosr_render.volume import Volume

W, H = 128, 96
GEOMETRY = ("mask", "normal", "depth", "position")
ALL = ("mask", "normal", "depth", "position", "ao", "color", "samples")


def _forward(camera: Camera) -> np.ndarray:
    return -camera.basis()[2]


# ---------------------------------------------------------------------------------------------
# Scenes shared by several tests (one Renderer per volume per module).


@pytest.fixture(scope="module")
def sphere_renderer(sphere_volume):
    return Renderer(sphere_volume, DEVICE, threads=2)


@pytest.fixture(scope="module")
def torus_renderer(torus_volume):
    return Renderer(torus_volume, DEVICE, threads=2)


SPHERE_R = 0.3
SPHERE_CAM = orbit(30.0, 20.0, 1.2)
TORUS_CAM = orbit(20.0, 40.0, 1.5)  # oblique: sees into the hole


@pytest.fixture(scope="module", params=["sphere", "torus"])
def scene(request, sphere_volume, torus_volume, sphere_renderer, torus_renderer):
    """A rendered frame with its analytic reference.

    Returns a dict: renderer, volume, camera, sdf, normal_fn, frame (numpy), eye, dirs,
    hit / t (analytic first hit per pixel center) and near_sil (rays within one voxel of a
    silhouette, where the discretized surface may legitimately differ).
    """
    name = request.param
    if name == "sphere":
        volume, renderer, camera = sphere_volume, sphere_renderer, SPHERE_CAM
        sdf = lambda p: sphere_sdf(p, SPHERE_R)  # noqa: E731
        normal_fn = lambda p: p / np.linalg.norm(p, axis=-1, keepdims=True)  # noqa: E731
    else:
        volume, renderer, camera = torus_volume, torus_renderer, TORUS_CAM
        sdf, normal_fn = torus_sdf, torus_normal
    voxel = volume.voxel_size_world()
    eye, dirs = pixel_rays(camera, W, H)
    if name == "sphere":
        hit, t, miss_dist = ray_sphere(eye, dirs, SPHERE_R)
        near_sil = miss_dist < voxel
    else:
        dist = np.linalg.norm(eye)
        hit, t, near_sil = ray_march_sdf(sdf, eye, dirs, dist - 0.6, dist + 0.6, 0.002, voxel)
    frame = render_np(renderer, camera, RenderRequest(W, H, volume.normalized_iso(0.0), outputs=GEOMETRY))
    return dict(name=name, renderer=renderer, volume=volume, camera=camera, sdf=sdf, normal_fn=normal_fn,
                frame=frame, eye=eye, dirs=dirs, hit=hit, t=t, near_sil=near_sil, voxel=voxel)


# ---------------------------------------------------------------------------------------------
# 1. Geometry against analytic surfaces.


def test_reference_rays_match_camera_project(scene):
    """Sanity of the test's own ray generation: analytic hits project back to pixel centers."""
    hit, t = scene["hit"], scene["t"]
    p = scene["eye"] + t[..., None] * scene["dirs"]
    pix, depth = scene["camera"].project(p[hit], W, H)
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    np.testing.assert_allclose(pix, np.stack([xs, ys], -1)[hit], atol=1e-6)
    assert (depth > 0).all()


def test_mask_matches_analytic_intersection(scene):
    mask = scene["frame"]["mask"]
    assert set(np.unique(mask)) <= {0.0, 1.0}  # spp = 1: binary
    hit = mask > 0.5
    differ = hit != scene["hit"]
    assert scene["hit"].sum() > 1000
    # Differences only where the analytic ray passes within a voxel of the silhouette.
    assert not (differ & ~scene["near_sil"]).any(), np.argwhere(differ & ~scene["near_sil"])[:10]
    assert differ.sum() <= 12


def test_positions_on_analytic_surface(scene):
    f, voxel = scene["frame"], scene["voxel"]
    hit = f["mask"] > 0.5
    p = f["position"][hit].astype(np.float64)
    err = np.abs(scene["sdf"](p))
    assert err.max() < 0.05 * voxel, err.max() / voxel


def test_positions_are_first_hits(scene):
    """Away from silhouettes the hit is the first surface along the pixel-center ray."""
    f, voxel = scene["frame"], scene["voxel"]
    ok = (f["mask"] > 0.5) & scene["hit"] & ~scene["near_sil"]
    p_ref = scene["eye"] + scene["t"][..., None] * scene["dirs"]
    err = np.linalg.norm(f["position"][ok] - p_ref[ok], axis=-1)
    assert ok.sum() > 0.7 * scene["hit"].sum()
    assert err.max() < 0.1 * voxel, err.max() / voxel


def test_normals_match_analytic(scene):
    f, camera = scene["frame"], scene["camera"]
    hit = f["mask"] > 0.5
    n_view = f["normal"].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n_view[hit], axis=-1), 1.0, atol=1e-5)
    ok = hit & ~scene["near_sil"]
    p = f["position"][ok].astype(np.float64)
    n_world = view_to_world(camera, n_view[ok])
    ang = angle_deg(n_world, scene["normal_fn"](p))  # outward = toward this outside camera
    assert ang.max() < 2.0, ang.max()
    # Facing the camera everywhere a hit is (conventions: dot(normal, to_camera) >= 0).
    to_cam = np.asarray(camera.eye) - f["position"][hit].astype(np.float64)
    assert (np.sum(view_to_world(camera, n_view[hit]) * to_cam, -1) >= 0).all()


def test_depth_is_distance_along_forward(scene):
    f, camera = scene["frame"], scene["camera"]
    hit = f["mask"] > 0.5
    expect = (f["position"][hit].astype(np.float64) - np.asarray(camera.eye)) @ _forward(camera)
    np.testing.assert_allclose(f["depth"][hit], expect, rtol=1e-5, atol=1e-6)
    assert (f["depth"][hit] > 0).all()


def test_buffers_empty_where_no_hit(scene):
    f = scene["frame"]
    miss = f["mask"] == 0
    assert miss.any()
    for name in ("normal", "depth", "position"):
        assert (f[name][miss] == 0).all(), name


@pytest.mark.parametrize("refine", ["bisection", "secant"])
@pytest.mark.parametrize("steps", [0, 8])
def test_refine_methods_hit_the_sphere(sphere_volume, sphere_renderer, refine, steps):
    req = RenderRequest(64, 48, sphere_volume.normalized_iso(0.0), outputs=("mask", "position"),
                        refine=refine, refine_steps=steps)
    f = render_np(sphere_renderer, SPHERE_CAM, req)
    p = f["position"][f["mask"] > 0.5].astype(np.float64)
    assert len(p) > 300
    assert np.abs(sphere_sdf(p, SPHERE_R)).max() < 0.05 * sphere_volume.voxel_size_world()


def test_supersampling_mask_is_coverage(sphere_volume, sphere_renderer):
    """spp > 1: mask is a coverage in [0, 1], fractional only along the silhouette."""
    w, h = 64, 48
    req = RenderRequest(w, h, sphere_volume.normalized_iso(0.0), outputs=("mask", "normal"), spp=8)
    f = render_np(sphere_renderer, SPHERE_CAM, req)
    eye, dirs = pixel_rays(SPHERE_CAM, w, h)
    hit, _, miss_dist = ray_sphere(eye, dirs, SPHERE_R)
    pixel_world = 2 * 1.2 * SPHERE_CAM.tan_half_fov() / h  # pixel footprint at the sphere, roughly
    edge = miss_dist < 1.5 * pixel_world
    mask = f["mask"]
    assert (mask >= 0).all() and (mask <= 1).all()
    frac = (mask > 0) & (mask < 1)
    assert frac.any() and not (frac & ~edge).any()
    assert (mask[hit & ~edge] == 1).all() and (mask[~hit & ~edge] == 0).all()
    assert abs(mask.sum() - hit.sum()) < 0.03 * hit.sum()
    n = np.linalg.norm(f["normal"], axis=-1)
    np.testing.assert_allclose(n[mask > 0], 1.0, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# 2. Empty-space skipping.


def test_skipping_same_image_far_fewer_samples():
    volume = field_volume(lambda p: sphere_sdf(p, 0.1))  # sparse: a small sphere in a 64^3 box
    renderer = Renderer(volume, DEVICE, threads=2)
    camera = orbit(30.0, 20.0, 1.8)
    frames = {skip: render_np(renderer, camera, RenderRequest(W, H, volume.normalized_iso(0.0),
                                                              outputs=("mask", "position", "samples"), skip=skip))
              for skip in (True, False)}
    a, b = frames[True], frames[False]
    assert a["mask"].sum() > 100
    assert (a["mask"] != b["mask"]).sum() <= 3
    both = (a["mask"] > 0) & (b["mask"] > 0)
    voxel = volume.voxel_size_world()
    assert np.abs(a["position"][both] - b["position"][both]).max() < 0.01 * voxel
    # Both are on the analytic sphere.
    assert np.abs(sphere_sdf(a["position"][both].astype(np.float64), 0.1)).max() < 0.05 * voxel
    ratio = a["samples"].sum() / b["samples"].sum()
    assert ratio < 0.5, ratio
    assert b["samples"].sum() > 0


def _smooth_noise(shape, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(shape)
    for axis in range(3):
        for _ in range(3):
            v = (np.roll(v, 1, axis) + v + np.roll(v, -1, axis)) / 3.0
    return v.astype(np.float32)


def _blobs(shape=(48, 48, 48), seed=5):
    """Sparse SDF: a dozen small spheres scattered in the box (long empty stretches to leap)."""
    rng = np.random.default_rng(seed)
    x, y, z = world_grid(shape)
    p = np.stack([x, y, z], -1)
    centers, radii = rng.uniform(-0.42, 0.42, (12, 3)), rng.uniform(0.02, 0.06, 12)
    return np.min([np.linalg.norm(p - c, axis=-1) - r for c, r in zip(centers, radii)], axis=0).astype(np.float32)


@pytest.mark.parametrize("kind, brick_size", [("noise", 1), ("noise", 3), ("noise", 8), ("blobs", 1), ("blobs", 4)])
def test_skipping_never_changes_hits(kind, brick_size):
    """Skipping gives bit-identical hits, from outside and inside the volume: dense irregular
    surfaces in a non-cubic anisotropic grid whose sides are not multiples of the brick, and
    sparse blobs with long empty stretches."""
    if kind == "noise":
        volume = Volume.from_array(_smooth_noise((37, 29, 23)), spacing=(1.0, 1.3, 2.0))
        isos = (0.35, 0.6)
    else:
        volume = Volume.from_array(_blobs())
        isos = (volume.normalized_iso(0.0),)
    renderer = Renderer(volume, DEVICE, threads=2, brick_size=brick_size)
    cameras = [orbit(30.0, 20.0, 1.8), orbit(-120.0, -50.0, 1.5), orbit(90.0, 0.0, 1.8),
               Camera((0.05, 0.02, 0.01), (1.0, 0.3, -0.2)), Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))]
    skipped = full = 0
    for iso in isos:
        for camera in cameras:
            a, b = (render_np(renderer, camera, RenderRequest(41, 31, iso, outputs=("mask", "position", "samples"),
                                                              skip=s)) for s in (True, False))
            np.testing.assert_array_equal(a["mask"], b["mask"])
            np.testing.assert_array_equal(a["position"], b["position"])
            skipped, full = skipped + a["samples"].sum(), full + b["samples"].sum()
    assert full > 0 and skipped <= full
    if kind == "blobs":
        assert skipped < 0.2 * full


def _filtered_scene(kind: str) -> tuple[Volume, tuple[float, ...]]:
    """Volumes whose marches decide near the iso: smooth noise (float32, and quantized to uint8:
    the texture's 8-bit path), a shell on a plateau at the iso, a one-voxel sheet, tiny anisotropic."""
    x, y, z = world_grid((40, 36, 28))
    r = np.sqrt(x * x + y * y + z * z)
    if kind == "noise":
        return Volume.from_array(_smooth_noise((37, 29, 23)), spacing=(1.0, 1.3, 2.0)), (0.35, 0.6)
    if kind == "noise_uint8":
        v = _smooth_noise((37, 29, 23))
        v = np.round((v - v.min()) / (v.max() - v.min()) * 255).astype(np.uint8)
        return Volume.from_array(v, spacing=(1.0, 1.3, 2.0)), (0.35, 0.6)
    if kind == "plateau":
        values = np.where(r < 0.15, 1.0, np.where(r < 0.35, 0.5, 0.0)).astype(np.float32)
        return Volume.from_array(values), (0.5, 0.5 + 1e-6)
    if kind == "sheet":
        values = np.zeros((24, 24, 24), np.float32)
        values[:, 12, :] = 1.0
        return Volume.from_array(values), (0.5, 0.999)
    values = np.zeros((2, 2, 2), np.float32)
    values[1, :, 0] = values[0, 1, 1] = 1.0
    return Volume.from_array(values, spacing=(1.0, 3.0, 0.5)), (0.5, 0.25)


@pytest.mark.parametrize("kind", ["noise", "noise_uint8", "plateau", "sheet", "tiny"])
def test_a_march_through_the_filtered_texture_gives_the_exact_marchs_buffers(kind):
    """The march's lattice samples from the voxels' texture (hardware-filtered on CUDA, 8-bit
    weights), decided exactly near the iso: every buffer equals the exact march's bit for bit,
    AO rays and sample counts included, from outside, inside and edge-on."""
    volume, isos = _filtered_scene(kind)
    exact, filtered = (Renderer(volume, DEVICE, threads=2, filtered=f) for f in (False, True))
    cameras = [orbit(30.0, 20.0, 1.8), orbit(-120.0, -50.0, 1.5), orbit(90.0, 0.0, 1.8),
               Camera((0.05, 0.02, 0.01), (1.0, 0.3, -0.2))]
    hits = 0
    for iso in isos:
        for camera in cameras:
            request = RenderRequest(41, 31, iso, outputs=("mask", "normal", "depth", "position", "ao", "samples"),
                                    ao_samples=4, ao_radius=0.3, spp=2)
            a, b = render_np(exact, camera, request), render_np(filtered, camera, request)
            for name in request.outputs:
                np.testing.assert_array_equal(a[name], b[name], err_msg=name)
            hits += int((a["mask"] > 0).sum())
    assert hits > 0
    assert filtered.memory().resident_bytes == 2 * exact.memory().resident_bytes


def test_a_filtered_march_that_cannot_have_its_texture_is_refused():
    volume = Volume.from_array(_smooth_noise((16, 16, 16)))
    with pytest.raises(ValueError, match=r"filtered: the voxels and their texture \(32768 bytes\) do not fit"):
        Renderer(volume, DEVICE, max_device_bytes=20000, filtered=True)
    with pytest.raises(ValueError, match="renders sparse past max_device_bytes=8000; only dense voxels"):
        Renderer(volume, DEVICE, max_device_bytes=8000, filtered=True)
    assert Renderer(volume, DEVICE, max_device_bytes=20000).memory().resident_bytes == 16384  # no texture


def test_a_texture_the_device_cannot_make_falls_back_to_the_exact_march_or_is_refused(monkeypatch):
    """A device that cannot make the texture (a side past its 3D texture extent, its memory):
    the default renders from the voxels alone; ``filtered=True`` says why it cannot."""
    import isosr_render.renderer as renderer_module

    def refuse(*_):
        raise RuntimeError("3D texture extent exceeded")

    monkeypatch.setattr(renderer_module, "filtered_layout", refuse)
    volume = Volume.from_array(_smooth_noise((16, 16, 16)))
    with pytest.raises(ValueError, match="filtered: .* cannot make the voxels' texture: 3D texture extent exceeded"):
        Renderer(volume, DEVICE, filtered=True)
    fallback = Renderer(volume, DEVICE)
    assert not fallback.filtered and fallback.memory().resident_bytes == 16384


# ---------------------------------------------------------------------------------------------
# 3. Ambient occlusion.

HOLLOW_R = 0.3
INSIDE_CAM = Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 60.0)


def _ao_inside_sphere(radius: float, ao_radius: float, offset: float) -> float:
    """Analytic AO on the inner wall of a sphere for cosine-weighted rays of length ``ao_radius``
    cast from ``offset`` inside the wall: a ray at angle theta to the inward normal leaves
    ``a cos + sqrt(R^2 - a^2 sin^2)`` before the wall (``a = R - offset``); it is occluded if that
    is shorter than ``ao_radius``. With mu = cos(theta) distributed as 2 mu dmu, AO = 1 - mu*^2."""
    a = radius - offset
    mu = np.linspace(0.0, 1.0, 200001)
    chord = a * mu + np.sqrt(radius ** 2 - a ** 2 * (1.0 - mu ** 2))
    mu_star = mu[np.argmax(chord >= ao_radius)] if (chord >= ao_radius).any() else 1.0
    return 1.0 - mu_star ** 2


def test_ao_is_one_on_convex_sphere(sphere_volume, sphere_renderer):
    req = RenderRequest(64, 48, sphere_volume.normalized_iso(0.0), outputs=("mask", "ao"), ao_samples=32)
    f = render_np(sphere_renderer, SPHERE_CAM, req)
    hit = f["mask"] > 0
    assert hit.sum() > 300
    assert f["ao"][hit].mean() > 0.97
    assert (f["ao"][~hit] == 0).all()


def test_ao_inside_hollow_sphere_matches_analytic(sphere_volume, sphere_renderer):
    """Camera at the center of a sphere: every hit is on the concave inner wall."""
    ao_radius = 0.45
    req = RenderRequest(32, 32, sphere_volume.normalized_iso(0.0), outputs=("mask", "ao"),
                        ao_samples=256, ao_radius=ao_radius)
    f = render_np(sphere_renderer, INSIDE_CAM, req)
    assert (f["mask"] == 1).all()
    # The renderer starts AO rays half a voxel off the surface (its documented bias).
    ref = _ao_inside_sphere(HOLLOW_R, ao_radius, 0.5 * sphere_volume.voxel_size_world())
    assert f["ao"].mean() < 0.7
    assert abs(f["ao"].mean() - ref) < 0.02, (f["ao"].mean(), ref)
    assert (f["ao"] >= 0).all() and (f["ao"] <= 1).all()


def test_ao_noise_falls_with_samples(sphere_volume, sphere_renderer):
    """RMS error against the analytic AO over a region ~ 1/sqrt(N): 256 rays vs 16 rays."""
    ao_radius = 0.45
    ref = _ao_inside_sphere(HOLLOW_R, ao_radius, 0.5 * sphere_volume.voxel_size_world())
    rms = {}
    for n in (16, 256):
        req = RenderRequest(32, 32, sphere_volume.normalized_iso(0.0), outputs=("ao",),
                            ao_samples=n, ao_radius=ao_radius, seed=3)
        ao = render_np(sphere_renderer, INSIDE_CAM, req)["ao"]
        rms[n] = float(np.sqrt(np.mean((ao - ref) ** 2)))
    assert rms[256] / rms[16] < 0.5, rms
    assert rms[16] > 0.05  # 16 rays are visibly noisy, so the ratio measures something


def test_ao_deterministic_per_seed(sphere_volume, sphere_renderer):
    def ao(seed):
        req = RenderRequest(16, 16, sphere_volume.normalized_iso(0.0), outputs=("ao",), ao_samples=16,
                            ao_radius=0.45, seed=seed)
        return render_np(sphere_renderer, INSIDE_CAM, req)["ao"]

    np.testing.assert_array_equal(ao(1), ao(1))
    assert not np.array_equal(ao(1), ao(2))


# ---------------------------------------------------------------------------------------------
# 4. Flow.

FLOW_PREV = orbit(20.0, 40.0, 1.5)
FLOW_CUR = orbit(23.0, 40.0, 1.5)


def _pixel_centers(w, h):
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([xs, ys], -1)


def test_flow_is_analytic_reprojection(torus_volume, torus_renderer):
    req = RenderRequest(W, H, torus_volume.normalized_iso(0.0), outputs=("mask", "position", "flow"),
                        prev_camera=FLOW_PREV)
    f = render_np(torus_renderer, FLOW_CUR, req)
    hit = f["mask"] > 0
    prev_px, prev_depth = FLOW_PREV.project(f["position"].astype(np.float64), W, H)
    expect = prev_px - _pixel_centers(W, H)
    assert hit.sum() > 1000 and (prev_depth[hit] > 0).all()
    err = np.abs(f["flow"][hit] - expect[hit])
    assert err.max() < 0.01, err.max()
    assert np.abs(f["flow"][hit]).mean() > 0.2  # a real motion, not a trivially zero flow
    assert (f["flow"][~hit] == 0).all()


def test_flow_zero_for_static_camera(torus_volume, torus_renderer):
    req = RenderRequest(64, 48, torus_volume.normalized_iso(0.0), outputs=("mask", "flow"), prev_camera=TORUS_CAM)
    f = render_np(torus_renderer, TORUS_CAM, req)
    assert (f["mask"] > 0).sum() > 100
    assert np.abs(f["flow"]).max() < 1e-3


def test_flow_zero_where_point_was_behind_previous_camera(sphere_volume, sphere_renderer):
    """Inside a sphere: now looking along +x, before along -z; wall points with z > 0 lay
    behind the previous camera (flow 0), the others reproject analytically."""
    cur = Camera((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), 60.0)
    prev = Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 60.0)
    w, h = 48, 32
    req = RenderRequest(w, h, sphere_volume.normalized_iso(0.0), outputs=("mask", "position", "flow"),
                        prev_camera=prev)
    f = render_np(sphere_renderer, cur, req)
    assert (f["mask"] == 1).all()
    prev_px, prev_depth = prev.project(f["position"].astype(np.float64), w, h)
    front = prev_depth > 1e-3
    behind = prev_depth < -1e-3
    assert front.sum() > 100 and behind.sum() > 100
    assert (f["flow"][behind] == 0).all()
    expect = prev_px - _pixel_centers(w, h)
    np.testing.assert_allclose(f["flow"][front], expect[front], rtol=1e-4, atol=0.01)


@pytest.mark.parametrize("fill", ["pushpull", "ns"])
def test_flow_fill_fills_holes_keeps_hits(torus_volume, torus_renderer, fill):
    base = RenderRequest(W, H, torus_volume.normalized_iso(0.0), outputs=("mask", "flow"), prev_camera=FLOW_PREV)
    plain = render_np(torus_renderer, FLOW_CUR, base)
    filled = render_np(torus_renderer, FLOW_CUR, dataclasses.replace(base, flow_fill=fill))
    hit = plain["mask"] > 0
    assert (~hit).sum() > 1000
    assert np.isfinite(filled["flow"]).all()
    np.testing.assert_array_equal(filled["flow"][hit], plain["flow"][hit])
    np.testing.assert_array_equal(filled["mask"], plain["mask"])
    # Holes get values within the range of the hit flows (a fill, not garbage).
    lo, hi = plain["flow"][hit].min(0), plain["flow"][hit].max(0)
    holes = filled["flow"][~hit]
    assert (holes >= lo - 1e-4).all() and (holes <= hi + 1e-4).all()
    assert np.abs(holes).max() > 0


def test_flow_fill_without_mask_output(torus_volume, torus_renderer):
    """Asking flow + fill alone still fills (the mask is computed internally, not returned)."""
    req = RenderRequest(64, 48, torus_volume.normalized_iso(0.0), outputs=("flow",), prev_camera=FLOW_PREV,
                        flow_fill="pushpull")
    frame = torus_renderer.render(FLOW_CUR, req)
    assert frame.present() == ["flow"]
    flow = frame.flow.cpu().numpy()
    assert np.isfinite(flow).all() and (np.linalg.norm(flow, axis=-1) > 0).all()


# ---------------------------------------------------------------------------------------------
# 5. Only what is asked is computed.


def test_only_asked_buffers_returned(sphere_volume, sphere_renderer):
    frame = sphere_renderer.render(SPHERE_CAM, RenderRequest(32, 24, sphere_volume.normalized_iso(0.0),
                                                             outputs=("mask",)))
    assert frame.present() == ["mask"]
    for name in ("normal", "depth", "position", "flow", "ao", "color", "samples"):
        assert getattr(frame, name) is None, name
    assert tuple(frame.mask.shape) == (24, 32)


def test_samples_count_only_asked_work(torus_volume, torus_renderer):
    iso = torus_volume.normalized_iso(0.0)

    def samples(outputs):
        return render_np(torus_renderer, TORUS_CAM, RenderRequest(64, 48, iso, outputs=outputs, ao_samples=8))

    base = samples(("mask", "samples"))
    hit = base["mask"] > 0
    assert hit.sum() > 100 and base["samples"][hit].min() > 0
    # Normals, depth and positions take no extra volume samples (no AO rays).
    for outputs in (("samples",), ("mask", "normal", "samples"), ("mask", "depth", "position", "samples"),
                    ("color", "samples")):
        np.testing.assert_array_equal(samples(outputs)["samples"], base["samples"], err_msg=str(outputs))
    with_ao = samples(("mask", "ao", "samples"))["samples"]
    assert (with_ao[hit] > base["samples"][hit]).all()  # AO rays are taken, at every hit
    np.testing.assert_array_equal(with_ao[~hit], base["samples"][~hit])


def test_flow_without_prev_camera_raises():
    with pytest.raises(ValueError, match="prev"):
        RenderRequest(32, 32, 0.5, outputs=("mask", "flow"))


def test_color_without_ao_shades_without_occlusion(torus_volume, torus_renderer):
    iso = torus_volume.normalized_iso(0.0)
    kw = dict(ao_samples=16, ao_radius=0.3)
    geo = torus_renderer.render(TORUS_CAM, RenderRequest(64, 48, iso, outputs=("mask", "normal", "ao"), **kw))
    color = torus_renderer.render(TORUS_CAM, RenderRequest(64, 48, iso, outputs=("color",), **kw))
    assert color.present() == ["color"]
    torch.testing.assert_close(color.color, shade(geo.mask, geo.normal, None), atol=1e-6, rtol=0)
    color_ao = torus_renderer.render(TORUS_CAM, RenderRequest(64, 48, iso, outputs=("color", "ao"), **kw))
    torch.testing.assert_close(color_ao.color, shade(geo.mask, geo.normal, geo.ao), atol=1e-6, rtol=0)
    assert (geo.ao[geo.mask > 0] < 0.9).any()  # the torus occludes itself at this radius
    assert not torch.allclose(color.color, color_ao.color)
    # Background where nothing is hit.
    miss = geo.mask == 0
    assert torch.all(color.color[miss] == 1.0)


# ---------------------------------------------------------------------------------------------
# 6. Hard cases: finite, bounded output (or a clear error).


def _render_all(volume: Volume, camera: Camera, iso: float, w: int = 48, h: int = 33, **kw) -> dict:
    """Render every buffer, flow against the same camera (so flow must be ~0), and check the
    conventions' bounds."""
    renderer = Renderer(volume, DEVICE, threads=2)
    req = RenderRequest(w, h, iso, outputs=ALL + ("flow",), prev_camera=camera, ao_samples=8, **kw)
    f = render_np(renderer, camera, req)
    for name, a in f.items():
        assert np.isfinite(a).all(), name
    mask = f["mask"]
    assert (mask >= 0).all() and (mask <= 1).all()
    hit = mask > 0
    n = np.linalg.norm(f["normal"], axis=-1)
    np.testing.assert_allclose(n[hit], 1.0, atol=1e-4)
    to_cam = np.asarray(camera.eye) - f["position"][hit].astype(np.float64)
    assert (np.sum(view_to_world(camera, f["normal"][hit].astype(np.float64)) * to_cam, -1) >= -1e-6).all()
    for name in ("normal", "depth", "position", "flow", "ao"):
        assert (f[name][~hit] == 0).all(), name
    assert (f["ao"] >= 0).all() and (f["ao"] <= 1).all()
    assert (f["depth"] >= 0).all() and (f["depth"][hit] > 0).all()
    assert (f["color"] >= 0).all() and (f["color"] <= 1).all()
    assert (f["samples"] >= 0).all()
    assert np.abs(f["flow"]).max(initial=0.0) < 1e-2
    if hit.any():
        expect = (f["position"][hit].astype(np.float64) - np.asarray(camera.eye)) @ _forward(camera)
        np.testing.assert_allclose(f["depth"][hit], expect, rtol=1e-4, atol=1e-5)
    return f


def _plane_y_volume(n=65):
    """Field y (world): the iso 0 plane lies exactly on voxel layer n // 2."""
    return Volume.from_array(world_grid((n, n, n))[1].astype(np.float32))


def test_grazing_along_top_face_of_box(sphere_volume):
    """Odd image height: the center row's rays run exactly in the box's top face y = 0.5."""
    cam = Camera((0.0, 0.5, 2.0), (0.0, 0.5, 0.0))
    f = _render_all(sphere_volume, cam, sphere_volume.normalized_iso(0.0))
    assert (f["mask"] > 0).sum() > 20  # the lower half of the image sees the sphere
    p = f["position"][f["mask"] > 0].astype(np.float64)
    assert np.abs(sphere_sdf(p, SPHERE_R)).max() < 0.05 * sphere_volume.voxel_size_world()


def test_grazing_along_side_face_with_surface_on_face():
    """Camera in the plane x = +0.5 (a face), field x with the iso on that face (the maximum)."""
    volume = Volume.from_array(world_grid((33, 33, 33))[0].astype(np.float32))
    _render_all(volume, Camera((0.5, 0.0, 2.0), (0.5, 0.0, 0.0)), 1.0, w=33)
    _render_all(volume, Camera((0.5, 0.0, 2.0), (0.5, 0.0, 0.0)), volume.normalized_iso(0.49), w=33)


@pytest.mark.parametrize("pitch", [0.0, 0.01, -0.01])
def test_plane_seen_edge_on(pitch):
    volume = _plane_y_volume()
    cam = orbit(17.0, pitch, 1.8)
    f = _render_all(volume, cam, volume.normalized_iso(0.0))
    hit = f["mask"] > 0
    if hit.any():  # hits, if any, are on the plane y = 0, normals along y
        voxel = volume.voxel_size_world()
        assert np.abs(f["position"][hit][:, 1]).max() < 0.05 * voxel
        n_world = view_to_world(cam, f["normal"][hit].astype(np.float64))
        assert (np.abs(n_world[:, 1]) > 0.999).all()


def test_iso_on_plateau():
    """A shell whose value equals the iso exactly (a plateau): hits on its outer boundary."""
    x, y, z = world_grid((64, 64, 64))
    r = np.sqrt(x * x + y * y + z * z)
    values = np.where(r < 0.15, 1.0, np.where(r < 0.35, 0.5, 0.0)).astype(np.float32)
    volume = Volume.from_array(values)
    f = _render_all(volume, orbit(30.0, 20.0, 1.8), volume.normalized_iso(0.5))
    hit = f["mask"] > 0
    assert hit.sum() > 100
    voxel = volume.voxel_size_world()
    radius = np.linalg.norm(f["position"][hit], axis=-1)
    assert radius.min() > 0.35 - 2.0 * voxel and radius.max() < 0.35 + 0.5 * voxel


@pytest.mark.parametrize("iso_value", [7.0, 6.0, 8.0])
def test_constant_volume(iso_value):
    volume = Volume.from_array(np.full((16, 16, 16), 7.0, dtype=np.float32))
    f = _render_all(volume, orbit(30.0, 20.0, 1.8), volume.normalized_iso(iso_value))
    if iso_value != 7.0:
        assert (f["mask"] == 0).all()


@pytest.mark.parametrize("refine", ["secant", "bisection"])
def test_flat_top_with_iso_at_plateau_value(refine):
    """Field min(y, 0.1): constant above y = 0.1, iso = that maximum. The set {f >= iso} is the
    plateau, which begins at the first voxel layer at or above y = 0.1; hits lie on that layer
    seen from above. A secant step stuck at a bracket end where f == iso falls back to
    bisection, so both methods converge onto the layer."""
    n = 48
    y_axis = world_grid((n, n, n))[1]
    volume = Volume.from_array(np.minimum(y_axis, 0.1).astype(np.float32))
    layer = y_axis[0, :, 0][y_axis[0, :, 0] >= 0.1].min()
    cam = orbit(30.0, 35.0, 1.8)
    f = _render_all(volume, cam, volume.normalized_iso(0.1), refine=refine, refine_steps=8)
    hit = f["mask"] > 0
    assert hit.sum() > 100
    voxel = volume.voxel_size_world()
    step = 0.5 * voxel
    y = f["position"][hit][:, 1]
    assert y.min() > layer - 1e-3 * voxel
    assert y.max() < layer + step / 2 ** 4 + 1e-3 * voxel
    n_world = view_to_world(cam, f["normal"][hit].astype(np.float64))
    assert (n_world[:, 1] > 0.99).all()


def test_camera_inside_hollow_shape():
    """Eye at the origin inside a spherical shell (radii 0.3..0.4): every ray hits the inner wall."""
    volume = field_volume(lambda p: np.abs(np.linalg.norm(p, axis=-1) - 0.35) - 0.05)
    f = _render_all(volume, INSIDE_CAM, volume.normalized_iso(0.0))
    assert (f["mask"] == 1).all()
    assert (f["depth"] > 0).all()
    voxel = volume.voxel_size_world()
    p = f["position"].reshape(-1, 3).astype(np.float64)
    assert np.abs(np.linalg.norm(p, axis=-1) - 0.3).max() < 0.05 * voxel
    n_world = view_to_world(INSIDE_CAM, f["normal"].reshape(-1, 3).astype(np.float64))
    assert angle_deg(n_world, -p).max() < 2.0  # facing the center, where the camera is


@pytest.mark.parametrize("camera", [Camera((0.0, 0.0, 2.0), (0.0, 0.0, 3.0)),
                                    Camera((0.0, 0.0, 0.6), (0.3, 0.2, 1.5))], ids=["outside", "at-face"])
def test_camera_facing_away(sphere_volume, camera):
    f = _render_all(sphere_volume, camera, sphere_volume.normalized_iso(0.0))
    assert (f["mask"] == 0).all()
    assert (f["samples"] == 0).all()  # no ray enters the box in front of the eye


@pytest.mark.parametrize("camera, top_only", [(Camera((0.3, 1.0, 0.4), (0.0, 0.0, 0.0)), True),
                                              (orbit(20.0, 35.0, 1.8), False)], ids=["over-the-box", "orbit"])
def test_one_voxel_sheet(camera, top_only):
    """A single slice of ones in zeros (the plane y = 0), iso 0.5: the level set is the slab
    |y| = voxel / 2. Seen from above it is visible, on y = +voxel / 2, with normals along +y.
    From the "over-the-box" eye (above the top face, inside its column) every ray enters
    through the top face, so the mask is the analytic square; from the orbit some rays enter
    the slab through a side face of the box and leave it through its bottom (y = -voxel / 2)."""
    values = np.zeros((33, 33, 33), dtype=np.float32)
    values[:, 16, :] = 1.0
    volume = Volume.from_array(values)
    w, h = 48, 33
    f = _render_all(volume, camera, 0.5, w=w, h=h)
    hit = f["mask"] > 0
    voxel = volume.voxel_size_world()
    eye, dirs = pixel_rays(camera, w, h)
    t = (0.5 * voxel - eye[1]) / dirs[..., 1]
    p = eye + t[..., None] * dirs
    inside = np.maximum(np.abs(p[..., 0]), np.abs(p[..., 2]))
    expect = (t > 0) & (inside <= 0.5)
    assert expect.sum() > 200
    if top_only:
        assert not ((hit != expect) & (np.abs(inside - 0.5) > 1e-3)).any()
    else:
        assert not (expect & ~hit & (np.abs(inside - 0.5) > 1e-3)).any()
    y = f["position"][hit][:, 1]
    assert np.abs(np.abs(y) - 0.5 * voxel).max() < 0.01 * voxel
    n_world = view_to_world(camera, f["normal"][hit].astype(np.float64))
    assert (np.abs(n_world[:, 1]) > 0.999).all()
    top = y > 0
    assert top.mean() > 0.9 and (n_world[top, 1] > 0).all()  # toward the camera above


def test_two_voxel_volume():
    """2x2x2 voxels, field x: the iso 0.5 surface is the square x = 0, |y|, |z| <= 0.5."""
    values = np.zeros((2, 2, 2), dtype=np.float32)
    values[1] = 1.0
    volume = Volume.from_array(values)
    cam = orbit(60.0, 20.0, 2.0)
    w, h = 48, 33
    f = _render_all(volume, cam, 0.5, w=w, h=h)
    eye, dirs = pixel_rays(cam, w, h)
    t = -eye[0] / dirs[..., 0]
    p = eye + t[..., None] * dirs
    inside = np.maximum(np.abs(p[..., 1]), np.abs(p[..., 2]))
    expect = (t > 0) & (inside <= 0.5)
    edge = np.abs(inside - 0.5) < 1e-3
    hit = f["mask"] > 0
    assert expect.sum() > 100
    assert not ((hit != expect) & ~edge).any()
    assert np.abs(f["position"][hit][:, 0]).max() < 1e-5
    n_world = view_to_world(cam, f["normal"][hit].astype(np.float64))
    assert (n_world[:, 0] > 0.999).all()  # the camera is on the +x side


def test_anisotropic_spacing_sphere_in_world_units():
    """Spacing 1:1:10: the sphere |p| = 0.3 in world units, sampled coarsely along z."""
    volume = field_volume(lambda p: sphere_sdf(p, SPHERE_R), (64, 64, 8), (1.0, 1.0, 10.0))
    scale, _ = volume.world_transform()
    coarse, fine = scale.max(), scale.min()
    cam = orbit(30.0, 20.0, 1.2)
    w, h = 96, 72
    f = _render_all(volume, cam, volume.normalized_iso(0.0), w=w, h=h)
    eye, dirs = pixel_rays(cam, w, h)
    expect, _, miss_dist = ray_sphere(eye, dirs, SPHERE_R)
    hit = f["mask"] > 0
    assert not ((hit != expect) & (miss_dist > fine)).any()
    p = f["position"][hit].astype(np.float64)
    # Trilinear interpolation of |p| over a 0.14-long voxel deviates by ~ h^2 / (8 R): allow
    # a tenth of the coarse voxel (an isotropic mix-up of the spacing would be off by ~0.1).
    assert np.abs(sphere_sdf(p, SPHERE_R)).max() < 0.1 * coarse
    ok = hit & (miss_dist > fine)
    n_world = view_to_world(cam, f["normal"][ok].astype(np.float64))
    assert angle_deg(n_world, f["position"][ok].astype(np.float64)).max() < 6.0


def _huge_sphere_values():
    x, y, z = world_grid((32, 32, 32))
    sdf = np.sqrt(x * x + y * y + z * z) - SPHERE_R
    return (sdf / np.abs(sdf).max() * 3e38).astype(np.float32)


def test_values_near_float32_limits_render_finite():
    values = _huge_sphere_values()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        volume = Volume.from_array(values)
    assert np.isfinite(volume.data).all() and volume.data.min() >= 0 and volume.data.max() <= 1
    f = _render_all(volume, orbit(30.0, 20.0, 1.2), volume.normalized_iso(0.0))
    hit = f["mask"] > 0
    assert hit.sum() > 100
    p = f["position"][hit].astype(np.float64)
    assert np.abs(sphere_sdf(p, SPHERE_R)).max() < 0.05 * volume.voxel_size_world()


def test_values_near_float32_limits_normalize_exactly():
    values = _huge_sphere_values()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        volume = Volume.from_array(values)
    v = values.astype(np.float64)
    expect = (v - v.min()) / (v.max() - v.min())
    np.testing.assert_allclose(volume.data, expect, atol=1e-6)


@pytest.mark.parametrize("iso_value", [-5.0, 5.0])
def test_iso_outside_data_range_gives_empty_image(sphere_volume, iso_value):
    iso = sphere_volume.normalized_iso(iso_value)
    assert not 0.0 <= iso <= 1.0
    f = _render_all(sphere_volume, SPHERE_CAM, iso)
    assert (f["mask"] == 0).all()
    assert (f["samples"] == 0).all()  # no brick's value range holds the iso: all skipped


def test_nonfinite_voxels_are_replaced_and_render_finite():
    x, y, z = world_grid((32, 32, 32))
    values = (np.sqrt(x * x + y * y + z * z) - SPHERE_R).astype(np.float32)
    values[0, 0, :5] = np.nan
    values[3, 7, 9] = np.inf
    values[31, 31, 31] = -np.inf
    values[16, 16, 16] = np.nan  # inside the sphere
    with pytest.warns(UserWarning, match="NaN"):
        volume = Volume.from_array(values)
    assert np.isfinite(volume.data).all()
    assert np.isfinite(volume.value_range).all()
    f = _render_all(volume, orbit(30.0, 20.0, 1.2), volume.normalized_iso(0.0))
    assert (f["mask"] > 0).sum() > 100


# ---------------------------------------------------------------------------------------------
# 7. CPU row bands.


def test_threads_give_bit_identical_buffers(torus_volume):
    one = Renderer(torus_volume, DEVICE, threads=1)
    two = Renderer(torus_volume, DEVICE, threads=2)
    req = RenderRequest(50, 37, torus_volume.normalized_iso(0.0), outputs=ALL + ("flow",), prev_camera=FLOW_PREV,
                        ao_samples=8, ao_radius=0.2, spp=2)
    a = one.render(FLOW_CUR, req)
    b = two.render(FLOW_CUR, req)
    assert a.present() == b.present()
    for name in a.present():
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert (a.mask > 0).sum() > 100


# ---------------------------------------------------------------------------------------------
# 8. Request validation.


@pytest.mark.parametrize("field, value", [
    ("width", 0), ("width", 64.0), ("width", 100000), ("height", -1),
    ("spp", 0), ("spp", 10 ** 6), ("spp", 2.0),
    ("step", 0.0), ("step", -0.01), ("step", float("nan")), ("step", float("inf")),
    ("refine", "newton"), ("refine_steps", -1), ("refine_steps", 33),
    ("flow_fill", "telea"), ("outputs", ("mask", "bogus")), ("outputs", ()),
    ("ao_samples", 0), ("ao_radius", 0.0), ("iso", float("nan")),
])
def test_request_validation(field, value):
    kw = dict(width=32, height=32, iso=0.5)
    kw[field] = value
    name = "output" if field == "outputs" else field
    with pytest.raises(ValueError, match=name):
        RenderRequest(**kw)


def test_request_validation_non_integer_refine_steps():
    with pytest.raises(ValueError, match="refine_steps"):
        RenderRequest(32, 32, 0.5, refine_steps=2.5)
