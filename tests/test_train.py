"""The training loop: exact resume, 1 vs 4 devices, frozen groups, NaN and config errors."""

import os
import textwrap

import jax
import numpy as np
import pytest

from skillplug_jax import experiment, fewshot, losses
from skillplug_jax.data import loader as data_loader
from skillplug_jax.data import normalization, rlds
from skillplug_jax.train import checkpoint, config, loop, run_files
from skillplug_jax.train.scalars import read_metrics
from host_devices import run_on_host_devices
from synthetic import state_dataset_name, synthetic_episode, write_synthetic, write_two_task_demos

pytestmark = pytest.mark.slow  # every test here trains (and one starts four simulated devices)

TASKS = ("jujube_pick", "kiwi_place")
TARGET = "block_place"  # an unseen task for the few-shot runs


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  root = tmp_path_factory.mktemp("datasets")
  rng = np.random.default_rng(0)
  write_two_task_demos(root, rng, TASKS)
  # the unseen task's demos: other actions and joint positions, so other statistics
  target = []
  for i in range(3):
    ep = synthetic_episode(rng, int(rng.integers(8, 40)))
    ep.action[:] = 3.0 * ep.action + 2.0
    ep.observation["joint_pos"][:] = 4.0 * ep.observation["joint_pos"] - 1.0
    target.append(rlds.EpisodeRecord(TARGET, 0, i, ep))
  write_synthetic(root, state_dataset_name(TARGET), rlds.DatasetSpec((TARGET,), None), target)
  return root


def tiny(data_dir, workdir, policy="skillplug", *extra):
  cfg = experiment.preset("quick", policy)
  return config.override(cfg, [
      "taskset=jujube_pick,kiwi_place", "demos=3", f"data_dir={data_dir}", f"workdir={workdir}",
      "model.hidden=32", "model.heads=2", "model.ff=64", "model.enc_layers=1", "model.dec_layers=2",
      "model.cvae_enc_layers=1", "model.plug.num_skills=3", "model.plug.skill_latent_dim=8",
      "model.plug.alignment_dim=16", "model.chunk=10", "batch_size=4", "max_steps=6", "log_every=2",
      "ckpt_every=3", "warmup_steps=2", *extra])


def leaves(params):
  return jax.tree.leaves(jax.tree.map(np.asarray, params))


def test_resume_equals_straight_run(data_dir, tmp_path):
  straight = loop.train(tiny(data_dir, tmp_path / "straight"), progress=False)
  cfg = tiny(data_dir, tmp_path / "killed")
  loop.train(cfg, progress=False, stop_after=3)  # "killed" after the step-3 checkpoint
  assert checkpoint.manager(cfg.run_dir).latest_step() == 3
  loop.train(cfg, progress=False)  # resumes at 3, trains 3..6
  _, a, step_a = loop.load_params(straight)
  _, b, step_b = loop.load_params(cfg.run_dir)
  assert step_a == step_b == 6
  for x, y in zip(leaves(a), leaves(b)):
    np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)
  # the scalar log holds each step once, every loss term included
  rows = read_metrics(cfg.run_dir)
  assert [r["step"] for r in rows] == [2, 3, 4, 6]
  assert {"loss/rec", "loss/kl", "loss/bsa", "loss/sd", "loss/cvae_kl", "loss/loss"} <= set(rows[0])
  assert {"diag/usage_entropy", "diag/routing_entropy_per_query", "diag/effective_skills", "diag/task_skill_mi"} <= set(rows[0])
  assert not any(k.startswith("loss/diag") for k in rows[0])  # diagnostics are not loss terms
  assert any(name.startswith("events.out.tfevents") for name in os.listdir(cfg.run_dir / "tensorboard"))


def test_four_devices_match_one(data_dir, tmp_path):
  one = loop.train(tiny(data_dir, tmp_path / "one", "skillplug", "max_steps=2", "ckpt_every=2"), progress=False)
  code = textwrap.dedent(f"""
      import sys, jax
      sys.path.insert(0, {os.path.dirname(__file__)!r})
      from test_train import tiny
      from skillplug_jax.train import loop
      assert jax.device_count() == 4
      loop.train(tiny({str(data_dir)!r}, {str(tmp_path / 'four')!r}, "skillplug", "max_steps=2", "ckpt_every=2"),
                 progress=False)
      print("OK")
  """)
  run_on_host_devices(code, 4, timeout=600)
  # the same losses and gradient norms (the all-reduce only reorders sums)...
  (m1,), (m4,) = read_metrics(one), read_metrics(tmp_path / "four")
  assert m1.keys() == m4.keys()
  for k in m1:
    if k.startswith("loss/") or k == "train/grad_norm":
      np.testing.assert_allclose(m4[k], m1[k], rtol=1e-5, err_msg=k)
  # ...and the same parameters, up to Adam turning float noise in near-zero
  # gradients into updates of at most lr * |g| / (|g| + eps)
  _, a, _ = loop.load_params(one)
  _, b, _ = loop.load_params(tmp_path / "four")
  for x, y in zip(leaves(a), leaves(b)):
    np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4)


def _changed_groups(source, adapted) -> set:
  _, before, _ = loop.load_params(source)
  _, after, _ = loop.load_params(adapted)
  assert set(before) == set(after)
  return {g for g in before if not all(np.array_equal(x, y) for x, y in zip(leaves(before[g]), leaves(after[g])))}


def test_skillplug_fewshot_trains_router_and_head_on_source_statistics(data_dir, tmp_path, monkeypatch):
  """The paper's SkillPlug few-shot run (`fewshot_config`): router and action head train,
  every other group stays bit-identical, and the target's batches are normalised with
  the source run's statistics (those its frozen encoder learned on), not the target's."""
  src_cfg = tiny(data_dir, tmp_path / "src", "skillplug", "max_steps=3")
  source = loop.train(src_cfg, progress=False)
  few = fewshot.fewshot_config(src_cfg, source, TARGET, experiment.FewShot(taskset=TARGET, demos=3, steps=3))
  normalised_with = []
  real = data_loader.ChunkLoader
  monkeypatch.setattr(data_loader, "ChunkLoader",
                      lambda data, *a, **kw: (normalised_with.append(data.stats), real(data, *a, **kw))[1])
  loop.train(few, progress=False)
  assert _changed_groups(source, few.run_dir) == {"router", "action_head"}
  source_stats = run_files.read_stats(source)
  assert set(source_stats) >= {"action", "joint_pos", "object_state"}  # object state normalised too
  target_stats = normalization.read_stats(data_dir / state_dataset_name(TARGET))
  assert not np.allclose(target_stats["action"]["mean"], source_stats["action"]["mean"], atol=0.5)
  assert not np.allclose(target_stats["joint_pos"]["std"], source_stats["joint_pos"]["std"], atol=0.5)
  assert normalised_with == [source_stats]
  assert run_files.read_stats(few.run_dir) == source_stats  # the controller un-normalises with them too


def test_act_fewshot_end_to_end(data_dir, tmp_path):
  """ACT's few-shot run: only its action head trains, from the source's statistics, and
  the adapted run is evaluated closed loop into the few-shot tables."""
  source = loop.train(tiny(data_dir, tmp_path / "src", "act", "max_steps=3"), progress=False)
  out = fewshot.adapt_and_evaluate([source], TARGET, demos=3, trials=2, batch=2, steps=3, progress=False)
  (r,) = out["results"]
  assert (r["task"], r["trainable"], r["steps"]) == (TARGET, ["action_head"], 3)
  assert loop.load_params(r["run"])[2] == 3
  assert _changed_groups(source, r["run"]) == {"action_head"}  # encoder and CVAE bit-identical
  assert run_files.read_stats(r["run"]) == run_files.read_stats(source)
  assert len(r["trial_success"]) == len(r["trial_queries"]) == 2
  assert list(out["rows"]) == ["ACT"] and out["rows"]["ACT"]["seeds"] == [0]
  assert out["table"]["rows"]["ACT"]["cells"][TARGET][0] == 100 * r["success_rate"]


def test_nan_loss_stops_and_keeps_checkpoint(data_dir, tmp_path, monkeypatch):
  cfg = tiny(data_dir, tmp_path / "nan")
  loop.train(cfg, progress=False, stop_after=3)

  real = losses.total_loss

  def nan_loss(outputs, batch, weights):  # as if the physics fed the policy garbage
    loss, metrics = real(outputs, batch, weights)
    return loss * np.nan, {**metrics, "loss": loss * np.nan}

  monkeypatch.setattr(losses, "total_loss", nan_loss)
  with pytest.raises(loop.TrainingError, match="non-finite loss.*checkpoint \\(step 3\\)"):
    loop.train(cfg, progress=False)
  assert checkpoint.manager(cfg.run_dir).latest_step() == 3


def test_incompatible_checkpoint_and_bad_overrides(data_dir, tmp_path):
  cfg = tiny(data_dir, tmp_path / "run")
  loop.train(cfg, progress=False, stop_after=3)
  wider = config.override(cfg, ["model.hidden=64"])
  with pytest.raises(checkpoint.CheckpointError, match="model.hidden: 32 -> 64"):
    loop.train(wider, progress=False)
  # a fine-tune may add an adapter or fix the routing (FINE_TUNE_ADDITIONS), nothing else of the model
  moved = fewshot.fewshot_config(cfg, cfg.run_dir, TARGET, experiment.FewShot(
      taskset=TARGET, demos=3, steps=2, train_overrides=("model.plug.site=decoder",)))
  with pytest.raises(checkpoint.CheckpointError, match="has a different model: plug.site: 'encoder' -> 'decoder'"):
    loop.train(moved, progress=False)
  with pytest.raises(ValueError, match="unknown setting 'model.hiden'"):
    config.override(cfg, ["model.hiden=3"])
  with pytest.raises(ValueError, match="lr='fast'"):
    config.override(cfg, ["lr=fast"])
  with pytest.raises(ValueError, match="unknown config 'huge'"):
    experiment.preset("huge")
  assert config.override(cfg, ["loss.sd=0.5", "model.use_images=false"]).loss.sd == 0.5
