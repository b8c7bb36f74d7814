"""SIGTERM and SIGINT: training checkpoints the step under way and stops; the same command resumes
bit for bit; the pipeline stops all its workers cleanly. Each signal goes to a real subprocess."""

import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from skillplug_jax.train import checkpoint, loop, preemption
from skillplug_jax.train.scalars import read_metrics
from test_train import data_dir, leaves, tiny  # noqa: F401  (data_dir: the module fixture of synthetic demos)

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}

# The tiny model of the runs started here as commands (test_train's `tiny`, one decoder layer).
SMALL = ("model.hidden=32", "model.heads=2", "model.ff=64", "model.enc_layers=1", "model.dec_layers=1",
         "model.cvae_enc_layers=1", "model.plug.num_skills=3", "model.plug.skill_latent_dim=8",
         "model.plug.alignment_dim=16", "model.chunk=10")

# Trains `tiny(...)` and sends itself SIGTERM while the scalars of step 3 are logged, just after the
# loop last looked for a stop: it runs step 4, sees the request, checkpoints 4 (between the periodic
# checkpoints 3 and 6) and stops. A signal at a known step, where a kill would lose step 4.
SELF_SIGNAL = """
import os, signal, sys
from pathlib import Path
from skillplug_jax.train import loop, preemption, scalars
from test_train import tiny

write = scalars.ScalarLog.write
def write_then_signal(self, step, values):
  write(self, step, values)
  if step == 3:
    os.kill(os.getpid(), signal.SIGTERM)
scalars.ScalarLog.write = write_then_signal
try:
  loop.train(tiny(Path(sys.argv[1]), Path(sys.argv[2])), progress=False)
except preemption.Preempted as e:
  print(e, file=sys.stderr)
  sys.exit(e.exit_code)
"""


def wait_for(predicate, proc, timeout: float, what: str, log: Path) -> None:
  deadline = time.monotonic() + timeout
  while not predicate():
    if proc.poll() is not None:
      pytest.fail(f"the process ended (rc {proc.returncode}) before {what}: {log.read_text()[-3000:]}")
    if time.monotonic() > deadline:
      pytest.fail(f"no {what} within {timeout} s")
    time.sleep(0.2)


def kill_group(proc) -> None:
  """The process and every process it started (a pipeline's workers), whatever the test's outcome."""
  try:
    os.killpg(proc.pid, signal.SIGKILL)
  except ProcessLookupError:
    pass
  proc.wait()


def logged_steps(run: Path) -> list[int]:
  return [r["step"] for r in read_metrics(run)] if (run / "metrics.jsonl").exists() else []


@pytest.mark.slow
def test_sigterm_checkpoints_the_step_under_way_and_resuming_is_bit_identical(data_dir, tmp_path):  # noqa: F811
  straight = loop.train(tiny(data_dir, tmp_path / "straight"), progress=False)
  cfg = tiny(data_dir, tmp_path / "stopped")
  proc = subprocess.run([sys.executable, "-c", SELF_SIGNAL, str(data_dir), str(cfg.workdir)], env=ENV,
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 128 + signal.SIGTERM, proc.stderr[-3000:]
  assert f"stopped by SIGTERM at step 4: checkpoint 4 saved in {cfg.run_dir / 'checkpoints'}" in proc.stderr
  assert "run the same command again to resume" in proc.stderr
  assert sorted(checkpoint.manager(cfg.run_dir).all_steps()) == [3, 4]  # a kill would have kept 3 only
  loop.train(cfg, progress=False)  # the same command: resumes at 4
  _, a, step_a = loop.load_params(straight)
  _, b, step_b = loop.load_params(cfg.run_dir)
  assert step_a == step_b == 6
  for x, y in zip(leaves(a), leaves(b)):
    np.testing.assert_array_equal(x, y)  # bit for bit, not merely close
  assert logged_steps(cfg.run_dir) == [2, 3, 4, 6]


@pytest.mark.slow
def test_cli_pretrain_stops_on_sigterm_with_the_resume_command(data_dir, tmp_path):  # noqa: F811
  """A real signal from outside, at a moment the test does not choose: the step checkpointed is the
  one the run had reached, and the message says how to resume."""
  run = tmp_path / "cli"
  overrides = ["demos=3", f"data_dir={data_dir}", *SMALL, "batch_size=4", "max_steps=1000000", "log_every=2",
               "ckpt_every=1000000", "warmup_steps=2"]
  cmd = [sys.executable, "-m", "skillplug_jax.cli", "pretrain", "--config", "quick", "--taskset",
         "jujube_pick,kiwi_place", "--workdir", str(run)] + [a for o in overrides for a in ("--set", o)]
  log = tmp_path / "stderr.txt"  # a file, not a pipe: the progress bar never fills it and blocks
  with open(log, "w") as f:
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=f, start_new_session=True)
  try:
    wait_for(lambda: len(logged_steps(run)) >= 2, proc, 600, "two logged windows", log)
    seen = logged_steps(run)[-1]
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=120)
    err = log.read_text()
  finally:
    kill_group(proc)
  assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
  step = checkpoint.manager(run).latest_step()
  assert step is not None and step >= seen  # the step under way, not an earlier periodic one
  assert f"skillplug: stopped by SIGTERM at step {step}: checkpoint {step} saved" in err
  assert "run the same command again to resume" in err
  assert logged_steps(run)[-1] == step  # the window up to the stop is logged, none after it


@pytest.mark.slow
def test_pipeline_stops_every_worker_cleanly_on_sigint(data_dir, tmp_path):  # noqa: F811
  """Ctrl-C reaches the pipeline's process alone here (as a cluster's SIGTERM may): both workers'
  training jobs checkpoint their step and stop, the queued jobs never start, and the exit code says
  the pipeline was interrupted."""
  out = tmp_path / "pipeline"
  (out / "datasets").mkdir(parents=True)
  for d in Path(data_dir).iterdir():  # the synthetic demos where the pipeline's runs look for them
    (out / "datasets" / d.name).symlink_to(d)
  overrides = ["train.taskset=jujube_pick,kiwi_place", "train.demos=3", "train.max_steps=1000000",
               "train.batch_size=4", "train.warmup_steps=1", "train.log_every=2", "train.ckpt_every=1000000",
               *(f"train.{o}" for o in SMALL if o != "model.cvae_enc_layers=1"), "run_fewshot=false", "workers=2",
               "seeds=0,1"]
  cmd = [sys.executable, "-m", "experiments.pipeline", "--config", "quick", "--out", str(out)]
  cmd += [a for o in overrides for a in ("--set", o)]
  log = tmp_path / "stderr.txt"
  with open(log, "w") as f:
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=f, cwd=ROOT, start_new_session=True)
  runs = {p: out / "runs" / f"jujube_pick,kiwi_place_{p}_quick_seed0" for p in ("act", "skillplug")}
  try:
    wait_for(lambda: all(logged_steps(r) for r in runs.values()), proc, 900, "a logged window in both runs", log)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=180)
    err = log.read_text()
  finally:
    kill_group(proc)
  assert proc.returncode == 128 + signal.SIGINT, err[-3000:]
  for policy, run in runs.items():
    step = checkpoint.manager(run).latest_step()
    assert step is not None and step >= logged_steps(run)[0]
    assert f"stopped by SIGTERM at step {step}: checkpoint {step} saved in {run / 'checkpoints'}" in err
  assert not list(out.glob("runs/*seed1*/checkpoints/*"))  # queued jobs did not start
  assert "pipeline: stopped by SIGINT" in err and "run the same command again to resume" in err
  assert not (out / "summary.json").exists()


def test_a_signal_the_process_ignores_stays_ignored_and_handlers_come_back():
  previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
  sigint = signal.signal(signal.SIGINT, signal.default_int_handler)  # whatever the test runner set
  try:
    with preemption.StopRequests() as stop:
      assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN  # nohup's choice is kept
      assert signal.getsignal(signal.SIGINT) == stop._handle
    assert signal.getsignal(signal.SIGINT) == signal.default_int_handler and not stop.requested
  finally:
    signal.signal(signal.SIGTERM, previous)
    signal.signal(signal.SIGINT, sigint)


def test_the_errors_pickle_with_their_fields():  # a pipeline worker's error reaches the parent whole
  e = pickle.loads(pickle.dumps(preemption.Preempted(signal.SIGTERM, 7, "runs/x")))
  assert (e.signum, e.step, e.run_dir, e.exit_code) == (signal.SIGTERM, 7, "runs/x", 143)
  assert "stopped by SIGTERM at step 7" in str(e)
  s = pickle.loads(pickle.dumps(preemption.Stopped(signal.SIGINT)))
  assert s.exit_code == 130 and "stopped by SIGINT" in str(s)
