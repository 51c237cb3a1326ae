"""`isosr datagen | train | eval | upscale` as a user runs them (in-process, through main())."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from isosr_cli.main import main
from isosr_net.datagen import MANIFEST
from isosr_net.evaluate import BASELINES, ORACLES, SCORES
from isosr_render.buffers import load_sequence, save_sequence
from net_fixtures import (TINY_DATAGEN, TINY_RECON_MODEL, relabel_as_val, render_lowres_frames, tiny_model_dir,
                          tiny_recon_data, tiny_train_config, tiny_train_data)


def write_json(path: Path, obj) -> Path:
    path.write_text(json.dumps(obj))
    return path


def one_line_error(capsys, command: str, *fragments: str) -> None:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"isosr {command}: error: "), err
    for fragment in fragments:
        assert fragment in err, err


@pytest.fixture(scope="module")
def cli_data(tmp_path_factory) -> Path:
    """A datagen folder written by `isosr datagen` (one volume, --sequences override)."""
    root = tmp_path_factory.mktemp("cli")
    config = {**asdict(TINY_DATAGEN), "volumes": ["proc:cloud:1@32"], "sequences": 5}
    path = write_json(root / "datagen.json", config)
    assert main(["datagen", str(path), "-o", str(root / "data"), "--sequences", "2", "--device", "cpu"]) == 0
    return root / "data"


def test_datagen(cli_data, capsys):
    manifest = json.loads((cli_data / MANIFEST).read_text())
    assert manifest["config"]["sequences"] == 2  # the override won over the file
    assert len(manifest["shards"]) == 2 and all(s["split"] == "train" for s in manifest["shards"])
    assert len(list((cli_data / "shards").glob("*.safetensors"))) == 2


def test_datagen_prints_a_summary(tmp_path, capsys):
    config = {**asdict(TINY_DATAGEN), "volumes": ["proc:sphere@32"], "sequences": 1}
    path = write_json(tmp_path / "datagen.json", config)
    assert main(["datagen", str(path), "-o", str(tmp_path / "data")]) == 0
    out = capsys.readouterr().out
    assert "1 sequences, crops per split {'train': " in out and str(tmp_path / "data") in out


def test_datagen_and_train_take_another_upscale_factor(tmp_path, tmp_path_factory):
    config = {**asdict(TINY_DATAGEN), "sequences": 1}
    path = write_json(tmp_path / "datagen.json", config)
    data = tmp_path / "data"
    assert main(["datagen", str(path), "-o", str(data), "--upscale", "4", "--lowres-size", "12"]) == 0
    relabel_as_val(data, "proc:sphere@32")
    manifest = json.loads((data / MANIFEST).read_text())
    assert manifest["config"]["upscale"] == 4 and manifest["config"]["lowres_size"] == 12
    train = write_json(tmp_path / "train.json", tiny_train_config(data, tmp_path / "run", steps=1))
    assert main(["train", str(train), "--upscale", "4"]) == 0
    assert json.loads((tmp_path / "run" / "last" / "config.json").read_text())["model"]["upscale"] == 4


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory) -> Path:
    """A run folder written by `isosr train` (--steps, --lr and --out overrides)."""
    root = tmp_path_factory.mktemp("cli_train")
    data = tiny_train_data(tmp_path_factory)
    path = write_json(root / "train.json", tiny_train_config(data, root / "ignored", steps=50))
    assert main(["train", str(path), "--steps", "2", "--lr", "0.0003", "--out", str(root / "run")]) == 0
    return root / "run"


def test_train(cli_run):
    assert not (cli_run.parent / "ignored").exists()
    for name in ("last", "best"):
        assert {"config.json", "model.safetensors"} <= {p.name for p in (cli_run / name).iterdir()}
    config = json.loads((cli_run / "last" / "config.json").read_text())
    assert config["step"] == 2 and config["training"]["steps"] == 2 and config["training"]["lr"] == 0.0003


def test_a_reconstruction_run_resumes(tmp_path, tmp_path_factory, capsys):
    """ReconNet's config holds a tuple (widths), a list once through config.json: resuming compares them alike."""
    data = tiny_recon_data(tmp_path_factory)
    config = tiny_train_config(data, tmp_path / "run", steps=2, model=dict(TINY_RECON_MODEL))
    path = write_json(tmp_path / "train.json", config)
    assert main(["train", str(path)]) == 0
    capsys.readouterr()
    assert main(["train", str(path), "--steps", "3"]) == 0
    assert f"resuming from {tmp_path / 'run' / 'last'} at step 2" in capsys.readouterr().out
    last = json.loads((tmp_path / "run" / "last" / "config.json").read_text())
    assert last["step"] == 3 and last["model"]["widths"] == list(TINY_RECON_MODEL["widths"])


def test_train_prints_the_metrics(tmp_path, tmp_path_factory, capsys):
    data = tiny_train_data(tmp_path_factory)
    path = write_json(tmp_path / "train.json", tiny_train_config(data, tmp_path / "run", steps=1))
    assert main(["train", str(path)]) == 0
    out = capsys.readouterr().out
    printed = json.loads(out[out.index("{"):])
    assert {"loss", "color_psnr", "mask_iou"} <= set(printed["step_metrics"])
    best = json.loads((tmp_path / "run" / "best" / "config.json").read_text())
    assert printed["best"] == {"step": best["step"], "color_psnr": best["validation"]["color_psnr"]}


def test_eval_prints_a_table_and_writes_json(cli_run, tmp_path_factory, tmp_path, capsys):
    data = tiny_train_data(tmp_path_factory)
    record_path = tmp_path / "eval" / "scores.json"
    assert main(["eval", "--model", str(cli_run / "best"), "--data", str(data), "--json", str(record_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| volume | method | " + " | ".join(SCORES) + " |"
    rows = [line for line in lines if line.startswith("| proc:")]
    assert sorted(line.split(" | ")[1] for line in rows) == sorted(("network",) + BASELINES)
    assert any(line.startswith("| proc:sphere@32 | network | ") for line in rows)
    assert any(line.startswith("| proc:sphere@32 | bilinear | ") for line in rows)
    assert any("proc:sphere@32: color PSNR gain" in line and "over bilinear" in line for line in lines)
    record = json.loads(record_path.read_text())
    assert record["split"] == "val" and record["precision"] == "fp32" and record["model"] == str(cli_run / "best")
    methods = ("network",) + BASELINES
    assert {(r["volume"], r["method"]) for r in record["rows"]} == {("proc:sphere@32", m) for m in methods}
    by_method = {r["method"]: r for r in record["rows"]}
    gains = record["gains"]["proc:sphere@32"]
    network = by_method["network"]["color_psnr"]
    assert gains["vs_bilinear"] == pytest.approx(network - by_method["bilinear"]["color_psnr"])
    best = max(by_method[m]["color_psnr"] for m in BASELINES)
    assert gains["vs_best_baseline"] == pytest.approx(network - best)
    for row in record["rows"]:
        assert set(SCORES) <= set(row) and 0 <= row["mask_iou"] <= 1


def test_eval_oracles_bound_the_error(cli_run, tmp_path_factory, tmp_path):
    data = tiny_train_data(tmp_path_factory)
    record_path = tmp_path / "scores.json"
    assert main(["eval", "--model", str(cli_run / "best"), "--data", str(data), "--oracles",
                 "--json", str(record_path)]) == 0
    by_method = {r["method"]: r for r in json.loads(record_path.read_text())["rows"]}
    assert set(ORACLES) < set(by_method)
    geometry, ao = by_method["oracle: true geometry, no AO"], by_method["oracle: bilinear + true AO"]
    assert geometry["normal_psnr"] == pytest.approx(100) and geometry["mask_iou"] == 1
    assert ao["ao_psnr"] == pytest.approx(100) and ao["normal_psnr"] == by_method["bilinear"]["normal_psnr"]
    # A sphere occludes nothing (true AO 1), so knowing the true AO leaves bilinear's color as it is.
    assert ao["color_psnr"] == pytest.approx(by_method["bilinear"]["color_psnr"])


def test_eval_another_split(cli_data, tmp_path_factory, capsys):
    model = tiny_model_dir(tmp_path_factory)
    assert main(["eval", "--model", str(model), "--data", str(cli_data), "--split", "train"]) == 0
    out = capsys.readouterr().out
    assert "| proc:cloud:1@32 | network | " in out and "| proc:cloud:1@32 | bicubic | " in out


def test_eval_errors(cli_data, tmp_path_factory, tmp_path, capsys):
    model = tiny_model_dir(tmp_path_factory)
    assert main(["eval", "--model", str(model), "--data", str(cli_data)]) == 2  # no "val" split there
    one_line_error(capsys, "eval", "no crops of split 'val'")
    assert main(["eval", "--model", str(model), "--data", str(tmp_path)]) == 2
    one_line_error(capsys, "eval", "no manifest.json")
    assert main(["eval", "--model", str(tmp_path / "nowhere"), "--data", str(cli_data)]) == 2
    one_line_error(capsys, "eval", "not a model folder")


@pytest.fixture
def sequence_file(tmp_path) -> Path:
    frames = render_lowres_frames(24, 24, frames=3)
    frames[0].flow = torch.zeros(24, 24, 2)  # a sequence file holds the same buffers in every frame
    path = tmp_path / "seq.npz"
    save_sequence(frames, path)
    return path


def test_upscale_writes_frames_and_pngs(sequence_file, tmp_path_factory, tmp_path, capsys):
    model = tiny_model_dir(tmp_path_factory)
    out, png = tmp_path / "out.npz", tmp_path / "png"
    assert main(["upscale", str(sequence_file), "-o", str(out), "--model", str(model), "--png", str(png)]) == 0
    assert "upscaled 3 frames to 48x48 on cpu" in capsys.readouterr().out
    frames = load_sequence(out)
    assert len(frames) == 3
    for frame in frames:
        assert frame.present() == ["mask", "normal", "depth", "ao"]
        assert frame.mask.shape == (48, 48) and frame.normal.shape == (48, 48, 3)
    with np.load(out) as z:
        assert z["mask"].shape == (3, 48, 48) and z["normal"].shape == (3, 48, 48, 3)
    assert sorted(p.name for p in png.iterdir()) == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    image = cv2.imread(str(png / "frame_0001.png"))
    assert image.shape == (48, 48, 3)
    assert (image == 255).all(axis=-1).any() and (image < 250).any()  # background and surface


def test_upscale_matches_the_upscaler_api(sequence_file, tmp_path_factory, tmp_path):
    from isosr_net.upscaler import Upscaler

    model = tiny_model_dir(tmp_path_factory)
    out = tmp_path / "out.npz"
    assert main(["upscale", str(sequence_file), "-o", str(out), "--model", str(model), "--tile", "8"]) == 0
    cli = load_sequence(out)
    up = Upscaler(model)
    for t, frame in enumerate(load_sequence(sequence_file)):
        if t == 0:
            frame.flow = None  # the first frame starts the stream, whatever flow the file holds
        expected = up.upscale(frame)
        for name in ("mask", "normal", "depth", "ao"):
            torch.testing.assert_close(getattr(cli[t], name), getattr(expected, name), atol=1e-4, rtol=0)


def test_upscale_with_the_shipped_model(sequence_file, tmp_path, capsys):
    out = tmp_path / "out.npz"
    assert main(["upscale", str(sequence_file), "-o", str(out)]) == 0
    assert load_sequence(out)[0].mask.shape == (96, 96)


def test_upscale_errors(sequence_file, tmp_path, capsys):
    assert main(["upscale", str(tmp_path / "missing.npz"), "-o", str(tmp_path / "o.npz")]) == 2
    one_line_error(capsys, "upscale")
    with np.load(sequence_file) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["normal"][1, 2, 3, 0] = np.nan
    bad = tmp_path / "nan.npz"
    np.savez(bad, **arrays)
    assert main(["upscale", str(bad), "-o", str(tmp_path / "o.npz")]) == 2
    one_line_error(capsys, "upscale", "normal holds NaN or Inf")
    assert not (tmp_path / "o.npz").exists()


@pytest.mark.parametrize("command", ["datagen", "train"])
@pytest.mark.parametrize("text, fragment", [
    ('{"volumes": ["proc:sphere"], "colour": 1}', "unknown keys ['colour'"),
    ('{"volumes": ["proc:sphere"],', "not valid JSON"),
    ('[1, 2]', "expected a JSON object"),
])
def test_bad_config_file_is_exit_code_2_with_one_line(tmp_path, capsys, command, text, fragment):
    path = tmp_path / "bad.json"
    path.write_text(text)
    argv = [command, str(path)] + (["-o", str(tmp_path / "out")] if command == "datagen" else [])
    assert main(argv) == 2
    one_line_error(capsys, command, str(path), fragment)
    assert not (tmp_path / "out").exists()


def test_missing_config_file_is_exit_code_2(tmp_path, capsys):
    assert main(["train", str(tmp_path / "none.json")]) == 2
    one_line_error(capsys, "train", "none.json")


def test_bad_config_values_are_exit_code_2(tmp_path, capsys):
    path = write_json(tmp_path / "d.json", {**asdict(TINY_DATAGEN), "crop": 64})
    assert main(["datagen", str(path), "-o", str(tmp_path / "out")]) == 2
    one_line_error(capsys, "datagen", "crop 64 exceeds the low-res render side 16")
    path = write_json(tmp_path / "t.json", {"data": str(tmp_path), "out": str(tmp_path / "run"),
                                            "lr_schedule": "exp", "device": "cpu"})
    assert main(["train", str(path)]) == 2
    one_line_error(capsys, "train", "lr_schedule must be")


def test_eval_in_bf16(cli_data, tmp_path_factory, tmp_path):
    model = tiny_model_dir(tmp_path_factory)
    path = tmp_path / "bf16.json"
    assert main(["eval", "--model", str(model), "--data", str(cli_data), "--split", "train", "--precision", "bf16",
                 "--json", str(path)]) == 0
    record = json.loads(path.read_text())
    assert record["precision"] == "bf16" and np.isfinite(record["gains"]["proc:cloud:1@32"]["vs_bilinear"])


def test_train_into_a_run_of_another_model_is_a_one_line_error(tmp_path, tmp_path_factory, capsys):
    data = tiny_train_data(tmp_path_factory)
    config = tiny_train_config(data, tmp_path / "run", steps=1)
    assert main(["train", str(write_json(tmp_path / "a.json", config))]) == 0
    capsys.readouterr()
    config["model"] = {**config["model"], "channels": 16}
    assert main(["train", str(write_json(tmp_path / "b.json", config)), "--steps", "2"]) == 2
    one_line_error(capsys, "train", str(tmp_path / "run"))


def test_a_model_folder_whose_weights_do_not_fit_is_a_one_line_error(sequence_file, tmp_path_factory, tmp_path,
                                                                      capsys):
    import shutil

    model = tmp_path / "model"
    shutil.copytree(tiny_model_dir(tmp_path_factory), model)
    config = json.loads((model / "config.json").read_text())
    config["model"]["channels"] = 16
    write_json(model / "config.json", config)
    assert main(["upscale", str(sequence_file), "-o", str(tmp_path / "o.npz"), "--model", str(model)]) == 2
    one_line_error(capsys, "upscale", "weights do not fit the config")
