"""SRNet: the frame-recurrent super-resolution network of Weiss et al., and its checkpoints.

Per frame the network sees the low-res buffers (mask, normal, depth) and its own previous
high-res output, warped to the current frame by the upscaled flow and flattened by
space-to-depth. Mask, normal and depth come out as residuals over the bilinearly upsampled
input; ambient occlusion is inferred from scratch. Channel orders:
:data:`isosr_render.conventions.LOWRES_CHANNELS` / ``HIGHRES_CHANNELS``.

A checkpoint is a folder that describes itself: ``model.safetensors`` beside
``config.json`` (its ``"format_version"``, the model's config under ``"model"``, plus
whatever the trainer adds: training config, validation metrics). Files written before the
version was recorded read as version 1.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save
from torch import nn

from isosr_render.atomic import atomic_write
from isosr_render.conventions import AO, DEPTH, HIGHRES_CHANNELS, LOWRES_CHANNELS, MASK, NORMAL
from isosr_render.shapes import check_shape
from isosr_net.architectures import ResidualBlock
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.reconnet import ReconNet, ReconNetConfig

LOWRES = len(LOWRES_CHANNELS)
HIGHRES = len(HIGHRES_CHANNELS)
FIRST_FRAME_MODES = ("zeros", "upsampled")
TAILS = ("full", "subpixel")
# The layout of config.json this code writes and reads; files without the key are version 1.
FORMAT_VERSION = 1
# A training checkpoint's optimizer state, step and the like, beside the model (torch.save).
TRAINING_STATE = "training_state.pt"


@dataclass(frozen=True)
class SRNetConfig:
    """SRNet's hyper-parameters.

    Attributes:
        upscale: resolution factor, a power of two (2, 4, 8).
        channels: feature channels.
        residual_blocks: residual blocks at low resolution.
        first_frame: the "previous output" of a sequence's first frame: ``"zeros"``, or the
            ``"upsampled"`` input with AO 1 (the paper's two options).
        tail: ``"full"``: log2(s) times bilinear 2x and a conv, then two convs at the output
            resolution (the paper's); ``"subpixel"``: two convs at low resolution, the last
            with ``6 s^2`` outputs rearranged into the high-res frame (``F.pixel_shuffle``),
            no convolution at the output resolution.
    """

    type: str = "SRNet"
    upscale: int = 4
    channels: int = 64
    residual_blocks: int = 10
    first_frame: str = "zeros"
    tail: str = "full"

    def __post_init__(self):
        if self.upscale < 2 or self.upscale & (self.upscale - 1):
            raise ValueError(f"upscale must be a power of two >= 2, got {self.upscale}")
        if self.first_frame not in FIRST_FRAME_MODES:
            raise ValueError(f"first_frame must be one of {FIRST_FRAME_MODES}, got {self.first_frame!r}")
        if self.tail not in TAILS:
            raise ValueError(f"tail must be one of {TAILS}, got {self.tail!r}")
        if self.channels < 1 or self.residual_blocks < 0:
            raise ValueError(f"channels must be >= 1 and residual_blocks >= 0, got {self.channels}, "
                             f"{self.residual_blocks}")


class SRNet(nn.Module):
    """Frame-recurrent upscaler of isosurface buffers.

    Shape:
        lowres: (B, 5, h, w). prev_warped: (B, 6, h * s, w * s). Returns (B, 6, h * s, w * s).
    """

    def __init__(self, config: SRNetConfig):
        super().__init__()
        self.config = config
        c, s = config.channels, config.upscale
        self.head = nn.Conv2d(LOWRES + HIGHRES * s * s, c, 3, padding=1)
        self.body = nn.Sequential(*[ResidualBlock(c) for _ in range(config.residual_blocks)])
        subpixel = config.tail == "subpixel"
        self.upsample = nn.ModuleList(nn.Conv2d(c, c, 3, padding=1) for _ in range(0 if subpixel else int(math.log2(s))))
        self.tail = nn.Sequential(nn.Conv2d(c, c, 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(c, HIGHRES * (s * s if subpixel else 1), 3, padding=1))

    def forward(self, lowres: torch.Tensor, prev_warped: torch.Tensor) -> torch.Tensor:
        s = self.config.upscale
        dims = check_shape(lowres, f"(B, {LOWRES}, h, w)", "lowres", "SRNet")
        check_shape(prev_warped, f"(B, {HIGHRES}, {dims['h'] * s}, {dims['w'] * s})", "prev_warped", "SRNet", dims)
        x = torch.cat([lowres, F.pixel_unshuffle(prev_warped, s)], dim=1)
        x = F.relu(self.head(x))
        raw = self.tail(self.upsample_features(self.body(x)))
        if self.config.tail == "subpixel":
            raw = F.pixel_shuffle(raw, s)
        base = F.interpolate(lowres, scale_factor=s, mode="bilinear", align_corners=False)
        mask = (base[:, MASK] + raw[:, MASK]).clamp(0.0, 1.0)
        normal = base[:, NORMAL] + raw[:, NORMAL]
        depth = base[:, DEPTH] + raw[:, DEPTH]
        ao = torch.sigmoid(raw[:, AO])
        return torch.cat([mask, normal, depth, ao], dim=1)

    def upsample_features(self, x: torch.Tensor) -> torch.Tensor:
        """log2(s) times (none with the subpixel tail): bilinear 2x, conv, ReLU."""
        for conv in self.upsample:
            x = F.relu(conv(F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)))
        return x

    def first_previous(self, lowres: torch.Tensor) -> torch.Tensor:
        """The stand-in for the previous output on a sequence's first frame."""
        b, _, h, w = lowres.shape
        s = self.config.upscale
        if self.config.first_frame == "zeros":
            return lowres.new_zeros(b, HIGHRES, h * s, w * s)
        base = F.interpolate(lowres, scale_factor=s, mode="bilinear", align_corners=False)
        return torch.cat([base, torch.ones_like(base[:, :1])], dim=1)

    def step(self, lowres: torch.Tensor, flow: torch.Tensor | None,
             previous: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrent step: warp ``previous`` by the upscaled ``flow``, then infer.

        ``previous`` (and ``flow``) are ``None`` on a sequence's first frame.

        Returns:
            ``(output, previous_warped)``, both (B, 6, H, W).

        Shape:
            lowres: (B, 5, h, w). flow: (B, 2, h, w), low-res pixels. previous: (B, 6, H, W).
        """
        if previous is None:
            warped = self.first_previous(lowres)
        else:
            if flow is None:
                raise ValueError("a step with a previous output needs the flow to warp it")
            warped = warp_by_flow(previous, upscale_flow(flow, self.config.upscale))
        return self(lowres, warped), warped


class Unrolled(nn.Module):
    """The recurrent network run over whole sequences: one forward per step, as DDP expects.

    The first frame has no previous frame: its flow slot is not read (see
    :class:`isosr_net.batch.SequenceBatch`).

    Shape:
        lowres: (B, T, 5, h, w). flow: (B, T, 2, h, w). Returns outputs and warped previous
        outputs, each (B, T, 6, H, W).
    """

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, lowres: torch.Tensor, flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        outputs, warped, previous = [], [], None
        for t in range(lowres.shape[1]):
            out, prev_warped = self.net.step(lowres[:, t], flow[:, t] if t else None, previous)
            outputs.append(out)
            warped.append(prev_warped)
            previous = out
        return torch.stack(outputs, 1), torch.stack(warped, 1)


MODELS = {"SRNet": (SRNet, SRNetConfig), "ReconNet": (ReconNet, ReconNetConfig)}


def build_model(config: dict) -> nn.Module:
    """A network from its config dict; the ``type`` key picks the class."""
    kind = config.get("type", "SRNet")
    if kind not in MODELS:
        raise ValueError(f"unknown model type {kind!r}; known: {sorted(MODELS)}")
    cls, config_cls = MODELS[kind]
    try:
        return cls(config_cls(**config))
    except TypeError as e:
        raise ValueError(f"bad model config {config}: {e}") from e


def save_pretrained(model: nn.Module, folder: str | os.PathLike, extra: dict | None = None) -> None:
    """Write ``model.safetensors`` and ``config.json`` (format version, model config, ``extra``) into ``folder``.

    Raises:
        ValueError: ``extra`` names ``format_version`` or ``model``.
    """
    reserved = sorted({"format_version", "model"} & set(extra or {}))
    if reserved:
        raise ValueError(f"save_pretrained: extra may not set {reserved}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().float().cpu().contiguous() for k, v in model.state_dict().items()}
    atomic_write(folder / "model.safetensors", lambda f: f.write(save(state)))
    config = {"format_version": FORMAT_VERSION, "model": asdict(model.config), **(extra or {})}
    atomic_write(folder / "config.json", lambda f: f.write(json.dumps(config, indent=1).encode()))


@dataclass
class Checkpoint:
    """A training checkpoint as :func:`load_checkpoint` found it.

    Attributes:
        folder: where it was read (the asked folder, or its ``.old`` twin).
        model: the network, in eval mode.
        config: its ``config.json``.
        state: the training state saved with it.
    """

    folder: Path
    model: nn.Module
    config: dict
    state: dict


def save_checkpoint(model: nn.Module, folder: str | os.PathLike, extra: dict | None = None,
                    training_state: dict | None = None) -> None:
    """Write a model folder whole or not at all, with ``training_state`` beside it when given.

    The folder is written beside the target (``.NAME.tmp``), then swapped in; during the swap
    the previous one is ``NAME.old``, which :func:`load_checkpoint` falls back to.

    Args:
        model: the network.
        folder: the checkpoint folder, e.g. ``run/last``.
        extra: more ``config.json`` entries (see :func:`save_pretrained`).
        training_state: what resuming needs (optimizer state, step), saved with ``torch.save``.
    """
    folder = Path(folder)
    tmp, old = folder.with_name(f".{folder.name}.tmp"), folder.with_name(f"{folder.name}.old")
    shutil.rmtree(tmp, ignore_errors=True)
    save_pretrained(model, tmp, extra)
    if training_state is not None:
        torch.save(training_state, tmp / TRAINING_STATE)
    if folder.exists():
        shutil.rmtree(old, ignore_errors=True)
        folder.rename(old)
    tmp.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def load_checkpoint(folder: str | os.PathLike, device: str | torch.device = "cpu") -> Checkpoint | None:
    """The training checkpoint :func:`save_checkpoint` left at ``folder``, or at ``folder.old``
    (a swap that was cut off); None where neither holds a training state."""
    folder = Path(folder)
    for candidate in (folder, folder.with_name(f"{folder.name}.old")):
        if (candidate / TRAINING_STATE).is_file():
            model, config = load_pretrained(candidate, device)
            state = torch.load(candidate / TRAINING_STATE, map_location=device, weights_only=True)
            return Checkpoint(candidate, model, config, state)
    return None


def read_config(folder: str | os.PathLike) -> dict:
    """A model folder's ``config.json``, its format version checked (absent: version 1).

    Raises:
        FileNotFoundError: the folder has no ``config.json``.
        ValueError: not a JSON object with a ``"model"`` entry, or a format version this code
            does not know (written by a newer isosr).
    """
    path = Path(folder) / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: not a model folder, config.json is missing")
    try:
        config = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON: {e}") from e
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict):
        raise ValueError(f"{path}: expected a JSON object with the model's config under \"model\"")
    version = config.get("format_version", 1)
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: unknown format version {version!r}; this isosr reads version {FORMAT_VERSION} "
                         f"(a file from a newer isosr needs that isosr)")
    return config


def load_pretrained(folder: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[nn.Module, dict]:
    """Load a checkpoint folder; returns the model (eval mode) and its ``config.json``.

    Raises:
        FileNotFoundError: the folder lacks ``config.json`` or ``model.safetensors``.
        ValueError: the config is unreadable (see :func:`read_config`) or the weights do not fit it.
    """
    folder = Path(folder)
    config = read_config(folder)
    if not (folder / "model.safetensors").is_file():
        raise FileNotFoundError(f"{folder}: not a model folder, model.safetensors is missing")
    model = build_model(config["model"])
    state = load_file(folder / "model.safetensors", device=str(device))
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in state.items()}
    if expected != found:
        missing, unexpected = sorted(set(expected) - set(found)), sorted(set(found) - set(expected))
        resized = sorted(k for k in set(expected) & set(found) if expected[k] != found[k])
        raise ValueError(f"{folder}: weights do not fit the config: {len(missing)} missing, {len(unexpected)} "
                         f"unexpected, {len(resized)} of another shape (first: {(missing + unexpected + resized)[0]})")
    model.load_state_dict(state)
    return model.to(device).eval(), config

