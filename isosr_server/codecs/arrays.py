"""Numpy arrays on the wire: ``{dtype, shape, data[, zlib]}`` (numpy and msgspec only).

dtype is one of `WIRE_DTYPES` (little-endian), ``shape`` 1 to `MAX_NDIM` sides of at least 1,
``data`` the C-order bytes, exactly ``prod(shape) * itemsize`` of them, or with ``zlib: true``
one zlib stream that inflates to exactly that many. Decoding checks the declared size against
the caller's bounds before it inflates anything, inflates at most one byte past the declared
size (a zlib bomb costs no more memory than an honest array of its shape), and refuses float
arrays that hold NaN or Inf.
"""

from __future__ import annotations

import math
import zlib
from typing import Annotated, Literal

import msgspec
import numpy as np

WIRE_DTYPES = {"float16": np.dtype("<f2"), "float32": np.dtype("<f4"), "uint8": np.dtype("u1"),
               "uint16": np.dtype("<u2")}
MAX_NDIM = 3
ZLIB_LEVEL = 1

DtypeName = Literal["float16", "float32", "uint8", "uint16"]


class WireArray(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One array as it travels (see the module docstring)."""

    dtype: DtypeName
    shape: Annotated[list[Annotated[int, msgspec.Meta(ge=1)]], msgspec.Meta(min_length=1, max_length=MAX_NDIM)]
    data: bytes
    zlib: bool = False


class ArrayTooBig(Exception):
    """A wire array declares more elements, or a longer side, than the receiver's bounds allow.

    Not a ValueError: it must pass through msgspec's decoding unwrapped, so that the protocol can
    answer it as "too big" rather than as "malformed".
    """


def encode_array(a: np.ndarray, compress: bool = False) -> WireArray:
    """``a`` as a wire array (little-endian, C order; zlib level `ZLIB_LEVEL` with ``compress``).

    Raises:
        ValueError: its dtype cannot travel (not one of `WIRE_DTYPES`, in either byte order).
    """
    a = np.asarray(a)
    name = next((n for n, dt in WIRE_DTYPES.items() if a.dtype in (dt, dt.newbyteorder("="))), None)
    if name is None:
        raise ValueError(f"dtype {a.dtype} cannot travel; use one of {', '.join(WIRE_DTYPES)}")
    data = np.ascontiguousarray(a, dtype=WIRE_DTYPES[name]).tobytes()
    if compress:
        return WireArray(name, list(a.shape), zlib.compress(data, ZLIB_LEVEL), True)
    return WireArray(name, list(a.shape), data)


def decode_array(wire: WireArray, max_elements: int, max_side: int, dtypes: tuple[str, ...] | None = None,
                 shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    """The array a wire array holds: read-only, a view of ``wire.data`` unless it was compressed.

    Args:
        wire: the decoded ``{dtype, shape, data[, zlib]}``.
        max_elements, max_side: bounds on the declared element count and on every side.
        dtypes: the dtype names accepted here (None: all of `WIRE_DTYPES`).
        shape: the expected shape, ``None`` entries free (None: any).

    Raises:
        ArrayTooBig: the declared shape exceeds ``max_elements`` or ``max_side`` (found before
            anything is inflated).
        ValueError: another dtype or shape than expected, a byte count that does not match the
            shape, zlib data that is corrupt, truncated, followed by other bytes or inflates
            past the declared size, NaN or Inf values.
    """
    dims = tuple(wire.shape)
    count = math.prod(dims)
    if count > max_elements or max(dims) > max_side:
        raise ArrayTooBig(f"declared shape {dims} of {count} elements exceeds the limits ({max_elements} elements, "
                          f"sides <= {max_side})")
    if dtypes is not None and wire.dtype not in dtypes:
        raise ValueError(f"dtype must be one of {', '.join(dtypes)}, got {wire.dtype}")
    if shape is not None and (len(dims) != len(shape) or any(s is not None and s != n for s, n in zip(shape, dims))):
        raise ValueError(f"shape must be {tuple('*' if s is None else s for s in shape)}, got {dims}")
    dtype = WIRE_DTYPES[wire.dtype]
    nbytes = count * dtype.itemsize
    data = _inflate(wire.data, nbytes) if wire.zlib else wire.data
    if len(data) != nbytes:
        raise ValueError(f"{len(data)} data bytes, but {wire.dtype} {dims} needs {nbytes}")
    a = np.frombuffer(data, dtype=dtype).reshape(dims)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError("holds NaN or Inf values")
    return a


def _inflate(data: bytes, nbytes: int) -> bytes:
    """One zlib stream that must inflate to exactly ``nbytes``; never more than ``nbytes + 1``
    bytes are inflated. ValueError for anything else."""
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(data, nbytes + 1)
    except zlib.error as e:
        raise ValueError(f"corrupt zlib data ({e})") from None
    if len(raw) > nbytes:
        raise ValueError(f"zlib data inflates past the {nbytes} bytes its shape declares")
    if not inflater.eof:  # fewer than nbytes + 1 bytes out and no end: the input ran out
        raise ValueError("truncated zlib data")
    if inflater.unused_data:
        raise ValueError(f"{len(inflater.unused_data)} bytes after the zlib stream")
    return raw
