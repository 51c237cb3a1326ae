"""The shared real volumes (``../shared/volumes``): where they are and their manifest."""

from __future__ import annotations

import json
import os
from pathlib import Path

ENV_VAR = "ISOSR_SHARED_VOLUMES"


def shared_volumes_dir() -> Path:
    """``$ISOSR_SHARED_VOLUMES``, else ``shared/volumes`` beside the project checkout."""
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR])
    return Path(__file__).resolve().parents[2] / "shared" / "volumes"


def manifest(root: Path | None = None) -> list[dict]:
    """The entries of ``volumes.json`` (name, file, shape_xyz, spacing_xyz, value_range, split, ...).

    Raises:
        FileNotFoundError: the folder or its manifest is absent, with where it was looked for.
    """
    root = root or shared_volumes_dir()
    path = root / "volumes.json"
    if not path.is_file():
        raise FileNotFoundError(f"no shared volume manifest at {path} (set {ENV_VAR} to the volumes folder)")
    return json.loads(path.read_text())


def entry(name: str, root: Path | None = None) -> dict:
    """One manifest entry by name, with ``path`` added."""
    root = root or shared_volumes_dir()
    for e in manifest(root):
        if e["name"] == name:
            return {**e, "path": root / e["file"]}
    raise KeyError(f"no volume named {name!r} in {root / 'volumes.json'}")
