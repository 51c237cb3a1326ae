"""The browser viewer in headless Chromium (Debian's ``chromium``, driven by Playwright) against a
real `isosr serve` process on loopback: page load, surface, drag, iso, modes, channels, split,
wrong token, a killed server; video decoded with WebCodecs (av1, vp9, h264) equal to the
library's frame, and jpeg with a notice where the server or the browser has no video; the page's
frame decoder's keyframe requests; and the page's msgpack coder against Python's msgpack.
``ISOSR_TEST_DEVICE=cuda`` serves from the GPU."""

from __future__ import annotations

import base64
import json
import os
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch

from conftest import DEVICE
from isosr_render import FrameBuffers, Renderer, RenderRequest, open_volume, orbit, resolve_iso, shade
from isosr_render.images import to_uint8
from isosr_server.channels import false_color
from isosr_server.codecs import video
from isosr_client.serve_process import free_port
from server_fixtures import CORNER_BYTES, write_corner_volume

CHROMIUM = Path("/usr/bin/chromium")
if not CHROMIUM.exists():
    pytest.skip("no browser: /usr/bin/chromium is absent (Debian: apt-get install chromium)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright for Python is not installed")

TOKEN = "viewer-test-token"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--no-first-run"]
# The side panel is 290 px wide: this window leaves a 320x240 view.
WINDOW = {"width": 610, "height": 240}
VOLUME = "proc:torus@32"
FRAME_TIMEOUT_MS = 30_000


@contextmanager
def serve(tmp_path: Path, port: int | None = None, env: dict[str, str] | None = None):
    """`isosr serve` as its own process on loopback (procedural volumes, a token), a free port unless
    given, with ``env`` over this process's environment."""
    port = port or free_port()
    volumes = tmp_path / "volumes"
    volumes.mkdir(exist_ok=True)
    log = open(tmp_path / f"serve-{port}.log", "wb")
    process = subprocess.Popen([sys.executable, "-m", "isosr_cli.main", "serve", "--port", str(port), "--volumes",
                                str(volumes), "--token", TOKEN, "--device", DEVICE, "--log-level", "warning"],
                               stdout=log, stderr=subprocess.STDOUT, env=os.environ | (env or {}))
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                request = urllib.request.Request(url + "/v2/health/ready", headers={"Authorization": f"Bearer {TOKEN}"})
                with urllib.request.urlopen(request, timeout=5):
                    break
            except (urllib.error.URLError, ConnectionError):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"isosr serve did not start: {(tmp_path / f'serve-{port}.log').read_text()}")
                time.sleep(0.2)
        yield process, url
    finally:
        process.terminate()
        process.wait(30)
        log.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with serve(tmp_path_factory.mktemp("viewer")) as (_, url):
        yield url


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


class Viewer:
    """One page of the viewer with its console errors collected; ``script`` runs before the page's own."""

    def __init__(self, browser, url: str, token: str | None, script: str | None = None, volume: str = VOLUME):
        # bypass_csp: the page's policy forbids eval, which Playwright's wait_for_function uses.
        self.page = browser.new_page(viewport=WINDOW, bypass_csp=True)
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        if token:
            self.page.add_init_script(f"sessionStorage.setItem('isosr.token', {json.dumps(token)})")
        if script:
            self.page.add_init_script(script)
        self.page.goto(f"{url}/?volume={volume}")

    def frames(self) -> int:
        return int(self.page.get_attribute("#view", "data-frames"))

    def wait(self, condition: str) -> None:
        self.page.wait_for_function(condition, timeout=FRAME_TIMEOUT_MS)

    def wait_frame_after(self, count: int, extra: str = "true") -> None:
        self.wait(f"Number(document.getElementById('view').dataset.frames) > {count} && ({extra})")

    def pixels(self) -> list[list[int]]:
        """The canvas as rows of RGB triples."""
        return self.shown()[0].tolist()

    def shown(self) -> tuple[np.ndarray, str, bool]:
        """The canvas, (H, W, 3) uint8, with the encoding and keyframe flag of the frame it shows (read at once)."""
        width, height, raw, encoding, keyframe = self.page.evaluate("""() => {
            const c = document.getElementById('view');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let s = '';
            for (let i = 0; i < d.length; i += 4) s += String.fromCharCode(d[i], d[i + 1], d[i + 2]);
            return [c.width, c.height, btoa(s), c.dataset.encoding, c.dataset.keyframe === 'true'];
        }""")
        return np.frombuffer(base64.b64decode(raw), np.uint8).reshape(height, width, 3), encoding, keyframe

    def settle(self, after: int) -> list[list[int]]:
        """The image of the first refined frame (a still view's last) after frame number ``after``."""
        self.wait_frame_after(after, "document.getElementById('view').dataset.refined === 'true'")
        return self.pixels()


def surface_fraction(pixels) -> float:
    """Share of pixels that differ from the white background."""
    flat = [p for row in pixels for p in row]
    return sum(1 for p in flat if min(p) < 230) / len(flat)


def difference(a, b) -> float:
    """Mean absolute difference of two images of the same size, 0-255."""
    flat_a = [c for row in a for p in row for c in p]
    flat_b = [c for row in b for p in row for c in p]
    assert len(flat_a) == len(flat_b)
    return sum(abs(x - y) for x, y in zip(flat_a, flat_b)) / len(flat_a)


def rect(page, element_id: str) -> tuple[float, float, float, float]:
    """An element's box in the window: left, top, right, bottom (getBoundingClientRect)."""
    return tuple(page.evaluate(f"(() => {{ const r = document.getElementById('{element_id}').getBoundingClientRect(); "
                               f"return [r.left, r.top, r.right, r.bottom]; }})()"))


def overlap(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def set_control(page, selector: str, value) -> None:
    page.evaluate("([s, v]) => { const e = document.querySelector(s); e.value = v; "
                  "e.dispatchEvent(new Event(e.type === 'range' ? 'input' : 'change')); }", [selector, value])


def test_viewer_explores_a_volume(server, browser):
    v = Viewer(browser, server, TOKEN)
    page = v.page
    v.wait_frame_after(0)
    assert page.get_attribute("#conn-state", "data-state") == "open"
    assert page.input_value("#mode") == "auto" and not page.is_visible("#interpolation-row")
    shaded = v.settle(0)
    assert 0.05 < surface_fraction(shaded) < 0.9, "no isosurface on the canvas"
    assert len(shaded) == 240 and len(shaded[0]) == 320, "the image does not fit the window"
    assert page.get_attribute("#refined", "data-refined") == "true"
    assert float(page.inner_text("#stat-fps")) >= 0 and "total" in page.inner_text("#stat-times")
    assert page.inner_text("#stat-method") not in ("", "-"), "the frame's method is shown"
    assert page.inner_text("#stat-volume") == "131.1 kB resident (dense float32)"  # 32^3 float32
    stats, view = rect(page, "stats"), rect(page, "view")
    assert not overlap(stats, view), f"the live numbers {stats} cover the image {view}"
    assert stats[2] <= WINDOW["width"] and stats[3] <= WINDOW["height"], f"the live numbers {stats} leave the window"

    # Drag: the camera orbits.
    n = v.frames()
    box = page.locator("#view").bounding_box()
    page.mouse.move(box["x"] + 100, box["y"] + 120)
    page.mouse.down()
    page.mouse.move(box["x"] + 220, box["y"] + 60, steps=5)
    page.mouse.up()
    v.wait_frame_after(n)
    assert page.evaluate("JSON.parse(document.getElementById('camera-json').value).yaw") != 30
    assert page.inner_text("#stat-latency").endswith("ms")
    dragged = v.settle(n)
    assert difference(shaded, dragged) > 1.0, "the drag did not change the image"

    # Wheel zooms, keys orbit, double-click resets; a pasted camera is checked, then applied.
    camera = "JSON.parse(document.getElementById('camera-json').value)"
    distance = page.evaluate(f"{camera}.distance")
    page.mouse.move(box["x"] + 160, box["y"] + 120)
    page.mouse.wheel(0, 300)
    page.wait_for_function(f"{camera}.distance > {distance}")
    yaw = page.evaluate(f"{camera}.yaw")
    page.keyboard.press("ArrowLeft")
    assert page.evaluate(f"{camera}.yaw") == pytest.approx(yaw + 5)
    page.mouse.dblclick(box["x"] + 160, box["y"] + 120)
    assert page.evaluate(camera) == {"yaw": 30, "pitch": 20, "distance": 1.8, "target": [0, 0, 0], "fov_y": 40}
    page.fill("#camera-json", '{"yaw": 10, "pitch": 95, "distance": 1.8}')
    page.click("#camera-apply")
    assert "camera.pitch must be a number in [-89, 89]" in page.inner_text("#banner")
    n = v.frames()
    page.fill("#camera-json", '{"yaw": 80, "pitch": 30, "distance": 1.8}')
    page.click("#camera-apply")
    assert not page.is_visible("#banner") and page.evaluate(f"{camera}.yaw") == 80
    pasted = v.settle(n)

    # Iso: another iso-value, another surface.
    n = v.frames()
    lo, hi = (float(page.get_attribute("#iso", k)) for k in ("min", "max"))
    iso = float(page.input_value("#iso"))
    set_control(page, "#iso", str(iso + 0.1 * (hi - lo)))
    moved = v.settle(n)
    assert difference(pasted, moved) > 1.0, "the iso slider did not change the surface"

    # Modes, from the server's list: each reaches the server and comes back; the AO rays control
    # shows for the modes that read it, starting at the mode's default and kept within its bounds
    # and the server's limit (more would end the session); classic upscaling its interpolation.
    infos = {m["name"]: m for m in page.evaluate("fetch('/v1/modes', {headers: {Authorization: 'Bearer "
                                                   + TOKEN + "'}}).then((r) => r.json())")["modes"]}
    menu = [tuple(o) for o in page.eval_on_selector_all("#mode option", "os => os.map((o) => [o.value, o.text])")]
    assert menu == [(name, m["label"]) for name, m in infos.items() if m["shaded"]]
    for mode in ("full", "upscale", "focus", "reconstruct", "network"):
        n = v.frames()
        set_control(page, "#mode", mode)
        v.wait_frame_after(n, f"document.getElementById('view').dataset.mode === '{mode}'")
        rays = next((o for o in infos[mode]["options"] if o["name"] == "ao_rays"), None)
        assert page.is_visible("#ao-row") == (rays is not None)
        assert page.is_visible("#interpolation-row") == (mode == "upscale")
        if mode == "upscale":
            n = v.frames()
            set_control(page, "#interpolation", "bicubic")
            v.wait_frame_after(n, "document.getElementById('view').dataset.mode === 'upscale'")
            assert not page.is_visible("#banner")
        if mode == "reconstruct":
            assert page.input_value("#ao-rays") == str(rays["default"])
            n = v.frames()
            set_control(page, "#ao-rays", "99999")
            v.wait_frame_after(n, "document.getElementById('view').dataset.mode === 'reconstruct'")
            assert 0 < int(page.input_value("#ao-rays")) <= rays["high"] and not page.is_visible("#banner")
            assert page.get_attribute("#conn-state", "data-state") == "open"

    # Channels: normals in false color (facing the camera: blue over red), depth with its legend.
    n = v.frames()
    set_control(page, "#channel", "normal")
    v.wait_frame_after(n, "document.getElementById('view').dataset.channel === 'normal'")
    normals = v.pixels()
    covered = [p for row in normals for p in row if p[2] > p[0] + 40]
    assert len(covered) > 0.5 * surface_fraction(moved) * 320 * 240, "normals are not in false color"
    assert page.is_visible("#legend-box")
    n = v.frames()
    set_control(page, "#channel", "depth")
    v.wait_frame_after(n, "document.getElementById('view').dataset.channel === 'depth'")
    near, far = (float(page.inner_text(s)) for s in ("#legend-lo", "#legend-hi"))
    assert 0 < near < far < 3, f"depth legend {near}..{far}"
    n = v.frames()
    set_control(page, "#channel", "shaded")
    v.wait_frame_after(n, "document.getElementById('view').dataset.channel === 'shaded'")
    assert not page.is_visible("#legend-box")

    # Keys 1..9 pick the modes in the menu's order.
    page.keyboard.press("3")
    assert page.input_value("#mode") == menu[2][0]
    n = v.frames()
    page.keyboard.press("2")
    assert page.input_value("#mode") == menu[1][0]
    v.wait_frame_after(n, f"document.getElementById('view').dataset.mode === '{menu[1][0]}'")

    # Picking: a click on the surface reads its value and voxel; a second one measures the distance
    # (the ruler); a click beside the surface says so. The server's answers come between frames.
    pixels = v.pixels()
    on = [(x, y) for y in range(8, 232, 8) for x in range(8, 312, 8) if min(pixels[y][x]) < 200]
    off = next((x, y) for y in range(4, 236, 8) for x in range(4, 316, 8) if min(pixels[y][x]) >= 250)
    box = page.locator("#view").bounding_box()
    readout = "document.getElementById('stat-pick').textContent"
    for (x, y), answer in ((on[0], f"{readout}.startsWith('value')"), (on[-1], f"{readout}.endsWith('previous pick')")):
        page.mouse.click(box["x"] + x + 0.5, box["y"] + y + 0.5)
        page.wait_for_function(answer)
    assert page.is_visible("#ruler")
    page.wait_for_function("!document.getElementById('slices').hidden")  # the slices through the pick
    page.wait_for_function("['x', 'y', 'z'].every((a) => document.getElementById(`slice-${a}`).naturalWidth > 0)")
    page.keyboard.press("v")
    page.wait_for_function("document.getElementById('slices').hidden")  # and stays so: a late answer keeps it off
    assert page.evaluate("document.getElementById('slices').hasAttribute('data-off')")

    # Meshes out: the current iso's surface as a PLY file.
    with page.expect_download() as saved:
        page.click("#mesh")
    assert saved.value.suggested_filename.endswith(".ply")
    assert Path(saved.value.path()).read_bytes().startswith(b"ply")
    assert float(page.get_attribute("#ruler", "data-distance")) > 0
    page.mouse.click(box["x"] + off[0] + 0.5, box["y"] + off[1] + 0.5)
    page.wait_for_function(f"{readout}.startsWith('no surface')")

    # Split: the right half comes from a second session in full mode.
    page.check("#split")
    v.wait("document.getElementById('view').dataset.split === 'full'")
    assert page.is_visible("#split-handle")
    assert v.errors == [], v.errors
    page.close()


def test_viewer_clip_plane_keys_and_handle(server, browser):
    """x puts a clip plane across x (keeping x <= 0: half the torus goes), . moves it, the handle drags it, X
    flips the kept side, a cap shows the cut faces; each reaches the server and changes the image."""
    v = Viewer(browser, server, TOKEN)
    page = v.page
    set_control(page, "#mode", "full")
    plain = v.settle(0)
    n = v.frames()
    page.keyboard.press("x")
    assert page.input_value("#clip-axis") == "x"
    cut = v.settle(n)
    assert surface_fraction(cut) < surface_fraction(plain) - 0.02, "the plane did not cut the torus"
    n = v.frames()
    for _ in range(5):
        page.keyboard.press(".")
    assert page.input_value("#clip-offset") == "0.1" and page.inner_text("#clip-value") == "<= 0.1"
    moved = v.settle(n)
    assert surface_fraction(moved) > surface_fraction(cut) + 0.005, "the plane did not move"
    n = v.frames()
    page.locator("#clip-offset").scroll_into_view_if_needed()
    box = page.locator("#clip-offset").bounding_box()  # the handle, dragged to its left end
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] - 20, box["y"] + box["height"] / 2, steps=4)
    page.mouse.up()
    assert page.input_value("#clip-offset") == "-0.5"
    v.settle(n)
    page.evaluate("document.activeElement.blur()")  # keys go to the page, not the handle
    page.keyboard.press("X")  # keep x >= -0.5: the whole torus
    assert page.inner_text("#clip-value") == ">= -0.5"
    page.keyboard.press("X")  # back to x <= -0.5: the camera (on +x) on the removed side, looking at the cut
    n = v.frames()
    set_control(page, "#clip-offset", "0")
    assert page.inner_text("#clip-value") == "<= 0"
    open_cut = v.settle(n)
    n = v.frames()
    set_control(page, "#cap", "below")  # the torus's inside is below its iso (a signed distance)
    capped = v.settle(n)
    assert difference(capped, open_cut) > 1.0, "no cut faces"
    assert v.errors == [], v.errors
    page.close()


def test_viewer_crop_box_handles(server, browser):
    """The crop box's handles: x's upper end at 0 keeps x <= 0 (half the torus goes); y's lower end dragged
    to its upper one leaves a box of no volume (nothing shown); back, the crop as before; whole again, the
    torus whole. Each reaches the server and changes the image. A colouring the server refuses leaves
    a notice and the session."""
    v = Viewer(browser, server, TOKEN)
    page = v.page
    set_control(page, "#mode", "full")
    plain = v.settle(0)
    n = v.frames()
    set_control(page, "#crop-x-hi", "0")
    assert page.inner_text("#crop-value") == "x -0.5…0, y -0.5…0.5, z -0.5…0.5"
    cropped = v.settle(n)
    assert surface_fraction(cropped) < surface_fraction(plain) - 0.02, "the box did not crop the torus"
    n = v.frames()
    page.locator("#crop-y-lo").scroll_into_view_if_needed()
    box = page.locator("#crop-y-lo").bounding_box()  # the handle, dragged to its right end
    page.mouse.move(box["x"] + 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] + 20, box["y"] + box["height"] / 2, steps=4)
    page.mouse.up()
    assert page.input_value("#crop-y-lo") == "0.5"
    assert surface_fraction(v.settle(n)) == 0, "a box of no volume keeps nothing"
    n = v.frames()
    set_control(page, "#crop-y-lo", "-0.5")
    assert difference(v.settle(n), cropped) < 1.0
    n = v.frames()
    set_control(page, "#crop-x-hi", "0.5")
    assert page.inner_text("#crop-value") == ""
    assert difference(v.settle(n), plain) < 1.0
    # A colouring the server refuses (no such volume): a notice naming it, the view as it was, frames going on.
    n = v.frames()
    set_control(page, "#color-by", "field")
    set_control(page, "#color-field", "nowhere")
    v.wait("document.getElementById('notice').textContent.includes('settings.coloring.by')")
    assert difference(v.settle(n), plain) < 1.0 and page.get_attribute("#conn-state", "data-state") == "open"
    assert v.errors == [], v.errors
    page.close()


def red_excess(pixels, where=None) -> float:
    """Mean red minus blue over the surface's pixels (those off the white background; of ``where``'s surface)."""
    where = pixels if where is None else where
    surface = [p for row, at in zip(pixels, where) for p, q in zip(row, at) if min(q) < 230]
    return sum(p[0] - p[2] for p in surface) / max(len(surface), 1)


def test_viewer_pins_a_second_surface(server, browser):
    """'add surface' pins the slider's iso in the chosen colour; with the slider lowered inside it, the pinned
    (outer) surface shows in its red; 'clear' shows the slider's alone again."""
    v = Viewer(browser, server, TOKEN)
    page = v.page
    set_control(page, "#mode", "full")
    plain = v.settle(0)
    page.click("#surface-add")
    assert page.inner_text("#surface-list").count("\u25A0") == 1
    page.evaluate("document.activeElement.blur()")  # keys go to the page, not the button
    n = v.frames()
    for _ in range(8):
        page.keyboard.press("[")  # the slider's iso inside the pinned surface
    pinned = v.settle(n)
    assert red_excess(pinned) > red_excess(plain) + 25, (red_excess(pinned), red_excess(plain))
    n = v.frames()
    page.click("#surface-clear")
    alone = v.settle(n)
    assert page.inner_text("#surface-list") == "" and surface_fraction(alone) < surface_fraction(pinned)
    assert abs(red_excess(alone) - red_excess(plain)) < 10
    page.evaluate("document.activeElement.blur()")
    for _ in range(4):
        page.keyboard.press("]")
    set_control(page, "#surface-opacity", "0.3")
    page.click("#surface-add")  # the slider's iso pinned at 30%
    assert page.inner_text("#surface-list").endswith("(30%)")
    page.evaluate("document.activeElement.blur()")
    n = v.frames()
    for _ in range(8):
        page.keyboard.press("]")  # the slider's iso outside the pinned one: its surface (opaque) hides the red
    hidden = v.settle(n)
    n = v.frames()
    for _ in range(12):
        page.keyboard.press("[")  # back inside the pinned one: the red at 30% over the slider's surface
    seen = v.settle(n)
    assert red_excess(hidden) < red_excess(alone) + 5  # the pinned surface hidden
    # Where the slider's surface shows alone, now 30% red over it: redder, less than the opaque red.
    assert red_excess(alone, alone) + 5 < red_excess(seen, alone) < red_excess(pinned, alone), \
        (red_excess(alone, alone), red_excess(seen, alone), red_excess(pinned, alone))
    assert v.errors == [], v.errors
    page.close()


def test_viewer_coders_match_python(server, browser):
    """The page's msgpack against Python's; its flow legend against the server's flow colors."""
    sample = {"type": "frame", "nil": None, "t": True, "f": False, "ints": [0, 127, 128, 255, 256, 65535, 65536,
              2**32 - 1, 2**32, 2**53, -1, -32, -33, -128, -129, -32768, -32769, -2**31, -2**31 - 1, -2**53],
              "float": 0.1, "neg": -1.5e300, "str": "héllo ✓", "long": "x" * 300, "longer": "y" * 70000,
              "bin0": b"", "bin": bytes(range(256)) * 2, "bigbin": b"\x01" * 70000, "list": list(range(20)),
              "map": {f"k{i}": i for i in range(20)}}
    packed = msgpack.packb(sample, use_bin_type=True)
    single = msgpack.packb({"f32": 0.5}, use_bin_type=True, use_single_float=True)
    v = Viewer(browser, server, TOKEN)
    out = v.page.evaluate("""async ([packed, single]) => {
        const m = await import('/static/msgpack.js');
        const bytes = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
        const value = m.decode(bytes(packed));
        const again = m.encode(value);
        let bad = null;
        try { m.decode(bytes(packed).slice(0, -1)); } catch (e) { bad = e.message; }
        const b64 = (u) => btoa(Array.from(u, (c) => String.fromCharCode(c)).join(''));
        return [b64(again), m.decode(bytes(single)).f32, bad, value.bin instanceof Uint8Array];
    }""", [base64.b64encode(packed).decode(), base64.b64encode(single).decode()])
    again, f32, truncated, is_bytes = out
    assert msgpack.unpackb(base64.b64decode(again), raw=False) == sample
    assert f32 == 0.5 and is_bytes
    assert truncated and "truncated" in truncated

    vectors = [(3.0, 0.0), (0.0, 1.5), (-1.0, -2.0), (2.0, -1.0), (-2.9, 0.4), (0.0, 0.0)]
    flow = torch.tensor(vectors)[None]
    rgb, legend = false_color(FrameBuffers(mask=torch.ones(1, len(vectors)), flow=flow), "flow")
    page_rgb = v.page.evaluate("""async ([vectors, hi]) => {
        const m = await import('/static/legend.js');
        return vectors.map(([x, y]) => m.flowColor(x, y, hi));
    }""", [vectors, legend["hi"]])
    assert torch.allclose(torch.tensor(page_rgb), rgb[0], atol=1e-5), (page_rgb, rgb[0])
    v.page.close()


def test_viewer_shows_a_sparse_volumes_resident_set_and_page_in(browser, tmp_path):
    (tmp_path / "volumes").mkdir()
    write_corner_volume(tmp_path / "volumes")
    with serve(tmp_path, env={"ISOSR_MAX_VOLUME_BYTES": str(CORNER_BYTES - 1)}) as (_, url):
        v = Viewer(browser, url, TOKEN, volume="corner")
        v.wait_frame_after(0)
        text = v.page.inner_text("#stat-volume")
        assert re.fullmatch(r"\d+\.\d kB resident \(sparse, \d+\.?\d*% of bricks\), last page-in \d+\.\d s", text), text
        assert not v.errors, v.errors


def test_viewer_plays_a_time_series(browser, tmp_path):
    (tmp_path / "volumes" / "runs").mkdir(parents=True)
    for i, cx in enumerate((8, 16, 24, 12)):  # a ball that moves
        x, y, z = np.meshgrid(*(np.arange(32.0),) * 3, indexing="ij")
        ball = np.clip(128 + 40 * (6.0 - np.sqrt((x - cx) ** 2 + (y - 16) ** 2 + (z - 16) ** 2)), 0, 255)
        np.save(tmp_path / "volumes" / "runs" / f"run_{i}.npy", ball.astype(np.uint8))
    with serve(tmp_path) as (_, url):
        v = Viewer(browser, url, TOKEN, volume="runs")
        v.wait_frame_after(0)
        assert v.page.is_visible("#time") and v.page.get_attribute("#step", "max") == "3"
        first = v.frames()
        set_control(v.page, "#step", 2)
        v.wait_frame_after(first, "document.getElementById('view').dataset.t === '2'")
        assert v.page.inner_text("#step-value") == "2 / 3"
        set_control(v.page, "#rate", 20)
        v.page.click("#play")
        v.wait("document.getElementById('view').dataset.t !== '2'")  # played on
        assert v.page.inner_text("#play") == "pause"
        v.page.click("#play")
        assert v.page.inner_text("#play") == "play"
        v.page.select_option("#volume", "proc:sphere")
        v.wait("document.getElementById('time').hidden")  # a volume has no time controls
        assert not v.errors, v.errors


def test_viewer_wrong_token_shows_error(server, browser):
    v = Viewer(browser, server, "wrong-token-0000")
    v.wait("document.getElementById('conn-state').dataset.state === 'error'")
    assert "token" in v.page.inner_text("#banner")
    assert v.frames() == 0
    v.page.close()


def test_viewer_shows_lost_connection_and_reconnects(browser, tmp_path):
    port = free_port()
    with serve(tmp_path, port) as (process, url):
        v = Viewer(browser, url, TOKEN)
        v.wait_frame_after(0)
        process.kill()
        process.wait(30)
        v.wait("document.getElementById('conn-state').dataset.state === 'lost'")
        assert "reconnecting" in v.page.inner_text("#banner")
        assert v.page.evaluate("document.getElementById('view').classList.contains('stale')")
    n = v.frames()
    with serve(tmp_path, port):
        v.wait_frame_after(n, "document.getElementById('conn-state').dataset.state === 'open'")
        assert not v.page.is_visible("#banner")
        assert not v.page.evaluate("document.getElementById('view').classList.contains('stale')")
        v.page.close()


# Color PSNR, dB, a video frame on the canvas keeps of the library's frame at the viewer's quality 90
# (measured on this 320x240 torus in Chromium 156: av1 47.3, vp9 46.8, h264 48.9; jpeg 46.1).
VIDEO_PSNR_DB = 40.0
VIDEO_CODEC_PREFIX = {"av1": "av01.", "vp9": "vp09.", "h264": "avc1."}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    assert a.shape == b.shape, (a.shape, b.shape)
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def library_frame(yaw: float, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    """The library's full-resolution frame without AO (the server's ``full`` mode) at the page's
    default camera turned to ``yaw``."""
    volume = open_volume(VOLUME)
    f = Renderer(volume, DEVICE).render(orbit(yaw, 20.0, 1.8), RenderRequest(*size, resolve_iso(VOLUME, volume),
                                                                             ("mask", "normal")))
    return to_uint8(shade(f.mask, f.normal, f.ao))


def test_viewer_decodes_video_into_the_canvas(server, browser):
    """auto asks for av1, the best both sides have; each codec's keyframe, and the delta frames
    after a camera move, reach the canvas through WebCodecs equal to the library's frame within
    the codec's error; the live numbers name the codec and its target bitrate."""
    v = Viewer(browser, server, TOKEN)
    page = v.page
    v.wait_frame_after(0)
    page.uncheck("#refine")  # no lossless refined frame replaces the video frame of a still view
    page.evaluate("document.activeElement.blur()")  # keys go to the view, not the checkbox
    page.keyboard.press("ArrowRight")  # an auto frame (no refined one follows): what auto expects of its method
    v.wait("/\\(auto: (measuring; budget [0-9.]+ ms|[0-9.]+ dB, [0-9.]+ of [0-9.]+ ms)/"
           ".test(document.getElementById('stat-method').textContent)")
    page.keyboard.press("ArrowLeft")  # back to the reference's camera
    set_control(page, "#mode", "full")
    reference = library_frame(30.0)
    for encoding in ("auto", "vp9", "h264"):
        expected = "av1" if encoding == "auto" else encoding
        if encoding != "auto":
            set_control(page, "#encoding", encoding)
        v.wait(f"document.getElementById('view').dataset.mode === 'full' && "
               f"document.getElementById('view').dataset.encoding === '{expected}'")
        image, shown, keyframe = v.shown()
        # A codec change starts with a keyframe; auto's av1 stream goes on across the mode change.
        assert shown == expected and (keyframe or encoding == "auto"), (shown, keyframe)
        assert psnr(image, reference) > VIDEO_PSNR_DB, f"{expected}: {psnr(image, reference):.1f} dB"
        assert page.inner_text("#stat-codec").startswith(f"{expected} ({VIDEO_CODEC_PREFIX[expected]}")
        assert "(target" in page.inner_text("#stat-rate") and page.inner_text("#stat-bytes").endswith("KiB")
    deltas, yaw = 0, 30.0
    for _ in range(4):  # each key press: one camera update, answered by one frame
        n = v.frames()
        page.keyboard.press("ArrowLeft")
        yaw += 5.0
        v.wait_frame_after(n)
        image, shown, keyframe = v.shown()
        assert shown == "h264" and psnr(image, library_frame(yaw)) > VIDEO_PSNR_DB
        deltas += not keyframe
    assert deltas > 0, "no delta frame was shown"
    assert v.errors == [], v.errors
    page.close()


def test_viewer_without_video_sends_jpeg_and_says_why(server, browser, tmp_path):
    """A browser without WebCodecs (as on a plain-http page off loopback) asks for jpeg and says
    why; a server without PyAV, asked for av1, sends jpeg with its notice; either side's missing
    codecs are greyed out in the menu."""
    v = Viewer(browser, server, TOKEN, script="delete window.VideoDecoder;")
    v.wait_frame_after(0)
    assert "this browser decodes no video here" in v.page.inner_text("#notice")
    assert v.page.inner_text("#stat-codec") in ("jpeg", "png")  # png: the refined frame
    assert v.page.get_attribute("#encoding option[value=av1]", "title") == "this browser cannot decode it"
    v.page.close()

    hidden = tmp_path / "no-pyav"
    (hidden / "av").mkdir(parents=True)
    (hidden / "av" / "__init__.py").write_text('raise ImportError("PyAV hidden by the test")\n')
    path = os.pathsep.join(p for p in (str(hidden), os.environ.get("PYTHONPATH")) if p)
    with serve(tmp_path, env={"PYTHONPATH": path}) as (_, url):
        v = Viewer(browser, url, TOKEN)
        v.wait_frame_after(0, "document.getElementById('notice').textContent.includes('PyAV')")
        notice = v.page.inner_text("#notice")
        assert "av1" in notice and "jpeg" in notice, notice
        assert v.page.get_attribute("#view", "data-encoding") in ("jpeg", "png")
        for encoding in ("av1", "vp9", "h264"):
            option = f"#encoding option[value={encoding}]"
            assert v.page.get_attribute(option, "title") == "the server cannot make it"
        assert v.errors == [], v.errors
        v.page.close()


def test_frame_decoder_asks_for_keyframes(server, browser):
    """The page's FrameDecoder on an h264 stream made here: a delta before any keyframe shows
    nothing and asks for a keyframe once; the keyframe and the deltas after it decode to the
    frames' size (63x47 of a 64x48 coded picture) and content; a decoder error asks for a
    keyframe, the third in a row gives the encoding up."""
    y, x = np.mgrid[0:47, 0:63]
    images = [np.stack([(4 * x + 9 * i) % 256, (5 * y) % 256, np.full_like(x, 128 + 20 * i)], -1).astype(np.uint8)
              for i in range(3)]
    encoder = video.VideoEncoder("h264", 63, 47, 90, 4000, 30.0)
    units = [encoder.encode(image, 1000 * (i + 1), keyframe=i == 0) for i, image in enumerate(images)]
    assert [key for _, key in units] == [True, False, False]
    frames = [{"encoding": "h264", "codec": encoder.codec, "keyframe": key, "timestamp_us": 1000 * (i + 1),
               "width": 63, "height": 47, "image": base64.b64encode(data).decode()}
              for i, (data, key) in enumerate(units)]
    v = Viewer(browser, server, TOKEN)
    pictures, calls = v.page.evaluate("""async (frames) => {
        const m = await import('/static/video.js');
        const calls = [];
        const decoder = new m.FrameDecoder({ keyframe: () => calls.push('keyframe'), failed: () => calls.push('failed') });
        const frame = (i, over = {}) => ({ ...frames[i], image: Uint8Array.from(atob(frames[i].image), (c) => c.charCodeAt(0)),
                                           ...over });
        const show = async (f) => {
            const image = await decoder.picture(f);
            if (!image) return null;
            const g = new OffscreenCanvas(image.width, image.height).getContext('2d');
            g.drawImage(image, 0, 0);
            const d = g.getImageData(0, 0, image.width, image.height).data;
            let s = '';
            for (let i = 0; i < d.length; i += 4) s += String.fromCharCode(d[i], d[i + 1], d[i + 2]);
            const out = [image.width, image.height, btoa(s)];
            image.close();
            return out;
        };
        const pictures = [await show(frame(1)), await show(frame(2))];
        calls.push('|');
        for (const i of [0, 1, 2]) pictures.push(await show(frame(i)));
        calls.push('|');
        for (const i of [0, 1, 2]) pictures.push(await show(frame(0, { codec: 'vp09.99.99.99', timestamp_us: 9000 + i })));
        return [pictures, calls];
    }""", frames)
    assert calls == ["keyframe", "|", "|", "keyframe", "keyframe", "failed"], calls
    assert pictures[:2] == [None, None] and pictures[5:] == [None, None, None]
    for (width, height, raw), image in zip(pictures[2:5], images):
        assert (width, height) == (63, 47)
        got = np.frombuffer(base64.b64decode(raw), np.uint8).reshape(47, 63, 3)
        # 4:2:0 chroma of these saturated stripes costs ~40 dB; the neighbouring frame scores ~20.
        assert psnr(got, image) > 30.0, psnr(got, image)
    v.page.close()
