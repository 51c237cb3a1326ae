"""Screenshots of the browser viewer for the README, taken in headless Chromium (Playwright)
against a running `isosr serve`:

    isosr serve --port 8771 &            # serves ../shared/volumes when present
    python scripts/viewer_screenshots.py --url http://127.0.0.1:8771 --volume bonsai

Writes docs/img/viewer_full.png (full resolution, shaded, AO), viewer_split.png (split slider:
network upscaling left, full resolution right) and viewer_normals.png (channel view).
A server token, if any, comes from $ISOSR_TOKEN.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import cv2
import numpy as np
from playwright.sync_api import sync_playwright

from isosr_render.atomic import atomic_write

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--no-first-run"]
TIMEOUT_MS = 120_000
MAX_BYTES = 300_000


def frames_after(page, count: int, condition: str = "true") -> None:
    page.wait_for_function(f"Number(document.getElementById('view').dataset.frames) > {count} && ({condition})",
                           timeout=TIMEOUT_MS)


def frames(page) -> int:
    return int(page.get_attribute("#view", "data-frames"))


def save(page, path: Path) -> None:
    """The page as a PNG at zlib level 9 (Chromium's are larger), refused above MAX_BYTES."""
    shot = cv2.imdecode(np.frombuffer(page.screenshot(type="png"), np.uint8), cv2.IMREAD_COLOR)
    data = cv2.imencode(".png", shot, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()
    if len(data) > MAX_BYTES:
        raise SystemExit(f"{path.name}: {len(data)} bytes exceed {MAX_BYTES}; use a smaller --size")
    atomic_write(path, lambda f: f.write(data))
    print(f"wrote {path} ({len(data) // 1024} KB)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default="http://127.0.0.1:8771")
    p.add_argument("--volume", default="bonsai")
    p.add_argument("--size", default="960x540", help="browser window, WIDTHxHEIGHT")
    p.add_argument("--camera", default='{"yaw": 35, "pitch": 15, "distance": 1.5, "target": [0, 0, 0], "fov_y": 40}')
    p.add_argument("--out", type=Path, default=Path("docs/img"))
    p.add_argument("--chromium", default="/usr/bin/chromium")
    args = p.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    token = os.environ.get("ISOSR_TOKEN", "")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=args.chromium, args=CHROMIUM_ARGS)
        # bypass_csp: the page forbids eval, which wait_for_function uses.
        page = browser.new_page(viewport={"width": width, "height": height}, bypass_csp=True)
        page.add_init_script(f"sessionStorage.setItem('isosr.token', {json.dumps(token)})")
        page.goto(f"{args.url}/?volume={args.volume}")
        frames_after(page, 0)
        page.fill("#camera-json", args.camera)
        page.click("#camera-apply")

        n = frames(page)
        page.select_option("#mode", "full")
        page.check("#ao")
        frames_after(page, n, "document.getElementById('view').dataset.refined === 'true'")
        save(page, args.out / "viewer_full.png")

        page.select_option("#mode", "network")
        page.select_option("#mode-b", "full")
        page.check("#split")
        page.wait_for_function("document.getElementById('view').dataset.split === 'full'", timeout=TIMEOUT_MS)
        save(page, args.out / "viewer_split.png")

        page.uncheck("#split")
        n = frames(page)
        page.select_option("#channel", "normal")
        frames_after(page, n, "document.getElementById('view').dataset.channel === 'normal' && "
                              "document.getElementById('view').dataset.refined === 'true'")
        save(page, args.out / "viewer_normals.png")
        browser.close()


if __name__ == "__main__":
    main()
