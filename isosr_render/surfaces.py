"""`Surfaces`: several isosurfaces in one frame, each with a colour, checked in one place.

    surfaces = Surfaces.of([(0.3, (0.9, 0.75, 0.65)), (0.6, (1.0, 1.0, 0.9))])  # (normalized iso, RGB)
    frame = renderer.render(camera, RenderRequest(640, 480, surfaces.iso, ("color",), surfaces=surfaces))

Each ray stops at its nearest crossing of any of the iso-values (:mod:`isosr_render.kernels`: a compile-time
variant, so that a one-iso request runs the plain kernels); the frame's ``surface`` buffer says which surface
each pixel shows (its index in :attr:`Surfaces.items`, -1 where nothing is hit) and its ``albedo`` that
surface's colour, which shading and every frame method use as a coloring's. With several rays per pixel the
``surface`` is that of the pixel's first ray that hits.

A surface of opacity below 1 is translucent: where a ray's first crossing is on one, the ray goes on to the next
crossing (of any surface, the same one's far side included), a second layer of buffers (``FrameBuffers.behind``),
and the colour is ``a * front + (1 - a) * behind`` (:func:`isosr_render.shading.composite`). At most 2 layers:
what lies behind the second is not seen.

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
    """One isosurface: its iso-value (normalized [0, 1] scale, as ``RenderRequest.iso``), colour (RGB in [0, 1])
    and opacity (in [0, 1]; below 1 translucent)."""

    iso: float
    color: tuple[float, float, float] = MATERIAL_RGB
    opacity: float = 1.0


@dataclass(frozen=True)
class Surfaces:
    """Up to :data:`MAX_SURFACES` isosurfaces of distinct iso-values (module docstring).

    Raises:
        ValueError: none or too many, an iso, colour channel or opacity not finite, a colour or opacity outside
            [0, 1] or two equal isos; the message names the field (``surfaces[i].color``).
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
            opacity = float(s.opacity)
            if not 0.0 <= opacity <= 1.0:  # NaN too
                raise ValueError(f"surfaces[{i}].opacity must be in [0, 1], got {s.opacity!r}")
            checked.append(Surface(iso, color, opacity))
        isos = [s.iso for s in checked]
        if len(set(np.float32(isos).tolist())) != len(isos):
            raise ValueError(f"surfaces: the iso-values must differ, got {isos}")
        object.__setattr__(self, "items", tuple(checked))

    @classmethod
    def of(cls, items) -> Surfaces:
        """Surfaces from ``(iso, color)`` or ``(iso, color, opacity)`` tuples."""
        return cls(tuple(Surface(*item) for item in items))

    @property
    def layers(self) -> int:
        """The layers a frame renders: 2 where a surface is translucent, else 1."""
        return 2 if any(s.opacity < 1.0 for s in self.items) else 1

    @property
    def iso(self) -> float:
        """The first surface's iso: a request's ``iso`` (what clip caps and a single-iso consumer read)."""
        return self.items[0].iso

    def order(self) -> list[int]:
        """The surfaces' indices by ascending iso: the kernels' table order (:meth:`table`)."""
        return sorted(range(len(self.items)), key=lambda i: self.items[i].iso)

    def table(self, pad: float) -> np.ndarray:
        """The kernels' table (float32): the isos ascending, :data:`MAX_SURFACES` of them padded with ``pad`` (above
        any value), then their opacities in that order (1 for the padding)."""
        values = np.ones(2 * MAX_SURFACES, np.float32)
        values[:MAX_SURFACES] = pad
        order = self.order()
        values[:len(order)] = [self.items[i].iso for i in order]
        values[MAX_SURFACES:MAX_SURFACES + len(order)] = [self.items[i].opacity for i in order]
        return values
