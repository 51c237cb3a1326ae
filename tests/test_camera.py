"""Camera: the matrices agree with each other and with `project`; bad cameras fail clearly."""

from __future__ import annotations

import numpy as np
import pytest

from isosr_render.camera import Camera, orbit


def test_view_and_projection_matrices_reproduce_project():
    cam = Camera(eye=(0.4, 0.3, 1.5), target=(0.05, -0.1, 0.0), up=(0.0, 1.0, 0.0), fov_y=35.0)
    w, h = 160, 90
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (50, 3))
    clip = (cam.projection_matrix(w, h) @ cam.view_matrix() @ np.c_[points, np.ones(50)].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    pixels = np.stack([(ndc[:, 0] + 1) * 0.5 * w, (1 - ndc[:, 1]) * 0.5 * h], axis=-1)
    expect, depth = cam.project(points, w, h)
    np.testing.assert_allclose(pixels, expect, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(clip[:, 3], depth, rtol=1e-12)  # w_clip = -z_view = depth
    assert (np.abs(ndc[:, 2]) <= 1).all()


def test_view_matrix_is_a_rigid_transform_that_puts_the_eye_at_the_origin_looking_down_minus_z():
    cam = orbit(40.0, 25.0, 2.0)
    view = cam.view_matrix()
    np.testing.assert_allclose(view[:3, :3] @ view[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(view @ np.r_[cam.eye, 1.0], [0, 0, 0, 1], atol=1e-12)
    target_view = view @ np.r_[cam.target, 1.0]
    np.testing.assert_allclose(target_view[:3], [0, 0, -2.0], atol=1e-12)


def test_orbit_distance_and_pitch():
    cam = orbit(0.0, 30.0, 1.5, target=(0.1, 0.0, 0.0))
    assert np.isclose(np.linalg.norm(np.subtract(cam.eye, cam.target)), 1.5)
    assert np.isclose(cam.eye[1], 1.5 * np.sin(np.radians(30.0)))


@pytest.mark.parametrize("kwargs, message", [
    (dict(eye=(0, 0, 0), target=(0, 0, 0)), "coincide"),
    (dict(eye=(0, 2, 0), target=(0, 0, 0), up=(0, 1, 0)), "parallel"),
    (dict(fov_y=0.0), "fov_y"),
    (dict(fov_y=180.0), "fov_y"),
    (dict(eye=(0, float("nan"), 2)), "eye"),
    (dict(target=(0, float("inf"), 0)), "target must be 3 finite"),
    (dict(up=(0, 10 ** 400, 0)), "up must be 3 finite"),  # past float's range
    (dict(eye="123"), "eye must be 3 finite"),  # a string is not three numbers, though its characters are
    (dict(eye=(1, 2)), "eye must be 3 finite"),
    (dict(eye=[[0, 0, 2]]), "eye must be 3 finite"),
    (dict(eye=None), "eye must be 3 finite"),
    (dict(eye=(0, 0, 1e300), up=(5e-324, 5e-324, 0)), "parallel"),  # a subnormal up: no unit axes from it
    (dict(eye=(1.7e308, 0, 0), target=(-1.7e308, 0, 0)), "too far apart"),  # each finite, their distance not
])
def test_bad_cameras_raise_with_the_reason(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Camera(**kwargs)


def test_extreme_but_valid_cameras_have_an_orthonormal_basis():
    for camera in (Camera(eye=(0, 0, 1e300), up=(0, 1e-9, 0)), Camera(eye=(3e5, -2e5, 1e5), up=(1e-6, 1, 0))):
        basis = camera.basis()
        assert np.isfinite(basis).all(), camera
        np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("pitch, distance", [(90.0, 1.0), (-95.0, 1.0), (10.0, 0.0)])
def test_bad_orbits_raise(pitch, distance):
    with pytest.raises(ValueError):
        orbit(0.0, pitch, distance)
