"""Meshes out: marching cubes of a sphere's distance field (anisotropic spacing) against its area,
volume and radius, the ray-cast surface, the file formats, the limits, clipped meshes and `isosr mesh`;
meshes made in slabs (the server's device-thread jobs) equal to the whole volume's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from isosr_cli.main import main
from isosr_render import Renderer, orbit
from isosr_render.clip import Clip
from isosr_render.steps import count_steps, finish_steps
from isosr_render.mesh import MESH_FORMATS, MESH_SLAB_VOXELS, Mesh, MeshTooLarge, _cut_one, _slabs, extract_mesh, mesh_steps, write_mesh
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


def edge_uses(mesh: Mesh) -> np.ndarray:
    """How many triangles each of the mesh's edges bounds."""
    edges = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(edges, axis=0, return_counts=True)[1]


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
    uses = edge_uses(half)
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
    half, ends = _cut_one(square, np.array([0.0, -1.0, 0.0, 1.0]))  # keeps x <= y: the diagonal 0-2 on the plane
    assert half.faces.tolist() == [[0, 1, 2]] and half.vertices.tolist() == [[0, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert ends.tolist() == [[0, -1], [2, -1], [3, -1]]  # all the square's own: no new vertex
    corner, _ = _cut_one(square, np.array([0.0, -1.0, -1.0, -1.0]))  # only vertex 0 kept, on the plane
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


# ---- slabs --------------------------------------------------------------------------------------


def canonical(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mesh``'s vertices and normals in sorted order and its faces on them, each rotated to start
    at its least vertex (the winding kept) and sorted: equal for meshes equal up to ordering."""
    order = np.lexsort(np.concatenate([mesh.vertices, mesh.normals], axis=1).T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    faces = rank[mesh.faces]
    faces = np.take_along_axis(faces, (np.argmin(faces, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    return mesh.vertices[order], mesh.normals[order], faces[np.lexsort(faces.T[::-1])]


def in_slabs(volume: Volume, iso: float, planes: int, clip: Clip = Clip()) -> Mesh:
    """The mesh made in slabs of ``planes`` z planes (at least two: the bound is in voxels)."""
    return finish_steps(mesh_steps(volume, iso, DEVICE, clip=clip,
                                   slab_voxels=planes * volume.shape[0] * volume.shape[1]))


def assert_same_mesh(slabbed: Mesh, whole: Mesh) -> None:
    assert len(slabbed.faces) == len(whole.faces) > 0
    for a, b in zip(canonical(slabbed), canonical(whole)):
        assert np.array_equal(a, b)


def closed(mesh: Mesh) -> bool:
    return set(edge_uses(mesh)) == {2}


@pytest.mark.parametrize("clip", [Clip(), HALF, Clip(HALF.planes, cap="below"), Clip(HALF.planes, cap="above"),
                                  Clip(box=((-0.5, -0.5, -0.5), (0.0, 0.5, 0.5))),
                                  Clip(planes=HALF.planes + (((0.05, 0.0, 0.0), (-1.0, 0.3, 0.2)),))],
                         ids=["whole", "cut", "capped below", "capped above", "box", "two planes"])
def test_slabs_give_the_whole_volumes_mesh(sphere, clip):
    """Slabs of 2, 3 and 7 planes (the anisotropic sphere's 20 planes: many shared, one slab short)
    weld to the whole volume's mesh: the same vertices, normals and faces up to ordering."""
    volume, iso, _ = sphere
    whole = extract_mesh(volume, iso, DEVICE, clip=clip)
    assert len(_slabs(volume.shape, MESH_SLAB_VOXELS)) == 1  # extract_mesh: the whole volume at once here
    for planes in (2, 3, 7):
        slabbed = in_slabs(volume, iso, planes, clip)
        assert_same_mesh(slabbed, whole)
        assert len(np.unique(slabbed.vertices, axis=0)) == len(slabbed.vertices), "a vertex left twice"
    if clip == Clip() or clip.cap == "below":  # (above: the outside, open at the volume's faces)
        assert closed(whole)


def test_slabs_weld_a_surface_through_voxels_on_their_shared_planes():
    """The hard case: the iso equal to voxel values, on the planes slabs share: a rounded distance
    field (its iso on whole voxels, rings of them on every plane) and a field rising with z whose
    surface is a shared plane itself (vertices where the crossing ends). Marching cubes makes a vertex
per crossed edge, so edges ending in one such voxel give coincident vertices: the whole volume's
as many as the slabs'."""
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in (12, 10, 13)], indexing="ij"), -1).astype(np.float64)
    rounded = Volume.from_array(np.rint(np.linalg.norm(grid - (5.5, 4.5, 6.0), axis=-1)).astype(np.float32))
    rising = Volume.from_array(grid[..., 2].astype(np.float32), spacing=(1.0, 2.0, 0.5))
    for volume, iso in ((rounded, rounded.normalized_iso(4.0)), (rising, rising.normalized_iso(4.0))):
        iso = float(volume.data[0, 0, 6]) if volume is rising else iso
        assert (volume.data == np.float32(iso)).any()
        whole = extract_mesh(volume, iso, DEVICE)
        for planes in (2, 3, 4):  # plane 6 (and 4) shared by two slabs in each
            assert_same_mesh(in_slabs(volume, iso, planes), whole)
        assert closed(whole) == (volume is rounded)


@pytest.mark.parametrize("shape", [(2, 2, 2), (2, 3, 2), (3, 2, 3)])
def test_tiny_volumes_fewer_planes_than_a_slab(shape):
    data = np.zeros(shape, np.float32)
    data[0, 0, 0] = 1.0
    volume = Volume.from_array(data, spacing=(0.5, 1.0, 2.0))
    whole = extract_mesh(volume, 0.5, DEVICE)
    assert len(whole.faces) == 1
    assert_same_mesh(in_slabs(volume, 0.5, 2), whole)
    assert np.allclose(whole.vertices, [[0.25, 0, 0], [0, 0.5, 0], [0, 0, 1.0]])


def cylinder(n: int) -> Volume:
    """An ``n``-cube volume of a cylinder's distance field along z: its surface crosses every slab."""
    x, y = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    radius = np.hypot(x - (n - 1) / 2, y - (n - 1) / 2)
    return Volume.from_array(np.repeat(radius[:, :, None], n, axis=2).astype(np.float32))


def test_a_mesh_is_made_in_steps_a_slab_each_and_refused_before_any_is_built():
    """64^3 in slabs of 8 planes (7 cells each): 9 slabs, a step each to count the crossed cells,
    then a step each to mesh them; over the triangle limit it raises after the counting steps."""
    volume = cylinder(64)
    iso = volume.normalized_iso(20.0)
    steps, mesh = count_steps(mesh_steps(volume, iso, DEVICE, slab_voxels=64 * 64 * 8))
    assert len(_slabs(volume.shape, 64 * 64 * 8)) == 9 and steps == 18 and len(mesh.faces) > 0
    assert len(mesh.faces) == len(extract_mesh(volume, iso, DEVICE).faces)
    refused = mesh_steps(volume, iso, DEVICE, max_triangles=100, slab_voxels=64 * 64 * 8)
    for _ in range(9):
        next(refused)
    with pytest.raises(MeshTooLarge, match="more triangles than the limit of 100"):
        next(refused)
