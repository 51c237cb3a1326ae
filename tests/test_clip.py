"""Clip planes, the crop box and caps (isosr_render.clip) against analytic references.

The sphere SDF (radius 0.3, 64^3; its inside is below the iso, so caps are ``"below"``) cut by
planes: the expected hits come from the ray-sphere and ray-plane intersections in float64.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import DEVICE, field_volume, pixel_rays, render_np, sphere_sdf
from isosr_render.camera import Camera, orbit
from isosr_render.clip import MAX_PLANES, Clip
from isosr_render import kernels
from isosr_render.renderer import Renderer, RenderRequest, clip_args

W, H = 48, 40
OUTS = ("mask", "normal", "depth", "ao", "cap", "color")
EYE = Camera((0.0, 0.0, 2.0))
# Keeps z <= 0.1: the sphere's front cap is cut away (a plane through its inside).
CUT = ((0.0, 0.0, 0.1), (0.0, 0.0, -1.0))


@pytest.fixture(scope="module")
def renderer(sphere_volume):
    return Renderer(sphere_volume, DEVICE, threads=2)


def _request(renderer, clip, **kw):
    return RenderRequest(W, H, renderer.volume.normalized_iso(0.0), kw.pop("outputs", OUTS), clip=clip,
                         ao_samples=8, **kw)


def _sphere_roots(eye, dirs, radius=0.3):
    """Both ray parameters where the rays meet the sphere (nan where they miss)."""
    b = dirs @ eye
    disc = b * b - (eye @ eye - radius * radius)
    root = np.sqrt(np.where(disc > 0, disc, np.nan))
    return -b - root, -b + root, np.abs(disc)


def _finite(frame):
    for name, a in frame.items():
        assert np.isfinite(a).all(), name


# ---------------------------------------------------------------------------------------------
# Settings


@pytest.mark.parametrize("kwargs, field", [
    ({"planes": [((0, 0, 0), (0, 0, 1))] * (MAX_PLANES + 1)}, "clip.planes"),
    ({"planes": [((0, 0, 0), (0, 0, 0))]}, "clip.planes[0].normal"),
    ({"planes": [((0, 0, 0), (0, 0, 1)), ((0, math.nan, 0), (0, 0, 1))]}, "clip.planes[1].point"),
    ({"planes": [((0, 0, 0), (0, math.inf, 1))]}, "clip.planes[0].normal"),
    ({"planes": [((0, 0), (0, 0, 1))]}, "clip.planes[0].point"),
    ({"box": ((0, 0, 0), (1, -1, 1))}, "clip.box"),
    ({"box": ((0, 0, math.nan), (1, 1, 1))}, "clip.box.lo"),
    ({"cap": "inside"}, "clip.cap"),
])
def test_bad_settings_are_refused_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
        Clip(**kwargs)


def test_normals_are_stored_unit_length():
    clip = Clip(planes=[((1, 2, 3), (0, 3, 4))])
    assert clip.planes == (((1.0, 2.0, 3.0), (0.0, 0.6, 0.8)),)
    np.testing.assert_allclose(clip.plane_rows()[0], [0.0, 0.6, 0.8, -(1.2 + 2.4)])
    assert not Clip().active and not Clip(cap="above").capped and Clip(box=((0,) * 3, (0,) * 3)).active


# ---------------------------------------------------------------------------------------------
# Primary rays


@pytest.mark.parametrize("cap", ["none", "below"])
def test_sphere_cut_by_a_plane(renderer, cap):
    """Where a ray enters the kept half-space before the sphere, it hits the sphere; where it enters
    it inside the sphere, it hits the cut face (cap) or, open, the sphere's far wall from inside."""
    camera = orbit(25.0, 15.0, 2.0)
    plane = ((0.05, -0.02, 0.08), (-0.3, 0.2, -1.0))
    clip = Clip(planes=[plane], cap=cap)
    frame = render_np(renderer, camera, _request(renderer, clip))
    _finite(frame)
    eye, dirs = pixel_rays(camera, W, H)
    (p, n) = clip.planes[0]
    dn = dirs @ np.asarray(n)
    t_plane = -(eye - np.asarray(p)) @ np.asarray(n) / dn  # the rays enter the kept side there (dn > 0)
    assert (dn > 0).all()
    t_a, t_b, disc = _sphere_roots(eye, dirs)
    on_sphere = t_a >= t_plane
    inside = (t_a < t_plane) & (t_b > t_plane)
    t_ref = np.where(on_sphere, t_a, np.where(inside, t_plane if cap == "below" else t_b, np.nan))
    forward = -camera.basis()[2]
    depth_ref = t_ref * (dirs @ forward)
    # Away from the silhouette and the rim where the plane meets the sphere (there a pixel may go either way).
    rim = np.abs(sphere_sdf(eye + t_plane[..., None] * dirs)) < 0.02
    clear = ~np.isnan(disc) & (disc > 0.01) & ~rim
    hit_ref = ~np.isnan(t_ref)
    assert (frame["mask"][clear] == hit_ref[clear]).all()
    both = clear & hit_ref
    assert both.sum() > 120 and (both & inside).sum() > 40, (both.sum(), (both & inside).sum())
    step = renderer.default_step()
    np.testing.assert_allclose(frame["depth"][both], depth_ref[both], atol=0.25 * step)
    capped = both & inside & (cap == "below")
    np.testing.assert_allclose(frame["depth"][capped], depth_ref[capped], atol=1e-5)
    # The cut face's normal is the plane's, turned to the camera, in view space.
    n_view = camera.basis() @ -np.asarray(n)
    np.testing.assert_allclose(frame["normal"][capped], np.broadcast_to(n_view, frame["normal"][capped].shape),
                               atol=1e-5)
    # The cap buffer: the pixels on the cut face and the SDF's normalized value there.
    assert ((frame["cap"][..., 0] == 1.0) == capped)[clear].all()
    if cap == "below":
        p_cap = eye + t_plane[capped][:, None] * dirs[capped]
        lo, hi = renderer.volume.value_range
        v = (sphere_sdf(p_cap) - lo) / (hi - lo)
        np.testing.assert_allclose(frame["cap"][capped][:, 1], v, atol=2e-3)
        assert (frame["ao"][capped] == 1.0).all(), "a cut face looks into the removed half-space"


def test_central_ray_depths(renderer):
    """Camera on +z: the sphere from 1.7, the cut plane at z = 0.1 from 1.9, the far wall from 2.3."""
    open_, capped = (render_np(renderer, EYE, _request(renderer, Clip(planes=[CUT], cap=c), outputs=("mask", "depth")))
                     for c in ("none", "below"))
    plain = render_np(renderer, EYE, _request(renderer, Clip(), outputs=("mask", "depth")))
    c = (H // 2, W // 2)
    step = renderer.default_step()
    assert abs(plain["depth"][c] - 1.7) < 0.25 * step
    assert abs(open_["depth"][c] - 2.3) < 0.25 * step
    assert abs(capped["depth"][c] - 1.9) < 1e-5


def test_supersampled_caps_cover_a_share_of_the_hits(renderer):
    frame = render_np(renderer, EYE, _request(renderer, Clip(planes=[CUT], cap="below"), spp=4))
    _finite(frame)
    assert (frame["cap"][..., 0] <= frame["mask"] + 1e-6).all()
    edge = (frame["cap"][..., 0] > 0) & (frame["cap"][..., 0] < frame["mask"])
    assert edge.any(), "pixels on the cut's rim mix the face and the surface"


def test_crop_box_cuts_like_its_six_planes(renderer):
    lo, hi = (-0.2, -0.15, -0.1), (0.1, 0.2, 0.15)
    planes = [((lo[a],) * 3, tuple(float(i == a) for i in range(3))) for a in range(3)]
    planes += [((hi[a],) * 3, tuple(-float(i == a) for i in range(3))) for a in range(3)]
    camera = orbit(35.0, 25.0, 2.0)
    box = render_np(renderer, camera, _request(renderer, Clip(box=(lo, hi), cap="below")))
    six = render_np(renderer, camera, _request(renderer, Clip(planes=planes, cap="below")))
    _finite(box)
    assert box["mask"].sum() > 100
    for name in ("mask", "depth", "cap"):
        np.testing.assert_allclose(box[name], six[name], atol=1e-5, err_msg=name)
    np.testing.assert_allclose(box["normal"], six["normal"], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Grazing and degenerate cases: empty frames, never NaN


@pytest.mark.parametrize("clip", [
    Clip(box=((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), cap="below"),  # a box of zero volume
    Clip(box=((-0.2, -0.2, 0.0), (0.2, 0.2, 0.0)), cap="below"),  # a flat box through the solid: no faces
    Clip(planes=[((0, 0, 0.2), (0, 0, 1)), ((0, 0, -0.2), (0, 0, -1))], cap="below"),  # disjoint half-spaces
    Clip(planes=[((0, 0, 0.3), (0, 0, 1))], cap="below"),  # tangent, keeping the outside
    Clip(planes=[((0, 0, 2.0), (0, 0, 1))], cap="below"),  # through the camera, keeping what is behind it
])
def test_clips_that_keep_nothing_give_an_empty_frame(renderer, clip):
    frame = render_np(renderer, EYE, _request(renderer, clip))
    _finite(frame)
    assert frame["mask"].sum() <= 1.0  # at most a grazing pixel at the tangent point
    assert (frame["cap"] == 0).all() or frame["mask"].sum() > 0


def test_tangent_plane_and_camera_planes_keep_the_sphere(renderer):
    plain = render_np(renderer, EYE, _request(renderer, Clip()))
    for clip in (Clip(planes=[((0, 0, 0.3), (0, 0, -1))], cap="below"),  # tangent, keeping the sphere
                 Clip(planes=[((0, 0, 2.0), (0, 0, -1))], cap="below"),  # through the camera, the scene kept
                 Clip(box=((-1, -1, -1), (1, 1, 3)), cap="below")):  # the camera inside the kept box
        frame = render_np(renderer, EYE, _request(renderer, clip))
        _finite(frame)
        assert np.abs(frame["mask"] - plain["mask"]).sum() <= 1.0
        np.testing.assert_allclose(frame["depth"], plain["depth"], atol=1e-5)


def test_a_plane_along_the_view_direction(renderer):
    """A plane through the camera that holds the view direction: the rays on its kept side see the
    sphere as without it, the others nothing; a central column of rays would graze it."""
    plain = render_np(renderer, EYE, _request(renderer, Clip()))
    frame = render_np(renderer, EYE, _request(renderer, Clip(planes=[(EYE.eye, (1.0, 0.0, 0.0))], cap="below")))
    _finite(frame)
    right = np.arange(W) >= W // 2
    np.testing.assert_array_equal(frame["mask"][:, ~right], 0.0)
    np.testing.assert_allclose(frame["depth"][:, right], plain["depth"][:, right], atol=1e-5)
    assert (frame["cap"] == 0).all()


# ---------------------------------------------------------------------------------------------
# AO


def test_ao_sees_only_kept_occluders():
    """A small sphere beside a big one shadows its top; a plane that removes the small one leaves the
    big one's AO exactly as without it."""
    def big(p):
        return sphere_sdf(p, 0.2)

    def pair(p):
        return np.minimum(big(p), sphere_sdf(p - np.array([0.36, 0.0, 0.0]), 0.12))

    camera = Camera((1.0, 0.0, 1.7))  # sees the big sphere's side that faces the small one
    iso_of = {}
    frames = {}
    for name, fn, clip in (("big", big, Clip()), ("pair", pair, Clip()),
                           ("cut", pair, Clip(planes=[((0.22, 0, 0), (-1, 0, 0))]))):
        volume = field_volume(fn)
        r = Renderer(volume, DEVICE, threads=2)
        iso_of[name] = volume.normalized_iso(0.0)
        frames[name] = render_np(r, camera, RenderRequest(W, H, iso_of[name], ("mask", "depth", "ao"), ao_samples=64,
                                                          ao_radius=0.4, clip=clip))
    hit = frames["big"]["mask"] > 0
    same = hit & (np.abs(frames["pair"]["depth"] - frames["big"]["depth"]) < 1e-6)  # the small one not in front
    assert (frames["pair"]["ao"][same] < frames["big"]["ao"][same] - 0.1).sum() > 10
    np.testing.assert_array_equal(frames["cut"]["mask"][hit], 1.0)
    np.testing.assert_allclose(frames["cut"]["ao"][hit], frames["big"]["ao"][hit], atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Unused, clipping costs no march work


def test_no_clip_is_a_no_op(renderer):
    """The default clip adds no work to the march: the same samples and buffers as a box around it all."""
    camera = orbit(30.0, 20.0, 1.8)
    outs = ("mask", "normal", "depth", "samples")
    plain = render_np(renderer, camera, _request(renderer, Clip(), outputs=outs))
    boxed = render_np(renderer, camera, _request(renderer, Clip(box=((-5,) * 3, (5,) * 3)), outputs=outs))
    for name in outs:
        np.testing.assert_array_equal(plain[name], boxed[name], err_msg=name)
    # Without a clip, a plan runs the plain kernels (NoClip: compiled as before clipping) and stages no clip.
    plan = renderer.plan(_request(renderer, Clip(), outputs=outs))
    assert not plan.clipped and isinstance(plan._clip, kernels.NoClip.cls)
    assert kernels.frame_kernels(False)["first_hit_kernel"].module is not kernels.frame_kernels(True)[
        "first_hit_kernel"].module
    region = clip_args(Clip(planes=[CUT], box=((-1,) * 3, (1,) * 3), cap="above"))["region"][0]
    assert (region["count"], region["boxed"], region["cap"]) == (1, 1, 1)


def test_a_plan_clips_each_frame_as_staged(renderer):
    """A clipping plan's recorded launches read the clip staged per frame (as a CUDA graph replays them):
    frames of one plan with other planes match fresh renders of those."""
    cuts = [Clip(planes=[CUT], cap="below"), Clip(planes=[((0.0, 0.05, 0.0), (0.0, 1.0, 0.0))], cap="below"),
            Clip(box=((-0.2,) * 3, (0.1, 0.2, 0.15)), cap="below")]
    camera = orbit(30.0, 20.0, 1.8)
    plan = renderer.plan(_request(renderer, cuts[0]))
    for clip in cuts:
        request = _request(renderer, clip)
        staged = {k: v.copy() for k, v in plan.render(camera, request).to_numpy().items()}
        fresh = render_np(renderer, camera, request)
        for name in ("mask", "depth", "cap"):
            np.testing.assert_array_equal(staged[name], fresh[name], err_msg=name)
    with pytest.raises(ValueError, match="clipped"):
        plan.render(camera, _request(renderer, Clip()))
