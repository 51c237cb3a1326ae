"""A real `isosr serve` app on uvicorn on a free loopback port, in a background thread, for tests;
plus small HTTP and WebSocket helpers and a root-logger handler that collects ERROR records."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
import urllib.error
import urllib.request
from contextlib import contextmanager

import uvicorn
from websockets.sync.client import connect

from isosr_server import protocol as P
from isosr_server.app import ServerConfig, create_app, uvicorn_options

# Clients accept big frames (the server's limit bounds what clients send).
CLIENT_LIMITS = P.Limits(max_message_bytes=2**28)


class ErrorRecords(logging.Handler):
    """Collects every record at ERROR or above that reaches the root logger."""

    def __init__(self):
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def messages(self) -> list[str]:
        return [f"{r.name}: {r.getMessage()}" for r in self.records]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RunningServer:
    """Where a test server listens, with helpers to call it."""

    def __init__(self, port: int, config: ServerConfig, errors: ErrorRecords):
        self.port, self.config, self.errors = port, config, errors
        self.http_url, self.ws_url = f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}"

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: dict | None = None) -> tuple[int, dict, bytes]:
        """``(status, headers, body)``; 4xx and 5xx are answers, not exceptions."""
        req = urllib.request.Request(self.http_url + path, data=body, method=method, headers=headers or {})
        if body is not None and "Content-Type" not in (headers or {}):
            req.add_header("Content-Type", P.MSGPACK_MEDIA_TYPE)
        try:
            with urllib.request.urlopen(req, timeout=60) as r:
                return r.status, dict(r.headers), r.read()
        except urllib.error.HTTPError as e:
            return e.code, dict(e.headers), e.read()

    def get_json(self, path: str, headers: dict | None = None) -> tuple[int, dict]:
        status, _, body = self.request("GET", path, headers=headers)
        return status, json.loads(body)

    def view(self, **kwargs):
        """A WebSocket connection to ``/v1/view`` (not yet opened)."""
        return self.ws("/v1/view", **kwargs)

    def ws(self, path: str, **kwargs):
        return connect(self.ws_url + path, max_size=2**28, proxy=None, compression=None, open_timeout=30, **kwargs)


def recv(ws, timeout: float = 60) -> P.Message:
    """The next server message of a view or upscale connection, validated."""
    return P.parse(ws.recv(timeout=timeout), CLIENT_LIMITS,
                   dict(P.SERVER_VIEW_MESSAGES, upscaled=P.UpscaleResponse))


@contextmanager
def running_server(config: ServerConfig):
    """Start the app on uvicorn in a thread; yields a `RunningServer`; stops it after."""
    errors = ErrorRecords()
    logging.getLogger().addHandler(errors)
    logging.getLogger("isosr").setLevel(logging.INFO)
    port = free_port()
    # log_config=None: uvicorn leaves logging alone, so its records reach the root logger too.
    server = uvicorn.Server(uvicorn.Config(create_app(config), host="127.0.0.1", port=port, log_config=None,
                                           **uvicorn_options(config.limits)))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the test server did not start")
        time.sleep(0.02)
    try:
        yield RunningServer(port, config, errors)
    finally:
        server.should_exit = True
        thread.join(30)
        logging.getLogger().removeHandler(errors)
