"""The viewer in a notebook: an anywidget (JupyterLab, Notebook, VS Code; no build step).

    import isosr_client
    w = isosr_client.widget("http://127.0.0.1:8000", "bonsai", token="...")   # a running server
    w = isosr_client.widget(array, spacing=(1.0, 1.0, 2.0))                  # a local one for an array
    w                          # shows it; drag to orbit, wheel to zoom
    w.iso = 0.3                # camera, iso, mode, t, width, height: traitlets, both ways
    rgb = w.frame()            # numpy (height, width, 3) uint8 of the current state

The browser side (``notebook.js``) opens the view WebSocket itself with the viewer page's
``session.js``, imported from the server. ``frame()`` uses this side's own view session
(:mod:`isosr_client.view`) with the widget's state, opened at its first call: a kernel hears
nothing from the browser while a cell runs, so the browser cannot hand it its pixels within the
call, and a widget that no browser shows (a script, ``nbconvert``) still has frames.

Needs the ``notebook`` extra (anywidget). The token is a synced traitlet: it is saved in the
notebook only where widget state is saved with it.
"""

from __future__ import annotations

import os
import secrets
import tempfile
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import anywidget
import numpy as np
import traitlets

from isosr_client.serve_process import ServeProcess
from isosr_client.view import ViewSession, connect
from isosr_server.protocol import CameraMsg, ProtocolError, convert

DEFAULT_CAMERA = {"yaw": 30.0, "pitch": 20.0, "distance": 1.8, "target": [0.0, 0.0, 0.0], "fov_y": 40.0}
# The settings traitlets, sent as a view session's settings.
SETTINGS = ("mode", "width", "height", "t", "encoding")


class Viewer(anywidget.AnyWidget):
    """A view session on ``url``'s ``volume`` shown in the notebook; the traitlets are its state.

    ``info`` (the volume's name, shape, value range, suggested iso, steps) and ``status``
    (connecting, open, lost, error ...) are set by the browser; ``iso`` None asks for the volume's
    suggested iso, which the browser then writes back.
    """

    _esm = Path(__file__).with_name("notebook.js")

    url = traitlets.Unicode().tag(sync=True)
    token = traitlets.Unicode(None, allow_none=True).tag(sync=True)
    volume = traitlets.Unicode().tag(sync=True)
    mode = traitlets.Unicode("auto").tag(sync=True)
    iso = traitlets.Float(None, allow_none=True).tag(sync=True)
    camera = traitlets.Dict(DEFAULT_CAMERA).tag(sync=True)
    t = traitlets.Int(0, min=0).tag(sync=True)
    width = traitlets.Int(480, min=8, max=8192).tag(sync=True)
    height = traitlets.Int(360, min=8, max=8192).tag(sync=True)
    encoding = traitlets.Unicode("jpeg").tag(sync=True)
    info = traitlets.Dict().tag(sync=True)
    status = traitlets.Unicode("").tag(sync=True)

    def __init__(self, server: LocalServer | None = None, **kwargs: Any):
        super().__init__(**kwargs)
        self._server = server  # the local server this widget started, stopped with it
        self._session: ViewSession | None = None
        self._applied: dict[str, Any] = {}  # the state the session has

    @traitlets.validate("camera")
    def _check_camera(self, proposal: dict) -> dict:
        """A partial camera updates the current one; orbit fields only, checked as the protocol does."""
        unknown = set(proposal["value"]) - set(DEFAULT_CAMERA)
        if unknown:
            raise traitlets.TraitError(f"camera: unknown fields {sorted(unknown)}; it takes {list(DEFAULT_CAMERA)}")
        camera = {**self.camera, **proposal["value"]}
        try:
            convert(camera, CameraMsg, "camera")
        except ProtocolError as e:
            raise traitlets.TraitError(str(e)) from None
        return camera

    def frame(self, timeout: float = 60.0) -> np.ndarray:
        """The image of the widget's current state, (height, width, 3) uint8 (module docstring).

        Raises:
            ServerError: the server refused the state (an unknown volume or mode, a bad iso ...).
        """
        state = {k: getattr(self, k) for k in SETTINGS} | {"camera": self.camera, "iso": self.iso}
        where = (self.url, self.token, self.volume)
        if self._session is None or self._applied.get("where") != where:
            self._close_session()
            self._session = connect(self.url, self.volume, self.mode, (self.width, self.height), token=self.token,
                                    settings={"t": self.t, "encoding": "png"}, camera=self.camera, iso=self.iso,
                                    timeout=timeout)
        else:
            changed = {k: state[k] for k in SETTINGS if k != "encoding" and state[k] != self._applied[k]}
            if changed:
                self._session.set_settings(**changed)
            if state["camera"] != self._applied["camera"]:
                self._session.set_camera(**state["camera"])
            if state["iso"] is not None and state["iso"] != self._applied["iso"]:
                self._session.set_iso(state["iso"])
        self._applied = state | {"where": where}
        return self._session.frame(timeout=timeout)

    def _close_session(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    def close(self) -> None:
        """Close the widget, this side's view session and the local server it started."""
        self._close_session()
        if self._server is not None:
            self._server.close()
        super().close()


class LocalServer:
    """`isosr serve` in a subprocess on a free loopback port with a fresh token, offering one array
    as volume ``name`` (from a temporary folder); stopped by `close` or when this process exits.

    A subprocess keeps the server's device, torch and threads out of the kernel.
    """

    def __init__(self, array: np.ndarray, spacing: Sequence[float] | None = None, name: str = "array",
                 device: str = "cpu", startup_s: float = 180.0):
        array = np.asarray(array)
        if array.ndim not in (3, 4):
            raise ValueError(f"a volume is a 3D (x, y, z) or 4D (t, z, y, x) array, got shape {array.shape}")
        if spacing is not None and (array.ndim == 4 or len(spacing) != 3):
            raise ValueError("spacing: three numbers (x, y, z), for a 3D array")
        self._folder = tempfile.TemporaryDirectory(prefix="isosr-widget-")
        folder = Path(self._folder.name)
        if spacing is None:
            np.save(folder / f"{name}.npy", array)
        else:
            np.savez(folder / f"{name}.npz", volume=array, spacing=np.asarray(spacing, float))
        self.name, self.token = name, secrets.token_urlsafe(24)
        # The token through the environment: a command line is readable by every local user.
        self._server = ServeProcess(("--volumes", str(folder), "--device", device),
                                    env=dict(os.environ, ISOSR_TOKEN=self.token), startup_s=startup_s)
        self.url = self._server.url
        self._stop = weakref.finalize(self, _stop, self._server, self._folder)  # also at exit
        try:
            self._server.start()
        except RuntimeError as e:
            self.close()
            raise RuntimeError(f"the local server did not start: {e}") from None

    @property
    def pid(self) -> int:
        return self._server.pid

    @property
    def running(self) -> bool:
        return self._server.running

    def close(self) -> None:
        self._stop()


def _stop(server: ServeProcess, folder: tempfile.TemporaryDirectory) -> None:
    """Stop the server and remove its folder."""
    server.stop()
    folder.cleanup()


def widget(source: str | np.ndarray, volume: str | None = None, *, token: str | None = None,
           spacing: Sequence[float] | None = None, device: str = "cpu", **traits: Any) -> Viewer:
    """A `Viewer` of ``volume`` on the server at URL ``source``, or of the array ``source`` on a
    local server started for it (loopback, its own token; stopped with the widget or the kernel).

    Args:
        source: a server URL (``http(s)://HOST:PORT``) or a 3D (x, y, z) / 4D (t, z, y, x) array.
        volume: the volume's name on the server (a URL's only).
        token: the server's token, if it has one (a URL's only).
        spacing: the array's voxel spacing (x, y, z); default 1.
        device: where the local server renders (cpu, cuda, cuda:N).
        traits: first values of the `Viewer` traitlets (iso, camera, mode, t, width, height, encoding).

    Raises:
        ValueError: a URL without a volume, or an array with a volume, token or bad shape.
        RuntimeError: the local server did not start.
    """
    if isinstance(source, str):
        if volume is None or spacing is not None:
            raise ValueError("a server URL takes the volume's name (and no spacing)")
        return Viewer(url=source, volume=volume, token=token, **traits)
    if volume is not None or token is not None:
        raise ValueError("an array is served locally under its own name and token: no volume or token")
    server = LocalServer(source, spacing, device=device)
    return Viewer(server, url=server.url, volume=server.name, token=server.token, **traits)
