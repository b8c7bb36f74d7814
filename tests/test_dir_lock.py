"""One writer per directory: a second writer is refused naming the holder, a dead holder's lock is
taken over with a warning (so a killed command resumes), the lock goes on any exit, readers take none."""

import contextlib
import json
import os
import pickle
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from skillplug_jax import dir_lock
from skillplug_jax.data import demos
from skillplug_jax.dir_lock import DirLock, DirLocked
from skillplug_jax.train import checkpoint, config, loop
from synthetic import write_two_task_demos

ROOT = Path(__file__).resolve().parents[1]
HOLD = ("import sys, time; from skillplug_jax.dir_lock import DirLock; "
        "DirLock(sys.argv[1], sys.argv[2]).acquire(); time.sleep(600)  # holder-marker")


@contextlib.contextmanager
def holder_process(directory: Path, name: str = dir_lock.LOCK_NAME):
  """A real process that takes `directory`'s lock and sleeps; killed (-9) on exit if still alive."""
  proc = subprocess.Popen([sys.executable, "-c", HOLD, str(directory), name], cwd=ROOT)
  try:
    deadline = time.monotonic() + 120
    while (dir_lock.holder(directory, name) or {}).get("pid") != proc.pid:
      assert proc.poll() is None, f"the holder exited with {proc.returncode}"
      assert time.monotonic() < deadline, "the holder never took the lock"
      time.sleep(0.05)
    yield proc
  finally:
    proc.kill()
    proc.wait()


def write_lock(directory: Path, **holder) -> Path:
  directory.mkdir(parents=True, exist_ok=True)
  path = directory / dir_lock.LOCK_NAME
  path.write_text(json.dumps(holder))
  return path


def dead_pid() -> int:
  proc = subprocess.Popen(["true"])
  proc.wait()  # reaped: the pid names no process
  return proc.pid


def test_a_second_writer_is_refused_naming_the_holder_and_a_killed_ones_lock_is_taken_over(tmp_path, capsys):
  with holder_process(tmp_path) as proc:
    with pytest.raises(DirLocked) as info:
      with DirLock(tmp_path, what="the test directory"):
        pytest.fail("a second writer got in")
    message = str(info.value)
    assert message.startswith("the test directory is being written by another process")
    assert f"pid {proc.pid} on {socket.gethostname()}" in message and "holder-marker" in message
    assert info.value.holder["pid"] == proc.pid
    proc.kill()  # as kill -9: the lock file stays behind
    proc.wait()
  assert dir_lock.holder(tmp_path)["pid"] == proc.pid
  capsys.readouterr()
  with DirLock(tmp_path):
    assert dir_lock.holder(tmp_path)["pid"] == os.getpid()
  err = capsys.readouterr().err
  assert f"taking over the lock on {tmp_path}: its holder, pid {proc.pid}" in err and "no longer running" in err
  assert not (tmp_path / dir_lock.LOCK_NAME).exists()


def test_the_lock_is_released_on_an_exception(tmp_path, capsys):
  with pytest.raises(KeyError):
    with DirLock(tmp_path / "run"):
      assert (tmp_path / "run" / dir_lock.LOCK_NAME).exists()
      raise KeyError("the writer failed")
  assert not (tmp_path / "run" / dir_lock.LOCK_NAME).exists()
  with DirLock(tmp_path / "run"):  # free again, with no warning
    pass
  assert capsys.readouterr().err == ""


def test_one_process_cannot_hold_a_directory_twice(tmp_path):
  with DirLock(tmp_path):
    with pytest.raises(DirLocked, match=f"pid {os.getpid()} "):
      DirLock(tmp_path).acquire()
  assert not (tmp_path / dir_lock.LOCK_NAME).exists()


def test_stale_locks_by_pid_and_foreign_hosts(tmp_path, capsys, monkeypatch):
  here = socket.gethostname()
  pid = dead_pid()
  write_lock(tmp_path / "dead", pid=pid, host=here, command="skillplug pretrain", started="then")
  with DirLock(tmp_path / "dead"):
    pass
  assert f"its holder, pid {pid} (skillplug pretrain), is no longer running" in capsys.readouterr().err
  # another host's lock is never taken over: its pid means nothing here
  lock = write_lock(tmp_path / "far", pid=pid, host="elsewhere.example", command="skillplug pretrain",
                    started="then")
  with pytest.raises(DirLocked, match=f"pid {pid} on elsewhere.example .*if that process has ended, delete "
                                      + re.escape(str(lock))):
    DirLock(tmp_path / "far").acquire()
  assert lock.exists()
  # a lock file left empty (its writer died before filling it) is taken over
  empty = tmp_path / "empty" / dir_lock.LOCK_NAME
  empty.parent.mkdir()
  empty.touch()
  with DirLock(tmp_path / "empty"):
    pass
  assert "names no process" in capsys.readouterr().err
  # without flock (some network filesystems) the pid decides: alive refuses, dead is taken over
  monkeypatch.setattr(dir_lock, "_flock", lambda fd: None)
  write_lock(tmp_path / "nfs", pid=os.getppid(), host=here, command="a live writer", started="now")
  with pytest.raises(DirLocked, match=f"pid {os.getppid()} on {here} since now: a live writer"):
    DirLock(tmp_path / "nfs").acquire()
  write_lock(tmp_path / "nfs", pid=pid, host=here, command="a dead writer", started="then")
  with DirLock(tmp_path / "nfs"):
    pass
  assert "a dead writer" in capsys.readouterr().err


RACE = """import os, sys, time
from pathlib import Path
from skillplug_jax.dir_lock import DirLock, DirLocked
where, me = Path(sys.argv[1]), sys.argv[2]
(where / f"ready{me}").touch()
while not (where / "go").exists():
  time.sleep(0.005)
try:
  with DirLock(where / "run"):
    print("won", flush=True)
    time.sleep(3)
except DirLocked:
  print("refused", flush=True)
"""


def test_racing_writers_over_a_dead_ones_lock_let_exactly_one_in(tmp_path):
  write_lock(tmp_path / "run", pid=dead_pid(), host=socket.gethostname(), command="killed", started="then")
  procs = [subprocess.Popen([sys.executable, "-c", RACE, str(tmp_path), str(i)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL) for i in range(4)]
  try:
    deadline = time.monotonic() + 120
    while not all((tmp_path / f"ready{i}").exists() for i in range(4)):
      assert time.monotonic() < deadline and all(p.poll() is None for p in procs)
      time.sleep(0.05)
    (tmp_path / "go").touch()
    outcomes = sorted(p.communicate(timeout=120)[0].strip() for p in procs)
  finally:
    for p in procs:
      p.kill()
      p.wait()
  assert outcomes == ["refused", "refused", "refused", "won"]
  assert not (tmp_path / "run" / dir_lock.LOCK_NAME).exists()


def test_the_error_pickles_with_its_holder():  # a pipeline worker's error reaches the parent whole
  err = DirLocked("run directory x", "x/.writer.lock", dict(pid=7, host="h", command="c", started="s"))
  back = pickle.loads(pickle.dumps(err))
  assert str(back) == str(err) and back.holder["pid"] == 7


# ---- where the library writes ----------------------------------------------------

@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  root = tmp_path_factory.mktemp("datasets")
  write_two_task_demos(root, np.random.default_rng(0))
  return root


def tiny(data_dir, workdir):
  from skillplug_jax import experiment
  return config.override(experiment.preset("quick", "act"), [
      "taskset=jujube_pick,kiwi_place", "demos=3", f"data_dir={data_dir}", f"workdir={workdir}",
      "model.hidden=16", "model.heads=2", "model.ff=32", "model.enc_layers=1", "model.dec_layers=1",
      "model.cvae_enc_layers=1", "model.chunk=5", "batch_size=2", "max_steps=4", "log_every=2",
      "ckpt_every=2", "warmup_steps=0"])


@pytest.mark.slow
def test_training_locks_its_run_directory_and_resumes_after_a_kill(data_dir, tmp_path, capsys):
  cfg = tiny(data_dir, tmp_path / "run")
  loop.train(cfg, progress=False, stop_after=2)
  assert not (cfg.run_dir / dir_lock.LOCK_NAME).exists()
  with holder_process(cfg.run_dir) as proc:  # a writer of the same run, still going
    with pytest.raises(DirLocked, match=re.escape(f"run directory {cfg.run_dir} is being written") + f".*pid {proc.pid}"):
      loop.train(cfg, progress=False)
    assert checkpoint.manager(cfg.run_dir).latest_step() == 2  # refused before any work
    # readers take no lock: the shared dataset reads while its writer's lock is held
    dataset = demos.dataset_path(loop.dataset_config(cfg), data_dir)
    with DirLock(data_dir, f".{dataset.name}{dir_lock.LOCK_NAME}"):
      assert loop.load_data(cfg, progress=False).num_episodes == 6
    proc.kill()
    proc.wait()
  capsys.readouterr()
  loop.train(cfg, progress=False)  # the same command again: takes the dead writer's lock, resumes
  assert f"its holder, pid {proc.pid}" in capsys.readouterr().err
  assert checkpoint.manager(cfg.run_dir).latest_step() == 4
  assert not (cfg.run_dir / dir_lock.LOCK_NAME).exists()
  assert not list(Path(data_dir).glob("*.lock"))


def test_a_dataset_has_one_writer(tmp_path, monkeypatch):
  cfg = demos.DemoConfig(taskset="jujube_pick", demos=2, images=False, backend="mujoco")
  monkeypatch.setattr(demos, "_write", lambda *a: pytest.fail("wrote a dataset another process holds"))
  name = f".{cfg.name}{dir_lock.LOCK_NAME}"
  with holder_process(tmp_path, name) as proc:
    with pytest.raises(DirLocked, match=re.escape(f"dataset {tmp_path / cfg.name} is being written") + f".*pid {proc.pid}"):
      demos.make_demos(cfg, tmp_path, progress=False)
  # the holder was killed: the next writer takes its lock over, writes, and lets go
  made = []
  monkeypatch.setattr(demos, "_write", lambda cfg, out, tasks, final, progress: made.append(final) or final)
  assert demos.make_demos(cfg, tmp_path, progress=False) == tmp_path / cfg.name
  assert made == [tmp_path / cfg.name] and not (tmp_path / name).exists()
