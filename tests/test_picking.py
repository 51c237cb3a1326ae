"""Picking: the isosurface point under a pixel, against analytic references (a sphere's distance
field of anisotropic spacing), and the hard cases (misses, grazing rays, the camera inside)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from isosr_render import Renderer, orbit
from isosr_render.camera import Camera
from isosr_render.clip import Clip
from isosr_render.picking import Pick, distance, pick
from isosr_render.slices import CONTOUR_RGB, slice_image
from isosr_render.volume import Volume

from conftest import DEVICE

SHAPE, SPACING, RADIUS = (40, 30, 20), (0.5, 1.0, 1.5), 6.0
CENTRE = (np.asarray(SHAPE) - 1) * np.asarray(SPACING) / 2
W, H = 64, 48


@pytest.fixture(scope="module")
def sphere():
    """The distance to the box's centre in physical units: the iso RADIUS is a sphere."""
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), -1) * np.asarray(SPACING)
    volume = Volume.from_array(np.linalg.norm(grid - CENTRE, axis=-1).astype(np.float32), spacing=SPACING)
    return Renderer(volume, DEVICE), volume.normalized_iso(RADIUS)


def test_a_pick_lies_on_the_sphere_with_the_iso_value_in_physical_units(sphere):
    renderer, iso = sphere
    hit = pick(renderer, orbit(30, 20, 1.8), iso, W, H, W / 2 + 0.5, H / 2 + 0.5)
    assert hit.hit and hit.value == pytest.approx(RADIUS, abs=0.05)
    assert math.dist(hit.position, CENTRE) == pytest.approx(RADIUS, abs=max(SPACING) / 2)
    assert hit.voxel == tuple(round(p / s) for p, s in zip(hit.position, SPACING))
    assert hit.depth > 0 and all(map(math.isfinite, hit.world))


def test_the_distance_of_two_picks_honours_the_spacing(sphere):
    """Physical distance = world distance times the box's longest physical side (the world's unit)."""
    renderer, iso = sphere
    camera = orbit(0, 0, 1.8)
    a, b = (pick(renderer, camera, iso, W, H, x, H / 2 + 0.5) for x in (W / 2 - 5.5, W / 2 + 6.5))
    longest = max((n - 1) * s for n, s in zip(SHAPE, SPACING))
    assert distance(a, b) == pytest.approx(math.dist(a.world, b.world) * longest, rel=1e-6)
    assert 0 < distance(a, b) < 2 * RADIUS


def test_misses_grazing_rays_and_a_camera_inside_stay_finite(sphere):
    renderer, iso = sphere
    assert pick(renderer, orbit(30, 20, 1.8), iso, W, H, 0.5, 0.5) == Pick(False)
    for x in np.linspace(0.5, W - 0.5, 33):  # a row across the silhouette: hits and misses, never NaN
        found = pick(renderer, orbit(30, 20, 1.8), iso, W, H, float(x), H / 2 + 0.5)
        assert not found.hit or (math.isfinite(found.value) and all(map(math.isfinite, found.position)))
    inside = Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 60.0)  # the eye at the sphere's centre
    found = pick(renderer, inside, iso, W, H, W / 2 + 0.5, H / 2 + 0.5)
    assert found.hit and found.value == pytest.approx(RADIUS, abs=0.05)


@pytest.mark.parametrize("x, y", [(-1.0, 5.0), (W, 5.0), (5.0, H + 0.5), (float("nan"), 1.0)])
def test_a_point_outside_the_view_is_refused(sphere, x, y):
    renderer, iso = sphere
    with pytest.raises(ValueError, match="lies outside the 64x48 image"):
        pick(renderer, orbit(30, 20, 1.8), iso, W, H, x, y)


def test_a_miss_has_no_distance(sphere):
    renderer, iso = sphere
    hit = pick(renderer, orbit(30, 20, 1.8), iso, W, H, W / 2 + 0.5, H / 2 + 0.5)
    with pytest.raises(ValueError, match="both picks must hit"):
        distance(hit, pick(renderer, orbit(30, 20, 1.8), iso, W, H, 0.5, 0.5))


def test_a_slice_through_the_sphere_shows_its_circle_at_the_physical_aspect(sphere):
    """Across z through the centre: x right, y down, 20 x 30 physical units (spacing 0.5, 1) scaled to
    512 rows; the iso contour is the circle of RADIUS around the centre, to a pixel and a voxel."""
    renderer, iso = sphere
    volume = renderer.volume
    k = round(CENTRE[2] / SPACING[2])
    image = slice_image(volume, 2, k, iso)
    assert image.shape == (512, round(512 * 40 * 0.5 / 30), 3) and image.dtype == np.uint8
    rows, cols = np.nonzero((image == CONTOUR_RGB).all(-1))
    scale = 512 / 30  # pixels per physical unit
    centre_at = (CENTRE[1] + 0.5) * scale, (CENTRE[0] + 0.25) * scale  # pixel centres of voxel rows, columns
    radii = np.hypot(rows + 0.5 - centre_at[0], cols + 0.5 - centre_at[1]) / scale
    dz = abs(k * SPACING[2] - CENTRE[2])
    assert len(rows) > 50 and np.abs(radii - math.sqrt(RADIUS ** 2 - dz ** 2)).max() < 1.5
    plain = slice_image(volume, 0, 0)
    assert not (plain == CONTOUR_RGB).all(-1).any() and plain.shape[0] == 512


@pytest.mark.parametrize("axis, index, words", [(3, 0, "axis"), (2, 20, r"index must be an integer in \[0, 19\]"),
                                                (0, -1, "index")])
def test_a_slice_outside_the_volume_is_refused(sphere, axis, index, words):
    with pytest.raises(ValueError, match=words):
        slice_image(sphere[0].volume, axis, index)


def test_a_pick_honours_the_clip(sphere):
    """A plane through the centre, square to the view, that removes the sphere's near half: open, the
    pick finds the far wall behind the cut; capped, the cut face (``cap``, the value there the
    volume's); a clip that removes the sphere leaves nothing to pick."""
    renderer, iso = sphere
    camera = orbit(30, 20, 1.8)
    toward = -np.asarray(camera.eye) / np.linalg.norm(camera.eye)  # keeps what lies beyond the centre
    x, y = W / 2, H / 2
    plain = pick(renderer, camera, iso, W, H, x, y)
    radius = math.dist(plain.world, (0.0, 0.0, 0.0))
    assert plain.hit and not plain.cap
    far = pick(renderer, camera, iso, W, H, x, y, Clip(planes=[((0.0, 0.0, 0.0), tuple(toward))]))
    assert far.hit and not far.cap and far.value == pytest.approx(RADIUS, abs=0.05)
    assert far.depth == pytest.approx(plain.depth + 2 * radius, abs=0.02)
    face = pick(renderer, camera, iso, W, H, x, y, Clip(planes=[((0.0, 0.0, 0.0), tuple(toward))], cap="below"))
    assert face.hit and face.cap and face.depth == pytest.approx(1.8, abs=1e-3)
    assert face.value < RADIUS / 2 and math.dist(face.world, (0.0, 0.0, 0.0)) < 0.02
    gone = Clip(planes=[((0.0, 0.0, 0.0), tuple(toward))], box=((-1.0,) * 3, (-0.5,) * 3), cap="below")
    assert pick(renderer, camera, iso, W, H, x, y, gone) == Pick(False)
