"""The training loop: exact resume, 1 vs 4 devices, frozen groups, NaN and config errors."""

import os
import sys
import textwrap

import jax
import numpy as np
import pytest

from skillplug_jax import fewshot, losses
from skillplug_jax.data import rlds
from skillplug_jax.train import checkpoint, config, loop
from skillplug_jax.train.scalars import read_metrics
from host_devices import run_on_host_devices
from synthetic import synthetic_episode, write_synthetic

TASKS = ("jujube_pick", "kiwi_place")


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  root = tmp_path_factory.mktemp("datasets")
  rng = np.random.default_rng(0)
  records = [rlds.EpisodeRecord(task, 0, i, synthetic_episode(rng, int(rng.integers(8, 40))))
             for task in TASKS for i in range(3)]
  write_synthetic(root, "jujube_pick+kiwi_place_3demos_state_seed0", rlds.DatasetSpec(TASKS, None), records)
  return root


def tiny(data_dir, workdir, policy="skillplug", *extra):
  cfg = config.preset("quick", policy)
  return config.override(cfg, [
      "taskset=jujube_pick,kiwi_place", "demos=3", f"data_dir={data_dir}", f"workdir={workdir}",
      "model.hidden=32", "model.heads=2", "model.ff=64", "model.enc_layers=1", "model.dec_layers=2",
      "model.cvae_enc_layers=1", "model.num_skills=3", "model.skill_latent_dim=8",
      "model.alignment_dim=16", "model.chunk=10", "batch_size=4", "max_steps=6", "log_every=2",
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


def test_frozen_groups_stay_bit_identical(data_dir, tmp_path):
  source = loop.train(tiny(data_dir, tmp_path / "src", "skillplug", "max_steps=3"), progress=False)
  few = tiny(data_dir, tmp_path / "few", "skillplug", f"init_from={source}", "trainable=router,action_head",
             "max_steps=3")
  loop.train(few, progress=False)
  _, before, _ = loop.load_params(source)
  _, after, _ = loop.load_params(few.run_dir)
  for group in before:
    same = all(np.array_equal(x, y) for x, y in zip(leaves(before[group]), leaves(after[group])))
    assert same == (group not in ("router", "action_head")), group
  # the frozen encoder keeps reading inputs normalised with the source run's statistics
  assert (few.run_dir / "norm_stats.json").read_text() == (source / "norm_stats.json").read_text()


def test_fewshot_configs_follow_the_paper(tmp_path):
  for policy, trainable in (("skillplug", ("action_head", "router")), ("act", ("action_head",))):
    src = config.preset("quick", policy)
    cfg = fewshot.fewshot_config(src, tmp_path / "src", "mouse_push", "discoverse_fewshot4", 10)
    assert cfg.trainable == trainable
    assert (cfg.taskset, cfg.data_taskset, cfg.demos) == ("mouse_push", "discoverse_fewshot4", 10)
    assert cfg.init_from == str(tmp_path / "src") and cfg.max_steps == fewshot.FEWSHOT_STEPS["quick"]
    assert cfg.model == src.model and cfg.run_dir == tmp_path / "src_fewshot" / "mouse_push"


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
  with pytest.raises(ValueError, match="unknown setting 'model.hiden'"):
    config.override(cfg, ["model.hiden=3"])
  with pytest.raises(ValueError, match="lr='fast'"):
    config.override(cfg, ["lr=fast"])
  with pytest.raises(ValueError, match="unknown preset"):
    config.preset("huge")
  assert config.override(cfg, ["loss.sd=0.5", "model.use_images=false"]).loss.sd == 0.5
