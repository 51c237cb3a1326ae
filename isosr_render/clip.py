"""`Clip`: the planes and the crop box that cut the volume, in world units, checked in one place.

    clip = Clip(planes=(((0.0, 0.0, 0.1), (0.0, 0.0, 1.0)),), box=((-0.4,) * 3, (0.4,) * 3), cap="below")
    request = RenderRequest(256, 256, iso, clip=clip)

A plane ``(point, normal)`` keeps the half-space its normal points into, ``dot(x - point, normal)
>= 0``; the box keeps ``lo <= x <= hi``; what is kept is their intersection, a convex region, so
a ray crosses it in one interval. Primary rays march only that interval, and AO rays count only
occluders in it (a cut casts no shadow of what it removed).

Capping: where a ray enters the kept region through a plane or a box face at a point inside the
solid (``cap="above"``: values at or above the iso are solid, as bone in a CT; ``"below"``: values
below it, as inside a signed distance), it hits the cut face: depth on the face, normal the face's
turned to the camera, and the ``cap`` buffer holds the volume's value there for the colour map
(:func:`isosr_render.shading.shade`).

numpy only (the protocol validates with it, without torch or Warp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Most planes a clip holds (the kernels' fixed plane table has this many rows).
MAX_PLANES = 6
# Which side of the iso is solid, for capping; "none": no caps (the cut surface stays open).
CAP_MODES = ("none", "above", "below")

Vec3 = tuple[float, float, float]


def _vec3(value, name: str) -> Vec3:
    """``value`` as three finite floats, else ValueError naming ``name``."""
    try:
        v = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be three numbers, got {value!r}") from None
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise ValueError(f"{name} must be three finite numbers, got {value!r}")
    return v


@dataclass(frozen=True)
class Clip:
    """Clip planes and a crop box, world units (module docstring); the default clips nothing.

    Attributes:
        planes: up to :data:`MAX_PLANES` ``(point, normal)`` pairs; normals are stored unit length.
        box: ``(lo, hi)`` corners of the kept box, ``lo <= hi`` per axis (a flat box keeps nothing
            of volume), or None.
        cap: one of :data:`CAP_MODES`.
    """

    planes: tuple[tuple[Vec3, Vec3], ...] = ()
    box: tuple[Vec3, Vec3] | None = None
    cap: str = "none"

    def __post_init__(self):
        planes = tuple(self.planes)
        if len(planes) > MAX_PLANES:
            raise ValueError(f"clip.planes: at most {MAX_PLANES} planes, got {len(planes)}")
        unit = []
        for i, plane in enumerate(planes):
            if len(plane) != 2:
                raise ValueError(f"clip.planes[{i}] must be a (point, normal) pair, got {plane!r}")
            point = _vec3(plane[0], f"clip.planes[{i}].point")
            normal = _vec3(plane[1], f"clip.planes[{i}].normal")
            length = math.sqrt(sum(c * c for c in normal))
            if not length > 1e-12 or not math.isfinite(length):
                raise ValueError(f"clip.planes[{i}].normal must be a nonzero vector, got {plane[1]!r}")
            unit.append((point, tuple(c / length for c in normal)))
        object.__setattr__(self, "planes", tuple(unit))
        if self.box is not None:
            if len(self.box) != 2:
                raise ValueError(f"clip.box must be a (lo, hi) pair, got {self.box!r}")
            lo, hi = _vec3(self.box[0], "clip.box.lo"), _vec3(self.box[1], "clip.box.hi")
            if any(a > b for a, b in zip(lo, hi)):
                raise ValueError(f"clip.box: lo must not exceed hi on any axis, got lo {lo} and hi {hi}")
            object.__setattr__(self, "box", (lo, hi))
        if self.cap not in CAP_MODES:
            raise ValueError(f"clip.cap must be one of {CAP_MODES}, got {self.cap!r}")

    @property
    def active(self) -> bool:
        """Whether anything is cut away."""
        return bool(self.planes) or self.box is not None

    @property
    def capped(self) -> bool:
        """Whether rays may hit cut faces (and the ``cap`` buffer means anything)."""
        return self.active and self.cap != "none"

    def plane_rows(self) -> np.ndarray:
        """The planes as rows ``(normal, -dot(normal, point))`` (kept where ``dot(row, (x, 1)) >= 0``),
        padded with zero rows to :data:`MAX_PLANES`.

        Shape:
            Returns (MAX_PLANES, 4) float64.
        """
        rows = np.zeros((MAX_PLANES, 4))
        for i, (point, normal) in enumerate(self.planes):
            rows[i, :3] = normal
            rows[i, 3] = -float(np.dot(normal, point))
        return rows

    def half_spaces(self) -> np.ndarray:
        """Every half-space kept, the planes' then the box's six faces, as rows ``(normal, offset)``:
        ``dot(row, (x, 1))`` is a world point's signed distance into it (kept where ``>= 0``).

        Shape:
            Returns (K, 4) float64, K = len(planes) (+ 6 with a box).
        """
        rows = [(*normal, -float(np.dot(normal, point))) for point, normal in self.planes]
        if self.box is not None:
            for axis in range(3):
                unit = np.eye(3)[axis]
                rows += [(*unit, -self.box[0][axis]), (*-unit, self.box[1][axis])]
        return np.asarray(rows, np.float64).reshape(-1, 4)

    def kept(self, points: np.ndarray) -> np.ndarray:
        """Whether world points lie in the kept region (a float64 reference of the kernels' rule).

        Shape:
            points: (..., 3). Returns (...,) bool.
        """
        p = np.asarray(points, dtype=np.float64)
        rows = self.half_spaces()
        return np.all(p @ rows[:, :3].T + rows[:, 3] >= 0.0, axis=-1)
