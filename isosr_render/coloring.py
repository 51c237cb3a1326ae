"""`Coloring`: what colours the isosurface, through which colour map and range, checked in one place.

    coloring = Coloring("temperature", colormap="magma", range=(250.0, 320.0))  # a second volume, by name
    coloring = Coloring("gradient")  # the iso volume's gradient magnitude, over its own range

``by`` names the values: ``"gradient"``, the gradient magnitude of the iso volume (data units per unit of
its spacing), or another volume of the same grid (its name: a file, a catalog name, a procedural spec).
The values at each pixel's hit map to ``t = (v - lo) / (hi - lo)`` clamped to [0, 1], and ``t`` to a
colour by the map's stops, piecewise linear; ``lo == hi`` colours everything with the map's middle.
The categorical ``labels`` map ignores the range: label ``v`` (rounded) takes stop ``v mod 10``,
sampled at the nearest voxel (no blend of two labels). :class:`isosr_render.color_field.ColorField`
puts the values on the device and samples them.

numpy only (the protocol validates with it, without torch or Warp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GRADIENT = "gradient"
# Colour maps: RGB stops in [0, 1] (viridis and magma at t = 0, 1/8, ..., 1; labels: tab10).
COLORMAPS = {
    "viridis": ((0.267, 0.005, 0.329), (0.279, 0.175, 0.483), (0.230, 0.322, 0.546), (0.173, 0.449, 0.558),
                (0.128, 0.567, 0.551), (0.158, 0.684, 0.502), (0.369, 0.789, 0.383), (0.678, 0.864, 0.190),
                (0.993, 0.906, 0.144)),
    "magma": ((0.001, 0.000, 0.014), (0.113, 0.065, 0.277), (0.317, 0.072, 0.485), (0.513, 0.148, 0.508),
              (0.716, 0.215, 0.475), (0.904, 0.320, 0.388), (0.987, 0.536, 0.382), (0.997, 0.770, 0.535),
              (0.987, 0.991, 0.750)),
    "gray": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    "labels": ((0.122, 0.467, 0.706), (1.000, 0.498, 0.055), (0.173, 0.627, 0.173), (0.839, 0.153, 0.157),
               (0.580, 0.404, 0.741), (0.549, 0.337, 0.294), (0.890, 0.467, 0.761), (0.498, 0.498, 0.498),
               (0.737, 0.741, 0.133), (0.090, 0.745, 0.812)),
}
# Maps whose stops are categories (a label's colour), not a ramp.
CATEGORICAL = ("labels",)


@dataclass(frozen=True)
class Coloring:
    """What colours the surface (module docstring).

    Attributes:
        by: ``"gradient"`` or the name of a volume of the iso volume's grid.
        colormap: one of :data:`COLORMAPS`.
        range: ``(lo, hi)`` in the values' units, finite, ``lo <= hi``; None: the values' own range.
    """

    by: str
    colormap: str = "viridis"
    range: tuple[float, float] | None = None

    def __post_init__(self):
        if not isinstance(self.by, str) or not self.by.strip():
            raise ValueError(f"coloring.by must be {GRADIENT!r} or a volume's name, got {self.by!r}")
        if self.colormap not in COLORMAPS:
            raise ValueError(f"coloring.colormap must be one of {', '.join(COLORMAPS)}, got {self.colormap!r}")
        if self.range is not None:
            try:
                lo, hi = (float(v) for v in self.range)
            except (TypeError, ValueError):
                raise ValueError(f"coloring.range must be two numbers (lo, hi), got {self.range!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise ValueError(f"coloring.range must be finite with lo <= hi, got {self.range!r}")
            object.__setattr__(self, "range", (lo, hi))

    @property
    def stops(self) -> tuple[tuple[float, float, float], ...]:
        """The colour map's RGB stops."""
        return COLORMAPS[self.colormap]

    @property
    def categorical(self) -> bool:
        """Whether the map colours labels (nearest voxel, ``v mod 10``) rather than a range."""
        return self.colormap in CATEGORICAL
