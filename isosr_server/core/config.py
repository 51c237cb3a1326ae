"""The service's settings: one typed, frozen object, read once from flags and the environment.

    settings = Settings.from_env()        # ISOSR_PORT, ISOSR_TOKEN, ISOSR_MAX_FPS, ... over the defaults
    settings = Settings.from_args(args)   # `isosr serve`'s flags over the environment

Every setting is an option (:func:`options`): a field of `Settings` or of its `Limits`, with the
flag ``--name-with-dashes`` (:func:`add_arguments` makes them) and the environment variable
``ISOSR_NAME_IN_CAPITALS``; a flag wins over the environment, the environment over the default.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import msgspec

from isosr_net.inference import PRECISIONS, default_precision
from isosr_net.reconstructor import DEFAULT_RECON_MODEL
from isosr_net.upscaler import DEFAULT_MODEL
from isosr_render.catalog import shared_volumes_dir
from isosr_server.protocol import Limits

ENV_PREFIX = "ISOSR_"
TOKEN_ENV = ENV_PREFIX + "TOKEN"
LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")
LOG_LEVELS = ("debug", "info", "warning", "error")
MIN_TOKEN_CHARS = 8


def default_volumes_dir() -> Path | None:
    """The shared volumes folder (``../shared/volumes`` or ``$ISOSR_SHARED_VOLUMES``) if it exists."""
    root = shared_volumes_dir()
    return root if root.is_dir() else None


def _option(default: Any, help: str, parse: Callable[[str], Any] = str, choices: tuple[str, ...] | None = None):
    """A settings field that is also an option: its help, how to parse its text, its choices."""
    return field(default=default, metadata={"help": help, "parse": parse, "choices": choices})


@dataclass(frozen=True)
class Settings:
    """Everything `isosr serve` configures; validated on construction.

    Attributes:
        host, port: where to listen; any host but loopback requires a token.
        volumes: the volumes folder (None: procedural volumes only; `from_env` and `from_args`
            fill in the shared folder where it exists).
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        precision: the networks' ``fp32``, ``bf16`` or ``fp16``; None: `default_precision`
            (`resolved_precision` says which).
        model, recon_model: the upscaling and the reconstruction model folders.
        token: the shared secret clients must send (None: no check, loopback only).
        limits: the protocol limits.
        target_fps: the frame rate the ``auto`` mode's budget aims at.
        slice_ms: device time a slice of a heavy view frame aims at (others' frames interleave
            between slices); None: 8 ms on CUDA, 100 ms on CPUs.
        max_volume_bytes: the most bytes a volume's voxels take on the device; a larger volume
            renders sparse (the bricks each iso needs, paged in); None: half the free GPU memory
            at load, no limit on CPUs.
        log_level: ``debug``, ``info``, ``warning`` or ``error``.
    """

    host: str = _option("127.0.0.1", "address to bind; any but loopback requires a token")
    port: int = _option(8000, "port to bind", int)
    volumes: Path | None = _option(None, "folder of volumes offered by name (default: ../shared/volumes if "
                                         "present; procedural proc: volumes always)", Path)
    device: str = _option("cpu", "cpu, cuda or cuda:N")
    precision: str | None = _option(None, "the networks' precision (default: fp16 on CUDA devices, fp32 on CPUs)",
                                    choices=tuple(PRECISIONS))
    model: Path = _option(DEFAULT_MODEL, "upscaling model folder", Path)
    recon_model: Path = _option(DEFAULT_RECON_MODEL, "reconstruction model folder (reconstruct mode)", Path)
    token: str | None = _option(None, f"shared secret clients must send, at least {MIN_TOKEN_CHARS} characters "
                                      "(default: none, loopback only)")
    limits: Limits = field(default_factory=Limits)
    target_fps: float = _option(30.0, "frame rate the auto mode's budget aims at", float)
    slice_ms: float | None = _option(None, "device time a slice of a heavy view frame aims at, other sessions' "
                                           "frames interleaving between slices (default: 8 on CUDA, 100 on CPUs)",
                                     float)
    max_volume_bytes: int | None = _option(None, "bytes a volume's voxels may take on the device; larger volumes "
                                                 "render sparse, paging in the bricks each iso needs (default: half "
                                                 "the free GPU memory, no limit on CPUs)", int)
    log_level: str = _option("info", "log level", choices=LOG_LEVELS)

    def __post_init__(self):
        if self.host not in LOOPBACK_HOSTS and not self.token:
            raise ValueError(f"binding {self.host} exposes the server beyond this machine: give --token "
                             f"(or set {TOKEN_ENV})")
        if self.token is not None and len(self.token) < MIN_TOKEN_CHARS:
            raise ValueError(f"the token must have at least {MIN_TOKEN_CHARS} characters")
        if self.precision is not None and self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.log_level not in LOG_LEVELS:
            raise ValueError(f"log_level must be one of {', '.join(LOG_LEVELS)}, got {self.log_level!r}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must lie in [0, 65535], got {self.port}")
        if self.max_volume_bytes is not None and self.max_volume_bytes <= 0:
            raise ValueError(f"max_volume_bytes must be a positive number of bytes, got {self.max_volume_bytes}")
        for name in ("target_fps", "slice_ms"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")

    @property
    def resolved_precision(self) -> str:
        """The networks' precision: the given one, else `default_precision` of the device."""
        return self.precision or default_precision(self.device)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **given: Any) -> Settings:
        """Settings from ``ISOSR_*`` variables of ``environ`` (default: the process's), with the
        ``given`` values that are not None winning; empty variables count as unset.

        Raises:
            ValueError: a variable's text does not parse, or the settings are invalid.
        """
        unknown = set(given) - {o.name for o in options()}
        if unknown:
            raise TypeError(f"unknown settings: {', '.join(sorted(unknown))}")
        environ = os.environ if environ is None else environ
        values = {}
        for o in options():
            value, text = given.get(o.name), environ.get(o.env)
            if value is None and text:
                try:
                    value = o.parse(text)
                except ValueError:
                    raise ValueError(f"{o.env}={text!r} is not a valid {o.name}") from None
            if value is not None:
                values[o.name] = value
        limits = Limits(**{o.name: values.pop(o.name) for o in options() if o.limit and o.name in values})
        values.setdefault("volumes", default_volumes_dir())
        return cls(**values, limits=limits)

    @classmethod
    def from_args(cls, args: argparse.Namespace, environ: Mapping[str, str] | None = None) -> Settings:
        """Settings from the flags of :func:`add_arguments` (None: not given) over ``environ``."""
        return cls.from_env(environ, **{o.name: getattr(args, o.name) for o in options()})


@dataclass(frozen=True)
class Option:
    """One setting as a flag and an environment variable."""

    name: str
    default: Any
    help: str
    parse: Callable[[str], Any]
    choices: tuple[str, ...] | None
    limit: bool  # a field of `Limits`

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.name.upper()


def options() -> list[Option]:
    """Every setting's option: the fields of `Settings`, then those of `Limits`."""
    own = [Option(f.name, f.default, f.metadata["help"], f.metadata["parse"], f.metadata["choices"], False)
           for f in fields(Settings) if f.metadata]
    limits = [Option(f.name, f.default, f.name.replace("_", " "), type(f.default), None, True)
              for f in msgspec.structs.fields(Limits)]
    return own + limits


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One flag per option (the limits in their own group); each help says its default once."""
    limits = parser.add_argument_group("limits")
    for o in options():
        help = o.help if "(default:" in o.help else f"{o.help} (default: {o.default})"
        (limits if o.limit else parser).add_argument(o.flag, type=o.parse, choices=o.choices, help=help)
