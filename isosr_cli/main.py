"""`isosr`: the one command line of the project."""

from __future__ import annotations

import argparse
import sys

import warp as wp

from isosr_render.volume import VolumeError


# The subcommands that need the `server` extra (their flags come from its settings and protocol).
SERVER_COMMANDS = ("serve", "client")


def build_parser() -> argparse.ArgumentParser:
    """The parser with every subcommand; without the `server` extra, ``serve`` and ``client`` only
    say how to install it (rendering and training need none of it)."""
    from isosr_cli import bench_cmd, demo_cmd, kernels_cmd, mesh_cmd, net_cmds, render_cmd
    from isosr_render.formats import help_text

    parser = argparse.ArgumentParser(prog="isosr", description="Isosurface rendering with learned super-resolution.",
                                     epilog=f"Volume files and folders it opens: {help_text()}.")
    subparsers = parser.add_subparsers(dest="command", required=True)
    render_cmd.add_parser(subparsers)
    mesh_cmd.add_parser(subparsers)
    net_cmds.add_parsers(subparsers)
    demo_cmd.add_parser(subparsers)
    bench_cmd.add_parser(subparsers)
    kernels_cmd.add_parser(subparsers)
    try:
        from isosr_cli import client_cmd, serve_cmd
    except ModuleNotFoundError as e:
        for name in SERVER_COMMANDS:
            add_missing_extra(subparsers, name, e.name)
    else:
        serve_cmd.add_parser(subparsers)
        client_cmd.add_parser(subparsers)
    return parser


def add_missing_extra(subparsers, name: str, module: str) -> None:
    """Register ``name`` as a command that fails with how to install the `server` extra."""
    def missing(args) -> int:
        raise RuntimeError(f"needs the server extra (pip install 'isosr[server]'): module {module!r} is not installed")

    p = subparsers.add_parser(name, help=f"(needs the server extra: module {module!r} is missing)",
                              prefix_chars="\0", add_help=False)  # no options: every argument lands in `rest`
    p.add_argument("rest", nargs="*")
    p.set_defaults(func=missing)


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
