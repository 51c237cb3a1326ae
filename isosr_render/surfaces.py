"""`Surfaces`: several isosurfaces in one frame, each with a colour, checked in one place.

    surfaces = Surfaces.of([(0.3, (0.9, 0.75, 0.65)), (0.6, (1.0, 1.0, 0.9))])  # (normalized iso, RGB)
    frame = renderer.render(camera, RenderRequest(640, 480, surfaces.iso, ("color",), surfaces=surfaces))

Each ray stops at its nearest crossing of any of the iso-values (:mod:`isosr_render.kernels`: a compile-time
variant, so that a one-iso request runs the plain kernels); the frame's ``surface`` buffer says which surface
each pixel shows (its index in :attr:`Surfaces.items`, -1 where nothing is hit) and its ``albedo`` that
surface's colour, which shading and every frame method use as a coloring's. With several rays per pixel the
``surface`` is that of the pixel's first ray that hits.

numpy only (the protocol validates with it, without torch or Warp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from isosr_render.conventions import MATERIAL_RGB

# The most isosurfaces one frame shows.
MAX_SURFACES = 4
# Colours of surfaces given without one, in turn: the material's, then red, blue and green tones.
PALETTE = (MATERIAL_RGB, (0.80, 0.36, 0.30), (0.30, 0.52, 0.80), (0.45, 0.70, 0.40))


@dataclass(frozen=True)
class Surface:
    """One isosurface: its iso-value (normalized [0, 1] scale, as ``RenderRequest.iso``) and colour (RGB in [0, 1])."""

    iso: float
    color: tuple[float, float, float] = MATERIAL_RGB


@dataclass(frozen=True)
class Surfaces:
    """Up to :data:`MAX_SURFACES` isosurfaces of distinct iso-values (module docstring).

    Raises:
        ValueError: none or too many, an iso or colour channel not finite, a colour outside [0, 1] or
            two equal isos; the message names the field (``surfaces[i].color``).
    """

    items: tuple[Surface, ...]

    def __post_init__(self):
        items = tuple(self.items)
        if not 1 <= len(items) <= MAX_SURFACES:
            raise ValueError(f"surfaces: 1 to {MAX_SURFACES} isosurfaces, got {len(items)}")
        checked = []
        for i, s in enumerate(items):
            iso = float(s.iso)
            if not math.isfinite(iso):
                raise ValueError(f"surfaces[{i}].iso must be finite, got {s.iso!r}")
            try:
                color = tuple(float(c) for c in s.color)
            except (TypeError, ValueError):
                raise ValueError(f"surfaces[{i}].color must be three numbers (RGB), got {s.color!r}") from None
            if len(color) != 3 or not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in color):
                raise ValueError(f"surfaces[{i}].color must be three numbers in [0, 1] (RGB), got {s.color!r}")
            checked.append(Surface(iso, color))
        isos = [s.iso for s in checked]
        if len(set(np.float32(isos).tolist())) != len(isos):
            raise ValueError(f"surfaces: the iso-values must differ, got {isos}")
        object.__setattr__(self, "items", tuple(checked))

    @classmethod
    def of(cls, pairs) -> Surfaces:
        """Surfaces from ``(iso, color)`` pairs."""
        return cls(tuple(Surface(iso, color) for iso, color in pairs))

    @property
    def iso(self) -> float:
        """The first surface's iso: a request's ``iso`` (what clip caps and a single-iso consumer read)."""
        return self.items[0].iso

    def order(self) -> list[int]:
        """The surfaces' indices by ascending iso: the kernels' table order (:meth:`table`)."""
        return sorted(range(len(self.items)), key=lambda i: self.items[i].iso)

    def table(self, pad: float) -> np.ndarray:
        """The isos ascending as float32, :data:`MAX_SURFACES` of them, padded with ``pad`` (above any value)."""
        values = np.full(MAX_SURFACES, pad, np.float32)
        values[:len(self.items)] = [self.items[i].iso for i in self.order()]
        return values
