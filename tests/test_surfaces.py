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
    return Surfaces.of([(renderer.volume.normalized_iso(v), c) for v, c in pairs])


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
