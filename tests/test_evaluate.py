"""Evaluation engine: the expert reproduced through it, NaN isolation, devices, videos, ensembling, tables."""

import dataclasses
import json
import textwrap
import time
from typing import NamedTuple

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import rollout as env_rollout
from envs.mujoco_batch import MujocoBatchEnv
from envs.env import SUCCESS_HOLD_STEPS
from skillplug_jax import experiment
from skillplug_jax.evaluate import groups, protocol, tables
from skillplug_jax.evaluate.policy_controller import policy_controller, temporal_ensemble
from envs.rollout import EpisodeResults, expert_controller, run_episodes
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop
from skillplug_jax.train import config as train_config
from host_devices import run_on_host_devices

TASK = "jujube_pick"


@pytest.fixture(scope="module")
def benv():
  return envs.make(TASK, num_envs=3, backend="mujoco")


@pytest.mark.parametrize("backend", ["mujoco", pytest.param("mjx-warp", marks=pytest.mark.slow)])
def test_engine_records_what_it_runs_on_both_backends(backend):
  """The engine's two loops (jitted while_loop on MJX-Warp, host loop on the C
  engine) count steps and queries alike, and a recorded run is the same run."""
  env = envs.make(TASK, num_envs=3, backend=backend)
  keys = env_rollout.reset_keys(4, 3)
  got = run_episodes(env, expert_controller(env), keys)
  rec = run_episodes(env, expert_controller(env), keys, record=True)
  assert got.success.all() and not got.nan.any() and got.routing is None
  for f in ("success", "first_success_step", "queries", "overflow"):
    np.testing.assert_array_equal(getattr(rec, f), getattr(got, f), err_msg=f)
  # one query per step until success is declared, after the predicate held for SUCCESS_HOLD_STEPS
  np.testing.assert_array_equal(got.queries, got.first_success_step + SUCCESS_HOLD_STEPS - 1)
  traj = rec.trajectory
  np.testing.assert_array_equal(traj.alive.sum(0), got.queries)  # a step recorded per query
  assert traj.action.shape == (got.steps_run, 3, 7) and got.steps_run == got.queries.max()
  np.testing.assert_allclose(traj.observation["joint_pos"][0], env.reset(keys).obs["joint_pos"], atol=1e-6)


class PoisonedEnv(MujocoBatchEnv):
  """Episode 0's velocities become NaN before its 4th step: a physics blow-up."""

  def step(self, state, actions):
    if int(state.info["t"][0]) == 3:
      self._saved["qvel"][0] = np.nan
    return super().step(state, actions)


def test_nan_episode_fails_alone(benv):
  keys = env_rollout.reset_keys(4, 3)
  poisoned = PoisonedEnv(benv.env, 3)
  got = run_episodes(poisoned, expert_controller(poisoned), keys)
  ref = run_episodes(benv, expert_controller(benv), keys)
  assert got.nan.tolist() == [True, False, False]
  assert not got.success[0] and got.success[1:].all()
  np.testing.assert_array_equal(got.first_success_step[1:], ref.first_success_step[1:])


@pytest.mark.slow
def test_two_devices_match_one_and_videos_follow_episodes(tmp_path):
  """The batch split over 2 (host) devices gives the same episodes as one
  device running it all; side-camera frames follow each episode to its end."""
  code = textwrap.dedent("""
      import jax, numpy as np
      import envs
      from envs import rollout as R
      from envs.env import SUCCESS_HOLD_STEPS
      from envs.rollout import expert_controller, local_devices_for, run_episodes as evaluate
      envs.quiet_warp()
      devices = local_devices_for(4)
      assert len(devices) == 2 and local_devices_for(1) is None
      assert local_devices_for(4, render=True) is None  # CPU shards would share one render context
      keys = R.reset_keys(4, 4)
      one = envs.make("jujube_pick", num_envs=4, render=True, image_size=(32, 32), backend="mjx-warp")
      ref = evaluate(one, expert_controller(one), keys, frames=2)
      two = envs.make("jujube_pick", num_envs=2, backend="mjx-warp")
      got = evaluate(two, expert_controller(two), keys, devices)
      assert ref.success.all(), ref
      for f in ("success", "first_success_step", "nan", "queries"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)
      assert got.steps_run == ref.steps_run
      for i in range(2):
        # the start, then every step to the one that declared the success
        assert ref.frames[i].shape == (ref.first_success_step[i] + SUCCESS_HOLD_STEPS, 32, 32, 3), ref.frames[i].shape
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
  protocol.write_videos(videos, tmp_path / "v", "jujube_pick")
  assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["jujube_pick_trial00.gif",
                                                                 "jujube_pick_trial01.gif"]
  back = iio.imread(tmp_path / "v" / "jujube_pick_trial01.gif", index=None)
  assert back.shape[0] == 9 and back.shape[1:3] == (16, 16)


def test_probe_sheet_stacks_each_modes_gif_in_order(tmp_path):
  """figures.probe_sheet: a row per routing mode (router, uniform, skill0, skill2, skill10), each
  the mode's own frames; no GIF of the task is a named error."""
  from figures import probe_sheet
  shades = {"skill10": 250, "skill2": 200, "uniform": 50, "router": 0, "skill0": 100}
  for mode, shade in shades.items():
    clip = np.full((4, 8, 8, 3), shade, np.uint8)
    clip[:, 0, 0] = np.arange(4)[:, None] * 60  # the frame's index, in one corner
    protocol.write_videos([clip], tmp_path / mode, "drawer_open")
  sheet, modes = probe_sheet.probe_sheet(tmp_path, "drawer_open", frames=4)
  assert modes == ["router", "uniform", "skill0", "skill2", "skill10"]
  assert sheet.shape == (5 * 8, 4 * 8, 3)
  for row, mode in enumerate(modes):
    assert abs(int(sheet[row * 8 + 4, 4, 0]) - shades[mode]) <= 8, mode  # GIF palettes are lossy
  assert [int(sheet[0, c * 8, 0]) // 50 for c in range(4)] == [0, 1, 2, 3]  # frames left to right
  with pytest.raises(ValueError, match="no laptop_close_trial00.gif"):
    probe_sheet.probe_sheet(tmp_path, "laptop_close")


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
  base = experiment.preset("quick").model
  m = dataclasses.replace(base, policy=policy, hidden=32, heads=2, ff=64, enc_layers=1, dec_layers=1,
                          cvae_enc_layers=1, chunk=8,
                          plug=dataclasses.replace(base.plug, num_skills=3, skill_latent_dim=8, alignment_dim=16))
  cfg = train_config.TrainConfig(preset="quick", model=m)
  params = loop.init_params(cfg, jax.random.PRNGKey(1))
  stats = {"action": {"mean": list(envs.robot.HOME_QPOS), "std": [0.01] * 7},
           "joint_pos": {"mean": [0.0] * 7, "std": [1.0] * 7},
           "object_state": {"mean": [0.0] * envs.OBJECT_STATE_DIM, "std": [1.0] * envs.OBJECT_STATE_DIM}}
  return m, params, stats


class ShortJujubePick(envs.TASKS[TASK]):
  time_limit_s = 1.0  # 20 control steps: an untrained policy runs to the limit quickly


def _router_on(m, params, trajectory):
  """The router's weights [T, B, K] on each recorded step's observation, recomputed outside the
  controller (the statistics of `_tiny_policy` normalise nothing: mean 0, std 1)."""
  obs = trajectory.observation
  t, b = obs["joint_pos"].shape[:2]
  flat = {"joint_pos": jnp.asarray(obs["joint_pos"].reshape(t * b, -1)),
          "object_state": envs.padded_object_state(jnp.asarray(obs["object_state"].reshape(t * b, -1)))}
  _, r = Policy(m).apply({"params": params}, flat, method=Policy.predict)
  return np.asarray(r).reshape(t, b, -1)


def test_policy_in_the_loop_records_routing_and_queries():
  benv = MujocoBatchEnv(ShortJujubePick(envs.EnvConfig(backend="mujoco")), 3)
  m, params, stats = _tiny_policy()
  keys = env_rollout.reset_keys(9, 3)
  every = run_episodes(benv, policy_controller(m, params, stats), keys, record=True)
  steps = every.steps_run
  assert steps == benv.episode_length  # an untrained policy does not succeed
  assert (every.queries == steps).all()
  assert every.routing.shape == (steps, 3, 3)
  np.testing.assert_allclose(every.routing, _router_on(m, params, every.trajectory), rtol=1e-5, atol=1e-6)
  chunked = run_episodes(benv, policy_controller(m, params, stats, query_every=5), keys)
  assert (chunked.queries == -(-steps // 5)).all()
  assert np.isnan(chunked.routing[1]).all() and not np.isnan(chunked.routing[5]).any()
  # another run of the same model reuses the compiled loop (its weights are an argument)
  leaves, tree = jax.tree.flatten(params)
  noise = [0.5 * jax.random.normal(jax.random.PRNGKey(i), x.shape) for i, x in enumerate(leaves)]
  other = jax.tree.unflatten(tree, [x + n for x, n in zip(leaves, noise)])  # router no longer uniform
  c1, c2 = policy_controller(m, params, stats), policy_controller(m, other, stats)
  assert c1.act is c2.act and c1.init is c2.init
  moved = run_episodes(benv, c2, keys, record=True)
  assert not np.allclose(moved.routing, every.routing)
  np.testing.assert_allclose(moved.routing, _router_on(m, other, moved.trajectory), rtol=1e-5, atol=1e-6)
  fixed = run_episodes(benv, policy_controller(m, params, stats, routing=[0.0, 1.0, 0.0]), keys)
  np.testing.assert_array_equal(fixed.routing[0], np.tile([0.0, 1.0, 0.0], (3, 1)))
  with pytest.raises(ValueError, match="query_every must be in 1..8"):
    policy_controller(m, params, stats, query_every=9)


class ObsOnly(NamedTuple):
  obs: dict  # what a learned policy's controller reads of the environment state


def test_controller_normalises_inputs_and_unnormalises_the_chunk():
  """The controller feeds the policy (x - mean) / std of the joint and (padded)
  object state and sends the env prediction * std + mean (hand-chosen
  statistics), step t of the chunk at step t, the fixed routing's chunk when
  one is given."""
  m, params, _ = _tiny_policy()
  assert m.normalize_object_state
  rng = np.random.default_rng(5)
  stats = {"action": {"mean": [0.1 * i - 0.2 for i in range(7)], "std": [0.5, 2.0, 0.1, 1.5, 3.0, 0.05, 0.7]},
           "joint_pos": {"mean": [0.3] * 7, "std": [0.2, 0.5, 1.0, 2.0, 0.25, 4.0, 0.1]},
           "object_state": {"mean": rng.normal(size=envs.OBJECT_STATE_DIM).tolist(),
                            "std": rng.uniform(0.01, 0.2, size=envs.OBJECT_STATE_DIM).tolist()}}
  raw = {"joint_pos": jnp.asarray(rng.normal(size=(2, 7)), jnp.float32),
         "object_state": jnp.asarray(rng.normal(size=(2, 7)), jnp.float32)}  # a task's own width
  state = ObsOnly(raw)
  a_mean, a_std = (np.asarray(stats["action"][k], np.float32) for k in ("mean", "std"))
  j_mean, j_std = (np.asarray(stats["joint_pos"][k], np.float32) for k in ("mean", "std"))
  o_mean, o_std = (np.asarray(stats["object_state"][k], np.float32) for k in ("mean", "std"))
  policy_input = {"joint_pos": (raw["joint_pos"] - j_mean) / j_std,
                  "object_state": (envs.padded_object_state(raw["object_state"]) - o_mean) / o_std}
  sent = {}
  for routing in (None, (0.0, 0.0, 1.0)):
    pred, _ = Policy(m).apply({"params": params}, policy_input, routing, method=Policy.predict)
    sent[routing] = np.asarray(pred) * a_std + a_mean
    c = policy_controller(m, params, stats, query_every=m.chunk, routing=routing)  # open loop: no averaging
    cstate, act = c.init(state), jax.jit(c.act)
    for t in range(m.chunk):
      action, cstate, _ = act(c.weights, cstate, state, jnp.int32(t))
      np.testing.assert_allclose(action, sent[routing][:, t], rtol=1e-5, atol=1e-5,
                                 err_msg=f"routing {routing}, step {t}")
  assert not np.allclose(sent[None], sent[(0.0, 0.0, 1.0)], atol=1e-3)  # the fixed skill is used
  without = {k: v for k, v in stats.items() if k != "object_state"}
  with pytest.raises(ValueError, match="no object_state entry"):
    policy_controller(m, params, without)
  # a run from before object state was normalised reads it raw, as it was trained
  legacy = dataclasses.replace(m, normalize_object_state=False)
  c = policy_controller(legacy, params, without, query_every=m.chunk)
  action, _, _ = jax.jit(c.act)(c.weights, c.init(state), state, jnp.int32(0))
  raw_input = dict(policy_input, object_state=envs.padded_object_state(raw["object_state"]))
  pred, _ = Policy(legacy).apply({"params": params}, raw_input, method=Policy.predict)
  np.testing.assert_allclose(action, np.asarray(pred)[:, 0] * a_std + a_mean, rtol=1e-5, atol=1e-5)


def test_trials_are_paired_across_policies(monkeypatch):
  """Trial i starts from the same state in every evaluate_task call, whatever the policy
  and the batch size (a partial last batch included); different trials start apart."""
  trials = 5
  starts = []

  def start_of_each_episode(benv, controller, keys, devices=None, frames=0):
    """In place of the rollout: report each episode's initial object state as its 'query count'."""
    obj = np.asarray(benv.reset(keys).obs["object_state"])
    starts.append(obj)
    codes = np.asarray([hash(np.round(o, 5).tobytes()) % 2**31 for o in obj])
    b = len(codes)
    return EpisodeResults(success=np.ones(b, bool), first_success_step=codes, nan=np.zeros(b, bool),
                          queries=codes, routing=None, steps_run=1)

  monkeypatch.setattr(protocol, "run_episodes", start_of_each_episode)
  act, skillplug = _tiny_policy("act"), _tiny_policy("skillplug")
  a = protocol.evaluate_task(TASK, policy_controller(*act), trials, batch=2)
  b = protocol.evaluate_task(TASK, policy_controller(*skillplug), trials, batch=5)
  assert len(starts) == 3 + 1  # 2 + 2 + 1 (padded) trials, then all 5 at once
  assert a["trial_queries"] == b["trial_queries"] and len(a["trial_queries"]) == trials
  benv = envs.make(TASK, num_envs=trials)
  direct = np.asarray(benv.reset(protocol.trial_keys(protocol.EVAL_SEED, trials)).obs["object_state"])
  np.testing.assert_allclose(np.concatenate(starts[:3])[:trials], direct, atol=1e-6)
  np.testing.assert_allclose(starts[3], direct, atol=1e-6)
  assert len(set(a["trial_queries"])) == trials  # every trial its own start
  assert all(not np.allclose(direct[i], direct[j]) for i in range(trials) for j in range(i + 1, trials))
  # evaluation starts are not the demonstrations' starts (data seed 0)
  demo = np.asarray(benv.reset(env_rollout.reset_keys(0, trials)).obs["object_state"])
  assert not np.allclose(demo, direct)


def test_a_longer_evaluation_begins_with_the_shorter_one():
  """Closed loop (the scripted expert): the first trials of a 7-trial evaluation in batches of 3
  are those of a 4-trial one in one batch, outcome for outcome; progress comes per batch."""
  controller = expert_controller(envs.make(TASK, num_envs=1, backend="mujoco"))
  done = []
  long = protocol.evaluate_task(TASK, controller, trials=7, batch=3, backend="mujoco", on_batch=done.append)
  short = protocol.evaluate_task(TASK, controller, trials=4, batch=4, backend="mujoco")
  assert done == [3, 3, 1]
  for key in ("trial_success", "trial_queries", "trial_success_step"):
    assert long[key][:4] == short[key], key
  assert len(long["trial_success_step"]) == 7 and len(set(long["trial_success_step"])) > 1  # trials differ


def test_an_evaluation_times_its_rendering():
  """render_s: the wall seconds spent drawing both cameras, within the evaluation's own time;
  0 when nothing is drawn (the rendering share of an evaluation, issue 29)."""
  controller = expert_controller(envs.make(TASK, num_envs=1, backend="mujoco"))
  t0 = time.monotonic()
  drawn = protocol.evaluate_task(TASK, controller, trials=2, batch=2, backend="mujoco", render=True,
                                 image_size=(16, 16))
  wall = time.monotonic() - t0
  plain = protocol.evaluate_task(TASK, controller, trials=2, batch=2, backend="mujoco")
  assert 0 < drawn["render_s"] < wall, (drawn["render_s"], wall)
  assert plain["render_s"] == 0.0
  assert drawn["trial_success"] == plain["trial_success"]  # drawing changes nothing the expert does


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


TASKS2 = ["jujube_pick", "drawer_open"]


def _run_results(policy: str, seed: int, outcomes: dict, *settings) -> list[dict]:
  """One run's per-task results as `protocol.evaluate_runs` records them (no simulation)."""
  cfg = train_config.override(experiment.preset("quick", policy),
                              ["taskset=quickstart3", f"seed={seed}", f"workdir=runs/{policy}{seed}", *settings])
  row = groups.row_fields(cfg, experiment.record(experiment.get("quick"), policy))
  return [dict(task=t, **row, run=str(cfg.run_dir), success_rate=float(np.mean(succ)),
               trial_success=[bool(x) for x in succ],
               trial_queries=list(q), trials=len(succ),
               solver_limit_episodes={"solver_iterations": 1, "linesearch_iterations": 0})
          for t, (succ, q) in outcomes.items()]


def _three_configurations() -> list[dict]:
  """K=4 (three seeds, written to different places and logged differently), K=2, ACT; 4 trials per task."""
  k4 = [_run_results("skillplug", 0, {"jujube_pick": ([1, 1, 0, 1], [10, 20, 99, 30]),
                                       "drawer_open": ([1, 0, 0, 0], [40, 99, 99, 99])}),
        _run_results("skillplug", 1, {"jujube_pick": ([1, 1, 1, 1], [12, 22, 32, 42]),
                                       "drawer_open": ([0, 0, 0, 0], [99, 99, 99, 99])}, "log_every=7"),
        _run_results("skillplug", 2, {"jujube_pick": ([0, 1, 0, 1], [99, 24, 99, 34]),
                                       "drawer_open": ([1, 1, 0, 0], [44, 54, 99, 99])}, "data_dir=elsewhere")]
  k2 = _run_results("skillplug", 0, {"jujube_pick": ([1, 1, 0, 0], [5, 15, 99, 99]),
                                      "drawer_open": ([1, 1, 1, 1], [1, 2, 3, 4])}, "model.plug.num_skills=2")
  act = _run_results("act", 0, {"jujube_pick": ([1, 1, 1, 1], [50, 50, 50, 50]),
                                 "drawer_open": ([1, 0, 1, 1], [60, 99, 60, 60])})
  return [r for run in k4 for r in run] + k2 + act


def test_rows_are_training_configurations_and_seeds_aggregate():
  out = tables.summarise(_three_configurations(), TASKS2)
  k4, k2 = "ACT+SkillPlug (num_skills=4)", "ACT+SkillPlug (num_skills=2)"
  assert list(out["rows"]) == [k4, k2, "ACT"]  # ACT ignores num_skills: its name does not say it
  assert out["rows"][k4]["seeds"] == [0, 1, 2] and out["rows"][k2]["seeds"] == [0]
  assert out["rows"][k4]["config"]["model.plug.num_skills"] == 4 and "seed" not in out["rows"][k4]["config"]
  assert out["rows"][k2]["overrides"] == {"model.plug.num_skills": 2, "taskset": "quickstart3"}
  json.dumps(out)  # the JSON keeps every row's full training key
  success = out["table"]["rows"][k4]
  assert success["seeds"] == 3
  mean, se = success["cells"]["jujube_pick"]
  assert mean == pytest.approx(75.0) and se == pytest.approx(np.std([75, 100, 50], ddof=1) / np.sqrt(3))
  assert success["cells"]["Avg."] == (pytest.approx(50.0), pytest.approx(0.0))  # per seed: 50, 50, 50
  assert out["table"]["rows"][k2]["cells"]["Avg."] == (pytest.approx(75.0), None)
  md = tables.markdown(out["table"])
  assert f"| {k4} | 75.0±14.4 | 25.0±14.4 | 50.0±0.0 |" in md and f"| {k2} | 50.0 | 100.0 | 75.0 |" in md
  # the same configuration and seed evaluated twice is an error, not a fourth seed
  with pytest.raises(ValueError, match="evaluated twice"):
    tables.summarise(_three_configurations() + _three_configurations()[:1], TASKS2)


def test_arms_on_different_suites_are_rows_on_their_own_tasks():
  jp = _run_results("act", 0, {"jujube_pick": ([1, 1, 0, 1], [10, 20, 99, 30])}, "taskset=jujube_pick")
  do = (_run_results("act", 0, {"drawer_open": ([1, 0, 0, 0], [40, 99, 99, 99])}, "taskset=drawer_open")
        + _run_results("act", 1, {"drawer_open": ([1, 1, 0, 0], [40, 50, 99, 99])}, "taskset=drawer_open"))
  own = lambda key: (key["taskset"],)
  out = tables.summarise(jp + do, TASKS2, row_tasks=own)
  a, b = "ACT (taskset=jujube_pick)", "ACT (taskset=drawer_open)"
  assert out["table"]["rows"][a]["cells"] == {"jujube_pick": (75.0, None), "drawer_open": None, "Avg.": (75.0, None)}
  assert out["table"]["rows"][b]["cells"]["jujube_pick"] is None
  assert out["table"]["rows"][b]["cells"]["Avg."] == (pytest.approx(37.5), pytest.approx(12.5))
  assert f"| {a} | 75.0 | - | 75.0 |" in tables.markdown(out["table"])
  # paired trials are those of the rows that ran the task
  assert out["queries_paired"]["paired_trials"] == {"jujube_pick": 3, "drawer_open": 1}
  # without row_tasks every row must cover every task; with it, every seed its own tasks
  with pytest.raises(ValueError, match="have no result on drawer_open"):
    tables.summarise(jp + do, TASKS2)
  with pytest.raises(ValueError, match=r"seed\(s\) \[1\] have no result on drawer_open"):
    tables.summarise(jp + do[:1] + _run_results("act", 1, {"jujube_pick": ([1], [1])}, "taskset=drawer_open"),
                     TASKS2, row_tasks=own)


def test_libero_arms_one_per_suite_are_one_row_of_the_papers_table():
  from experiments import publish
  tasks = ["libero_object:0", "libero_goal:0"]
  results = []
  for suite, task, rate in (("libero_object", tasks[0], [1, 1, 0, 0]), ("libero_goal", tasks[1], [1, 0, 0, 0])):
    for r in _run_results("act", 0, {task: (rate, [5] * 4)}, f"taskset={suite}"):
      results.append(dict(r, libero_success_rate=r["success_rate"]))
  stage = publish.merged_summary([dict(pretrain=results)], "pretrain", tasks,
                                 row_tasks=lambda key: envs.taskset(key["taskset"])[:1])
  assert len(stage["rows"]) == 2  # two training keys (suites) ...
  per_suite = stage["libero"]["libero_success"]["per_suite"]
  assert list(per_suite["rows"]) == ["ACT"]  # ... one row of the paper's table, a column per suite
  assert per_suite["rows"]["ACT"]["cells"] == {"Object": (50.0, None), "Goal": (25.0, None), "Avg.": (37.5, None)}
  assert "atoms_reached" not in stage["libero"]  # results from before progress was recorded
  # with it: the share of goal atoms reached, per suite, and a table of it in the report
  progress = [dict(r, atoms_reached_rate=0.5 * r["success_rate"] + 0.5) for r in results]
  stage = publish.merged_summary([dict(pretrain=progress)], "pretrain", tasks,
                                 row_tasks=lambda key: envs.taskset(key["taskset"])[:1])
  cells = stage["libero"]["atoms_reached"]["per_suite"]["rows"]["ACT"]["cells"]
  assert cells == {"Object": (75.0, None), "Goal": (62.5, None), "Avg.": (68.75, None)}
  assert "| ACT | 75.0 | 62.5 | 68.8 |" in publish.libero_report(stage, "pretrain")


def test_queries_tables_per_seed_and_over_paired_trials():
  out = tables.summarise(_three_configurations(), TASKS2)
  k4, k2 = "ACT+SkillPlug (num_skills=4)", "ACT+SkillPlug (num_skills=2)"
  q = out["queries"]["rows"]
  # each seed's mean over its own successes: J.P. 20, 27, 29; D.O. 40, (none), 49
  assert q[k4]["cells"]["jujube_pick"] == (pytest.approx(76 / 3),
                                           pytest.approx(np.std([20, 27, 29], ddof=1) / np.sqrt(3)))
  assert q[k4]["cells"]["drawer_open"] == (pytest.approx(44.5), pytest.approx(4.5)) and q[k4]["n"]["drawer_open"] == 2
  assert q[k4]["cells"]["Avg."][0] == pytest.approx(np.mean([30, 27, 39]))  # per seed, over the tasks it solved
  assert q[k2]["cells"]["drawer_open"] == (2.5, None) and q["ACT"]["cells"]["drawer_open"] == (60.0, None)
  # paired: J.P. trial 1 is the only trial all five runs solved; no D.O. trial was (seed 1 solved none)
  p = out["queries_paired"]
  assert p["paired_trials"] == {"jujube_pick": 1, "drawer_open": 0}
  assert p["rows"][k4]["cells"]["jujube_pick"] == (pytest.approx(22.0), pytest.approx(2 / np.sqrt(3)))
  assert p["rows"][k2]["cells"]["jujube_pick"] == (15.0, None)
  assert p["rows"]["ACT"]["cells"]["jujube_pick"] == (50.0, None)
  assert all(row["cells"]["drawer_open"] is None for row in p["rows"].values())
  md = tables.markdown(p)
  assert md.splitlines()[0] == "| Method | J.P. | D.O. | Avg. |"
  assert f"| {k4} | 22.0±1.2 | - | 22.0±1.2 |" in md and "| ACT | 50.0 | - | 50.0 |" in md
  assert md.endswith("Trials every run solved: J.P. 1/4, D.O. 0/4")
  assert tables.csv(p).splitlines()[3] == "ACT,1,50.00,,,,50.00,"


def test_eval_cli_and_pipeline_print_and_write_every_table(tmp_path, monkeypatch, capsys):
  from experiments import publish
  from skillplug_jax import cli
  results = _three_configurations()
  monkeypatch.setattr(protocol, "evaluate_runs", lambda runs, tasks, trials, **kw: dict(
      trials=trials, results=results, **tables.summarise(results, tasks)))
  assert cli.main(["eval", "--ckpt", "any", "--taskset", ",".join(TASKS2), "--trials", "4",
                   "--out", str(tmp_path / "ev")]) == 0
  printed = capsys.readouterr().out
  for title in ("Success rate (%)", "Policy queries per successful episode (each",
                "over the paired trials", "Trials every run solved"):
    assert printed.count(title) == 1, title
  assert "ACT+SkillPlug (num_skills=2): quick preset, seeds [0]" in printed
  n, episodes = len(results), sum(r["trials"] for r in results)
  assert (f"solver stopped at its iteration limit in {n} and its line search (MuJoCo Warp only) in 0 of "
          f"{episodes} episodes" in printed)
  saved = json.loads((tmp_path / "ev.json").read_text())
  assert saved["rows"]["ACT+SkillPlug (num_skills=4)"]["seeds"] == [0, 1, 2]
  assert (tmp_path / "ev.md").read_text().count("| Method |") == 3
  assert (tmp_path / "ev.queries_paired.csv").read_text().startswith("method,seeds,J.P._mean")
  assert '"ACT+SkillPlug (num_skills=2)"' not in (tmp_path / "ev.csv").read_text()  # no comma: not quoted
  # the pipeline (and so the quickstart) merges its jobs' runs into one set of rows
  act = [r for r in results if r["policy"] == "ACT"]
  sp = [r for r in results if r["train_seed"] == 0 and r["config"]["model.plug.num_skills"] == 4 and r["policy"] != "ACT"]
  parts = [dict(pretrain=act, fewshot=act[:1]), dict(pretrain=sp, fewshot=sp[:1])]
  exp = dataclasses.asdict(experiment.get("quick"))
  text = publish.report(dict(
      config="quick", experiment=exp, pretrain=publish.merged_summary(parts, "pretrain", TASKS2),
      fewshot=publish.merged_summary(parts, "fewshot", TASKS2[:1]),
      stages_s={"pretrain": 1.0}, runs=["a", "b"], wall_s=60.0, device="cpu", backend="mujoco"))
  assert text.count("| ACT+SkillPlug | ") == 6 and text.count("| ACT | ") == 6  # 3 tables x 2 stages
  assert "Trials every run solved: J.P. 3/4, D.O. 1/4" in text


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


def test_an_image_policy_on_another_renderer_is_warned_about(capsys):
  """MJX-Warp's ray caster and MuJoCo's OpenGL draw different pixels: evaluating
  an image policy on the other backend says so; a state policy is not warned about."""
  images = dataclasses.replace(experiment.preset("quick").model, use_images=True)
  cfg = train_config.TrainConfig(preset="quick", model=images, backend="mjx-warp")
  protocol.warn_if_other_renderer("runs/img", cfg, "mujoco")
  err = capsys.readouterr().err
  assert "WARNING: runs/img is an image policy trained on warp-raycast images" in err
  assert "evaluated on mujoco-opengl images (mujoco backend)" in err
  protocol.warn_if_other_renderer("runs/img", cfg, "mjx-warp")
  protocol.warn_if_other_renderer("runs/state", dataclasses.replace(cfg, model=experiment.preset("quick").model), "mujoco")
  assert capsys.readouterr().err == ""


def test_routing_smoothing_averages_the_routers_weights_over_queries():
  """With routing_smoothing s, query t decodes with r_t = s r_(t-1) + (1 - s) router(o_t), r_0 the
  router's own: two observations whose routers differ, seen one after the other."""
  m, params, stats = _tiny_policy()
  leaves, tree = jax.tree.flatten(params)
  params = jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(jax.random.PRNGKey(i), x.shape)
                                     for i, x in enumerate(leaves)])  # a router that is not uniform
  rng = np.random.default_rng(2)
  states = [ObsOnly({"joint_pos": jnp.asarray(rng.normal(size=(2, 7)), jnp.float32),
                     "object_state": jnp.asarray(rng.normal(size=(2, 14)), jnp.float32)}) for _ in range(2)]
  own = [np.asarray(run_episodes_free_routing(m, params, stats, s)) for s in states]
  assert np.abs(own[0] - own[1]).max() > 0.05, own
  c = policy_controller(m, params, stats, routing_smoothing=0.75)
  cstate, act = c.init(states[0]), jax.jit(c.act)
  _, cstate, info0 = act(c.weights, cstate, states[0], jnp.int32(0))
  _, cstate, info1 = act(c.weights, cstate, states[1], jnp.int32(1))
  np.testing.assert_allclose(info0["routing"], own[0], rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(info1["routing"], 0.75 * own[0] + 0.25 * own[1], rtol=1e-5, atol=1e-6)
  # and the chunk sent is the one decoded with those weights
  plain = policy_controller(m, params, stats, routing=None)
  action, _, _ = jax.jit(plain.act)(plain.weights, plain.init(states[0]), states[0], jnp.int32(0))
  first, _, _ = act(c.weights, c.init(states[0]), states[0], jnp.int32(0))
  np.testing.assert_allclose(first, action, rtol=1e-5, atol=1e-5)
  for bad, match in ((dict(routing_smoothing=1.0), r"in \[0, 1\)"),
                     (dict(routing_smoothing=0.5, routing=[1.0, 0.0, 0.0]), "its own router"),
                     (dict(routing_smoothing=0.5, query_every=4), "a query every step")):
    with pytest.raises(ValueError, match=match):
      policy_controller(m, params, stats, **bad)
  act_model, act_params, _ = _tiny_policy("act")
  with pytest.raises(ValueError, match="ACT\\+SkillPlug"):
    policy_controller(act_model, act_params, stats, routing_smoothing=0.5)


def run_episodes_free_routing(m, params, stats, state):
  """The router's own weights for `state` (the unsmoothed controller's routing at t = 0)."""
  c = policy_controller(m, params, stats)
  _, _, info = jax.jit(c.act)(c.weights, c.init(state), state, jnp.int32(0))
  return info["routing"]
