"""Training data: rendered low-res / high-res sequence pairs, written as shards with a manifest.

As in the paper: per volume, sequences of frames along smooth random camera orbits at a
random iso-value; low-res inputs (mask, normal, depth, flow from the previous frame) without
AO, and high-res ground truth (mask, normal, depth, AO) with many AO rays and supersampling.
Each sequence is rendered at one of the configured frame sides (so that the same crop side
covers whole objects in small frames and a few pixels' worth of AO reach at 4K scale) and
yields crops (same window in every frame) that the surface covers at least half. One shard
per sequence (``safetensors``), listed in ``manifest.json`` with its volume and split; a run
that is stopped resumes where it stopped and writes the same data.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save
from tqdm import tqdm

from isosr_render import Renderer, RenderRequest, Volume, open_volume, orbit
from isosr_render.atomic import atomic_write
from isosr_render.catalog import SHARED_PREFIX, entry, resolve_iso
from isosr_render.conventions import AO_RADIUS, HIGHRES_BUFFERS, LOWRES_BUFFERS
from isosr_render.sequence import sequence_requests
from isosr_net.batch import FIELDS, SequenceBatch
from isosr_net.reconnet import RayLimits
from isosr_net.reconstructor import recon_inputs

MANIFEST = "manifest.json"
# Config fields a folder may be extended with: more sequences, another device (same data).
EXTENDABLE = ("sequences", "device")


@dataclass(frozen=True)
class DatagenConfig:
    """What to render.

    Attributes:
        volumes: procedural specs (``proc:cloud:3@96``, split "train") or shared volumes
            (``shared:bonsai``, split from ``../shared/volumes/volumes.json``).
        sequences: sequences per volume.
        frames: frames per sequence.
        lowres_size: side of the full low-res render, or several sides, of which each sequence
            draws one; the high-res one is ``upscale`` times.
        upscale: resolution factor between input and ground truth; 1 renders data for a
            reconstruction network (:mod:`isosr_net.reconnet`): inputs at the ground truth's
            resolution with sampled AO, ``isosr_render.conventions.RECON_CHANNELS``.
        reconstruction: (upscale > 1) low-res inputs as a reconstruction network reads them
            (sampled AO and the sampling channels), for one that also upscales; upscale 1 data
            always has them.
        crop: low-res crop side (the high-res crop is ``upscale`` times).
        crops: crops kept per sequence at most.
        min_coverage: least mean mask coverage of a crop over its frames.
        ao_samples, ao_radius, spp: ground-truth AO rays per hit, their length (world
            units), and rays per pixel.
        input_spp, input_ao_rays: (reconstruction data) each sequence's inputs are rendered with rays
            per pixel and AO rays per hit drawn from these, within ``max_spp`` and ``max_ao_rays``.
        max_ao_rays, max_spp: (reconstruction data) the :class:`~isosr_net.reconnet.RayLimits` that scale the
            inputs' sampling channels: those of the model to train on the data.
        ray_history: (reconstruction data) each frame's AO rays accumulated along the flow with
            the sequence's earlier ones, as at inference (:mod:`isosr_net.ray_history`); the
            sampling channels then count each pixel's rays.
        iso_jitter: iso-values are drawn uniformly within +-this fraction of the volume's
            reference iso (Otsu's, or the procedural default).
        seed: base seed; each (volume, sequence) derives its own.
        device: where to render.
    """

    volumes: tuple[str, ...] = ("proc:cloud:1@96", "proc:metaballs:1@96")
    sequences: int = 4
    frames: int = 10
    lowres_size: int | tuple[int, ...] = 96
    upscale: int = 4
    reconstruction: bool = False
    crop: int = 32
    crops: int = 4
    min_coverage: float = 0.5
    ao_samples: int = 256
    ao_radius: float = AO_RADIUS
    spp: int = 4
    input_spp: tuple[int, ...] = (1,)
    input_ao_rays: tuple[int, ...] = (0,)
    max_ao_rays: int = 8
    max_spp: int = 4
    ray_history: bool = False
    iso_jitter: float = 0.25
    seed: int = 0
    device: str = "cuda"

    def __post_init__(self):
        for name in ("volumes", "input_spp", "input_ao_rays"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if isinstance(self.lowres_size, (list, tuple)):
            object.__setattr__(self, "lowres_size", tuple(self.lowres_size))
        if not self.sides or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in self.sides):
            raise ValueError(f"lowres_size must be a positive integer or a non-empty list of them, got "
                             f"{self.lowres_size}")
        if self.upscale < 1:
            raise ValueError(f"upscale must be at least 1, got {self.upscale}")
        if not self.recon_inputs and (self.input_spp != (1,) or self.input_ao_rays != (0,) or self.ray_history):
            raise ValueError("input_spp, input_ao_rays and ray_history are for reconstruction data (upscale 1, or "
                             "reconstruction); an upscaler's inputs have 1 ray per pixel and no AO")
        limits = self.limits
        for name, low, high in (("input_spp", 1, limits.max_spp), ("input_ao_rays", 0, limits.max_ao_rays)):
            values = getattr(self, name)
            if not values or any(isinstance(v, bool) or not isinstance(v, int) or not low <= v <= high
                                 for v in values):
                raise ValueError(f"{name} must be a non-empty list of integers in [{low}, {high}], got {values}")
        if self.crop > min(self.sides):
            raise ValueError(f"crop {self.crop} exceeds the low-res render side {min(self.sides)}")
        if self.frames < 2:
            raise ValueError(f"a sequence needs at least 2 frames, got {self.frames}")

    @property
    def recon_inputs(self) -> bool:
        """Whether the inputs are a reconstruction network's (:data:`~isosr_render.conventions.RECON_CHANNELS`)."""
        return self.upscale == 1 or self.reconstruction

    @property
    def sides(self) -> tuple[int, ...]:
        """The low-res render sides a sequence draws from."""
        return self.lowres_size if isinstance(self.lowres_size, tuple) else (self.lowres_size,)

    @property
    def limits(self) -> RayLimits:
        """The ray limits the inputs' sampling channels are scaled by."""
        return RayLimits(self.max_ao_rays, self.max_spp)


def resolve_volume(spec: str) -> tuple[Volume, str, float]:
    """``(volume, split, reference normalized iso)`` for a procedural or ``shared:NAME`` spec."""
    volume = open_volume(spec)
    split = entry(spec.removeprefix(SHARED_PREFIX))["split"] if spec.startswith(SHARED_PREFIX) else "train"
    return volume, split, resolve_iso(spec, volume)


def camera_path(rng: np.random.Generator, frames: int) -> list:
    """A smooth random orbit: steady yaw and pitch rates, distance drifting slowly."""
    yaw, pitch, distance = rng.uniform(0, 360), rng.uniform(-45, 45), rng.uniform(1.2, 2.0)
    d_yaw, d_pitch, d_dist = rng.choice([-1, 1]) * rng.uniform(1.0, 3.0), rng.uniform(-1.0, 1.0), rng.uniform(-0.01, 0.01)
    target = rng.uniform(-0.08, 0.08, 3)
    return [orbit(yaw + t * d_yaw, float(np.clip(pitch + t * d_pitch, -80, 80)), distance + t * d_dist,
                  target=tuple(target)) for t in range(frames)]


def pick_crops(mask: np.ndarray, crop: int, count: int, min_coverage: float, rng: np.random.Generator) -> list:
    """Up to ``count`` crop corners ``(row, col)`` whose mask coverage, averaged over frames, is enough.

    Shape:
        mask: (T, h, w).
    """
    _, h, w = mask.shape
    integral = np.pad(mask.mean(axis=0), ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    coverage = (integral[crop:, crop:] - integral[:-crop, crop:] - integral[crop:, :-crop]
                + integral[:-crop, :-crop]) / (crop * crop)  # (h - crop + 1, w - crop + 1)
    rows, cols = np.nonzero(coverage >= min_coverage)
    if len(rows) == 0:
        return []
    chosen = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
    return [(int(rows[i]), int(cols[i])) for i in chosen]


def render_sequence(renderer: Renderer, cameras: list, iso: float, config: DatagenConfig, seed: int,
                    side: int, input_spp: int = 1, input_ao_rays: int = 0) -> SequenceBatch:
    """Full-frame inputs (``side`` pixels square) and high-res ground truth of one sequence, on the CPU.

    Inputs are rendered at 1/upscale of the ground truth's sides; a reconstruction network's
    (:attr:`DatagenConfig.recon_inputs`) with ``input_spp`` rays per pixel and ``input_ao_rays``
    AO rays per hit (other seeds than the ground truth's, new ones each frame), accumulated
    along the flow where :attr:`DatagenConfig.ray_history`.

    Shape:
        Returns lowres (T, 5, h, w), or (T, 8, h, w) for a reconstruction network; flow (T, 2,
        h, w) (zeros on frame 0); highres (T, 6, H, W).
    """
    n, s, recon = side, config.upscale, config.recon_inputs
    lowres, flows, highres, history = [], [], [], None
    sampled = recon and input_ao_rays
    outputs = LOWRES_BUFFERS + ("flow",) + (("ao",) if sampled else ()) + \
        (("position",) if sampled and config.ray_history else ())
    requests = sequence_requests(cameras, n, n, iso, outputs, spp=input_spp, ao_samples=max(1, input_ao_rays),
                                 ao_radius=config.ao_radius)
    for t, (camera, request) in enumerate(requests):
        lo = renderer.render(camera, replace(request, seed=(seed + t + 2**30) % 2**31))
        hi = renderer.render(camera, RenderRequest(n * s, n * s, iso, HIGHRES_BUFFERS, spp=config.spp,
                                                   ao_samples=config.ao_samples, ao_radius=config.ao_radius,
                                                   seed=seed + t))
        if recon:
            inputs, _, history = recon_inputs(lo, input_ao_rays, input_spp, config.limits, history=history)
        lowres.append(inputs[0].cpu() if recon else lo.channels_first(LOWRES_BUFFERS).cpu())
        flows.append(torch.zeros(2, n, n) if lo.flow is None else lo.flow.permute(2, 0, 1).cpu())
        highres.append(hi.channels_first(HIGHRES_BUFFERS).cpu())
    return SequenceBatch(torch.stack(lowres), torch.stack(flows), torch.stack(highres))


def _cut(frames: torch.Tensor, corners: list, size: int, scale: int = 1) -> torch.Tensor:
    """The crops at low-res ``corners`` of a (T, C, H, W) stack at ``scale`` times low-res: (K, T, C, k, k)."""
    k = size * scale
    if not corners:
        return frames.new_zeros((0, *frames.shape[:2], k, k))
    return torch.stack([frames[:, :, r * scale:r * scale + k, q * scale:q * scale + k] for r, q in corners])


def crops(sequence: SequenceBatch, corners: list, size: int, upscale: int) -> SequenceBatch:
    """The crops of one sequence at low-res ``corners``, ``size`` low-res pixels wide, as a batch.

    Shape:
        sequence: lowres (T, 5, h, w), ... Returns lowres (K, T, 5, size, size), flow (K, T, 2,
        size, size), highres (K, T, 6, size * upscale, size * upscale).
    """
    return SequenceBatch(_cut(sequence.lowres, corners, size), _cut(sequence.flow, corners, size),
                         _cut(sequence.highres, corners, size, upscale))


def _slug(spec: str) -> str:
    """A file-name-safe form of a volume spec."""
    return re.sub(r"[^A-Za-z0-9]+", "_", spec).strip("_")


def _load_manifest(out: Path, config: DatagenConfig) -> dict:
    """The manifest to extend: the existing one (same data config) or a fresh one."""
    path = out / MANIFEST
    wanted = json.loads(json.dumps(asdict(config)))
    if path.is_file():
        manifest = json.loads(path.read_text())
        # A field added since the folder was written reads as its default (what it rendered then).
        written = {**json.loads(json.dumps(asdict(DatagenConfig()))), **manifest["config"]}
        differs = sorted(k for k in wanted if k not in EXTENDABLE and written[k] != wanted[k])
        if differs:
            raise ValueError(f"{path} was written with other {differs}; use a new folder or the same config")
        manifest["config"] = wanted
        return manifest
    return {"version": 1, "config": wanted, "shards": []}


def generate(config: DatagenConfig, out: str | Path, progress: bool = True) -> dict:
    """Render every (volume, sequence) not yet in ``out``'s manifest; returns the manifest."""
    out = Path(out)
    (out / "shards").mkdir(parents=True, exist_ok=True)
    manifest = _load_manifest(out, config)
    done = {shard["file"] for shard in manifest["shards"]}
    todo = [(v, spec, k) for v, spec in enumerate(config.volumes) for k in range(config.sequences)
            if f"shards/{_slug(spec)}_{k:04d}.safetensors" not in done]
    renderers: dict[str, tuple[Renderer, str, float]] = {}
    for v, spec, k in tqdm(todo, desc="sequences", disable=not progress):
        if spec not in renderers:
            renderers.clear()  # one volume on the device at a time
            volume, split, iso_ref = resolve_volume(spec)
            renderers[spec] = (Renderer(volume, config.device), split, iso_ref)
        renderer, split, iso_ref = renderers[spec]
        rng = np.random.default_rng([config.seed, v, k])
        iso = float(np.clip(iso_ref * rng.uniform(1 - config.iso_jitter, 1 + config.iso_jitter), 1e-3, 1 - 1e-3))
        sampling = {}
        if config.recon_inputs:
            sampling = {"input_spp": int(rng.choice(config.input_spp)),
                        "input_ao_rays": int(rng.choice(config.input_ao_rays))}
        # Drawn only from several sides: a config of one side renders what it rendered before sides were listed.
        side = config.sides[0] if len(config.sides) == 1 else int(rng.choice(config.sides))
        frames = render_sequence(renderer, camera_path(rng, config.frames), iso, config,
                                 seed=int(rng.integers(2**31 - config.frames)), side=side, **sampling)
        corners = pick_crops(frames.lowres[:, 0].numpy(), config.crop, config.crops, config.min_coverage, rng)
        cut = crops(frames, corners, config.crop, config.upscale)
        # Stored in float16, the flow in float32 (sub-pixel motion over tens of pixels).
        tensors = {"lowres": cut.lowres.half(), "flow": cut.flow.float(), "highres": cut.highres.half()}
        name = f"shards/{_slug(spec)}_{k:04d}.safetensors"
        data = save({key: t.contiguous() for key, t in tensors.items()})
        atomic_write(out / name, lambda f: f.write(data))
        manifest["shards"].append({"file": name, "volume": spec, "split": split, "sequence": k, "iso": iso,
                                   "crops": len(corners), "side": side, **sampling})
        atomic_write(out / MANIFEST, lambda f: f.write(json.dumps(manifest, indent=1).encode()))
    return manifest


class SequenceDataset(torch.utils.data.Dataset):
    """The crops of one split, held in memory (as stored: float16, flow float32).

    Items: float32 :class:`SequenceBatch` sequences, lowres (T, 5, c, c), flow (T, 2, c, c),
    highres (T, 6, C, C); :meth:`batch` gives several at once.
    """

    def __init__(self, root: str | Path, split: str):
        root = Path(root)
        path = root / MANIFEST
        if not path.is_file():
            raise FileNotFoundError(f"no {MANIFEST} in {root}: run `isosr datagen` first")
        manifest = json.loads(path.read_text())
        self.config = manifest["config"]
        shards = [s for s in manifest["shards"] if s["split"] == split and s["crops"]]
        if not shards:
            raise ValueError(f"{root}: no crops of split {split!r}; splits there: "
                             f"{sorted({s['split'] for s in manifest['shards']})}")
        self.crops = SequenceBatch.cat([SequenceBatch(*(load_file(root / s["file"])[k] for k in FIELDS))
                                        for s in shards])
        self.volumes = [s["volume"] for s in shards for _ in range(s["crops"])]

    @property
    def limits(self) -> RayLimits:
        """The ray limits its reconstruction inputs' sampling channels are scaled by."""
        return DatagenConfig(**self.config).limits

    def to(self, device: str | torch.device) -> "SequenceDataset":
        """Move the crops (kept in float16) to ``device``; returns self."""
        self.crops = self.crops.to(device)
        return self

    def __len__(self) -> int:
        return len(self.volumes)

    def __getitem__(self, i: int) -> SequenceBatch:
        return self.crops.apply(lambda t: t[i]).float()

    def batch(self, index: torch.Tensor | slice) -> SequenceBatch:
        """The float32 crops at ``index`` (an index tensor or a slice), as a batch."""
        return self.crops[index].float()
