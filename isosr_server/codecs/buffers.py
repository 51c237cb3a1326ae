"""The ``buffers`` view mode's coding: packing of the quantized codes and their decoding (numpy only,
for clients; the server quantizes on its device with :mod:`isosr_server.codecs.buffers_device`).

Per low-res buffer (conventions of :mod:`isosr_render.conventions`), in a `ViewBuffers`:
    mask   uint8 coverage ``round(255 m)``, at least 1 where ``m > 0`` (so "no hit" survives
           exactly); error <= 1/255.
    normal octahedral, 2 x uint16 per pixel; angular error < 1e-3 rad (float16 xyz: 6 bytes
           a pixel instead of 4, and 37% more after zlib); 0 where the mask is 0.
    depth  uint16, linear between the frame's nearest and farthest hit (``depth_range``);
           error <= (far - near) / 131070 (float16: relative 4.9e-4, 1e-3 at depth 2, about a
           voxel of a 1024^3 volume; 30% fewer bytes, but the network reads depth edges).
    flow   float16 pixels, clipped to +-FLOW_CLIP; error <= |flow| * 2^-11.
    Each array zlib level 1 (stdlib; zstd is not in 3.12's; level 6 saved only 4% more).
    Measured on a 480x270 low-res frame of bonsai (1080p / 4, 10% covered, Otsu iso, orbit
    30/20/1.8): 147 KB against 3.63 MB of float32 (mask 3.1 KB, normal 59 KB, depth 30 KB,
    flow 54 KB); decode 9 ms on one CPU core. A bit-packed mask would save 1.6 KB (1%) and
    lose coverage, so the mask stays uint8.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np

from isosr_server.codecs.arrays import ArrayTooBig, WireArray, decode_array, encode_array
from isosr_server.protocol import CLOSE_TOO_BIG, Limits, ProtocolError, ViewBuffers

# The largest code of the uint8 mask and of the uint16 normal and depth codes.
MASK_MAX = 255
CODE_MAX = 65535


def pack_view_buffers(mask: np.ndarray, normal: np.ndarray | None, depth: np.ndarray | None,
                      depth_range: tuple[float, float] | None, flow: np.ndarray | None) -> ViewBuffers:
    """Quantized buffers, each zlib-compressed (in parallel: zlib releases the GIL), as they travel.

    Args:
        mask: uint8 coverage codes.
        normal: uint16 octahedral codes.
        depth, depth_range: uint16 depth codes and the (near, far) they span.
        flow: float16 flow, clipped.

    Shape:
        mask, depth: (h, w). normal, flow: (h, w, 2).
    """
    arrays = {"mask": mask, "normal": normal, "depth": depth, "flow": flow}
    coded = dict(zip(arrays, _packer().map(lambda a: None if a is None else encode_array(a, True), arrays.values())))
    return ViewBuffers(**coded, depth_range=None if depth is None else (float(depth_range[0]), float(depth_range[1])))


@lru_cache(maxsize=1)
def _packer() -> ThreadPoolExecutor:
    """The threads that compress a frame's arrays side by side (made on first use)."""
    return ThreadPoolExecutor(max_workers=4, thread_name_prefix="isosr-zlib")


def octahedral_decode(code: np.ndarray) -> np.ndarray:
    """Octahedral codes to unit vectors.

    Shape:
        code: (..., 2) uint16. Returns (..., 3) float32.
    """
    xy = code.astype(np.float64) / CODE_MAX * 2 - 1
    z = 1.0 - np.abs(xy).sum(-1, keepdims=True)
    sign = np.where(xy >= 0, 1.0, -1.0)
    xy = np.where(z < 0, (1.0 - np.abs(xy[..., ::-1])) * sign, xy)
    n = np.concatenate([xy, z], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def decode_view_buffers(wire: ViewBuffers, limits: Limits) -> dict[str, np.ndarray]:
    """The float32 buffers of a `ViewBuffers`: mask, and what was sent of normal, depth, flow,
    within the tolerances in the module docstring; 0 where the mask is 0.

    Raises:
        ProtocolError: an array that does not decode, or of another dtype or shape than the
            coding's (CLOSE_BAD_MESSAGE); one over ``limits`` (CLOSE_TOO_BIG).

    Shape:
        Returns mask, depth: (h, w). normal: (h, w, 3). flow: (h, w, 2).
    """
    mask_code = _decode(wire.mask, "mask", limits, "uint8", (None, None))
    h, w = mask_code.shape
    covered = mask_code > 0
    out = {"mask": mask_code.astype(np.float32) / MASK_MAX}
    if wire.normal is not None:
        n = octahedral_decode(_decode(wire.normal, "normal", limits, "uint16", (h, w, 2)))
        out["normal"] = np.where(covered[..., None], n, 0).astype(np.float32)
    if wire.depth is not None:
        q = _decode(wire.depth, "depth", limits, "uint16", (h, w))
        near, far = wire.depth_range
        out["depth"] = np.where(covered, near + q.astype(np.float64) * ((far - near) / CODE_MAX), 0).astype(np.float32)
    if wire.flow is not None:
        out["flow"] = _decode(wire.flow, "flow", limits, "float16", (h, w, 2)).astype(np.float32)
    return out


def _decode(wire: WireArray, name: str, limits: Limits, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    try:
        return decode_array(wire, *limits.array_bounds(), (dtype,), shape)
    except ArrayTooBig as e:
        raise ProtocolError(f"buffers.{name}: {e}", CLOSE_TOO_BIG, 413) from None
    except ValueError as e:
        raise ProtocolError(f"buffers.{name}: {e}"[:200]) from None
