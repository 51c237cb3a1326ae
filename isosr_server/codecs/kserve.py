"""The KServe v2 (Open Inference Protocol) infer body: JSON tensors, and Triton's binary tensor
data extension. numpy and msgspec only.

A request is a JSON object ``{id?, parameters?, inputs: [{name, shape, datatype, parameters?,
data?}], outputs?: [{name, parameters?}]}``. With the ``Inference-Header-Content-Length: N``
header the body's first N bytes are that JSON and the rest holds, in the inputs' order, the raw
little-endian bytes of every input whose parameters give ``binary_data_size``; the others carry
their values as ``data`` (a flat row-major list, or nested lists). A response is built the same
way: an output is binary when its request entry asks ``binary_data`` (else when the request's
``binary_data_output`` parameter does).

A model declares its tensors once (`ModelSpec` of `TensorSpec`): its metadata and the checks of
its requests (`ModelSpec.check`: names, shapes, value ranges, outputs) both come from that.
Triton's sequence parameters (`sequence`) name a recurrent state; custom integer parameters are
read with `int_parameter`.

Every malformed body is a `ProtocolError` (400) that names the tensor and what is wrong with it.
The body is checked against what it declares before any tensor's values are decoded: the JSON is
first read with every ``data`` kept raw (`msgspec.Raw`: skipped, not decoded), then each input's
datatype and shape (no zero dimension; within the element and side bounds the caller gives, else
413), its ``binary_data_size`` and the body's length (the binary tensors must fill it exactly),
and its raw ``data`` (numbers only, nested no deeper than the shape's rank, no more values than
the shape holds: counted on the raw bytes); only then are the values decoded. JSON nested deeper
than the decoder's depth is a 400, as is any other malformed JSON.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any

import msgspec
import numpy as np
from msgspec import Meta

from isosr_server.protocol import CLOSE_TOO_BIG, SESSION_ID, ProtocolError

HEADER_LENGTH = "inference-header-content-length"
JSON_MEDIA_TYPE = "application/json"
BINARY_MEDIA_TYPE = "application/octet-stream"
# KServe datatypes the decoder takes, as little-endian numpy types.
DATATYPES: dict[str, np.dtype] = {"FP32": np.dtype("<f4"), "FP16": np.dtype("<f2")}
MAX_RANK = 8
Parameters = dict[str, bool | int | float | str]


class TensorIn(msgspec.Struct, frozen=True):
    name: str
    shape: Annotated[list[Annotated[int, Meta(ge=0)]], Meta(max_length=MAX_RANK)]
    datatype: str
    parameters: Parameters = {}
    # Kept raw (its bytes in the body, skipped by the decoder) until the declared shape is checked.
    data: msgspec.Raw = msgspec.Raw()

    def raw_data(self) -> msgspec.Raw | None:
        """The ``data`` value's JSON bytes; None when absent or null."""
        n = len(self.data)
        return None if n == 0 or (n == 4 and bytes(self.data) == b"null") else self.data


class TensorOut(msgspec.Struct, frozen=True):
    name: str
    parameters: Parameters = {}


class RequestHeader(msgspec.Struct, frozen=True):
    inputs: list[TensorIn]
    id: str | None = None
    parameters: Parameters = {}
    outputs: list[TensorOut] | None = None


@dataclass(frozen=True)
class InferRequest:
    """A decoded request.

    Attributes:
        id: the client's request id (echoed in the response), if any.
        inputs: the input tensors by name, in the datatype they came in.
        parameters: the request's parameters (sequence ids, custom ones).
        outputs: the requested output names, each with whether it goes binary; None: all outputs,
            binary as ``binary_output`` says.
        binary_output: the request's ``binary_data_output`` parameter.
    """

    id: str | None
    inputs: dict[str, np.ndarray]
    parameters: Parameters
    outputs: dict[str, bool] | None
    binary_output: bool


def decode_request(body: bytes | bytearray, header_length: str | None, max_elements: int | None = None,
                   max_side: int | None = None) -> InferRequest:
    """The request in ``body``; ``header_length`` is the ``Inference-Header-Content-Length`` value.

    Every input is checked against what it declares before any tensor is decoded (module
    docstring): ``max_elements`` and ``max_side`` (None: unbounded) bound each input's declared
    element count and every dimension.

    Raises:
        ProtocolError: (400) the body, a tensor's shape, datatype, byte count or values do not fit;
            (413) a declared shape exceeds ``max_elements`` or ``max_side``.
    """
    if header_length is None:
        n = len(body)
    else:
        try:
            n = int(header_length)
        except ValueError:
            raise ProtocolError(f"Inference-Header-Content-Length must be an integer, got {header_length!r}"[:200])
        if not 0 <= n <= len(body):
            raise ProtocolError(f"Inference-Header-Content-Length {n} lies outside the body's {len(body)} bytes")
    try:
        header = msgspec.json.decode(memoryview(body)[:n], type=RequestHeader)
    except msgspec.DecodeError as e:
        raise ProtocolError(f"malformed inference request: {e}"[:300]) from None
    except RecursionError:  # msgspec's depth bound (the interpreter's recursion limit), not a server fault
        raise ProtocolError("malformed inference request: JSON nested too deeply") from None
    # Everything declared is checked before a tensor is decoded.
    names: set[str] = set()
    offset = n
    for t in header.inputs:
        if t.name in names:
            raise ProtocolError(f"input {t.name!r} is given twice")
        names.add(t.name)
        offset = _check_declared(t, len(body), offset, max_elements, max_side)
    if offset != len(body):
        raise ProtocolError(f"the body has {len(body) - offset} bytes beyond its binary tensors")
    inputs: dict[str, np.ndarray] = {}
    offset = n
    for t in header.inputs:
        inputs[t.name], offset = _decode_tensor(t, body, offset)
    outputs = None
    if header.outputs is not None:
        outputs = {o.name: bool(o.parameters.get("binary_data", False)) for o in header.outputs}
    return InferRequest(header.id, inputs, header.parameters, outputs,
                        bool(header.parameters.get("binary_data_output", False)))


def _check_declared(t: TensorIn, body_length: int, offset: int, max_elements: int | None,
                    max_side: int | None) -> int:
    """`ProtocolError` unless input ``t``'s datatype, shape and bytes fit (module docstring), its
    values not decoded; the offset after its binary data (``offset`` for a JSON tensor)."""
    dtype = _datatype(t)
    if 0 in t.shape:
        raise ProtocolError(f"input {t.name!r}: shape {t.shape} has a zero dimension (dimension "
                            f"{t.shape.index(0)}): a tensor must hold values"[:200])
    count = math.prod(t.shape)
    side = max(t.shape, default=1)
    if (max_elements is not None and count > max_elements) or (max_side is not None and side > max_side):
        raise ProtocolError(f"input {t.name!r}: declared shape {t.shape} of {count} elements exceeds the limits "
                            f"({max_elements} elements, sides <= {max_side})"[:200], CLOSE_TOO_BIG, 413)
    size = t.parameters.get("binary_data_size")
    raw = t.raw_data()
    if size is not None:
        if raw is not None:
            raise ProtocolError(f"input {t.name!r}: give binary_data_size or data, not both")
        if isinstance(size, bool) or not isinstance(size, int):
            raise ProtocolError(f"input {t.name!r}: binary_data_size must be an integer, got {size!r}"[:200])
        if size != count * dtype.itemsize:
            raise ProtocolError(f"input {t.name!r}: binary_data_size is {size} bytes; shape {t.shape} of "
                                f"{t.datatype} needs {count * dtype.itemsize}"[:200])
        if offset + size > body_length:
            raise ProtocolError(f"input {t.name!r}: the body ends {offset + size - body_length} bytes before its data")
        return offset + size
    if raw is None:
        raise ProtocolError(f"input {t.name!r}: no data and no binary_data_size")
    depth, values = _scan_data(raw)
    if depth is None:
        raise ProtocolError(f"input {t.name!r}: data must be numbers (a flat list or nested lists of one shape)")
    if depth > len(t.shape):
        raise ProtocolError(f"input {t.name!r}: data nested {depth} deep; shape {t.shape} allows lists nested "
                            f"at most {len(t.shape)} deep"[:200])
    if values > count:
        raise ProtocolError(f"input {t.name!r}: {values} values for shape {t.shape} ({count} values)"[:200])
    return offset


def _datatype(t: TensorIn) -> np.dtype:
    dtype = DATATYPES.get(t.datatype)
    if dtype is None:
        raise ProtocolError(f"input {t.name!r}: datatype must be {' or '.join(DATATYPES)}, got {t.datatype!r}"[:200])
    return dtype


# Per byte of a JSON value: +1 opening a list or object, -1 closing one.
_NESTING = np.zeros(256, np.int8)
_NESTING[[ord("["), ord("{")]] = 1
_NESTING[[ord("]"), ord("}")]] = -1
_SCAN_CHUNK = 1 << 20


def _scan_data(raw: msgspec.Raw) -> tuple[int | None, int]:
    """``(deepest nesting, values)`` of a tensor's raw ``data`` (valid JSON: the decoder checked
    its syntax when it skipped it), counted on its bytes in chunks without decoding them; a depth
    of None when it is no list or holds strings. ``values`` is one more than its commas: the
    number of values of nested lists, none of them empty."""
    a = np.frombuffer(raw, np.uint8)
    if a[0] != ord("["):
        return None, 0
    depth = deepest = commas = 0
    for i in range(0, len(a), _SCAN_CHUNK):
        chunk = a[i:i + _SCAN_CHUNK]
        if (chunk == ord('"')).any():
            return None, 0
        commas += int(np.count_nonzero(chunk == ord(",")))
        levels = np.cumsum(_NESTING[chunk], dtype=np.int32)
        deepest = max(deepest, depth + int(levels.max()))
        depth += int(levels[-1])
    return deepest, commas + 1


def _decode_tensor(t: TensorIn, body: bytes | bytearray, offset: int) -> tuple[np.ndarray, int]:
    """One input tensor, checked by `_check_declared`: from the body's bytes at ``offset`` (binary)
    or from its ``data``; the next offset."""
    dtype = _datatype(t)
    count = math.prod(t.shape)
    size = t.parameters.get("binary_data_size")
    if size is not None:
        return _finite(t.name, np.frombuffer(body, dtype, count, offset).reshape(t.shape)), offset + size
    try:
        values = np.asarray(msgspec.json.decode(t.raw_data()), dtype)
    except (ValueError, TypeError, RecursionError):
        raise ProtocolError(f"input {t.name!r}: data must be numbers (a flat list or nested lists of one shape)")
    if values.size != count:
        raise ProtocolError(f"input {t.name!r}: {values.size} values for shape {t.shape} ({count} values)"[:200])
    return _finite(t.name, values.reshape(t.shape)), offset


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    if not np.isfinite(a).all():
        raise ProtocolError(f"input {name!r}: NaN or Inf values")
    return a


@dataclass(frozen=True)
class TensorSpec:
    """One tensor of a model, as its metadata declares it and its requests are checked.

    Attributes:
        name: the tensor's name.
        shape: per dimension a size, or a letter: an input size that every input with that letter
            shares (any size: -1 in the metadata).
        bounds: an input's value range ``(lo, hi)``; None: any finite value.
        optional: an input that a request may leave out.
    """

    name: str
    shape: tuple[int | str, ...]
    bounds: tuple[float, float] | None = None
    optional: bool = False

    def metadata(self, datatypes: list[str]) -> dict[str, Any]:
        """The tensor's metadata: datatype FP32, shape, and in ``parameters`` whether it may be left
        out, the ``datatypes`` the server takes and its value range."""
        parameters: dict[str, Any] = {"optional": self.optional, "accepted_datatypes": datatypes}
        if self.bounds is not None:
            parameters["range"] = list(self.bounds)
        return {"name": self.name, "datatype": "FP32", "shape": [d if isinstance(d, int) else -1 for d in self.shape],
                "parameters": parameters}


@dataclass(frozen=True)
class ModelSpec:
    """A model's tensors: the one declaration its metadata and its requests' checks come from."""

    name: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]

    def metadata(self) -> dict[str, Any]:
        """``inputs`` and ``outputs`` of the model's metadata (inputs taken in every datatype of `DATATYPES`)."""
        return {"inputs": [t.metadata(list(DATATYPES)) for t in self.inputs],
                "outputs": [t.metadata(["FP32"]) for t in self.outputs]}

    def check(self, req: InferRequest) -> dict[str, int]:
        """The size each shape letter takes in ``req`` (e.g. ``{"H": 48, "W": 64}``), after checking
        that its inputs are the model's, none missing, each of its shape and within its bounds, and
        that the outputs it asks for are the model's.

        Raises:
            ProtocolError: (400) naming the first input or output that does not fit.
        """
        names = [t.name for t in self.inputs]
        unknown = [n for n in req.inputs if n not in names]
        if unknown:
            raise ProtocolError(f"unknown input {unknown[0]!r}; {self.name} takes {', '.join(names)}"[:200])
        missing = [t.name for t in self.inputs if not t.optional and t.name not in req.inputs]
        if missing:
            raise ProtocolError(f"missing input {missing[0]!r}")
        sizes: dict[str, int] = {}
        for spec in (t for t in self.inputs if t.name in req.inputs):
            a = req.inputs[spec.name]
            _check_shape(spec, a.shape, sizes)
            if spec.bounds is not None and a.size:
                # Compared as Python floats: a bound beyond float16's range cast to float16 would be inf.
                (lo, hi), low, high = spec.bounds, float(a.min()), float(a.max())
                if low < lo or high > hi:
                    raise ProtocolError(f"input {spec.name!r}: values must lie in [{lo:g}, {hi:g}], "
                                        f"got [{low:g}, {high:g}]")
        outputs = [t.name for t in self.outputs]
        unknown = [n for n in req.outputs or () if n not in outputs]
        if unknown:
            raise ProtocolError(f"unknown output {unknown[0]!r}; {self.name} gives {', '.join(outputs)}"[:200])
        return sizes

    def wanted(self, req: InferRequest) -> tuple[str, ...]:
        """The outputs ``req`` asks for (all the model's when it names none), in the model's order."""
        return tuple(t.name for t in self.outputs if req.outputs is None or t.name in req.outputs)


def _check_shape(spec: TensorSpec, shape: tuple[int, ...], sizes: dict[str, int]) -> None:
    """`ProtocolError` unless ``shape`` fits ``spec.shape`` with the letters' sizes seen so far
    (``sizes``, where new letters' sizes are recorded)."""
    fits = len(shape) == len(spec.shape) and all(
        n == d if isinstance(d, int) else sizes.setdefault(d, n) == n for n, d in zip(shape, spec.shape))
    if not fits:
        known = ", ".join(f"{k}={v}" for k, v in sizes.items())
        raise ProtocolError(f"input {spec.name!r}: shape {list(shape)} does not fit [{', '.join(map(str, spec.shape))}]"
                            f"{f' with {known}' if known else ''}"[:200])


def sequence(req: InferRequest) -> tuple[str | None, bool]:
    """Triton's sequence parameters: ``(sequence_id as a session id, or None for none; sequence_start)``.

    Raises:
        ProtocolError: (400) the id is neither an integer nor a string of `SESSION_ID`'s form.
    """
    sequence_id = req.parameters.get("sequence_id", 0)
    if isinstance(sequence_id, bool) or not isinstance(sequence_id, int | str):
        raise ProtocolError("sequence_id must be an integer or a string")
    session = str(sequence_id) if sequence_id not in (0, "") else None
    if session is not None and not SESSION_ID.fullmatch(session):
        raise ProtocolError(f"sequence_id must match {SESSION_ID.pattern}")
    return session, bool(req.parameters.get("sequence_start", False))


def int_parameter(req: InferRequest, name: str, default: int, lo: int, hi: int) -> int:
    """The request's integer parameter ``name`` (``default`` when absent); `ProtocolError` (400) outside [lo, hi]."""
    value = req.parameters.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ProtocolError(f"parameter {name!r} must be an integer in [{lo}, {hi}], got {value!r}"[:200])
    return value


def encode_response(model: str, version: str, request: InferRequest, outputs: dict[str, np.ndarray]) -> \
        tuple[bytes, int | None]:
    """The response body for ``outputs`` (float32 arrays: at least those ``request`` asks for,
    checked by `ModelSpec.check`) as it asks (in its order; when it names none, all of ``outputs``
    in theirs), and the JSON header's length when some output is binary (else None)."""
    wanted = request.outputs
    if wanted is None:
        wanted = dict.fromkeys(outputs, request.binary_output)
    entries: list[dict[str, Any]] = []
    blobs: list[bytes] = []
    for name, binary in wanted.items():
        a = np.ascontiguousarray(outputs[name], "<f4")
        entry: dict[str, Any] = {"name": name, "datatype": "FP32", "shape": list(a.shape)}
        if binary:
            blobs.append(a.tobytes())
            entry["parameters"] = {"binary_data_size": a.nbytes}
        else:
            entry["data"] = a.ravel().tolist()
        entries.append(entry)
    reply: dict[str, Any] = {"model_name": model, "model_version": version, "outputs": entries}
    if request.id is not None:
        reply["id"] = request.id
    header = msgspec.json.encode(reply)
    return (header + b"".join(blobs), len(header)) if blobs else (header, None)
