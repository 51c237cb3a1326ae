"""Training (isosr_net.train): checkpoints, logs, resuming, configs, the GAN setup, DDP on CPU."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from isosr_bench import bench_train
from isosr_net.configs import load_config
from isosr_net.datagen import DatagenConfig
from isosr_render.conventions import SAMPLED_AO, SAMPLING
from isosr_net.losses import PAPER_LOSSES
from isosr_net.model import Unrolled, build_model, load_pretrained, save_pretrained
from isosr_net.reconnet import GATE_LOGIT_INIT, ReconNet, ReconNetConfig
from isosr_net.train import Trainer, TrainConfig, narrowed_config, start_configs, weights_config
from test_reconnet import recon_batch
from net_fixtures import (TINY_MODEL, TINY_RECON_MODEL, random_vgg19, tiny_recon_upscaling_data, tiny_train_config,
                          tiny_train_data, tiny_wide_recon_data)

METRIC_KEYS = {"loss", "color_psnr", "color_ssim", "normal_psnr", "ao_psnr", "mask_iou"}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return tiny_train_data(tmp_path_factory)


def trainer(data: Path, out: Path, **overrides) -> Trainer:
    return Trainer(TrainConfig(**tiny_train_config(data, out, **overrides)))


def weights(folder: Path) -> dict[str, torch.Tensor]:
    net, _ = load_pretrained(folder)
    return net.state_dict()


def assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)


@pytest.fixture(scope="module")
def run3(data, tmp_path_factory) -> tuple[Path, dict]:
    """A 3-step run (2 crops per batch, 2 steps per epoch): its folder and returned metrics."""
    out = tmp_path_factory.mktemp("run3")
    t = trainer(data, out, steps=3)
    assert len(t.train_set) == 4  # the epoch arithmetic of these tests assumes 2 batches of 2 per epoch
    metrics = t.run(progress=False)
    return out, metrics


def test_a_tiny_run_writes_checkpoints_logs_and_metrics(run3, data):
    out, metrics = run3
    assert set(metrics) == METRIC_KEYS and all(isinstance(v, float) for v in metrics.values())
    assert 0 <= metrics["mask_iou"] <= 1 and 0 <= metrics["color_ssim"] <= 1
    for name in ("last", "best"):
        assert {"config.json", "model.safetensors"} <= {p.name for p in (out / name).iterdir()}, name
    assert (out / "last" / "training_state.pt").is_file()
    assert not (out / "best" / "training_state.pt").exists()
    assert not any(p.name.endswith((".tmp", ".old")) for p in out.iterdir())  # the swaps finished
    last = json.loads((out / "last" / "config.json").read_text())
    assert last["step"] == 3 and last["validation"] == metrics
    assert last["timing"]["processes"] == 1 and last["timing"]["steps"] == 3 and last["timing"]["train_s"] > 0
    assert 0 < last["timing"]["warmup_s"] <= last["timing"]["train_s"]  # the first WARMUP_STEPS (3), timed apart
    assert last["training"]["data"] == str(data) and last["training"]["steps"] == 3
    assert last["model"] == {"type": "SRNet", "upscale": 2, "channels": 8, "residual_blocks": 1,
                             "first_frame": "zeros", "tail": "full"}
    best = json.loads((out / "best" / "config.json").read_text())
    assert set(best["validation"]) == METRIC_KEYS and best["step"] in (2, 3)
    state = torch.load(out / "last" / "training_state.pt", weights_only=True)
    assert state["step"] == 3 and state["best"] == pytest.approx(best["validation"]["color_psnr"])
    events = list((out / "tb").glob("events.out.tfevents.*"))
    assert events and events[0].stat().st_size > 0


def test_tensorboard_logs_hold_train_and_val_scalars(run3):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run3[0] / "tb"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"train/total", "train/mask_l2", "train/normal_l1", "train/ao_l1"} <= tags
    assert {f"val/{k}" for k in METRIC_KEYS} <= tags
    assert [e.step for e in acc.Scalars("train/total")] == [1, 2, 3]
    assert [e.step for e in acc.Scalars("val/loss")] == [2, 3]  # after each epoch and at the end


def test_validations_come_every_validate_every_steps_across_epochs(data, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "run"
    trainer(data, out, steps=7, validate_every=3).run(progress=False)  # epochs of 2 steps
    acc = EventAccumulator(str(out / "tb"))
    acc.Reload()
    assert [e.step for e in acc.Scalars("val/loss")] == [3, 6, 7]
    assert json.loads((out / "last" / "config.json").read_text())["step"] == 7
    with pytest.raises(ValueError, match="validate_every"):
        TrainConfig(data="d", out="o", validate_every=-1)


def test_resuming_between_validations_equals_an_uninterrupted_run(data, tmp_path):
    whole, split = tmp_path / "whole", tmp_path / "split"
    trainer(data, whole, steps=5, validate_every=4).run(progress=False)
    trainer(data, split, steps=3, validate_every=4).run(progress=False)  # the last step saves mid-epoch
    trainer(data, split, steps=5, validate_every=4).run(progress=False)
    assert_same_weights(weights(whole / "last"), weights(split / "last"))


def test_training_changes_the_weights(run3, data, tmp_path):
    init = trainer(data, tmp_path)  # nothing to resume in an empty folder: the seeded initialization
    assert init.step == 0
    trained = weights(run3[0] / "last")
    assert any(not torch.equal(v, trained[k]) for k, v in init.net.state_dict().items())


def test_a_second_run_resumes_from_last(run3, data, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(run3[0], out)
    resumed = trainer(data, out, steps=5)
    assert "resuming from" in capsys.readouterr().out
    assert resumed.step == 3
    assert_same_weights(resumed.net.state_dict(), weights(run3[0] / "last"))
    assert resumed.optimizer.state_dict()["state"]  # Adam's moments came back too
    resumed.run(progress=False)
    assert resumed.step == 5
    assert json.loads((out / "last" / "config.json").read_text())["step"] == 5
    # Nothing left to do: a third run resumes at 5 and stops at once.
    again = trainer(data, out, steps=5)
    assert again.step == 5


def test_resuming_at_an_epoch_boundary_equals_an_uninterrupted_run(data, tmp_path):
    whole, split = tmp_path / "whole", tmp_path / "split"
    trainer(data, whole, steps=4).run(progress=False)
    trainer(data, split, steps=2).run(progress=False)  # 2 steps = one epoch of the tiny data
    trainer(data, split, steps=4).run(progress=False)
    assert_same_weights(weights(whole / "last"), weights(split / "last"))


def test_resuming_mid_epoch_equals_an_uninterrupted_run(data, tmp_path):
    whole, split = tmp_path / "whole", tmp_path / "split"
    trainer(data, whole, steps=4).run(progress=False)
    trainer(data, split, steps=3).run(progress=False)  # stops after the first batch of epoch 2
    trainer(data, split, steps=4).run(progress=False)
    assert_same_weights(weights(whole / "last"), weights(split / "last"))


def test_init_fine_tunes_a_model_folder_from_its_validated_start(run3, data, tmp_path, capsys):
    out = tmp_path / "tune"
    tune = trainer(data, out, steps=1, init=str(run3[0] / "best"))
    assert "fine-tuning" in capsys.readouterr().out and tune.step == 0
    assert_same_weights(tune.net.state_dict(), weights(run3[0] / "best"))
    assert not tune.optimizer.state_dict()["state"]  # a fresh optimizer: only the weights came
    tune.run(progress=False)
    assert "step 0: " in capsys.readouterr().out  # the starting model validated on this data first
    best = json.loads((out / "best" / "config.json").read_text())
    assert best["step"] in (0, 1) and set(best["validation"]) == METRIC_KEYS
    # A run that left last/ resumes from it, not from init.
    assert trainer(data, out, steps=2, init=str(run3[0] / "best")).step == 1


def test_a_fine_tune_that_never_beats_its_start_says_best_is_the_start(run3, data, tmp_path, capsys):
    out = tmp_path / "tune"
    tune = trainer(data, out, steps=2, init=str(run3[0] / "best"), lr=0.0)  # no step can beat the start
    tune.run(progress=False)
    assert tune.best_step == 0 and "best/ is the starting model" in capsys.readouterr().out
    assert trainer(data, out, steps=3, init=str(run3[0] / "best")).best_step == 0  # resumed with last/'s state
    trained = trainer(data, tmp_path / "trained", steps=2, init=str(run3[0] / "best"))
    trained.run(progress=False)
    assert ("best/ is the starting model" in capsys.readouterr().out) == (trained.best_step == 0)


@pytest.mark.parametrize("select, best_step", [("color_psnr", 1), ("loss", 2)])
def test_best_is_the_validated_step_with_the_best_selected_score(data, tmp_path, capsys, select, best_step):
    t = trainer(data, tmp_path / "run", select=select)
    validated = {1: {"color_psnr": 30.0, "loss": 0.5}, 2: {"color_psnr": 29.0, "loss": 0.4},
                 3: {"color_psnr": 29.5, "loss": 0.45}}
    for t.step, metrics in validated.items():
        t._validated(dict(metrics), writer=None)
    best = json.loads((tmp_path / "run" / "best" / "config.json").read_text())
    assert best["step"] == t.best_step == best_step
    assert t.best_score == validated[best_step][select] == best["validation"][select]
    with pytest.raises(ValueError, match="select must be one of"):
        trainer(data, tmp_path / "other", select="ao_psnr")


def test_init_of_another_model_config_is_refused(run3, data, tmp_path):
    with pytest.raises(ValueError, match="init .* holds a model of another config"):
        trainer(data, tmp_path / "tune", init=str(run3[0] / "best"), model={**TINY_MODEL, "channels": 4})


def test_resume_falls_back_to_last_old(run3, data, tmp_path):
    # A crash between the two renames of a checkpoint swap leaves only `last.old`.
    out = tmp_path / "run"
    shutil.copytree(run3[0] / "last", out / "last.old")
    assert trainer(data, out, steps=5).step == 3


def test_lr_schedules():
    constant = TrainConfig(data="d", out="o", steps=100, lr_schedule="constant")
    assert all(constant.lr_factor(s) == 1.0 for s in (0, 50, 100))
    cosine = TrainConfig(data="d", out="o", steps=100, lr_schedule="cosine", warmup_steps=10)
    assert cosine.lr_factor(0) == pytest.approx(0.1)
    assert cosine.lr_factor(9) == pytest.approx(1.0) and cosine.lr_factor(10) == pytest.approx(1.0)
    assert cosine.lr_factor(55) == pytest.approx(0.505)
    assert cosine.lr_factor(100) == pytest.approx(0.01) and cosine.lr_factor(500) == pytest.approx(0.01)
    factors = [cosine.lr_factor(s) for s in range(10, 101)]
    assert all(a >= b for a, b in zip(factors, factors[1:]))
    with pytest.raises(ValueError, match="lr_schedule must be 'constant' or 'cosine', got 'step'"):
        TrainConfig(data="d", out="o", lr_schedule="step")


def test_the_optimizer_follows_the_schedule(data, tmp_path):
    t = trainer(data, tmp_path, steps=10, lr=1e-3, lr_schedule="cosine", warmup_steps=4)
    batch = next(t._batches(t.train_set, shuffle=True, epoch=0))
    for step in range(3):
        t.step = step
        t.train_step(batch)
        assert t.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * (step + 1) / 4)


def test_unrolled_runs_the_recurrence_and_backpropagates_through_time(data):
    from isosr_net.model import build_model

    torch.manual_seed(0)
    net = build_model({"type": "SRNet", "upscale": 2, "channels": 8, "residual_blocks": 1})
    g = torch.Generator().manual_seed(1)
    lowres, flow = torch.rand(2, 3, 5, 4, 4, generator=g), torch.randn(2, 3, 2, 4, 4, generator=g)
    lowres.requires_grad_(True)
    outputs, warped = Unrolled(net)(lowres, flow)
    assert outputs.shape == warped.shape == (2, 3, 6, 8, 8)
    torch.testing.assert_close(warped[:, 0], net.first_previous(lowres[:, 0]))
    out1, warped1 = net.step(lowres[:, 1], flow[:, 1], outputs[:, 0])
    torch.testing.assert_close(outputs[:, 1], out1)
    torch.testing.assert_close(warped[:, 1], warped1)
    outputs[:, 2].sum().backward()  # the last frame depends on the first through the recurrence
    assert lowres.grad[:, 0].abs().sum() > 0


def test_data_for_another_upscale_is_refused(data, tmp_path):
    with pytest.raises(ValueError, match="is for upscale 2, the model upscales 4"):
        trainer(data, tmp_path, model={"type": "SRNet", "upscale": 4, "channels": 8, "residual_blocks": 1})


def test_cuda_without_a_gpu_is_a_clear_error(data, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(RuntimeError, match="device cuda asked for, but torch sees no GPU"):
        trainer(data, tmp_path, device="cuda")


def test_a_batch_larger_than_the_training_set_does_not_hang(data, tmp_path, monkeypatch):
    validations = []
    real = Trainer.validate

    def guarded(self):
        validations.append(1)
        if len(validations) > 4:
            raise RuntimeError("the training loop makes no progress")
        return real(self)

    monkeypatch.setattr(Trainer, "validate", guarded)
    with pytest.raises(ValueError, match="fewer than one batch"):
        trainer(data, tmp_path, steps=2, batch_size=64)


# ---------------------------------------------------------------- configs


def test_load_config_reads_json_and_applies_overrides(data, tmp_path):
    path = tmp_path / "train.json"
    path.write_text(json.dumps(tiny_train_config(data, tmp_path / "run")))
    config = load_config(TrainConfig, path, steps=7, out=None)
    assert config.steps == 7 and config.out == str(tmp_path / "run") and config.batch_size == 2
    assert config.losses == PAPER_LOSSES["l1-normal"]


@pytest.mark.parametrize("text, match", [
    ('{"data": "d", "out": "o", "learning_rate": 0.1}', r"unknown keys \['learning_rate'\]; TrainConfig knows"),
    ('{"data": "d", "out": "o",}', "not valid JSON"),
    ('["data", "out"]', "expected a JSON object of TrainConfig fields"),
    ('{"out": "o"}', "missing 1 required positional argument: 'data'"),
    ('{"data": "d", "out": "o", "lr_schedule": "linear"}', "lr_schedule must be"),
    ('{"data": "d", "out": "o", "batch_size": 0}', "batch_size must be at least 1, got 0"),
])
def test_load_config_errors_name_the_file(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        load_config(TrainConfig, path)
    if "lr_schedule" not in text and "batch_size" not in text:
        assert str(path) in str(info.value)


def test_the_shipped_configs_load():
    root = Path(__file__).resolve().parents[1] / "configs"
    for name in ("train_l1_normal.json", "train_gan1.json", "train_gan2.json"):
        config = load_config(TrainConfig, root / name)
        assert config.model["type"] == "SRNet"


@pytest.mark.parametrize("train, datagen", [("train_recon.json", "datagen_recon.json"),
                                            ("train_recon2.json", "datagen_recon2.json"),
                                            ("train_recon_x2.json", "datagen_recon_x2.json"),
                                            ("train_recon_history.json", "datagen_recon_history.json"),
                                            ("train_recon_x2_history.json", "datagen_recon_x2_history.json"),
                                            ("train_recon_x4.json", "datagen_recon_x4.json"),
                                            ("train_recon_4k.json", "datagen_recon_4k.json"),
                                            ("train_recon_blend.json", "datagen_recon_blend.json"),
                                            ("train_recon_blend_geo.json", "datagen_recon_blend_geo.json"),
                                            ("train_recon_gates.json", "datagen_recon_gates.json"),
                                            ("train_recon_shipped_gates.json", "datagen_recon_shipped_gates.json"),
                                            ("train_recon_map.json", "datagen_recon_map.json"),
                                            ("train_recon_map_4k.json", "datagen_recon_4k.json"),
                                            ("train_recon_variance_4k.json", "datagen_recon_4k.json"),
                                            ("train_recon_no_worse_4k.json", "datagen_recon_4k.json"),
                                            ("train_recon_narrow.json", "datagen_recon_4k.json"),
                                            ("train_recon_whole_4k.json", "datagen_recon_4k_seed1.json"),
                                            ("train_recon_spp4_4k.json", "datagen_recon_spp4_4k.json"),
                                            ("train_recon_teacher_4k.json", "datagen_recon_4k_seed1.json"),
                                            ("train_recon_stem.json", "datagen_recon_4k.json"),
                                            ("train_recon_stem_distil.json", "datagen_recon_4k.json"),
                                            ("train_recon_stem_geometry.json", "datagen_recon_4k.json"),
                                            ("train_recon_stem_pixel.json", "datagen_recon_4k.json")])
def test_each_reconstruction_config_fits_its_data_config(train, datagen):
    root = Path(__file__).resolve().parents[1] / "configs"
    config, data = load_config(TrainConfig, root / train), load_config(DatagenConfig, root / datagen)
    model = build_model(config.model).config
    if config.init:  # a project-relative model folder that the trainer starts this model from
        start = load_pretrained(root.parent / config.init)[0].config
        assert narrowed_config(weights_config(start), model) in start_configs(model)
    assert model.limits == data.limits and model.upscale == data.upscale and data.recon_inputs
    assert max(data.input_ao_rays) == data.max_ao_rays and max(data.input_spp) == data.max_spp
    run = train.removeprefix("train_").removesuffix(".json")  # scripts/train_recon.sh's RUN
    data_run = datagen.removeprefix("datagen_").removesuffix(".json")  # its own, or the data it shares (recon_map_4k)
    assert (config.data, config.out) == (f"data/{data_run}", f"runs/{run}")


def recon_step_with_the_temporal_loss(data: Path, tmp_path: Path, model: dict) -> Trainer:
    """A trainer of ``model`` on ``data`` after one step under the color and temporal losses: its
    losses finite, the temporal one not 0, the weights moved."""
    losses = [{"type": "channel", "channel": "color", "kind": "l1"}, {"type": "temporal", "weight": 1.0}]
    t = trainer(data, tmp_path / "run", steps=2, model=model, losses=losses)
    before = [p.detach().clone() for p in t.net.parameters()]
    logs = t.train_step(next(t._batches(t.train_set, shuffle=True, epoch=0)))
    assert logs["temporal"] > 0 and all(torch.isfinite(torch.tensor(v)) for v in logs.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, t.net.parameters()))
    return t


def test_a_reconstruction_model_over_the_rays_trains_with_the_temporal_loss_and_refuses_other_limits(
        tmp_path, tmp_path_factory):
    wide = tiny_wide_recon_data(tmp_path_factory)
    recon_step_with_the_temporal_loss(wide, tmp_path, {**TINY_RECON_MODEL, "ao_prior": "rays", "max_ao_rays": 16})
    with pytest.raises(ValueError, match=r"scales its sampling channels by RayLimits\(max_ao_rays=16, max_spp=4\), "
                                         r"the model by RayLimits\(max_ao_rays=8"):
        trainer(wide, tmp_path / "other", model=dict(TINY_RECON_MODEL))


@pytest.mark.parametrize("loss", ["ao_no_worse", "ao_psnr_no_worse"])
def test_a_reconstruction_trains_under_the_ao_no_worse_losses_and_an_upscaler_is_told_it_cannot(
        data, tmp_path, tmp_path_factory, loss):
    """The trainer gives a reconstruction's loss contexts its inputs (the rays' AO and counts), so the hinges on AO
    error beyond the rays' own (per pixel, per frame) train; an upscaler's run is told at its first step that the
    loss needs them."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    losses = [{"type": "channel", "channel": "color", "kind": "l1"}, {"type": loss, "weight": 1.0}]
    t = trainer(wide, tmp_path / "recon", steps=2, model={**TINY_RECON_MODEL, "ao_prior": "rays", "max_ao_rays": 16},
                losses=losses)
    batch = next(t._batches(t.train_set, shuffle=True, epoch=0))
    before = [p.detach().clone() for p in t.net.parameters()]
    logs = t.train_step(batch)
    assert math.isfinite(logs[loss]) and logs[loss] >= 0
    assert any(not torch.equal(a, b) for a, b in zip(before, t.net.parameters()))
    upscaler = trainer(data, tmp_path / "upscale", steps=2, losses=losses)
    with pytest.raises(ValueError, match=f"{loss} loss compares a reconstruction's AO"):
        upscaler.train_step(next(upscaler._batches(upscaler.train_set, shuffle=True, epoch=0)))


def test_a_fine_tune_held_to_its_teacher_starts_at_no_shortfall_and_trains(tmp_path, tmp_path_factory):
    """With its start as the teacher, a fine-tune's teacher loss is 0 before the first step (the same outputs), finite
    after, and the teacher stays as it was; a teacher no loss reads, a loss without a teacher and a teacher of other
    limits are refused, each naming what to give."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    model, _ = saved_wide_model(tmp_path / "start")
    losses = [{"type": "channel", "channel": "color", "kind": "l1"}, {"type": "teacher_psnr_no_worse", "weight": 1.0}]
    t = trainer(wide, tmp_path / "run", steps=2, model=model, losses=losses, init=str(tmp_path / "start"),
                teacher=str(tmp_path / "start"))
    batch = next(t._batches(t.train_set, shuffle=True, epoch=0))
    teacher = [p.detach().clone() for p in t.teacher.parameters()]
    assert t._losses(batch)[1]["teacher_psnr_no_worse"].item() == 0.0
    for _ in range(2):
        logs = t.train_step(batch)
    assert math.isfinite(logs["teacher_psnr_no_worse"]) and logs["teacher_psnr_no_worse"] >= 0
    assert all(torch.equal(a, b) for a, b in zip(teacher, t.teacher.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(teacher, t.net.parameters()))
    assert "loss" in t.validate()
    with pytest.raises(ValueError, match="no loss reads it"):
        trainer(wide, tmp_path / "r2", model=model, teacher=str(tmp_path / "start"))
    with pytest.raises(ValueError, match="give teacher, a model folder"):
        trainer(wide, tmp_path / "r3", model=model, losses=losses)
    saved_wide_model(tmp_path / "other", max_ao_rays=8)
    with pytest.raises(ValueError, match="sampling limits"):
        trainer(wide, tmp_path / "r4", model=model, losses=losses, teacher=str(tmp_path / "other"))


def test_a_stem_distils_a_teacher_of_another_architecture(tmp_path, tmp_path_factory):
    """A student with a stem of stride 2 trains against a stride-1 teacher's output (channel losses against the
    teacher): the terms are logged, finite, and move the student alone."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    saved_wide_model(tmp_path / "teacher")
    student, _ = saved_wide_model(tmp_path / "unused", stem_stride=2)
    losses = [{"type": "channel", "channel": "color", "kind": "l1"},
              {"type": "channel", "channel": "color", "kind": "l1", "against": "teacher"},
              {"type": "channel", "channel": "normal", "kind": "l1", "weight": 0.5, "against": "teacher"}]
    t = trainer(wide, tmp_path / "run", steps=2, model=student, losses=losses, teacher=str(tmp_path / "teacher"))
    batch = next(t._batches(t.train_set, shuffle=True, epoch=0))
    before = [p.detach().clone() for p in t.net.parameters()]
    logs = t.train_step(batch)
    assert logs["color_l1_teacher"] > 0 and math.isfinite(logs["normal_l1_teacher"])
    assert any(not torch.equal(a, b) for a, b in zip(before, t.net.parameters()))
    assert all(not p.requires_grad for p in t.teacher.parameters())


def saved_wide_model(folder: Path, **config) -> tuple[dict, ReconNet]:
    """A tiny ReconNet over 16 AO rays of ``config`` (TINY_RECON_MODEL's, changed), saved in ``folder``, for a run to
    start from: ``(its config as a run's model takes it, the model)``."""
    model = {**TINY_RECON_MODEL, "max_ao_rays": 16, **config}
    source = ReconNet(ReconNetConfig(**model))
    save_pretrained(source, folder)
    return model, source


def test_a_blend_model_fine_tunes_from_a_rays_model_and_trains_its_weight(tmp_path, tmp_path_factory):
    """ao_prior "blend" starts from a "rays" model of the same config (its weights, the blend at its first
    value) and trains the blend's weight with the rest; a model of another config stays refused."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    rays, source = saved_wide_model(tmp_path / "rays", ao_prior="rays")
    t = trainer(wide, tmp_path / "run", steps=2, model={**rays, "ao_prior": "blend"}, init=str(tmp_path / "rays"))
    assert all(torch.equal(v, t.net.state_dict()[k]) for k, v in source.state_dict().items())
    blend = t.net.ao_blend_log.detach().clone()
    cast = next(t._batches(t.train_set, shuffle=True, epoch=0))
    cast.lowres[:, :, SAMPLING.start] = 1.0  # 16 AO rays at each hit (without any the blend is the network's AO)
    cast.lowres[:, :, SAMPLED_AO] = 0.5
    logs = t.train_step(cast)
    assert all(torch.isfinite(torch.tensor(v)) for v in logs.values()) and not torch.equal(t.net.ao_blend_log, blend)
    with pytest.raises(ValueError, match="init .* holds a model of another config"):
        trainer(wide, tmp_path / "other", model={**rays, "ao_prior": "blend", "blocks": 2}, init=str(tmp_path / "rays"))
    save_pretrained(t.net, tmp_path / "blend")  # blend_beyond has no weights: a blend model starts one with it, whole
    beyond = trainer(wide, tmp_path / "beyond", model={**rays, "ao_prior": "blend", "blend_beyond": 1.0},
                     init=str(tmp_path / "blend"))
    assert beyond.net.config.blend_beyond == 1.0
    assert all(torch.equal(v, beyond.net.state_dict()[k]) for k, v in t.net.state_dict().items())


def test_a_narrower_reconnet_starts_from_a_wider_ones_first_channels_at_each_level(tmp_path, tmp_path_factory):
    """Widths under the init's at some levels: each tensor cut to its leading entries, which are each level's
    first channels; where the cut channels carry nothing (zeroed), the narrow model computes what the wide one
    does. A model wider than its init at any level stays refused."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    model, source = saved_wide_model(tmp_path / "wide", ao_prior="blend", blend_map=True, widths=(8, 4, 8, 16))
    with torch.no_grad():  # level 0's channels 4-7 and level 3's 8-15 off: the wide model is the narrow one, padded
        for layer, kept in ((source.head, 4), (source.reduce[0], 4), (source.fuse[0], 4), (source.down[2], 8),
                            *((conv, 8) for block in source.body for conv in (block.conv1, block.conv2))):
            layer.weight[kept:] = 0
            layer.bias[kept:] = 0
    save_pretrained(source, tmp_path / "wide")
    narrow = {**model, "widths": (4, 4, 8, 8)}
    t = trainer(wide, tmp_path / "run", steps=2, model=narrow, init=str(tmp_path / "wide"))
    assert t.net.head.weight.shape[0] == 4 and torch.equal(t.net.head.weight, source.head.weight[:4])
    assert torch.equal(t.net.tail.weight, source.tail.weight[:, :4]) and torch.equal(t.net.ao_blend_log,
                                                                                       source.ao_blend_log)
    inputs = recon_batch(1, 16, 24, seed=3)
    previous = torch.rand(1, 6, 16, 24, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        torch.testing.assert_close(t.net.eval()(inputs, previous), source.eval()(inputs, previous), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="init .* holds a model of another config"):
        trainer(wide, tmp_path / "other", model={**model, "widths": (8, 8, 8, 16)}, init=str(tmp_path / "wide"))


def test_a_gated_blend_model_fine_tunes_from_a_rays_model_and_trains_its_gates(tmp_path, tmp_path_factory):
    """geometry_gate: a model with the gates starts from one without (its weights, the gates at their start,
    nearly 1) and trains the gates of the batch's rays per pixel with the rest."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    rays, source = saved_wide_model(tmp_path / "rays", ao_prior="rays")
    t = trainer(wide, tmp_path / "run", steps=2, model={**rays, "ao_prior": "blend", "geometry_gate": True},
                init=str(tmp_path / "rays"))
    assert all(torch.equal(v, t.net.state_dict()[k]) for k, v in source.state_dict().items())
    gates = t.net.gate_logits.detach().clone()
    torch.testing.assert_close(gates, torch.full((4,), GATE_LOGIT_INIT))
    logs = t.train_step(next(t._batches(t.train_set, shuffle=True, epoch=0)))
    assert all(torch.isfinite(torch.tensor(v)) for v in logs.values())
    moved = (t.net.gate_logits - gates).abs().max().item()
    assert moved > 10 * t.config.lr, "the logits move GATE_RATE times faster than a weight"


def test_closed_gates_reopen_and_hold_while_the_corrections_learn(tmp_path, tmp_path_factory):
    """gates_open_until: a model whose gates closed starts with them open again; they stay there, untrained, while
    the rest trains, and train from that step on (a resumed run past it leaves them as they are); a model without
    gates is refused."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    model, source = saved_wide_model(tmp_path / "unused", ao_prior="blend", geometry_gate=True, stem_stride=2)
    with torch.no_grad():
        source.geometry_gate_raw.fill_(-0.2)  # closed: sigmoid(-10)
    save_pretrained(source, tmp_path / "closed")
    t = trainer(wide, tmp_path / "run", steps=2, model=model, init=str(tmp_path / "closed"), gates_open_until=2)
    opened = torch.full((4,), GATE_LOGIT_INIT)
    torch.testing.assert_close(t.net.gate_logits, opened)
    t.run(progress=False)
    torch.testing.assert_close(t.net.gate_logits, opened, rtol=0, atol=0)
    assert not torch.equal(t.net.tail.weight, source.tail.weight)
    resumed = trainer(wide, tmp_path / "run", steps=3, model=model, init=str(tmp_path / "closed"), gates_open_until=2)
    torch.testing.assert_close(resumed.net.gate_logits, opened, rtol=0, atol=0)  # its last/'s, not reopened
    resumed.run(progress=False)
    assert (resumed.net.gate_logits - opened).abs().max().item() > 10 * resumed.config.lr
    plain, _ = saved_wide_model(tmp_path / "plain")
    with pytest.raises(ValueError, match="gates_open_until holds a gated ReconNet's geometry gates"):
        trainer(wide, tmp_path / "other", model=plain, gates_open_until=2)
    with pytest.raises(ValueError, match="gates_open_until must be a step"):
        TrainConfig(data="d", out="o", gates_open_until=-1)


def test_a_stem_fine_tunes_into_one_with_a_pixel_tail_from_its_own_output(tmp_path, tmp_path_factory):
    """pixel_tail: a model with it starts from one without (its weights; the MLP's last layer zero, so the same
    output) and trains the MLP with the rest."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    stem, source = saved_wide_model(tmp_path / "stem", ao_prior="blend", geometry_gate=True, stem_stride=2)
    t = trainer(wide, tmp_path / "run", steps=2, model={**stem, "pixel_tail": 8}, init=str(tmp_path / "stem"))
    assert all(torch.equal(v, t.net.state_dict()[k]) for k, v in source.state_dict().items())
    assert not t.net.pixel_tail[2].weight.any() and not t.net.pixel_tail[2].bias.any()
    t.run(progress=False)
    assert t.net.pixel_tail[2].weight.abs().max().item() > 0.1 * t.config.lr
    back = {**stem, "pixel_tail": 0}
    with pytest.raises(ValueError, match="init .* holds a model of another config"):  # no way back: it has more
        trainer(wide, tmp_path / "back", model=back, init=str(tmp_path / "run" / "last"))


def test_a_run_trains_the_parameters_it_names_alone(tmp_path, tmp_path_factory):
    """``trainable``: the gates, the blend's weight and its map (a model with them, weighed by the rays' variance,
    started from a blend model without) move, every other parameter stays as ``init`` made it; a name the
    model lacks is refused."""
    wide = tiny_wide_recon_data(tmp_path_factory)
    blend, _ = saved_wide_model(tmp_path / "blend", ao_prior="blend")
    named = ["geometry_gate_raw", "ao_blend_log", "ao_blend_map.weight", "ao_blend_map.bias"]
    t = trainer(wide, tmp_path / "run", steps=2, init=str(tmp_path / "blend"), trainable=named,
                model={**blend, "geometry_gate": True, "blend_map": True, "blend_variance": True})
    assert not t.net.ao_blend_map.weight.any() and not t.net.ao_blend_map.bias.any()  # the map at its start
    before = {k: v.detach().clone() for k, v in t.net.named_parameters()}
    cast = next(t._batches(t.train_set, shuffle=True, epoch=0))
    cast.lowres[:, :, SAMPLING.start] = 1.0  # AO rays at each hit, so that the blend's weight has a gradient
    t.train_step(cast)
    moved = {k for k, v in t.net.named_parameters() if not torch.equal(v, before[k])}
    assert moved == set(named), moved
    with pytest.raises(ValueError, match="the model has no parameter gates"):
        trainer(wide, tmp_path / "other", model=blend, trainable=["gates"])


@pytest.mark.parametrize("s", [2, 4])
def test_a_reconstruction_model_that_upscales_trains_on_its_data_and_a_full_resolution_one_is_refused(
        tmp_path, tmp_path_factory, s):
    data = tiny_recon_upscaling_data(tmp_path_factory, s)
    t = recon_step_with_the_temporal_loss(data, tmp_path, {**TINY_RECON_MODEL, "ao_prior": "rays", "upscale": s})
    assert all(torch.isfinite(torch.tensor(v)) for v in t.validate().values())
    with pytest.raises(ValueError, match=f"is for upscale {s}, the model upscales 1"):
        trainer(data, tmp_path / "other", model=dict(TINY_RECON_MODEL))


# ---------------------------------------------------------------- the adversarial setup


def test_an_adversarial_run_trains_and_resumes_its_discriminator(data, tmp_path, tmp_path_factory):
    losses = [dict(c) for c in PAPER_LOSSES["gan-1"]]
    for c in losses:
        if c["type"] == "perceptual":
            c["weights_path"] = str(random_vgg19(tmp_path_factory))
    with pytest.raises(ValueError, match="discriminator's own step is not compiled"):
        trainer(data, tmp_path / "compiled", steps=2, losses=losses, compile="default")
    t = trainer(data, tmp_path, steps=2, losses=losses)
    assert t.d_optimizer is not None and len(t.adversarial) == 1
    d_before = {k: v.clone() for k, v in t.adversarial[0].state_dict().items()}
    logs = t.train_step(next(t._batches(t.train_set, shuffle=True, epoch=0)))
    assert {"total", "discriminator", "perceptual", "temporal", "adversarial"} <= set(logs)
    assert all(torch.isfinite(torch.tensor(v)) for v in logs.values())
    assert any(not torch.equal(v, t.adversarial[0].state_dict()[k]) for k, v in d_before.items())
    t.step = 0
    metrics = t.run(progress=False)
    assert t.step == 2 and set(metrics) == METRIC_KEYS
    state = torch.load(tmp_path / "last" / "training_state.pt", weights_only=True)
    assert "d_optimizer" in state and len(state["discriminators"]) == 1
    resumed = trainer(data, tmp_path, steps=3, losses=losses)
    assert resumed.step == 2
    for k, v in state["discriminators"][0].items():
        assert torch.equal(resumed.adversarial[0].state_dict()[k], v), k


# ---------------------------------------------------------------- DDP


def test_ddp_refuses_a_batch_smaller_than_its_processes(data, tmp_path):
    config = tmp_path / "train.json"
    config.write_text(json.dumps(tiny_train_config(data, tmp_path / "run", batch_size=1)))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("CUDA_VISIBLE_DEVICES", None)
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone",
                           "-m", "isosr_cli.main", "train", str(config)],
                          capture_output=True, text=True, timeout=180, env=env, cwd=tmp_path)
    assert proc.returncode != 0
    assert "batch_size 1 gives some of the 2 processes no share of a batch" in proc.stdout + proc.stderr


def test_ddp_on_two_cpu_processes_and_bench_train_compares_one_and_two_processes(data, tmp_path, monkeypatch):
    """The scaling study trains the same config from its start in 1 and 2 processes (gloo on CPUs) and
    reads both back: the same steps, times per step, the speedup against 1 and the scores. Its
    2-process run is `isosr train` under torchrun, DDP on two CPU processes: checked here as well."""
    config = tmp_path / "train.json"
    config.write_text(json.dumps(tiny_train_config(data, tmp_path / "unused", steps=5)))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    rows = bench_train.main(["--config", str(config), "--steps", "2", "--gpus", "1,2", "--device", "cpu",
                             "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "results")])
    ddp = tmp_path / "runs" / "processes2_seed0"
    assert {"config.json", "model.safetensors", "training_state.pt"} <= {p.name for p in (ddp / "last").iterdir()}
    last = json.loads((ddp / "last" / "config.json").read_text())
    assert last["step"] == 2 and last["timing"]["processes"] == 2 and last["timing"]["steps"] == 2
    assert (ddp / "best" / "model.safetensors").is_file()
    assert '"step_metrics"' in (ddp / "train.log").read_text()
    assert [(r["processes"], r["steps"], r["seed"]) for r in rows] == [(1, 2, 0), (2, 2, 0)]
    assert rows[0]["speedup"] == 1.0 and rows[1]["efficiency"] == pytest.approx(rows[1]["speedup"] / 2)
    assert all(r["ms_per_step"] > 0 and math.isfinite(r["val_color_psnr"]) and r["spread_db"] is None for r in rows)
    record = json.loads((tmp_path / "results" / "bench_train_cpu.json").read_text())
    assert record["rows"] == rows and not (tmp_path / "unused").exists()
    # Two seeds of one process, at once: two different models, their spread the range of their scores.
    rows = bench_train.main(["--config", str(config), "--steps", "2", "--gpus", "1", "--seeds", "0,1", "--concurrent",
                             "--batch-size", "4", "--device", "cpu", "--runs", str(tmp_path / "runs"),
                             "--out", str(tmp_path / "results")])
    assert [(r["seed"], r["batch_size"]) for r in rows] == [(0, 4), (1, 4)]
    assert rows[0]["val_color_psnr"] != rows[1]["val_color_psnr"]
    assert rows[0]["spread_db"] == pytest.approx(abs(rows[0]["val_color_psnr"] - rows[1]["val_color_psnr"]))
    # One seed again in a later call: the earlier call's other seed of the same study is kept beside it.
    again = bench_train.main(["--config", str(config), "--steps", "2", "--gpus", "1", "--seeds", "1",
                              "--batch-size", "4", "--device", "cpu", "--runs", str(tmp_path / "runs"),
                              "--out", str(tmp_path / "results")])
    assert [(r["seed"], r["batch_size"]) for r in again] == [(0, 4), (1, 4)]
    assert again[0]["val_color_psnr"] == rows[0]["val_color_psnr"] and again[1]["spread_db"] is not None
    with pytest.raises(SystemExit):
        bench_train.main(["--config", str(config), "--gpus", "2", "--device", "cpu"])  # no baseline


def test_a_compiled_step_is_the_eager_step(data, tmp_path, monkeypatch):
    """TrainConfig.compile: the step's forward and losses through torch.compile (here Dynamo's tracing
    with the eager backend and AOTAutograd, inductor's code generation left to the GPU) give the eager
    step's loss terms and weights; a bad mode is refused (adversarial losses: the adversarial test)."""
    compiled = []
    real = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, mode=None: compiled.append(mode) or real(fn, backend="aot_eager"))
    eager, fast = trainer(data, tmp_path / "eager", steps=2), trainer(data, tmp_path / "fast", steps=2, compile="default")
    assert compiled == ["default"]
    batch = next(eager._batches(eager.train_set, shuffle=False, epoch=0))
    for _ in range(2):
        a, b = eager.train_step(batch), fast.train_step(batch)
        assert a.keys() == b.keys() and all(abs(a[k] - b[k]) <= 1e-5 * max(1.0, abs(a[k])) for k in a), (a, b)
    for p, q in zip(eager.net.parameters(), fast.net.parameters()):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="compile must be one of"):
        TrainConfig(data=str(data), out=str(tmp_path / "x"), compile="reduce-overhead")
