"""`isosr bench --pareto --smoke`: the record, the fronts, the budget part, merging, the report."""

from __future__ import annotations

import json
import math

import pytest
import torch

from isosr_bench.bench_pareto import budget_ladder, dominator, learned_scorecard, merge, pareto_front, scores
from isosr_net.budget import front_psnr
from isosr_render import FrameBuffers
from isosr_net.methods import unavailable_kinds

FIELDS = {"volume", "size", "method", "learned", "ms", "color_psnr", "color_ssim", "image_psnr", "image_ssim",
          "ao_rmse", "flicker", "flicker_ratio", "color_psnr_8bit"}
OIDN = unavailable_kinds().get("oidn") is None


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from isosr_cli.main import main as cli

    out = tmp_path_factory.mktemp("pareto")
    assert cli(["bench", "--pareto", "--smoke", "--out", str(out)]) == 0
    return out, json.loads((out / "pareto_cpu.json").read_text())


def test_the_record_holds_one_complete_row_per_volume_size_and_method(smoke):
    _, record = smoke
    assert record["device"] and record["commit"] and record["command"]
    rows = [r for r in record["rows"] if r["part"] == "pareto"]
    keys = [(r["volume"], r["size"], r["method"]) for r in rows]
    assert len(keys) == len(set(keys)) and {r["volume"] for r in rows} == {"sphere", "cloud"}
    for r in rows:
        assert FIELDS <= set(r) and r["ms"] > 0 and r["learned"] == (r["kind"] in ("reconstruct", "network"))
        numbers = FIELDS - {"volume", "size", "method", "learned"} - ({"ao_rmse"} if r["kind"] == "oidn" else set())
        assert all(isinstance(r[k], float) and math.isfinite(r[k]) for k in numbers)
        assert 0 < r["color_ssim"] <= 1 and r["color_psnr"] > 10
        assert r["flicker_ratio"] == pytest.approx(r["flicker"] / r["flicker_reference"])
        assert (r["ao_rmse"] is None) == (r["kind"] == "oidn")  # a color without AO: nothing to score
    assert {r["kind"] for r in rows} == {"full", "atrous", "svgf", "reconstruct", "upscale", "network"} | (
        {"oidn"} if OIDN else set())
    full = [r["method"] for r in rows if r["kind"] == "full"]
    assert all(m.startswith("full, AO ") for m in full) and "full, AO 8, spp 1" in full
    # Both shipped reconstructions, as the server's auto mode offers them: full size and x2.
    assert {r["factor"] for r in rows if r["kind"] == "reconstruct"} == {1, 2}


def test_ao_changes_nothing_on_the_sphere_and_something_on_the_cloud(smoke):
    _, record = smoke
    psnr = {(r["volume"], r["method"]): r["color_psnr"] for r in record["rows"] if r["part"] == "pareto"}
    assert psnr[("sphere", "full, AO 8, spp 1")] == psnr[("sphere", "full, AO 0, spp 1")]
    assert psnr[("cloud", "full, AO 8, spp 2")] != psnr[("cloud", "full, AO 0, spp 2")]


def test_the_budget_part_compares_the_policy_with_the_best_fixed_setting(smoke):
    _, record = smoke
    budget = [r for r in record["rows"] if r["part"] == "budget"]
    assert {(r["volume"], r["budget_ms"]) for r in budget} == {(v, b) for v in ("sphere", "cloud") for b in (3.0, 30.0)}
    for r in budget:
        assert not r["fits"] or r["probe_ms"] <= r["budget_ms"]
        assert r["ao_matters"] == (r["volume"] == "cloud")
        if r["volume"] == "sphere":  # no AO rays where AO changes nothing
            assert "AO 0" in r["method"] or not r["method"].startswith("full")
        if r["best_fixed"] is not None:
            assert r["psnr_gap"] == pytest.approx(r["best_fixed_psnr"] - r["color_psnr_scene"]), "like with like"


def test_fronts_dominated_points_and_undefined_scores():
    points = [(1.0, 20.0), (2.0, 25.0), (2.0, 19.0), (3.0, 24.0), (0.5, None), (4.0, float("nan")), (5.0, 30.0)]
    assert pareto_front(points) == [True, True, False, False, False, False, True]
    rows = [{"method": str(i), "ms": ms, "color_psnr": None if p is None or math.isnan(p) else p}
            for i, (ms, p) in enumerate(points)]
    assert dominator(rows[3], rows)["method"] == "1"  # 2 ms and 25 dB beat 3 ms and 24 dB
    assert dominator(rows[2], rows)["method"] == "0"  # the fastest of those that beat it
    assert dominator(rows[1], rows) is None and dominator(rows[4], rows) is None


def test_a_scenes_rows_rank_on_its_region_where_they_were_scored_on_it():
    """Each method's covered region differs (a half-covered pixel is in one mask and not another): the fronts,
    dominance and the scorecard rank by color_psnr_scene, the same pixels for every row; rows without it (written
    before it was scored) by color_psnr."""
    own = [_row("plain", "full", 1.0, 30.0) | {"color_psnr_scene": 28.0},
           _row("recon", "reconstruct", 2.0, 29.0) | {"color_psnr_scene": 29.5}]
    assert [front_psnr(r) for r in own] == [28.0, 29.5] and front_psnr(_row("old", "full", 1.0, 30.0)) == 30.0
    assert dominator(own[1], own) is None, "on its own region plain would dominate it: 1 ms and 30 dB"
    assert front_psnr(own[0] | {"color_psnr_scene": None}) is None, "nothing covered: unscored, never 0"
    card = learned_scorecard(own)
    wins = [b["learned_best"] for b in card["budgets"]]
    assert wins[0] is False and len(wins) > 2 and all(wins[1:]), "1.5 ms: plain alone fits; from 2 ms: recon"


def test_an_empty_image_scores_null_not_zero_or_inf():
    h, w = 16, 16
    empty = FrameBuffers(mask=torch.zeros(h, w), normal=torch.zeros(h, w, 3), ao=torch.zeros(h, w),
                         color=torch.ones(h, w, 3), flow=torch.zeros(h, w, 2))
    s = scores([empty, empty], [empty, empty])
    assert s["color_psnr"] is None and s["color_ssim"] is None and s["ao_rmse"] is None and s["flicker"] is None
    assert s["image_psnr"] == pytest.approx(100.0)  # identical whole images: the PSNR ceiling


def test_the_8bit_psnr_scores_the_colors_a_viewer_receives():
    """Colors within half a level of 8 bits of the reference are what it shows (the PSNR ceiling) where their float
    PSNR is finite; a whole level off everywhere is 20 log10(255) dB; NaN or out-of-range colors stay bounded."""
    h, w = 16, 16
    ref = torch.full((h, w, 3), 100 / 255)

    def frame(color: torch.Tensor) -> FrameBuffers:
        return FrameBuffers(mask=torch.ones(h, w), normal=torch.zeros(h, w, 3), ao=torch.ones(h, w), color=color)

    near, level = scores([frame(ref + 0.4 / 255)], [frame(ref)]), scores([frame(ref + 1 / 255)], [frame(ref)])
    assert near["color_psnr"] < 60 and near["color_psnr_8bit"] == pytest.approx(100.0)
    assert level["color_psnr_8bit"] == pytest.approx(20 * math.log10(255), abs=1e-3)
    hostile = ref.clone()
    hostile[0, 0] = torch.tensor([math.nan, math.inf, -5.0])
    assert math.isfinite(scores([frame(hostile)], [frame(ref)])["color_psnr_8bit"])


def test_flicker_is_the_color_change_along_the_flow_and_ignores_buffers():
    """A color that alternates frame to frame flickers by the change, whatever its AO buffer says; a
    color that moves with the flow does not flicker."""
    h, w = 16, 16
    base = (0.5 - 0.5 * torch.cos(torch.arange(w) * (2 * math.pi / w))).expand(h, w)  # 0 at the border

    def frame(color, ao=None, shift=0):
        ao = torch.ones(h, w) if ao is None else ao
        return FrameBuffers(mask=torch.ones(h, w), normal=torch.zeros(h, w, 3), ao=ao,
                            color=torch.roll(color, shift, dims=1)[..., None].expand(h, w, 3).contiguous(),
                            flow=torch.full((h, w, 2), 0.0))
    steady = [frame(base, ao=torch.rand(h, w)) for _ in range(3)]  # AO noise that never reaches the color
    assert scores(steady, steady)["flicker"] == 0
    alternating = [frame(base + 0.1 * (t % 2)) for t in range(3)]
    assert scores(alternating, steady)["flicker"] == pytest.approx(0.1, rel=1e-5)
    moving = [frame(base, shift=t) for t in range(3)]  # one pixel right per frame: the flow points left
    along = [frame(base, shift=t) for t in range(3)]
    for f in along:
        f.flow = torch.tensor([-1.0, 0.0]).expand(h, w, 2)
    assert scores(moving, along)["flicker"] < 0.2 * scores(moving, steady)["flicker"]


def test_a_partial_run_merges_into_the_result_file(smoke, tmp_path):
    _, record = smoke
    path = tmp_path / "pareto_cpu.json"
    path.write_text(json.dumps(record))
    rerun = [{**r, "ms": r["ms"] + 1.0} for r in record["rows"] if r["volume"] == "sphere"]
    merged = merge(path, rerun)
    assert [r for r in merged if r["volume"] == "cloud"] == [r for r in record["rows"] if r["volume"] == "cloud"]
    assert [r for r in merged if r["volume"] == "sphere"] == rerun and len(merged) == len(record["rows"])
    assert merge(tmp_path / "absent.json", rerun) == rerun
    assert all(r["device"] == record["device"] and r["commit"] for r in record["rows"]), "each row names its run"
    unstamped = [{k: v for k, v in r.items() if k != "device"} for r in record["rows"]]
    path.write_text(json.dumps({**record, "rows": unstamped}))  # rows of a file from before rows named a device
    assert all(r["device"] == record["device"] for r in merge(path, rerun) if r["volume"] == "cloud")


def test_a_selection_of_kinds_compares_two_models_without_touching_the_studys_file(smoke, tmp_path):
    """``--kinds``: only those methods (here the shipped reconstruction against a second copy of
    it, and SVGF), no budget part, in their own file; the study's file is left alone."""
    from isosr_bench.bench_pareto import main
    from isosr_net.reconstructor import DEFAULT_RECON_MODEL

    out = tmp_path / "select"
    out.mkdir()
    (out / "pareto_cpu.json").write_text(json.dumps(smoke[1]))
    rows = main(["--device", "cpu", "--smoke", "--out", str(out), "--volumes", "sphere", "--kinds", "reconstruct,svgf",
                 "--models", f"again={DEFAULT_RECON_MODEL}"])
    assert json.loads((out / "pareto_cpu.json").read_text()) == smoke[1]
    record = json.loads((out / "pareto_select_cpu.json").read_text())
    assert record["rows"] == rows and {r["part"] for r in rows} == {"pareto"}
    assert {r["kind"] for r in rows} == {"reconstruct", "svgf"}
    again = {r["method"].replace("again", "recon"): r["color_psnr"] for r in rows if ", again " in r["method"]}
    shipped = {r["method"]: r["color_psnr"] for r in rows if ", recon " in r["method"]}
    assert again and again == shipped  # the same model twice scores the same


def test_the_report_has_the_section_and_a_plot_per_volume(smoke):
    out, _ = smoke
    report = (out / "report_cpu.md").read_text()
    assert "Every way to make a frame" in report and "Wins" in report and "budget policy" in report
    assert "x4 network fp32" in report and "full, AO 2, spp 1, recon fp32" in report
    assert "full, AO 2, svgf" in report and "flicker_ratio" in report
    assert "Where a learned method is the best there is" in report
    assert (out / "pareto_sphere_cpu.png").stat().st_size > 0 and (out / "pareto_cloud_cpu.png").stat().st_size > 0


def test_bad_selections_are_refused(capsys):
    from isosr_cli.main import main as cli

    assert cli(["bench", "--smoke", "--volumes", "sphere"]) == 2
    assert "give --pareto too" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["bench", "--pareto", "--smoke", "--kinds", "reconstruct,denoise"])
    assert "unknown kinds ['denoise']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["bench", "--pareto", "--smoke", "--volumes", "nowhere"])
    assert "unknown volumes ['nowhere']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["bench", "--pareto", "--smoke", "--sizes", "8k"])
    assert "unknown sizes ['8k']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["bench", "--pareto", "--smoke", "--ao-rays", "2,many"])
    assert "--spp and --ao-rays take comma-separated integers" in capsys.readouterr().err
    assert cli(["bench", "--smoke", "--spp", "2"]) == 2
    assert "give --pareto too" in capsys.readouterr().err


def test_a_selection_of_sampling_measures_only_those_methods(tmp_path):
    """``--spp`` and ``--ao-rays``: only the methods of those counts, every kind that has them."""
    from isosr_bench.bench_pareto import main

    rows = main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--kinds", "full,svgf",
                 "--spp", "1", "--ao-rays", "2"])
    assert {r["method"] for r in rows} == {"full, AO 2, spp 1", "full, AO 2, svgf"}
    assert json.loads((tmp_path / "pareto_select_cpu.json").read_text())["rows"] == rows
    assert not (tmp_path / "pareto_cpu.json").exists()


def test_a_selection_is_scored_against_references_of_the_rays_per_pixel_asked(tmp_path, monkeypatch, capsys):
    """``--reference-spp``: the references rendered at that many rays per pixel, the rows saying so; refused
    without a selection (the policy's part keeps its own references) and outside [1, MAX_SPP]."""
    from isosr_bench import bench_pareto

    asked, render = [], bench_pareto.reference_frames
    monkeypatch.setattr(bench_pareto, "reference_frames", lambda *a, **k: (asked.append(k["spp"]), render(*a, **k))[1])
    rows = bench_pareto.main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--kinds",
                              "full", "--spp", "1", "--ao-rays", "2", "--reference-spp", "16"])
    assert asked == [16] and rows and all(r["reference_spp"] == 16 for r in rows)
    for argv, words in ((["--reference-spp", "16"], "give a selection"),
                        (["--kinds", "full", "--reference-spp", "0"], "--reference-spp must lie in [1, 256], got 0")):
        with pytest.raises(SystemExit):
            bench_pareto.main(["--device", "cpu", "--smoke", "--out", str(tmp_path), *argv])
        assert words in capsys.readouterr().err


def test_a_selection_is_scored_over_draws_of_its_ao_rays(tmp_path, capsys):
    """``--draws K``: each row's scores the means over K draws of the AO rays, each draw's scene PSNR listed (other
    rays, other scores on the cloud; none cast, the same); refused without a selection and outside [1, MAX_DRAWS]."""
    from isosr_bench import bench_pareto

    rows = bench_pareto.main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "cloud", "--kinds",
                              "full", "--spp", "1", "--ao-rays", "0,2", "--draws", "3"])
    by_rays = {r["ao_rays"]: r for r in rows}
    assert set(by_rays) == {0, 2} and all(r["draws"] == 3 and len(r["color_psnr_scene_draws"]) == 3 for r in rows)
    for r in rows:
        assert r["color_psnr_scene"] == pytest.approx(sum(r["color_psnr_scene_draws"]) / 3)
    assert len(set(by_rays[2]["color_psnr_scene_draws"])) == 3, "each draw its own rays"
    assert len(set(by_rays[0]["color_psnr_scene_draws"])) == 1, "no AO rays: one frame, whatever the draw"
    most = bench_pareto.MAX_DRAWS
    for argv, words in ((["--draws", "2"], "give a selection"),
                        (["--kinds", "full", "--draws", "0"], f"--draws must lie in [1, {most}], got 0")):
        with pytest.raises(SystemExit):
            bench_pareto.main(["--device", "cpu", "--smoke", "--out", str(tmp_path), *argv])
        assert words in capsys.readouterr().err


def test_translucent_rows_stand_beside_the_single_surface_s(tmp_path, capsys):
    """``--translucent``: each method again on a translucent surface over an inner one, rows of part ``layers`` with
    the surfaces, scored against references of the same surfaces; an opacity of 1 (no second layer) is refused."""
    from isosr_cli.main import main as cli

    assert cli(["bench", "--pareto", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--kinds",
                "full,atrous", "--ao-rays", "2", "--spp", "1", "--translucent", "0.3"]) == 0
    rows = json.loads((tmp_path / "pareto_select_cpu.json").read_text())["rows"]
    single, layers = ([r for r in rows if r["part"] == part] for part in ("pareto", "layers"))
    assert ([r["method"] for r in layers] == [r["method"] for r in single]
            == ["full, AO 2, spp 1", "full, AO 2, a-trous"])
    for r in layers:
        assert [s[1] for s in r["surfaces"]] == [0.3, 1.0] and r["surfaces"][1][0] > r["surfaces"][0][0]
        assert r["ms"] > 0 and math.isfinite(r["color_psnr"]) and 0 <= r["color_ssim"] <= 1
    assert cli(["bench", "--smoke", "--translucent", "0.3"]) == 2
    assert "give --pareto too" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["bench", "--pareto", "--smoke", "--translucent", "1"])
    assert "--translucent must be in [0, 1)" in capsys.readouterr().err


def _row(method, kind, ms, psnr, ao_rays=0, spp=1):
    return {"method": method, "kind": kind, "ms": ms, "color_psnr": psnr, "ao_rays": ao_rays, "spp": spp,
            "learned": kind in ("reconstruct", "network")}


def test_the_budget_ladder_runs_from_one_and_a_half_times_the_cheapest_frame_to_the_top():
    ladder = budget_ladder(2.0, 10.0)
    assert ladder[0] == pytest.approx(3.0) and ladder[-1] == 10.0
    assert all(b / a == pytest.approx(math.sqrt(2)) for a, b in zip(ladder[:-2], ladder[1:-1]))
    assert budget_ladder(40.0, 50.0) == [50.0]  # 1.5 times the cheapest is past the top: only the top


def test_the_scorecard_finds_where_a_learned_method_is_best_and_compares_like_with_like():
    rows = [_row("full, AO 0", "full", 2.0, 25.0), _row("full, AO 64", "full", 30.0, 34.0, ao_rays=64),
            _row("a-trous 1", "atrous", 4.0, 33.0, ao_rays=1), _row("recon 1", "reconstruct", 5.0, 35.0, ao_rays=1),
            _row("recon 1 spp 4", "reconstruct", 9.0, 36.0, ao_rays=1, spp=4),
            _row("full, AO 128, spp 4", "full", 45.0, 48.0, ao_rays=128, spp=4)]
    card = learned_scorecard(rows)
    by_budget = {round(b["budget_ms"], 2): b for b in card["budgets"]}
    assert not by_budget[3.0]["learned_best"] and by_budget[3.0]["learned"] is None
    assert by_budget[4.24]["best"] == "a-trous 1" and not by_budget[4.24]["learned_best"]
    assert by_budget[6.0]["best"] == "recon 1" and by_budget[6.0]["learned_best"]
    assert by_budget[50.0]["best"] == "full, AO 128, spp 4" and by_budget[50.0]["learned"] == "recon 1 spp 4"
    assert card["baselines"] == [{"kind": "atrous", "method": "a-trous 1", "ao_rays": 1, "ms": 4.0, "psnr": 33.0,
                                  "flicker_ratio": None, "recon": "recon 1", "recon_ms": 5.0, "recon_psnr": 35.0,
                                  "recon_flicker_ratio": None}]  # spp 4 is not the same sampling
    assert card["ao64"]["learned"] == "recon 1" and card["ao64"]["speedup"] == pytest.approx(6.0)
    rows[3]["color_psnr"] = rows[4]["color_psnr"] = 30.0  # now no learned method reaches 64 rays
    assert learned_scorecard(rows)["ao64"]["learned"] is None
    assert learned_scorecard([_row("x4", "upscale", 1.0, 20.0)]) == {"budgets": [], "baselines": [], "ao64": None}


def test_the_scorecard_names_a_scene_where_ao_changes_nothing_visible_as_no_goal():
    from isosr_bench.report import scorecard_markdown

    rows = [_row("full, AO 0", "full", 2.0, 40.0), _row("recon 1", "reconstruct", 5.0, 35.0, ao_rays=1)]
    lines = scorecard_markdown({("blobs", "1080p"): rows, ("head", "1080p"): rows},
                               {("blobs", "1080p"): 57.1, ("head", "1080p"): 27.0})
    blobs, head = (next(line for line in lines if line.startswith(f"| {v},")) for v in ("blobs", "head"))
    assert "AO changes nothing visible: 57.1 dB; no goal scene" in blobs and "no goal" not in head


def test_the_policy_alone_is_scored_by_the_rows_the_file_holds(smoke, tmp_path):
    """``--budget-only``: the policy's rows anew, the methods' rows kept as measured."""
    from isosr_bench.bench_pareto import main

    out = tmp_path / "budget"
    out.mkdir()
    (out / "pareto_cpu.json").write_text(json.dumps(smoke[1]))
    rows = main(["--device", "cpu", "--smoke", "--out", str(out), "--volumes", "sphere", "--budget-only"])
    old, new = smoke[1]["rows"], json.loads((out / "pareto_cpu.json").read_text())["rows"]
    key = lambda r: json.dumps(r, sort_keys=True)  # noqa: E731
    assert sorted(map(key, (r for r in new if r["part"] == "pareto"))) == \
        sorted(map(key, (r for r in old if r["part"] == "pareto")))
    assert [r for r in new if r["part"] == "budget" and r["volume"] == "cloud"] == \
        [r for r in old if r["part"] == "budget" and r["volume"] == "cloud"]
    budget = [r for r in rows if r["part"] == "budget"]
    assert budget and {r["volume"] for r in budget} == {"sphere"} and budget == [r for r in new if r in budget]
    measured = {r["method"]: r for r in old if r["part"] == "pareto" and r["volume"] == "sphere"}
    for r in budget:
        assert r["ms"] == measured[r["method"]]["ms"] and r["rows_commit"] == measured[r["method"]]["commit"]


def test_the_policy_alone_needs_measured_rows_of_this_device(smoke, tmp_path):
    from isosr_bench.bench_pareto import main

    with pytest.raises(ValueError, match="holds no measured rows of sphere"):
        main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--budget-only"])
    elsewhere = {**smoke[1], "rows": [{**r, "device": "NVIDIA H100 80GB HBM3"} for r in smoke[1]["rows"]]}
    (tmp_path / "pareto_cpu.json").write_text(json.dumps(elsewhere))
    with pytest.raises(ValueError, match="measured on NVIDIA H100 80GB HBM3"):
        main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--budget-only"])
    with pytest.raises(SystemExit):
        main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--budget-only", "--kinds", "full"])
    from isosr_cli.main import main as cli

    assert cli(["bench", "--smoke", "--budget-only", "--out", str(tmp_path)]) == 2  # without --pareto
    assert cli(["bench", "--pareto", "--smoke", "--budget-only", "--volumes", "sphere", "--out", str(tmp_path)]) == 2


def test_a_model_s_graphs_are_freed_before_the_next_model_s_frames(tmp_path, monkeypatch):
    """Several models at 4K held every model's captured graphs at once (120 GB on an H200): each network's are
    freed after its last method of the scene, before another network makes a frame."""
    import shutil

    from isosr_bench.bench_pareto import main
    from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor

    events = []
    reconstruct, drop = Reconstructor.reconstruct, Reconstructor.drop_graphs
    monkeypatch.setattr(Reconstructor, "reconstruct",
                        lambda self, *a, **k: events.append(("frame", id(self.net))) or reconstruct(self, *a, **k))
    monkeypatch.setattr(Reconstructor, "drop_graphs", lambda self: events.append(("drop", id(self.net))) or drop(self))
    shutil.copytree(DEFAULT_RECON_MODEL, tmp_path / "copy")
    main(["--device", "cpu", "--smoke", "--out", str(tmp_path), "--volumes", "sphere", "--kinds", "reconstruct",
          "--spp", "1", "--ao-rays", "1,2", "--models", f"copy={tmp_path / 'copy'}"])
    networks = list(dict.fromkeys(net for _, net in events))
    assert len(networks) == 3  # the shipped x1 and x2 models and the copy
    for net, following in zip(networks, networks[1:] + [None]):
        frames = [i for i, event in enumerate(events) if event == ("frame", net)]
        dropped = events.index(("drop", net))
        assert frames[-1] < dropped  # after its last frame...
        if following is not None:  # ...and before the next network's first
            assert dropped < events.index(("frame", following))
