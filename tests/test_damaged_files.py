"""Damaged files get named errors: dataset shards, checkpoints (eval fails, a resumed run falls back)."""

import json
import re
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

from skillplug_jax import checksums, cli
from skillplug_jax.data import loader, rlds
from skillplug_jax.data.rlds import DatasetError
from skillplug_jax.evaluate.policy_controller import load_controller
from skillplug_jax.train import checkpoint, loop, run_files
from skillplug_jax.train.scalars import read_metrics
from synthetic import synthetic_episode, write_synthetic, write_two_task_demos
from test_train import TASKS, tiny


def shard_of(dataset: Path) -> Path:
  (shard,) = dataset.glob("*.array_record-*")
  return shard


def truncate(path: Path, keep: float = 0.5) -> None:
  data = path.read_bytes()
  path.write_bytes(data[:int(len(data) * keep)])


def flip_byte(path: Path, offset: int, mask: int = 0xFF) -> None:
  data = bytearray(path.read_bytes())
  data[offset] ^= mask
  path.write_bytes(bytes(data))


def spread_offsets(path: Path, n: int) -> list[int]:
  """`n` offsets from the first byte to the last, evenly spaced (fewer in a smaller file)."""
  return sorted(set(np.linspace(0, path.stat().st_size - 1, n).astype(int).tolist()))


# ---- datasets -----------------------------------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  rng = np.random.default_rng(0)
  records = [rlds.EpisodeRecord("jujube_pick", 0, i, synthetic_episode(rng, 12)) for i in range(4)]
  return write_synthetic(tmp_path_factory.mktemp("ds"), "ds", rlds.DatasetSpec(("jujube_pick",), None), records)


def test_writing_a_dataset_prints_no_download_lines(tmp_path, capfd):
  rng = np.random.default_rng(1)
  records = [rlds.EpisodeRecord("jujube_pick", 0, 0, synthetic_episode(rng, 5))]
  path = write_synthetic(tmp_path, "quiet", rlds.DatasetSpec(("jujube_pick",), None), records)
  out, err = capfd.readouterr()
  assert "Downloading" not in out + err and "downloaded and prepared" not in out + err, out + err
  assert loader.load_demonstrations(path).num_episodes == 1


@pytest.mark.parametrize("damage", ["truncated", "empty", "missing"])
def test_unreadable_dataset_shard_is_named_when_opened(dataset, tmp_path, damage):
  copy = tmp_path / "ds"
  shutil.copytree(dataset, copy)
  shard = shard_of(copy)
  if damage == "truncated":
    truncate(shard, 0.01)  # as a copy cut short: the library said 'ArrayRecord file should be at least 64KB big'
  elif damage == "empty":
    shard.write_bytes(b"")
  else:
    shard.unlink()
  with pytest.raises(DatasetError, match=f"dataset file {re.escape(str(shard))} is damaged .*"
                                         f"Delete {re.escape(str(copy))} and "):
    rlds.open_dataset(copy)  # at open, before any record is read
  with pytest.raises(DatasetError, match=re.escape(shard.name)):
    loader.load_demonstrations(copy)


def test_corrupt_record_is_named_when_read(dataset, tmp_path):
  copy = tmp_path / "ds"
  shutil.copytree(dataset, copy)
  (copy / rlds.CHECKSUMS).unlink()  # without checksums (an older dataset): ArrayRecord's own checks
  shard = shard_of(copy)
  data = bytearray(shard.read_bytes())
  data[100:2000:7] = bytes(b ^ 0xFF for b in data[100:2000:7])  # inside the records; the footer is intact
  shard.write_bytes(bytes(data))
  rlds.open_dataset(copy)
  with pytest.raises(DatasetError, match=f"dataset file {re.escape(str(shard))} is damaged "
                                         "\\(record 0 cannot be read: "):
    loader.load_demonstrations(copy)


def test_every_byte_flip_in_a_dataset_is_caught_when_opened(dataset, tmp_path):
  """One byte (one bit, then all eight) flipped at offsets spread over every file of a dataset,
  each alone, densest in the shard's records and footer: open_dataset names the file at once."""
  copy = tmp_path / "ds"
  shutil.copytree(dataset, copy)
  files = sorted(p for p in copy.iterdir() if p.is_file() and p.name != rlds.CHECKSUMS)
  flips = 0
  for file in files:
    pristine = file.read_bytes()
    offsets = spread_offsets(file, 24)
    if file == shard_of(copy):  # the records fill the start, the footer the end; zero padding between
      used = np.nonzero(np.frombuffer(pristine, np.uint8))[0]
      offsets = sorted(set(offsets) | set(used[np.linspace(0, len(used) - 1, 60).astype(int)].tolist()))
    for offset in offsets:
      for mask in (0x01, 0xFF):
        flip_byte(file, offset, mask)
        with pytest.raises(DatasetError, match=f"dataset file {re.escape(str(file))} is damaged "
                                               "\\(it does not match its checksum"):
          rlds.open_dataset(copy)
        file.write_bytes(pristine)
        flips += 1
  assert flips > 250
  assert loader.load_demonstrations(copy).num_episodes == 4  # the files put back load


def test_a_flipped_digit_in_the_statistics_is_caught(dataset, tmp_path):
  """Without checksums one flipped bit in norm_stats.json loads other normalisation statistics
  without a word (ArrayRecord's checks cover the records only); with them it is named."""
  copy = tmp_path / "ds"
  shutil.copytree(dataset, copy)
  stats = copy / "norm_stats.json"
  text = stats.read_text()
  first = re.search(r"\d", text[text.index('"mean": ['):]).start() + text.index('"mean": [')
  offset = first + 2  # a digit of the first action mean: '0.37...' becomes '0.27...'
  flip_byte(stats, offset, 0x01)
  with pytest.raises(DatasetError, match=f"dataset file {re.escape(str(stats))} is damaged"):
    loader.load_demonstrations(copy)
  (copy / rlds.CHECKSUMS).unlink()
  assert loader.load_demonstrations(copy).stats != loader.load_demonstrations(dataset).stats


def test_regenerate_advice_repeats_the_generating_command(tmp_path):
  cfg = dict(taskset="jujube_pick", demos=2, images=False, image_size=[64, 64], seed=3, batch=2, backend="mujoco")
  advice = rlds.regenerate_advice(tmp_path / "name", {"config": cfg})
  assert f"Delete {tmp_path / 'name'} and generate it again: `skillplug demos --taskset jujube_pick --demos 2 " \
         f"--state-only --seed 3 --backend mujoco --out {tmp_path}`" in advice
  cfg.update(images=True, image_size=[32, 32])
  assert "--image-size 32 --seed 3" in rlds.regenerate_advice(tmp_path / "name", {"config": cfg})
  assert rlds.regenerate_advice(tmp_path / "x", {"test": True}) == f"Delete {tmp_path / 'x'} and write it again"


# ---- checkpoints --------------------------------------------------------------

@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  root = tmp_path_factory.mktemp("datasets")
  write_two_task_demos(root, np.random.default_rng(0), TASKS)
  return root


@pytest.fixture(scope="module")
def finished_run(data_dir, tmp_path_factory):
  """A tiny run trained to the end: checkpoints 3 and 6, and its final parameters."""
  run = loop.train(tiny(data_dir, tmp_path_factory.mktemp("runs") / "run"), progress=False)
  assert checkpoint.manager(run).all_steps() == [3, 6]
  _, params, _ = loop.load_params(run)
  return run, jax.tree.map(np.asarray, params)


def copy_run(run: Path, dst: Path) -> Path:
  shutil.copytree(run, dst)
  return dst


def largest_file(step_dir: Path) -> Path:
  return max((p for p in step_dir.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)


def largest_array_file(step_dir: Path) -> Path:
  return max((p for p in step_dir.glob("*/ocdbt.process_*/d/*") if p.is_file()), key=lambda p: p.stat().st_size)


# Which file is the largest differs between runs (OCDBT packs the arrays into
# a varying number of files, and the tiny model's _METADATA is as large), so
# each kind is damaged on purpose: arrays, orbax's JSON tree, and any largest.
@pytest.mark.parametrize("pick", [largest_array_file, lambda d: d / "default" / "_METADATA", largest_file],
                         ids=["array-file", "metadata", "largest"])
@pytest.mark.slow  # reads or resumes the module's trained run
def test_damaged_checkpoint_fails_evaluation_naming_it(finished_run, tmp_path, capsys, pick):
  run = copy_run(finished_run[0], tmp_path / "run")
  step6 = run / "checkpoints" / "6"
  bad = pick(step6)
  truncate(bad)
  with pytest.raises(checkpoint.DamagedCheckpoint,
                     match=f"checkpoint {re.escape(str(step6))} is damaged .*{bad.name} is truncated"
                           ".*from checkpoint 3"):
    load_controller(run)
  capsys.readouterr()
  rc = cli.main(["eval", "--runs", str(run), "--taskset", "jujube_pick", "--trials", "1", "--batch", "1"])
  err = capsys.readouterr().err
  assert rc == 2
  assert f"skillplug: error: checkpoint {step6} is damaged" in err and "Traceback" not in err, err
  assert (step6 / "default").is_dir()  # evaluation only reports; it moves nothing


@pytest.mark.slow  # reads or resumes the module's trained run
def test_corrupt_checkpoint_index_is_named(finished_run, tmp_path):
  run = copy_run(finished_run[0], tmp_path / "run")
  manifest = run / "checkpoints" / "6" / "default" / "manifest.ocdbt"
  data = bytearray(manifest.read_bytes())
  data[len(data) // 2] ^= 0xFF
  manifest.write_bytes(bytes(data))
  with pytest.raises(checkpoint.DamagedCheckpoint, match="manifest.ocdbt.*checksum"):
    loop.load_params(run)


@pytest.mark.slow  # reads or resumes the module's trained run
def test_checkpoint_of_another_model_is_not_called_damaged(finished_run, data_dir):
  wider = tiny(data_dir, "unused", "skillplug", "model.hidden=64")
  like = loop.init_params(wider, jax.random.PRNGKey(0))
  with pytest.raises(checkpoint.CheckpointError, match="does not fit this model: .* has shape") as info:
    loop.load_params(finished_run[0], like=like)
  assert not isinstance(info.value, checkpoint.DamagedCheckpoint)


@pytest.mark.slow  # reads or resumes the module's trained run
def test_evaluation_reads_the_parameters_without_an_optimizer(finished_run, monkeypatch):
  """load_params gets exactly the parameters that restoring the whole training state gets,
  and builds no optimiser to do so."""
  run = finished_run[0]
  cfg = run_files.read_config(run)
  params = loop.init_params(cfg, jax.random.PRNGKey(0))
  whole = loop.TrainState(jax.numpy.zeros((), "int32"), params, loop.optimizer(cfg, params, cfg.max_steps).init(params))
  mngr = checkpoint.manager(run)
  whole, whole_step, _ = checkpoint.restore_latest(mngr, whole)
  mngr.close()

  def no_optimizer(*args, **kwargs):
    raise AssertionError("load_params built an optimizer")

  monkeypatch.setattr(loop, "optimizer", no_optimizer)
  _, params, step = loop.load_params(run)
  assert step == whole_step == int(whole.step) == 6
  assert jax.tree.structure(params) == jax.tree.structure(whole.params)
  for x, y in zip(jax.tree.leaves(whole.params), jax.tree.leaves(params)):
    assert isinstance(y, jax.Array) and y.dtype == x.dtype
    np.testing.assert_array_equal(np.asarray(y), np.asarray(x))


@pytest.mark.parametrize("damage", ["truncated", "one-byte-flip", "step-metadata"])
@pytest.mark.slow  # reads or resumes the module's trained run
def test_resume_falls_back_to_the_previous_intact_checkpoint(finished_run, data_dir, tmp_path, capsys, damage):
  run, final = finished_run
  run = copy_run(run, tmp_path / "run")
  if damage == "truncated":
    truncate(largest_file(run / "checkpoints" / "6"))
  elif damage == "step-metadata":  # read by orbax when it opens the directory, before any restore
    meta = run / "checkpoints" / "6" / "_CHECKPOINT_METADATA"
    flip_byte(meta, meta.read_bytes().index(b"item_handlers") + 1, 0x01)
  else:  # found only by the checksums: orbax restores most such flips without a word
    bad = largest_array_file(run / "checkpoints" / "6")
    flip_byte(bad, bad.stat().st_size // 2)
  capsys.readouterr()
  loop.train(tiny(data_dir, run), progress=False)  # the same command again: resumes
  err = capsys.readouterr().err
  assert f"warning: checkpoint {run / 'checkpoints' / '6'} is damaged" in err
  assert f"moved it to {run / 'damaged_checkpoints' / '6'} and resuming from checkpoint 3" in err
  assert (run / "damaged_checkpoints" / "6" / "default").is_dir()
  assert checkpoint.manager(run).all_steps() == [3, 6]
  # steps 3..6 trained again give the parameters the undamaged run ended with
  _, params, step = loop.load_params(run)
  assert step == 6
  for x, y in zip(jax.tree.leaves(final), jax.tree.leaves(jax.tree.map(np.asarray, params))):
    np.testing.assert_array_equal(y, x)  # bit-identical, as after a kill
  assert [r["step"] for r in read_metrics(run)] == [2, 3, 4, 6]  # each step logged once


@pytest.mark.slow  # reads or resumes the module's trained run
def test_no_intact_checkpoint_left(finished_run, data_dir, tmp_path):
  run = copy_run(finished_run[0], tmp_path / "run")
  for step in (3, 6):
    truncate(largest_file(run / "checkpoints" / str(step)))
  with pytest.raises(checkpoint.CheckpointError,
                     match=f"no intact checkpoint in {re.escape(str(run / 'checkpoints'))}: 6 is damaged "
                           f".*; 3 is damaged .*Delete {re.escape(str(run / 'checkpoints'))} to train"):
    loop.train(tiny(data_dir, run), progress=False)
  assert checkpoint.manager(run).all_steps() == [3, 6]  # nothing moved when nothing can be resumed


# ---- checksums ----------------------------------------------------------------

def read_files(step_dir: Path) -> list[Path]:
  """Every file of a checkpoint but orbax's commit markers (only their presence counts)."""
  return sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != "commit_success.txt")


def training_state(run: Path) -> loop.TrainState:
  """The shape of what a resumed run restores: step, parameters and optimiser state."""
  cfg = run_files.read_config(run)
  params = loop.init_params(cfg, jax.random.PRNGKey(0))
  return loop.TrainState(jax.numpy.zeros((), "int32"), params, loop.optimizer(cfg, params, cfg.max_steps).init(params))


@pytest.mark.slow  # reads or resumes the module's trained run
def test_checkpoints_hold_checksums_of_their_files(finished_run):
  for step in (3, 6):
    item = finished_run[0] / "checkpoints" / str(step) / "default"
    listed = set(json.loads((item / checkpoint.CHECKSUMS).read_text())["files"])
    on_disk = {p.relative_to(item).as_posix() for p in item.rglob("*") if p.is_file()}
    assert listed == on_disk - {checkpoint.CHECKSUMS, "commit_success.txt"}
    assert checksums.problems(item, checkpoint.CHECKSUMS) == []


@pytest.mark.slow  # reads or resumes the module's trained run
def test_every_byte_flip_in_a_checkpoint_is_caught(finished_run, tmp_path):
  """One byte flipped at 24 offsets across each file a restore reads (each flip alone): evaluation
  and a resumed run's restore both raise DamagedCheckpoint naming the file. Without the
  checksums most flips in the array files restore without a word (docs/training.md)."""
  run = copy_run(finished_run[0], tmp_path / "run")
  step6 = run / "checkpoints" / "6"
  state = training_state(run)
  params = state.params
  mngr = checkpoint.manager(run)
  flips = 0
  try:
    for file in read_files(step6):
      pristine = file.read_bytes()
      for offset in spread_offsets(file, 24):
        flip_byte(file, offset)
        with pytest.raises(checkpoint.DamagedCheckpoint, match=re.escape(file.name)):
          checkpoint.restore_params(run, params)
        with pytest.raises(checkpoint.DamagedCheckpoint, match=re.escape(file.name)):
          checkpoint.restore(mngr, 6, state)
        file.write_bytes(pristine)
        flips += 1
  finally:
    mngr.close()
  assert flips > 300
  checkpoint.restore_params(run, params)  # the files put back restore


@pytest.mark.slow  # reads or resumes the module's trained run
def test_a_byte_flip_orbax_misses_is_caught(finished_run, tmp_path, monkeypatch):
  """A flip in the largest array file that orbax alone restores into other numbers (most do:
  docs/training.md), found by trying offsets without the checksums; with them it is named."""
  run = copy_run(finished_run[0], tmp_path / "run")
  state = training_state(run)
  mngr = checkpoint.manager(run)
  ref = jax.tree.leaves(jax.tree.map(np.asarray, checkpoint.restore(mngr, 6, state)))
  file = largest_array_file(run / "checkpoints" / "6")
  pristine = file.read_bytes()
  try:
    with monkeypatch.context() as m:
      m.setattr(checkpoint, "check_checksums", lambda path: None)
      for offset in spread_offsets(file, 40)[1:-1]:
        flip_byte(file, offset)
        try:
          got = jax.tree.leaves(jax.tree.map(np.asarray, checkpoint.restore(mngr, 6, state)))
          if any(not np.array_equal(x, y) for x, y in zip(ref, got)):
            break
        except checkpoint.DamagedCheckpoint:
          pass
        file.write_bytes(pristine)
      else:
        pytest.fail("without the checksums every flip was caught or harmless")
    with pytest.raises(checkpoint.DamagedCheckpoint, match=f"{re.escape(str(file))} does not match its checksum"):
      checkpoint.restore(mngr, 6, state)
  finally:
    mngr.close()


@pytest.mark.slow  # reads or resumes the module's trained run
def test_checkpoint_without_checksums_restores_with_a_note(finished_run, tmp_path, capsys):
  """Runs written before checksums were kept still evaluate and resume; a lost manifest of a
  checkpoint whose step metadata says it had one is damage."""
  run = copy_run(finished_run[0], tmp_path / "run")
  step6 = run / "checkpoints" / "6"
  (step6 / "default" / checkpoint.CHECKSUMS).unlink()
  with pytest.raises(checkpoint.DamagedCheckpoint, match=f"{checkpoint.CHECKSUMS} \\(its checksums\\) is missing"):
    loop.load_params(run)
  meta = json.loads((step6 / "_CHECKPOINT_METADATA").read_text())
  meta["custom_metadata"] = {}  # as orbax wrote it before
  (step6 / "_CHECKPOINT_METADATA").write_text(json.dumps(meta))
  capsys.readouterr()
  _, params, step = loop.load_params(run)
  assert step == 6
  assert f"note: checkpoint {step6} has no checksums" in capsys.readouterr().err


def test_checksums_are_written_before_the_checkpoint_appears(tmp_path, monkeypatch):
  """The manifest goes into orbax's temporary directory, so the rename that completes a
  checkpoint brings it: a kill never leaves a checkpoint without one."""
  seen = []
  write = checksums.write_manifest

  def spy(root, name, skip=()):
    seen.append((Path(root), (tmp_path / "checkpoints" / "1").exists()))
    return write(root, name, skip)

  monkeypatch.setattr(checksums, "write_manifest", spy)
  state = {"w": jax.numpy.arange(12.0).reshape(3, 4)}
  mngr = checkpoint.manager(tmp_path)
  checkpoint.save(mngr, 1, state)
  mngr.wait_until_finished()
  (root, final_existed), = seen
  assert "tmp" in root.name and not final_existed
  mngr.close()
  assert (tmp_path / "checkpoints" / "1" / "default" / checkpoint.CHECKSUMS).is_file()


@pytest.mark.slow  # reads or resumes the module's trained run
def test_a_flipped_bit_in_the_step_metadata_is_named(finished_run, tmp_path):
  """Orbax reads every step's _CHECKPOINT_METADATA when it lists the checkpoints (it writes that
  file after the items, outside their manifest); a flipped bit in a key was a bare ValueError."""
  run = copy_run(finished_run[0], tmp_path / "run")
  meta = run / "checkpoints" / "6" / "_CHECKPOINT_METADATA"
  flip_byte(meta, meta.read_bytes().index(b"item_handlers") + 1, 0x01)
  with pytest.raises(checkpoint.DamagedCheckpoint,
                     match=f"{re.escape(str(meta))} is corrupt .*Move or delete {re.escape(str(meta.parent))}"):
    loop.load_params(run)
