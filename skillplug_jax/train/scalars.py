"""Training scalars: TensorBoard event files plus a JSON-lines copy for notebooks and tests."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
from tensorboardX import SummaryWriter

METRICS_FILE = "metrics.jsonl"


class ScalarLog:
  """Writes {name: value} per step to <run>/tensorboard and <run>/metrics.jsonl.

  Several processes (jax.distributed) training one run log the same (replicated)
  scalars: only the first writes them; the others' logs write nothing.
  """

  def __init__(self, run_dir: Path, resume_step: int = 0):
    self.path = Path(run_dir) / METRICS_FILE
    self._tb = None
    if jax.process_index() != 0:
      return
    self._drop_after(resume_step)  # a killed run logged past its last checkpoint
    self._tb = SummaryWriter(os.fspath(Path(run_dir) / "tensorboard"), purge_step=resume_step or None)

  def _drop_after(self, step: int) -> None:
    if not self.path.exists():
      return
    keep = [line for line in self.path.read_text().splitlines()
            if line.strip() and json.loads(line)["step"] <= step]
    tmp = self.path.with_suffix(".tmp")
    tmp.write_text("".join(line + "\n" for line in keep))
    os.replace(tmp, self.path)

  def write(self, step: int, scalars: dict) -> None:
    if self._tb is None:  # not the first process
      return
    for k, v in scalars.items():
      self._tb.add_scalar(k, v, step)
    with open(self.path, "a") as f:
      f.write(json.dumps({"step": step, **scalars}) + "\n")

  def close(self) -> None:
    if self._tb is not None:
      self._tb.close()


def read_metrics(run_dir: Path) -> list[dict]:
  path = Path(run_dir) / METRICS_FILE
  return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
