"""`isosr serve`: the remote visualization and frame upscaling service (FastAPI on uvicorn)."""

from __future__ import annotations

import argparse
import logging
import os
from msgspec.structs import fields
from pathlib import Path

from isosr_net.reconstructor import DEFAULT_RECON_MODEL
from isosr_net.upscaler import DEFAULT_MODEL, PRECISIONS
from isosr_server.protocol import Limits

TOKEN_ENV = "ISOSR_TOKEN"


def add_parser(subparsers) -> None:
    """Register ``serve`` and its options (one ``--limit-name`` flag per `Limits` field)."""
    p = subparsers.add_parser("serve", help="serve view sessions and frame upscaling over HTTP and WebSockets",
                              description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--host", default="127.0.0.1", help="address to bind; any but loopback requires --token")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--volumes", type=Path, help="folder of volumes offered by name (default: ../shared/volumes "
                                               "if present; procedural proc: volumes always)")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="model folder")
    p.add_argument("--recon-model", type=Path, default=DEFAULT_RECON_MODEL,
                   help="reconstruction model folder (reconstruct mode)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--precision", default="fp32", choices=sorted(PRECISIONS), help="the network's precision")
    p.add_argument("--token", help=f"shared secret clients must send (default: ${TOKEN_ENV})")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    limits = p.add_argument_group("limits")
    for f in fields(Limits):
        limits.add_argument("--" + f.name.replace("_", "-"), type=type(f.default), default=f.default,
                            help=f.name.replace("_", " "))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from isosr_server.app import ServerConfig, create_app, default_volumes_dir, uvicorn_options
    from isosr_server.engine import EngineConfig

    limits = Limits(**{f.name: getattr(args, f.name) for f in fields(Limits)})
    config = ServerConfig(host=args.host, volumes=args.volumes or default_volumes_dir(),
                          engine=EngineConfig(args.model, args.device, args.precision, args.recon_model),
                          token=args.token or os.environ.get(TOKEN_ENV) or None, limits=limits)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(create_app(config), host=args.host, port=args.port, log_level=args.log_level,
                access_log=args.log_level == "debug", **uvicorn_options(limits))
    return 0
