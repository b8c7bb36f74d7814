"""Closed-loop LIBERO trials of a policy (envs/libero/rollout.py) and their tables
(skillplug_jax/evaluate/libero.py): the expert's actions replayed through a jitted controller
succeed on the benchmark's init states as the expert does; a policy that never lets go succeeds by
LIBERO's rule and not by ours; a still arm by neither; a camera policy sees both cameras at its size."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from envs.libero import engine, expert, rollout, scene, suites
from envs.rollout import Controller
from skillplug_jax.evaluate import libero as libero_eval

TASK = "libero_object:1"  # pick up the cream cheese and place it in the basket
TRIALS = 2


@pytest.fixture(scope="module")
def expert_actions():
  """The expert's actions and phases [T, B] from the first init states, recorded as run() drives it."""
  t = suites.parse(TASK)
  b = engine.LiberoBatch(scene.scene(t.suite, t.index), TRIALS, nthread=1)
  b.reset(suites.init_states(t.suite, t.index)[:TRIALS])
  for _ in range(suites.SETTLE_STEPS):
    b.step(np.tile(rollout.REST, (TRIALS, 1)))
  e = expert.Expert(b)
  actions, phases = [], []
  for _ in range(t.time_limit):
    actions.append(e.act())
    phases.append(e.phase.copy())
    b.step(actions[-1])
  return np.stack(actions).astype(np.float32), np.stack(phases)


def replay(actions: np.ndarray) -> Controller:
  return Controller(lambda s: (), lambda w, c, s, t: (w[jnp.minimum(t, w.shape[0] - 1)], c, {}), 0, "replay",
                    jnp.asarray(actions))


def test_the_experts_actions_replayed_as_a_policy_succeed_as_the_expert(expert_actions):
  actions, _ = expert_actions
  row = libero_eval.evaluate_task(TASK, replay(actions), trials=TRIALS)
  assert row["trial_success"] == [True] * TRIALS and row["trial_libero_success"] == [True] * TRIALS
  assert expert.run("libero_object", 1, trials=TRIALS, nthread=1)["success"] == 1.0
  assert row["abbr"] == "O1" and row["median_steps"] < row["time_limit"]
  assert row["goal_atoms"] == ["In(cream_cheese_1, basket_1_contain_region)"]
  assert row["trial_atoms_reached"] == [[True]] * TRIALS and row["atoms_reached_rate"] == 1.0


def test_holding_on_is_libero_success_but_not_ours(expert_actions):
  actions, phases = expert_actions
  clumsy = actions.copy()
  clumsy[:, :, 6] = np.where(phases >= expert.CLOSE, 1.0, clumsy[:, :, 6])  # never opens once it has closed
  r = rollout.run_trials(TASK, replay(clumsy), trials=TRIALS, nthread=1)
  assert r.libero_success.all() and not r.success.any()
  assert r.steps_run == suites.TIME_LIMITS["libero_object"]


def test_a_still_arm_succeeds_by_neither_rule():
  still = np.tile(rollout.REST, (1, TRIALS, 1)).astype(np.float32)
  r = rollout.run_trials(TASK, replay(still), trials=TRIALS, nthread=1)
  assert not r.libero_success.any() and not r.success.any()
  assert r.atoms_reached.shape == (TRIALS, 1) and not r.atoms_reached.any()


def test_the_goals_atoms_are_reached_each_on_its_own():
  """LIBERO-10 8 (both moka pots on the stove) starts with its stove on: a still arm reaches that
  atom and neither placement, and the trial fails."""
  still = np.tile(rollout.REST, (1, 1, 1)).astype(np.float32)
  r = rollout.run_trials("libero_10:8", replay(still), trials=1, nthread=1)
  assert r.atoms == ("On(moka_pot_1, flat_stove_1_cook_region)", "On(moka_pot_2, flat_stove_1_cook_region)",
                     "TurnOn(flat_stove_1)")
  assert r.atoms_reached.tolist() == [[False, False, True]] and not r.libero_success.any()


def test_a_camera_policy_reads_both_cameras_at_its_size(expert_actions):
  seen = {}

  def act(w, c, s, t):  # the expert's actions, from a controller that is handed the cameras
    seen.update({k: v.shape for k, v in s.obs.items()})  # at trace time
    return w[jnp.minimum(t, w.shape[0] - 1)], c, {}

  policy = Controller(lambda s: (), act, 0, "camera", jnp.asarray(expert_actions[0][:, :1]), (24, 24))
  r = rollout.run_trials(TASK, policy, trials=1, nthread=1)
  assert seen["agentview_rgb"] == (1, 24, 24, 3) and seen["eye_in_hand_rgb"] == (1, 24, 24, 3)
  assert seen["object_state"] == (1, 64) and seen["joint_pos"] == (1, 7) and seen["gripper_qpos"] == (1, 2)
  assert r.success.all()
  with pytest.raises(ValueError, match="square"):
    rollout.run_trials(TASK, policy._replace(image_size=(24, 32)), trials=1)
  with pytest.raises(ValueError, match="init states 0..49"):
    rollout.run_trials(TASK, policy, trials=2, first=49)


def test_the_suite_table_averages_tasks_per_seed_then_suites():
  rates = {"p": {"libero_object:0": [1.0, 0.5], "libero_object:1": [0.0, 0.5], "libero_goal:0": [1.0, 1.0]}}
  table = libero_eval.suite_table(rates, list(rates["p"]))
  cells = table["rows"]["p"]["cells"]
  assert table["suites"] == ["Object", "Goal"]
  assert cells["Object"] == (50.0, 0.0) and cells["Goal"] == (100.0, 0.0)
  assert cells["Avg."] == (75.0, 0.0)
  assert "| p | 50.0 ± 0.0 | 100.0 ± 0.0 | 75.0 ± 0.0 |" in libero_eval.markdown(table)


def test_the_report_says_how_far_failed_trials_got():
  results = [dict(policy="p", seed=0, task=t, success_rate=0.0, libero_success_rate=0.0, atoms_reached_rate=rate)
             for t, rate in (("libero_10:0", 0.5), ("libero_10:8", 1 / 3))]
  tasks = ["libero_10:0", "libero_10:8"]
  out = {"trials": 2, "tables": {m: libero_eval.tables_of(results, tasks, m)
                                 for m in libero_eval.MEASURES + (libero_eval.PROGRESS,)}}
  text = libero_eval.report(out)
  assert "| p | 0.0 | 0.0 |" in text and "| p | 41.7 | 41.7 |" in text.split("How far the trials got")[1]
  with pytest.raises(ValueError, match="unknown measure 'atoms'"):
    libero_eval.tables_of(results, tasks, "atoms")


def test_the_papers_rows_stand_beside_ours_in_our_columns():
  rates = {"p": {"libero_object:0": [1.0], "libero_goal:0": [0.5], "libero_10:0": [0.0]}}
  table = libero_eval.suite_table(rates, list(rates["p"]))
  fewshot = libero_eval.markdown(table, paper="fewshot").splitlines()
  # the paper's few-shot table has no Long column, so no average over our three suites
  assert fewshot[-1] == "| paper: OpenVLA-OFT+SkillPlug | 79.6 ± 1.6 | 83.2 ± 1.7 | - | - |"
  assert fewshot[2] == "| p | 100.0 | 50.0 | 0.0 | 50.0 |"  # one seed: no SE
  goal_and_object = libero_eval.suite_table({"p": {k: rates["p"][k] for k in ("libero_object:0", "libero_goal:0")}},
                                            ["libero_object:0", "libero_goal:0"])
  rows = libero_eval.markdown(goal_and_object, paper="fewshot").splitlines()
  assert rows[-2] == "| paper: OpenVLA-OFT | 47.4 ± 2.1 | 45.4 ± 2.2 | 46.4 |"
  multi = libero_eval.markdown(table, paper="pretrain").splitlines()
  assert multi[-2] == "| paper: OpenVLA-OFT | 97.6 ± 0.6 | 96.5 ± 0.9 | 92.9 ± 1.2 | 95.7 |"
  with pytest.raises(ValueError, match="stages pretrain, fewshot"):
    libero_eval.markdown(table, paper="posttrain")


def test_trial_i_starts_from_the_benchmarks_init_state_i(monkeypatch):
  seen = []
  original = engine.LiberoBatch.reset

  def reset(self, states):
    seen.append(np.array(states))
    return original(self, states)

  monkeypatch.setattr(engine.LiberoBatch, "reset", reset)
  still = np.tile(rollout.REST, (1, 2, 1)).astype(np.float32)
  rollout.run_trials("libero_spatial:0", replay(still), trials=2, first=7, nthread=1)
  assert np.array_equal(seen[0], suites.init_states("libero_spatial", 0)[7:9])


def test_a_routing_policys_weights_and_queries_are_recorded_per_trial(expert_actions, tmp_path):
  """ACT+SkillPlug's routing on LIBERO, as on DISCOVERSE: each query's weights, NaN between queries
  and after a trial ends, the queries counted per trial, and the arrays written beside the result."""
  actions, _ = expert_actions
  k = 3

  def act(w, c, s, t):  # the expert's actions; asked every other step, routing = one-hot of t % K
    queried = jnp.full((TRIALS,), t % 2 == 0)
    routing = jnp.tile(jnp.eye(k)[t % k], (TRIALS, 1))
    return w[jnp.minimum(t, w.shape[0] - 1)], c, {"routing": routing, "queried": queried}

  policy = Controller(lambda s: (), act, k, "routed", jnp.asarray(actions))
  routing_file = tmp_path / "O1.routing.npz"
  row = libero_eval.evaluate_task(TASK, policy, trials=TRIALS, routing_file=routing_file)
  assert row["trial_success"] == [True] * TRIALS
  ends = np.asarray(row["trial_success_step"])
  assert row["trial_queries"] == [int(e // 2 + 1) for e in ends]  # steps 0, 2, ... up to its end
  from skillplug_jax.evaluate import protocol
  saved = protocol.read_routing(routing_file)
  assert saved["routing"].shape[0] == TRIALS and saved["task"] == TASK
  w = saved["routing"][0]
  np.testing.assert_array_equal(w[2], np.eye(k)[2])  # queried at step 2: its weights
  assert np.isnan(w[1]).all() and np.isnan(w[ends[0] + 1:]).all()  # no query: NaN, and after the end
  assert row["diagnostics"]["queries"] == sum(row["trial_queries"])
