"""Demonstrations on disk: one TensorFlow-Datasets dataset in RLDS layout.

Each record is an episode: `steps` (observation, action, reward, discount,
is_first, is_last, is_terminal) and `episode_metadata` (task, reset seed and
index, length, expert success). Files are ArrayRecord, so the dataset is
written and read back without TensorFlow (`tfds.builder_from_directory(path)
.as_data_source()`), and any RLDS tool can read it. Images are PNG, encoded
through PIL.

Step t holds the observation the expert saw and the action it then sent. The
last step of an episode is its last action; `is_terminal` is set there when
the episode ended in success.

The writer seals a dataset with a manifest of its files' checksums
(`skillplug_checksums.json`, `write_checksums`) before the rename that
publishes it; `open_dataset` compares every file with it. ArrayRecord's own
checks catch changed bytes in the records, but the JSON beside them
(norm_stats.json, dataset_info.json, metadata.json) has none: a flipped digit
there parses and changes the data's normalisation or its split without a word.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np
import PIL.Image
import tensorflow_datasets as tfds

import envs
from envs.libero import layout as libero_layout
from envs.robot import CAMERAS
from skillplug_jax import checksums
from skillplug_jax.data.recording import Episode

ACTION_DIM = envs.robot.ACTION_DIM
# 2.0.0: episodes run until the completion predicate has held for 0.5 s (through
# the release); 1.0.0 episodes were cut at the first step a looser check passed.
FORMAT_VERSION = "3.0.0"
BUILDER_NAME = "skillplug_demos"
CHECKSUMS = "skillplug_checksums.json"


class DatasetError(ValueError):
  """A dataset is missing, corrupt, or does not match what the caller needs."""


class Layout(NamedTuple):
  """The observation and action a benchmark's datasets hold: low-dim fields with their widths (in
  order), the cameras, and whether an episode carries a language instruction."""
  name: str
  state: tuple[tuple[str, int], ...]
  cameras: tuple[str, ...]
  action_dim: int
  language: bool
  action_meaning: str


# Our DISCOVERSE rebuild: joint targets; LIBERO: OSC_POSE deltas (envs/libero/layout.py).
DISCOVERSE = Layout("discoverse", (("joint_pos", ACTION_DIM), ("object_state", envs.OBJECT_STATE_DIM)), CAMERAS,
                    ACTION_DIM, False, "6 joint targets + gripper opening")
LIBERO = Layout("libero", libero_layout.STATE, libero_layout.CAMERAS, 7, True,
                "end-effector delta position and axis-angle + gripper, LIBERO's OSC_POSE")
LAYOUTS = {layout.name: layout for layout in (DISCOVERSE, LIBERO)}


class DatasetSpec(NamedTuple):
  """What a dataset holds: its tasks, its image size (None: state only) and its layout's name."""
  tasks: tuple[str, ...]
  image_size: tuple[int, int] | None  # (height, width) of both cameras
  layout: str = "discoverse"


def layout_of(spec: DatasetSpec) -> Layout:
  if spec.layout not in LAYOUTS:
    raise DatasetError(f"unknown dataset layout {spec.layout!r}; known layouts: {', '.join(LAYOUTS)}")
  return LAYOUTS[spec.layout]


def features(spec: DatasetSpec) -> tfds.features.FeaturesDict:
  lay = layout_of(spec)
  obs = {k: tfds.features.Tensor(shape=(w,), dtype=np.float32) for k, w in lay.state}
  if spec.image_size is not None:
    h, w = spec.image_size
    for cam in lay.cameras:
      obs[f"{cam}_rgb"] = tfds.features.Image(shape=(h, w, 3), dtype=np.uint8, encoding_format="png")
  language = {"language_instruction": tfds.features.Text()} if lay.language else {}
  return tfds.features.FeaturesDict({
      "steps": tfds.features.Dataset({
          "observation": tfds.features.FeaturesDict(obs),
          "action": tfds.features.Tensor(shape=(lay.action_dim,), dtype=np.float32),
          "reward": tfds.features.Scalar(dtype=np.float32),
          "discount": tfds.features.Scalar(dtype=np.float32),
          "is_first": tfds.features.Scalar(dtype=np.bool_),
          "is_last": tfds.features.Scalar(dtype=np.bool_),
          "is_terminal": tfds.features.Scalar(dtype=np.bool_),
      }),
      "episode_metadata": tfds.features.FeaturesDict({
          "episode_id": tfds.features.Text(),
          "task": tfds.features.Text(),
          "task_id": tfds.features.Scalar(dtype=np.int32),
          "reset_seed": tfds.features.Scalar(dtype=np.int64),
          "reset_index": tfds.features.Scalar(dtype=np.int64),
          "length": tfds.features.Scalar(dtype=np.int32),
          "success": tfds.features.Scalar(dtype=np.bool_),
          **language,
      }),
  })


class EpisodeRecord(NamedTuple):
  """An episode with the metadata it is written with."""
  task: str
  reset_seed: int
  reset_index: int
  episode: Episode
  language: str = ""  # the instruction (layouts with language)


def rlds_example(spec: DatasetSpec, rec: EpisodeRecord) -> dict:
  lay = layout_of(spec)
  ep = rec.episode
  length = len(ep.action)
  steps = []
  for t in range(length):
    obs = {k: ep.observation[k][t] for k, _ in lay.state}
    if spec.image_size is not None:
      for cam in lay.cameras:
        obs[f"{cam}_rgb"] = PIL.Image.fromarray(ep.observation[f"{cam}_rgb"][t])
    last = t == length - 1
    steps.append(dict(observation=obs, action=ep.action[t],
                      reward=np.float32(last and ep.success), discount=np.float32(1.0),
                      is_first=t == 0, is_last=last, is_terminal=last and ep.success))
  meta = dict(episode_id=episode_id(rec.task, rec.reset_index), task=rec.task,
              task_id=spec.tasks.index(rec.task), reset_seed=rec.reset_seed,
              reset_index=rec.reset_index, length=length, success=ep.success)
  if lay.language:
    if not rec.language:
      raise ValueError(f"{rec.task}: a {lay.name} episode needs its language instruction")
    meta["language_instruction"] = rec.language
  return {"steps": steps, "episode_metadata": meta}


def episode_id(task: str, reset_index: int) -> str:
  return f"{task}/{reset_index:06d}"


class _Builder(tfds.core.GeneratorBasedBuilder):
  """Writes the episodes handed to it; reading goes through builder_from_directory."""

  VERSION = tfds.core.Version(FORMAT_VERSION)
  _checksums_path = None  # nothing is downloaded (and the lookup needs importlib_resources)
  RELEASE_NOTES = {"1.0.0": "Scripted-expert demonstrations, RLDS layout.",
                   "2.0.0": "Episodes recorded until success is declared (completion held 0.5 s).",
                   FORMAT_VERSION: "Physics backend and renderer recorded; contact impratio 1 (was 10)."}

  def __init__(self, *, spec: DatasetSpec, records: Callable[[], Iterable[EpisodeRecord]],
               metadata: dict, **kwargs):
    self._spec, self._records, self._metadata = spec, records, metadata
    super().__init__(**kwargs)

  def _info(self):
    return self.dataset_info_from_configs(
        features=features(self._spec),
        description="SkillPlug-JAX scripted-expert demonstrations (RLDS).",
        metadata=tfds.core.MetadataDict(self._metadata))

  def _split_generators(self, dl_manager):
    return {"train": self._generate_examples()}

  def _generate_examples(self) -> Iterator:
    for rec in self._records():
      yield episode_id(rec.task, rec.reset_index), rlds_example(self._spec, rec)

  # tfds prints "Downloading and preparing dataset ..." and "... downloaded and
  # prepared to ..." with termcolor, whatever its logging or absl verbosity.
  # These two hooks are all that prints them; nothing is downloaded here and the
  # caller reports where the dataset went. Errors still raise as before.
  def _log_download_bytes(self) -> None:
    pass

  def _log_download_done(self) -> None:
    pass


_Builder.name = BUILDER_NAME


@contextlib.contextmanager
def _tfds_bars_off():
  active = tfds.core.utils.tqdm_utils._active
  tfds.display_progress_bar(False)  # our own bar shows progress; tfds' would interleave
  try:
    yield
  finally:
    tfds.display_progress_bar(active)


def write_dataset(build_root: str | os.PathLike, spec: DatasetSpec,
                  records: Callable[[], Iterable[EpisodeRecord]], metadata: dict) -> Path:
  """Build the dataset under `build_root`; return its version directory.

  tfds writes into an `incomplete.*` directory and renames it when done, so
  a killed build leaves nothing that loads. The caller moves the returned
  directory to its final place (one rename: atomic too).
  """
  metadata = {**metadata, "tasks": list(spec.tasks), "layout": spec.layout,
              "image_size": None if spec.image_size is None else list(spec.image_size)}
  builder = _Builder(spec=spec, records=records, metadata=metadata,
                     data_dir=os.fspath(build_root), file_format="array_record")
  with _tfds_bars_off():
    builder.download_and_prepare(download_config=tfds.download.DownloadConfig(try_download_gcs=False))
  return Path(builder.data_dir)


def write_checksums(dataset_dir: str | os.PathLike) -> None:
  """Checksum every file of a finished dataset (its statistics too): the last write before the
  rename that publishes it, so a published dataset always has its manifest."""
  checksums.write_manifest(dataset_dir, CHECKSUMS)


# ---- reading ----------------------------------------------------------------

REQUIRED_STEP_FIELDS = ("observation", "action", "is_first", "is_last", "is_terminal")
REQUIRED_META_FIELDS = ("task", "task_id", "length", "success")


def open_dataset(path: str | os.PathLike):
  """The tfds builder of a dataset directory, with errors that say what is wrong."""
  path = Path(path)
  if not path.is_dir():
    raise DatasetError(f"no dataset at {path} (generate one with `skillplug demos`)")
  if not (path / "dataset_info.json").is_file() or not (path / "features.json").is_file():
    raise DatasetError(f"{path} is not a complete dataset: dataset_info.json or features.json "
                       "is missing (an interrupted write?); delete it and generate it again")
  check_checksums(path)
  try:
    builder = tfds.builder_from_directory(os.fspath(path))
  except Exception as e:  # noqa: BLE001  tfds raises many kinds; name the file
    raise DatasetError(f"{path}: cannot read the dataset ({type(e).__name__}: {e})") from e
  if str(builder.info.version) != FORMAT_VERSION:
    raise DatasetError(
        f"{path} has dataset format {builder.info.version}, this code reads {FORMAT_VERSION} "
        f"({_Builder.RELEASE_NOTES.get(FORMAT_VERSION)}). "
        f"{regenerate_advice(path, builder.info.metadata)}")
  check_data_files(builder)
  return builder


def check_data_files(builder) -> None:
  """Open each ArrayRecord data file's footer (its record index, not its records).

  A truncated, missing or overwritten file fails here, with its name, instead
  of deep in the ArrayRecord library at the first read ("ArrayRecord file
  should be at least 64KB big"). The record count must match dataset_info.json.
  """
  if builder.info.file_format != tfds.core.FileFormat.ARRAY_RECORD:
    return
  adapter = tfds.core.file_adapters.ArrayRecordFileAdapter
  for split in builder.info.splits.values():
    for file, expected in zip(split.filepaths, split.shard_lengths):
      try:
        found = adapter.num_examples(file)
      except Exception as e:  # noqa: BLE001  the ArrayRecord reader raises RuntimeError with its reason
        reason = f"the ArrayRecord reader cannot open it: {_reason(e)}"
        raise DatasetError(damaged_file_message(builder, file, reason)) from e
      if found != expected:
        raise DatasetError(damaged_file_message(
            builder, file, f"it holds {found} records, dataset_info.json says {expected}"))


def check_checksums(path: Path) -> None:
  """Compare every file of a dataset with its checksum manifest, before tfds reads any.

  A changed, truncated or missing file raises DatasetError naming it. A dataset
  without a manifest (written before checksums were kept, or by another tool)
  is read with the readers' own checks alone. Hashing costs about a second per
  GB, little next to decoding the episodes.
  """
  if not (path / CHECKSUMS).is_file():
    return
  found = checksums.problems(path, CHECKSUMS)
  if not found:
    return
  (file, what), more = found[0], (f"; {len(found) - 1} more files differ" if len(found) > 1 else "")
  damaged = {f for f, _ in found}
  try:  # the generator's settings, for the command that writes the dataset again
    metadata = None if path / "metadata.json" in damaged else json.loads((path / "metadata.json").read_bytes())
  except (OSError, ValueError):
    metadata = None
  raise DatasetError(f"dataset file {file} is damaged (it {what}{more}). {regenerate_advice(path, metadata)}")


def damaged_file_message(builder, file, reason: str) -> str:
  return (f"dataset file {file} is damaged ({reason}). "
          f"{regenerate_advice(Path(builder.data_dir), builder.info.metadata)}")


def regenerate_advice(path: Path, metadata) -> str:
  """What to run to write the dataset again, from the generator config kept in its metadata."""
  cfg = (metadata or {}).get("config")
  if not isinstance(cfg, dict) or not {"taskset", "demos", "seed"} <= set(cfg):
    return f"Delete {path} and write it again"
  args = [f"--taskset {cfg['taskset']}", f"--demos {cfg['demos']}"]
  size = cfg.get("image_size") or [64, 64]
  if not cfg.get("images", True):
    args.append("--state-only")
  elif size[0] == size[1]:
    args.append(f"--image-size {size[0]}")
  args.append(f"--seed {cfg['seed']}")
  if cfg.get("backend"):
    args.append(f"--backend {cfg['backend']}")
  args.append(f"--out {path.parent}")
  return (f"Delete {path} and generate it again: `skillplug demos {' '.join(args)}` "
          "(`skillplug pretrain` also regenerates a missing dataset)")


def _reason(e: BaseException) -> str:
  text = str(e).strip().splitlines()[0] if str(e).strip() else ""
  return f"{type(e).__name__}: {text}" if text else type(e).__name__


def spec_of(builder) -> DatasetSpec:
  """The dataset's tasks, image size and layout, checked against its features."""
  feats = builder.info.features
  meta = builder.info.metadata or {}
  name = meta.get("layout", DISCOVERSE.name)  # datasets written before layouts are DISCOVERSE's
  if name not in LAYOUTS:
    raise DatasetError(f"{builder.data_dir}: unknown dataset layout {name!r}; known layouts: {', '.join(LAYOUTS)}")
  lay = LAYOUTS[name]
  _check_fields(builder.data_dir, feats, lay)
  if "tasks" not in meta:
    raise DatasetError(f"{builder.data_dir}: metadata has no task list (not a skillplug dataset?)")
  obs = feats["steps"]["observation"]
  image_size = None
  if f"{lay.cameras[0]}_rgb" in obs:
    h, w, _ = obs[f"{lay.cameras[0]}_rgb"].shape
    image_size = (h, w)
  return DatasetSpec(tasks=tuple(meta["tasks"]), image_size=image_size, layout=name)


def _check_fields(where, feats, lay: Layout = DISCOVERSE):
  names = set(feats.keys())
  if "steps" not in names or "episode_metadata" not in names:
    raise DatasetError(f"{where}: not RLDS: expected 'steps' and 'episode_metadata', found {sorted(names)}")
  steps = feats["steps"]
  missing = [k for k in REQUIRED_STEP_FIELDS if k not in steps.keys()]
  missing += [f"observation/{k}" for k, _ in lay.state if k not in steps["observation"].keys()]
  missing += [f"episode_metadata/{k}" for k in REQUIRED_META_FIELDS + (("language_instruction",) if lay.language else ())
              if k not in feats["episode_metadata"].keys()]
  if missing:
    raise DatasetError(f"{where}: missing fields {missing}")
  adim = steps["action"].shape
  if adim != (lay.action_dim,):
    raise DatasetError(f"{where}: action has shape {adim}, expected ({lay.action_dim},) ({lay.action_meaning})")
  for k, width in lay.state:
    sdim = steps["observation"][k].shape
    if sdim != (width,):
      raise DatasetError(f"{where}: {k} has shape {sdim}, expected ({width},) (the {lay.name} layout)")


def read_episodes(builder) -> Iterator[tuple[dict, dict]]:
  """Yield (metadata, steps) per episode; steps are stacked numpy arrays.

  A record that cannot be read or decoded (damage inside a file whose footer
  is intact) raises DatasetError naming the file that holds it.
  """
  split = builder.info.splits["train"]
  ends = np.cumsum(split.shard_lengths)
  source = builder.as_data_source(split="train")
  for i in range(len(source)):
    try:
      ex = source[i]
      meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in ex["episode_metadata"].items()}
      steps = ex["steps"]
      rows = [steps[t] for t in range(len(steps))]
    except Exception as e:  # noqa: BLE001  ArrayRecord, protobuf and tfds decoding all raise their own kinds
      file = split.filepaths[min(int(np.searchsorted(ends, i, side="right")), len(ends) - 1)]
      reason = f"record {i} cannot be read: {_reason(e)}"
      raise DatasetError(damaged_file_message(builder, file, reason)) from e
    yield meta, _stack(rows)


def _stack(rows: list[dict]) -> dict:
  out = {}
  for k, v in rows[0].items():
    if isinstance(v, dict):
      out[k] = _stack([r[k] for r in rows])
    else:
      out[k] = np.stack([np.asarray(r[k]) for r in rows])
  return out
