"""JSON and text files written by one rename: a reader sees the old file or the new one, never half."""

from __future__ import annotations

import json
import os
from pathlib import Path


def write_json_atomic(path: str | os.PathLike, payload) -> None:
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = Path(f"{path}.tmp")
  with open(tmp, "w") as f:
    json.dump(payload, f, indent=2)
  os.replace(tmp, path)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = Path(f"{path}.tmp")
  tmp.write_text(text)
  os.replace(tmp, path)


def read_json(path: str | os.PathLike):
  with open(path) as f:
    return json.load(f)
