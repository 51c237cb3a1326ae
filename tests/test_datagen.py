"""Training data (isosr_net.datagen): shards and manifest, resuming, crops, the dataset."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

import isosr_net.datagen as datagen
from isosr_net.batch import SequenceBatch
from isosr_net.datagen import MANIFEST, DatagenConfig, SequenceDataset, generate, pick_crops
from isosr_net.reconnet import RayLimits
from isosr_render.catalog import shared_volumes_dir
from isosr_render.conventions import AO, MASK, SAMPLED_AO, SAMPLING
from net_fixtures import (TINY_DATAGEN, TINY_RECON_DATAGEN, TINY_RECON_X2_DATAGEN, tiny_datagen, tiny_recon_data,
                          tiny_recon_upscaling_data, tiny_train_data)


def shard_tensors(root: Path) -> dict[str, dict[str, torch.Tensor]]:
    """Every shard of a datagen folder by file name."""
    manifest = json.loads((root / MANIFEST).read_text())
    return {s["file"]: load_file(root / s["file"]) for s in manifest["shards"]}


def assert_same_data(a: Path, b: Path) -> None:
    """Two datagen folders hold the same manifest entries (in any order) and the same shards."""
    ma, mb = (json.loads((r / MANIFEST).read_text()) for r in (a, b))
    assert ma["config"] == mb["config"]
    assert sorted(ma["shards"], key=lambda s: s["file"]) == sorted(mb["shards"], key=lambda s: s["file"])
    ta, tb = shard_tensors(a), shard_tensors(b)
    assert sorted(ta) == sorted(tb)
    for name in ta:
        for key in ("lowres", "flow", "highres"):
            assert torch.equal(ta[name][key], tb[name][key]), (name, key)


def file_stamps(root: Path) -> dict[str, tuple[int, int]]:
    """(inode, mtime_ns) of every shard file: a rewrite (atomic or not) changes one of them."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (root / "shards").iterdir()}


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    """A fresh tiny run: 2 volumes x 2 sequences."""
    root = tmp_path_factory.mktemp("fresh")
    generate(TINY_DATAGEN, root, progress=False)
    return root


def test_generate_writes_shards_and_manifest(fresh):
    manifest = json.loads((fresh / MANIFEST).read_text())
    assert manifest["version"] == 1
    assert manifest["config"] == json.loads(json.dumps(TINY_DATAGEN.__dict__))
    files = sorted(s["file"] for s in manifest["shards"])
    assert files == ["shards/proc_cloud_1_32_0000.safetensors", "shards/proc_cloud_1_32_0001.safetensors",
                     "shards/proc_sphere_32_0000.safetensors", "shards/proc_sphere_32_0001.safetensors"]
    assert sorted(p.name for p in (fresh / "shards").iterdir()) == [Path(f).name for f in files]
    c, s, t = TINY_DATAGEN.crop, TINY_DATAGEN.upscale, TINY_DATAGEN.frames
    for shard in manifest["shards"]:
        assert shard["split"] == "train"  # procedural volumes train
        assert shard["volume"] in TINY_DATAGEN.volumes and shard["sequence"] in (0, 1)
        assert 0 < shard["iso"] < 1
        assert 1 <= shard["crops"] <= TINY_DATAGEN.crops
        tensors = load_file(fresh / shard["file"])
        k = shard["crops"]
        assert tensors["lowres"].shape == (k, t, 5, c, c) and tensors["lowres"].dtype == torch.float16
        assert tensors["flow"].shape == (k, t, 2, c, c) and tensors["flow"].dtype == torch.float32
        assert tensors["highres"].shape == (k, t, 6, c * s, c * s) and tensors["highres"].dtype == torch.float16
        assert (tensors["flow"][:, 0] == 0).all()  # no previous frame for frame 0
        lowres_mask, highres = tensors["lowres"][:, :, 0].float(), tensors["highres"].float()
        # Every kept crop is covered enough, averaged over its frames.
        assert (lowres_mask.mean(dim=(1, 2, 3)) >= TINY_DATAGEN.min_coverage).all()
        assert set(lowres_mask.unique().tolist()) <= {0.0, 1.0}  # one ray per low-res pixel
        ao = highres[:, :, 5]
        assert ao.min() >= 0 and ao.max() <= 1
        hit = highres[:, :, 0] > 0
        normal_len = highres[:, :, 1:4].norm(dim=2)
        assert (normal_len[hit] - 1).abs().max() < 5e-3  # float16 unit normals
        assert (highres[:, :, 1:][(~hit)[:, :, None].expand(-1, -1, 5, -1, -1)] == 0).all()


def test_sequences_differ_in_iso_and_camera(fresh):
    manifest = json.loads((fresh / MANIFEST).read_text())
    isos = [s["iso"] for s in manifest["shards"]]
    assert len(set(isos)) == len(isos)
    tensors = shard_tensors(fresh)
    a = tensors["shards/proc_cloud_1_32_0000.safetensors"]["lowres"]
    b = tensors["shards/proc_cloud_1_32_0001.safetensors"]["lowres"]
    assert not torch.equal(a[:1], b[:1])


def test_a_second_run_of_the_same_config_renders_nothing(fresh, monkeypatch):
    stamps = file_stamps(fresh)
    calls = []
    monkeypatch.setattr(datagen, "render_sequence", lambda *a, **k: calls.append(a) or pytest.fail("rendered"))
    manifest = generate(TINY_DATAGEN, fresh, progress=False)
    assert calls == [] and len(manifest["shards"]) == 4
    assert file_stamps(fresh) == stamps


def test_an_interrupted_run_resumes_and_writes_the_same_data(fresh, tmp_path, monkeypatch):
    real = datagen.render_sequence
    calls = []

    def stop_on_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(datagen, "render_sequence", stop_on_third)
    with pytest.raises(KeyboardInterrupt):
        generate(TINY_DATAGEN, tmp_path, progress=False)
    assert len(json.loads((tmp_path / MANIFEST).read_text())["shards"]) == 2
    stamps = file_stamps(tmp_path)
    calls.clear()
    monkeypatch.setattr(datagen, "render_sequence", lambda *a, **k: calls.append(1) or real(*a, **k))
    generate(TINY_DATAGEN, tmp_path, progress=False)
    assert len(calls) == 2  # only the missing two
    after = file_stamps(tmp_path)
    assert all(after[name] == stamp for name, stamp in stamps.items())  # the first two untouched
    assert_same_data(tmp_path, fresh)


def test_more_sequences_renders_only_the_new_ones_and_equals_a_fresh_run(fresh, tmp_path, monkeypatch):
    generate(tiny_datagen(sequences=1), tmp_path, progress=False)
    stamps = file_stamps(tmp_path)
    real, calls = datagen.render_sequence, []
    monkeypatch.setattr(datagen, "render_sequence", lambda *a, **k: calls.append(1) or real(*a, **k))
    generate(tiny_datagen(sequences=2), tmp_path, progress=False)
    assert len(calls) == 2  # one new sequence per volume
    after = file_stamps(tmp_path)
    assert all(after[name] == stamp for name, stamp in stamps.items())
    assert_same_data(tmp_path, fresh)


@pytest.mark.parametrize("change", [{"seed": 1}, {"crop": 4}, {"volumes": ("proc:cloud:2@32",)}, {"ao_samples": 8}])
def test_a_manifest_from_another_config_is_refused(fresh, change, monkeypatch):
    monkeypatch.setattr(datagen, "render_sequence", lambda *a, **k: pytest.fail("rendered"))
    stamps = file_stamps(fresh)
    with pytest.raises(ValueError, match=rf"manifest.json was written with other \[.{next(iter(change))}.\]; use a new folder"):
        generate(tiny_datagen(**change), fresh, progress=False)
    assert file_stamps(fresh) == stamps


@pytest.mark.parametrize("kwargs, match", [
    ({"crop": 17}, "crop 17 exceeds the low-res render side 16"),
    ({"lowres_size": (32, 6)}, "crop 8 exceeds the low-res render side 6"),
    ({"lowres_size": ()}, "lowres_size must be a positive integer or a non-empty list"),
    ({"lowres_size": (16, 0)}, "lowres_size must be"),
    ({"lowres_size": 16.0}, "lowres_size must be"),
    ({"frames": 1}, "at least 2 frames"),
])
def test_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tiny_datagen(**kwargs)


@pytest.mark.parametrize("kwargs, match", [
    ({"input_spp": (1, 2)}, "input_spp, input_ao_rays and ray_history are for reconstruction data"),
    ({"upscale": 2, "input_ao_rays": (2,)}, r"reconstruction data \(upscale 1, or reconstruction\)"),
    ({"input_ao_rays": (2,)}, "input_spp, input_ao_rays and ray_history are for reconstruction data"),
    ({"upscale": 1, "input_spp": (0, 1)}, r"input_spp must be a non-empty list of integers in \[1, 4\]"),
    ({"upscale": 1, "input_spp": (8,)}, r"input_spp must be a non-empty list of integers in \[1, 4\]"),
    ({"upscale": 1, "input_spp": ()}, "input_spp must be a non-empty list"),
    ({"upscale": 1, "input_spp": (1.5,)}, "input_spp must be"),
    ({"upscale": 1, "input_ao_rays": (2, 9)}, r"input_ao_rays must be a non-empty list of integers in \[0, 8\]"),
    ({"upscale": 1, "max_ao_rays": 16, "input_ao_rays": (17,)}, r"input_ao_rays .* in \[0, 16\]"),
    ({"upscale": 1, "max_spp": 2, "input_spp": (4,)}, r"input_spp .* in \[1, 2\]"),
    ({"upscale": 1, "max_ao_rays": 0}, "max_ao_rays must be an integer >= 1, got 0"),
    ({"upscale": 1, "input_ao_rays": (-1,)}, "input_ao_rays must be"),
    ({"upscale": 1, "input_ao_rays": (True,)}, "input_ao_rays must be"),
    ({"upscale": 0}, "upscale must be at least 1"),
])
def test_config_rejects_bad_sampling_of_reconstruction_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tiny_datagen(**kwargs)


def test_config_volumes_and_sides_become_tuples():
    config = DatagenConfig(volumes=["proc:sphere"], lowres_size=[32, 64], crop=16)
    assert config.volumes == ("proc:sphere",) and config.lowres_size == config.sides == (32, 64)
    assert DatagenConfig(lowres_size=48, crop=16).sides == (48,)


# ---------------------------------------------------------------- crops


def brute_force_coverage(mask: np.ndarray, crop: int) -> np.ndarray:
    mean = mask.mean(axis=0)
    h, w = mean.shape
    return np.array([[mean[r:r + crop, c:c + crop].mean() for c in range(w - crop + 1)] for r in range(h - crop + 1)])


def test_pick_crops_respects_min_coverage():
    rng = np.random.default_rng(0)
    mask = np.zeros((3, 20, 24), np.float32)
    mask[:, 4:14, 6:18] = 1.0  # a 10 x 12 block, in every frame
    mask[1, 14:18, 6:18] = 1.0  # and a strip in one frame only
    coverage = brute_force_coverage(mask, 6)
    for min_coverage in (0.25, 0.5, 0.9, 1.0):
        corners = pick_crops(mask, 6, 1000, min_coverage, rng)
        eligible = {(int(r), int(c)) for r, c in zip(*np.nonzero(coverage >= min_coverage - 1e-6))}
        assert len(corners) == len(set(corners)) == len(eligible)  # each eligible corner once
        assert set(corners) == eligible
    corners = pick_crops(mask, 6, 5, 0.5, rng)
    assert len(corners) == 5 and all(coverage[r, c] >= 0.5 - 1e-6 for r, c in corners)
    assert all(0 <= r <= 20 - 6 and 0 <= c <= 24 - 6 for r, c in corners)


def test_pick_crops_with_a_soft_mask_averages_over_frames():
    rng = np.random.default_rng(1)
    mask = np.random.default_rng(2).random((4, 12, 12)).astype(np.float32)
    coverage = brute_force_coverage(mask, 5)
    threshold = float(np.median(coverage))
    corners = pick_crops(mask, 5, 10_000, threshold, rng)
    assert set(corners) == {(int(r), int(c)) for r, c in zip(*np.nonzero(coverage >= threshold))}


def test_pick_crops_nothing_covered_enough_and_full_size_crop():
    rng = np.random.default_rng(3)
    mask = np.zeros((2, 8, 8), np.float32)
    assert pick_crops(mask, 4, 3, 0.5, rng) == []
    mask[:, :, :5] = 1
    assert pick_crops(mask, 8, 3, 0.5, rng) == [(0, 0)]  # crop == image: one candidate
    assert pick_crops(mask, 8, 3, 0.7, rng) == []


def test_pick_crops_is_deterministic_for_a_seed():
    mask = np.ones((2, 16, 16), np.float32)
    a = pick_crops(mask, 4, 5, 0.5, np.random.default_rng(7))
    b = pick_crops(mask, 4, 5, 0.5, np.random.default_rng(7))
    assert a == b


def test_no_crop_covered_enough_gives_empty_shards(tmp_path):
    config = tiny_datagen(volumes=("proc:sphere@32",), sequences=1, min_coverage=1.01)
    manifest = generate(config, tmp_path, progress=False)
    assert [s["crops"] for s in manifest["shards"]] == [0]
    tensors = load_file(tmp_path / manifest["shards"][0]["file"])
    assert tensors["lowres"].shape == (0, 3, 5, 8, 8) and tensors["highres"].shape == (0, 3, 6, 16, 16)
    with pytest.raises(ValueError, match="no crops of split 'train'"):
        SequenceDataset(tmp_path, "train")


def test_highres_crops_line_up_with_lowres_crops(fresh):
    """The high-res mask, average-pooled to low-res, is the low-res mask up to the silhouette."""
    s = TINY_DATAGEN.upscale
    errors, shifted_errors = [], []
    for tensors in shard_tensors(fresh).values():
        lo = tensors["lowres"][:, :, 0].float().flatten(0, 1)  # (K * T, c, c)
        hi = tensors["highres"][:, :, 0].float().flatten(0, 1)[:, None]
        pooled = F.avg_pool2d(hi, s)[:, 0]
        errors.append((pooled - lo).abs().mean())
        # The same comparison one low-res pixel off: clearly worse, so the test can see misalignment.
        shifted_errors.append((pooled[:, 1:, 1:] - lo[:, :-1, :-1]).abs().mean())
    error, shifted = float(torch.stack(errors).mean()), float(torch.stack(shifted_errors).mean())
    assert error < 0.12, error
    assert shifted > 1.5 * error, (error, shifted)


def test_flow_moves_the_surface_and_is_zero_off_it(fresh):
    """Frames after the first carry the flow from the previous frame: nonzero on the surface, 0 off it."""
    moved = 0.0
    for tensors in shard_tensors(fresh).values():
        mask, flow = tensors["lowres"][:, 1:, 0].float(), tensors["flow"][:, 1:]
        assert (flow[(mask == 0)[:, :, None].expand(-1, -1, 2, -1, -1)] == 0).all()
        moved = max(moved, float(flow.norm(dim=2)[mask > 0].max()))
    assert 0.01 < moved < 16  # the camera orbits a few degrees per frame


# ---------------------------------------------------------------- reconstruction data (upscale 1)


def test_reconstruction_shards_hold_full_resolution_inputs_with_their_sampling(tmp_path_factory):
    root = tiny_recon_data(tmp_path_factory)
    manifest = json.loads((root / MANIFEST).read_text())
    config = TINY_RECON_DATAGEN
    assert manifest["config"]["upscale"] == 1 and manifest["config"]["input_ao_rays"] == [0, 2, 8]
    assert len(manifest["shards"]) == len(config.volumes) * config.sequences
    c, t = config.crop, config.frames
    for shard in manifest["shards"]:
        spp, rays = shard["input_spp"], shard["input_ao_rays"]
        assert spp in config.input_spp and rays in config.input_ao_rays
        tensors = load_file(root / shard["file"])
        k = shard["crops"]
        assert k >= 1
        assert tensors["lowres"].shape == (k, t, 8, c, c) and tensors["highres"].shape == (k, t, 6, c, c)
        lowres = tensors["lowres"].float()
        sampling = lowres[:, :, SAMPLING]
        assert (sampling[:, :, 0] == rays / config.max_ao_rays).all()
        assert (sampling[:, :, 1] == spp / config.max_spp).all()
        ao = lowres[:, :, SAMPLED_AO]
        if rays:
            assert ao.min() >= 0 and ao.max() <= 1 and (ao > 0).any()
        else:
            assert (ao == 0).all()
        if spp == 1:  # one ray per pixel: a hit or not
            assert set(lowres[:, :, MASK].unique().tolist()) <= {0.0, 1.0}
    draws = {(s["input_spp"], s["input_ao_rays"]) for s in manifest["shards"]}
    assert len(draws) > 1  # the sequences were not all rendered alike


@pytest.mark.parametrize("s", [2, 4])
def test_data_for_a_model_that_also_upscales_has_reconstruction_inputs_at_1_over_s_of_the_sides(tmp_path_factory, s):
    root = tiny_recon_upscaling_data(tmp_path_factory, s)
    config = TINY_RECON_X2_DATAGEN
    c, t = config.crop, config.frames
    for shard in json.loads((root / MANIFEST).read_text())["shards"]:
        tensors, k = load_file(root / shard["file"]), shard["crops"]
        assert tensors["lowres"].shape == (k, t, 8, c, c) and tensors["highres"].shape == (k, t, 6, s * c, s * c)
        sampling = tensors["lowres"].float()[:, :, SAMPLING]
        assert (sampling[:, :, 0] == shard["input_ao_rays"] / config.max_ao_rays).all()
        assert (sampling[:, :, 1] == shard["input_spp"] / config.max_spp).all()
    assert not replace(config, upscale=4, reconstruction=False, input_spp=(1,), input_ao_rays=(0,)).recon_inputs


def test_ray_history_data_accumulates_each_frames_rays_as_at_inference():
    """With ``ray_history`` the inputs' AO is the mean of the sequence's rays so far (closer to the
    ground truth than one frame's) and the sampling's AO plane counts them per pixel; frame 0,
    without a history, is the frame's own rays."""
    config = replace(TINY_RECON_DATAGEN, frames=4, lowres_size=48, ao_samples=64, ray_history=True)
    volume, _, iso = datagen.resolve_volume("proc:cloud:1@32")
    renderer = datagen.Renderer(volume, "cpu")
    cameras = datagen.camera_path(np.random.default_rng(3), config.frames)
    kwargs = dict(iso=iso, seed=11, side=48, input_spp=1, input_ao_rays=2)
    accumulated = datagen.render_sequence(renderer, cameras, config=config, **kwargs)
    single = datagen.render_sequence(renderer, cameras, config=replace(config, ray_history=False), **kwargs)
    assert torch.equal(accumulated.lowres[0], single.lowres[0])
    own = 2 / config.max_ao_rays
    plane = accumulated.lowres[:, SAMPLING.start]
    assert (plane >= own).all() and (plane <= 1).all() and plane[-1].max() > 2 * own
    assert (single.lowres[:, SAMPLING.start] == own).all()
    truth, covered = accumulated.highres[-1, AO.start], accumulated.highres[-1, MASK.start] > 0.5
    error = [(run.lowres[-1, SAMPLED_AO.start] - truth)[covered].abs().mean() for run in (accumulated, single)]
    assert error[0] < 0.8 * error[1]


def test_ray_history_data_for_a_model_that_also_upscales_accumulates_at_the_inputs_size():
    config = replace(TINY_RECON_X2_DATAGEN, frames=3, input_ao_rays=(2,), ray_history=True)
    volume, _, iso = datagen.resolve_volume("proc:cloud:1@32")
    cameras = datagen.camera_path(np.random.default_rng(3), config.frames)
    sequence = datagen.render_sequence(datagen.Renderer(volume, "cpu"), cameras, iso, config, seed=5, side=16,
                                       input_spp=1, input_ao_rays=2)
    plane = sequence.lowres[:, SAMPLING.start]
    assert plane.shape == (3, 16, 16) and sequence.highres.shape[-1] == 32
    assert (plane[0] == 2 / config.max_ao_rays).all() and plane[-1].max() > plane[0].max()


def test_ray_history_is_for_reconstruction_data():
    with pytest.raises(ValueError, match="ray_history are for reconstruction data"):
        tiny_datagen(ray_history=True)


def test_a_folder_written_before_a_config_field_existed_reads_it_as_its_default(fresh, tmp_path, monkeypatch):
    """Resuming a folder whose manifest predates ``reconstruction`` renders nothing new."""
    old = tmp_path / "old"
    old.mkdir()
    for item in fresh.iterdir():
        (old / item.name).symlink_to(item)
    manifest = json.loads((fresh / MANIFEST).read_text())
    del manifest["config"]["reconstruction"]
    (old / MANIFEST).unlink()
    (old / MANIFEST).write_text(json.dumps(manifest))
    monkeypatch.setattr(datagen, "render_sequence", lambda *a, **k: pytest.fail("rendered"))
    assert len(generate(TINY_DATAGEN, old, progress=False)["shards"]) == len(manifest["shards"])


def test_several_sides_render_sequences_of_each_with_crops_of_one_side_scaled_by_the_limits(tmp_path):
    config = replace(TINY_RECON_DATAGEN, volumes=("proc:sphere@32",), sequences=6, lowres_size=(16, 40),
                     input_ao_rays=(12, 16), max_ao_rays=16)
    manifest = generate(config, tmp_path, progress=False)
    assert {s["side"] for s in manifest["shards"]} == {16, 40}  # each side drawn (seeded: fixed)
    for shard in manifest["shards"]:
        lowres = load_file(tmp_path / shard["file"])["lowres"].float()
        assert lowres.shape[-2:] == (16, 16) and shard["crops"] == len(lowres)
        assert (lowres[:, :, SAMPLING][:, :, 0] == shard["input_ao_rays"] / 16).all()
    dataset = SequenceDataset(tmp_path, "train")
    assert dataset.limits == RayLimits(16, 4) and len(dataset) == sum(s["crops"] for s in manifest["shards"])


def test_a_single_side_renders_as_before_sides_could_be_listed(fresh, tmp_path):
    generate(tiny_datagen(lowres_size=(16,)), tmp_path, progress=False)
    listed = shard_tensors(tmp_path)
    for name, tensors in shard_tensors(fresh).items():
        for key in ("lowres", "flow", "highres"):
            assert torch.equal(tensors[key], listed[name][key]), (name, key)


# ---------------------------------------------------------------- the dataset


def test_sequence_dataset_items(tmp_path_factory):
    root = tiny_train_data(tmp_path_factory)
    manifest = json.loads((root / MANIFEST).read_text())
    train, val = SequenceDataset(root, "train"), SequenceDataset(root, "val")
    n_train = sum(s["crops"] for s in manifest["shards"] if s["split"] == "train")
    n_val = sum(s["crops"] for s in manifest["shards"] if s["split"] == "val")
    assert len(train) == n_train and len(val) == n_val
    assert train.volumes == ["proc:cloud:1@32"] * n_train and val.volumes == ["proc:sphere@32"] * n_val
    assert train.config == manifest["config"]
    item = train[0]
    assert isinstance(item, SequenceBatch) and item.frames == 3
    assert item.lowres.shape == (3, 5, 8, 8) and item.flow.shape == (3, 2, 8, 8)
    assert item.highres.shape == (3, 6, 16, 16)
    assert all(v.dtype == torch.float32 for v in item.tensors().values())
    assert item.flow_at(0) is None and torch.equal(item.flow_at(2), item.flow[2])
    # Items come in manifest order: the first crop of the first train shard.
    first = next(s for s in manifest["shards"] if s["split"] == "train")
    torch.testing.assert_close(item.highres, load_file(root / first["file"])["highres"][0].float())
    batch = train.batch(torch.tensor([1, 0]))
    assert len(batch) == 2 and torch.equal(batch[1].lowres, item.lowres) and batch.flow_at(1).shape == (2, 2, 8, 8)
    assert train.to("cpu") is train and train.crops.lowres.dtype == torch.float16


def test_sequence_dataset_errors(tmp_path_factory, tmp_path):
    root = tiny_train_data(tmp_path_factory)
    with pytest.raises(ValueError, match=r"no crops of split 'test'; splits there: \['train', 'val'\]"):
        SequenceDataset(root, "test")
    with pytest.raises(FileNotFoundError, match=r"no manifest.json in .*run `isosr datagen` first"):
        SequenceDataset(tmp_path, "train")


def test_shared_volumes_take_their_split_from_the_catalog(tmp_path):
    if not (shared_volumes_dir() / "volumes.json").is_file():
        pytest.skip(f"shared volumes not found at {shared_volumes_dir()} (set ISOSR_SHARED_VOLUMES)")
    config = tiny_datagen(volumes=("shared:headsq",), sequences=1, min_coverage=0.05)
    manifest = generate(config, tmp_path, progress=False)
    assert [s["split"] for s in manifest["shards"]] == ["val"]  # headsq is a validation volume
    assert manifest["shards"][0]["file"] == "shards/shared_headsq_0000.safetensors"
    assert len(SequenceDataset(tmp_path, "val")) == manifest["shards"][0]["crops"] > 0
