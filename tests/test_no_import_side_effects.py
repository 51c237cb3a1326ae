"""Importing the project changes nothing process-wide: Warp's global config and the umask stay
as they were; the renderer's kernels turn off gradients for their own module only. The plain
server (its app, the command line, the replica middleware) imports no Ray: only
`isosr_server.cluster` does."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

from isosr_render.atomic import atomic_write

_CHECK = """
import os, sys, warp as wp
before = (wp.config.log_level, wp.config.enable_backward)
umask = os.umask(0o022); os.umask(umask)
import isosr_render, isosr_render.kernels, isosr_render.atomic, isosr_net.upscaler, isosr_net.train, isosr_cli.main
import isosr_bench.common
assert (wp.config.log_level, wp.config.enable_backward) == before, ((wp.config.log_level, wp.config.enable_backward), before)
assert wp.get_module_options(isosr_render.kernels)["enable_backward"] is False
now = os.umask(0o022); os.umask(now)
assert now == umask, (now, umask)
import isosr_server.replica
from isosr_server.app import create_app
from isosr_server.core.config import Settings
create_app(Settings())
assert not [m for m in sys.modules if m == 'ray' or m.startswith('ray.')]
print("clean")
"""


def test_imports_leave_warp_config_and_umask_alone_and_the_plain_server_imports_no_ray():
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", _CHECK], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0 and "clean" in result.stdout, result.stderr[-2000:]


def test_atomic_write_uses_the_umask_of_the_moment(tmp_path):
    for umask in (0o027, 0o002):
        previous = os.umask(umask)
        try:
            atomic_write(tmp_path / f"{umask:o}.bin", lambda f: f.write(b"x"))
        finally:
            os.umask(previous)
        assert stat.S_IMODE((tmp_path / f"{umask:o}.bin").stat().st_mode) == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["2.bin", "27.bin"]  # no temporary left
