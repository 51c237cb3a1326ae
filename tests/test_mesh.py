"""Meshes out: marching cubes of a sphere's distance field (anisotropic spacing) against its area,
volume and radius, the ray-cast surface, the file formats, the limits, clipped meshes and `isosr mesh`."""

from __future__ import annotations

import math

import numpy as np
import pytest

from isosr_cli.main import main
from isosr_render import Renderer, orbit
from isosr_render.clip import Clip
from isosr_render.mesh import MESH_FORMATS, Mesh, _cut_one, extract_mesh, write_mesh
from isosr_render.picking import pick
from isosr_render.volume import Volume

from conftest import DEVICE

meshio = pytest.importorskip("meshio", reason="writing meshes needs meshio (the mesh extra)")

SHAPE, SPACING, RADIUS = (40, 30, 20), (0.5, 1.0, 1.5), 6.0
CENTRE = (np.asarray(SHAPE) - 1) * np.asarray(SPACING) / 2


@pytest.fixture(scope="module")
def sphere():
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), -1) * np.asarray(SPACING)
    volume = Volume.from_array(np.linalg.norm(grid - CENTRE, axis=-1).astype(np.float32), spacing=SPACING)
    iso = volume.normalized_iso(RADIUS)
    return volume, iso, extract_mesh(volume, iso, DEVICE)


def area_and_enclosed(mesh) -> tuple[float, float]:
    """The mesh's area and the volume it encloses about the sphere's centre (if closed)."""
    v, f = mesh.vertices.astype(np.float64), mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2
    return area, abs(np.einsum("ij,ij->i", a - CENTRE, np.cross(b - CENTRE, c - CENTRE)).sum()) / 6


def test_the_sphere_has_its_radius_area_and_volume_in_physical_units(sphere):
    _, _, mesh = sphere
    v = mesh.vertices.astype(np.float64)
    assert np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS).max() < max(SPACING) / 2
    area, enclosed = area_and_enclosed(mesh)
    assert area == pytest.approx(4 * math.pi * RADIUS**2, rel=0.03)
    assert enclosed == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.03)
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)
    # Values above the iso are inside: normals point to lower values, here the centre.
    assert (np.einsum("ij,ij->i", mesh.normals, v - CENTRE) < 0).mean() > 0.99


def test_ray_hits_lie_on_the_mesh_within_half_a_voxel(sphere):
    volume, iso, mesh = sphere
    renderer = Renderer(volume, DEVICE)
    hits = [p for x in range(4, 64, 3) if (p := pick(renderer, orbit(30, 20, 1.8), iso, 64, 48, x + 0.5, 24.5)).hit]
    assert len(hits) >= 4
    for hit in hits:
        nearest = np.linalg.norm(mesh.vertices - np.asarray(hit.position), axis=1).min()
        assert nearest < max(SPACING) / 2 + max(SPACING) / 2, hit  # a vertex per cell edge: half a voxel each way


@pytest.mark.parametrize("suffix", list(MESH_FORMATS))
def test_every_format_reads_back(sphere, tmp_path, suffix):
    _, _, mesh = sphere
    path = tmp_path / f"sphere{suffix}"
    write_mesh(mesh, path)
    back = meshio.read(path)
    assert sum(len(c.data) for c in back.cells if c.type == "triangle") == len(mesh.faces)
    assert np.abs(back.points.min(0) - mesh.vertices.min(0)).max() < 1e-3
    assert [p.name for p in tmp_path.iterdir()] == [path.name], "no scratch file left"


def test_limits_and_a_bad_suffix_are_refused_before_anything_is_built_or_written(sphere, tmp_path):
    volume, iso, mesh = sphere
    with pytest.raises(ValueError, match="over the limit of 1,000"):
        extract_mesh(volume, iso, DEVICE, max_voxels=1000)
    with pytest.raises(ValueError, match="more triangles than the limit of 100"):
        extract_mesh(volume, iso, DEVICE, max_triangles=100)
    with pytest.raises(ValueError, match="must end in one of .ply, .obj, .stl, .vtu"):
        write_mesh(mesh, tmp_path / "sphere.glb")
    assert not list(tmp_path.iterdir())
    assert len(extract_mesh(volume, 2.0, DEVICE).faces) == 0  # an iso past the range: no surface


def test_isosr_mesh_writes_a_file_and_refuses_no_surface(tmp_path, capsys):
    out = tmp_path / "sphere.ply"
    assert main(["mesh", "proc:sphere@32", "-o", str(out)]) == 0
    assert "triangles on cpu" in capsys.readouterr().out and len(meshio.read(out).cells[0].data) > 100
    assert main(["mesh", "proc:sphere@32", "-o", str(tmp_path / "x.glb")]) == 2
    assert "must end in one of .ply, .obj, .stl, .vtu" in capsys.readouterr().err and not (tmp_path / "x.glb").exists()


# A plane through the sphere's centre (the world origin: the grid's centre), oblique to the grid.
NORMAL = np.array([1.0, 2.0, -2.0]) / 3.0
HALF = Clip(planes=(((0.0, 0.0, 0.0), tuple(NORMAL)),))


def beyond_the_plane(mesh) -> float:
    """The farthest a vertex lies on the removed side of HALF's plane, physical units."""
    return float(max(0.0, -((mesh.vertices.astype(np.float64) - CENTRE) @ NORMAL).min()))


def test_a_plane_through_the_centre_leaves_half_the_sphere_open(sphere):
    volume, iso, whole = sphere
    half = extract_mesh(volume, iso, DEVICE, clip=HALF)
    area, _ = area_and_enclosed(half)
    assert area == pytest.approx(2 * math.pi * RADIUS**2, rel=0.03)
    assert area == pytest.approx(area_and_enclosed(whole)[0] / 2, rel=0.01)
    assert beyond_the_plane(half) < 1e-4
    rim = np.abs((half.vertices.astype(np.float64) - CENTRE) @ NORMAL) < 1e-4
    assert np.abs(np.linalg.norm(half.vertices[rim] - CENTRE, axis=1) - RADIUS).max() < max(SPACING) / 2
    # The cut shares its new vertices: every edge on the rim bounds one triangle, every other edge two.
    edges = np.sort(half.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert set(uses) == {1, 2} and (uses == 1).sum() >= rim.sum() - 1
    assert np.allclose(np.linalg.norm(half.normals, axis=1), 1.0, atol=1e-5)


def test_a_crop_box_keeps_the_surface_inside_it(sphere):
    volume, iso, whole = sphere
    scale, offset = volume.world_transform()
    box = ((-0.5, -0.5, -0.5), (0.0, 0.5, 0.5))  # world x <= 0: half the sphere
    cropped = extract_mesh(volume, iso, DEVICE, clip=Clip(box=box))
    world = cropped.vertices.astype(np.float64) * (scale / np.asarray(SPACING)) + offset
    assert world[:, 0].max() < 1e-6 and Clip(box=((-0.5,) * 3, (1e-6, 0.5, 0.5))).kept(world).all()
    assert area_and_enclosed(cropped)[0] == pytest.approx(area_and_enclosed(whole)[0] / 2, rel=0.01)


def test_a_plane_through_vertices_cuts_there_without_slivers():
    """A plane through mesh vertices (distance exactly 0) keeps them as they are: no copies, no
    triangles of no area."""
    square = Mesh(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2], [0, 2, 3]]),
                  np.tile(np.array([[0, 0, 1]], np.float32), (4, 1)))
    half = _cut_one(square, np.array([0.0, -1.0, 0.0, 1.0]))  # keeps x <= y: the diagonal 0-2 on the plane
    assert half.faces.tolist() == [[0, 1, 2]] and half.vertices.tolist() == [[0, 0, 0], [1, 1, 0], [0, 1, 0]]
    corner = _cut_one(square, np.array([0.0, -1.0, -1.0, -1.0]))  # only vertex 0 kept, on the plane
    assert len(corner.faces) == 0


def test_a_capped_cut_closes_the_half_sphere_with_a_disc(sphere):
    volume, iso, _ = sphere
    capped = extract_mesh(volume, iso, DEVICE, clip=Clip(HALF.planes, cap="below"))  # inside: below the radius
    area, enclosed = area_and_enclosed(capped)
    # Marching cubes chamfers the rim, the sharp edge of half sphere and disc, within a cell: about
    # a cell's width (up to 1.5 here) along the rim's 2 pi r, a twentieth of the area at this radius.
    assert area == pytest.approx(3 * math.pi * RADIUS**2, rel=0.07)  # the half sphere and its disc
    assert enclosed == pytest.approx(2 / 3 * math.pi * RADIUS**3, rel=0.05)
    assert beyond_the_plane(capped) < 1e-4
    edges = np.sort(capped.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    assert set(np.unique(edges, axis=0, return_counts=True)[1]) == {2}, "closed: every edge bounds two triangles"
    on = np.abs((capped.vertices.astype(np.float64) - CENTRE) @ NORMAL) < 1e-4
    assert on.sum() > 100 and np.linalg.norm(capped.vertices[on] - CENTRE, axis=1).max() < RADIUS + 0.1


def test_clips_that_keep_nothing_give_an_empty_mesh_or_name_the_box(sphere):
    volume, iso, _ = sphere
    away = Clip(planes=(((0.0, 0.0, 0.9), (0.0, 0.0, 1.0)),))  # past the volume's end
    assert len(extract_mesh(volume, iso, DEVICE, clip=away).faces) == 0
    with pytest.raises(ValueError, match=r"clip.box .* has zero volume"):
        extract_mesh(volume, iso, DEVICE, clip=Clip(box=((-0.2, 0.0, -0.2), (0.2, 0.0, 0.2))))
    inner = extract_mesh(volume, iso, DEVICE, clip=Clip(box=((-0.05,) * 3, (0.05,) * 3)))  # inside the sphere
    assert len(inner.faces) == 0


def test_isosr_mesh_takes_the_clip_options(tmp_path, capsys):
    whole, half = tmp_path / "whole.ply", tmp_path / "half.ply"
    assert main(["mesh", "proc:sphere@32", "-o", str(whole)]) == 0
    assert main(["mesh", "proc:sphere@32", "--clip-plane=0,0,0,0,0,-1", "-o", str(half)]) == 0
    points = meshio.read(half).points
    assert len(meshio.read(whole).points) > len(points) > 0
    assert main(["mesh", "proc:sphere@32", "--crop-box=0,0,0,0,0.2,0.2", "-o", str(tmp_path / "flat.ply")]) == 2
    assert "clip.box" in capsys.readouterr().err and not (tmp_path / "flat.ply").exists()
