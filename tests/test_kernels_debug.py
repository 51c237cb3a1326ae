"""The kernels under Warp's debug mode, which checks every array access against its bounds.

Release builds do not check out-of-bounds writes (``../shared/notes/warp.md``), so hard cases
run here once in a subprocess with ``wp.config.mode = "debug"``: a 2x2x2 volume, a tiny
anisotropic one with bricks that do not divide it, cameras outside and inside, odd image
sizes, supersampling, every buffer. One thread: Warp 1.19's debug CPU build crashes when
two threads launch at once (release builds are safe and tested bit-identical).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import numpy as np, warp as wp
    wp.config.mode = "debug"
    wp.config.log_level = wp.LOG_WARNING
    from isosr_render import Camera, Renderer, RenderRequest, Volume, orbit
    volumes = [Volume.from_array(np.arange(8, dtype=np.float32).reshape(2, 2, 2)),
               Volume.from_array(np.random.default_rng(0).random((9, 5, 17)), spacing=(1, 1, 10))]
    cameras = [orbit(30, 20, 1.6), Camera((0.0, 0.0, 0.0), (1.0, 0.2, 0.1)), Camera((0.5, 0.5, 0.5), (0.6, 0.7, 0.9))]
    outputs = ("mask", "normal", "depth", "position", "flow", "ao", "color", "samples")
    for volume in volumes:
        for brick in (3, 8):
            renderer = Renderer(volume, "cpu", threads=1, brick_size=brick)
            for camera in cameras:
                request = RenderRequest(13, 7, 0.5, outputs, spp=2, ao_samples=4, prev_camera=orbit(28, 20, 1.6))
                frame = renderer.render(camera, request)
                assert all(np.isfinite(a).all() for a in frame.to_numpy().values())
    print("debug renders ok")
""")


def test_hard_cases_pass_warp_bounds_checks():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "debug renders ok" in result.stdout
