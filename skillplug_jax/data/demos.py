"""Generate a demonstration dataset: vectorised experts, successes only, written atomically.

Work is staged per task (`<out>/.<name>.staging-v<format>/<task>.npz`, each file
written by one rename), so a killed run resumes with the tasks it finished.
The tfds dataset is then built in `<out>/.<name>.building/` and moved to
`<out>/<name>/` by a rename: a dataset directory either is complete or does
not exist. Running again with the same arguments reuses the finished dataset.
One process writes a dataset (its lock, `<out>/.<name>.writer.lock`: `dir_lock`);
a second stops at once, naming the first. Readers take no lock.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

import envs
from envs import rollout
from envs.libero import suites as libero_suites
from skillplug_jax import dir_lock
from skillplug_jax.data import libero_recording, normalization, rlds
from skillplug_jax.data.recording import Episode, record_expert


@dataclasses.dataclass(frozen=True)
class DemoConfig:
  """What to generate. Episode i of a task starts from `rollout.reset_keys(seed, ...)[i]`; of a
  LIBERO task, from drawn start i of `seed` (`envs.libero.starts`)."""
  taskset: str = "discoverse7"  # taskset name or comma-separated task names
  demos: int = 300  # successful episodes kept per task
  images: bool = True
  image_size: tuple[int, int] = (64, 64)  # (H, W)
  seed: int = 0
  batch: int = 64  # environments simulated at once
  backend: str = "auto"  # envs.BACKENDS; resolved when the config is made, so it holds "mujoco" or "mjx-warp"

  def __post_init__(self):  # an API call's edge: "auto" is resolved here, once (envs.resolve_backend)
    object.__setattr__(self, "backend", envs.resolve_backend(self.backend))
    kinds = {libero_suites.is_libero(part) for part in self.taskset.split(",")}
    if len(kinds) > 1:
      raise ValueError(f"taskset {self.taskset!r} mixes LIBERO and DISCOVERSE tasks: their observations and "
                       "actions differ, so one dataset holds one benchmark's tasks")
    if self.layout == "libero":
      if self.backend != "mujoco":
        raise ValueError(f"LIBERO demonstrations run on MuJoCo's C engine (backend 'mujoco'); "
                         f"the {self.backend} path for LIBERO is not built yet")
      if self.images and self.image_size[0] != self.image_size[1]:
        raise ValueError(f"LIBERO's cameras are square; got image size {self.image_size}")

  @property
  def layout(self) -> str:
    return "libero" if libero_suites.is_libero(self.taskset.split(",")[0]) else "discoverse"

  @property
  def tasks(self) -> tuple[str, ...]:
    return tuple(n for part in self.taskset.split(",") for n in envs.taskset(part))

  @property
  def name(self) -> str:
    obs = f"img{self.image_size[0]}x{self.image_size[1]}" if self.images else "state"
    return (f"{self.taskset.replace(',', '+')}_{self.demos}demos_{obs}_seed{self.seed}_"
            f"{self.backend}")

  @property
  def spec(self) -> rlds.DatasetSpec:
    return rlds.DatasetSpec(self.tasks, tuple(self.image_size) if self.images else None, self.layout)


def dataset_path(cfg: DemoConfig, out: str | os.PathLike) -> Path:
  return Path(out) / cfg.name


def make_demos(cfg: DemoConfig, out: str | os.PathLike = "results/datasets", progress: bool = True) -> Path:
  """Generate (or reuse) the dataset for `cfg` under `out`; return its directory."""
  if cfg.demos < 1:
    raise ValueError(f"demos must be >= 1, got {cfg.demos}")
  tasks = cfg.tasks  # validates names
  final = dataset_path(cfg, out)
  if final.exists():
    return _reused(cfg, final, progress)
  with dir_lock.DirLock(out, name=f".{cfg.name}{dir_lock.LOCK_NAME}", what=f"dataset {final}"):
    if final.exists():  # a writer that held the lock finished it meanwhile
      return _reused(cfg, final, progress)
    return _write(cfg, out, tasks, final, progress)


def _reused(cfg: DemoConfig, final: Path, progress: bool) -> Path:
  builder = rlds.open_dataset(final)  # raises if it is not a complete dataset
  if rlds.spec_of(builder) != cfg.spec:
    raise rlds.DatasetError(f"{final} exists but holds {rlds.spec_of(builder)}, not {cfg.spec}")
  if progress:
    print(f"reusing {final}", file=sys.stderr)
  return final


def _write(cfg: DemoConfig, out: str | os.PathLike, tasks: tuple[str, ...], final: Path, progress: bool) -> Path:
  """Generate the dataset (under its lock: one writer per dataset, `dir_lock`)."""
  # Staged episodes are only reused by the recording format that made them.
  staging = Path(out) / f".{cfg.name}.staging-v{rlds.FORMAT_VERSION}"
  staging.mkdir(parents=True, exist_ok=True)
  bar = tqdm(total=cfg.demos * len(tasks), desc="demos kept", unit="ep", file=sys.stderr,
             disable=not progress, dynamic_ncols=True)
  stats = {}
  for task in tasks:
    path = staging / f"{task}.npz"
    if not path.exists():
      kept, info = _generate_task(cfg, task, bar)
      _save_stage(path, kept, info)
    else:
      bar.update(cfg.demos)
    stats[task] = _stage_info(path)
  bar.close()

  language = {t: libero_suites.parse(t).language for t in tasks} if cfg.layout == "libero" else {}

  def records():
    for task in tasks:
      kept, info = _load_stage(staging / f"{task}.npz")
      for idx, ep in zip(info["reset_index"], kept):
        yield rlds.EpisodeRecord(task, cfg.seed, int(idx), ep, language.get(task, ""))

  if progress:
    print(f"writing {final} ...", file=sys.stderr)
  building = Path(out) / f".{cfg.name}.building"
  shutil.rmtree(building, ignore_errors=True)
  renderer = (None if not cfg.images else LIBERO_RENDERER if cfg.layout == "libero" else envs.renderer_of(cfg.backend))
  metadata = dict(generator="skillplug_jax.data.demos", config=_config_dict(cfg),
                  device=str(jax.devices()[0]), backend=cfg.backend, renderer=renderer,
                  per_task={t: {k: v for k, v in s.items() if k != "reset_index"} for t, s in stats.items()})
  if language:
    metadata["language"] = language
  version_dir = rlds.write_dataset(building, cfg.spec, records, metadata)
  fields = [k for k, _ in rlds.layout_of(cfg.spec).state]
  actions, state = [], {k: [] for k in fields}
  for t in tasks:  # only the arrays the statistics need, not the images
    with np.load(staging / f"{t}.npz") as z:
      actions.append(z["action"])
      for k in fields:
        state[k].append(z[f"obs/{k}"])
  normalization.write_stats(version_dir, normalization.stats_of(
      np.concatenate(actions), **{k: np.concatenate(v) for k, v in state.items()}))
  rlds.write_checksums(version_dir)
  os.replace(version_dir, final)
  shutil.rmtree(building, ignore_errors=True)
  shutil.rmtree(staging, ignore_errors=True)
  return final


def _config_dict(cfg: DemoConfig) -> dict:
  d = dataclasses.asdict(cfg)
  d["image_size"] = list(cfg.image_size)
  return d


# How LIBERO demonstrations' cameras are drawn (libero_recording.record_expert).
LIBERO_RENDERER = "MuJoCo C engine, LIBERO's camera settings, no multisampling"


def _generate_libero_task(cfg: DemoConfig, task: str, bar) -> tuple[list[Episode], dict]:
  """Run expert batches from drawn LIBERO starts (`envs.libero.starts`, seeded by cfg.seed) until
  `cfg.demos` episodes succeed."""
  kept, indices, attempts, successes, nans, t0 = [], [], 0, 0, 0, time.time()
  max_attempts = 3 * cfg.demos + 2 * min(cfg.batch, cfg.demos)
  while len(kept) < cfg.demos:
    if attempts >= max_attempts:
      raise RuntimeError(f"{task}: only {len(kept)} of {attempts} expert episodes succeeded; "
                         f"cannot collect {cfg.demos} demonstrations")
    # a LIBERO episode costs seconds (its drawn start, cameras in software GL): once a batch has run,
    # the next simulates only what is missing, with a margin for the expert's failures
    num = min(cfg.batch, cfg.demos) if not attempts else min(cfg.batch, 2 * (cfg.demos - len(kept)) + 2)
    bar.set_postfix_str(f"{task} (simulating {num})")
    episodes = libero_recording.record_expert(task, attempts, num, seed=cfg.seed, images=cfg.images,
                                              image_size=cfg.image_size[0])
    for b, ep in enumerate(episodes):
      nans += ep.nan
      successes += ep.success
      if ep.success and len(kept) < cfg.demos:
        kept.append(ep)
        indices.append(attempts + b)
        bar.update(1)
    attempts += num
  info = dict(reset_index=np.asarray(indices, np.int64), attempts=attempts, kept=len(kept),
              expert_success_rate=successes / attempts, nan_episodes=nans, starts="drawn (envs.libero.starts)",
              wall_s=round(time.time() - t0, 2), mean_length=float(np.mean([len(e.action) for e in kept])))
  return kept, info


def _generate_task(cfg: DemoConfig, task: str, bar) -> tuple[list[Episode], dict]:
  """Run seeded expert batches until `cfg.demos` episodes succeed."""
  if cfg.layout == "libero":
    return _generate_libero_task(cfg, task, bar)
  benv = envs.make(task, num_envs=min(cfg.batch, cfg.demos), render=cfg.images,
                   image_size=cfg.image_size, backend=cfg.backend)
  kept, indices, attempts, successes, nans, t0 = [], [], 0, 0, 0, time.time()
  overflow = []
  max_attempts = 3 * cfg.demos + 2 * benv.num_envs
  while len(kept) < cfg.demos:
    if attempts >= max_attempts:
      raise RuntimeError(f"{task}: only {len(kept)} of {attempts} expert episodes succeeded; "
                         f"cannot collect {cfg.demos} demonstrations")
    bar.set_postfix_str(f"{task} (simulating {benv.num_envs})")
    keys = rollout.reset_keys(cfg.seed, benv.num_envs, offset=attempts)
    for b, ep in enumerate(record_expert(benv, keys)):
      nans += ep.nan
      successes += ep.success
      overflow.append(ep.overflow)
      if ep.success and len(kept) < cfg.demos:
        kept.append(ep)
        indices.append(attempts + b)
        bar.update(1)
    attempts += benv.num_envs
  wall = time.time() - t0
  info = dict(reset_index=np.asarray(indices, np.int64), attempts=attempts, kept=len(kept),
              expert_success_rate=successes / attempts if attempts else 0.0, nan_episodes=nans,
              **{f"{k}_limit_episodes": v for k, v in envs.env.solver_limit_counts(overflow).items()},
              wall_s=round(wall, 2), **({} if benv.render_s is None else {"render_s": round(benv.render_s, 2)}),
              mean_length=float(np.mean([len(e.action) for e in kept])))
  return kept, info


def _save_stage(path: Path, kept: list[Episode], info: dict) -> None:
  """All kept episodes of a task, concatenated, in one atomically written .npz."""
  lengths = np.asarray([len(e.action) for e in kept], np.int64)
  arrays = {f"obs/{k}": np.concatenate([e.observation[k] for e in kept]) for k in kept[0].observation}
  arrays.update(action=np.concatenate([e.action for e in kept]), lengths=lengths,
                nan=np.asarray([e.nan for e in kept]), success=np.asarray([e.success for e in kept]))
  for k, v in info.items():
    arrays[f"info/{k}"] = np.asarray(v)
  tmp = path.with_suffix(".tmp.npz")
  np.savez(tmp, **arrays)
  os.replace(tmp, path)


def _stage_info(path: Path) -> dict:
  with np.load(path) as z:
    return {k[5:]: z[k].item() if z[k].ndim == 0 else z[k] for k in z.files if k.startswith("info/")}


def _load_stage(path: Path) -> tuple[list[Episode], dict]:
  with np.load(path) as z:
    lengths = z["lengths"]
    ends = np.cumsum(lengths)
    starts = ends - lengths
    obs = {k[4:]: z[k] for k in z.files if k.startswith("obs/")}
    action = z["action"]
    eps = [Episode(observation={k: v[s:e] for k, v in obs.items()}, action=action[s:e],
                   success=bool(z["success"][i]), nan=bool(z["nan"][i]))
           for i, (s, e) in enumerate(zip(starts, ends))]
  return eps, _stage_info(path)

