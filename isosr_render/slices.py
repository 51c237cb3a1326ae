"""Orthogonal slices of a volume: the plane through a voxel across one axis, in grey levels over the
volume's range, the iso contour drawn on it, at the physical aspect (spacing honoured).

    image = slice_image(volume, axis=2, index=40, iso=volume.normalized_iso(300.0))   # (H, W, 3) uint8

Axes as the voxels index them (``[x, y, z]``): a slice across ``z`` shows x to the right and y
down, across ``y`` x and z, across ``x`` y and z.
"""

from __future__ import annotations

import cv2
import numpy as np

from isosr_render.shapes import check_int
from isosr_render.volume import Volume

AXES = ("x", "y", "z")
MAX_SLICE_SIDE = 512  # the longest side of a slice image, pixels
CONTOUR_RGB = (255, 64, 32)


def slice_image(volume: Volume, axis: int, index: int, iso: float | None = None,
                max_side: int = MAX_SLICE_SIDE) -> np.ndarray:
    """The slice of ``volume`` across ``axis`` (0, 1, 2: x, y, z) at voxel ``index``.

    Args:
        iso: normalized iso-value whose contour is drawn (None: none); outside [0, 1] no pixel
            crosses it.
        max_side: the image's longest side at most (the slice is scaled to its physical aspect).

    Raises:
        ValueError: an axis other than 0, 1, 2 or an index outside the volume.

    Shape:
        Returns (H, W, 3) uint8: rows along the plane's second axis, columns along its first.
    """
    check_int(axis, "axis", 0, 2, where="slice")
    check_int(index, "index", 0, volume.shape[axis] - 1, where=f"slice across {AXES[axis]}")
    check_int(max_side, "max_side", 2, where="slice")
    box = [slice(0, n) for n in volume.shape]
    box[axis] = slice(index, index + 1)
    plane = volume.read_normalized(*box).squeeze(axis).T  # (rows, cols)
    grey = np.clip(plane * 255.0 + 0.5, 0, 255).astype(np.uint8)
    image = np.repeat(grey[..., None], 3, axis=-1)
    if iso is not None:
        image[_crossings(plane, iso)] = CONTOUR_RGB
    spacing = [s for a, s in enumerate(volume.spacing) if a != axis]  # (columns', rows') physical step
    width, height = plane.shape[1] * spacing[0], plane.shape[0] * spacing[1]
    scale = max_side / max(width, height)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)


def _crossings(plane: np.ndarray, iso: float) -> np.ndarray:
    """Pixels on the iso contour: at or above ``iso`` with a 4-neighbour below it."""
    inside = plane >= iso
    edge = np.zeros_like(inside)
    edge[1:] |= inside[1:] != inside[:-1]
    edge[:, 1:] |= inside[:, 1:] != inside[:, :-1]
    return edge & inside
