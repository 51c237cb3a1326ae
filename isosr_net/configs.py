"""Typed configs from JSON files: one reader for every stage's dataclass."""

from __future__ import annotations

import json
import os
from dataclasses import fields
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def load_config(cls: type[T], path: str | os.PathLike, **overrides) -> T:
    """``cls(**json)`` with ``overrides`` (None values ignored) on top.

    Raises:
        ValueError: not JSON, unknown keys, or what ``cls`` rejects; the message names the file.
    """
    try:
        raw = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON: {e}") from e
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a JSON object of {cls.__name__} fields")
    raw.update({k: v for k, v in overrides.items() if v is not None})
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; {cls.__name__} knows {sorted(known)}")
    try:
        return cls(**raw)
    except TypeError as e:
        raise ValueError(f"{path}: {e}") from e
