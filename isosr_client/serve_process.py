"""`ServeProcess`: `isosr serve` in a subprocess on a free loopback port, waited for until ready and
stopped (SIGINT, then SIGKILL): the notebook widget's local server (:mod:`isosr_client.notebook`)
and the benchmarks' and tests' servers (:class:`isosr_bench.bench_server.ServerProcess`).

    with ServeProcess(("--device", "cpu")) as server:
        print(server.url)               # http://127.0.0.1:PORT, ready
"""

from __future__ import annotations

import json
import signal
import socket
import ssl
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Mapping, Sequence


def free_port() -> int:
    """A loopback port free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServeProcess:
    """`isosr serve` on 127.0.0.1 and a free port, in a subprocess; a context manager that starts it,
    waits for ``/v2/health/ready`` and stops it on exit.

    Args:
        args: `isosr serve` options besides the host and port.
        env: the server's environment (default: this process's).
        startup_s: how long to wait for ready (a GPU server with empty kernel caches compiles and
            tunes its kernels first: more than 180 s on an H200).
        tls: a client context that trusts the server's certificate, where ``args`` give it one (the
            server then speaks HTTPS).
    """

    def __init__(self, args: Sequence[str] = (), env: Mapping[str, str] | None = None, startup_s: float = 420.0,
                 tls: ssl.SSLContext | None = None):
        self.port = free_port()
        self.tls = tls
        self.url = f"{'http' if tls is None else 'https'}://127.0.0.1:{self.port}"
        self.command = [sys.executable, "-m", "isosr_cli.main", "serve", "--host", "127.0.0.1", "--port",
                        str(self.port), "--log-level", "warning", *args]
        self.env, self.startup_s = env, startup_s
        self.process: subprocess.Popen | None = None
        self.ready_s: float | None = None  # seconds from the start to ready, once started

    def start(self) -> ServeProcess:
        """Start the server and wait until it is ready.

        Raises:
            RuntimeError: it exited (with the end of its log) or was not ready in ``startup_s`` (then stopped).
        """
        self.log = tempfile.TemporaryFile()  # a file, not a pipe: a full pipe nobody reads would stall the server
        self.process = subprocess.Popen(self.command, stdout=subprocess.DEVNULL, stderr=self.log,
                                        env=None if self.env is None else dict(self.env))
        started = time.monotonic()
        deadline = started + self.startup_s
        while not self._ready():
            if self.process.poll() is not None:
                self.log.seek(0)
                log = self.log.read().decode(errors="replace")[-2000:]
                self.stop()
                raise RuntimeError(f"the server exited ({self.process.returncode}): {log}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the server was not ready within {self.startup_s:g} s")
            time.sleep(0.2)
        self.ready_s = time.monotonic() - started
        return self

    def _ready(self) -> bool:
        try:
            with urllib.request.urlopen(self.url + "/v2/health/ready", timeout=2, context=self.tls) as r:
                return json.loads(r.read()).get("ready") is True
        except OSError:
            return False

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self) -> None:
        """Stop the server (SIGINT, then SIGKILL after 20 s); nothing where it was stopped already."""
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()

    def __enter__(self) -> ServeProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
