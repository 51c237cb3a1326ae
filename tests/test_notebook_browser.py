"""The notebook widget in a real browser: JupyterLab on loopback (a subprocess, its own token and
folders), a notebook that shows ``isosr_client.widget(array)``, headless Chromium (Playwright) running
its cells: the widget draws a frame; ``w.iso`` set from Python changes the next one; a drag in the
widget reaches Python's ``w.camera``; the widget's server ends with the kernel."""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from isosr_bench.load import proc_stat
from isosr_client.serve_process import free_port

CHROMIUM = Path("/usr/bin/chromium")
if not CHROMIUM.exists():
    pytest.skip("no browser: /usr/bin/chromium is absent (Debian: apt-get install chromium)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright for Python is not installed")
pytest.importorskip("anywidget", reason="anywidget is not installed (the notebook extra: pip install -e '.[notebook]')")
pytest.importorskip("jupyterlab", reason="JupyterLab is not installed (the notebook extra: pip install -e '.[notebook]')")

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--no-first-run"]
WAIT_MS = 60_000
CELLS = [
    "import numpy as np, isosr_client\n"
    "x, y, z = np.meshgrid(*(np.linspace(-1, 1, 32),) * 3, indexing='ij')\n"
    # An iso given: the browser then sends no suggested iso back, which could reach the kernel after the next
    # cell's w.iso = 0.5 and overwrite it there (seen once in four CI runs: the race is noted in docs/notebook.md).
    "w = isosr_client.widget(np.sqrt(x * x + y * y + z * z).astype(np.float32), iso=0.9, width=160, height=120)\n"
    "w",
    "w.iso = 0.5",
    "print('yaw', w.camera['yaw'], 'iso', w.iso, 'server', w._server.pid)",
]


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie does not)."""
    try:
        return proc_stat(pid)[0] != "Z"
    except FileNotFoundError:
        return False


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()  # the server shuts its kernels down
        process.wait(30)


def write_notebook(path: Path) -> None:
    cells = [{"cell_type": "code", "metadata": {}, "execution_count": None, "outputs": [], "source": source}
             for source in CELLS]
    path.write_text(json.dumps({"cells": cells, "nbformat": 4, "nbformat_minor": 5, "metadata": {
        "kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}}}))


@pytest.fixture
def lab(tmp_path):
    """JupyterLab on a free loopback port over ``tmp_path``, with its settings and runtime there too:
    ``(url, token, process)``."""
    token, port = secrets.token_hex(16), free_port()
    write_notebook(tmp_path / "widget.ipynb")
    env = os.environ | {"JUPYTER_CONFIG_DIR": str(tmp_path / "config"), "JUPYTER_RUNTIME_DIR": str(tmp_path / "run"),
                        "JUPYTERLAB_SETTINGS_DIR": str(tmp_path / "settings"),
                        "JUPYTERLAB_WORKSPACES_DIR": str(tmp_path / "workspaces")}
    log = open(tmp_path / "lab.log", "wb")
    process = subprocess.Popen(
        [sys.executable, "-m", "jupyterlab", "--no-browser", "--ServerApp.ip=127.0.0.1", f"--ServerApp.port={port}",
         f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={tmp_path}", "--allow-root",
         "--LabApp.expose_app_in_browser=True", "--LabApp.extension_manager=readonly"],
        stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"{url}/api/status?token={token}", timeout=5):
                    break
            except (urllib.error.URLError, ConnectionError):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"JupyterLab did not start: {(tmp_path / 'lab.log').read_text()[-3000:]}")
                time.sleep(0.3)
        yield url, token, process
    finally:
        stop(process)
        log.close()


def test_widget_in_jupyterlab(lab):
    url, token, process = lab
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1000, "height": 800})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{url}/lab/tree/widget.ipynb?token={token}")
        # The notebook is open and its kernel idle.
        page.wait_for_selector(".jp-Notebook .jp-Cell", timeout=WAIT_MS)
        page.wait_for_function("() => window.jupyterapp?.shell.currentWidget?.sessionContext?.session?.kernel"
                               "?.status === 'idle'", timeout=WAIT_MS)

        def run(cell: int) -> None:
            page.evaluate("(i) => { window.jupyterapp.shell.currentWidget.content.activeCellIndex = i; "
                          "return window.jupyterapp.commands.execute('notebook:run-cell'); }", cell)

        run(0)
        view = ".isosr-widget-view"
        page.wait_for_function(f"() => Number(document.querySelector('{view}')?.dataset.frames) > 0", timeout=WAIT_MS)
        first = page.evaluate(f"() => document.querySelector('{view}').toDataURL()")
        frames = int(page.get_attribute(view, "data-frames"))

        run(1)  # w.iso = 0.5 in Python: the browser's session asks for it
        page.wait_for_function(f"([n, before]) => {{ const c = document.querySelector('{view}'); "
                               "return Number(c.dataset.frames) > n && c.toDataURL() !== before; }",
                               arg=[frames, first], timeout=WAIT_MS)

        box = page.locator(view).bounding_box()
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(cx, cy)
        page.mouse.down()
        page.mouse.move(cx - 50, cy, steps=5)
        page.mouse.up()
        run(2)
        output = page.locator(".jp-OutputArea-output pre", has_text="yaw")
        output.wait_for(timeout=WAIT_MS)
        words = output.inner_text().split()
        assert words[0] == "yaw" and float(words[1]) > 30.0, words  # dragged left: yaw up from 30
        assert words[2:4] == ["iso", "0.5"], words
        status = page.locator(".isosr-widget-status").inner_text()
        assert not status.startswith(("error", "lost")), status
        assert not errors, errors
        browser.close()

    server = int(words[5])
    assert alive(server)
    stop(process)
    deadline = time.monotonic() + 30
    while alive(server):
        assert time.monotonic() < deadline, "the widget's server outlived its kernel"
        time.sleep(0.2)
