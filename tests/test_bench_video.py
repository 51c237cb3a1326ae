"""The video benchmark in its smoke mode (its three studies, so that its code cannot rot) and
its throttled link (the pace it promises)."""

from __future__ import annotations

import json
import socket
import sys
import threading
import time

import pytest

from isosr_bench import bench_switch, bench_video
from isosr_bench.video_link import Throttle
from isosr_server.codecs import video
from isosr_server.video import video_threads

pytestmark = pytest.mark.skipif(video._av() is None or "h264" not in video.available(),
                                reason="PyAV with libx264 (the video extra) is not installed")


def test_bench_video_smoke_writes_every_study(tmp_path, capsys):
    rows = bench_video.main(["--device", "cpu", "--smoke", "--codecs", "h264,vp9", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "bench_video_smoke_cpu.json").read_text())
    assert record["device"] and record["commit"] and record["command"] and record["rows"] == rows
    methods = {r["method"] for r in rows if r["study"] == "matched"}
    assert methods == {"full, AO 1, spp 1, recon fp32", "full, AO 0, spp 1"}  # reconstruct:1 and full:0
    for method in methods:
        matched = {r["encoding"]: r for r in rows if r["study"] == "matched" and r["method"] == method}
        assert list(matched) == ["jpeg", "h264", "vp9"] and matched["jpeg"]["bytes_vs_jpeg"] == 1.0
        for r in (matched["h264"], matched["vp9"]):  # the lowest quality reaching JPEG's PSNR, or the best there is
            assert r["psnr_db"] >= matched["jpeg"]["psnr_db"] or r["quality"] == 100
            assert r["keyframe_bytes"] > r["delta_bytes_per_frame"] > 0
        rates = [r for r in rows if r["study"] == "rate" and r["method"] == method]
        assert [(r["encoding"], r["bitrate_kbps"]) for r in rates] == [("h264", 100), ("vp9", 100), ("h264", 300),
                                                                       ("vp9", 300)]
        for r in rates:
            assert r["budget_bytes"] == pytest.approx(1e3 * r["bitrate_kbps"] / 8 / 30)
            assert r["fits_30fps"] == (r["p99_bytes"] <= r["budget_bytes"]) and r["keyframes"] == 1
            assert r["jpeg_fps"] == pytest.approx(1e3 * r["bitrate_kbps"] / 8 / matched["jpeg"]["bytes_per_frame"])
    link = [r for r in rows if r["study"] == "link"]
    assert [(r["encoding"], r["bitrate_cap_kbps"]) for r in link] == [("h264", 0), ("jpeg", 0)]
    for r in link:
        assert r["frames"] > 0 and r["undecodable"] == 0 and r["encodings"] == [r["encoding"]]
        assert 0 < r["latency_p50_ms"] <= r["latency_p99_ms"] <= r["display_latency_p99_ms"]
        assert 0 < r["payload_kbps"] <= r["link_kbps"] <= 1.05e3 * r["link_mbit"]  # the link carries the frames
    assert "| smoke | full, AO 0, spp 1 | h264 |" in capsys.readouterr().out


def test_bench_video_compares_encoder_threads_at_matched_psnr(tmp_path, capsys):
    """--encoder-threads: a matched row per codec and thread count, each reaching JPEG's PSNR (or at quality 100),
    with its encode times; counts below 1 are refused by name."""
    rows = bench_video.main(["--device", "cpu", "--smoke", "--codecs", "h264", "--methods", "full:0",
                             "--encoder-threads", "1,2", "--link-encodings", "", "--rates", "", "--out", str(tmp_path)])
    matched = [r for r in rows if r["study"] == "matched"]
    assert [(r["encoding"], r.get("encoder_threads")) for r in matched] == [("jpeg", None), ("h264", 1), ("h264", 2)]
    for r in matched[1:]:
        assert r["psnr_db"] >= matched[0]["psnr_db"] or r["quality"] == 100
        assert r["encode_ms"] > 0 and r["encode_cpu_ms"] > 0
    with pytest.raises(SystemExit):
        bench_video.main(["--device", "cpu", "--smoke", "--encoder-threads", "0"])
    assert "--encoder-threads: counts of 1 or more, got '0'" in capsys.readouterr().err


def test_bench_video_refuses_a_bad_method(capsys):
    with pytest.raises(SystemExit):
        bench_video.main(["--device", "cpu", "--smoke", "--methods", "bogus:1"])
    assert "'bogus:1' is not KIND:AO_RAYS" in capsys.readouterr().err


def test_the_throttle_carries_bytes_at_its_rate_and_no_faster():
    """250 kB through a 2 Mbit/s throttle take at least the second their bits need at that rate."""
    payload, rate = bytes(250_000), 2e6
    with socket.create_server(("127.0.0.1", 0)) as server, Throttle(server.getsockname()[1], rate) as link:
        port = int(link.url.rsplit(":", 1)[1])

        def serve():
            conn, _ = server.accept()
            with conn:
                conn.sendall(payload)

        threading.Thread(target=serve, daemon=True).start()
        got, start = bytearray(), time.perf_counter()
        with socket.create_connection(("127.0.0.1", port)) as client:
            while chunk := client.recv(65536):
                got += chunk
        elapsed = time.perf_counter() - start
    assert bytes(got) == payload and link.carried == len(payload)
    assert elapsed >= 8 * len(payload) / rate - 0.01, elapsed  # SLACK_S of burst at most


def test_bench_switch_times_coding_per_interval_and_restores_pythons(tmp_path, capsys):
    """bench_switch: a row per switch interval and encoding (the video codecs, then JPEG) with coding times alone and
    beside busy Python and that thread's share; the process's own interval is back after it; bad intervals are
    refused by name."""
    before = sys.getswitchinterval()
    rows = bench_switch.main(["--device", "cpu", "--smoke", "--codecs", "h264", "--intervals", "2,0.5",
                              "--out", str(tmp_path)])
    assert sys.getswitchinterval() == before
    assert [(r["switch_interval_ms"], r["encoding"]) for r in rows] == [(2, "h264"), (2, "jpeg"), (0.5, "h264"),
                                                                        (0.5, "jpeg")]
    for r in rows:
        assert r["encode_ms_alone"] > 0 and r["encode_ms_beside"] > 0 and r["busy_share"] > 0
        assert r["beside_over_alone"] == pytest.approx(r["encode_ms_beside"] / r["encode_ms_alone"])
    assert json.loads((tmp_path / "bench_switch_smoke_cpu.json").read_text())["rows"] == rows
    for bad in ("0", "5,-1", "", "2000", "fast", "nan"):
        with pytest.raises(SystemExit):
            bench_switch.main(["--device", "cpu", "--smoke", "--intervals", bad])
        assert f"--intervals: milliseconds in (0, 1000], comma-separated, got {bad!r}" in capsys.readouterr().err


@pytest.mark.parametrize("size, cores, threads", [((1920, 1080), 32, 4), ((1920, 1080), 2, 1), ((3840, 2160), 32, 16),
                                                  ((3840, 2160), 8, 4), ((160, 90), 32, 1)])
def test_a_video_encoder_takes_a_thread_per_half_megapixel_within_half_the_cores(size, cores, threads):
    assert video_threads(*size, cores) == threads
