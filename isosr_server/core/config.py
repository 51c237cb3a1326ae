"""The service's settings: one typed, frozen object, read once from flags and the environment.

    settings = Settings.from_env()        # ISOSR_PORT, ISOSR_TOKEN, ISOSR_MAX_FPS, ... over the defaults
    settings = Settings.from_args(args)   # `isosr serve`'s flags over the environment

Every setting is an option (:func:`options`): a field of `Settings` or of its `Limits`, with the
flag ``--name-with-dashes`` (:func:`add_arguments` makes them) and the environment variable
``ISOSR_NAME_IN_CAPITALS``; a flag wins over the environment, the environment over the default.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import ssl
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import msgspec

from isosr_net.inference import PRECISIONS, default_precision
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL
from isosr_net.upscaler import DEFAULT_MODEL
from isosr_render.catalog import shared_volumes_dir
from isosr_server.protocol import Limits

ENV_PREFIX = "ISOSR_"
TOKEN_ENV = ENV_PREFIX + "TOKEN"
LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")
LOG_LEVELS = ("debug", "info", "warning", "error")
MIN_TOKEN_CHARS = 8
# A thread that lets go of the interpreter lock in a C call (a video encoder's x264, a GPU sync) waits up to the switch
# interval to take it back while a Python thread runs (the device thread, the event loop): beside one busy thread a
# 1080p h264 frame took 49 ms at Python's 5 ms, 26 at 1 ms, 20 alone (bench_switch_1080p_cpu.json; 0.5 ms no better).
SWITCH_INTERVAL_MS = 1.0
MAX_SWITCH_INTERVAL_MS = 1000.0
SWITCH_TEXTS = {"1": True, "true": True, "yes": True, "on": True, "0": False, "false": False, "no": False, "off": False}


def parse_switch(text: str) -> bool:
    """An on/off setting's text (``1``/``true``/``yes``/``on`` or ``0``/``false``/``no``/``off``)."""
    try:
        return SWITCH_TEXTS[text.strip().lower()]
    except KeyError:
        raise ValueError(f"expected one of {', '.join(SWITCH_TEXTS)}, got {text!r}") from None


def default_volumes_dir() -> Path | None:
    """The shared volumes folder (``../shared/volumes`` or ``$ISOSR_SHARED_VOLUMES``) if it exists."""
    root = shared_volumes_dir()
    return root if root.is_dir() else None


def _option(default: Any, help: str, parse: Callable[[str], Any] = str, choices: tuple[str, ...] | None = None):
    """A settings field that is also an option: its help, how to parse its text, its choices."""
    return field(default=default, metadata={"help": help, "parse": parse, "choices": choices})


def configure_process(settings: Settings) -> None:
    """What a server's process takes from its settings: its logs at ``settings.log_level``, to stderr where nothing
    handles them yet, and isosr's loggers at that level where something does (a Ray Serve replica's worker, whose
    stderr is its log file); its interpreter lock's switch interval."""
    level = settings.log_level.upper()
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("isosr").setLevel(level)
    sys.setswitchinterval(settings.switch_interval_ms / 1e3)


def check_min_fps(min_fps: float, target_fps: float) -> float:
    """``min_fps`` as the auto mode's least frame rate, which lies in (0, ``target_fps``] (ValueError otherwise)."""
    if not 0 < min_fps <= target_fps:
        raise ValueError(f"min_fps must lie in (0, target_fps = {target_fps:g}], got {min_fps!r}")
    return float(min_fps)


def check_gpu_share(share: float) -> float:
    """``share`` as a server's part of its GPU, which lies in (0, 1] (ValueError otherwise)."""
    if not 0 < share <= 1:
        raise ValueError(f"gpu_share must lie in (0, 1], got {share!r}")
    return float(share)


@dataclass(frozen=True)
class Settings:
    """Everything `isosr serve` configures; validated on construction.

    Attributes:
        host, port: where to listen; any host but loopback requires a token, and TLS unless
            ``insecure`` (`check_exposure`).
        volumes: the volumes folder (None: procedural volumes only; `from_env` and `from_args`
            fill in the shared folder where it exists).
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        precision: the networks' ``fp32``, ``bf16`` or ``fp16``; None: `default_precision`
            (`resolved_precision` says which).
        model, recon_model: the upscaling and the reconstruction model folders.
        recon_x2_model: the folder of the reconstruction that also upscales x2 (the auto mode's
            cheapest learned frames).
        token: the shared secret clients must send (None: no check, loopback only).
        tls_cert, tls_key: a PEM certificate (chain) and its unencrypted private key: serve HTTPS
            and WSS (None: plain HTTP and WS); both or neither, checked to load.
        insecure: allow plain HTTP beyond loopback.
        limits: the protocol limits.
        target_fps: the frame rate the ``auto`` mode's budget aims at.
        min_fps: the least frame rate the ``auto`` mode gives a session to keep AO that matters in its scene
            where ``target_fps`` would drop it (None: half of ``target_fps``; ``target_fps``: never).
        slice_ms: device time a slice of a heavy view frame aims at (others' frames interleave
            between slices); None: 8 ms on CUDA, 100 ms on CPUs.
        batch_wait_ms: how long a batch of view frames may wait for the sessions that have not
            asked for their next frame yet (:meth:`isosr_server.engine.Engine._batch_sync`).
        max_volume_bytes: the most bytes a volume's voxels take on the device; a larger volume
            renders sparse (the bricks each iso needs, paged in); None: half the free GPU memory
            at load, no limit on CPUs. It also picks a multiscale OME-Zarr's level
            (:mod:`isosr_server.volumes`).
        probe_cache: the auto mode's probe results file (None: kept in memory only).
        gpu_share: the part of its GPU this server has: 1, or a replica's share where replicas
            share one (`isosr serve --gpus-per-replica`, set from Ray's assignment); the auto
            mode's budget is the sessions' share of that part.
        log_level: ``debug``, ``info``, ``warning`` or ``error``.
        switch_interval_ms: how long a thread of the server's process may hold Python's interpreter lock while
            another waits for it (``sys.setswitchinterval``, :func:`configure_process`): the video encoders and the
            device thread let go of it in every C call and wait up to this long to take it back.
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
    recon_x2_model: Path = _option(RECON_X2_MODEL, "model folder of the reconstruction that also upscales x2 (auto "
                                                   "mode, at small budgets)", Path)
    token: str | None = _option(None, f"shared secret clients must send, at least {MIN_TOKEN_CHARS} characters "
                                      "(default: none, loopback only)")
    tls_cert: Path | None = _option(None, "PEM certificate (chain) to serve HTTPS and WSS with; needs --tls-key "
                                          "(default: plain HTTP)", Path)
    tls_key: Path | None = _option(None, "the unencrypted PEM private key of --tls-cert (default: none)", Path)
    insecure: bool = _option(False, "serve plain HTTP beyond loopback: the token and frames travel readable, and "
                                    "browsers decode no video (WebCodecs needs HTTPS)", parse_switch)
    limits: Limits = field(default_factory=Limits)
    target_fps: float = _option(30.0, "frame rate the auto mode's budget aims at", float)
    min_fps: float | None = _option(None, "least frame rate the auto mode gives a session to keep the AO its scene "
                                          "shows where --target-fps would drop it (default: half of --target-fps; "
                                          "equal to it: never)", float)
    slice_ms: float | None = _option(None, "device time a slice of a heavy view frame aims at, other sessions' "
                                           "frames interleaving between slices (default: 8 on CUDA, 100 on CPUs)",
                                     float)
    batch_wait_ms: float = _option(0.0, "milliseconds a batch of view frames may wait for the frames of sessions "
                                        "that have not asked yet, never past its first frame's deadline (default: 0, "
                                        "a batch takes the frames asked for until the device is free)", float)
    max_volume_bytes: int | None = _option(None, "bytes a volume's voxels may take on the device; larger volumes "
                                                 "render sparse, paging in the bricks each iso needs (default: half "
                                                 "the free GPU memory, no limit on CPUs); an OME-Zarr is served at "
                                                 "its finest level that fits, else its coarsest", int)
    probe_cache: Path | None = _option(None, "JSON file where the auto mode keeps what its probes learn per device, "
                                             "volume, iso and size, for later starts (default: memory only)", Path)
    log_level: str = _option("info", "log level", choices=LOG_LEVELS)
    switch_interval_ms: float = _option(SWITCH_INTERVAL_MS, "milliseconds a thread may hold Python's interpreter "
                                                            "lock while another waits for it (Python's own: 5)",
                                        float)
    gpu_share: float = 1.0

    def __post_init__(self):
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("--tls-cert and --tls-key go together: give both or neither")
        if self.tls_cert is not None:
            check_tls_files(self.tls_cert, self.tls_key)
        check_exposure(self.host, self.token, self.tls_cert is not None, self.insecure)
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
        if not (math.isfinite(self.batch_wait_ms) and self.batch_wait_ms >= 0):
            raise ValueError(f"batch_wait_ms must be a number of milliseconds, 0 or more, got {self.batch_wait_ms}")
        check_gpu_share(self.gpu_share)
        if not 0 < self.switch_interval_ms <= MAX_SWITCH_INTERVAL_MS:  # Python takes 1e300 s for 0 without a word
            raise ValueError(f"switch_interval_ms must lie in (0, {MAX_SWITCH_INTERVAL_MS:g}], "
                             f"got {self.switch_interval_ms}")
        for name in ("target_fps", "slice_ms"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.min_fps is not None:
            check_min_fps(self.min_fps, self.target_fps)

    @property
    def resolved_min_fps(self) -> float:
        """The auto mode's least frame rate: the given one, else half of ``target_fps``."""
        return self.target_fps / 2 if self.min_fps is None else self.min_fps

    @property
    def resolved_precision(self) -> str:
        """The networks' precision: the given one, else `default_precision` of the device."""
        return self.precision or default_precision(self.device)

    @property
    def scheme(self) -> str:
        """``https`` with a certificate, else ``http``."""
        return "http" if self.tls_cert is None else "https"

    def tls_context(self) -> ssl.SSLContext | None:
        """The server's TLS context (None without TLS): the certificate chain and its key, TLS 1.2 or
        newer (:func:`isosr_server.transport.protocol_class` makes the handshakes with it)."""
        if self.tls_cert is None:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls_cert, self.tls_key)
        return context

    def tls_options(self) -> dict[str, str]:
        """The certificate and key as Ray Serve's ``ssl_certfile`` and ``ssl_keyfile`` (none without TLS)."""
        return {} if self.tls_cert is None else {"ssl_certfile": str(self.tls_cert), "ssl_keyfile": str(self.tls_key)}

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


def check_exposure(host: str, token: str | None, tls: bool, insecure: bool) -> None:
    """The rule for serving beyond this machine (any host but loopback): a token, and TLS unless
    ``insecure``: over plain HTTP the token and the frames are readable by anyone on the path, and
    browsers give the viewer's video decoder (WebCodecs) only to HTTPS pages and loopback.

    Raises:
        ValueError: the host is not loopback and the token, or TLS, is missing.
    """
    if host in LOOPBACK_HOSTS:
        return
    if not token:
        raise ValueError(f"binding {host} exposes the server beyond this machine: give --token (or set {TOKEN_ENV})")
    if not (tls or insecure):
        raise ValueError(f"binding {host} without TLS sends the token and frames readable by anyone on the path, "
                         "and browsers decode no video there (WebCodecs needs HTTPS): give --tls-cert and "
                         "--tls-key, or --insecure")


# Ray Serve's switch for its HAProxy ingress (read when ray.serve is imported, by every Ray process it starts):
# HAProxy carries requests straight to each replica's own port, where Serve's proxy (Python, one a node) did.
HAPROXY_SWITCH = "RAY_SERVE_ENABLE_HA_PROXY"
INGRESSES = ("serve", "haproxy")
# HAProxy's files as Ray names them, by the variable that places each: by default all in /tmp/haproxy-serve, its admin
# socket mode 666 at level admin (any user of the node could drive it) and one such folder a node.
HAPROXY_FILES = {"RAY_SERVE_HAPROXY_CONFIG_FILE_LOC": "haproxy.cfg", "RAY_SERVE_HAPROXY_SOCKET_PATH": "admin.sock",
                 "RAY_SERVE_HAPROXY_METRICS_SOCKET_PATH": "metrics.sock", "RAY_SERVE_HAPROXY_SERVER_STATE_BASE": "",
                 "RAY_SERVE_HAPROXY_SERVER_STATE_FILE": "server-state"}


def haproxy_environment(private: Path, environ: Mapping[str, str]) -> dict[str, str]:
    """What to add to ``environ`` (before ray.serve is imported) for ``--ingress haproxy``: Serve's switch, and
    HAProxy's files in ``private`` (a folder only this user may enter: its admin socket no one else's), each
    where ``environ`` places none."""
    files = {name: str(private / file) if file else str(private) for name, file in HAPROXY_FILES.items()}
    return {HAPROXY_SWITCH: "1"} | {name: path for name, path in files.items() if name not in environ}


def check_ingress(ingress: str, settings: Settings) -> None:
    """What ``--ingress`` can carry: Serve's proxy anything; HAProxy no TLS (Ray's configuration of it
    terminates none: a reverse proxy in front does).

    Raises:
        ValueError: an unknown ingress, or HAProxy with a certificate.
    """
    if ingress not in INGRESSES:
        raise ValueError(f"--ingress must be one of {', '.join(INGRESSES)}, got {ingress!r}")
    if ingress == "haproxy" and settings.tls_cert is not None:
        raise ValueError("--ingress haproxy terminates no TLS: drop --tls-cert/--tls-key and terminate TLS in the "
                         "reverse proxy in front (--behind-proxy), or use --ingress serve")


def check_replica_exposure(host: str, accepted: bool) -> None:
    """The rule for replicas beyond this machine: Ray Serve's proxy, their front door, bounds neither a
    request's header size and read time nor TLS handshakes, nor its connections, nor a WebSocket's
    frames before the app sees them (the plain server does all of these, :mod:`isosr_server.transport`);
    beyond loopback it must sit behind a reverse proxy that does, which the user says with ``accepted``.

    Raises:
        ValueError: the host is not loopback and ``accepted`` is false.
    """
    if host not in LOOPBACK_HOSTS and not accepted:
        raise ValueError(f"binding {host} with --replicas exposes Ray Serve's proxy, which bounds neither header "
                         "size and time, TLS handshakes, connections nor WebSocket frames before authentication: "
                         "serve it through a reverse proxy that bounds them (docs/serving.md, 'Replicas beyond this "
                         "machine'): on this machine, bind --host 127.0.0.1; on another, pass --behind-proxy")


def check_tls_files(cert: Path, key: Path) -> None:
    """That ``cert`` holds a PEM certificate and ``key`` its unencrypted PEM private key.

    Raises:
        ValueError: naming the flag and file that is missing, unreadable or wrong.
    """
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        context.load_verify_locations(cafile=cert)
    except ssl.SSLError:
        raise ValueError(f"--tls-cert {cert}: no PEM certificate in it") from None
    except OSError as e:
        raise ValueError(f"--tls-cert {cert}: {e.strerror}") from None
    try:
        context.load_cert_chain(cert, key, password=b"")  # an encrypted key fails here, not at a prompt
    except ssl.SSLError:
        raise ValueError(f"--tls-key {key}: not the unencrypted PEM private key of {cert}") from None
    except OSError as e:
        raise ValueError(f"--tls-key {key}: {e.strerror}") from None


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
        group = limits if o.limit else parser
        if o.parse is parse_switch:  # a switch: given turns it on, absent leaves the environment's
            group.add_argument(o.flag, action="store_const", const=True, help=f"{o.help} (default: off)")
            continue
        help = o.help if "(default:" in o.help else f"{o.help} (default: {o.default})"
        group.add_argument(o.flag, type=o.parse, choices=o.choices, help=help)
