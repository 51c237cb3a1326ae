"""Shared helpers of the network tests: tiny datagen folders, tiny models, random VGG weights.

Everything is sized to run in seconds on two CPU cores. The data and model built here are
cached per test session (keyed by the pytest session's temporary root), so every test module
that asks for them shares one copy.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import torch
from safetensors.torch import save_file

from isosr_net.datagen import MANIFEST, DatagenConfig, generate
from isosr_net.model import build_model, save_pretrained

# The smallest data that still exercises everything: two procedural volumes, 16x16 low-res,
# x2 ground truth with a few AO rays, 3 frames per sequence, 8x8 crops.
TINY_DATAGEN = DatagenConfig(volumes=("proc:cloud:1@32", "proc:sphere@32"), sequences=2, frames=3,
                             lowres_size=16, upscale=2, crop=8, crops=2, min_coverage=0.3,
                             ao_samples=4, spp=1, device="cpu")
TINY_MODEL = {"type": "SRNet", "upscale": 2, "channels": 8, "residual_blocks": 1}
# Reconstruction data (upscale 1): 32x32 frames, 16x16 crops (ReconNet's 1/8 level: 2x2),
# inputs of 1 or 2 rays per pixel and 0, 2 or 8 AO rays; 2 frames per sequence.
TINY_RECON_DATAGEN = replace(TINY_DATAGEN, frames=2, lowres_size=32, upscale=1, crop=16, input_spp=(1, 2),
                             input_ao_rays=(0, 2, 8))
TINY_RECON_MODEL = {"type": "ReconNet", "widths": (4, 4, 8, 8), "blocks": 1}
# For a model over the input rays taking up to 16: frames of two sides, 0 or 16 AO rays.
TINY_WIDE_RECON_DATAGEN = replace(TINY_RECON_DATAGEN, lowres_size=(16, 32), input_ao_rays=(0, 16), max_ao_rays=16)
# For a model that reconstructs and upscales x2: inputs at half the ground truth's sides.
TINY_RECON_X2_DATAGEN = replace(TINY_RECON_DATAGEN, lowres_size=16, upscale=2, reconstruction=True, crop=8)

_CACHE: dict[tuple, Path] = {}


def tiny_datagen(**overrides) -> DatagenConfig:
    """:data:`TINY_DATAGEN` with ``overrides``."""
    return replace(TINY_DATAGEN, **overrides)


def relabel_as_val(root: Path, volume: str) -> None:
    """Mark the shards of ``volume`` as split "val" in ``root``'s manifest.

    Procedural volumes always land in "train"; only shared volumes carry a "val" split. The
    training and evaluation tests relabel one procedural volume instead, so that they do not
    depend on the shared volumes being present.
    """
    path = root / MANIFEST
    manifest = json.loads(path.read_text())
    for shard in manifest["shards"]:
        if shard["volume"] == volume:
            shard["split"] = "val"
    path.write_text(json.dumps(manifest, indent=1))


def _tiny_data(tmp_path_factory, config, name: str) -> Path:
    """``config`` rendered into a folder with a "train" (cloud) and a "val" (sphere) split, made once per session."""
    key = (name, str(tmp_path_factory.getbasetemp()))
    if key not in _CACHE:
        root = tmp_path_factory.mktemp(name)
        generate(config, root, progress=False)
        relabel_as_val(root, "proc:sphere@32")
        _CACHE[key] = root
    return _CACHE[key]


def tiny_train_data(tmp_path_factory) -> Path:
    """:data:`TINY_DATAGEN` rendered (see :func:`_tiny_data`)."""
    return _tiny_data(tmp_path_factory, TINY_DATAGEN, "tiny_data")


def tiny_recon_data(tmp_path_factory) -> Path:
    """:data:`TINY_RECON_DATAGEN` rendered (see :func:`_tiny_data`)."""
    return _tiny_data(tmp_path_factory, TINY_RECON_DATAGEN, "tiny_recon_data")


def tiny_wide_recon_data(tmp_path_factory) -> Path:
    """:data:`TINY_WIDE_RECON_DATAGEN` rendered (see :func:`_tiny_data`)."""
    return _tiny_data(tmp_path_factory, TINY_WIDE_RECON_DATAGEN, "tiny_wide_recon_data")


def tiny_recon_upscaling_data(tmp_path_factory, s: int = 2) -> Path:
    """:data:`TINY_RECON_X2_DATAGEN` upscaling ``s`` times rendered (see :func:`_tiny_data`)."""
    return _tiny_data(tmp_path_factory, replace(TINY_RECON_X2_DATAGEN, upscale=s), f"tiny_recon_x{s}_data")


def tiny_model_dir(tmp_path_factory, seed: int = 0, **model) -> Path:
    """A saved, randomly initialized tiny SRNet (upscale 2, 8 channels, 1 block), made once per session."""
    config = {**TINY_MODEL, **model}
    key = ("model", str(tmp_path_factory.getbasetemp()), seed, json.dumps(config, sort_keys=True))
    if key not in _CACHE:
        torch.manual_seed(seed)
        net = build_model(config)
        # Random init leaves the tail's output near zero; make the residual visible.
        with torch.no_grad():
            net.tail[-1].weight.mul_(10.0)
        folder = tmp_path_factory.mktemp("tiny_model")
        save_pretrained(net, folder, {"note": "random weights for tests"})
        _CACHE[key] = folder
    return _CACHE[key]


def tiny_train_config(data: Path, out: Path, **overrides) -> dict:
    """A TrainConfig dict for the tiny data and model on the CPU."""
    config = {"data": str(data), "out": str(out), "model": dict(TINY_MODEL), "batch_size": 2, "steps": 2,
              "checkpoint_every": 1, "device": "cpu", "amp": False, "seed": 0}
    config.update(overrides)
    return config


# torchvision's vgg19().features: (index, out channels, in channels) of its 16 convolutions.
_VGG_CONVS = [(0, 64, 3), (2, 64, 64), (5, 128, 64), (7, 128, 128), (10, 256, 128), (12, 256, 256),
              (14, 256, 256), (16, 256, 256), (19, 512, 256), (21, 512, 512), (23, 512, 512),
              (25, 512, 512), (28, 512, 512), (30, 512, 512), (32, 512, 512), (34, 512, 512)]


def random_vgg19(tmp_path_factory) -> Path:
    """A VGG-19 features safetensors file with random He-initialized weights, made once per session."""
    key = ("vgg", str(tmp_path_factory.getbasetemp()))
    if key not in _CACHE:
        gen = torch.Generator().manual_seed(0)
        state = {}
        for index, c_out, c_in in _VGG_CONVS:
            state[f"{index}.weight"] = torch.randn(c_out, c_in, 3, 3, generator=gen) * (2.0 / (9 * c_in)) ** 0.5
            state[f"{index}.bias"] = torch.zeros(c_out)
        path = tmp_path_factory.mktemp("vgg") / "vgg19_features.safetensors"
        save_file(state, str(path))
        _CACHE[key] = path
    return _CACHE[key]


def render_lowres_frames(width: int, height: int, frames: int = 3, volume: str = "proc:cloud:1@32",
                         yaw_step: float = 4.0) -> list:
    """Low-res frames (mask, normal, depth, and flow from the previous frame; none on frame 0) on an orbit.

    Cached by arguments; callers get fresh copies of the buffers.
    """
    from isosr_render import Renderer, open_volume, orbit, resolve_iso
    from isosr_render.buffers import FrameBuffers
    from isosr_render.sequence import sequence_requests

    key = ("frames", width, height, frames, volume, yaw_step)
    if key not in _CACHE:
        vol = open_volume(volume)
        renderer = Renderer(vol, "cpu")
        cameras = [orbit(30.0 + t * yaw_step, 20.0, 1.4) for t in range(frames)]
        requests = sequence_requests(cameras, width, height, resolve_iso(volume, vol),
                                     ("mask", "normal", "depth", "flow"))
        _CACHE[key] = [renderer.render(camera, request) for camera, request in requests]
    return [FrameBuffers(**{k: getattr(f, k).clone() for k in f.present()}) for f in _CACHE[key]]
