"""Training: `isosr train CONFIG.json`.

Sequences from `isosr datagen` are unrolled through the recurrent network (gradients flow
through time), losses come from the config, validation metrics are computed every epoch.
Checkpoints are model folders (`model.safetensors` + `config.json`) with the optimizer state
beside them; a killed run resumes from `OUT/last`. Multi-GPU (or multi-process CPU) through
`torchrun`: each process takes its share of every batch (DistributedDataParallel).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from isosr_render.conventions import LOWRES_CHANNELS, RECON_CHANNELS
from isosr_net.batch import SequenceBatch
from isosr_net.datagen import SequenceDataset
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.losses import PAPER_LOSSES, AdversarialLoss, LossContext, build_losses, total_loss
from isosr_net.metrics import frame_scores
from isosr_net.model import Unrolled, build_model, load_checkpoint, load_pretrained, save_checkpoint
from isosr_net.reconnet import GATE_PARAMETER, WEIGHTLESS_FIELDS, ReconNet, ReconNetConfig


# TrainConfig.compile's modes: "" (eager) and torch.compile's without CUDA graphs, which a step's
# distributed backward and optimizer do not replay.
COMPILE_MODES = ("", "default", "max-autotune-no-cudagraphs")
WARMUP_STEPS = 3  # a run's first steps, timed apart: a compiled step compiles (and recompiles) there


# The validation scores a run's best/ may be picked by, and the sign that makes each "higher is better".
SELECTS = {"color_psnr": 1.0, "loss": -1.0}


@dataclass
class TrainConfig:
    """A training run. Lengths are optimizer steps; an epoch is one pass over the training crops.

    Attributes:
        data: folder written by `isosr datagen`.
        out: run folder: `last/` and `best/` checkpoints, `tb/` TensorBoard logs.
        model: network config (`type` picks the class).
        losses: loss configs (see `isosr_net.losses`); default the paper's L1-normal network.
        batch_size: sequences per step, over all processes.
        steps: optimizer steps in total.
        lr, lr_discriminator: Adam learning rates (the latter for adversarial losses).
        lr_schedule: "constant", or "cosine": linear warm-up over `warmup_steps`, then cosine
            decay to 1% of `lr` at `steps`.
        warmup_steps: steps of the cosine schedule's warm-up.
        checkpoint_every: steps between `last/` checkpoints (also at every validation).
        validate_every: steps between validations (each followed by a `last/` checkpoint); 0: at every epoch's end.
            A larger batch makes shorter epochs: this keeps its validations as far apart in steps as a smaller one's.
        amp: bf16 autocast on CUDA.
        device: "cuda", "cpu" or "auto".
        seed: seed for initialization and data order.
        time_limit_minutes: stop (validated and checkpointed) after this long; 0: no limit.
        init: a model folder to fine-tune (its config must be ``model``'s): its weights, a fresh
            optimizer and schedule; validated before the first step, so that ``best/`` is only
            replaced by a better model. A run that left ``OUT/last`` resumes from that instead.
        trainable: the names of the model's parameters this run trains (the others stay as they start:
            ``init``'s); empty: all. E.g. a gated blend model's ``geometry_gate_raw`` and ``ao_blend_log``
            alone: a few scalars that small data and a CPU can fit.
        compile: a ``torch.compile`` mode for a step's forward and losses (their backward follows):
            ``"default"`` or ``"max-autotune-no-cudagraphs"``; "" runs them eagerly. A step of the
            recurrent network, its losses and shadings is hundreds of small kernels, whose launches
            bound it on a GPU; compiled, they fuse (the first steps compile, minutes on a GPU).
        select: the validation score that picks ``best/``: ``"color_psnr"`` (the highest) or ``"loss"`` (the
            lowest total of ``losses``: a fine-tune whose losses ask for more than color, e.g. ``ao_no_worse``).
        teacher: a model folder run frozen on every sequence beside the model, for the losses that read its output
            (``teacher_psnr_no_worse``); "" for none. Typically ``init``: a fine-tune held to its start.
        gates_open_until: a gated ReconNet's geometry gates held open (at their start) and untrained before this
            step, so that its mask and normal corrections learn before the gates may weigh them: gates that close
            first (as random corrections make them) never reopen, since the corrections then get no gradient. A
            run starting before it opens them (its ``init``'s or its resumed gates too); 0: trained from the start.
    """

    data: str
    out: str
    model: dict = field(default_factory=lambda: {"type": "SRNet", "upscale": 4})
    losses: list = field(default_factory=lambda: PAPER_LOSSES["l1-normal"])
    batch_size: int = 8
    steps: int = 1000
    lr: float = 1e-4
    lr_discriminator: float = 1e-4
    lr_schedule: str = "constant"
    warmup_steps: int = 200
    checkpoint_every: int = 200
    validate_every: int = 0
    amp: bool = True
    device: str = "auto"
    seed: int = 0
    time_limit_minutes: float = 0.0
    init: str = ""
    trainable: tuple[str, ...] = ()
    compile: str = ""
    select: str = "color_psnr"
    teacher: str = ""
    gates_open_until: int = 0

    def __post_init__(self):
        if self.compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, got {self.compile!r}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}")
        if self.select not in SELECTS:
            raise ValueError(f"select must be one of {sorted(SELECTS)}, got {self.select!r}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be at least 1, got {self.batch_size}")
        if self.validate_every < 0:
            raise ValueError(f"validate_every must be 0 (each epoch's end) or a number of steps, got {self.validate_every}")
        if isinstance(self.trainable, str) or not all(isinstance(name, str) for name in self.trainable):
            raise ValueError(f"trainable must be a list of parameter names, got {self.trainable!r}")
        self.trainable = tuple(self.trainable)
        if isinstance(self.gates_open_until, bool) or not isinstance(self.gates_open_until, int) or \
                self.gates_open_until < 0:
            raise ValueError(f"gates_open_until must be a step (0: none), got {self.gates_open_until!r}")

    def lr_factor(self, step: int) -> float:
        """The learning-rate multiplier at ``step``."""
        if self.lr_schedule == "constant":
            return 1.0
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        progress = min(1.0, (step - self.warmup_steps) / max(1, self.steps - self.warmup_steps))
        return 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * progress))


def contexts(batch: SequenceBatch, outputs: torch.Tensor, warped: torch.Tensor, upscale: int,
             teacher: torch.Tensor | None = None) -> list[LossContext]:
    """The loss context of every frame of a batch of sequences (an x1 reconstruction's: with its inputs; with
    ``teacher``, the teacher's outputs of the same shape as ``outputs``, each frame's)."""
    lowres, target = batch.lowres, batch.highres
    recon = upscale == 1 and lowres.shape[2] == len(RECON_CHANNELS)
    result = []
    for t in range(batch.frames):
        flow = batch.flow_at(t)
        prev_target = None if flow is None else warp_by_flow(target[:, t - 1], upscale_flow(flow, upscale))
        result.append(LossContext(
            pred=outputs[:, t], target=target[:, t], prev_warped=warped[:, t] if t else None,
            lowres_up=F.interpolate(lowres[:, t, :len(LOWRES_CHANNELS)], scale_factor=upscale, mode="bilinear",
                                    align_corners=False),
            prev_target_warped=prev_target, recon_inputs=lowres[:, t] if recon else None,
            teacher=None if teacher is None else teacher[:, t]))
    return result


def weights_config(config):
    """A model config as its weights see it: a ReconNet's :data:`~isosr_net.reconnet.WEIGHTLESS_FIELDS` off."""
    return (replace(config, **dict.fromkeys(WEIGHTLESS_FIELDS, 0.0)) if isinstance(config, ReconNetConfig)
            else config)


def narrowed(state: dict[str, torch.Tensor], like: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A ReconNet's weights cut to a narrower one's (``like``, its state): each level's first channels. Every axis
    of ReconNet's tensors is a level's channels, the inputs', the outputs' or the kernel's taps, so each tensor's
    leading entries along every axis are that cut (:meth:`Trainer._init_from`)."""
    return {name: t[tuple(slice(0, n) for n in like[name].shape)] if name in like else t for name, t in state.items()}


def narrowed_config(weights, config):
    """A weights' config as a run of model ``config`` takes it: a ReconNet's widths cut to the run's where it is as
    wide or wider at every level (:func:`narrowed`), else as it is."""
    if (isinstance(config, ReconNetConfig) and isinstance(weights, ReconNetConfig) and weights.widths != config.widths
            and all(n <= w for n, w in zip(config.widths, weights.widths))):
        return replace(weights, widths=config.widths)
    return weights


def start_configs(config) -> list:
    """The weights' configs (:func:`weights_config`) a run of model ``config`` may start from (``init``), its own
    first: a blend ReconNet also from one over the rays, one with gates, a map, a variance blend or a pixel tail
    also from one without (:meth:`Trainer._init_from`; with the weights' widths cut first, :func:`narrowed_config`)."""
    config = weights_config(config)
    if not isinstance(config, ReconNetConfig):
        return [config]
    priors = [config.ao_prior] + (["rays"] if config.ao_prior == "blend" else [])
    return [replace(config, ao_prior=p, geometry_gate=g, blend_map=m, blend_variance=v, pixel_tail=t)
            for p in priors for g in dict.fromkeys((config.geometry_gate, False))
            for m in dict.fromkeys((config.blend_map, False)) for v in dict.fromkeys((config.blend_variance, False))
            for t in dict.fromkeys((config.pixel_tail, 0)) if p == "blend" or not (m or v)]


class Trainer:
    """Runs a :class:`TrainConfig`: data, model, optimizers, checkpoints, logs."""

    def __init__(self, config: TrainConfig):
        self.config = config
        self.distributed = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
        self.device = self._device()
        if self.distributed:
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo")
        self.rank = dist.get_rank() if self.distributed else 0
        self.world = dist.get_world_size() if self.distributed else 1
        if config.batch_size < self.world:
            raise ValueError(f"batch_size {config.batch_size} gives some of the {self.world} processes no share of a "
                             f"batch; give at least {self.world}")
        # This process's training: its steps and their wall seconds (validation and saving apart), and
        # the seconds of its first WARMUP_STEPS (a compiled step compiles there).
        self.timing = {"processes": self.world, "steps": 0, "train_s": 0.0, "warmup_s": None}
        torch.manual_seed(config.seed)
        self.out = Path(config.out)
        self.net = build_model(config.model).to(self.device)
        if self.device.type == "cuda":
            self.net = self.net.to(memory_format=torch.channels_last)  # faster convolutions with bf16
        self.upscale = self.net.config.upscale
        self.losses = build_losses(config.losses).to(self.device)
        self.teacher = self._teacher()
        self.adversarial = [m for m in self.losses if isinstance(m, AdversarialLoss)]
        unrolled = Unrolled(self.net)
        self.unrolled = DistributedDataParallel(unrolled) if self.distributed else unrolled
        if config.compile and self.adversarial:
            raise ValueError("compile: a discriminator's own step is not compiled; train adversarial losses eagerly")
        self._forward_losses = torch.compile(self._losses, mode=config.compile) if config.compile else self._losses
        self.optimizer = torch.optim.Adam(self._trained(), lr=config.lr)
        d_params = [p for m in self.adversarial for p in m.parameters()]
        self.d_optimizer = torch.optim.Adam(d_params, lr=config.lr_discriminator) if d_params else None
        self.train_set = SequenceDataset(config.data, "train").to(self.device)
        self.val_set = SequenceDataset(config.data, "val").to(self.device)
        if len(self.train_set) < config.batch_size:
            raise ValueError(f"{config.data} holds {len(self.train_set)} training crops, fewer than one batch "
                             f"({config.batch_size}); lower batch_size or render more data")
        data_upscale = self.train_set.config["upscale"]
        if data_upscale != self.upscale:
            raise ValueError(f"the data in {config.data} is for upscale {data_upscale}, the model upscales "
                             f"{self.upscale}")
        if isinstance(self.net, ReconNet) and self.train_set.limits != self.net.config.limits:
            raise ValueError(f"the data in {config.data} scales its sampling channels by {self.train_set.limits}, "
                             f"the model by {self.net.config.limits}: give both the same max_ao_rays and max_spp")
        self.step, self.best, self.best_step = 0, -math.inf, None
        self._resume()
        self._open_held_gates()

    def _open_held_gates(self) -> None:
        """Open the geometry gates where ``config.gates_open_until`` holds them past this run's start (ValueError: it
        asks a model without gates)."""
        if not self.config.gates_open_until:
            return
        if not (isinstance(self.net, ReconNet) and self.net.config.geometry_gate):
            raise ValueError("gates_open_until holds a gated ReconNet's geometry gates; this model has none "
                             "(give a ReconNet with geometry_gate, or 0)")
        if self.step < self.config.gates_open_until:
            self.net.open_gates()

    def _teacher(self) -> Unrolled | None:
        """The frozen teacher, unrolled, where a loss reads it (ValueError: a loss that reads it without a teacher, a
        teacher no loss reads, or one of another upscale or sampling limits than the model)."""
        reading = [m.name for m in self.losses if m.reads_teacher]
        if not self.config.teacher:
            if reading:
                raise ValueError(f"the {', '.join(reading)} loss compares with a teacher's output: give teacher, a "
                                 "model folder (the init, to hold a fine-tune to its start)")
            return None
        if not reading:
            raise ValueError(f"teacher {self.config.teacher}: no loss reads it (teacher_psnr_no_worse and a channel "
                             "loss against the teacher do); give one or no teacher")
        teacher, _ = load_pretrained(self.config.teacher, self.device)
        theirs, ours = ((c.upscale, getattr(c, "limits", None)) for c in (teacher.config, self.net.config))
        if theirs != ours:
            raise ValueError(f"teacher {self.config.teacher} upscales x{theirs[0]} with sampling limits {theirs[1]}; "
                             f"the model x{ours[0]} with {ours[1]}: give a teacher of the same")
        teacher.requires_grad_(False)
        if self.device.type == "cuda":
            teacher = teacher.to(memory_format=torch.channels_last)
        return Unrolled(teacher)

    @torch.no_grad()
    def _teacher_outputs(self, batch: SequenceBatch) -> torch.Tensor | None:
        """The teacher's outputs over ``batch``'s sequences (float32), or None without a teacher."""
        if self.teacher is None:
            return None
        with self._autocast():
            return self.teacher(batch.lowres, batch.flow)[0].float()

    def _device(self) -> torch.device:
        """The configured device; under torchrun on CUDA, this process's GPU."""
        want = self.config.device
        if want == "auto":
            want = "cuda" if torch.cuda.is_available() else "cpu"
        if want.startswith("cuda"):
            if not torch.cuda.is_available():
                raise RuntimeError("device cuda asked for, but torch sees no GPU")
            return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        return torch.device(want)

    def _resume(self) -> None:
        """Continue from `OUT/last` if a previous run left it (or `last.old`, mid-swap); else
        start from ``init``'s weights where given."""
        checkpoint = load_checkpoint(self.out / "last", self.device)
        if checkpoint is None:
            if self.config.init:
                self._init_from(self.config.init)
            return
        if checkpoint.model.config != self.net.config:
            raise ValueError(f"{checkpoint.folder} holds a model of another config ({checkpoint.config['model']}); "
                             f"train into a new folder or with the same model config")
        self.net.load_state_dict(checkpoint.model.state_dict())
        state = checkpoint.state
        self.optimizer.load_state_dict(state["optimizer"])
        if self.d_optimizer is not None and "d_optimizer" in state:
            self.d_optimizer.load_state_dict(state["d_optimizer"])
            for m, sd in zip(self.adversarial, state["discriminators"]):
                m.load_state_dict(sd)
        self.step, self.best, self.best_step = state["step"], state["best"], state.get("best_step")
        if state.get("select", "color_psnr") != self.config.select:  # best/ was picked by another score
            self.best, self.best_step = -math.inf, None
        if self.rank == 0:
            print(f"resuming from {checkpoint.folder} at step {self.step}")

    def _trained(self) -> list[torch.nn.Parameter]:
        """The parameters the optimizer steps: ``config.trainable``'s (ValueError: a name the model lacks), or all."""
        named = dict(self.net.named_parameters())
        missing = [name for name in self.config.trainable if name not in named]
        if missing:
            raise ValueError(f"trainable: the model has no parameter {', '.join(missing)} (it has {', '.join(named)})")
        return [named[name] for name in self.config.trainable] if self.config.trainable else list(named.values())

    def _init_from(self, folder: str) -> None:
        """Load the weights of the model folder ``folder`` (ValueError: a model of a config it cannot start
        from). A ReconNet that blends its AO with the rays' (``ao_prior="blend"``) starts from one that
        corrects them (``"rays"``), one with a ``geometry_gate``, a ``blend_map``, ``blend_variance`` or a
        ``pixel_tail`` from one without: the same weights, its blend at :data:`~isosr_net.reconnet.BLEND_RAYS_INIT`
        rays, its gates, map and pixel tail at their start; with any ``blend_beyond`` (it has no weights). A
        ReconNet narrower at some levels starts from one wider there: each level's first channels (:func:`narrowed`)."""
        model, _ = load_pretrained(folder, self.device)
        config, weights = weights_config(self.net.config), weights_config(model.config)
        cut = narrowed_config(weights, config)
        if cut not in start_configs(self.net.config):
            raise ValueError(f"init {folder} holds a model of another config ({model.config}); the run trains "
                             f"{self.net.config}")
        state = model.state_dict() if cut == weights else narrowed(model.state_dict(), self.net.state_dict())
        self.net.load_state_dict(state, strict=cut == config)
        if self.rank == 0:
            print(f"fine-tuning {folder}")

    def _batches(self, dataset: SequenceDataset, shuffle: bool, epoch: int, skip: int = 0):
        """This process's share of each batch, indexed straight from the device-resident crops.

        ``skip`` batches of the epoch are passed over (a run resumed mid-epoch).
        """
        order = (torch.randperm(len(dataset), generator=torch.Generator().manual_seed(self.config.seed + epoch))
                 if shuffle else torch.arange(len(dataset)))
        size = self.config.batch_size
        stop = len(order) - len(order) % size if shuffle else len(order)
        for start in range(skip * size, stop, size):
            index = order[start:start + size][self.rank::self.world].to(self.device)
            if len(index):
                yield dataset.batch(index)

    def _autocast(self):
        return torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.config.amp and self.device.type == "cuda")

    def train_step(self, batch: SequenceBatch) -> dict:
        """One optimizer step on a batch of sequences; returns the loss terms."""
        loss, logs, ctxs = self._forward_losses(batch)
        for group in self.optimizer.param_groups:
            group["lr"] = self.config.lr * self.config.lr_factor(self.step)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.step < self.config.gates_open_until:  # held open: Adam leaves a parameter without a gradient as it is
            getattr(self.net, GATE_PARAMETER).grad = None
        self.optimizer.step()
        if self.d_optimizer is not None:
            with self._autocast():
                d_loss = sum(m.discriminator_loss(ctx) for m in self.adversarial for ctx in ctxs) / len(ctxs)
            self.d_optimizer.zero_grad(set_to_none=True)
            d_loss.backward()
            self._average_gradients([p for m in self.adversarial for p in m.parameters()])
            self.d_optimizer.step()
            logs["discriminator"] = d_loss.detach()
        logs["total"] = loss.detach()
        return dict(zip(logs, torch.stack([v.float() for v in logs.values()]).tolist()))  # the step's one read

    def _losses(self, batch: SequenceBatch) -> tuple[torch.Tensor, dict, list[LossContext]]:
        """A step's forward: the loss, each term's mean over the frames, and the frames' loss contexts."""
        with self._autocast():
            outputs, warped = self.unrolled(batch.lowres, batch.flow)
            ctxs = contexts(batch, outputs.float(), warped.float(), self.upscale, self._teacher_outputs(batch))
            terms = [total_loss(self.losses, ctx) for ctx in ctxs]
        logs = {k: sum(t[1][k] for t in terms) / len(terms) for k in terms[0][1]}
        return sum(t[0] for t in terms) / len(terms), logs, ctxs

    def _average_gradients(self, params: list) -> None:
        """All-reduce the discriminators' gradients (they are not wrapped in DDP)."""
        if not self.distributed:
            return
        for p in params:
            if p.grad is not None:
                dist.all_reduce(p.grad)
                p.grad /= self.world

    @torch.no_grad()
    def validate(self) -> dict:
        """Mean loss and scores over the validation crops (each process over its share)."""
        self.net.eval()
        sums, count = {}, 0
        for batch in self._batches(self.val_set, shuffle=False, epoch=0):
            with self._autocast():
                outputs, warped = Unrolled(self.net)(batch.lowres, batch.flow)
            outputs, warped = outputs.float(), warped.float()
            ctxs = contexts(batch, outputs, warped, self.upscale, self._teacher_outputs(batch))
            frame_loss = sum(float(total_loss(self.losses, ctx)[0]) for ctx in ctxs) / len(ctxs)
            b, t = outputs.shape[:2]
            scores = frame_scores(outputs.flatten(0, 1), batch.highres.flatten(0, 1))
            sums["loss"] = sums.get("loss", 0.0) + frame_loss * b
            for k, v in scores.items():
                sums[k] = sums.get(k, 0.0) + float(torch.nanmean(v.float())) * b
            count += b
        self.net.train()
        names = sorted(sums)
        totals = torch.tensor([count] + [sums[k] for k in names], dtype=torch.float64, device=self.device)
        if self.distributed:
            dist.all_reduce(totals)
        return {k: float(v / totals[0]) for k, v in zip(names, totals[1:])}

    def _validated(self, metrics: dict, writer) -> None:
        """Log the validation ``metrics`` of this step; a better score (``select``) than the best so far is the new
        `best/`."""
        if writer:
            for k, v in metrics.items():
                writer.add_scalar(f"val/{k}", v, self.step)
        score = SELECTS[self.config.select] * metrics[self.config.select]
        if score > self.best:
            self.best, self.best_step = score, self.step
            self.save("best", metrics)
        if self.rank == 0:
            tqdm.write(f"step {self.step}: " + ", ".join(f"{k} {v:.4f}" for k, v in metrics.items()))

    @property
    def best_score(self) -> float:
        """``best/``'s validation score (``select``), as the metrics give it."""
        return SELECTS[self.config.select] * self.best

    def save(self, name: str, metrics: dict | None = None) -> None:
        """Write a checkpoint folder `OUT/name` atomically; `last` with the state to resume from."""
        if self.rank != 0:
            return
        state = None
        if name == "last":
            state = {"optimizer": self.optimizer.state_dict(), "step": self.step, "best": self.best,
                     "best_step": self.best_step, "select": self.config.select}
            if self.d_optimizer is not None:
                state["d_optimizer"] = self.d_optimizer.state_dict()
                state["discriminators"] = [m.state_dict() for m in self.adversarial]
        save_checkpoint(self.net, self.out / name, {"training": asdict(self.config), "step": self.step,
                                                    "validation": metrics or {}, "timing": self.timing}, state)

    def run(self, progress: bool = True) -> dict:
        """Train to `steps`; returns the last validation metrics."""
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(self.out / "tb") if self.rank == 0 else None
        steps_per_epoch = max(1, len(self.train_set) // max(1, self.config.batch_size))
        metrics = {}
        bar = tqdm(total=self.config.steps, initial=self.step, desc="train", disable=not progress or self.rank != 0)
        deadline = time.monotonic() + 60 * self.config.time_limit_minutes if self.config.time_limit_minutes else math.inf
        if self.step == 0 and self.config.init:
            self._validated(self.validate(), writer)  # the starting model on this data: best/ beats it or is it
        first_step = self.step
        validate_every = self.config.validate_every or steps_per_epoch
        while self.step < self.config.steps and time.monotonic() < deadline:
            epoch = self.step // steps_per_epoch
            started = time.monotonic()  # each step's loss read (float) syncs: the loop's wall time is its steps'
            due = False  # a validation: the interval's, the last step's or the deadline's
            for batch in self._batches(self.train_set, shuffle=True, epoch=epoch, skip=self.step % steps_per_epoch):
                logs = self.train_step(batch)
                self.step += 1
                if self.step - first_step == WARMUP_STEPS:
                    self.timing["warmup_s"] = self.timing["train_s"] + time.monotonic() - started
                bar.update(1)
                bar.set_postfix(loss=f"{logs['total']:.4f}")
                if writer:
                    for k, v in logs.items():
                        writer.add_scalar(f"train/{k}", v, self.step)
                if self.step % self.config.checkpoint_every == 0:
                    saving = time.monotonic()
                    self.save("last")
                    started += time.monotonic() - saving  # the timing leaves saving out
                due = (self.step >= self.config.steps or self.step % validate_every == 0
                       or time.monotonic() > deadline)
                if due or self.step % steps_per_epoch == 0:
                    break
            self.timing["train_s"] += time.monotonic() - started
            self.timing["steps"] = self.step - first_step
            if not due:  # the epoch's end between validations
                continue
            metrics = self.validate()
            self._validated(metrics, writer)
            self.save("last", metrics)
        bar.close()
        if self.rank == 0 and self.config.init and self.best_step == 0 and self.step > 0:
            tqdm.write(f"best/ is the starting model ({self.config.init}): no step beat its validation "
                       f"{self.config.select} {self.best_score:.4f}; last/ holds step {self.step}'s weights")
        if writer:
            writer.close()
        if self.distributed:  # every process past rank 0's saving; DDP's reducer lets go of the group
            dist.barrier()
            self.unrolled = self.unrolled.module
            dist.destroy_process_group()
        return metrics
