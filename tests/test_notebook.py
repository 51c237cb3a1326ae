"""The notebook widget (:mod:`isosr_client.notebook`) without a browser: a light import, the
traitlets' checks, the `widget` arguments, and `widget(array)` starting a loopback server that answers, whose frames
follow the traitlets, and that stops with the widget."""

from __future__ import annotations

import os
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import traitlets

pytest.importorskip("anywidget", reason="anywidget is not installed (the notebook extra: pip install -e '.[notebook]')")

import isosr_client  # noqa: E402
from isosr_client.notebook import DEFAULT_CAMERA, Viewer  # noqa: E402


def ball(n: int = 32) -> np.ndarray:
    """Distances from the centre of an n^3 grid over [-1, 1]^3: spheres as iso-surfaces."""
    x, y, z = np.meshgrid(*(np.linspace(-1, 1, n),) * 3, indexing="ij")
    return np.sqrt(x * x + y * y + z * z).astype(np.float32)


def test_import_leaves_the_server_out():
    """The kernel that imports the widget loads neither torch, Warp, the renderer nor the server's app."""
    check = ("import sys, isosr_client; isosr_client.widget; print(sorted(m for m in sys.modules if m.split('.')[0] "
             "in ('torch', 'warp', 'fastapi', 'uvicorn') or m in ('isosr_render.renderer', 'isosr_server.app')))")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, env=env, timeout=60, cwd=root)
    assert result.returncode == 0 and result.stdout.strip() == "[]", (result.stdout, result.stderr[-2000:])


def test_camera_updates_partially_and_is_checked():
    w = Viewer(url="http://127.0.0.1:1", volume="proc:torus@32")
    w.camera = {"yaw": 75}
    assert w.camera == DEFAULT_CAMERA | {"yaw": 75}
    with pytest.raises(traitlets.TraitError, match="pitch"):
        w.camera = {"pitch": 95}
    with pytest.raises(traitlets.TraitError, match="unknown fields"):
        w.camera = {"eye": [1, 2, 3]}
    assert w.camera["yaw"] == 75
    with pytest.raises(traitlets.TraitError):
        w.t = -1
    w.close()


def test_widget_arguments():
    w = isosr_client.widget("http://127.0.0.1:8000", "bonsai", token="a-token-of-some-length", iso=0.25)
    assert (w.url, w.volume, w.token, w.iso, w.mode) == ("http://127.0.0.1:8000", "bonsai", "a-token-of-some-length",
                                                         0.25, "auto")
    w.close()
    with pytest.raises(ValueError, match="volume"):
        isosr_client.widget("http://127.0.0.1:8000")
    with pytest.raises(ValueError, match="no volume or token"):
        isosr_client.widget(ball(), token="x" * 12)
    with pytest.raises(ValueError, match="3D"):
        isosr_client.widget(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="spacing"):
        isosr_client.widget(ball(), spacing=(1, 2))


def test_widget_of_an_array_serves_it_on_loopback():
    w = isosr_client.widget(ball(), spacing=(1.0, 1.0, 2.0), width=64, height=48)
    server = w._server
    folder = Path(server._folder.name)
    try:
        assert w.url.startswith("http://127.0.0.1:") and w.volume == "array" and len(w.token) >= 32
        # The token guards the API; the viewer's modules are public, for any origin (the widget's page).
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(w.url + "/v1/volumes", timeout=10)
        assert refused.value.code == 401
        request = urllib.request.Request(w.url + "/v1/volumes", headers={"Authorization": f"Bearer {w.token}"})
        with urllib.request.urlopen(request, timeout=10) as r:
            assert b'"array"' in r.read()
        with urllib.request.urlopen(w.url + "/static/session.js", timeout=10) as r:
            assert r.headers["Access-Control-Allow-Origin"] == "*"

        first = w.frame()
        assert first.shape == (48, 64, 3) and first.dtype == np.uint8
        assert (first != first[0, 0]).any(), "an empty frame"
        w.iso = 0.5  # a smaller sphere
        smaller = w.frame()
        assert (smaller != first).any()
        w.camera = {"yaw": 120.0}
        w.width, w.height = 32, 24
        assert w.frame().shape == (24, 32, 3)
    finally:
        w.close()
    assert not server.running and not folder.exists()
