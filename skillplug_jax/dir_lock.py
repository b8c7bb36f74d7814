"""One writer per directory: a lock file that names the process writing there.

    with DirLock(run_dir, what=f"run directory {run_dir}"):   # <run_dir>/.writer.lock
      ...  # checkpoints

Two processes writing one run directory (or one dataset) would both run to the end and
overwrite each other's checkpoints. The lock file is created atomically (O_CREAT | O_EXCL) and
holds the writer's pid, host and command line; it is removed on exit, exceptions included. A
second writer stops at once with `DirLocked`, naming the holder. Readers take no lock.

The holder also keeps an flock on the file, which the kernel drops when the process dies, however
it dies (kill -9 included): a lock left by a dead process of this host is taken over with a
warning, so rerunning a killed command resumes. Where flock is not supported (some network
filesystems), the holder's pid decides. A lock from another host is never taken over, as its pid
means nothing here: the error says to delete the file once that process has ended.
"""

from __future__ import annotations

import fcntl
import json
import os
import shlex
import socket
import sys
import time
from pathlib import Path

LOCK_NAME = ".writer.lock"


class DirLocked(RuntimeError):
  """Another process is writing this directory."""

  def __init__(self, what: str, lock: str, holder: dict, other_host: bool = False):
    self.what, self.lock, self.holder, self.other_host = str(what), str(lock), dict(holder), other_host
    who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('started', '?')}: "
           f"{holder.get('command', '?')}") if holder else "a process that is taking the lock now"
    advice = (f"if that process has ended, delete {lock}" if other_host
              else "wait for it to finish or stop it (a killed writer's lock is taken over)")
    super().__init__(f"{what} is being written by another process ({who}); {advice}")

  def __reduce__(self):  # pickles (from a pipeline worker) with its own arguments, not the message
    return type(self), (self.what, self.lock, self.holder, self.other_host)


def this_process() -> dict:
  """What a lock records of its holder."""
  return dict(pid=os.getpid(), host=socket.gethostname(), command=shlex.join(sys.orig_argv),
              started=time.strftime("%Y-%m-%d %H:%M:%S"))


class DirLock:
  """Context manager: hold `directory`'s lock file `name` (the directory is created)."""

  def __init__(self, directory: str | os.PathLike, name: str = LOCK_NAME, what: str = ""):
    self.directory = Path(directory)
    self.path = self.directory / name
    self.what = what or str(self.directory)
    self._fd = None

  def __enter__(self) -> "DirLock":
    self.acquire()
    return self

  def __exit__(self, *exc) -> None:
    self.release()

  def acquire(self) -> None:
    if self._fd is not None:
      raise RuntimeError(f"{self.path} is already held by this DirLock")
    self.directory.mkdir(parents=True, exist_ok=True)
    while True:
      try:
        fd, created = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
      except FileExistsError:
        try:
          fd, created = os.open(self.path, os.O_RDWR), False
        except FileNotFoundError:  # its holder released it meanwhile
          continue
      try:
        if self._lock(fd, created):
          self._fd = fd
          return
      except BaseException:
        os.close(fd)
        raise
      os.close(fd)  # the file was released and replaced while we opened it: try again

  def _lock(self, fd: int, created: bool) -> bool:
    """Hold the file open as `fd`, or raise DirLocked; False: `fd` is no longer the lock file."""
    flocked = _flock(fd)
    if not _same_file(fd, self.path):  # its holder let it go meanwhile
      return False
    if flocked is False:
      raise DirLocked(self.what, self.path, _read(fd, wait_s=1.0))
    if not created:
      self._take_over(_read(fd), flocked, fd)
    me = json.dumps(this_process()).encode()
    os.ftruncate(fd, 0)
    os.pwrite(fd, me, 0)
    os.fsync(fd)
    return True

  def _take_over(self, holder: dict, flocked: bool | None, fd: int) -> None:
    """Return if the lock `holder` left may be taken; raise DirLocked if it may still be held."""
    if not holder:  # a writer died between creating the file and filling it (or is filling it now)
      if flocked is None and time.time() - os.fstat(fd).st_mtime < 5.0:
        raise DirLocked(self.what, self.path, {})
      print(f"warning: taking over the lock on {self.what}: {self.path} names no process", file=sys.stderr)
      return
    if holder.get("host") != socket.gethostname():
      raise DirLocked(self.what, self.path, holder, other_host=True)
    if flocked is None and _alive(holder.get("pid")):
      raise DirLocked(self.what, self.path, holder)
    print(f"warning: taking over the lock on {self.what}: its holder, pid {holder.get('pid')} "
          f"({holder.get('command')}), is no longer running", file=sys.stderr)

  def release(self) -> None:
    if self._fd is None:
      return
    try:
      if _same_file(self._fd, self.path):  # unlinked while still locked: no one takes the old file
        os.unlink(self.path)
    finally:
      os.close(self._fd)
      self._fd = None


def holder(directory: str | os.PathLike, name: str = LOCK_NAME) -> dict | None:
  """Who holds `directory`'s lock (None: no lock file; {} when it names no process)."""
  try:
    fd = os.open(Path(directory) / name, os.O_RDONLY)
  except FileNotFoundError:
    return None
  try:
    return _read(fd)
  finally:
    os.close(fd)


def _flock(fd: int) -> bool | None:
  """True: now held; False: another process holds it; None: this filesystem has no flock."""
  try:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except BlockingIOError:
    return False
  except OSError:
    return None
  return True


def _read(fd: int, wait_s: float = 0.0) -> dict:
  """The holder a lock file names; {} if it names none (yet: its writer fills it after taking it)."""
  deadline = time.monotonic() + wait_s
  while True:
    try:
      holder = json.loads(os.pread(fd, 1 << 16, 0).decode())
      if isinstance(holder, dict):
        return holder
    except ValueError:
      pass
    if time.monotonic() >= deadline:
      return {}
    time.sleep(0.05)


def _same_file(fd: int, path: Path) -> bool:
  try:
    st = os.stat(path)
  except FileNotFoundError:
    return False
  fst = os.fstat(fd)
  return (st.st_dev, st.st_ino) == (fst.st_dev, fst.st_ino)


def _alive(pid) -> bool:
  if not isinstance(pid, int) or pid <= 0:
    return False
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's process
    return True
  return True
