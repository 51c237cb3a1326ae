"""Tests for isosr_render.series: every form of a time series, natural order, steps that differ,
the bounded cache and the prefetch, and that a recurrent method shows nothing of the step before."""

from __future__ import annotations

import time
from dataclasses import fields
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch

from isosr_net.methods import RUNNERS, FrameMethod, FrameResult, FrameStream, Networks, unavailable_kinds
from isosr_render import Renderer, orbit
from isosr_render.series import VolumeSeries, is_series, natural_key, open_series, step_iso
from isosr_render.volume_io import load_volume
from isosr_render.voxels import ArraySource, VolumeError

N = 24
CENTERS = (7.0, 16.0, 11.0)  # the ball's x per step: it jumps


def ball(cx: float, n: int = N, dtype=np.uint8) -> np.ndarray:
    """A smooth ball of radius 5 voxels about (cx, 12, 12), indexed [x, y, z], values 0..255."""
    x, y, z = np.meshgrid(*(np.arange(n, dtype=np.float64),) * 3, indexing="ij")
    d = np.sqrt((x - cx) ** 2 + (y - 12.0) ** 2 + (z - 12.0) ** 2)
    return np.clip(128 + 40 * (5.0 - d), 0, 255).astype(dtype)


def tzyx() -> np.ndarray:
    """The steps as one (t, z, y, x) array."""
    return np.stack([ball(c).transpose(2, 1, 0) for c in CENTERS])


def write_nifti_files(folder: Path, names=("run_1", "run_2", "run_10")) -> list[Path]:
    folder.mkdir(exist_ok=True)
    paths = []
    for name, c in zip(names, CENTERS):
        paths.append(folder / f"{name}.nii.gz")
        nib.save(nib.Nifti1Image(ball(c), np.diag([0.5, 0.5, 1.0, 1.0])), paths[-1])
    return paths


def assert_steps(series: VolumeSeries, spacing=(1.0, 1.0, 1.0)) -> None:
    """The series holds the ball at CENTERS, in order, indexed [x, y, z]."""
    assert series.count == len(CENTERS)
    for i, c in enumerate(CENTERS):
        volume = series.step(i)
        assert volume.shape == (N, N, N) and volume.spacing == pytest.approx(spacing)
        stored = np.asarray(volume.source.read(slice(0, N), slice(0, N), slice(0, N)))
        np.testing.assert_array_equal(stored, ball(c))


def test_natural_order_puts_run_2_before_run_10():
    names = ["run_10.nii", "run_2.nii", "run_1.nii", "Run_3.nii"]
    assert sorted(names, key=natural_key) == ["run_1.nii", "run_2.nii", "Run_3.nii", "run_10.nii"]


def test_a_glob_and_a_folder_open_in_natural_order(tmp_path):
    write_nifti_files(tmp_path / "runs")
    glob = open_series(str(tmp_path / "runs" / "run_*.nii.gz"))
    assert glob.labels == ["run_1.nii.gz", "run_2.nii.gz", "run_10.nii.gz"]
    assert_steps(glob, (0.5, 0.5, 1.0))
    folder = open_series(tmp_path / "runs")
    assert folder.labels == glob.labels and folder.name == "runs"
    assert_steps(folder, (0.5, 0.5, 1.0))
    assert is_series(tmp_path / "runs") and not is_series(tmp_path / "runs" / "run_1.nii.gz")


def test_a_4d_nifti_is_a_series_along_its_fourth_axis(tmp_path):
    path = tmp_path / "four.nii"
    nib.save(nib.Nifti1Image(np.stack([ball(c) for c in CENTERS], axis=-1), np.diag([2.0, 1.0, 1.0, 1.0])), path)
    series = open_series(path)
    assert_steps(series, (2.0, 1.0, 1.0))
    assert series.step(1).name == "four.nii[t=1]"
    with pytest.raises(VolumeError, match="3D"):  # a series, not a volume
        load_volume(path)


def test_a_numpy_array_is_t_z_y_x(tmp_path):
    np.save(tmp_path / "runs.npy", tzyx())
    assert_steps(open_series(tmp_path / "runs.npy"))


def test_an_ome_zarr_with_a_t_axis(tmp_path):
    zarr = pytest.importorskip("zarr", reason="Zarr series need zarr (the data extra)")
    group = zarr.open_group(str(tmp_path / "runs.ome.zarr"), mode="w")
    group.create_array("0", data=tzyx(), chunks=(1, 8, 8, 8))
    group.attrs["multiscales"] = [{"version": "0.4", "axes": [
        {"name": "t", "type": "time"}, {"name": "z", "type": "space"}, {"name": "y", "type": "space"},
        {"name": "x", "type": "space"}], "datasets": [{"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, 3.0, 1.0, 1.0]}]}]}]
    assert_steps(open_series(tmp_path / "runs.ome.zarr"), (1.0, 1.0, 3.0))
    with pytest.raises(VolumeError, match="t=3 hold more than one entry; a t axis is a time series"):
        load_volume(tmp_path / "runs.ome.zarr")


def test_an_hdf5_dataset(tmp_path):
    h5py = pytest.importorskip("h5py", reason="HDF5 series need h5py (the data extra)")
    with h5py.File(tmp_path / "sim.h5", "w") as f:
        f["/fields/density"] = tzyx()
    assert_steps(open_series(f"{tmp_path}/sim.h5#/fields/density"))
    with pytest.raises(VolumeError, match="sim.h5#/nothing: cannot open"):
        open_series(f"{tmp_path}/sim.h5#/nothing")


@pytest.mark.parametrize("bad, words", [
    (lambda: nib.Nifti1Image(ball(7.0, n=20), np.diag([0.5, 0.5, 1.0, 1.0])), "shape (20, 20, 20) instead of (24, 24, 24)"),
    (lambda: nib.Nifti1Image(ball(7.0), np.diag([0.5, 0.5, 2.0, 1.0])), "spacing (0.5, 0.5, 2.0) instead of (0.5, 0.5, 1.0)"),
    (lambda: nib.Nifti1Image(ball(7.0, dtype=np.int16), np.diag([0.5, 0.5, 1.0, 1.0])), "dtype int16 instead of uint8"),
])
def test_a_step_that_differs_is_refused_naming_the_first(tmp_path, bad, words):
    write_nifti_files(tmp_path / "runs", names=("run_1", "run_2", "run_4"))
    nib.save(bad(), tmp_path / "runs" / "run_3.nii.gz")
    nib.save(bad(), tmp_path / "runs" / "run_5.nii.gz")
    with pytest.raises(VolumeError) as e:
        open_series(tmp_path / "runs")
    assert str(e.value) == f"runs: step 2 (run_3.nii.gz) differs from step 0 (run_1.nii.gz): {words}"


def test_a_step_read_later_is_checked_too():
    values = [ball(7.0), ball(9.0), ball(9.0)[:20]]
    series = VolumeSeries("mixed", 3, lambda i: ArraySource(values[i]), ["a", "b", "c"])
    series.step(1)
    with pytest.raises(VolumeError, match=r"step 2 \(c\) differs from step 0 \(a\): shape \(20, 24, 24\)"):
        series.step(2)


def test_the_cache_keeps_the_recently_used_steps_within_its_bytes_and_prefetch_reads_ahead():
    reads = []

    def read(i):
        reads.append(i)
        return ArraySource(ball(CENTERS[i % 3]))
    series = VolumeSeries("s", 5, read, [str(i) for i in range(5)], max_bytes=2 * N**3)
    series.step(0), series.step(1), series.step(0), series.step(2)
    assert series.cached() == [0, 2] and series.held_bytes() == 2 * N**3
    series.prefetch(3)  # steps 4 and 0 (playback wraps around); 0 is held already
    deadline = time.monotonic() + 30
    while 4 not in series.cached() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert reads == [0, 1, 2, 4] and 4 in series.cached()
    series.step(4)
    assert reads == [0, 1, 2, 4]  # from the cache
    series.close()
    with pytest.raises(IndexError, match="step 5 outside 0..4"):
        series.step(5)


def test_a_missing_step_file_names_the_step(tmp_path):
    paths = write_nifti_files(tmp_path / "runs")
    series = open_series(tmp_path / "runs")
    paths[1].unlink()
    with pytest.raises(VolumeError, match="run_2.nii.gz: no such file"):
        series.step(1)
    assert series.step(2).shape == (N, N, N)  # the others still read


def test_an_iso_keeps_its_data_value_across_steps():
    a = VolumeSeries("a", 2, lambda i: ArraySource(ball(7.0).astype(np.float32) * (1 + i)), ["0", "1"])
    first, second = a.step(0), a.step(1)
    assert step_iso(0.25, first, second) == pytest.approx(0.125)


RECURRENT = [kind for kind, runner in RUNNERS.items() if runner.recurrent]


def jump_method(kind: str) -> FrameMethod:
    """``kind`` at 1 AO ray where it takes AO rays, else at its defaults."""
    takes = {f.name for f in fields(RUNNERS[kind].options_type)}
    return FrameMethod.of(kind, **({"ao_rays": 1} if "ao_rays" in takes else {}))


def shown(result: FrameResult, method: FrameMethod) -> dict[str, torch.Tensor]:
    """What a frame shows: its color, else (an unshaded kind) the buffers it makes, flow aside."""
    runner = method.runner
    names = ("color",) if runner.shaded else [n for n in runner.makes(method) if n != "flow"]
    return {n: getattr(result.buffers, n) for n in names}


@pytest.mark.parametrize("kind", RECURRENT)
def test_nothing_of_the_step_before_ghosts_into_the_next(tmp_path, kind):
    """A ball that jumps between steps under every recurrent method, the camera still (where history
    would line up best with the new frame): after a few frames of step 0, the first frame of step 1
    equals a fresh stream's first frame of step 1, and where only the old ball was it shows the
    background (each step is a renderer of its own: a cut, as in the server's view session)."""
    if kind in unavailable_kinds():
        pytest.skip(unavailable_kinds()[kind])
    np.save(tmp_path / "runs.npy", tzyx())
    series = open_series(tmp_path / "runs.npy")
    renderers = [Renderer(series.step(i), "cpu") for i in range(2)]
    iso, method, cam = series.step(0).normalized_iso(128.0), jump_method(kind), orbit(0.0, 10.0, 1.8)
    networks = Networks.eager()
    stream = FrameStream(networks.fork())
    for prev in (None, cam, cam):
        played = stream.frame(method, renderers[0], iso, 64, 48, cam, prev)
        assert played.continued == (prev is not None)
    before = {n: t.clone() for n, t in shown(played, method).items()}
    before_mask = played.buffers.mask.clone()
    jumped = stream.frame(method, renderers[1], iso, 64, 48, cam, cam)
    fresh = FrameStream(networks.fork()).frame(method, renderers[1], iso, 64, 48, cam, None)
    assert not jumped.continued
    torch.testing.assert_close(shown(jumped, method), shown(fresh, method), atol=1e-5, rtol=0)
    old_only = (before_mask > 0.5) & (fresh.buffers.mask < 0.5)
    assert old_only.float().mean() > 0.05  # the ball moved off these pixels
    assert (jumped.buffers.mask[old_only] < 0.5).all()
    for name, image in shown(jumped, method).items():  # not what step 0 showed there
        assert (before[name][old_only] - image[old_only]).abs().amax() > 0.1, name
