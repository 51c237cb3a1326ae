"""What lies under a pixel: the isosurface point a view shows there, in world, voxel and physical
units, with the volume's value at it, and the distance between two such points.

    hit = pick(renderer, camera, iso, 640, 480, x=320.5, y=240.5)   # pixel centres at +0.5
    hit.position, hit.value, distance(hit, other)                   # physical units (spacing)

A pick casts the one image row through the pixel (the view's own rays, one per pixel, no AO),
so it finds the surface the frame shows at that pixel; with the view's clip
(:mod:`isosr_render.clip`) too: on the removed side it finds what lies behind, and with caps it
may land on a cut face (``cap``), where the value is the volume's there rather than the iso. With the view's
several surfaces (:mod:`isosr_render.surfaces`) it finds the nearest of them and says which (``surface``): the
front layer, so a translucent surface is picked, not what shows through it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from isosr_render.camera import Camera
from isosr_render.clip import Clip
from isosr_render.renderer import Renderer, RenderRequest
from isosr_render.shapes import check_int
from isosr_render.surfaces import Surfaces


@dataclass(frozen=True)
class Pick:
    """One pixel's isosurface point (all None but ``hit`` where its ray misses the surface).

    Attributes:
        hit: whether the pixel's ray hits the isosurface.
        world: the point in world units (the volume's box centred at 0, longest side 1).
        voxel: the nearest voxel's index (x, y, z).
        position: the point in the volume's physical units: voxel coordinates times the spacing,
            from the centre of voxel (0, 0, 0).
        value: the volume's value there (trilinear), in its data units.
        depth: the point's view-space depth, world units.
        cap: whether the point lies on a face that the clip cut (capped), not on the isosurface.
        surface: with several surfaces, the index in their list of the one hit; None without them, on a miss
            and on a cut face (shown grey by its value, not as a surface; the renderer's index there is only
            the iso nearest that value).
    """

    hit: bool
    world: tuple[float, float, float] | None = None
    voxel: tuple[int, int, int] | None = None
    position: tuple[float, float, float] | None = None
    value: float | None = None
    depth: float | None = None
    cap: bool = False
    surface: int | None = None


def pick(renderer: Renderer, camera: Camera, iso: float, width: int, height: int, x: float, y: float,
         clip: Clip = Clip(), surfaces: Surfaces | None = None) -> Pick:
    """The isosurface point under pixel coordinate ``(x, y)`` of a ``width`` x ``height`` view.

    Args:
        iso: normalized iso-value (as the view renders it; with ``surfaces``, their first's).
        x, y: pixel coordinates, x right and y down, in ``[0, width)`` and ``[0, height)``.
        clip: the view's clip planes, crop box and caps: the pick finds what the clipped view shows.
        surfaces: the view's several isosurfaces (None: the one ``iso``).

    Raises:
        ValueError: a size that is not a positive integer, a point outside the image, or what
            :class:`RenderRequest` refuses (``surfaces`` not of ``iso``).
    """
    check_int(width, "width", 1, where="the picked view")
    check_int(height, "height", 1, where="the picked view")
    if not (math.isfinite(x) and math.isfinite(y) and 0 <= x < width and 0 <= y < height):
        raise ValueError(f"pick: ({x!r}, {y!r}) lies outside the {width}x{height} image")
    row, column = int(y), int(x)
    outputs = (("mask", "position", "depth") + (("cap",) if clip.capped else ())
               + (("surface",) if surfaces is not None else ()))
    request = RenderRequest(width, height, iso, outputs, clip=clip, surfaces=surfaces)
    frame = renderer.render(camera, request, rows=(row, row + 1))  # its first layer: the front surface
    if float(frame.mask[row, column]) < 0.5:
        return Pick(False)
    on_cap = frame.cap is not None and float(frame.cap[row, column, 0]) >= 0.5
    surface = None if surfaces is None or on_cap else int(frame.surface[row, column])
    world = frame.position[row, column].double().cpu().numpy()
    volume = renderer.volume
    scale, offset = volume.world_transform()
    at = np.clip((world - offset) / scale, 0.0, np.asarray(volume.shape, np.float64) - 1.0)
    return Pick(True, tuple(world.tolist()), tuple(int(v) for v in np.rint(at)),
                tuple((at * np.asarray(volume.spacing)).tolist()), _trilinear(volume, at),
                float(frame.depth[row, column]), on_cap, surface)


def distance(a: Pick, b: Pick) -> float:
    """The physical distance between two hit picks (the volume's units, spacing honoured).

    Raises:
        ValueError: either pick missed the surface.
    """
    if not (a.hit and b.hit):
        raise ValueError("distance: both picks must hit the surface")
    return math.dist(a.position, b.position)


def _trilinear(volume, at: np.ndarray) -> float:
    """The volume's value at voxel coordinates ``at`` (inside it), trilinear, in data units."""
    low = np.minimum(np.floor(at).astype(int), np.asarray(volume.shape) - 2).clip(0)
    cube = volume.read_normalized(*(slice(i, i + 2) for i in low)).astype(np.float64)
    t = np.clip(at - low, 0.0, 1.0)
    for axis in range(3):  # collapse x, then y, then z
        cube = cube[0] * (1.0 - t[axis]) + cube[1] * t[axis]
    lo, hi = volume.value_range
    return float(lo + float(cube) * (hi - lo))
