"""The renderer benchmark in its smoke mode, so that its code cannot rot."""

from __future__ import annotations

import json
import signal
from contextlib import redirect_stdout
from io import StringIO

import pytest

from isosr_bench import bench_cluster
from isosr_net.reconstructor import RECON_X2_MODEL
from net_fixtures import tiny_model_dir


@pytest.fixture(scope="module")
def bench_smoke(tmp_path_factory):
    """`isosr bench --smoke` run once: its folder and what it printed. Its render study is
    bench_render's smoke run (``main(["--device", "cpu", "--out", OUT, "--smoke"])``), so the render
    record is read from there rather than from a second run of the same study."""
    from isosr_cli.main import main as cli

    out = tmp_path_factory.mktemp("bench_smoke")
    tiny = tiny_model_dir(tmp_path_factory)  # an x2 network for the upscale sweep
    printed = StringIO()
    with redirect_stdout(printed):
        assert cli(["bench", "--smoke", "--out", str(out), "--models", f"tiny={tiny}"]) == 0
    return out, printed.getvalue()


def test_bench_render_smoke_writes_a_complete_record(bench_smoke):
    out, printed = bench_smoke
    record = json.loads((out / "bench_render_cpu.json").read_text())
    assert record["device"] and record["commit"] and record["command"]
    cases = {r["case"] for r in record["rows"]}
    assert {"first hit", "first hit, no skipping", "first hit, two surfaces", "first hit, two surfaces, 30%",
            "low-res", "flow fill ns", "flow fill pushpull",
            "recon render, AO 1 + flow: render()", "recon render, AO 1 + flow: plan"} <= cases
    first = next(r for r in record["rows"] if r["case"] == "first hit")
    assert first["ms"] > 0 and first["skip speedup"] > 0 and 0 < first["coverage"] <= 1
    assert "| first hit |" in printed.split("== render\n", 1)[1]  # the render study's table


def test_isosr_bench_smoke_writes_every_study_the_report_and_plots(bench_smoke):
    out, _ = bench_smoke
    for study in ("network", "pipeline", "knobs", "render"):
        record = json.loads((out / f"bench_{study}_cpu.json").read_text())
        assert record["rows"] and all(r["ms"] > 0 for r in record["rows"] if "ms" in r)
    knobs = json.loads((out / "bench_knobs_cpu.json").read_text())["rows"]
    assert {"AO samples", "ray step (voxels)", "refinement steps (secant)", "supersampling (rays/pixel)",
            "sample lookup", "upscale x4"} <= {r["knob"] for r in knobs}
    assert {("upscale x4", "L1-normal fp32"), ("upscale x2", "tiny fp32")} <= {(r["knob"], r["setting"]) for r in knobs}
    ao = [r["error"] for r in knobs if r["knob"] == "AO samples"]
    assert ao[0] > ao[-1]  # more AO rays, less noise
    lookup = {r["setting"]: r for r in knobs if r["knob"] == "sample lookup"}
    assert lookup.keys() == {"voxels", "filtered texture (2x memory)"}
    textured = lookup["filtered texture (2x memory)"]
    assert textured["error"] == 0 and textured["mask mismatch"] == 0 and textured["ms"] > 0  # the same hits
    pipeline = json.loads((out / "bench_pipeline_cpu.json").read_text())["rows"]
    assert {"table", "resolution", "volume size"} == {r["part"] for r in pipeline}
    report = (out / "report_cpu.md").read_text()
    assert "The network's fast path" in report and "What accuracy costs in time" in report
    assert (out / "knobs_cpu.png").stat().st_size > 0 and (out / "scaling_cpu.png").stat().st_size > 0


def test_isosr_bench_rejects_unknown_studies(capsys):
    from isosr_cli.main import main as cli

    assert cli(["bench", "--smoke", "--only", "render,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err
    assert cli(["bench", "--smoke", "--only", "knobs", "--models", "x2=/nowhere"]) == 2
    assert "is not NAME=MODEL_FOLDER" in capsys.readouterr().err


def test_bench_knobs_runs_the_sweeps_named_and_refuses_others(tmp_path, capsys):
    from isosr_bench import bench_knobs
    from isosr_bench.report import plots

    rows = bench_knobs.main(["--device", "cpu", "--smoke", "--knobs", "lookup", "--out", str(tmp_path)])
    assert [r["knob"] for r in rows] == ["sample lookup", "sample lookup"]
    assert plots(tmp_path, "cpu") and (tmp_path / "knobs_cpu.png").stat().st_size > 0  # one panel
    with pytest.raises(SystemExit):
        bench_knobs.main(["--device", "cpu", "--smoke", "--knobs", "lookup,speed", "--out", str(tmp_path)])
    assert "--knobs: unknown speed; choose from ao," in capsys.readouterr().err


def test_bench_knobs_lookup_without_a_texture_measures_the_voxels_and_says_why(tmp_path, capsys, monkeypatch):
    from isosr_bench import bench_knobs
    import isosr_render.renderer as renderer_module

    def refuse(*args):
        raise RuntimeError("3D texture extent exceeded")

    monkeypatch.setattr(renderer_module, "filtered_layout", refuse)
    rows = bench_knobs.main(["--device", "cpu", "--smoke", "--knobs", "lookup", "--out", str(tmp_path)])
    assert [r["setting"] for r in rows] == ["voxels"] and rows[0]["error"] == 0
    assert "no texture row: filtered: cpu cannot make the voxels' texture: 3D texture extent" in capsys.readouterr().out


def test_recon_path_smoke_times_every_stage(tmp_path):
    from isosr_bench import bench_recon_path

    rows = bench_recon_path.main(["--device", "cpu", "--smoke", "--out", str(tmp_path)])
    assert len(rows) == len(bench_recon_path.SAMPLINGS) and (tmp_path / "bench_recon_path_cpu.json").is_file()
    for row in rows:
        assert all(row[k] > 0 for k in ("full", "path", "render", "network_gflop", "floor_ms"))
        assert row["added"] == row["path"] - row["full"]
    rows = bench_recon_path.main(["--device", "cpu", "--smoke", "--model", str(RECON_X2_MODEL), "--out", str(tmp_path)])
    assert [row["method"] for row in rows] == [f"x2, AO 1, spp {spp}, recon_x2_model fp32"
                                               for _, spp in bench_recon_path.SAMPLINGS]
    assert all(row["path"] > 0 for row in rows)


def test_limits_smoke_runs_the_heaviest_requests_in_slices(tmp_path):
    from isosr_bench import bench_limits

    rows = bench_limits.main(["--device", "cpu", "--smoke", "--out", str(tmp_path)])
    assert [r["request"].split()[0] for r in rows] == ["view", "upscale"]
    assert all(r["seconds"] > 0 and r["slices"] >= 1 and r["peak_growth_mib"] >= 0 for r in rows)
    assert json.loads((tmp_path / "bench_limits_cpu.json").read_text())["rows"] == rows


def test_volume_memory_smoke_loads_native_and_pages_a_sparse_volume(tmp_path):
    from isosr_bench import bench_volume_memory

    rows = bench_volume_memory.main(["--device", "cpu", "--smoke", "--out", str(tmp_path)])
    by = {(r["case"], r["path"], r.get("step")): r for r in rows}
    native, today = by[("ct", "native", None)], by[("ct", "today (float32)", None)]
    assert native["storage"] == "uint16" and today["storage"] == "float32"
    assert native["resident_gb"] * 2 == today["resident_gb"]
    huge = [r for r in rows if r["case"] == "huge"]
    assert [r["mode"] for r in huge] == ["sparse", "sparse"] and all(r["camera_move_bricks_paged"] == 0 for r in huge)
    assert 0 < huge[1]["bricks_paged"] < huge[0]["bricks_paged"]  # an iso change pages the difference
    assert json.loads((tmp_path / "bench_volume_memory_cpu.json").read_text())["rows"] == rows


def test_cluster_scaling_compares_each_server_with_one_replica(tmp_path):
    """Efficiency is frames/s over N times one replica's at the same sessions; p99 against one
    replica's at 1/N of the sessions; a later run keeps the servers it does not measure."""
    def row(server, sessions, fps, p99):
        return {"server": server, "replicas": 0 if server == "plain" else int(server[3:]), "mode": "full", "ao": 8,
                "sessions": sessions, "fps": fps, "latency_p99_ms": p99}

    rows = [row("ray1", 16, 100.0, 200.0), row("ray1", 32, 110.0, 400.0), row("ray1", 64, 105.0, 800.0),
            row("ray2", 32, 198.0, 220.0), row("ray2", 48, 150.0, 300.0), row("ray4", 64, 300.0, 500.0),
            row("plain", 32, 120.0, 300.0)]
    two, four = bench_cluster.scaling(rows)  # ray2 at 48 sessions: no 1-replica row to compare
    assert (two["replicas"], two["sessions"]) == (2, 32)
    assert two["efficiency"] == pytest.approx(0.9) and two["p99_ratio"] == pytest.approx(1.1)
    assert four["efficiency"] == pytest.approx(300 / 420) and four["p99_ratio"] == pytest.approx(2.5)

    path = tmp_path / "bench_cluster_gpus_1080p_cuda.json"
    path.write_text(json.dumps({"device": "GPU A", "commit": "abc", "lease": "L1", "rows": rows + [two]}))
    merged = bench_cluster.merge(path, [dict(row("ray4", 64, 320.0, 480.0), device="GPU B", lease="L1")],
                                 {("ray4", "L1")})
    assert [r["server"] for r in merged] == ["ray1", "ray1", "ray1", "ray2", "ray2", "plain", "ray4"]
    assert merged[0]["device"] == "GPU A" and merged[-1]["device"] == "GPU B" and merged[-1]["fps"] == 320.0

    # A later lease keeps the first lease's rows of the same server and is compared only within itself.
    later = [dict(row("ray4", 64, 250.0, 480.0), lease="L2")]
    merged = bench_cluster.merge(path, later, {("ray4", "L2")})
    assert [(r["lease"], r["fps"]) for r in merged if r["server"] == "ray4"] == [("L1", 300.0), ("L2", 250.0)]
    assert [r["fps"] for r in bench_cluster.scaling(merged) if r["server"] == "ray4"] == [300.0]


def test_cluster_scaling_reads_the_replica_count_of_each_row_not_the_servers_name():
    rows = [{"server": name, "replicas": n, "mode": "full", "ao": 0, "sessions": 8, "fps": fps, "latency_p99_ms": 9.0}
            for name, n, fps in (("one", 1, 50.0), ("pair", 2, 90.0), ("ray7", 0, 60.0))]
    (pair,) = bench_cluster.scaling(rows)
    assert (pair["server"], pair["replicas"], pair["efficiency"]) == ("pair", 2, pytest.approx(0.9))


@pytest.mark.parametrize("replicas", ["", "1,-1"])
def test_cluster_bench_refuses_no_servers_or_a_negative_count(tmp_path, capsys, replicas):
    with pytest.raises(SystemExit):
        bench_cluster.main(["--smoke", "--replicas", replicas, "--out", str(tmp_path)])
    assert "--replicas: one or more replica counts of 0 or more" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_the_server_benches_refuse_a_volume_their_servers_would_not_offer_before_starting_one(tmp_path, capsys,
                                                                                              monkeypatch):
    """Where a started server would answer 'no volume named ...' to each session (minutes of start-up later), the
    bench says so at once, naming the folder the server reads; a volume of the folder and a procedural spec pass."""
    from isosr_bench import bench_server
    from isosr_render.catalog import ENV_VAR

    (tmp_path / "vols").mkdir()
    (tmp_path / "vols" / "tiny.npy").write_bytes(b"")  # named by the listing; not opened before a session asks
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "vols"))
    monkeypatch.setattr(bench_cluster, "ServerProcess", lambda *a, **k: pytest.fail("a server started"))
    monkeypatch.setattr(bench_server, "ServerProcess", lambda *a, **k: pytest.fail("a server started"))
    for bench in (bench_cluster, bench_server):
        with pytest.raises(SystemExit):
            bench.main(["--volume", "bonsai", "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert "--volume: no volume named 'bonsai'" in err and f"the volumes folder {tmp_path / 'vols'}" in err
    bench_server.check_offered("tiny"), bench_server.check_offered("proc:sphere@16")
    with pytest.raises(ValueError, match="no procedural volume"):
        bench_server.check_offered("proc:sphere@big")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "absent"))
    with pytest.raises(ValueError, match=r"no volumes folder \(.*absent is absent\)"):
        bench_server.check_offered("bonsai")
    assert not (tmp_path / "out").exists()


def test_cluster_smoke_writes_every_case_and_a_rerun_replaces_its_server(tmp_path):
    """The plain server's cases on the CPU: a row per case, written as measured; the same run again
    replaces that server's rows instead of adding to them."""
    argv = ["--smoke", "--replicas", "0", "--sessions", "2", "--failover-sessions", "0", "--client-processes", "1",
            "--seconds", "0.3", "--out", str(tmp_path)]
    for _ in range(2):
        bench_cluster.main(argv)
        record = json.loads((tmp_path / "bench_cluster_smoke_cpu.json").read_text())
        assert [(r["server"], r["replicas"], r["mode"], r["ao"]) for r in record["rows"]] == [
            ("plain", 0, mode, ao) for mode, ao in bench_cluster.CASES]
        assert all(r["errors"] == 0 and r["fps"] > 0 and r["commit"] == record["commit"] for r in record["rows"])
        # The device thread's share of each span in jobs (its seconds' rate from /metrics): some, at most all
        # (within the reads' timing: a 0.3 s span read over HTTP on a loaded machine).
        busy = [r["device_thread_busy"] for r in record["rows"]]
        assert all(0 < b <= 1.1 for b in busy), busy


def test_first_frame_smoke_starts_auto_from_the_prior_and_stops_mid_probe(tmp_path):
    """A real server on the CPU: each case's first frame comes (auto's is the prior, before any probe),
    later frames come too, and SIGTERM during a probe ends the server (uvicorn shuts down, then
    re-raises the signal: status 0 or -SIGTERM)."""
    from isosr_bench import bench_first_frame

    rows = bench_first_frame.main(["--smoke", "--device", "cpu", "--out", str(tmp_path)])
    cases = [r for r in rows if "mode" in r]
    assert [(r["mode"], r["frames"]) for r in cases] == [("auto", 3), ("full", 3)]
    assert cases[0]["first_method"] == "full, AO 0, spp 1" and all(r["first_frame_s"] > 0 for r in cases)
    assert rows[-1]["study"] == "shutdown" and rows[-1]["returncode"] in (0, -signal.SIGTERM)
    assert json.loads((tmp_path / "bench_first_frame_cpu.json").read_text())["rows"] == rows
