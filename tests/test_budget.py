"""quality="auto": the budget policy on small scenes (on the CPU; on a GPU machine
``ISOSR_TEST_DEVICE=cuda pytest tests/test_budget.py`` runs the policy there)."""

from __future__ import annotations

import math

import pytest
import torch

from isosr_render import Renderer, open_volume, orbit, orbit_path, resolve_iso
from conftest import DEVICE, record_make_batch
from isosr_net.budget import (AO_MATTERS_DB, BATCH_WARMUP, BudgetConfig, choose_method, default_candidates,
                              default_probe_height, probe_size, render_within_budget)
from isosr_net import budget as policy
from isosr_net.methods import FrameMethod, Networks
from isosr_net.model import save_pretrained
from isosr_net.reconnet import RayLimits, ReconNet, ReconNetConfig
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL, Reconstructor, recon_limits
from isosr_server.auto import AutoPolicy

SIZE = (96, 64)
FEW = (FrameMethod.of("upscale", factor=4), FrameMethod.of("full"), FrameMethod.of("full", ao_rays=4),
       FrameMethod.of("atrous", ao_rays=2), FrameMethod.of("full", spp=2), FrameMethod.of("full", ao_rays=8, spp=2))


def scene(spec: str):
    volume = open_volume(spec)
    return Renderer(volume, DEVICE), resolve_iso(spec, volume)


@pytest.fixture(scope="module")
def sphere():
    return scene("proc:sphere@32")


@pytest.fixture(scope="module")
def cloud():
    return scene("proc:cloud:7@48")


def check_budget_respected(choice, headroom: float = BudgetConfig().headroom):
    """The choice fits in its own timing within the headroom, every better candidate was timed
    over it, none after it."""
    ranked = [row.method for row in choice.table]
    at = ranked.index(choice.method)
    limit = headroom * choice.budget_ms
    if choice.fits:
        assert choice.ms <= limit
        assert all(row.ms > limit for row in choice.table[:at])
        assert all(row.ms is None for row in choice.table[at + 1:])
    else:
        assert all(row.ms is not None and row.ms > limit for row in choice.table)
        assert choice.ms == min(row.ms for row in choice.table)



def test_a_frame_fits_a_budget_within_its_headroom():
    """The policy's one test of fitting, its bound inclusive; an untimed (inf) or unmeasurable (NaN) time fits no
    budget."""
    assert policy.fits(9.0, 10.0, 0.9) and not policy.fits(9.001, 10.0, 0.9) and policy.fits(10.0, 10.0, 1.0)
    assert not policy.fits(math.nan, 10.0, 0.9) and not policy.fits(math.inf, 1e9, 1.0)


def test_a_convex_sphere_gets_no_ao(sphere):
    renderer, iso = sphere
    choice = choose_method(renderer, iso, *SIZE, 1000.0)  # the default candidates, network included
    assert choice.ao_effect_db >= AO_MATTERS_DB and not choice.ao_matters
    assert all(row.method.ao_rays == 0 for row in choice.table)
    assert {row.method.kind for row in choice.table} == {"full", "upscale", "network"}
    assert choice.method.ao_rays == 0 and choice.fits
    check_budget_respected(choice)


def test_ao_rays_where_ao_matters(cloud):
    renderer, iso = cloud
    choice = choose_method(renderer, iso, *SIZE, 1000.0, BudgetConfig(candidates=FEW))
    assert choice.ao_matters and choice.ao_effect_db < AO_MATTERS_DB
    assert choice.method.ao_rays > 0 and choice.fits
    check_budget_respected(choice)
    # Expected quality ranks the table; AO rays beat none at the same rays per pixel.
    psnr = {row.method: row.expected_psnr for row in choice.table}
    assert psnr[FrameMethod.of("full", ao_rays=8, spp=2)] > psnr[FrameMethod.of("full", spp=2)]
    assert [row.expected_psnr for row in choice.table] == sorted(psnr.values(), reverse=True)


@pytest.mark.filterwarnings("ignore:no method fits:RuntimeWarning")  # 2 ms may fit nothing on a busy CPU
@pytest.mark.parametrize("budget", [2.0, 6.0])
def test_the_choice_respects_the_budget_in_the_probes_own_timing(cloud, budget):
    renderer, iso = cloud
    choice = choose_method(renderer, iso, *SIZE, budget, BudgetConfig(candidates=FEW))
    check_budget_respected(choice)


def test_a_budget_below_anything_feasible_takes_the_fastest_and_says_so(cloud):
    renderer, iso = cloud
    with pytest.warns(RuntimeWarning, match="no method fits the budget of 0.0001 ms"):
        choice = choose_method(renderer, iso, *SIZE, 1e-4, BudgetConfig(candidates=FEW))
    assert not choice.fits and "NOTHING FITS" in choice.summary()
    check_budget_respected(choice)


def test_an_empty_image_ties_every_candidate_and_takes_the_first_that_fits(cloud):
    renderer, _ = cloud
    frame, choice = render_within_budget(renderer, orbit(30, 20, 1.8), 2.0, *SIZE, 1000.0,
                                         BudgetConfig(candidates=FEW))  # iso 2: outside the data
    assert math.isnan(choice.expected_psnr) and math.isnan(choice.ao_effect_db) and not choice.ao_matters
    assert choice.method == FEW[0] and choice.fits
    assert frame.mask.max() == 0 and frame.color.min() == 1  # the background


def test_bad_sizes_budgets_and_configs_are_refused(cloud):
    renderer, iso = cloud
    for w, h in ((0, 64), (96, 0), (96.0, 64)):
        with pytest.raises(ValueError, match="must be an integer >= 1"):
            choose_method(renderer, iso, w, h, 10.0)
    for budget in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="budget_ms"):
            choose_method(renderer, iso, *SIZE, budget)
    with pytest.raises(ValueError, match="divides"):
        choose_method(renderer, iso, 97, 64, 10.0, BudgetConfig(candidates=(FrameMethod.of("upscale", factor=4),)))
    with pytest.raises(ValueError, match="probe_height"):
        BudgetConfig(probe_height=0)
    with pytest.raises(ValueError, match="candidates is empty"):
        BudgetConfig(candidates=())


def test_probe_size_keeps_the_aspect_in_multiples_of_8():
    assert probe_size(1920, 1080, 96) == (168, 96)
    gpu_rows = default_probe_height("cuda:0")
    assert probe_size(1920, 1080, gpu_rows, 0.25) == probe_size(3840, 2160, gpu_rows, 0.25) == (968, 544)
    assert probe_size(1920, 1080, default_probe_height("cpu"), 0.25) == (480, 272)
    assert probe_size(3840, 2160, 96) == (168, 96)
    assert probe_size(96, 64, 96) == (96, 64)


def test_isosr_render_budget_ms_prints_the_choice_and_writes_its_frame(tmp_path, capsys):
    from isosr_cli.main import main as cli

    out = tmp_path / "frame.npz"
    assert cli(["render", "proc:sphere@32", "--size", "96x64", "--budget-ms", "1000", "--device", DEVICE,
                "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "quality auto: full, AO 0" in said and "no AO" in said  # the sphere: no AO rays
    import numpy as np

    with np.load(out) as frame:
        assert frame["color"].shape == (64, 96, 3) and "ao" not in frame.files
        whole = frame["mask"].sum()
    # With a clip, the probe and the frame are clipped: a plane across x keeps less of the sphere.
    assert cli(["render", "proc:sphere@32", "--size", "96x64", "--budget-ms", "1000", "--device", DEVICE,
                "--clip-plane=0,0,0,-1,0,0", "-o", str(out)]) == 0
    assert "quality auto:" in capsys.readouterr().out
    with np.load(out) as frame:
        assert 0 < frame["mask"].sum() < 0.8 * whole
    with pytest.raises(SystemExit) as refused:  # before the volume is opened
        cli(["render", "proc:sphere@32", "--size", "96x0", "--budget-ms", "10", "-o", str(out)])
    assert refused.value.code == 2 and "sides must be positive, got '96x0'" in capsys.readouterr().err
    assert cli(["render", "proc:sphere@32", "--budget-ms", "-5", "-o", str(tmp_path / "bad.png")]) == 2
    assert "budget_ms must be a positive" in capsys.readouterr().err
    assert not (tmp_path / "bad.png").exists()


@pytest.mark.parametrize("headroom", [0.0, -0.5, 1.01])
def test_headroom_outside_0_1_is_refused(headroom):
    with pytest.raises(ValueError, match="headroom"):
        BudgetConfig(headroom=headroom)


def test_the_candidates_reach_the_models_rays_per_pixel_and_more_ao_rays_there():
    """The reconstruction's candidates stay within its model's rays per pixel; at 4 they go past
    its AO rays (32, 64: its runner reads their mean as its max_ao_rays)."""
    def recon_samplings(candidates, factor=1):
        return {(m.ao_rays, m.spp) for m in candidates if m.kind == "reconstruct" and m.factor == factor}

    shipped = recon_samplings(default_candidates("cpu"))
    assert {(8, 2), (8, 4), (16, 4), (32, 4), (64, 4)} <= shipped
    assert max(n for n, s in shipped if s < 4) == 8 and max(n for n, _ in shipped) == 64
    assert recon_samplings(default_candidates("cpu", limits=RayLimits(8, 2))) == {
        (n, s) for n in (1, 2, 4) for s in (1, 2)} | {(8, 2)}
    # A server on the first model (8 AO rays, 4 rays per pixel at most): past 8 it reads 8.
    v1 = DEFAULT_RECON_MODEL.parent / "recon_model_v1"
    policy = AutoPolicy.for_server("cpu", "fp32", 4, {Reconstructor: (v1, "recon")}, 30.0, Networks())
    served = recon_samplings(policy.candidates)
    assert {(16, 4), (64, 4)} <= served and recon_limits(v1).read(64) == 8
    assert all(m.options.model == str(v1) for m in policy.candidates if m.kind == "reconstruct")
    assert not recon_samplings(policy.candidates, factor=2), "no x2 model given: no x2 candidates"


def test_the_x2_reconstruction_is_a_candidate_at_the_samplings_its_model_takes(tmp_path):
    x2 = [m for m in default_candidates("cuda") if m.kind == "reconstruct" and m.factor == 2]
    assert {(m.ao_rays, m.spp) for m in x2} == {(1, 1), (2, 1), (4, 1), (8, 1), (16, 1), (4, 2)}
    assert all((m.options.model, m.options.precision, m.name.startswith("x2, ")) == (str(RECON_X2_MODEL), "fp16", True)
               for m in x2)
    save_pretrained(ReconNet(ReconNetConfig(widths=(4, 4, 8, 8), blocks=1, upscale=2, max_ao_rays=4, max_spp=2)), tmp_path)
    small = [m for m in default_candidates("cpu", x2_model=tmp_path) if m.factor == 2 and m.kind == "reconstruct"]
    assert {(m.ao_rays, m.spp) for m in small} == {(1, 1), (2, 1), (4, 1), (4, 2)}
    assert not [m for m in default_candidates("cpu", x2_model=None) if m.kind == "reconstruct" and m.factor == 2]


# default_candidates("cuda") before the kinds declared their own candidates (issue 46): (kind, name).
CUDA_CANDIDATES = [
    ("upscale", "x4 bilinear"), ("upscale", "x2 bilinear"), ("full", "full, AO 0, spp 1"),
    ("network", "x4 network bf16"), ("full", "full, AO 1, spp 1"), ("reconstruct", "x2, AO 1, spp 1, recon_x2 fp16"),
    ("atrous", "full, AO 1, a-trous"), ("reconstruct", "x2, AO 2, spp 1, recon_x2 fp16"),
    ("reconstruct", "full, AO 1, spp 1, network fp16"), ("full", "full, AO 2, spp 1"),
    ("reconstruct", "x2, AO 4, spp 1, recon_x2 fp16"), ("atrous", "full, AO 2, a-trous"),
    ("reconstruct", "full, AO 2, spp 1, network fp16"), ("reconstruct", "x2, AO 8, spp 1, recon_x2 fp16"),
    ("full", "full, AO 4, spp 1"), ("atrous", "full, AO 4, a-trous"),
    ("reconstruct", "x2, AO 4, spp 2, recon_x2 fp16"), ("reconstruct", "full, AO 4, spp 1, network fp16"),
    ("reconstruct", "x2, AO 16, spp 1, recon_x2 fp16"), ("reconstruct", "full, AO 1, spp 2, network fp16"),
    ("full", "full, AO 8, spp 1"), ("full", "full, AO 0, spp 2"), ("reconstruct", "full, AO 2, spp 2, network fp16"),
    ("reconstruct", "full, AO 4, spp 2, network fp16"), ("full", "full, AO 16, spp 1"),
    ("full", "full, AO 8, spp 2"), ("full", "full, AO 0, spp 4"), ("reconstruct", "full, AO 1, spp 4, network fp16"),
    ("reconstruct", "full, AO 2, spp 4, network fp16"), ("reconstruct", "full, AO 4, spp 4, network fp16"),
    ("reconstruct", "full, AO 8, spp 2, network fp16"), ("reconstruct", "full, AO 8, spp 4, network fp16"),
    ("full", "full, AO 32, spp 1"), ("full", "full, AO 64, spp 1"), ("full", "full, AO 16, spp 4"),
    ("reconstruct", "full, AO 16, spp 4, network fp16"), ("reconstruct", "full, AO 32, spp 4, network fp16"),
    ("reconstruct", "full, AO 64, spp 4, network fp16"),
]


def test_the_default_candidates_are_the_same_in_the_same_order():
    """The kinds' own candidates, merged by rank, are the list the policy had (ties break by order)."""
    cuda = default_candidates("cuda")
    assert [(m.kind, m.name) for m in cuda] == CUDA_CANDIDATES
    assert all(getattr(m.options, "model", None) == (str(RECON_X2_MODEL) if m.name.startswith("x2, ") else None)
               for m in cuda)
    cpu = default_candidates("cpu")
    assert [(m.kind, m.name) for m in cpu] == [(k, n.replace("bf16", "fp32").replace("fp16", "fp32"))
                                               for k, n in CUDA_CANDIDATES]


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA graphs: ISOSR_TEST_DEVICE=cuda on the GPU machine")
def test_no_timed_frame_captures_a_graph(cloud, monkeypatch):
    """A reconstruction timed along a path replays its CUDA graphs in every timed frame: the
    warm-up has captured them all (a timed capture made it look twice as slow and lose budgets)."""
    import isosr_net.budget as budget

    captures, timed = [], []
    capture, frame_ms = Reconstructor._capture, budget._frame_ms
    monkeypatch.setattr(Reconstructor, "_capture", lambda self, *a, **k: captures.append(1) or capture(self, *a, **k))

    def counted(*args):
        before = len(captures)
        ms = frame_ms(*args)
        timed.append(len(captures) - before)
        return ms

    monkeypatch.setattr(budget, "_frame_ms", counted)
    method = FrameMethod.of("reconstruct", ao_rays=1, precision="fp16")
    choose_method(*cloud, *SIZE, 1e4, BudgetConfig(candidates=(method,)), orbit_path(6, yaw_step=3.0),
                  networks=Networks())
    assert captures and timed == [0] * BudgetConfig().timing_frames


def test_a_candidate_whose_floor_is_over_twice_the_budget_is_not_timed(cloud):
    """A candidate whose probe-size frame took 8 ms, at a frame of 16 times the pixels, has a floor of
    64 ms: at a 10 ms budget it is not timed (its row says floored), while one that took 0.1 ms is; a
    quality probe without times (a GPU's) floors nothing."""
    renderer, iso = cloud
    dear, cheap = FrameMethod.of("full", ao_rays=4, spp=4), FrameMethod.of("upscale", factor=4)
    w, h = SIZE
    quality = policy.QualityProbe((w // 4, h // 4), {dear: 40.0, cheap: 30.0}, 10.0, True, 0.0, {dear: 8.0, cheap: 0.1})
    assert policy.floor_ms(dear, quality, w, h) == pytest.approx(64.0)
    timings = {}
    choice = choose_method(renderer, iso, w, h, 10.0, BudgetConfig(candidates=(dear, cheap)), quality=quality,
                           timings=timings)
    assert dear not in timings and cheap in timings
    rows = {row.method: row for row in choice.table}
    assert rows[dear].floored and rows[dear].ms == pytest.approx(64.0)
    assert not rows[cheap].floored and choice.method == cheap
    untimed = policy.QualityProbe(quality.size, quality.psnr, 10.0, True, 0.0)
    timings = {}
    choose_method(renderer, iso, w, h, 10.0, BudgetConfig(candidates=(dear, cheap)), quality=untimed, timings=timings)
    assert dear in timings


def drain(steps):
    """A generator of device-thread units run to its end: (units yielded, its result)."""
    yields = 0
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return yields, done.value
        yields += 1


def test_the_reference_in_row_bands_is_the_whole_reference_bit_for_bit(cloud):
    renderer, iso = cloud
    cameras = [orbit(30, 20, 1.8), orbit(33, 20, 1.8)]
    whole = policy.reference_frames(renderer, iso, SIZE, cameras, flow=True)
    yields, banded = drain(policy.reference_frames_steps(renderer, iso, SIZE, cameras, flow=True, bands=3))
    assert yields == 2 * (3 - 1)  # between the bands of each frame
    for a, b in zip(whole, banded):
        for name in ("mask", "normal", "ao", "color", "flow"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_the_quality_probe_yields_between_every_frame_of_every_candidate(cloud):
    """A unit of the background probe is one frame (a candidate's first one may carry its one-off
    costs): between the reference's bands and between each candidate's frames; the scores are the
    probe's own, run whole."""
    renderer, iso = cloud
    config = BudgetConfig(candidates=(FrameMethod.of("full"), FrameMethod.of("full", ao_rays=2)), probe_frames=3,
                          probe_height=SIZE[1])
    yields, sliced = drain(policy.probe_quality_steps(renderer, iso, *SIZE, config))
    bands = 1 if renderer.device.is_cuda else policy.REFERENCE_BANDS_CPU
    assert yields == 1 + 3 * (bands - 1) + len(sliced.psnr) * 3
    assert sliced.psnr == pytest.approx(policy.probe_quality(renderer, iso, *SIZE, config).psnr, nan_ok=True)


def test_a_batched_timing_makes_each_candidates_frames_for_several_streams_at_once(cloud, monkeypatch):
    """BudgetConfig.batch: after a frame alone, a timed candidate's frames are made for ``batch``
    streams at once by its kind's make_batch (the streams' own recurrent state: twins of the
    networks), its time their batch's over their count; the choice still respects the budget."""
    renderer, iso = cloud
    batches = []
    record_make_batch(monkeypatch, lambda frames: batches.append(
        (type(frames[0][0]).kind, len(frames), len({id(r) for r, _, _ in frames}))))
    config = BudgetConfig(candidates=FEW[1:4], batch=3, warmup_frames=1, timing_frames=2)
    choice = choose_method(renderer, iso, *SIZE, 1000.0, config)
    check_budget_respected(choice)
    timed = [row.method for row in choice.table if row.ms is not None]
    assert timed and batches and all(n == 3 and streams == 3 for _, n, streams in batches)
    assert len(batches) == (BATCH_WARMUP + 2) * len(timed), "warm-up batches and timing_frames batches a candidate"
    with pytest.raises(ValueError, match="batch"):
        BudgetConfig(batch=0)


def test_a_candidate_dear_alone_is_still_timed_in_its_batch(sphere, monkeypatch):
    """A batch shares at most all of a frame's work, so a frame alone of up to ``batch`` budgets may still fit as a
    batch's frame: the frame alone stops the timing only past OVER_BUDGET_STOP budgets times the batch (on an H200
    under load a reconstruction alone took 19-45 ms against budgets of 2-8 ms a frame and was never timed in its
    batch of 4, the way the service makes it)."""
    renderer, iso = sphere
    cheap, dear = FrameMethod.of("full"), FrameMethod.of("full", ao_rays=4)
    budget_ms, batch = 2.0, 4
    alone, batched, stops = {}, [], []

    def time_alone(runner, cameras, config, stop_budget_ms, slice_ms=None):  # no device work: set times
        stops.append(stop_budget_ms)
        return alone[runner.method]
        yield

    def time_batch(runners, cameras, config):
        batched.append(runners[0].method)
        return alone[runners[0].method] / 3  # the network shared by the batch
        yield

    monkeypatch.setattr(policy, "_time_candidate_steps", time_alone)
    monkeypatch.setattr(policy, "_time_batch_steps", time_batch)
    quality = policy.QualityProbe(SIZE, {cheap: 20.0, dear: 28.0}, 12.0, True, 0.0)
    config = BudgetConfig(candidates=(cheap, dear), batch=batch, headroom=0.9)

    def choose(dear_alone_ms: float):
        alone.update({cheap: 0.5, dear: dear_alone_ms})
        batched.clear(), stops.clear()
        return choose_method(renderer, iso, *SIZE, budget_ms, config, quality=quality)

    choice = choose(5.0)  # 2.5 budgets alone, 0.83 in its batch
    assert batched == [dear] and choice.method == dear and choice.fits and choice.ms == pytest.approx(5.0 / 3)
    assert stops == [budget_ms * batch], "the frame alone's own early stop at the batch's budgets too"
    choice = choose(2.0 * batch * budget_ms + 0.1)  # dearer alone than a whole batch's budgets: not batched
    assert batched == [cheap] and choice.method == cheap


def test_the_service_times_candidates_in_batches_only_on_gpus_under_load():
    from types import SimpleNamespace

    from isosr_server.auto import PROBE_BATCH, probe_batch

    gpu, cpu = (SimpleNamespace(device=SimpleNamespace(is_cuda=c)) for c in (True, False))
    assert [probe_batch(gpu, n) for n in (1, 3, 4, 7, 8, 15, 16, 64)] == [1, 1, 2, 2, 4, 4, PROBE_BATCH, PROBE_BATCH]
    assert probe_batch(cpu, 64) == 1
