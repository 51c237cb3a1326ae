"""`isosr serve`: the remote visualization and frame upscaling service (FastAPI on uvicorn).

Every option can also be set by the environment: ISOSR_ and the option's name in capitals
(ISOSR_TOKEN, ISOSR_DEVICE, ISOSR_MAX_FPS, ...); a flag wins over the environment.
"""

from __future__ import annotations

import argparse
import logging

from isosr_server.core.config import Settings, add_arguments


def add_parser(subparsers) -> None:
    """Register ``serve`` and its options (from `Settings`: one ``--limit-name`` flag per `Limits` field)."""
    p = subparsers.add_parser("serve", help="serve view sessions and frame upscaling over HTTP and WebSockets",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from isosr_server.app import create_app, uvicorn_options

    settings = Settings.from_args(args)
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level,
                access_log=settings.log_level == "debug", **uvicorn_options(settings.limits))
    return 0
