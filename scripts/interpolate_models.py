"""Weights between two reconstruction models of one architecture (a fine-tune and its start): ``(1 - t) * A + t * B``
for each weight, written as a model folder (WiSE-FT's interpolation: part of a fine-tune's gain, part of its start's
strength where the fine-tune lost).

    python scripts/interpolate_models.py isosr_net/recon_model isosr_net/recon_model_v6 0.3 OUT

The measured study: docs/measurements.md, "Half the sequences at 4 rays a pixel, and weights between".
"""

import argparse
import math

from isosr_net.model import load_pretrained, save_pretrained


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("start", help="model folder A (t = 0)")
    parser.add_argument("end", help="model folder B (t = 1), A's architecture")
    parser.add_argument("t", type=float, help="where between: 0 is A, 1 is B")
    parser.add_argument("out", help="the new model folder")
    args = parser.parse_args(argv)
    if not math.isfinite(args.t):
        parser.error(f"t must be a finite number (0: start, 1: end), got {args.t}")
    a, b = load_pretrained(args.start)[0], load_pretrained(args.end)[0]
    if a.config != b.config:  # the configs as built, defaults filled in
        raise SystemExit(f"{args.start} and {args.end} differ in architecture: {a.config} != {b.config}")
    ends = b.state_dict()
    a.load_state_dict({name: w.lerp(ends[name], args.t) if w.is_floating_point() else w
                       for name, w in a.state_dict().items()})
    save_pretrained(a, args.out, {"interpolated": {"start": args.start, "end": args.end, "t": args.t}})


if __name__ == "__main__":
    main()
