"""`ColorField`: a :class:`~isosr_render.coloring.Coloring`'s values on the device, sampled at the hits.

    field = ColorField.of(Coloring("temperature"), volume, open_volume("temperature.nii.gz"), "cuda")
    frame = renderer.render(camera, RenderRequest(640, 480, iso, ("color",), coloring=field))  # frame.albedo too

The values (data units, float32) live on the device for as long as the field: one float32 copy of
the volume. A pixel's albedo is the colour of the values at its ``position`` buffer, trilinear (the
voxels are point samples at the grid's nodes: ``align_corners=True``); with several rays per pixel
that is the mean hit, an approximation of the mean of the rays' colours that differs only where a
pixel's rays hit far apart (silhouettes, creases).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from isosr_render.coloring import GRADIENT, Coloring
from isosr_render.volume import Volume


class ColorField:
    """A coloring's values on a device (module docstring); equal only to itself (a frame stream's key).

    Attributes:
        coloring: what colours the surface.
        lo, hi: the range mapped to the colour map (the coloring's, else the values' own).
    """

    def __init__(self, coloring: Coloring, values: torch.Tensor, scale, offset):
        """Use :meth:`of`. ``values`` indexed ``[x, y, z]``; ``world = voxel * scale + offset``."""
        self.coloring = coloring
        # grid_sample's coordinate in [-1, 1] per axis: voxel / (n - 1) * 2 - 1, with voxel = (world - offset) / scale.
        a = 2.0 / ((np.asarray(values.shape) - 1.0) * scale)
        self._a, self._b = (torch.tensor(v, dtype=torch.float32, device=values.device) for v in (a, -offset * a - 1.0))
        self._values = values.permute(2, 1, 0).contiguous()[None, None]  # (1, 1, nz, ny, nx): grid (x, y, z)
        self.lo, self.hi = coloring.range or (float(values.min()), float(values.max()))
        self._stops = torch.tensor(coloring.stops, dtype=torch.float32, device=values.device)

    @classmethod
    def of(cls, coloring: Coloring, volume: Volume, field: Volume | None = None,
           device: torch.device | str = "cpu") -> ColorField:
        """The values of ``coloring`` for the iso ``volume``: its gradient magnitude, or ``field``'s values.

        Raises:
            ValueError: a field asked for and none given, given for the gradient, or of another grid
                (naming both shapes).
        """
        if (coloring.by == GRADIENT) != (field is None):
            raise ValueError(f"coloring by {coloring.by!r}: " + ("the gradient takes no field" if field is not None
                                                                 else "give the field's volume"))
        if field is not None and field.shape != volume.shape:
            raise ValueError(f"coloring by {coloring.by!r}: the field's grid {field.shape} is not the volume's "
                             f"{volume.shape} ({volume.name or 'the iso volume'})")
        values = data_units(field or volume, device)
        if field is None:
            values = torch.linalg.vector_norm(torch.stack(torch.gradient(values, spacing=volume.spacing)), dim=0)
        return cls(coloring, values, *volume.world_transform())

    def albedo(self, position: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The colour of the values at world points, 0 where ``mask`` is 0.

        Shape:
            position: (H, W, 3). mask: (H, W). Returns (H, W, 3).
        """
        if position.shape != (*mask.shape, 3):
            raise ValueError(f"albedo: position must be mask's shape + (3,), got {tuple(position.shape)} "
                             f"and {tuple(mask.shape)}")
        grid = (position.float() * self._a + self._b)[None, None]
        mode = "nearest" if self.coloring.categorical else "bilinear"  # bilinear on a 5D input: trilinear
        v = F.grid_sample(self._values, grid, mode=mode, padding_mode="border", align_corners=True)[0, 0, 0]
        color = self.colormap(v)
        return torch.where(mask[..., None] > 0, color, torch.zeros_like(color))

    def colormap(self, v: torch.Tensor) -> torch.Tensor:
        """Colours of values (module docstring of :mod:`isosr_render.coloring`). Shape: (...) -> (..., 3)."""
        if self.coloring.categorical:
            return self._stops[torch.remainder(torch.nan_to_num(v).round().long(), len(self._stops))]
        span = self.hi - self.lo
        t = ((v - self.lo) / span).clamp(0.0, 1.0) if span > 0 else torch.full_like(v, 0.5)
        return ramp(torch.nan_to_num(t, 0.0), self._stops)

    def legend(self) -> dict:
        """What a legend bar shows: ``by, colormap, lo, hi, stops``."""
        c = self.coloring
        return {"by": c.by, "colormap": c.colormap, "lo": self.lo, "hi": self.hi, "stops": [list(s) for s in c.stops]}


def ramp(t: torch.Tensor, stops) -> torch.Tensor:
    """Colours of ``t`` in [0, 1], piecewise linear through ``stops`` (RGB, evenly spaced; a tensor or
    a tuple of triples). Shape: (...) -> (..., 3)."""
    table = torch.as_tensor(stops, dtype=torch.float32, device=t.device)
    x = t * (len(table) - 1)
    i = x.floor().long().clamp(0, len(table) - 2)
    f = (x - i)[..., None]
    return table[i] * (1.0 - f) + table[i + 1] * f


def data_units(volume: Volume, device: torch.device | str) -> torch.Tensor:
    """The volume's values in its data units (rescale applied), float32 on ``device``, indexed ``[x, y, z]``."""
    lo, hi = volume.value_range
    return torch.from_numpy(volume.data).to(device) * (hi - lo) + lo
