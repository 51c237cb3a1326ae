"""Colour by a field (isosr_render.coloring, isosr_render.color_field) against analytic references.

The sphere SDF (radius 0.3, 64^3) coloured by f(p) = x on its grid: at each hit the albedo is the
colour map of the hit's x, the hit from the ray-sphere intersection in float64. The SDF's gradient
magnitude is 1 (data units per world unit: the grid's spacing here is the world's times 63).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import DEVICE, field_volume, pixel_rays
from isosr_net.methods import FrameMethod, make_runner
from isosr_render.camera import Camera, orbit
from isosr_render.color_field import ColorField
from isosr_render.coloring import COLORMAPS, Coloring
from isosr_render.renderer import Renderer, RenderRequest
from isosr_render.shading import shade

W, H = 48, 40
EYE = Camera((0.0, 0.0, 2.0))


@pytest.fixture(scope="module")
def renderer(sphere_volume):
    return Renderer(sphere_volume, DEVICE, threads=2)


@pytest.fixture(scope="module")
def x_field(sphere_volume):
    return field_volume(lambda p: p[..., 0])


def _request(renderer, coloring, **kw):
    return RenderRequest(W, H, renderer.volume.normalized_iso(0.0), kw.pop("outputs", ("mask", "normal", "color")),
                         coloring=coloring, **kw)


def _reference(stops, t):
    """The colour map in float64 (numpy's interp per channel)."""
    xs = np.linspace(0.0, 1.0, len(stops))
    return np.stack([np.interp(t, xs, np.asarray(stops)[:, c]) for c in range(3)], axis=-1)


# ---------------------------------------------------------------------------------------------
# Settings


@pytest.mark.parametrize("kwargs, says", [
    ({"by": "x", "colormap": "jet"}, "viridis, magma, gray, labels"),
    ({"by": "x", "range": (math.nan, 1.0)}, "coloring.range"),
    ({"by": "x", "range": (2.0, 1.0)}, "lo <= hi"),
    ({"by": "x", "range": (1.0,)}, "coloring.range"),
    ({"by": ""}, "coloring.by"),
])
def test_bad_settings_are_refused_naming_the_field(kwargs, says):
    with pytest.raises(ValueError, match=says.replace("(", r"\(")):
        Coloring(**kwargs)


def test_a_field_of_another_grid_is_refused_naming_both_shapes(sphere_volume):
    other = field_volume(lambda p: p[..., 0], shape=(32, 32, 48))
    with pytest.raises(ValueError, match=r"\(32, 32, 48\).*\(64, 64, 64\)"):
        ColorField.of(Coloring("other"), sphere_volume, other)
    with pytest.raises(ValueError, match="give the field's volume"):
        ColorField.of(Coloring("other"), sphere_volume)


# ---------------------------------------------------------------------------------------------
# Against the analytic reference


@pytest.mark.parametrize("spp", (1, 4))
def test_a_linear_field_on_a_sphere(renderer, sphere_volume, x_field, spp):
    field = ColorField.of(Coloring("x", "viridis", (-0.3, 0.3)), sphere_volume, x_field, DEVICE)
    frame = renderer.render(EYE, _request(renderer, field, spp=spp)).to_numpy()
    eye, dirs = pixel_rays(EYE, W, H)
    b = dirs @ eye
    disc = b * b - (eye @ eye - 0.09)
    inside = disc > 0.02  # away from the silhouette, where subpixel rays may miss
    hit = eye + (-b - np.sqrt(np.where(disc > 0, disc, 0.0)))[..., None] * dirs
    want = _reference(COLORMAPS["viridis"], (hit[..., 0] + 0.3) / 0.6)
    covered = inside & (frame["mask"] == 1)
    assert covered.sum() > 100
    # Trilinear x is exact; the error is the hit's (secant, within a voxel's fraction) through the map's slope.
    err = np.abs(frame["albedo"] - want)[covered].max()
    assert err < 0.02, err
    assert (frame["albedo"][frame["mask"] == 0] == 0).all()
    assert np.isfinite(frame["color"]).all() and frame["color"].min() >= 0 and frame["color"].max() <= 1


def test_the_gradient_of_a_distance_field_is_constant(renderer, sphere_volume):
    field = ColorField.of(Coloring("gradient", "gray"), sphere_volume, device=DEVICE)
    # Data units per unit of spacing (1 per voxel): the SDF changes by one voxel's world size per voxel.
    voxel = sphere_volume.voxel_size_world()
    frame = renderer.render(EYE, _request(renderer, field, outputs=("mask", "position"))).to_numpy()
    grid = torch.as_tensor(frame["position"], device=DEVICE)
    magnitude = torch.nn.functional.grid_sample(field._values, (grid * field._a + field._b)[None, None],
                                                align_corners=True)[0, 0, 0].cpu().numpy()
    assert np.allclose(magnitude[frame["mask"] == 1], voxel, rtol=0.03)


def test_equal_ends_give_one_colour_and_labels_take_the_nearest_voxel(renderer, sphere_volume, x_field):
    flat = ColorField.of(Coloring("x", "magma", (0.1, 0.1)), sphere_volume, x_field, DEVICE)
    albedo = renderer.render(EYE, _request(renderer, flat)).albedo
    mask = renderer.render(EYE, _request(renderer, flat)).mask
    covered = albedo[mask > 0]
    assert torch.isfinite(albedo).all() and covered.numel() and (covered == covered[0]).all()
    labels = field_volume(lambda p: np.where(p[..., 0] > 0, 3.0, 7.0))
    frame = renderer.render(EYE, _request(renderer, ColorField.of(Coloring("l", "labels"), sphere_volume, labels,
                                                                  DEVICE))).to_numpy()
    seen = {tuple(c) for c in frame["albedo"][frame["mask"] == 1]}
    assert seen == {tuple(np.float32(COLORMAPS["labels"][i])) for i in (3, 7)}


def test_the_shading_uses_the_albedo(renderer, sphere_volume, x_field):
    field = ColorField.of(Coloring("x"), sphere_volume, x_field, DEVICE)
    frame = renderer.render(EYE, _request(renderer, field, outputs=("mask", "normal", "color")))
    assert torch.equal(frame.color, shade(frame.mask, frame.normal, None, albedo=frame.albedo))
    plain = renderer.render(EYE, _request(renderer, None)).color
    assert (frame.color - plain).abs().max() > 0.1


def test_plain_frames_do_not_change(renderer):
    """Without a coloring nothing is added: no albedo, no position, the same color as shade's."""
    frame = renderer.render(EYE, _request(renderer, None))
    assert frame.present() == ["mask", "normal", "color"]
    assert torch.equal(frame.color, shade(frame.mask, frame.normal))
    with pytest.raises(ValueError, match="albedo output needs a coloring"):
        _request(renderer, None, outputs=("albedo",))


@pytest.mark.parametrize("kind", ("full", "atrous", "svgf", "upscale"))
def test_frame_methods_shade_with_the_albedo(renderer, sphere_volume, x_field, kind):
    method = FrameMethod.of(kind, **({"ao_rays": 2} if kind != "upscale" else {"factor": 2}))
    field = ColorField.of(Coloring("x"), sphere_volume, x_field, DEVICE)
    iso = sphere_volume.normalized_iso(0.0)
    colored = make_runner(method, renderer, iso, W, H, coloring=field)
    plain = make_runner(method, renderer, iso, W, H)
    cams = (orbit(20, 10, 2.0), orbit(24, 10, 2.0))
    for prev, cam in ((None, cams[0]), (cams[0], cams[1])):
        got, ref = colored.frame(cam, prev).buffers, plain.frame(cam, prev).buffers
        assert got.albedo.shape == (H, W, 3) and torch.isfinite(got.color).all()
        assert got.color.min() >= 0 and got.color.max() <= 1
        assert (got.color - ref.color).abs().max() > 0.1
