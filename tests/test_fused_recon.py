"""The fused ReconNet (isosr_net.fused_recon): its weights' layout, traffic floors and fallback here;
its Triton kernels in a subprocess (tests/fused_checks.py) under the interpreter and on CUDA."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from isosr_net.flow_warp import warp_by_flow
from isosr_net.fused_recon import (FusedReconNet, fused_reconnet, fused_runs_on, fused_traffic, tap_weights,
                                   triton_imports)
from isosr_net.reconnet import ReconNet, ReconNetConfig
from isosr_net.reconstructor import Reconstructor

from conftest import SHARD_ENV
from test_reconnet import recon_batch

ROOT = Path(__file__).resolve().parents[1]


def run_checks(interpret: bool) -> None:
    """tests/fused_checks.py in fresh processes (TRITON_INTERPRET is read when the kernels are defined):
    under the interpreter its tests shared out over one process a core (conftest's shards), on CUDA one."""
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    if interpret:
        env["TRITON_INTERPRET"] = "1"
    shards = max(1, min(2, os.cpu_count() or 1)) if interpret else 1
    runs = [subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/fused_checks.py"],
                             cwd=ROOT, env=env | {SHARD_ENV: f"{k}/{shards}"}, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for k in range(shards)]
    for run in runs:
        stdout, stderr = run.communicate(timeout=600)
        assert run.returncode == 0 and " passed" in stdout, stdout[-6000:] + stderr[-2000:]
        assert "skipped" not in stdout, stdout[-2000:]


@pytest.mark.skipif(not triton_imports(), reason="triton is not installed (pip install triton==3.6.0)")
def test_the_kernels_equal_their_references_under_the_interpreter():
    run_checks(interpret=True)


@pytest.mark.skipif(not (torch.cuda.is_available() and triton_imports()),
                    reason="the CUDA kernels need a CUDA GPU and Triton (run on the GPU machine)")
def test_the_kernels_equal_their_references_on_cuda():
    run_checks(interpret=False)


def test_tap_weights_are_tap_major_and_zero_padded():
    weight = torch.randn(6, 10, 3, 3, dtype=torch.float64)
    taps = tap_weights(weight, 16, 16)
    assert taps.shape == (9, 16, 16) and taps.dtype == torch.float16 and taps.is_contiguous()
    for ky, kx in ((0, 0), (1, 2), (2, 1)):
        torch.testing.assert_close(taps[3 * ky + kx, :10, :6], weight[:, :, ky, kx].T.half(), rtol=0, atol=0)
    assert (taps[:, 10:] == 0).all() and (taps[:, :, 6:] == 0).all()
    with pytest.raises(ValueError, match=r"tap_weights: weight \(6, 10, 3, 3\) does not fit 8 in, 16 out"):
        tap_weights(weight, 8, 16)
    with pytest.raises(ValueError, match=r"tap_weights: weight must be \(Co, Ci, 3, 3\), got \(6, 10, 1, 1\)"):
        tap_weights(weight[..., :1, :1], 16, 16)


def test_fused_traffic_counts_each_tensor_once():
    traffic = fused_traffic(1080, 1920)  # the default architecture
    pixels = 1080 * 1920  # 1080 is a multiple of 8: no padding
    assert list(traffic) == ["pack", "head", "down1", "down2", "down3", "body1.1", "body1.2", "body2.1", "body2.2",
                             "up2", "fuse2", "up1", "fuse1", "up0", "fuse0", "tail"]
    assert traffic["pack"] == (8 * 4 + 4 * 4 + 16 * 2) * pixels
    assert traffic["head"] == (16 * 2 + 16 * 2) * pixels
    assert traffic["down1"] == 16 * 2 * pixels + 32 * 2 * pixels // 4
    assert traffic["up0"] == (32 + 16 + 32) * pixels  # skip, the 32-channel coarse (a quarter of the pixels), sum
    assert traffic["fuse0"] == (32 + 32) * pixels
    assert traffic["tail"] == (32 + 5 * 4 + 6 * 4) * pixels
    wide = fused_traffic(1080, 1920, ReconNetConfig(widths=(16, 32, 64, 128), ao_prior="rays"))
    assert wide["body2.2"] == 3 * 128 * 2 * pixels // 64
    assert wide["up2"] == 2 * 64 * 2 * pixels // 16 + 128 * 2 * pixels // 64
    assert wide["tail"] == (32 + 8 * 4 + 6 * 4) * pixels  # the rays' AO and sampling read too
    assert fused_traffic(1080, 1920, warp=False)["pack"] == traffic["pack"] - 2 * 4 * pixels
    x2 = fused_traffic(1080, 1920, ReconNetConfig(upscale=2))  # 1080p rendered, 4K out
    assert x2["pack"] == (8 * 4 + (2 * 4 + 2) * 4 + 16 * 2) * pixels  # the previous output's 2x2 pixels
    assert x2["tail"] == (32 + 5 * 4 + 4 * 6 * 4) * pixels and x2["head"] == traffic["head"]
    assert fused_traffic(13, 21)["head"] == 64 * 16 * 24  # the padded frame
    assert "body1.1" not in fused_traffic(13, 21, ReconNetConfig(blocks=0))
    stem = fused_traffic(1080, 1920, ReconNetConfig(widths=(32, 32, 64, 64), stem_stride=2))  # 1088 rows padded
    padded = 1088 * 1920
    assert stem["pack"] == (8 * 4 + 4 * 4) * pixels + 16 * 2 * padded  # the packed input at full resolution
    assert stem["head"] == 16 * 2 * padded + 32 * 2 * padded // 4  # the first level at half the sides
    assert stem["fuse0"] == 64 * 2 * padded // 4
    assert stem["tail"] == 32 * 2 * padded // 4 + (5 + 6) * 4 * pixels
    with pytest.raises(ValueError, match=r"fused_traffic: h must be an integer >= 1, got 0"):
        fused_traffic(0, 21)


def test_fused_reconnet_refuses_what_it_cannot_fuse():
    with pytest.raises(TypeError, match="fused_reconnet needs a ReconNet, got Conv2d"):
        fused_reconnet(nn.Conv2d(1, 1, 3))
    with pytest.raises(ValueError, match=r"the widths and pixel_tail must be at most 64, the upscale one of "
                                         r"\(1, 2\) \(1 with a pixel tail\), got \(16, 32, 64, 128\), 0 and 1"):
        fused_reconnet(ReconNet(ReconNetConfig(widths=(16, 32, 64, 128))))
    with pytest.raises(ValueError, match=r"got \(16, 32, 64, 64\), 0 and 4"):  # x4's packed input: 40 channels
        fused_reconnet(ReconNet(ReconNetConfig(upscale=4)))
    with pytest.raises(ValueError, match=r"got \(16, 32, 64, 64\), 16 and 2"):  # the tail's MLP reads input pixels
        fused_reconnet(ReconNet(ReconNetConfig(upscale=2, pixel_tail=16)))
    with pytest.raises(ValueError, match=r"got \(32, 32, 64, 64\), 128 and 1"):  # wider than a tile
        fused_reconnet(ReconNet(ReconNetConfig(widths=(32, 32, 64, 64), stem_stride=2, pixel_tail=128)))


@pytest.mark.skipif(fused_runs_on("cpu"), reason="under the interpreter the fused path runs on the CPU")
def test_off_cuda_the_fused_module_is_the_reference():
    torch.manual_seed(0)
    net = ReconNet(ReconNetConfig()).eval()
    fused = fused_reconnet(net)
    assert isinstance(fused, FusedReconNet) and fused.reference is not net  # a copy; net untouched
    inputs, previous, flow = recon_batch(2, 13, 21), torch.rand(2, 6, 13, 21), torch.randn(2, 2, 13, 21)
    with torch.no_grad():
        out, read = fused.step(inputs, flow, previous)
        expected, warped = net.step(inputs, flow, previous)
        torch.testing.assert_close(fused(inputs, warped), expected, rtol=0, atol=0)
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    torch.testing.assert_close(read, warp_by_flow(previous, flow)[:, [0, 5]], rtol=0, atol=0)
    torch.testing.assert_close(fused.first_previous(inputs), net.first_previous(inputs), rtol=0, atol=0)
    with pytest.raises(ValueError, match="needs the flow to warp it"):
        fused.step(inputs, None, previous)


@pytest.mark.skipif(fused_runs_on("cpu"), reason="under the interpreter the fused path runs on the CPU")
def test_a_fused_reconstructor_is_refused_where_it_cannot_run():
    with pytest.raises(ValueError, match="fused: the fused kernels need precision fp16 on a CUDA device"):
        Reconstructor(precision="fp16", fused=True)
    with pytest.raises(ValueError, match="without fast_layers or compile; got fp32"):
        Reconstructor(device="cuda", fused=True)
    assert not isinstance(Reconstructor.fastest(device="cpu").net, FusedReconNet)
