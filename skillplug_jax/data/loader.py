"""The chunked batch loader: ACT's sampling over an in-memory copy of the dataset.

ACT's epoch draws one random timestep from every training episode. We keep
that as a stream: draw j of the stream belongs to epoch j // N (N episodes),
each epoch visits the episodes in a fresh permutation, and each visit picks
t uniformly in the episode. Batch i is draws [iB, (i+1)B). Both the
permutation and the timesteps of epoch e come from `default_rng([seed, e])`,
so any batch can be rebuilt from (seed, step) alone: a resumed run sees the
batches a straight run would have seen, and fewer episodes than the batch
size (few-shot: 10 demos, batch 16) still gives full batches.

A sample is the observation at t (joint state normalised, object state too
unless the model reads it raw), the normalised action chunk t..t+chunk-1
(zeros and `action_mask` False past the episode end), and the task id, for
reporting only; with `skill_labels`, the step's mined label too. The dataset
is decoded once into flat numpy arrays (images
too: 64x64 PNGs decode at load time, and a batch is then a gather); a thread
builds the next batches and puts them on the devices while the current step
runs.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from pathlib import Path
from typing import Iterator, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from skillplug_jax.data import normalization, rlds
from skillplug_jax.data.rlds import DatasetError


@dataclasses.dataclass(frozen=True)
class Demonstrations:
  """A dataset decoded into flat arrays: step arrays are indexed by start[e] + t."""
  path: Path
  tasks: tuple[str, ...]
  image_size: tuple[int, int] | None
  steps: dict  # the layout's low-dim fields (joint_pos [S,7], object_state [S,D], ...), action [S,7], <camera>_rgb [S,H,W,3]
  start: np.ndarray  # [E] first step of each episode
  length: np.ndarray  # [E]
  task_id: np.ndarray  # [E] index into tasks
  episode_id: tuple[str, ...]
  stats: dict
  layout: rlds.Layout = rlds.DISCOVERSE
  language: tuple[str, ...] = ()  # per task, in `tasks` order (layouts with language)

  @property
  def num_episodes(self) -> int:
    return len(self.length)

  def episode(self, e: int) -> dict:
    s, n = self.start[e], self.length[e]
    return {k: v[s:s + n] for k, v in self.steps.items()}


def load_demonstrations(path: str | Path, *, tasks: Sequence[str] | None = None,
                        image_size: tuple[int, int] | None = None, images: bool = False,
                        progress: bool = False) -> Demonstrations:
  """Read and validate a dataset.

  tasks: the tasks the caller trains on; each must be present with episodes.
  images / image_size: whether the caller needs images, and of what size.
  """
  builder = rlds.open_dataset(path)
  spec = rlds.spec_of(builder)
  if images:
    if spec.image_size is None:
      raise DatasetError(f"{path}: the config uses images but the dataset is state-only "
                         "(generate it with images)")
    if image_size is not None and tuple(image_size) != tuple(spec.image_size):
      raise DatasetError(f"{path}: images are {spec.image_size[0]}x{spec.image_size[1]} (HxW), "
                         f"the config expects {image_size[0]}x{image_size[1]}")
  wanted = tuple(tasks) if tasks is not None else spec.tasks
  unknown = [t for t in wanted if t not in spec.tasks]
  if unknown:
    raise DatasetError(f"{path}: has no task {unknown} (it holds {', '.join(spec.tasks)})")

  lay = rlds.layout_of(spec)
  keys = tuple(k for k, _ in lay.state) + (tuple(f"{c}_rgb" for c in lay.cameras) if images else ())
  cols = {k: [] for k in keys + ("action",)}
  length, task_id, ids, language = [], [], [], {}
  episodes = rlds.read_episodes(builder)
  if progress:
    from tqdm import tqdm
    episodes = tqdm(episodes, total=builder.info.splits["train"].num_examples, desc="loading", unit="ep")
  for meta, steps in episodes:
    if meta["task"] not in wanted:
      continue
    act = steps["action"]
    if not np.all(np.isfinite(act)):
      raise DatasetError(f"{path}: episode {meta.get('episode_id', '?')} has non-finite actions")
    for k in keys:
      cols[k].append(steps["observation"][k])
    cols["action"].append(act.astype(np.float32))
    length.append(len(act))
    task_id.append(wanted.index(meta["task"]))
    if lay.language:
      language.setdefault(meta["task"], meta["language_instruction"])
    ids.append(meta.get("episode_id", ""))
  counts = np.bincount(np.asarray(task_id, np.int64), minlength=len(wanted))
  empty = [t for t, c in zip(wanted, counts) if c == 0]
  if empty:
    raise DatasetError(f"{path}: no episodes for task(s) {', '.join(empty)}")

  flat = {k: np.concatenate(v) for k, v in cols.items()}
  stats = normalization.read_stats(path, {"action": lay.action_dim, **dict(lay.state)})
  if stats is None:  # a dataset written elsewhere: compute once, keep beside it
    stats = normalization.stats_of(flat["action"], **{k: flat[k] for k, _ in lay.state})
    normalization.write_stats(path, stats)
  elif "object_state" not in stats:  # written before object state was normalised: the loaded tasks'
    stats = {**stats, "object_state": normalization.moments(flat["object_state"])}
  length = np.asarray(length, np.int64)
  order = np.argsort(ids, kind="stable")  # tfds shuffles records; sort for a fixed episode order
  starts = np.concatenate([[0], np.cumsum(length)[:-1]])
  flat_order = np.concatenate([np.arange(starts[e], starts[e] + length[e]) for e in order])
  flat = {k: v[flat_order] for k, v in flat.items()}
  length = length[order]
  return Demonstrations(
      path=Path(path), tasks=wanted, image_size=spec.image_size if images else None, steps=flat,
      start=np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64), length=length,
      task_id=np.asarray(task_id, np.int32)[order], episode_id=tuple(ids[i] for i in order), stats=stats,
      layout=lay, language=tuple(language[t] for t in wanted) if lay.language else ())


def data_sharding(mesh: Mesh | None = None) -> NamedSharding:
  """Batch axis split over every device (all hosts): plain data parallelism."""
  mesh = mesh or Mesh(np.asarray(jax.devices()), ("data",))
  return NamedSharding(mesh, PartitionSpec("data"))


class ChunkLoader:
  """Batches of (observation at t, action chunk from t, mask, task id)."""

  def __init__(self, demos: Demonstrations, batch_size: int, chunk: int = 25, seed: int = 0,
               images: bool = False, sharding: NamedSharding | None = None,
               normalize_object_state: bool = True, skill_labels: np.ndarray | None = None,
               instructions: np.ndarray | None = None):
    if images and demos.image_size is None:
      raise DatasetError("images requested but the demonstrations were loaded without images")
    if normalize_object_state and "object_state" not in demos.stats:
      raise DatasetError(f"{demos.path}: the statistics have no object_state entry to normalise with")
    self.normalize_object_state = normalize_object_state
    if skill_labels is not None and len(skill_labels) != len(demos.steps["action"]):
      raise ValueError(f"{len(skill_labels)} skill labels for {len(demos.steps['action'])} steps")
    self.skill_labels = skill_labels  # [S] per step (data/segments.py), or None
    if instructions is not None and len(instructions) != len(demos.tasks):
      raise ValueError(f"{len(instructions)} instructions for {len(demos.tasks)} tasks")
    self.instructions = instructions  # [tasks, words] word ids per task (data/language.py), or None
    self.demos, self.batch_size, self.chunk, self.seed, self.images = demos, batch_size, chunk, seed, images
    self.sharding = sharding or data_sharding()
    n_dev = self.sharding.mesh.size
    if batch_size % n_dev:
      raise ValueError(f"batch size {batch_size} does not split over {n_dev} devices")
    procs, pid = jax.process_count(), jax.process_index()
    if batch_size % procs:
      raise ValueError(f"batch size {batch_size} does not split over {procs} processes")
    per = batch_size // procs
    self._local = slice(pid * per, (pid + 1) * per)  # this host's rows of the global batch
    self._epoch_cache: tuple[int, np.ndarray, np.ndarray] | None = None
    self.wait_s = 0.0  # time the consumer spent blocked on the next batch

  def _epoch(self, e: int):
    if self._epoch_cache is None or self._epoch_cache[0] != e:
      rng = np.random.default_rng([self.seed, e])
      n = self.demos.num_episodes
      self._epoch_cache = (e, rng.permutation(n), rng.random(n))
    return self._epoch_cache[1:]

  def indices(self, step: int) -> tuple[np.ndarray, np.ndarray]:
    """(episode, timestep) of each row of global batch `step`."""
    n = self.demos.num_episodes
    draws = np.arange(step * self.batch_size, (step + 1) * self.batch_size)
    ep, t = np.empty_like(draws), np.empty_like(draws)
    for e in np.unique(draws // n):
      perm, u = self._epoch(int(e))
      sel = draws // n == e
      pos = draws[sel] % n
      ep[sel] = perm[pos]
      t[sel] = np.floor(u[pos] * self.demos.length[perm[pos]]).astype(np.int64)
    return ep, t

  def numpy_batch(self, step: int, local: bool = False) -> dict:
    """Global batch `step` as numpy (only this host's rows if `local`)."""
    ep, t = self.indices(step)
    if local:
      ep, t = ep[self._local], t[self._local]
    return self.gather(ep, t)

  def gather(self, ep: np.ndarray, t: np.ndarray) -> dict:
    """The samples at (episode, timestep) pairs, as a numpy batch."""
    d = self.demos
    stats = d.stats
    row = d.start[ep] + t
    offs = t[:, None] + np.arange(self.chunk)[None, :]
    mask = offs < d.length[ep][:, None]
    idx = d.start[ep][:, None] + np.minimum(offs, d.length[ep][:, None] - 1)
    actions = normalization.normalize(d.steps["action"][idx], stats, "action")
    batch = {k: normalization.normalize(d.steps[k][row], stats, k).astype(np.float32)
             for k, _ in d.layout.state if k != "object_state"}
    batch.update({
        "object_state": (normalization.normalize(d.steps["object_state"][row], stats, "object_state")
                         if self.normalize_object_state else d.steps["object_state"][row]).astype(np.float32),
        "actions": np.where(mask[..., None], actions, 0.0).astype(np.float32),
        "action_mask": mask,
        "task_id": d.task_id[ep].astype(np.int32),
    })
    if self.images:
      for cam in d.layout.cameras:
        batch[f"{cam}_rgb"] = d.steps[f"{cam}_rgb"][row]
    if self.skill_labels is not None:
      batch["skill_label"] = self.skill_labels[row].astype(np.int32)
    if self.instructions is not None:
      batch["instruction"] = self.instructions[d.task_id[ep]].astype(np.int32)
    return batch

  def device_batch(self, step: int) -> dict:
    local = self.numpy_batch(step, local=True)
    return {k: jax.make_array_from_process_local_data(self.sharding, v) for k, v in local.items()}

  def iterate(self, start_step: int = 0, num_steps: int | None = None, prefetch: int = 2) -> Iterator[dict]:
    """Device batches from `start_step`, built `prefetch` ahead on a thread."""
    end = None if num_steps is None else start_step + num_steps
    q: queue.Queue = queue.Queue(maxsize=max(1, prefetch))
    stop = threading.Event()

    def produce():
      step = start_step
      try:
        while not stop.is_set() and (end is None or step < end):
          item = self.device_batch(step)
          while not stop.is_set():
            try:
              q.put(item, timeout=0.1)
              break
            except queue.Full:
              continue
          step += 1
        q.put(None)
      except BaseException as e:  # noqa: BLE001  hand the error to the consumer
        q.put(e)

    worker = threading.Thread(target=produce, daemon=True, name="chunk-loader")
    worker.start()
    try:
      while True:
        t0 = time.perf_counter()
        item = q.get()
        self.wait_s += time.perf_counter() - t0
        if item is None:
          return
        if isinstance(item, BaseException):
          raise item
        yield item
    finally:  # close() or exhaustion: stop the producer before returning
      stop.set()
      worker.join(timeout=10)
