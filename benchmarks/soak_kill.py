"""Soak test of resuming: a short training killed with kill -9 again and again ends bit-identical.

    python -m benchmarks.soak_kill --kills 8 --out results/soak_kill.json      # make soak

The same `skillplug pretrain` command runs to the end once, uninterrupted; then
again in another run directory, killed with SIGKILL (no handler runs, nothing is
flushed) each time its logged step reaches a random target, and restarted,
`--kills` times; one of those times, at a random place in the sequence, the
process kills itself the moment it has handed a checkpoint to orbax, in the
middle of the write. Then it runs to the end. The final parameters of the two
runs must be equal bit for bit. The JSON records every kill: the step it
landed after, the checkpoint the next start resumed from, and whether a
half-written checkpoint was left behind.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from skillplug_jax.atomic_json import write_json_atomic
from skillplug_jax.startup import cpu_name

# Runs `skillplug pretrain ARGS...` with checkpoint.save wrapped: the first save this process asks
# for is handed to orbax, which writes it in the background, and the process SIGKILLs itself at once.
KILL_IN_SAVE = """
import os, signal, sys
from skillplug_jax import cli
from skillplug_jax.train import checkpoint
save = checkpoint.save
def save_then_die(mngr, step, state):
  save(mngr, step, state)
  os.kill(os.getpid(), signal.SIGKILL)
checkpoint.save = save_then_die
sys.exit(cli.main(sys.argv[1:]))
"""

# The quick preset at a size that trains 400 steps in about a minute of this project's CPU.
DEFAULT_SET = ("model.hidden=64", "model.heads=4", "model.ff=128", "model.enc_layers=1", "model.dec_layers=2",
               "model.cvae_enc_layers=1", "batch_size=8", "warmup_steps=10")


def pretrain_command(workdir: Path, taskset: str, steps: int, ckpt_every: int, overrides) -> list[str]:
  sets = [*overrides, f"max_steps={steps}", f"ckpt_every={ckpt_every}", "log_every=1"]
  return ["pretrain", "--config", "quick", "--taskset", taskset, "--workdir", str(workdir),
          *(a for o in sets for a in ("--set", o))]


def logged_step(run: Path) -> int:
  """The last step in the run's metrics.jsonl (0 if none); a line being written is skipped."""
  path = run / "metrics.jsonl"
  if not path.exists():
    return 0
  for line in reversed(path.read_text().splitlines()):
    if line.endswith("}"):
      return int(line.split('"step": ', 1)[1].split(",", 1)[0])
  return 0


def log_identity(run: Path):
  """The metrics file's inode (None if absent): a resumed run replaces the file when it trims the
  rows past its checkpoint, so a new inode means the rows read are this start's."""
  try:
    return (run / "metrics.jsonl").stat().st_ino
  except FileNotFoundError:
    return None


def latest_checkpoint(run: Path) -> int:
  steps = [int(p.name) for p in (run / "checkpoints").glob("*") if p.name.isdigit()]
  return max(steps, default=0)


def half_written(run: Path) -> list[str]:
  """Orbax's temporary step directories: a write that never finished."""
  return sorted(p.name for p in (run / "checkpoints").glob("*") if not p.name.isdigit())


def soak(work: Path, kills: int, steps: int, ckpt_every: int, seed: int = 0,
         taskset: str = "jujube_pick,kiwi_place", overrides=DEFAULT_SET, env=None, log=print,
         in_process: bool = False) -> dict:
  """Run the drill in `work`; return what happened, `identical` the verdict.

  in_process: the uninterrupted run and the last restart call the CLI in this process (the same
  command, less start-up time: the test's small version); the killed starts are always processes.
  """
  from skillplug_jax import cli as skillplug_cli
  from skillplug_jax.train import loop

  rng = random.Random(seed)
  cli = [sys.executable, "-m", "skillplug_jax.cli"]
  straight, killed = work / "straight", work / "killed"
  stderr = work / "stderr.txt"  # a file, not a pipe: the progress bar never fills it and blocks

  def to_the_end(command: list[str]) -> None:
    if in_process:
      rc = skillplug_cli.main(command)
    else:
      with open(stderr, "w") as f:
        rc = subprocess.run(cli + command, env=env, stdout=subprocess.DEVNULL, stderr=f).returncode
    if rc:
      raise RuntimeError(f"skillplug {' '.join(command)} failed (rc {rc}): {stderr.read_text()[-2000:] if stderr.exists() else ''}")

  work.mkdir(parents=True, exist_ok=True)
  t0 = time.time()
  to_the_end(pretrain_command(straight, taskset, steps, ckpt_every, overrides))
  log(f"uninterrupted run: {steps} steps in {time.time() - t0:.0f} s")
  cmd = pretrain_command(killed, taskset, steps, ckpt_every, overrides)
  in_save = rng.randrange(kills)
  events = []
  for i in range(kills):
    start = latest_checkpoint(killed)
    if i == in_save:
      proc = subprocess.run([sys.executable, "-c", KILL_IN_SAVE, *cmd], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
      event = dict(kind="during a checkpoint write", resumed_from=start, rc=proc.returncode,
                   after_step=logged_step(killed), half_written=half_written(killed))
    else:
      target = rng.randint(start + 1, max(start + 1, (start + steps) // 2))  # in the first half of what is left
      stale = log_identity(killed)  # the log the last start left: rows past `start` until the run trims it
      with open(stderr, "w") as f:
        proc = subprocess.Popen(cli + cmd, env=env, stdout=subprocess.DEVNULL, stderr=f)
      while proc.poll() is None and (log_identity(killed) == stale or logged_step(killed) < target):
        time.sleep(0.01)
      time.sleep(rng.uniform(0, 0.02))  # between steps or inside one, by chance
      proc.send_signal(signal.SIGKILL)
      proc.wait()
      if proc.returncode not in (0, -signal.SIGKILL):
        raise RuntimeError(f"the run failed (rc {proc.returncode}) instead of being killed: "
                           f"{stderr.read_text()[-2000:]}")
      event = dict(kind="kill -9 at a random step", target=target, resumed_from=start, rc=proc.returncode,
                   after_step=logged_step(killed), half_written=half_written(killed))
    events.append(event)
    log(f"kill {i + 1}/{kills}: {event}")
    if proc.returncode == 0:
      break  # it finished before the kill
  to_the_end(cmd)
  _, a, step_a = loop.load_params(straight)
  _, b, step_b = loop.load_params(killed)
  diffs = [float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)), initial=0.0))
           for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))]
  identical = step_a == step_b == steps and all(
      np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
  return dict(steps=steps, ckpt_every=ckpt_every, taskset=taskset, overrides=list(overrides), seed=seed,
              kills=events, landed=sum(e["rc"] == -signal.SIGKILL for e in events), final_steps=[step_a, step_b],
              identical=bool(identical), max_abs_diff=max(diffs), wall_s=round(time.time() - t0, 1))


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--kills", type=int, default=8, help="restarts killed with SIGKILL (one during a checkpoint write)")
  p.add_argument("--steps", type=int, default=400)
  p.add_argument("--ckpt-every", type=int, default=25)
  p.add_argument("--seed", type=int, default=0, help="of the kill moments")
  p.add_argument("--work", default="results/soak_kill", help="the two run directories (emptied first)")
  p.add_argument("--data-dir", default="results/datasets", help="the demonstrations (generated when missing)")
  p.add_argument("--out", default="results/soak_kill.json")
  args = p.parse_args(argv)
  if args.kills < 1 or args.steps < 4 or args.ckpt_every < 1:
    p.error("--kills and --ckpt-every must be >= 1, --steps >= 4")
  work = Path(args.work)
  for run in (work / "straight", work / "killed"):
    if run.exists():
      subprocess.run(["rm", "-rf", str(run)], check=True)
  overrides = (*DEFAULT_SET, "demos=3", f"data_dir={args.data_dir}")
  result = soak(work, args.kills, args.steps, args.ckpt_every, args.seed, overrides=overrides,
                env={**os.environ})
  result["cpu"] = cpu_name()
  write_json_atomic(Path(args.out), result)
  print(f"{'bit-identical' if result['identical'] else 'DIFFERENT'} after {result['landed']} kills "
        f"({result['wall_s']:.0f} s); wrote {args.out}")
  return 0 if result["identical"] else 1


if __name__ == "__main__":
  sys.exit(main())
