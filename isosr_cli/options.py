"""Option types the commands share."""

from __future__ import annotations

import argparse

from isosr_render.clip import CAP_MODES, Clip


def numbers(count: int):
    """An argparse type: ``count`` comma-separated numbers."""
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) != count:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}")
        return values
    return parse


def add_clip_options(p: argparse.ArgumentParser) -> None:
    """--clip-plane, --crop-box and --cap (:func:`clip_of` reads them)."""
    cut = p.add_argument_group("clipping (world units: the volume's box centred at 0, its longest side 1)")
    cut.add_argument("--clip-plane", type=numbers(6), action="append", default=[], metavar="X,Y,Z,NX,NY,NZ",
                     help="a clip plane through X,Y,Z keeping the side its normal NX,NY,NZ points into (repeatable; "
                          "values starting with '-' go as --clip-plane=-0.1,...)")
    cut.add_argument("--crop-box", type=numbers(6), metavar="X0,Y0,Z0,X1,Y1,Z1",
                     help="keep only this box (negative values: --crop-box=-0.5,...)")
    cut.add_argument("--cap", choices=CAP_MODES, default="none",
                     help="close the cut where it cuts the solid, the values at or above the iso ('above', as bone "
                          "in a CT) or below it (as inside a signed distance); renders show the cut face in grey by "
                          "the volume's value")


def clip_of(args: argparse.Namespace) -> Clip:
    """The clip of --clip-plane, --crop-box and --cap."""
    box = None if args.crop_box is None else (args.crop_box[:3], args.crop_box[3:])
    return Clip(tuple((p[:3], p[3:]) for p in args.clip_plane), box, args.cap)
