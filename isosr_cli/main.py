"""`isosr`: the one command line of the project."""

from __future__ import annotations

import argparse
import sys

import warp as wp

from isosr_render.volume import VolumeError


def build_parser() -> argparse.ArgumentParser:
    """The parser with every subcommand."""
    from isosr_cli import bench_cmd, client_cmd, demo_cmd, net_cmds, render_cmd, serve_cmd

    parser = argparse.ArgumentParser(prog="isosr", description="Isosurface rendering with learned super-resolution.")
    subparsers = parser.add_subparsers(dest="command", required=True)
    render_cmd.add_parser(subparsers)
    net_cmds.add_parsers(subparsers)
    demo_cmd.add_parser(subparsers)
    bench_cmd.add_parser(subparsers)
    serve_cmd.add_parser(subparsers)
    client_cmd.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run a subcommand; bad input ends with a one-line error and exit code 2."""
    args = build_parser().parse_args(argv)
    log_level, wp.config.log_level = wp.config.log_level, wp.LOG_WARNING  # no Warp banner on every command
    try:
        return args.func(args)
    except (VolumeError, ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"isosr {args.command}: error: {e}", file=sys.stderr)
        return 2
    finally:
        wp.config.log_level = log_level


if __name__ == "__main__":
    sys.exit(main())
