"""`isosr datagen | train | eval | upscale`: the network's stages on the command line."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from isosr_render.atomic import atomic_write
from isosr_render.buffers import load_sequence, save_sequence
from isosr_cli.images import write_png
from isosr_net.configs import load_config


def add_parsers(subparsers) -> None:
    """Register the network's subcommands."""
    p = subparsers.add_parser("datagen", help="render training / evaluation data (shards + manifest)")
    p.add_argument("config", help="JSON file of DatagenConfig fields (see isosr_net/datagen.py)")
    p.add_argument("-o", "--out", required=True, help="output folder; an existing one is resumed")
    p.add_argument("--device", help="override the config's device")
    p.add_argument("--sequences", type=int, help="override sequences per volume")
    p.add_argument("--upscale", type=int, help="override the upscale factor")
    p.add_argument("--lowres-size", type=int, help="override the low-res render side")
    p.set_defaults(func=run_datagen)

    p = subparsers.add_parser("train", help="train a network from a JSON config")
    p.add_argument("config", help="JSON file of TrainConfig fields (see isosr_net/train.py)")
    p.add_argument("--data", help="override the data folder")
    p.add_argument("--out", help="override the run folder")
    p.add_argument("--steps", type=int, help="override the number of steps")
    p.add_argument("--seed", type=int, help="override the seed (initialization and data order)")
    p.add_argument("--batch-size", type=int, help="override the sequences per step (over all processes)")
    p.add_argument("--lr", type=float, help="override the peak learning rate")
    p.add_argument("--device", help="override the device")
    p.add_argument("--time-limit-minutes", type=float, help="stop, validated and saved, after this long")
    p.add_argument("--validate-every", type=int, help="override the steps between validations (0: each epoch's end)")
    p.add_argument("--upscale", type=int, help="override the model's upscale factor")
    p.add_argument("--compile", help="override the torch.compile mode of a step (default, "
                                     "max-autotune-no-cudagraphs; '' none)")
    p.set_defaults(func=run_train)

    p = subparsers.add_parser("eval", help="score the network against nearest/bilinear/bicubic per volume")
    p.add_argument("--model", help="model folder (default: the shipped model)")
    p.add_argument("--data", required=True, help="datagen folder")
    p.add_argument("--split", default="val")
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32")
    p.add_argument("--json", help="also write the rows and gains to this JSON file")
    p.add_argument("--oracles", action="store_true",
                   help="also score two oracles: bilinear with the true AO, the true geometry without AO")
    p.set_defaults(func=run_eval)

    p = subparsers.add_parser("upscale", help="upscale a low-res sequence file")
    p.add_argument("input", help="IN.npz: mask (T,H,W), normal (T,H,W,3), depth (T,H,W), flow (T,H,W,2)")
    p.add_argument("-o", "--output", required=True, help="OUT.npz: high-res mask, normal, depth, ao (T,...)")
    p.add_argument("--model", help="model folder (default: the shipped model)")
    p.add_argument("--png", help="also write the shaded frames into this folder")
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32")
    p.add_argument("--tile", type=int, help="low-res tile side for frames that do not fit whole")
    p.set_defaults(func=run_upscale)


def run_datagen(args: argparse.Namespace) -> int:
    from isosr_net.datagen import DatagenConfig, generate

    config = load_config(DatagenConfig, args.config, device=args.device, sequences=args.sequences,
                         upscale=args.upscale, lowres_size=args.lowres_size)
    start = time.perf_counter()
    manifest = generate(config, args.out)
    crops = {}
    for shard in manifest["shards"]:
        crops[shard["split"]] = crops.get(shard["split"], 0) + shard["crops"]
    print(f"{len(manifest['shards'])} sequences, crops per split {crops}, in {time.perf_counter() - start:.1f} s "
          f"-> {args.out}")
    return 0


def run_train(args: argparse.Namespace) -> int:
    from isosr_net.train import Trainer, TrainConfig

    config = load_config(TrainConfig, args.config, data=args.data, out=args.out, steps=args.steps, seed=args.seed,
                         batch_size=args.batch_size, lr=args.lr, device=args.device,
                         time_limit_minutes=args.time_limit_minutes, validate_every=args.validate_every,
                         compile=args.compile)
    if args.upscale is not None:
        config = dataclasses.replace(config, model={**config.model, "upscale": args.upscale})
    trainer = Trainer(config)
    metrics = trainer.run()
    best = {"step": trainer.best_step, config.select: trainer.best_score}
    print(json.dumps({"step_metrics": metrics, "best": best, "timing": trainer.timing}, indent=1))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from isosr_net.evaluate import SCORES, evaluate, gains
    from isosr_net.model import load_pretrained
    from isosr_net.inference import PRECISIONS
    from isosr_net.upscaler import DEFAULT_MODEL

    net, _ = load_pretrained(args.model or DEFAULT_MODEL, args.device)
    rows = evaluate(net, args.data, args.split, args.device, PRECISIONS[args.precision], oracles=args.oracles)
    print("| volume | method | " + " | ".join(SCORES) + " |")
    print("|---|---|" + "---|" * len(SCORES))
    for r in rows:
        print(f"| {r['volume']} | {r['method']} | " + " | ".join(f"{r[k]:.4g}" for k in SCORES) + " |")
    gain = gains(rows)
    for volume, g in gain.items():
        print(f"{volume}: color PSNR gain {g['vs_bilinear']:+.2f} dB over bilinear, "
              f"{g['vs_best_baseline']:+.2f} dB over the best baseline")
    if args.json:
        record = {"command": " ".join(sys.orig_argv), "model": str(args.model or DEFAULT_MODEL), "data": args.data,
                  "split": args.split, "precision": args.precision, "rows": rows, "gains": gain}
        atomic_write(args.json, lambda f: f.write(json.dumps(record, indent=1).encode()))
    return 0


def run_upscale(args: argparse.Namespace) -> int:
    from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
    from isosr_render.images import to_uint8
    from isosr_render.shading import shade

    frames = load_sequence(args.input)
    upscaler = Upscaler(args.model or DEFAULT_MODEL, args.device, args.precision, args.tile)
    start = time.perf_counter()
    outputs = []
    for t, frame in enumerate(frames):
        if t == 0:
            frame.flow = None  # a sequence starts without a previous frame
        outputs.append(upscaler.upscale(frame))
    elapsed = time.perf_counter() - start
    save_sequence(outputs, args.output)
    if args.png:
        for t, out in enumerate(outputs):
            write_png(Path(args.png) / f"frame_{t:04d}.png", to_uint8(shade(out.mask, out.normal, out.ao)))
    h, w = outputs[0].mask.shape
    print(f"upscaled {len(frames)} frames to {w}x{h} on {args.device} in {elapsed:.2f} s "
          f"({elapsed / len(frames) * 1e3:.1f} ms per frame) -> {args.output}")
    return 0

