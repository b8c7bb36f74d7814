"""Stopping on request: SIGTERM (what a cluster sends before it preempts a job) and SIGINT (Ctrl-C).

The training loop holds a `StopRequests` while it steps: a signal only sets a
flag, the loop finishes the step under way, checkpoints it and raises
`Preempted`; the same command then resumes from that step, as if the run had
not stopped. A second signal while it saves acts at once (the default
action), so an impatient user is never stuck; orbax's atomic saves keep the
previous checkpoint whole even then. A signal the process ignores (SIG_IGN,
as `nohup` or a worker pool may set) stays ignored.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import jax
import numpy as np

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Stopped(Exception):
  """Work stopped on a signal; what it had written is whole (atomic writes), and rerunning resumes."""

  def __init__(self, signum: int, message: str = ""):
    self.signum = int(signum)
    super().__init__(message or f"stopped by {signal.Signals(self.signum).name}; what was written is "
                                "kept: run the same command again to resume")

  @property
  def exit_code(self) -> int:
    """The shell's convention for a process ended by a signal (143 for SIGTERM, 130 for SIGINT)."""
    return 128 + self.signum

  def __reduce__(self):  # crosses process boundaries (pipeline workers) with its own arguments
    return type(self), (self.signum, str(self))


class Preempted(Stopped):
  """Training stopped on a signal after checkpointing its current step; rerun the command to resume."""

  def __init__(self, signum: int, step: int, run_dir: str | Path):
    self.step, self.run_dir = int(step), str(run_dir)
    super().__init__(signum, f"stopped by {signal.Signals(int(signum)).name} at step {self.step}: checkpoint "
                             f"{self.step} saved in {Path(self.run_dir) / 'checkpoints'}; run the same "
                             f"command again to resume from it")

  def __reduce__(self):
    return type(self), (self.signum, self.step, self.run_dir)


class StopRequests:
  """A context manager whose `signum` becomes the first SIGTERM/SIGINT received while it is held.

  Outside the main thread (where Python cannot install handlers) it holds nothing and never fires.
  """

  def __init__(self, signals=SIGNALS):
    self.signals, self.signum, self._previous = tuple(signals), None, {}

  @property
  def requested(self) -> bool:
    return self.signum is not None

  def agreed(self) -> bool:
    """Whether to stop now. With several processes (jax.distributed) they must stop at the same step,
    or one would wait in the checkpoint's collectives while another steps on: a signal to any of them
    stops all, through an all-gather of the flag after every step (a scalar; one process: no cost)."""
    if jax.process_count() == 1:
      return self.requested
    from jax.experimental import multihost_utils
    return bool(np.any(multihost_utils.process_allgather(np.asarray(self.requested))))

  def _handle(self, signum, frame) -> None:
    self.signum = signum
    for s, previous in self._previous.items():  # the next signal acts at once
      signal.signal(s, previous)

  def __enter__(self) -> StopRequests:
    if threading.current_thread() is threading.main_thread():
      for s in self.signals:
        previous = signal.getsignal(s)
        if previous is not None and previous is not signal.SIG_IGN:  # None: a handler from C, kept
          self._previous[s] = previous
          signal.signal(s, self._handle)
    return self

  def __exit__(self, exc_type, exc, tb) -> None:
    if threading.current_thread() is threading.main_thread():
      for s, previous in self._previous.items():
        if signal.getsignal(s) == self._handle:
          signal.signal(s, previous)
    self._previous = {}
    if self.signum is not None and exc_type is None:  # it came too late for its holder to act on it:
      signal.raise_signal(self.signum)  # delivered again, to whatever handles it outside


class RaiseOnSignal:
  """A context manager in which SIGTERM/SIGINT raise `Stopped` where the main thread is, so that work
  outside training (an evaluation) ends as an exception its caller can report, not a killed process.
  Training inside it still checkpoints first (its `StopRequests` takes the signals while it steps)."""

  def __init__(self, signals=SIGNALS):
    self.signals, self._previous = tuple(signals), {}

  @staticmethod
  def _raise(signum, frame):
    raise Stopped(signum)

  def __enter__(self) -> RaiseOnSignal:
    if threading.current_thread() is threading.main_thread():
      self._previous = {s: signal.signal(s, self._raise) for s in self.signals}
    return self

  def __exit__(self, *exc) -> None:
    for s, previous in self._previous.items():
      signal.signal(s, previous if previous is not None else signal.SIG_DFL)
    self._previous = {}
