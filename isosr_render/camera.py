"""A look-at perspective camera, orbit helpers and the matrices the renderer needs.

Frames and units follow :mod:`isosr_render.conventions`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``eye`` at ``target``.

    Attributes:
        eye: camera position, world frame.
        target: point the camera looks at.
        up: approximate up direction; must not be parallel to ``target - eye``.
        fov_y: vertical field of view in degrees, in (0, 180).
    """

    eye: tuple[float, float, float] = (0.0, 0.0, 2.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y: float = 40.0

    def __post_init__(self):
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _finite3(f"camera {name}", getattr(self, name)))
        if not 0.0 < self.fov_y < 180.0:
            raise ValueError(f"camera fov_y must lie in (0, 180) degrees, got {self.fov_y}")
        forward = _sub(self.target, self.eye)
        distance = math.hypot(*forward)
        if distance < 1e-12:
            raise ValueError("camera eye and target coincide")
        if not math.isfinite(distance):
            raise ValueError(f"camera eye and target are too far apart ({self.eye}, {self.target})")
        up = math.hypot(*self.up)  # at least 1e-12: the basis's axes then stay normal floats
        if up < 1e-12 or math.hypot(*_cross(_unit(forward), self.up)) < 1e-9 * up:
            raise ValueError("camera up is parallel to the viewing direction (or zero)")

    @functools.cached_property
    def _basis(self) -> np.ndarray:
        """Rows: the camera's right, up and backward (+z view) axes in world coordinates."""
        backward = _unit(_sub(self.eye, self.target))  # hypot: no overflow at extreme but valid positions
        right = _unit(_cross(self.up, backward))
        return np.array([right, _cross(backward, right), backward])

    def basis(self) -> np.ndarray:
        """Rows: the camera's right, up and backward (+z view) axes in world coordinates."""
        return self._basis.copy()

    def view_matrix(self) -> np.ndarray:
        """4x4 world-to-view matrix."""
        rot = self.basis()
        view = np.eye(4)
        view[:3, :3] = rot
        view[:3, 3] = -rot @ np.asarray(self.eye)
        return view

    def projection_matrix(self, width: int, height: int, near: float = 0.01, far: float = 10.0) -> np.ndarray:
        """4x4 OpenGL-style perspective matrix (view space to clip space, depth to [-1, 1])."""
        t = self.tan_half_fov()
        proj = np.zeros((4, 4))
        proj[0, 0] = 1.0 / (t * width / height)
        proj[1, 1] = 1.0 / t
        proj[2, 2] = -(far + near) / (far - near)
        proj[2, 3] = -2.0 * far * near / (far - near)
        proj[3, 2] = -1.0
        return proj

    def tan_half_fov(self) -> float:
        return math.tan(math.radians(self.fov_y) * 0.5)

    def project(self, points: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixel coordinates (x right, y down).

        Returns:
            ``(pixels, depth)``: pixels of shape (..., 2) and view depth ``-z_view`` of shape
            (...,). Points with depth <= 0 are behind the camera; their pixels are meaningless.
        """
        p = np.asarray(points, dtype=np.float64)
        view = self.view_matrix()
        pv = p @ view[:3, :3].T + view[:3, 3]
        depth = -pv[..., 2]
        safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
        t = self.tan_half_fov()
        aspect = width / height
        ndc_x = pv[..., 0] / (safe * t * aspect)
        ndc_y = pv[..., 1] / (safe * t)
        px = (ndc_x + 1.0) * 0.5 * width
        py = (1.0 - ndc_y) * 0.5 * height
        return np.stack([px, py], axis=-1), depth


# Camera checks on 3-tuples in plain floats (numpy on 3 values cost ~35 us a camera, made for every frame).
def _finite3(name: str, value) -> tuple[float, float, float]:
    """``value`` as 3 finite floats, or ValueError naming ``name``."""
    try:
        v = () if isinstance(value, (str, bytes)) else tuple(float(c) for c in value)
    except (TypeError, ValueError, OverflowError):
        v = ()
    if len(v) != 3 or not all(map(math.isfinite, v)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value}")
    return v


def _sub(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _cross(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _unit(a: tuple[float, ...]) -> tuple[float, float, float]:
    n = math.hypot(*a)
    return a[0] / n, a[1] / n, a[2] / n


def orbit(yaw: float, pitch: float, distance: float, target=(0.0, 0.0, 0.0), fov_y: float = 40.0) -> Camera:
    """A camera on a sphere around ``target``, world +y up.

    Args:
        yaw: degrees around +y, 0 looks from +z.
        pitch: degrees above the xz plane, in (-90, 90).
        distance: distance from ``target``, positive.
    """
    if not -90.0 < pitch < 90.0:
        raise ValueError(f"orbit pitch must lie in (-90, 90) degrees, got {pitch}")
    if not distance > 0:
        raise ValueError(f"orbit distance must be positive, got {distance}")
    y, p = math.radians(yaw), math.radians(pitch)
    offset = (distance * math.cos(p) * math.sin(y), distance * math.sin(p), distance * math.cos(p) * math.cos(y))
    return Camera(tuple(t + o for t, o in zip(target, offset)), tuple(target), (0.0, 1.0, 0.0), fov_y)


def orbit_path(frames: int, yaw0: float = 0.0, yaw_step: float = 2.0, pitch: float = 20.0,
               distance: float = 1.8, fov_y: float = 40.0) -> list[Camera]:
    """A smooth orbit: ``frames`` cameras, ``yaw_step`` degrees apart."""
    return [orbit(yaw0 + i * yaw_step, pitch, distance, fov_y=fov_y) for i in range(frames)]
