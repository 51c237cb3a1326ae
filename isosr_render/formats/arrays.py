"""Volume files read whole: NIfTI, NRRD, Volume Library ``.dat`` + ``.raw``, named ``.raw`` and NumPy.

Each ``open_*`` returns an :class:`~isosr_render.voxels.ArraySource` of the stored values indexed
``[x, y, z]`` (x is the first axis), named after the file, with its spacing and rescale:

- Volume Library ``.dat`` text header beside a ``.raw`` file (``ObjectFileName``,
  ``Resolution``, ``SliceThickness``, ``Format`` UCHAR/USHORT/FLOAT), little-endian.
- ``name_XxYxZ_dtype.raw`` and ``.raw.gz`` (little-endian, spacing 1).
- NIfTI ``.nii`` / ``.nii.gz`` (either byte order, spacing from the zooms, stored type kept and
  ``scl_slope``/``scl_inter`` as the rescale).
- NRRD ``.nrrd`` / ``.nhdr``, including detached headers over a numbered list of data files
  (``data file: slice.%03d 1 93 1``), which pynrrd does not read.
- NumPy ``.npy`` / ``.npz`` stored as (x, y, z), never unpickled.

Time series (:mod:`isosr_render.series`): a 4D NIfTI's fourth axis is time (``nifti_steps``,
one step read at a time); a 4D ``.npy`` is ``(t, z, y, x)`` (``numpy_steps``, memory-mapped: C
order, as most simulation codes write a series), each step handed out as ``[x, y, z]``.
``nifti_header`` and ``numpy_header`` read a file's :class:`~isosr_render.formats.base.Layout`
without its voxels.

Raw voxels are x-fastest on disk: they are read flat, shaped (z, y, x) and transposed. 64-bit
integers are handed out as float64 (as :func:`isosr_render.formats.base.stored_dtype`).
"""

from __future__ import annotations

import gzip
import os
import re
import zlib
from collections.abc import Callable
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np

from isosr_render.formats.base import Layout, TimeSteps, stored_dtype
from isosr_render.voxels import ArraySource, VolumeError

# A reader's result: stored values [x, y, z], spacing, and optionally (slope, intercept).
_Loaded = tuple[np.ndarray, tuple[float, ...]] | tuple[np.ndarray, tuple[float, ...], tuple[float, float]]

_RAW_NAME = re.compile(r"_(\d+)x(\d+)x(\d+)_([a-z]+\d*)\.raw(\.gz)?$", re.IGNORECASE)
_RAW_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
_DAT_FORMATS = {"UCHAR": "u1", "USHORT": "<u2", "FLOAT": "<f4"}
# NRRD multi-file form: "<printf pattern> <min> <max> <step> [<subdim>]".
_NRRD_FILE_LIST = re.compile(r"(\S*%\S*)\s+(-?\d+)\s+(-?\d+)\s+(-?\d+)(?:\s+\d+)?")
# What the file and array libraries raise on bad input; re-raised as VolumeError.
_LIBRARY_ERRORS = (OSError, EOFError, ValueError, zlib.error, nrrd.NRRDError,
                   nib.filebasedimages.ImageFileError)


def open_dat(path: str | os.PathLike) -> ArraySource:
    """A Volume Library ``.dat`` header and the ``.raw`` file it names."""
    return _array_source(Path(path), _read_dat)


def open_raw(path: str | os.PathLike) -> ArraySource:
    """A ``name_XxYxZ_dtype.raw[.gz]`` file: shape and dtype come from the name."""
    return _array_source(Path(path), _read_named_raw)


def open_nifti(path: str | os.PathLike) -> ArraySource:
    """A NIfTI image in its stored dtype, with the header's scaling as the rescale."""
    return _array_source(Path(path), _read_nifti)


def open_nrrd(path: str | os.PathLike) -> ArraySource:
    """An NRRD file or detached header, including the multi-file ``data file`` form."""
    return _array_source(Path(path), _read_nrrd)


def open_numpy(path: str | os.PathLike) -> ArraySource:
    """A ``.npy`` array, or the ``volume``/``data``/only array (and ``spacing``) of a ``.npz``."""
    return _array_source(Path(path), _read_numpy)


def nifti_header(path: str | os.PathLike) -> Layout:
    """A NIfTI file's layout (of one step, for a 4D file), from its header only."""
    path = Path(path)
    image = _library_call(path, nib.load, path)
    return Layout(tuple(int(n) for n in (*image.shape, 1, 1)[:3]), tuple(float(z) for z in image.header.get_zooms()[:3]),
                  stored_dtype(image.get_data_dtype(), path.name))


def nifti_steps(path: str | os.PathLike) -> TimeSteps | None:
    """A 4D NIfTI's time steps (its fourth axis; each read alone), or None for a 3D file."""
    path = Path(path)
    image = _library_call(path, nib.load, path)
    if len(image.shape) != 4 or image.shape[3] < 2:
        return None
    proxy = image.dataobj

    def read(i: int) -> _Loaded:
        values = proxy._get_unscaled((slice(None),) * 3 + (i,))  # noqa: SLF001 - the one step, stored type kept
        return values, tuple(float(z) for z in image.header.get_zooms()[:3]), (float(proxy.slope), float(proxy.inter))
    return TimeSteps(int(image.shape[3]), lambda i: _array_source(path, lambda _: read(i), f"{path.name}[t={i}]"))


def numpy_header(path: str | os.PathLike) -> Layout:
    """A ``.npy`` file's layout (of one step, for a 4D ``(t, z, y, x)`` array), from its header only;
    a ``.npz`` is opened."""
    path = Path(path)
    if path.name.lower().endswith(".npz"):
        return Layout.of(open_numpy(path))
    array = _library_call(path, np.load, path, mmap_mode="r", allow_pickle=False)
    shape = tuple(int(n) for n in (array.shape[:0:-1] if array.ndim == 4 else array.shape))
    return Layout(shape, (1.0, 1.0, 1.0), stored_dtype(array.dtype, path.name))


def numpy_steps(path: str | os.PathLike) -> TimeSteps | None:
    """A 4D ``.npy`` array's time steps: ``(t, z, y, x)``, memory-mapped, each step read alone; None otherwise."""
    path = Path(path)
    if path.name.lower().endswith(".npz"):
        return None
    array = _library_call(path, np.load, path, mmap_mode="r", allow_pickle=False)
    if array.ndim != 4 or array.shape[0] < 2:
        return None
    return TimeSteps(int(array.shape[0]), lambda i: _array_source(
        path, lambda _: (np.array(array[i].transpose(2, 1, 0)), (1.0, 1.0, 1.0)), f"{path.name}[t={i}]"))


def _library_call(path: Path, fn: Callable, *args, **kwargs):
    """``fn(*args, **kwargs)``, the file libraries' errors as `VolumeError` naming ``path``."""
    try:
        return fn(*args, **kwargs)
    except _LIBRARY_ERRORS as e:
        raise VolumeError(f"{path}: cannot read ({type(e).__name__}: {e})") from e


def _array_source(path: Path, read: Callable[[Path], _Loaded], name: str | None = None) -> ArraySource:
    """Read ``path`` with ``read`` and hand the values out as a source named ``name`` (default: the
    file's name); library errors as `VolumeError`."""
    try:
        values, spacing, *rescale = read(path)
    except VolumeError:
        raise
    except _LIBRARY_ERRORS as e:
        raise VolumeError(f"{path}: cannot read ({type(e).__name__}: {e})") from e
    values = np.asarray(values)
    if not (np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_):
        raise VolumeError(f"{path.name}: unsupported voxel dtype {values.dtype}")
    if values.dtype.kind in "iu" and values.dtype.itemsize == 8:  # 64-bit integers: as float64
        values = values.astype(np.float64)
    return ArraySource(values, spacing, name=name or path.name, rescale=rescale[0] if rescale else (1.0, 0.0))


def _read_xfastest(path: Path, dtype: np.dtype, shape: tuple[int, int, int], label: str) -> np.ndarray:
    """Read x-fastest voxels from a plain or gzipped file, checking the size, as [x, y, z]."""
    expected = int(np.prod(shape)) * dtype.itemsize
    gzipped = path.name.lower().endswith(".gz")
    if gzipped:
        with gzip.open(path, "rb") as f:
            buffer = f.read()
        found = len(buffer)
    else:
        found = path.stat().st_size
    if found != expected:
        raise VolumeError(f"{label}: size mismatch, expected {expected} bytes for shape {shape} "
                          f"of {dtype.name}, found {found} bytes")
    flat = np.frombuffer(buffer, dtype) if gzipped else np.fromfile(path, dtype)
    return flat.reshape(shape[::-1]).transpose(2, 1, 0)


def _read_named_raw(path: Path) -> _Loaded:
    """Read ``name_XxYxZ_dtype.raw[.gz]``: shape and dtype come from the file name."""
    match = _RAW_NAME.search(path.name)
    if match is None:
        raise VolumeError(f"{path}: cannot tell shape and dtype, a raw file name must look like "
                          "name_XxYxZ_dtype.raw or .raw.gz")
    dtype_name = match.group(4).lower()
    if dtype_name not in _RAW_DTYPES:
        raise VolumeError(f"{path}: unknown dtype '{dtype_name}' in the file name "
                          f"(expected one of {', '.join(_RAW_DTYPES)})")
    shape = tuple(int(match.group(i)) for i in (1, 2, 3))
    return _read_xfastest(path, np.dtype(dtype_name).newbyteorder("<"), shape, str(path)), (1.0, 1.0, 1.0)


def _dat_numbers(path: Path, fields: dict[str, str], key: str, kind: type) -> tuple:
    """Parse the three numbers of a ``.dat`` header field."""
    text = fields[key.lower()]
    try:
        numbers = tuple(kind(v) for v in text.split())
    except ValueError:
        numbers = ()
    if len(numbers) != 3:
        raise VolumeError(f"{path}: unparseable header line '{key}: {text}' (expected 3 numbers)")
    return numbers


def _read_dat(path: Path) -> _Loaded:
    """Read a Volume Library ``.dat`` header and the ``.raw`` file it names."""
    fields = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        key, colon, value = line.partition(":")
        if not colon or not key.strip():
            raise VolumeError(f"{path}: unparseable header line {number}: '{line.strip()}'")
        fields[key.strip().lower()] = value.strip()
    missing = [k for k in ("ObjectFileName", "Resolution", "Format") if k.lower() not in fields]
    if missing:
        raise VolumeError(f"{path}: header lacks {', '.join(missing)}")
    fmt = fields["format"].upper()
    if fmt not in _DAT_FORMATS:
        raise VolumeError(f"{path}: unknown Format '{fields['format']}' "
                          f"(expected {', '.join(_DAT_FORMATS)})")
    shape = _dat_numbers(path, fields, "Resolution", int)
    spacing = (1.0, 1.0, 1.0)
    if "slicethickness" in fields:
        spacing = _dat_numbers(path, fields, "SliceThickness", float)
    raw = path.parent / fields["objectfilename"]
    if not raw.is_file():
        raise VolumeError(f"{path}: missing data file {raw} (ObjectFileName)")
    label = f"{path}: data file {raw.name}"
    return _read_xfastest(raw, np.dtype(_DAT_FORMATS[fmt]), shape, label), spacing


def _read_nifti(path: Path) -> _Loaded:
    """Read a NIfTI image in its stored dtype, with the header's scaling as the rescale."""
    image = nib.load(path)
    proxy = image.dataobj
    values = np.asanyarray(proxy.get_unscaled())
    while values.ndim > 3 and values.shape[-1] == 1:
        values = values[..., 0]
    rescale = (float(proxy.slope), float(proxy.inter))
    return values, tuple(float(z) for z in image.header.get_zooms()[:3]), rescale


def _read_nrrd_file_list(path: Path, header: dict, match: re.Match) -> np.ndarray:
    """Read the data files of a multi-file detached header, in order, as one array."""
    pattern, first, last, step = match.group(1), *(int(match.group(i)) for i in (2, 3, 4))
    if step == 0:
        raise VolumeError(f"{path}: unparseable 'data file' list, step is 0")
    try:
        files = [path.parent / (pattern % i) for i in range(first, last + (1 if step > 0 else -1), step)]
    except (TypeError, ValueError) as e:
        raise VolumeError(f"{path}: unparseable 'data file' pattern '{pattern}' ({e})") from e
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise VolumeError(f"{path}: missing {len(missing)} of {len(files)} slice files: "
                          f"{', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}")
    sizes = np.asarray(header["sizes"], dtype=np.int64)
    total = int(sizes.prod())
    if total % len(files):
        raise VolumeError(f"{path}: sizes {sizes.tolist()} do not split evenly over {len(files)} data files")
    # Files hold consecutive x-fastest chunks, whatever the subdim: read each flat, then join.
    part = {k: v for k, v in header.items() if k not in ("data file", "datafile")}
    part.update(dimension=1, sizes=np.array([total // len(files)]))
    chunks = []
    for file in files:
        try:
            chunks.append(nrrd.read_data({**part, "data file": str(file.resolve())}, filename=str(path)))
        except nrrd.NRRDError as e:
            raise VolumeError(f"{path}: slice file {file.name} does not match the header: {e}") from e
    return np.concatenate(chunks).reshape(sizes[::-1]).T


def _nrrd_spacing(header: dict) -> tuple[float, ...]:
    """Voxel size per axis from ``space directions`` (row lengths) or ``spacings``, else 1."""
    if "space directions" in header:
        spacing = np.linalg.norm(np.asarray(header["space directions"], dtype=np.float64), axis=1)
    elif "spacings" in header:
        spacing = np.asarray(header["spacings"], dtype=np.float64)
    else:
        spacing = np.ones(len(header["sizes"]))
    return tuple(float(s) for s in np.where(np.isnan(spacing), 1.0, spacing)[:3])


def _read_nrrd(path: Path) -> _Loaded:
    """Read an NRRD file or detached header, including the multi-file ``data file`` form."""
    with open(path, "rb") as fh:
        header = nrrd.read_header(fh)
        match = _NRRD_FILE_LIST.fullmatch(header.get("data file", header.get("datafile", "")).strip())
        if match:
            values = _read_nrrd_file_list(path, header, match)
        else:
            values = nrrd.read_data(header, fh, str(path))
    return values, _nrrd_spacing(header)


def _read_numpy(path: Path) -> _Loaded:
    """Read a ``.npy`` array or the ``volume``/``data``/only array (and ``spacing``) of a ``.npz``."""
    loaded = np.load(path, allow_pickle=False)
    if isinstance(loaded, np.ndarray):
        return loaded, (1.0, 1.0, 1.0)
    with loaded:
        names = [n for n in loaded.files if n != "spacing"]
        key = next((n for n in ("volume", "data") if n in names), names[0] if len(names) == 1 else None)
        if key is None:
            raise VolumeError(f"{path}: cannot tell which array is the volume among {names}; "
                              "name it 'volume' or 'data'")
        spacing = loaded["spacing"].ravel() if "spacing" in loaded.files else (1.0, 1.0, 1.0)
        return loaded[key], tuple(float(s) for s in spacing)
