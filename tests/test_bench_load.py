"""The load sampler of the service benchmarks: CPU cores per process group over a span, and
bench_cluster's cases and GPU shares as its command line gives them."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from isosr_bench import bench_cluster
from isosr_bench.load import LoadSampler, cpu_ticks, executable, titled

SPIN = "import time\nend = time.monotonic() + 30\nwhile time.monotonic() < end: pass"
NAP = "import time; time.sleep(30)"


@pytest.fixture
def spinner_and_sleeper():
    procs = [subprocess.Popen([sys.executable, "-c", code]) for code in (SPIN, NAP)]
    for p in procs:  # until each runs its own command line (a child just forked still shows its parent's)
        for _ in range(500):
            if b"-c\x00" in Path(f"/proc/{p.pid}/cmdline").read_bytes():
                break
            time.sleep(0.01)
    yield procs
    for p in procs:
        p.kill()
        p.wait()


def test_a_spinning_process_counts_about_one_core_and_a_sleeping_one_none(spinner_and_sleeper):
    spin, nap = spinner_and_sleeper
    load = LoadSampler({"spin": lambda: [spin.pid], "nap": lambda: [nap.pid], "both": lambda: [spin.pid, nap.pid]},
                       gpus=False)
    assert load.result() == {}  # never started
    load.start(1.0)
    result = load.result()
    cores = result["cpu_cores"]
    # A loaded 2-core machine may give the spinner less than a core; it gets more than a sleeper.
    assert 0.2 < cores["spin"]["cores"] <= 1.2 and cores["nap"]["cores"] < 0.1
    assert cores["both"]["processes"] == 2 and cores["both"]["busiest"] == cores["spin"]["cores"]
    assert result["machine_cores"] >= cores["spin"]["cores"] - 0.1 and result["gpu_busy"] is None


def test_a_process_gone_before_the_span_ends_is_left_out(spinner_and_sleeper):
    _, nap = spinner_and_sleeper
    load = LoadSampler({"nap": lambda: [nap.pid]}, gpus=False)
    load.start(0.5)
    nap.kill()
    nap.wait()
    assert cpu_ticks(nap.pid) is None
    assert load.result()["cpu_cores"]["nap"] == {"processes": 0, "cores": 0.0, "busiest": 0.0}


def test_titled_finds_processes_by_the_start_of_their_command_line(spinner_and_sleeper):
    spin, nap = spinner_and_sleeper
    found = titled(sys.executable.encode())()
    assert {spin.pid, nap.pid} <= set(found)
    assert titled(b"ray::NoSuchActor")() == []
    name = Path(sys.executable).name.encode()  # a program by its name, whatever folder it runs from (HAProxy's)
    assert {spin.pid, nap.pid} <= set(executable(name)()) and executable(b"no-such-program")() == []
    assert not {spin.pid, nap.pid} & set(executable(name[:-1])()), "the whole name, not a prefix"


def test_cluster_cases_and_gpu_shares():
    assert bench_cluster.parse_cases("full:0,reconstruct:1") == (("full", 0), ("reconstruct", 1))
    for bad in ("full", "full:-1", "warp:0", "full:0,"):
        with pytest.raises(ValueError, match="MODE:AO_RAYS"):
            bench_cluster.parse_cases(bad)
    shares = {name: (gpus, extra) for name, _, gpus, extra in bench_cluster.servers([0, 2, 4], "split", "cuda")}
    assert shares["plain"] == (1.0, ())
    assert shares["ray2"] == (1.0, ("--replicas", "2", "--ingress", "serve", "--gpus-per-replica", "0.5"))
    assert shares["ray4"] == (1.0, ("--replicas", "4", "--ingress", "serve", "--gpus-per-replica", "0.25"))
    behind = bench_cluster.servers([0, 2], "split", "cuda", "haproxy")
    assert [extra[2:4] for _, _, _, extra in behind] == [(), ("--ingress", "haproxy")]
    assert [gpus for _, _, gpus, _ in bench_cluster.servers([1, 2], "1", "cuda")] == [1.0, 2.0]
    assert [gpus for _, _, gpus, _ in bench_cluster.servers([0, 2], "1", "cpu")] == [0.0, 0.0]


def test_cluster_bench_refuses_an_unknown_case_share_or_settle(tmp_path, capsys):
    for argv in (["--cases", "warp:0"], ["--gpus-per-replica", "half"], ["--settle", "-1"], ["--settle", "nan"]):
        with pytest.raises(SystemExit):
            bench_cluster.main(["--smoke", "--out", str(tmp_path), *argv])
    err = capsys.readouterr().err
    assert "--cases: 'warp:0' is not MODE:AO_RAYS" in err and "--gpus-per-replica: a share of 0 or more" in err
    assert "--settle: untimed seconds, 0 or more, got -1.0" in err and "got nan" in err
    assert not list(tmp_path.iterdir())


def test_a_counter_s_rate_over_the_span():
    """A counter read at the start and the end counts as its rate over the span; one that cannot be read
    (its server gone, or no such sample) counts as None."""
    ticks = iter([10.0, 10.5])
    load = LoadSampler({}, gpus=False, counters={"busy": lambda: next(ticks), "gone": lambda: None})
    load.start(0.5)
    counters = load.result()["counters"]
    assert counters["gone"] is None and 0.5 / 0.7 < counters["busy"] <= 1.0  # 0.5 over a span of about 0.5 s


def test_cluster_rows_name_the_settings_servers_take_from_the_environment_but_the_token(monkeypatch):
    monkeypatch.setenv("ISOSR_SWITCH_INTERVAL_MS", "5")
    monkeypatch.setenv("ISOSR_TOKEN", "secret-token")
    monkeypatch.setenv("OTHER_SETTING", "1")
    environment = bench_cluster.server_environment()
    assert environment["ISOSR_SWITCH_INTERVAL_MS"] == "5"
    assert "ISOSR_TOKEN" not in environment and "OTHER_SETTING" not in environment


def test_an_auto_row_keeps_the_replicas_auto_lines_of_its_case_alone(tmp_path):
    """auto_log: the ``auto mode`` lines appended to the replicas' logs since the case began (files new since
    included), after each file's name, the last ones within the cap; none where Ray kept no logs."""
    logs = tmp_path / "logs"
    (logs / "serve").mkdir(parents=True)
    old = logs / "serve" / "replica_a.log"
    old.write_text("INFO auto mode, bonsai at 1920x1080: before the case\nINFO other\n")
    before = bench_cluster.log_sizes(logs)
    with open(old, "a") as f:
        f.write("INFO auto mode, bonsai at 1920x1080, budget 4.08 ms: x2 bilinear\nINFO a frame\n")
    (logs / "worker-1.err").write_bytes(b"auto mode: full, AO 0 drops the AO the scene shows \xff\n")
    lines = bench_cluster.auto_log(before, logs)
    assert lines == ["replica_a.log: INFO auto mode, bonsai at 1920x1080, budget 4.08 ms: x2 bilinear",
                     "worker-1.err: auto mode: full, AO 0 drops the AO the scene shows \ufffd"]
    assert bench_cluster.auto_log(before, logs, most=1) == lines[-1:]
    assert bench_cluster.auto_log(bench_cluster.log_sizes(logs), logs) == []
    assert bench_cluster.log_sizes(tmp_path / "none") == {} and bench_cluster.auto_log({}, tmp_path / "none") == []
