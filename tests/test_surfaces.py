"""Several isosurfaces (isosr_render.surfaces) against analytic references.

The field is the distance from the origin (64^3): its isos 0.3 and 0.4 are two nested spheres. From outside,
every ray stops on the outer one; from an eye between them (radius 0.36), rays towards the centre stop on the
inner sphere's near side and the others on the outer sphere from inside. Hits from the ray-sphere roots in
float64.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DEVICE, field_volume, pixel_rays, render_np

from isosr_render.camera import Camera
from isosr_render.clip import Clip
from isosr_render.picking import Pick, pick
from isosr_render.renderer import Renderer, RenderRequest
from isosr_render.surfaces import MAX_SURFACES, Surface, Surfaces

W, H = 40, 32
OUTER, INNER = 0.4, 0.3  # radii = data values of the isos
RED, BLUE = (0.9, 0.1, 0.1), (0.1, 0.2, 0.9)
OUTSIDE = Camera((0.0, 0.0, 1.5))
BETWEEN = Camera((0.0, 0.0, 0.36), target=(0.3, 0.0, 0.2))


@pytest.fixture(scope="module")
def renderer():
    return Renderer(field_volume(lambda p: np.linalg.norm(p, axis=-1)), DEVICE, threads=2)


def _surfaces(renderer, *pairs) -> Surfaces:
    return Surfaces.of([(renderer.volume.normalized_iso(v), *rest) for v, *rest in pairs])


def _request(surfaces, outputs=("mask", "depth", "surface", "albedo", "color"), **kw) -> RenderRequest:
    return RenderRequest(W, H, surfaces.iso, outputs, surfaces=surfaces, **kw)


def _roots(camera, radius):
    """Both ray-sphere roots per pixel (nan where the ray misses), the rays' forward cosine, and the discriminant."""
    eye, dirs = pixel_rays(camera, W, H)
    b = dirs @ eye
    disc = b * b - (eye @ eye - radius * radius)
    root = np.sqrt(np.where(disc > 0, disc, np.nan))
    return -b - root, -b + root, dirs @ -camera.basis()[2], disc


def _finite(frame):
    for name, a in frame.items():
        assert np.isfinite(a).all(), name


def test_outer_sphere_hides_the_inner(renderer):
    # User order outer first: the kernels' table is ascending (inner first), so the index is mapped back.
    surfaces = _surfaces(renderer, (OUTER, RED), (INNER, BLUE))
    frame = render_np(renderer, OUTSIDE, _request(surfaces))
    _finite(frame)
    t_near, _, forward, disc = _roots(OUTSIDE, OUTER)
    clear = np.abs(disc) > 0.01  # away from the silhouette
    hit = ~np.isnan(t_near)
    assert (frame["mask"][clear] == hit[clear]).all() and (hit & clear).sum() > 200
    step = renderer.default_step()
    np.testing.assert_allclose(frame["depth"][hit & clear], (t_near * forward)[hit & clear], atol=0.25 * step)
    assert (frame["surface"][hit & clear] == 0).all() and (frame["surface"][~hit & clear] == -1).all()
    np.testing.assert_allclose(frame["albedo"][hit & clear], np.broadcast_to(RED, ((hit & clear).sum(), 3)))
    assert (frame["albedo"][frame["mask"] == 0] == 0).all()


def test_nearest_of_two_from_between(renderer):
    surfaces = _surfaces(renderer, (OUTER, RED), (INNER, BLUE))
    frame = render_np(renderer, BETWEEN, _request(surfaces))
    _finite(frame)
    inner, _, forward, disc_in = _roots(BETWEEN, INNER)
    _, outer_exit, _, _ = _roots(BETWEEN, OUTER)  # the eye is inside: the outer sphere's far root
    on_inner = ~np.isnan(inner)
    clear = np.abs(disc_in) > 0.01
    assert (frame["mask"] == 1).all()
    assert on_inner[clear].sum() > 100 and (~on_inner & clear).sum() > 100
    ref = np.where(on_inner, inner, outer_exit) * forward
    step = renderer.default_step()
    np.testing.assert_allclose(frame["depth"][clear], ref[clear], atol=0.25 * step)
    np.testing.assert_array_equal(frame["surface"][clear], np.where(on_inner, 1, 0)[clear])
    np.testing.assert_allclose(frame["albedo"][clear & on_inner], np.broadcast_to(BLUE, ((clear & on_inner).sum(), 3)))


def test_several_rays_per_pixel(renderer):
    surfaces = _surfaces(renderer, (OUTER, RED), (INNER, BLUE))
    frame = render_np(renderer, BETWEEN, _request(surfaces, spp=4))
    _finite(frame)
    inner, _, _, disc_in = _roots(BETWEEN, INNER)
    clear = np.abs(disc_in) > 0.02
    np.testing.assert_array_equal(frame["surface"][clear], np.where(np.isnan(inner), 0, 1)[clear])


def test_one_surface_as_the_plain_iso(renderer):
    iso = renderer.volume.normalized_iso(OUTER)
    plain = render_np(renderer, OUTSIDE, RenderRequest(W, H, iso, ("mask", "normal", "depth", "ao"), ao_samples=8))
    one = render_np(renderer, OUTSIDE, _request(Surfaces((Surface(iso, RED),)), ("mask", "normal", "depth", "ao"),
                                                ao_samples=8))
    for name in plain:
        np.testing.assert_allclose(one[name], plain[name], atol=1e-6, err_msg=name)


@pytest.mark.parametrize("values", [(-5.0, 9.0), (0.4, 9.0)])
def test_isos_outside_the_range(renderer, values):
    """Isos outside the data (0 to ~0.87) hit nothing: an empty frame where all are, never NaN."""
    surfaces = _surfaces(renderer, *((v, RED) for v in values))
    frame = render_np(renderer, OUTSIDE, _request(surfaces))
    _finite(frame)
    if values[0] < 0:
        assert (frame["mask"] == 0).all() and (frame["surface"] == -1).all()
    else:
        assert set(np.unique(frame["surface"])) == {-1.0, 0.0}


def test_bad_surfaces_refused_naming_the_field():
    with pytest.raises(ValueError, match=f"1 to {MAX_SURFACES}"):
        Surfaces.of([(0.1 * i, RED) for i in range(5)])
    with pytest.raises(ValueError, match=r"surfaces\[1\]\.color"):
        Surfaces.of([(0.1, RED), (0.2, (0.1, float("nan"), 0.2))])
    with pytest.raises(ValueError, match=r"surfaces\[0\]\.iso"):
        Surfaces.of([(float("inf"), RED)])
    with pytest.raises(ValueError, match=r"surfaces\[0\]\.color"):
        Surfaces.of([(0.1, (1.0, 2.0, 0.0))])
    with pytest.raises(ValueError, match="must differ"):
        Surfaces.of([(0.1, RED), (0.1, BLUE)])
    surfaces = Surfaces.of([(0.1, RED), (0.2, BLUE)])
    with pytest.raises(ValueError, match="first surface"):
        RenderRequest(W, H, 0.2, surfaces=surfaces)
    with pytest.raises(ValueError, match="surface output needs"):
        RenderRequest(W, H, 0.2, ("surface",))


# -- translucency ---------------------------------------------------------------------------------------------


def test_translucent_outer_shows_the_inner_behind(renderer):
    """Outer at 30%: the first layer is the outer sphere, the second the inner one where the ray meets it, else
    the outer's far side; the colour composites both."""
    surfaces = _surfaces(renderer, (OUTER, RED, 0.3), (INNER, BLUE))
    assert surfaces.layers == 2
    frame = renderer.render(OUTSIDE, _request(surfaces, ("mask", "depth", "surface", "color")))
    behind = frame.behind.to_numpy()
    front = frame.to_numpy()
    _finite(front)
    _finite(behind)
    outer_near, outer_far, forward, disc_out = _roots(OUTSIDE, OUTER)
    inner_near, _, _, disc_in = _roots(OUTSIDE, INNER)
    on_inner = ~np.isnan(inner_near)
    clear = (disc_out > 0.01) & (np.abs(disc_in) > 0.01)
    assert (clear & on_inner).sum() > 100 and (clear & ~on_inner).sum() > 50
    step = renderer.default_step()
    np.testing.assert_allclose(front["depth"][clear], (outer_near * forward)[clear], atol=0.25 * step)
    ref = np.where(on_inner, inner_near, outer_far) * forward
    np.testing.assert_allclose(behind["depth"][clear], ref[clear], atol=0.25 * step)
    np.testing.assert_array_equal(behind["surface"][clear], np.where(on_inner, 1, 0)[clear])
    assert (behind["mask"][disc_out < -0.01] == 0).all()  # nothing in front, nothing behind
    # The colour: 0.3 of the front layer's, 0.7 of the inner's (opaque) or of the far side's at 30% over white.
    opaque = render_np(renderer, OUTSIDE, _request(_surfaces(renderer, (OUTER, RED), (INNER, BLUE)), ("color",)))
    inner = render_np(renderer, OUTSIDE, _request(_surfaces(renderer, (INNER, BLUE)), ("color",)))
    both = clear & on_inner
    np.testing.assert_allclose(front["color"][both], 0.3 * opaque["color"][both] + 0.7 * inner["color"][both],
                               atol=1e-5)


def test_opacity_zero_and_one(renderer):
    """Outer at 0: the picture is the inner sphere's alone (the outer's far side too is invisible); outer at 1 with
    a translucent inner: no ray goes on (nothing behind an opaque first hit), the opaque picture."""
    inner_alone = render_np(renderer, OUTSIDE, _request(_surfaces(renderer, (INNER, BLUE)), ("color",)))
    clear = np.abs(_roots(OUTSIDE, OUTER)[3]) > 0.01
    invisible = render_np(renderer, OUTSIDE, _request(_surfaces(renderer, (OUTER, RED, 0.0), (INNER, BLUE)),
                                                      ("color",)))
    np.testing.assert_allclose(invisible["color"][clear], inner_alone["color"][clear], atol=1e-5)
    opaque = render_np(renderer, OUTSIDE, _request(_surfaces(renderer, (OUTER, RED), (INNER, BLUE)), ("color",)))
    frame = renderer.render(OUTSIDE, _request(_surfaces(renderer, (OUTER, RED, 1.0), (INNER, BLUE, 0.5)),
                                              ("mask", "color")))
    assert float(frame.behind.mask.max()) == 0.0
    np.testing.assert_allclose(frame.color.cpu().numpy(), opaque["color"], atol=1e-6)


def test_translucent_several_rays_per_pixel(renderer):
    surfaces = _surfaces(renderer, (OUTER, RED, 0.5), (INNER, BLUE))
    frame = renderer.render(OUTSIDE, _request(surfaces, ("mask", "depth", "surface", "color"), spp=4))
    _finite(frame.to_numpy())
    _finite(frame.behind.to_numpy())
    inner_near, _, _, disc_in = _roots(OUTSIDE, INNER)
    clear = np.abs(disc_in) > 0.02
    np.testing.assert_array_equal(frame.behind.surface.cpu().numpy()[clear & ~np.isnan(inner_near)], 1)


def test_bad_opacity_refused_naming_the_field():
    with pytest.raises(ValueError, match=r"surfaces\[1\]\.opacity must be in \[0, 1\]"):
        Surfaces.of([(0.1, RED), (0.2, BLUE, float("nan"))])
    with pytest.raises(ValueError, match=r"surfaces\[0\]\.opacity"):
        Surfaces.of([(0.1, RED, 1.5)])


def test_rows_of_a_frame(renderer):
    """A frame of some rows (a focus region, a band): those rows as in the whole frame, whatever the others held."""
    surfaces = _surfaces(renderer, (OUTER, RED, 0.3), (INNER, BLUE))
    request = _request(surfaces, ("mask", "surface", "color"))
    whole = render_np(renderer, OUTSIDE, request)
    plan = renderer.plan(request)
    plan.tensors["surface"].fill_(float("nan"))
    part = plan.render(OUTSIDE, request, rows=(10, 20))
    for name in ("surface", "color"):
        np.testing.assert_allclose(getattr(part, name).cpu().numpy()[10:20], whole[name][10:20], atol=1e-6, err_msg=name)


def test_a_translucent_shell_occludes_by_its_opacity(renderer):
    """AO rays of the inner sphere (radius 0.15, past the shell 0.1 away) count a hit of the outer shell by its
    opacity: none at 0 (a sphere does not occlude itself), and at 0.5 half what they count at 0.99 (the same rays)."""
    def inner_ao(opacity):
        surfaces = _surfaces(renderer, (OUTER, RED, opacity), (INNER, BLUE))
        frame = renderer.render(OUTSIDE, _request(surfaces, ("mask", "surface", "ao"), ao_samples=32, ao_radius=0.15))
        return frame.behind.ao.cpu().numpy(), frame.behind.surface.cpu().numpy() == 1

    clear, occluded, half = inner_ao(0.0), inner_ao(0.99), inner_ao(0.5)
    on_inner = clear[1] & occluded[1] & half[1]
    assert on_inner.sum() > 100
    np.testing.assert_array_equal(clear[0][on_inner], 1.0)
    assert (occluded[0][on_inner] < 0.9).mean() > 0.9
    np.testing.assert_allclose(1.0 - half[0][on_inner], (1.0 - occluded[0][on_inner]) * 0.5 / 0.99, atol=1e-5)


# -- picking --------------------------------------------------------------------------------------------------


def _pick(renderer, surfaces, x, y, clip=Clip()):
    return pick(renderer, OUTSIDE, surfaces.iso, W, H, x, y, clip, surfaces)


@pytest.mark.parametrize("opacity", [1.0, 0.3])
def test_a_pick_lands_on_the_front_surface_and_names_it(renderer, opacity):
    """From outside, the centre pixel's ray meets the outer sphere first: the pick is there (the analytic near root)
    with the outer's index, translucent or not, though the first surface (the request's iso) is the inner one."""
    surfaces = _surfaces(renderer, (INNER, BLUE), (OUTER, RED, opacity))
    row, col = H // 2, W // 2
    found = _pick(renderer, surfaces, col + 0.5, row + 0.5)
    near, _, forward, _ = _roots(OUTSIDE, OUTER)
    assert found.hit and found.surface == 1 and not found.cap
    assert found.depth == pytest.approx(near[row, col] * forward[row, col], abs=0.25 * renderer.default_step())
    assert found.value == pytest.approx(OUTER, abs=0.01)


def test_a_pick_on_the_outer_sphere_alone_and_a_miss(renderer):
    """A pixel whose ray passes the inner sphere by and meets the outer one: the outer's; a corner misses both."""
    surfaces = _surfaces(renderer, (INNER, BLUE), (OUTER, RED))
    near, _, forward, disc_out = _roots(OUTSIDE, OUTER)
    disc_in = _roots(OUTSIDE, INNER)[3]
    row = H // 2
    col = int(np.flatnonzero((disc_out[row] > 0.01) & (disc_in[row] < -0.01))[0])
    found = _pick(renderer, surfaces, col + 0.5, row + 0.5)
    assert found.hit and found.surface == 1
    assert found.depth == pytest.approx(near[row, col] * forward[row, col], abs=0.25 * renderer.default_step())
    assert disc_out[0, 0] < 0 and _pick(renderer, surfaces, 0.5, 0.5) == Pick(False)


def test_a_picks_surface_follows_the_lists_order(renderer):
    swapped = _surfaces(renderer, (OUTER, RED), (INNER, BLUE))
    assert _pick(renderer, swapped, W / 2, H / 2).surface == 0


def test_a_pick_on_a_cut_face_names_no_surface(renderer):
    """The near half cut away, capped below the first iso (inside the outer sphere is solid): the centre pixel is
    on the cut face through the origin (depth 1.5), ``cap`` and no surface."""
    surfaces = _surfaces(renderer, (OUTER, RED), (INNER, BLUE))
    found = _pick(renderer, surfaces, W / 2, H / 2, Clip(planes=[((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))], cap="below"))
    assert found.hit and found.cap and found.surface is None
    assert found.depth == pytest.approx(1.5, abs=1e-3)


def test_a_pick_with_surfaces_not_of_its_iso_is_refused(renderer):
    surfaces = _surfaces(renderer, (INNER, BLUE), (OUTER, RED))
    with pytest.raises(ValueError, match="iso must be the first surface's"):
        pick(renderer, OUTSIDE, surfaces.items[1].iso, W, H, 0.5, 0.5, Clip(), surfaces)
