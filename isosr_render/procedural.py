"""Deterministic procedural volumes: analytic SDFs, fractal clouds and metaballs.

Every generator samples its field at the voxel positions in the world frame of
``conventions`` (box centered at the origin, longest side 1), so distances are in world
units. Cloud and metaball fields are defined on that box, independent of the grid size:
``proc:cloud:7@128`` is a finer sampling of the same field as ``proc:cloud:7@64``.

Specs: ``proc:sphere``, ``proc:torus``, ``proc:cloud[:SEED]``, ``proc:metaballs[:SEED]``,
each with an optional ``@SIZE`` suffix (voxels per axis), e.g. ``proc:cloud:7@128``.

:class:`SpheresSource` is a voxel source of any size computed box by box (nothing held): a
stand-in for scans larger than memory in tests and benchmarks.
"""

from __future__ import annotations

import numpy as np

from isosr_render.conventions import world_from_voxel
from isosr_render.volume import Volume, VolumeError
from isosr_render.voxels import check_source

PROCEDURAL_NAMES = ("sphere", "torus", "cloud", "metaballs")
DEFAULT_SIZE = 64
MAX_SIZE = 512
DEFAULT_SEED = 0

# Iso-values in original data units. SDFs: the zero level set. Cloud: the density is a
# normalized fBm sum (mean 0.5) times a falloff that is 1 in the core, so 0.45 keeps the
# denser half of the core as lumpy blobs and the falloff closes them before the border.
# Metaballs: each blob is exp(-(d/r)^2), so 0.5 puts a lone blob's surface at d ~ 0.83 r.
_DEFAULT_ISO = {"sphere": 0.0, "torus": 0.0, "cloud": 0.45, "metaballs": 0.5}
_SEEDED = ("cloud", "metaballs")
_VALID = ("valid specs: proc:sphere, proc:torus, proc:cloud[:SEED], proc:metaballs[:SEED], "
          f"each with an optional @SIZE (2..{MAX_SIZE}); names: {', '.join(PROCEDURAL_NAMES)}")


def _world_axes(size: int, spacing) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World coordinates of the voxel centers per axis, shaped to broadcast to (n, n, n)."""
    scale, offset = world_from_voxel((size,) * 3, spacing)
    idx = np.arange(size, dtype=np.float32)
    x, y, z = (idx * np.float32(s) + np.float32(o) for s, o in zip(scale, offset))
    return x[:, None, None], y[None, :, None], z[None, None, :]


def sphere_sdf(size: int = DEFAULT_SIZE, radius: float = 0.3, center=(0.0, 0.0, 0.0),
               spacing=(1.0, 1.0, 1.0)) -> Volume:
    """Signed distance to a sphere, in world units; the surface is at original value 0.

    The analytic reference is ``|p - center| - radius`` at the world position ``p`` of each
    voxel, so ``volume.normalized_iso(0.0)`` is the normalized iso of the exact sphere.

    Args:
        size: voxels per axis.
        radius: sphere radius in world units.
        center: sphere center in world units.
        spacing: voxel spacing; anisotropic spacing stretches the box, not the sphere.

    Returns:
        The volume, named ``proc:sphere@SIZE``.

    Shape:
        data: (size, size, size).
    """
    x, y, z = _world_axes(size, spacing)
    cx, cy, cz = (np.float32(c) for c in center)
    dist = np.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) - np.float32(radius)
    return Volume.from_array(dist, spacing, f"proc:sphere@{size}")


def torus_sdf(size: int = DEFAULT_SIZE, major: float = 0.3, minor: float = 0.1,
              spacing=(1.0, 1.0, 1.0)) -> Volume:
    """Signed distance to a torus around the z axis, in world units; surface at value 0.

    The analytic reference is ``sqrt((sqrt(x^2 + y^2) - major)^2 + z^2) - minor``.

    Args:
        size: voxels per axis.
        major: distance from the z axis to the tube's center line, in world units.
        minor: tube radius in world units.
        spacing: voxel spacing.

    Returns:
        The volume, named ``proc:torus@SIZE``.

    Shape:
        data: (size, size, size).
    """
    x, y, z = _world_axes(size, spacing)
    ring = np.sqrt(x ** 2 + y ** 2) - np.float32(major)
    dist = np.sqrt(ring ** 2 + z ** 2) - np.float32(minor)
    return Volume.from_array(dist, spacing, f"proc:torus@{size}")


def _fade(t: np.ndarray) -> np.ndarray:
    """Quintic smoothstep ``6t^5 - 15t^4 + 10t^3`` (C2-continuous interpolation weight)."""
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _upsample_axis(lattice: np.ndarray, t: np.ndarray, axis: int) -> np.ndarray:
    """Interpolate ``lattice`` along ``axis`` at lattice coordinates ``t`` with quintic weights."""
    i0 = np.minimum(np.floor(t).astype(np.intp), lattice.shape[axis] - 2)
    w = _fade(t - i0.astype(np.float32)).reshape([-1 if a == axis else 1 for a in range(3)])
    a, b = np.take(lattice, i0, axis=axis), np.take(lattice, i0 + 1, axis=axis)
    return a + (b - a) * w


def _value_noise(rng: np.random.Generator, cells: int, size: int) -> np.ndarray:
    """Value noise in [0, 1] with ``cells`` lattice cells across the box, sampled on size^3."""
    noise = rng.random((cells + 1,) * 3, dtype=np.float32)
    t = np.linspace(0.0, cells, size, dtype=np.float32)
    for axis in range(3):
        noise = _upsample_axis(noise, t, axis)
    return noise


def cloud(seed: int, size: int = DEFAULT_SIZE, octaves: int = 5) -> Volume:
    """Smoke-like density: fractal value noise times a soft falloff toward the border.

    Octave ``k`` has ``3 * 2^k`` lattice cells across the box and weight ``0.5^k``; the
    weighted sum is normalized to [0, 1] (mean 0.5). The falloff is 1 within world radius
    0.2 of the center and drops smoothly to 0 at radius 0.5 (the faces' centers), so the
    isosurface at ``default_iso("cloud")`` forms blobs that stay inside the box.

    Args:
        seed: seed of ``np.random.default_rng`` for the lattice values.
        size: voxels per axis.
        octaves: number of noise octaves.

    Returns:
        The volume, named ``proc:cloud:SEED@SIZE``.

    Shape:
        data: (size, size, size).
    """
    rng = np.random.default_rng(seed)
    weights = 0.5 ** np.arange(octaves, dtype=np.float32)
    density = np.zeros((size,) * 3, dtype=np.float32)
    for k, weight in enumerate(weights):
        density += weight * _value_noise(rng, 3 * 2 ** k, size)
    density /= weights.sum()
    x, y, z = _world_axes(size, (1.0, 1.0, 1.0))
    r = np.clip((np.sqrt(x ** 2 + y ** 2 + z ** 2) - 0.2) / 0.3, 0.0, 1.0)
    density *= 1.0 - r * r * (3.0 - 2.0 * r)
    return Volume.from_array(density, (1.0, 1.0, 1.0), f"proc:cloud:{seed}@{size}")


def metaballs(seed: int, size: int = DEFAULT_SIZE, count: int = 8) -> Volume:
    """Sum of Gaussian blobs ``exp(-(|p - c| / r)^2)`` at random centers and radii.

    Centers are uniform in ``[-0.25, 0.25]^3`` and radii uniform in ``[0.06, 0.14]`` (world
    units), drawn from ``np.random.default_rng(seed)``, so blobs fade out before the border.

    Args:
        seed: seed for the blob centers and radii.
        size: voxels per axis.
        count: number of blobs.

    Returns:
        The volume, named ``proc:metaballs:SEED@SIZE``.

    Shape:
        data: (size, size, size).
    """
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-0.25, 0.25, (count, 3)).astype(np.float32)
    radii = rng.uniform(0.06, 0.14, count).astype(np.float32)
    x, y, z = _world_axes(size, (1.0, 1.0, 1.0))
    field = np.zeros((size,) * 3, dtype=np.float32)
    for (cx, cy, cz), r in zip(centers, radii):  # separable: exp(-a-b-c) = e^-a e^-b e^-c
        field += (np.exp(-((x - cx) / r) ** 2) * np.exp(-((y - cy) / r) ** 2)
                  * np.exp(-((z - cz) / r) ** 2))
    return Volume.from_array(field, (1.0, 1.0, 1.0), f"proc:metaballs:{seed}@{size}")


def _parse(spec: str) -> tuple[str, int | None, int]:
    """Split a spec into ``(kind, seed or None, size)``, raising VolumeError when invalid."""
    body, _, size_text = spec.strip().partition("@")
    parts = body.split(":")
    if len(parts) not in (2, 3) or parts[0] != "proc" or parts[1] not in PROCEDURAL_NAMES:
        raise VolumeError(f"unknown procedural volume {spec!r}; {_VALID}")
    kind, seed_text = parts[1], parts[2] if len(parts) == 3 else None
    if seed_text is not None and (kind not in _SEEDED or not seed_text.isdigit()):
        raise VolumeError(f"bad seed {seed_text!r} in {spec!r} (a non-negative integer, "
                          f"for {' and '.join(_SEEDED)} only); {_VALID}")
    if size_text and not size_text.isdigit() or size_text and not 2 <= int(size_text) <= MAX_SIZE:
        raise VolumeError(f"bad size {size_text!r} in {spec!r}; {_VALID}")
    size = int(size_text) if size_text else DEFAULT_SIZE
    return kind, None if seed_text is None else int(seed_text), size


def parse_procedural(spec: str) -> Volume:
    """Build the volume a spec such as ``proc:cloud:7@128`` names (see the module docstring).

    Seeded kinds without a seed use seed 0; the size defaults to 64 voxels per axis.

    Raises:
        VolumeError: unknown name, bad seed or bad size; the message lists the valid specs.

    Shape:
        data: (size, size, size).
    """
    kind, seed, size = _parse(spec)
    if kind == "sphere":
        return sphere_sdf(size)
    if kind == "torus":
        return torus_sdf(size)
    generator = cloud if kind == "cloud" else metaballs
    return generator(DEFAULT_SEED if seed is None else seed, size)


def default_iso(spec_or_volume_name: str) -> float:
    """A good iso-value, in original data units, for a procedural spec or volume name.

    0.0 for the SDFs (the exact surface), 0.45 for cloud and 0.5 for metaballs (see
    ``_DEFAULT_ISO`` for why).

    Raises:
        VolumeError: the name is not a procedural spec.
    """
    return _DEFAULT_ISO[_parse(spec_or_volume_name)[0]]


class SpheresSource:
    """A voxel source computed box by box: the signed distance (world units) to the nearest of a
    few seeded spheres, with a ripple, stored as ``dtype`` (integers quantize the distance range
    [-0.25, 1] over the type's range; ``rescale`` maps back to world units, so iso 0 is the surface).

    Args:
        shape: voxels (x, y, z), spacing 1.
        dtype: ``uint8``, ``uint16``, ``int16`` or ``float32``.
        seed: the spheres' seed.
        chunks: the chunk shape it reports.
        spheres: how many spheres.
    """

    def __init__(self, shape: tuple[int, int, int], dtype="uint16", seed: int = 0,
                 chunks: tuple[int, int, int] = (128, 128, 128), spheres: int = 4):
        self.shape, self.dtype, self.chunks = tuple(int(n) for n in shape), np.dtype(dtype), tuple(chunks)
        self.name = f"spheres:{seed}@{'x'.join(map(str, self.shape))}:{self.dtype.name}"
        self.spacing = (1.0, 1.0, 1.0)
        rng = np.random.default_rng(seed)
        self.centers = rng.uniform(-0.25, 0.25, (spheres, 3)).astype(np.float32)
        self.radii = rng.uniform(0.08, 0.18, spheres).astype(np.float32)
        self.axes = world_from_voxel(self.shape, self.spacing)
        self.rescale = (1.0, 0.0)
        if self.dtype.kind in "iu":
            info = np.iinfo(self.dtype)
            self.step = 1.25 / (int(info.max) - int(info.min))
            self.rescale = (self.step, -0.25 - int(info.min) * self.step)
        check_source(self)

    def read(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """The box ``[x, y, z]`` computed now."""
        scale, offset = self.axes
        p = [(np.arange(s.start, s.stop, dtype=np.float32) * np.float32(scale[a]) + np.float32(offset[a]))
             for a, s in enumerate((x, y, z))]
        px, py, pz = p[0][:, None, None], p[1][None, :, None], p[2][None, None, :]
        dist = None
        for (cx, cy, cz), r in zip(self.centers, self.radii):
            d = np.sqrt((px - cx) ** 2 + (py - cy) ** 2 + (pz - cz) ** 2) - r
            dist = d if dist is None else np.minimum(dist, d, out=dist)
        dist += np.float32(0.004) * np.sin(np.float32(60.0) * px)
        if self.dtype.kind == "f":
            return dist.astype(self.dtype)
        info = np.iinfo(self.dtype)
        stored = np.rint((dist - self.rescale[1]) / np.float32(self.step))
        return np.clip(stored, info.min, info.max).astype(self.dtype)
