"""`isosr kernels`: the project's Warp modules compiled ahead of time by NVRTC on this machine (no GPU
needed), a cubin and a PTX per architecture, where Warp's loader on a GPU node finds them when
WARP_CACHE_PATH names the folder; an architecture NVRTC cannot compile is refused naming those it can."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import warp as wp

from isosr_cli.main import main
from isosr_net.warp_modules import WARP_MODULES, warp_module

ROOT = Path(__file__).resolve().parents[1]
SMALL_MODULE = "isosr_net.ray_history"  # one kernel: about a second a format for sm_90 here

# In a fresh process with WARP_CACHE_PATH set, as on the node: per format, whether Warp's own cache lookup
# (the one Module.load makes) would compile the module for sm_90 (True) or finds it (False).
LOOKUP = """
import json, sys, warp as wp
from isosr_net.warp_modules import warp_module
wp.init()
module = warp_module(sys.argv[1])
print(json.dumps({fmt: module._compile(None, output_arch=90, use_ptx=fmt == "ptx") for fmt in ("cubin", "ptx")}))
"""


@pytest.fixture(autouse=True)
def nvrtc():
    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build's NVRTC cannot compile for sm_90 (a build without CUDA)")


@pytest.mark.slow
def test_writes_a_cubin_and_a_ptx_where_warps_loader_looks(tmp_path, capsys):
    assert main(["kernels", "--arch", "90", "--module", SMALL_MODULE, "--cache", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    ident = warp_module(SMALL_MODULE).get_module_identifier()
    folder = tmp_path / wp.config.version / ident
    assert {p.name for p in folder.iterdir()} >= {f"{ident}.sm90.cubin", f"{ident}.sm90.ptx", f"{ident}.meta"}
    assert f"{SMALL_MODULE}: " in out and f"WARP_CACHE_PATH={tmp_path.resolve()}" in out

    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path),
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run([sys.executable, "-c", LOOKUP, SMALL_MODULE], env=env, capture_output=True, text=True,
                            timeout=300, check=False)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == {"cubin": False, "ptx": False}


def test_an_arch_nvrtc_cannot_compile_is_refused_naming_the_supported_ones(tmp_path, capsys):
    assert main(["kernels", "--arch", "90", "--arch", "91", "--cache", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    supported = ", ".join(map(str, wp.get_cuda_supported_archs()))
    assert err.startswith("isosr kernels: error:") and "--arch 91;" in err and supported in err
    assert not list(tmp_path.iterdir())  # refused before compiling anything


def test_list_prints_the_project_warp_modules_each_of_which_has_kernels(capsys):
    assert main(["kernels", "--list"]) == 0
    assert capsys.readouterr().out.split() == list(WARP_MODULES)
    assert all(warp_module(name).kernels for name in WARP_MODULES)
