"""Every script in examples/ runs as a user runs it (a subprocess, small sizes, on the CPU) and makes
what it says: a non-uniform PNG, saved view frames, an upscaled image of the right size, a timing
table of finite numbers. The view and upscale examples talk to a real `isosr serve` on 127.0.0.1
(the client tests' server fixture)."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
from client_fixtures import server  # noqa: F401  (the module's `isosr serve` on a free loopback port)

from isosr_render.image_codec import decode_image

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run_example(name: str, *args: str, cwd: Path) -> str:
    """Run ``examples/NAME`` on the CPU in ``cwd``; its stdout (the test fails on a non-zero exit)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, str(EXAMPLES / name), *args, "--device", "cpu"], cwd=cwd, env=env,
                            capture_output=True, text=True, timeout=180, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def read_png(path: Path) -> np.ndarray:
    assert path.is_file(), f"{path} was not written"
    return decode_image(path.read_bytes())


def test_every_example_is_tested():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == ["render_volume.py", "time_methods.py",
                                                             "upscale_http.py", "view_remote.py"]


def test_render_volume_writes_a_shaded_png(tmp_path):
    out = run_example("render_volume.py", "--volume", "proc:cloud:0@32", "--size", "96x64", "--ao-rays", "2",
                      cwd=tmp_path)
    rgb = read_png(tmp_path / "example-out" / "render.png")  # the default --out, under the working directory
    assert rgb.shape == (64, 96, 3)
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 10  # a shaded surface over the background
    assert "render.png" in out


def test_view_remote_saves_the_frames_of_a_session(tmp_path, server):  # noqa: F811
    out = run_example("view_remote.py", "--url", server.url, "--frames", "2", "--size", "64x48",
                      "--out", str(tmp_path / "view"), cwd=tmp_path)
    frames = sorted((tmp_path / "view").glob("frame_*.png"))
    assert [p.name for p in frames] == ["frame_0000.png", "frame_0001.png"]
    images = [read_png(p) for p in frames]
    assert all(im.shape == (48, 64, 3) and im.std() > 0 for im in images)
    assert not np.array_equal(images[0], images[1])  # the camera moved between them
    assert len(re.findall(r"^frame \d: ", out, re.MULTILINE)) == 2


def test_upscale_http_returns_an_image_factor_times_the_frame(tmp_path, server):  # noqa: F811
    with urllib.request.urlopen(server.url + "/v2/models/isosr", timeout=30) as r:
        factor = int(json.loads(r.read())["parameters"]["upscale_factor"])
    out = run_example("upscale_http.py", "--url", server.url, "--size", "24x16", "--out", str(tmp_path / "up.png"),
                      cwd=tmp_path)
    rgb = read_png(tmp_path / "up.png")
    assert rgb.shape == (16 * factor, 24 * factor, 3) and rgb.std() > 0
    assert f"-> {24 * factor}x{16 * factor} (x{factor})" in out


def test_time_methods_prints_a_finite_row_per_method(tmp_path):
    out = run_example("time_methods.py", "--methods", "full:2,atrous:2", "--size", "48x32", "--frames", "2",
                      cwd=tmp_path)
    rows = re.findall(r"^(full, .+?)\s+(\S+)\s+(\S+)$", out, re.MULTILINE)
    assert [name for name, _, _ in rows] == ["full, AO 2, spp 1", "full, AO 2, a-trous"], out
    for _, ms, db in rows:
        assert math.isfinite(float(ms)) and float(ms) > 0 and math.isfinite(float(db))
