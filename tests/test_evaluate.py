"""Evaluation engine: the expert reproduced through it, NaN isolation, devices, videos, ensembling, tables."""

import dataclasses
import textwrap

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import rollout as env_rollout
from envs.batched import BatchedEnv
from skillplug_jax.evaluate import protocol, tables
from skillplug_jax.evaluate.policy_controller import policy_controller, temporal_ensemble
from skillplug_jax.evaluate.rollout import evaluate, expert_controller
from skillplug_jax.model import config as model_config
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop
from skillplug_jax.train import config as train_config
from host_devices import run_on_host_devices

TASK = "jujube_pick"


@pytest.fixture(scope="module")
def benv():
  return envs.make(TASK, num_envs=3)


def test_expert_through_engine_reproduces_expert(benv):
  keys = env_rollout.reset_keys(4, 3)
  ref = env_rollout.run_expert(benv, keys)
  got = evaluate(benv, expert_controller(benv), keys)
  assert ref.success.all()
  np.testing.assert_array_equal(got.success, ref.success)
  np.testing.assert_array_equal(got.first_success_step, ref.first_success_step)
  np.testing.assert_array_equal(got.queries, ref.first_success_step)  # one query per step until success
  assert not got.nan.any() and got.routing is None


class PoisonedEnv(BatchedEnv):
  """Episode 0's velocities become NaN before its 4th step: a physics blow-up."""

  def step(self, state, actions):
    d = state.pipeline_state
    hit = state.info["t"][0] == 3
    qvel = d.qvel.at[0].set(jnp.where(hit, jnp.nan, d.qvel[0]))
    return super().step(state.replace(pipeline_state=d.replace(qvel=qvel)), actions)


def test_nan_episode_fails_alone(benv):
  keys = env_rollout.reset_keys(4, 3)
  poisoned = PoisonedEnv(benv.env, 3)
  got = evaluate(poisoned, expert_controller(poisoned), keys)
  ref = evaluate(benv, expert_controller(benv), keys)
  assert got.nan.tolist() == [True, False, False]
  assert not got.success[0] and got.success[1:].all()
  np.testing.assert_array_equal(got.first_success_step[1:], ref.first_success_step[1:])


def test_two_devices_match_one_and_videos_follow_episodes(tmp_path):
  """The batch split over 2 (host) devices gives the same episodes as one
  device running it all; side-camera frames follow each episode to its end."""
  code = textwrap.dedent("""
      import jax, numpy as np
      import envs
      from envs import rollout as R
      from skillplug_jax.evaluate.rollout import evaluate, expert_controller, local_devices_for
      envs.quiet_warp()
      devices = local_devices_for(4)
      assert len(devices) == 2 and local_devices_for(1) is None
      assert local_devices_for(4, render=True) is None  # CPU shards would share one render context
      keys = R.reset_keys(4, 4)
      one = envs.make("jujube_pick", num_envs=4, render=True, image_size=(32, 32))
      ref = evaluate(one, expert_controller(one), keys, frames=2)
      two = envs.make("jujube_pick", num_envs=2)
      got = evaluate(two, expert_controller(two), keys, devices)
      assert ref.success.all(), ref
      for f in ("success", "first_success_step", "nan", "queries"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)
      assert got.steps_run == ref.steps_run
      for i in range(2):
        assert ref.frames[i].shape == (ref.first_success_step[i] + 1, 32, 32, 3), ref.frames[i].shape
        assert np.abs(np.diff(ref.frames[i].astype(int), axis=0)).sum() > 0  # the arm moves
      try:
        evaluate(one, expert_controller(one), R.reset_keys(4, 8), devices)
        raise SystemExit("a rendering batch was split over CPU devices")
      except ValueError as e:
        assert "render context" in str(e), e
      print("OK")
  """)
  run_on_host_devices(code, 2, timeout=900)


def test_videos_are_written_as_gifs(tmp_path):
  rng = np.random.default_rng(0)
  videos = [rng.integers(0, 255, (n, 16, 16, 3), dtype=np.uint8) for n in (5, 9)]
  protocol._write_videos(videos, tmp_path / "v", "jujube_pick")
  assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["jujube_pick_trial00.gif",
                                                                 "jujube_pick_trial01.gif"]
  back = iio.imread(tmp_path / "v" / "jujube_pick_trial01.gif", index=None)
  assert back.shape[0] == 9 and back.shape[1:3] == (16, 16)


def test_temporal_ensemble_matches_act_formula():
  rng = np.random.default_rng(0)
  chunk, k, steps = 4, 0.3, 7
  preds = rng.normal(size=(steps, 1, chunk, 2)).astype(np.float32)
  buf = jnp.zeros((1, chunk, chunk, 2))
  for t in range(steps):
    action, buf = temporal_ensemble(buf, jnp.asarray(preds[t]), t, k)
    # ACT: every chunk made at s <= t that covers t, oldest first, weights exp(-k i)
    cands = [preds[s, 0, t - s] for s in range(max(0, t - chunk + 1), t + 1)]
    w = np.exp(-k * np.arange(len(cands)))
    np.testing.assert_allclose(np.asarray(action[0]), (w[:, None] * np.stack(cands)).sum(0) / w.sum(),
                               rtol=1e-5, atol=1e-6)


def _tiny_policy(policy="skillplug"):
  m = dataclasses.replace(model_config.quick(), policy=policy, hidden=32, heads=2, ff=64, enc_layers=1,
                          dec_layers=1, cvae_enc_layers=1, num_skills=3, skill_latent_dim=8,
                          alignment_dim=16, chunk=8)
  cfg = train_config.TrainConfig(preset="quick", model=m)
  params = loop.init_params(cfg, jax.random.PRNGKey(1))
  stats = {"action": {"mean": list(envs.robot.HOME_QPOS), "std": [0.01] * 7},
           "joint_pos": {"mean": [0.0] * 7, "std": [1.0] * 7}}
  return m, params, stats


class ShortJujubePick(envs.TASKS[TASK]):
  time_limit_s = 1.0  # 20 control steps: an untrained policy runs to the limit quickly


def test_policy_in_the_loop_records_routing_and_queries():
  benv = BatchedEnv(ShortJujubePick(envs.EnvConfig(num_envs=3)), 3)
  m, params, stats = _tiny_policy()
  keys = env_rollout.reset_keys(9, 3)
  every = evaluate(benv, policy_controller(m, params, stats), keys)
  steps = every.steps_run
  assert steps == benv.episode_length  # an untrained policy does not succeed
  assert (every.queries == steps).all()
  assert every.routing.shape == (steps, 3, 3)
  np.testing.assert_allclose(every.routing.sum(-1), 1.0, rtol=1e-5)
  chunked = evaluate(benv, policy_controller(m, params, stats, query_every=5), keys)
  assert (chunked.queries == -(-steps // 5)).all()
  assert np.isnan(chunked.routing[1]).all() and not np.isnan(chunked.routing[5]).any()
  # another run of the same model reuses the compiled loop (its weights are an argument)
  leaves, tree = jax.tree.flatten(params)
  noise = [0.5 * jax.random.normal(jax.random.PRNGKey(i), x.shape) for i, x in enumerate(leaves)]
  other = jax.tree.unflatten(tree, [x + n for x, n in zip(leaves, noise)])  # router no longer uniform
  c1, c2 = policy_controller(m, params, stats), policy_controller(m, other, stats)
  assert c1.act is c2.act and c1.init is c2.init
  assert not np.allclose(evaluate(benv, c2, keys).routing, every.routing)
  fixed = evaluate(benv, policy_controller(m, params, stats, routing=[0.0, 1.0, 0.0]), keys)
  np.testing.assert_array_equal(fixed.routing[0], np.tile([0.0, 1.0, 0.0], (3, 1)))
  # the action the env receives is the unnormalised chunk: mean + std * prediction
  pred, _ = Policy(m).apply({"params": params}, {
      "joint_pos": jnp.zeros((1, 7)), "object_state": jnp.zeros((1, envs.OBJECT_STATE_DIM))},
      method=Policy.predict)
  assert np.isfinite(np.asarray(pred)).all()
  with pytest.raises(ValueError, match="query_every must be in 1..8"):
    policy_controller(m, params, stats, query_every=9)


def test_trials_are_paired_across_policies():
  a, b = protocol.trial_keys(1000, 10), protocol.trial_keys(1000, 10)
  np.testing.assert_array_equal(a, b)
  np.testing.assert_array_equal(protocol.trial_keys(1000, 4), a[:4])  # batch size does not matter
  e1, e2 = envs.make(TASK, num_envs=4), envs.make(TASK, num_envs=4)
  s1, s2 = e1.reset(a[:4]), e2.reset(b[:4])
  np.testing.assert_array_equal(s1.obs["object_state"], s2.obs["object_state"])
  # evaluation starts are not the demonstrations' starts (data seed 0)
  demo = e1.reset(env_rollout.reset_keys(0, 4))
  assert not np.allclose(demo.obs["object_state"], s1.obs["object_state"])


def test_success_table_mean_and_standard_error():
  rates = {"ACT": {"jujube_pick": [0.5, 0.7, 0.9], "kiwi_place": [0.1, 0.1, 0.4]},
           "ACT+SkillPlug": {"jujube_pick": [1.0], "kiwi_place": [0.5]}}
  t = tables.success_table(rates, ["jujube_pick", "kiwi_place"])
  mean, se = t["rows"]["ACT"]["cells"]["jujube_pick"]
  assert mean == pytest.approx(70.0) and se == pytest.approx(np.std([50, 70, 90], ddof=1) / np.sqrt(3))
  avg = [30.0, 40.0, 65.0]  # per-seed means over the two tasks
  mean, se = t["rows"]["ACT"]["cells"]["Avg."]
  assert mean == pytest.approx(np.mean(avg)) and se == pytest.approx(np.std(avg, ddof=1) / np.sqrt(3))
  assert t["rows"]["ACT+SkillPlug"]["cells"]["Avg."] == (75.0, None)
  md = tables.markdown(t)
  assert md.splitlines()[0] == "| Method | J.P. | K.P. | Avg. |"
  assert "| ACT | 70.0±11.5 | 20.0±10.0 | 45.0±10.4 |" in md
  assert "| ACT+SkillPlug | 100.0 | 50.0 | 75.0 |" in md
  assert tables.csv(t).splitlines()[2] == "ACT+SkillPlug,1,100.00,,50.00,,75.00,"
  with pytest.raises(ValueError, match="different numbers of seeds"):
    tables.success_table({"X": {"jujube_pick": [1.0], "kiwi_place": [1.0, 0.0]}}, ["jujube_pick", "kiwi_place"])


def test_eval_cli_expands_seed_templates_and_rejects_bad_ones(capsys):
  from skillplug_jax import cli
  assert cli._expand_seeds(["r/a_seed{seed}", "r/b_seed{seed}"], "0,2") == [
      "r/a_seed0", "r/a_seed2", "r/b_seed0", "r/b_seed2"]
  assert cli._expand_seeds(["r/a_seed0"], "") == ["r/a_seed0"]
  assert cli.main(["eval", "--ckpt", "r/a_seed{seed}", "--taskset", "jujube_pick"]) == 2
  assert "give --seeds" in capsys.readouterr().err
  assert cli.main(["eval", "--ckpt", "r/a_seed0", "--seeds", "0,x"]) == 2
  assert "comma-separated integers" in capsys.readouterr().err
  assert cli.main(["eval", "--ckpt", "r/missing_run", "--taskset", "jujube_pick"]) == 2
  assert "missing_run" in capsys.readouterr().err
