"""Demonstration datasets: RLDS round trip, chunk sampling, validation, atomic generation."""

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
import tensorflow_datasets as tfds

import envs
from envs import rollout
from skillplug_jax import cli
from skillplug_jax.data import demos, loader, normalization, rlds
from skillplug_jax.data.rlds import DatasetError
from host_devices import run_on_host_devices
from synthetic import synthetic_episode, write_synthetic

D = envs.OBJECT_STATE_DIM


@pytest.fixture(scope="module")
def image_dataset(tmp_path_factory):
  rng = np.random.default_rng(0)
  spec = rlds.DatasetSpec(("jujube_pick", "kiwi_place"), (16, 12))
  lengths = {("jujube_pick", 0): 7, ("jujube_pick", 3): 30, ("kiwi_place", 1): 4, ("kiwi_place", 2): 12}
  records = [rlds.EpisodeRecord(task, 5, idx, synthetic_episode(rng, n, images=(16, 12)))
             for (task, idx), n in lengths.items()]
  path = write_synthetic(tmp_path_factory.mktemp("ds"), "img", spec, records)
  return path, records


def test_round_trip_with_plain_tfds(image_dataset):
  path, records = image_dataset
  builder = tfds.builder_from_directory(str(path))  # no skillplug code needed to read it
  source = builder.as_data_source(split="train")
  assert len(source) == len(records)
  by_id = {rlds.episode_id(r.task, r.reset_index): r for r in records}
  seen = set()
  for i in range(len(source)):
    ex = source[i]
    meta = ex["episode_metadata"]
    rec = by_id[meta["episode_id"].decode()]
    seen.add(meta["episode_id"].decode())
    ep = rec.episode
    assert meta["task"].decode() == rec.task
    assert meta["task_id"] == ("jujube_pick", "kiwi_place").index(rec.task)
    assert meta["reset_seed"] == 5 and meta["reset_index"] == rec.reset_index
    assert meta["length"] == len(ep.action) and bool(meta["success"])
    steps = ex["steps"]
    assert len(steps) == len(ep.action)
    for t in range(len(steps)):
      s = steps[t]
      for k, v in ep.observation.items():
        np.testing.assert_array_equal(s["observation"][k], v[t])
      np.testing.assert_array_equal(s["action"], ep.action[t])
      assert bool(s["is_first"]) == (t == 0)
      assert bool(s["is_last"]) == (t == len(steps) - 1)
      assert bool(s["is_terminal"]) == (t == len(steps) - 1)
  assert seen == set(by_id)
  assert builder.info.metadata["tasks"] == ["jujube_pick", "kiwi_place"]


def test_loader_reads_every_step(image_dataset):
  path, records = image_dataset
  d = loader.load_demonstrations(path, images=True, image_size=(16, 12))
  assert d.num_episodes == len(records) and d.image_size == (16, 12)
  by_id = {rlds.episode_id(r.task, r.reset_index): r.episode for r in records}
  for e, eid in enumerate(d.episode_id):
    got, want = d.episode(e), by_id[eid]
    np.testing.assert_array_equal(got["action"], want.action)
    for k in ("joint_pos", "object_state", "side_rgb", "wrist_rgb"):
      np.testing.assert_array_equal(got[k], want.observation[k])
    assert d.tasks[d.task_id[e]] == eid.split("/")[0]
  # the statistics beside the dataset are those of all its steps
  all_actions = np.concatenate([r.episode.action for r in records])
  np.testing.assert_allclose(d.stats["action"]["mean"], all_actions.mean(0), rtol=1e-5, atol=1e-6)
  assert d.stats["num_steps"] == len(all_actions)


def test_chunk_padding_and_mask_at_episode_end(image_dataset):
  path, _ = image_dataset
  d = loader.load_demonstrations(path, images=True)
  chunk = 25
  ld = loader.ChunkLoader(d, batch_size=4, chunk=chunk, seed=3, images=True, normalize_object_state=False)
  mean = np.asarray(d.stats["action"]["mean"], np.float32)
  std = np.asarray(d.stats["action"]["std"], np.float32)
  checked_padding = False
  for step in range(6):
    batch = ld.numpy_batch(step)
    eps, ts = ld.indices(step)
    for row, (e, t) in enumerate(zip(eps, ts)):
      ep = d.episode(e)
      n = len(ep["action"])
      assert 0 <= t < n
      valid = min(chunk, n - t)
      assert batch["action_mask"][row, :valid].all() and not batch["action_mask"][row, valid:].any()
      np.testing.assert_allclose(batch["actions"][row, :valid], (ep["action"][t:t + valid] - mean) / std,
                                 rtol=1e-5, atol=1e-5)
      assert (batch["actions"][row, valid:] == 0).all()
      np.testing.assert_array_equal(batch["side_rgb"][row], ep["side_rgb"][t])
      np.testing.assert_array_equal(batch["object_state"][row], ep["object_state"][t])
      assert batch["task_id"][row] == d.task_id[e]
      checked_padding |= valid < chunk
  assert checked_padding
  # object state z-scored with the dataset's statistics when the model asks for it
  o_mean, o_std = (np.asarray(d.stats["object_state"][k], np.float32) for k in ("mean", "std"))
  normed = loader.ChunkLoader(d, batch_size=4, chunk=chunk, seed=3, images=True)  # the default
  eps, ts = normed.indices(0)
  want = (d.steps["object_state"][d.start[eps] + ts] - o_mean) / o_std
  np.testing.assert_allclose(normed.numpy_batch(0)["object_state"], want, rtol=1e-5, atol=1e-5)
  moving = np.asarray(d.stats["object_state"]["std"]) > normalization.MIN_STD
  assert moving.any()
  every = (d.steps["object_state"] - o_mean) / o_std
  np.testing.assert_allclose(every.mean(0), 0.0, atol=1e-4)
  np.testing.assert_allclose(every.std(0)[moving], 1.0, rtol=1e-3)


def test_sampling_follows_act_epochs_and_is_deterministic(image_dataset):
  path, _ = image_dataset
  d = loader.load_demonstrations(path)
  n = d.num_episodes
  a = loader.ChunkLoader(d, batch_size=2, seed=7)
  b = loader.ChunkLoader(d, batch_size=2, seed=7)
  c = loader.ChunkLoader(d, batch_size=2, seed=8)
  for epoch in range(3):  # every episode exactly once per epoch
    eps = np.concatenate([a.indices(s)[0] for s in range(epoch * n // 2, (epoch + 1) * n // 2)])
    assert sorted(eps) == list(range(n))
  for step in (0, 5, 1, 17):  # random access: a batch depends on (seed, step) only
    for k, v in a.numpy_batch(step).items():
      np.testing.assert_array_equal(v, b.numpy_batch(step)[k])
  differs = any(not np.array_equal(a.numpy_batch(s)["actions"], c.numpy_batch(s)["actions"]) for s in range(4))
  assert differs
  # few-shot: fewer episodes than the batch still gives full batches, from all episodes
  big = loader.ChunkLoader(d, batch_size=10, seed=0)
  assert big.numpy_batch(0)["actions"].shape == (10, 25, 7)
  assert set(big.indices(0)[0]) == set(range(n))
  # the prefetching iterator yields the same batches as random access
  got = list(a.iterate(start_step=3, num_steps=3))
  for i, batch in enumerate(got):
    np.testing.assert_array_equal(np.asarray(batch["actions"]), a.numpy_batch(3 + i)["actions"])


@pytest.mark.slow
def test_batches_shard_over_four_devices(image_dataset):
  path, _ = image_dataset
  code = textwrap.dedent(f"""
      import numpy as np, jax
      from skillplug_jax.data import loader
      assert jax.device_count() == 4
      d = loader.load_demonstrations({str(path)!r})
      ld = loader.ChunkLoader(d, batch_size=8, seed=1)
      it = ld.iterate()
      b = next(it)
      it.close()  # stops the prefetch thread
      ref = ld.numpy_batch(0)
      for k, v in b.items():
        assert len(v.addressable_shards) == 4, k
        assert v.addressable_shards[0].data.shape[0] == 2, k
        np.testing.assert_array_equal(np.asarray(v), ref[k])
      try:
        loader.ChunkLoader(d, batch_size=6)
      except ValueError as e:
        assert "does not split over 4 devices" in str(e)
      else:
        raise AssertionError("batch 6 over 4 devices accepted")
      print("OK")
  """)
  run_on_host_devices(code, 4, timeout=300)


# ---- validation -------------------------------------------------------------

def test_missing_and_incomplete_dataset(tmp_path):
  with pytest.raises(DatasetError, match="no dataset at"):
    loader.load_demonstrations(tmp_path / "nope")
  half = tmp_path / "half"
  half.mkdir()
  (half / "features.json").write_text("{}")
  with pytest.raises(DatasetError, match="not a complete dataset"):
    loader.load_demonstrations(half)


def test_datasets_of_an_older_recording_format_are_refused(tmp_path):
  """Format 1.0.0 episodes were cut before the release: never train on them silently."""
  rng = np.random.default_rng(2)
  path = write_synthetic(tmp_path, "old", rlds.DatasetSpec(("jujube_pick",), None),
                         [rlds.EpisodeRecord("jujube_pick", 0, 0, synthetic_episode(rng, 5))])
  assert loader.load_demonstrations(path).num_episodes == 1
  (path / rlds.CHECKSUMS).unlink()  # as written then: before checksums were kept
  info = path / "dataset_info.json"
  info.write_text(json.dumps({**json.loads(info.read_text()), "version": "1.0.0"}))
  with pytest.raises(DatasetError, match=f"dataset format 1.0.0, this code reads {rlds.FORMAT_VERSION}"):
    loader.load_demonstrations(path)


def test_image_and_task_mismatch(image_dataset, tmp_path):
  path, _ = image_dataset
  with pytest.raises(DatasetError, match=r"images are 16x12 \(HxW\), the config expects 64x64"):
    loader.load_demonstrations(path, images=True, image_size=(64, 64))
  with pytest.raises(DatasetError, match="has no task"):
    loader.load_demonstrations(path, tasks=("stack_block",))
  rng = np.random.default_rng(1)
  state = write_synthetic(tmp_path, "state", rlds.DatasetSpec(("jujube_pick",), None),
                          [rlds.EpisodeRecord("jujube_pick", 0, 0, synthetic_episode(rng, 5))])
  with pytest.raises(DatasetError, match="state-only"):
    loader.load_demonstrations(state, images=True)


def test_empty_task_and_nan_actions(tmp_path):
  rng = np.random.default_rng(2)
  spec = rlds.DatasetSpec(("jujube_pick", "kiwi_place"), None)
  only_one = write_synthetic(tmp_path, "one", spec,
                             [rlds.EpisodeRecord("jujube_pick", 0, 0, synthetic_episode(rng, 5))])
  with pytest.raises(DatasetError, match="no episodes for task.*kiwi_place"):
    loader.load_demonstrations(only_one)
  bad = synthetic_episode(rng, 6)
  bad.action[3, 2] = np.nan
  nan_ds = write_synthetic(tmp_path, "nan", rlds.DatasetSpec(("jujube_pick",), None),
                           [rlds.EpisodeRecord("jujube_pick", 0, 4, bad)], stats=False)
  with pytest.raises(DatasetError, match="jujube_pick/000004 has non-finite actions"):
    loader.load_demonstrations(nan_ds)


def _edit_step_features(path: Path, edit) -> None:
  with open(path / "features.json") as f:
    feats = json.load(f)
  edit(feats["featuresDict"]["features"]["steps"]["sequence"]["feature"]["featuresDict"]["features"])
  with open(path / "features.json", "w") as f:
    json.dump(feats, f)


def test_wrong_fields_and_action_dimension(image_dataset, tmp_path):
  import shutil
  path, _ = image_dataset
  no_terminal, short_action = tmp_path / "a", tmp_path / "b"
  shutil.copytree(path, no_terminal)
  shutil.copytree(path, short_action)
  for d in (no_terminal, short_action):  # as written by another tool, without checksums
    (d / rlds.CHECKSUMS).unlink()
  _edit_step_features(no_terminal, lambda steps: steps.pop("is_terminal"))
  with pytest.raises(DatasetError, match="missing fields \\['is_terminal'\\]"):
    loader.load_demonstrations(no_terminal)

  def six(steps):
    steps["action"]["tensor"]["shape"]["dimensions"] = ["6"]
  _edit_step_features(short_action, six)
  with pytest.raises(DatasetError, match="action has shape \\(6,\\), expected \\(7,\\)"):
    loader.load_demonstrations(short_action)


def test_corrupt_statistics(image_dataset, tmp_path):
  path, records = image_dataset
  copy = tmp_path / "copy"
  import shutil
  shutil.copytree(path, copy)
  (copy / rlds.CHECKSUMS).unlink()  # a dataset without checksums (older, or another tool's)
  (copy / normalization.STATS_FILE).write_text('{"action": {"mean": [0]}}')
  with pytest.raises(DatasetError, match="norm_stats.json is corrupt"):
    loader.load_demonstrations(copy)
  (copy / normalization.STATS_FILE).unlink()  # missing: recomputed and written beside it
  d = loader.load_demonstrations(copy)
  assert (copy / normalization.STATS_FILE).exists()
  assert normalization.read_stats(copy) == d.stats
  # recomputed from every step of every episode: mean, population std, min, max
  for key, steps in (("action", [r.episode.action for r in records]),
                     ("joint_pos", [r.episode.observation["joint_pos"] for r in records]),
                     ("object_state", [r.episode.observation["object_state"] for r in records])):
    x = np.concatenate(steps).astype(np.float64)
    mean = x.sum(0) / len(x)
    np.testing.assert_allclose(d.stats[key]["mean"], mean, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(d.stats[key]["std"], np.sqrt(((x - mean) ** 2).sum(0) / len(x)), rtol=1e-6)
    np.testing.assert_array_equal(d.stats[key]["min"], x.min(0))
    np.testing.assert_array_equal(d.stats[key]["max"], x.max(0))
  # a dataset from before object state was normalised: its statistics are made at load time
  legacy = {k: v for k, v in d.stats.items() if k != "object_state"}
  (copy / normalization.STATS_FILE).write_text(json.dumps(legacy))
  assert loader.load_demonstrations(copy).stats == d.stats
  assert d.stats["num_steps"] == sum(len(r.episode.action) for r in records)
  # a joint the experts never move: its std is clipped to MIN_STD, not 0 (no division by zero)
  still = normalization.stats_of(np.tile([[0.5] * 6 + [1.0]], (4, 1)) + np.arange(4)[:, None] * np.eye(7)[0],
                                 np.zeros((4, 7)))
  assert still["action"]["std"] == pytest.approx([np.std([0.5, 1.5, 2.5, 3.5])] + [normalization.MIN_STD] * 6)
  assert still["joint_pos"]["std"] == [normalization.MIN_STD] * 7


# ---- generation with the real experts ---------------------------------------

def test_demos_generate_resume_and_reuse(tmp_path, monkeypatch):
  cfg = demos.DemoConfig(taskset="jujube_pick", demos=2, images=False, batch=2, seed=0)

  def killed(*a, **k):
    raise KeyboardInterrupt("killed while writing")

  monkeypatch.setattr(rlds, "write_dataset", killed)
  with pytest.raises(KeyboardInterrupt):
    demos.make_demos(cfg, out=tmp_path, progress=False)
  assert not demos.dataset_path(cfg, tmp_path).exists()  # nothing half-written loads
  with pytest.raises(DatasetError):
    loader.load_demonstrations(demos.dataset_path(cfg, tmp_path))
  monkeypatch.undo()

  def no_simulation(*a, **k):
    raise AssertionError("staged task simulated again")

  monkeypatch.setattr(demos, "_generate_task", no_simulation)
  path = demos.make_demos(cfg, out=tmp_path, progress=False)  # resumes from the staged task
  d = loader.load_demonstrations(path, tasks=("jujube_pick",))
  assert d.num_episodes == 2 and d.image_size is None
  meta = tfds.builder_from_directory(str(path)).info.metadata
  assert meta["per_task"]["jujube_pick"]["kept"] == 2
  # the physics it came from is in its name and metadata (auto: the C engine on a CPU)
  assert path.name.endswith("_mujoco") and meta["backend"] == "mujoco" and meta["renderer"] is None
  assert meta["per_task"]["jujube_pick"]["expert_success_rate"] == 1.0
  assert 0 <= meta["per_task"]["jujube_pick"]["solver_iterations_limit_episodes"] <= 2  # counted, not printed
  assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # staging cleaned up
  # each kept episode is a success whose last step is terminal, and its
  # first observation is the seeded reset state
  source = tfds.builder_from_directory(str(path)).as_data_source(split="train")
  benv = envs.make("jujube_pick", num_envs=1)
  for i in range(len(source)):
    ex = source[i]
    assert ex["episode_metadata"]["success"]
    steps = ex["steps"]
    assert steps[len(steps) - 1]["is_terminal"]
    idx = int(ex["episode_metadata"]["reset_index"])
    reset = benv.reset(rollout.reset_keys(0, 1, offset=idx))
    np.testing.assert_allclose(steps[0]["observation"]["object_state"],
                               np.asarray(envs.padded_object_state(reset.obs["object_state"]))[0], atol=1e-6)
  assert demos.make_demos(cfg, out=tmp_path, progress=False) == path  # reused, not regenerated
  rc = cli.main(["demos", "--taskset", "jujube_pick", "--demos", "2", "--batch", "2",
                 "--state-only", "--out", str(tmp_path)])
  assert rc == 0


def test_demos_cli_rejects_unknown_taskset(tmp_path, capsys):
  assert cli.main(["demos", "--taskset", "nope", "--demos", "1", "--out", str(tmp_path)]) == 2
  assert "unknown taskset 'nope'" in capsys.readouterr().err
