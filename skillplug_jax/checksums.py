"""Per-file checksums written beside files that are read back later (checkpoints, datasets).

A manifest is one JSON file in the directory it covers: each file's size and
SHA-256, by path relative to that directory. Decompression and the libraries'
own checks miss some changed bytes (a flip in stored array data can decode to
other numbers without complaint), so the readers compare every file with the
manifest before they use it.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Iterable

from skillplug_jax.atomic_json import write_json_atomic

ALGORITHM = "sha256"
_CHUNK = 1 << 20


def digest(path: Path, algorithm: str = ALGORITHM) -> str:
  h = hashlib.new(algorithm)
  with open(path, "rb") as f:
    while chunk := f.read(_CHUNK):
      h.update(chunk)
  return h.hexdigest()


def write_manifest(root: str | os.PathLike, name: str, skip: Iterable[str] = ()) -> Path:
  """Checksum every file under `root` (but the manifest and `skip`) into <root>/<name>, atomically."""
  root = Path(root)
  skip = {name, f"{name}.tmp", *skip}
  files = {}
  for p in sorted(root.rglob("*")):
    rel = p.relative_to(root).as_posix()
    if p.is_file() and rel not in skip:
      files[rel] = {"size": p.stat().st_size, ALGORITHM: digest(p)}
  write_json_atomic(root / name, {"algorithm": ALGORITHM, "files": files})
  return root / name


def problems(root: str | os.PathLike, name: str) -> list[tuple[Path, str]]:
  """(file, what is wrong) for each file under `root` that differs from its manifest <root>/<name>
  ([] when all match). Files the manifest does not list are not checked."""
  root = Path(root)
  try:
    manifest = json.loads((root / name).read_bytes())
    files, algorithm = manifest["files"], manifest["algorithm"]
    hashlib.new(algorithm)
  except (ValueError, KeyError, TypeError) as e:  # JSON, Unicode, a missing key, an unknown algorithm
    return [(root / name, f"is corrupt: it is the checksum manifest ({type(e).__name__}: {e})")]
  out = []
  for rel, want in files.items():
    path = root / rel
    try:
      size = path.stat().st_size
    except FileNotFoundError:
      out.append((path, "is missing"))
      continue
    if size != want.get("size"):
      kind = "truncated" if size < want.get("size", 0) else "not the file written"
      out.append((path, f"is {kind} ({size} bytes, {want.get('size')} when written)"))
    elif digest(path, algorithm) != want.get(algorithm):
      out.append((path, "does not match its checksum: its bytes changed after it was written"))
  return out
