"""Procedural volumes: deterministic, analytic where they claim to be, and well placed in the box."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import world_grid
from isosr_render.procedural import (PROCEDURAL_NAMES, cloud, default_iso, metaballs, parse_procedural,
                                     sphere_sdf, torus_sdf)
from isosr_render.volume import VolumeError


def test_same_seed_same_volume_other_seed_other_volume():
    np.testing.assert_array_equal(cloud(3, 32).data, cloud(3, 32).data)
    assert not np.array_equal(cloud(3, 32).data, cloud(4, 32).data)
    np.testing.assert_array_equal(metaballs(5, 32).data, metaballs(5, 32).data)
    assert not np.array_equal(metaballs(5, 32).data, metaballs(6, 32).data)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (1.0, 1.0, 4.0)])
def test_sphere_is_the_world_space_signed_distance(spacing):
    volume = sphere_sdf(33, radius=0.3, spacing=spacing)
    x, y, z = world_grid(volume.shape, spacing)
    expect = np.sqrt(x ** 2 + y ** 2 + z ** 2) - 0.3
    lo, hi = volume.value_range
    np.testing.assert_allclose(volume.data * (hi - lo) + lo, expect, atol=1e-5)
    inside = volume.data < volume.normalized_iso(0.0)
    np.testing.assert_array_equal(inside, expect < 0)


def test_torus_is_the_world_space_signed_distance():
    volume = torus_sdf(33, major=0.3, minor=0.1)
    x, y, z = world_grid(volume.shape)
    expect = np.hypot(np.hypot(x, y) - 0.3, z) - 0.1
    lo, hi = volume.value_range
    np.testing.assert_allclose(volume.data * (hi - lo) + lo, expect, atol=1e-5)


@pytest.mark.parametrize("make", [lambda: cloud(1, 48), lambda: metaballs(2, 48)])
def test_noise_fields_have_a_surface_inside_the_box(make):
    volume = make()
    kind = volume.name.split(":")[1]
    iso = volume.normalized_iso(default_iso(f"proc:{kind}"))
    d = volume.data
    assert np.isfinite(d).all() and d.min() >= 0 and d.max() <= 1
    inside = d >= iso
    assert 0.01 < inside.mean() < 0.5
    border = np.concatenate([a.ravel() for a in (inside[0], inside[-1], inside[:, 0], inside[:, -1],
                                                  inside[:, :, 0], inside[:, :, -1])])
    assert border.mean() < 0.1


@pytest.mark.parametrize("spec, name, size", [("proc:sphere", "proc:sphere@64", 64),
                                              ("proc:torus@24", "proc:torus@24", 24),
                                              ("proc:cloud", "proc:cloud:0@64", 64),
                                              ("proc:cloud:7@32", "proc:cloud:7@32", 32),
                                              ("proc:metaballs:2@16", "proc:metaballs:2@16", 16)])
def test_parse_procedural(spec, name, size):
    volume = parse_procedural(spec)
    assert volume.name == name and volume.shape == (size, size, size)


@pytest.mark.parametrize("spec", ["proc:cube", "proc:sphere:3", "proc:cloud:x", "proc:cloud@1", "proc:cloud@99999",
                                  "sphere", "proc:cloud:1:2"])
def test_bad_specs_list_the_valid_ones(spec):
    with pytest.raises(VolumeError) as e:
        parse_procedural(spec)
    assert all(n in str(e.value) for n in PROCEDURAL_NAMES)
