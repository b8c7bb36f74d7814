"""The toy skill problem (envs/toy_skills.py) and its driver (experiments/toy_skills.py)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import toy_skills as toy
from experiments import toy_skills as driver
from skillplug_jax.model.policy import Policy

CFG = toy.ToySkillsConfig()
_step = jax.jit(lambda state, action: toy.step(CFG, state, action))


@pytest.fixture(scope="module")
def demos():
  tasks = np.repeat(np.arange(toy.NUM_TASKS), 16)
  final, traj = jax.jit(lambda k: toy.demonstrations(CFG, k, tasks))(jax.random.PRNGKey(3))
  return tasks, jax.device_get(final), jax.device_get(traj)


def test_expert_solves_every_task(demos):
  tasks, final, _ = demos
  for t in range(toy.NUM_TASKS):
    assert final.success[tasks == t].all(), toy.task_name(t)
  assert (final.stage == toy.TASK_LENGTH[tasks]).all()


def test_labels_cover_every_primitive_seen_and_unseen(demos):
  tasks, _, traj = demos
  for group in (toy.SEEN, toy.UNSEEN):
    rows = np.isin(tasks, group)
    labels = traj.label[rows][traj.active[rows]]
    assert set(labels.tolist()) == set(range(len(toy.PRIMITIVES)))
  # a label is the primitive the task's table names at the step's stage
  stage = traj.obs["object_state"][..., toy.STAGE_BITS].argmax(-1)
  expected = toy.TASK_TABLE[tasks[:, None], stage]
  assert (traj.label[traj.active] == expected[traj.active]).all()


def _state(task, pos, grip=0.0, stage=0):
  s = toy.reset(CFG, jax.random.PRNGKey(0), task)
  landmarks = jnp.array([[-0.6, -0.6], [0.6, -0.6], [0.0, 0.6]])
  return s._replace(landmarks=landmarks, pos=jnp.asarray(pos, jnp.float32), grip=jnp.float32(grip),
                    stage=jnp.int32(stage), stage_grip=jnp.float32(grip))


def _hold(state, action, steps):
  for _ in range(steps):
    state = _step(state, jnp.asarray(action, jnp.float32))
  return state


def test_reaching_the_last_landmark_with_a_stage_skipped_does_nothing():
  task = toy.TASKS.index((0, 1))  # A then B
  s = _hold(_state(task, [0.6, -0.6]), [0.6, -0.6, 0.0], 20)  # sits on B, never visits A
  assert int(s.stage) == 0 and not bool(s.success)
  task = toy.TASKS.index((0, 3, 1))  # A, toggle, B: reach A and B, never toggle
  s = _hold(_state(task, [-0.6, -0.6]), [-0.6, -0.6, 0.0], 3)
  assert int(s.stage) == 1
  s = _hold(s, [0.6, -0.6, 0.0], 30)
  assert int(s.stage) == 1 and not bool(s.success)
  s = _hold(s, [0.6, -0.6, 1.0], CFG.toggle_steps)  # the toggle, done at B: then B holds
  assert int(s.stage) == 2
  s = _hold(s, [0.6, -0.6, 1.0], CFG.hold_steps)
  assert bool(s.success)


def test_last_stage_must_hold_and_toggle_needs_consecutive_commands():
  task = toy.TASKS.index((0, 1))
  s = _hold(_state(task, [0.6, -0.6], stage=1), [0.6, -0.6, 0.0], CFG.hold_steps - 1)  # at B, briefly
  s = _hold(s._replace(pos=jnp.zeros(2)), [0.0, 0.0, 0.0], 10)  # then leaves
  assert int(s.stage) == 1 and not bool(s.success)
  s = _hold(s, [0.6, -0.6, 0.0], 20)
  assert bool(s.success)
  task = toy.TASKS.index((0, 3, 1))  # A, toggle, B: at the toggle
  s = _state(task, [0.0, 0.0], stage=1)
  s = _hold(s, [0.0, 0.0, 1.0], CFG.toggle_steps - 1)
  s = _step(s, jnp.array([0.0, 0.0, 0.0]))  # interrupted: the count restarts
  s = _hold(s, [0.0, 0.0, 1.0], CFG.toggle_steps - 1)
  assert float(s.grip) == 0.0 and int(s.stage) == 1
  s = _hold(s, [0.0, 0.0, 1.0], 1)
  assert float(s.grip) == 1.0 and int(s.stage) == 2 and not bool(s.success)


def test_unseen_tasks_recombine_what_seen_tasks_show():
  """Every (place in the sequence, primitive) of an unseen task occurs in some seen task, so a
  frozen encoder reads only inputs set in pretraining; the sequences themselves are new."""
  seen = {(i, p) for t in toy.SEEN_TASKS for i, p in enumerate(t)}
  for t in toy.UNSEEN_TASKS:
    assert t not in toy.SEEN_TASKS
    assert {(i, p) for i, p in enumerate(t)} <= seen, t


def test_bounded_step_and_landmark_separation():
  s = jax.jit(lambda k: toy.reset_batch(CFG, k, np.zeros(256, np.int32)))(jax.random.PRNGKey(1))
  d = np.linalg.norm(np.asarray(s.landmarks)[:, :, None] - np.asarray(s.landmarks)[:, None], axis=-1)
  assert (d + 9 * np.eye(3) >= CFG.min_separation).all()
  moved = jax.jit(jax.vmap(lambda st: toy.step(CFG, st, jnp.array([1.0, 1.0, 0.0]))))(s)
  assert np.all(np.linalg.norm(np.asarray(moved.pos - s.pos), axis=-1) <= CFG.max_step + 1e-6)


def test_observation_and_action_shapes_fit_the_model():
  model = driver.toy_train_config().model
  s = jax.jit(lambda k: toy.reset_batch(CFG, k, np.arange(toy.NUM_TASKS)))(jax.random.PRNGKey(0))
  obs = jax.jit(jax.vmap(toy.observe))(s)
  assert obs["joint_pos"].shape == (toy.NUM_TASKS, model.joint_dim)
  assert obs["object_state"].shape == (toy.NUM_TASKS, toy.OBJECT_STATE_DIM)
  assert toy.OBJECT_STATE_DIM % toy.SLOT == 0  # whole object slots (model.object_tokens=per_object)
  slots = np.asarray(obs["object_state"][:, :3 * toy.SLOT]).reshape(-1, 3, toy.SLOT)
  np.testing.assert_array_equal(slots[..., :2], np.asarray(s.landmarks))
  program = np.asarray(obs["object_state"][:, toy.PROGRAM_BITS]).reshape(toy.NUM_TASKS, toy.MAX_STAGES, -1)
  np.testing.assert_array_equal(np.where(program.any(-1), program.argmax(-1), -1), toy.TASK_TABLE)
  assert (np.asarray(obs["object_state"][:, toy.STAGE_BITS]).argmax(-1) == 0).all()
  assert jax.vmap(toy.expert)(s).shape == (toy.NUM_TASKS, model.action_dim)
  def predict():  # shapes only (eval_shape): nothing is compiled
    params = driver.init_params(model, jax.random.PRNGKey(0))
    return Policy(model).apply({"params": params}, obs, method=Policy.predict)
  pred, routing = jax.eval_shape(predict)
  assert pred.shape == (toy.NUM_TASKS, model.chunk, model.action_dim)
  assert routing.shape == (toy.NUM_TASKS, model.num_skills)


def test_routing_statistics_on_constructed_arrays():
  k = 4
  uniform = driver.routing_stats(np.full((100, k), 1.0 / k))
  assert uniform["routing_entropy_per_query"] == pytest.approx(1.0)
  assert uniform["usage_entropy"] == pytest.approx(1.0)
  assert uniform["effective_skills"] == pytest.approx(k)
  one_skill = driver.routing_stats(np.tile(np.eye(k)[2], (100, 1)))
  assert one_skill["routing_entropy_per_query"] == pytest.approx(0.0, abs=1e-6)
  assert one_skill["effective_skills"] == pytest.approx(1.0, abs=1e-6)
  library = driver.routing_stats(np.tile(np.eye(k), (25, 1)))  # each query one skill, all used alike
  assert library["routing_entropy_per_query"] == pytest.approx(0.0, abs=1e-6)
  assert library["usage_entropy"] == pytest.approx(1.0)
  assert library["effective_skills"] == pytest.approx(k)
  two = driver.routing_stats(np.tile([[0.5, 0.5, 0.0, 0.0]], (10, 1)))
  assert two["routing_entropy_per_query"] == pytest.approx(math.log(2) / math.log(k))
  assert two["effective_skills"] == pytest.approx(2.0)


def test_nmi():
  rng = np.random.default_rng(0)
  y = rng.integers(0, 4, 20000)
  assert driver.nmi((y + 1) % 4 * 7, y) == pytest.approx(1.0)  # relabelled one-to-one
  assert driver.nmi(rng.integers(0, 4, 20000), y) < 0.01
  assert driver.nmi(np.zeros_like(y), y) == 0.0  # a router that always picks one skill
  assert 0.0 < driver.nmi(y // 2, y) < 1.0  # a coarser partition


def test_probe_classes():
  out = dict(landmarks=np.array([[[0.0, 0.0], [0.5, 0.5], [-0.5, 0.5]]] * 3),
             final_pos=np.array([[0.49, 0.5], [0.9, -0.9], [0.9, -0.9]]), toggled=np.array([True, True, False]))
  assert driver.probe_classes(out, 0.15).tolist() == [1, 3, 4]


def test_a_setting_that_does_not_exist_is_an_error_naming_the_variant():
  with pytest.raises(ValueError, match="'x'.*no_such_field"):
    driver.variant_config(driver.ToyExperiment(), driver.ToyVariant("x", ("model.no_such_field=1",)))
  exp = driver.apply_settings(driver.ToyExperiment(), ["fewshot_steps=7", "model.num_skills=3", "loss.sd=0.5"])
  assert exp.fewshot_steps == 7 and exp.train.model.num_skills == 3 and exp.train.loss.sd == 0.5


@pytest.mark.slow
def test_driver_writes_the_summary(tmp_path):
  tiny = ["demos_seen=3", "demos_unseen=2", "eval_trials=2", "probe_trials=1", "fewshot_steps=2",
          "steps_per_call=1", "model.hidden=16", "model.heads=2", "model.ff=32", "model.enc_layers=1",
          "model.dec_layers=1", "model.skill_latent_dim=4", "model.alignment_dim=8"]
  argv = ["--out", str(tmp_path), "--variants", "skillplug_paper", "--steps", "2", "--no-progress"]
  for s in tiny:
    argv += ["--set", s]
  assert driver.main(argv) == 0
  summary = json.loads((tmp_path / "summary.json").read_text())
  v = summary["variants"]["skillplug_paper"]
  assert v["status"] == "ok"
  for key in ("multitask_success", "fewshot_success", "routing_entropy_per_query", "usage_entropy",
              "effective_skills", "nmi", "fixed_skill_probe"):
    assert v[key] is not None, key
  assert set(v["multitask_success"]["per_task"]) == {toy.task_name(t) for t in toy.SEEN}
  assert set(v["fewshot_success"]["per_task"]) == {toy.task_name(t) for t in toy.UNSEEN}
  assert 0.0 <= v["routing_entropy_per_query"]["mean"] <= 1.0 + 1e-6
  assert 1.0 - 1e-6 <= v["effective_skills"]["mean"] <= 4.0 + 1e-6
  assert len(v["per_seed"][0]["fixed_skill_probe"]["skills"]) == 4
  assert (tmp_path / "summary.md").exists()

  # the same command again keeps the finished variant (resumes); other settings recompute it
  summary["variants"]["skillplug_paper"]["marker"] = 1
  (tmp_path / "summary.json").write_text(json.dumps(summary))
  assert driver.main(argv) == 0
  assert json.loads((tmp_path / "summary.json").read_text())["variants"]["skillplug_paper"]["marker"] == 1
  assert driver.main(argv + ["--set", "eval_seed=7"]) == 0
  assert "marker" not in json.loads((tmp_path / "summary.json").read_text())["variants"]["skillplug_paper"]

  # --combine: two runs' variants in one summary; runs with other settings are refused
  other = tmp_path / "other"
  other.mkdir()
  summary = json.loads((tmp_path / "summary.json").read_text())
  summary["variants"] = {"act": dict(summary["variants"]["skillplug_paper"], label="renamed")}
  (other / "summary.json").write_text(json.dumps(summary))
  assert driver.main(["--combine", f"{tmp_path},{other}", "--out", str(tmp_path / "both")]) == 0
  both = json.loads((tmp_path / "both" / "summary.json").read_text())
  assert list(both["variants"]) == ["act", "skillplug_paper"] and both["sources"] == [str(tmp_path), str(other)]
  assert "renamed" in (tmp_path / "both" / "summary.md").read_text()
  summary["config"]["eval_seed"] = 1
  (other / "summary.json").write_text(json.dumps(summary))
  with pytest.raises(ValueError, match="eval_seed"):
    driver.main(["--combine", f"{tmp_path},{other}", "--out", str(tmp_path / "both2")])


@pytest.mark.slow
def test_oracle_variant_routes_by_the_primitive_the_batches_carry():
  """The oracle diagnostic: batches carry each step's primitive and the router_label term
  teaches the router to choose skill = primitive, which the paper's loss never does."""
  exp = driver.apply_settings(driver.ToyExperiment(), [
      "model.hidden=32", "model.heads=2", "model.ff=64", "model.enc_layers=1", "model.dec_layers=1",
      "model.skill_latent_dim=4", "model.alignment_dim=8", "train.max_steps=300", "train.warmup_steps=20"])
  data = driver.demo_arrays(exp.env, jax.random.PRNGKey(0), toy.SEEN, 20, exp.train.model.chunk)
  batch = driver.sample_batch({k: jnp.asarray(v) for k, v in data.items()}, jax.random.PRNGKey(1), 256,
                              exp.train.model.chunk)
  assert batch["skill_label"].shape == (256,) and set(np.unique(batch["skill_label"])) <= set(range(4))

  def accuracy(name, params):
    cfg = driver.variant_config(exp, next(v for v in driver.VARIANTS if v.name == name))
    out = Policy(cfg.model).apply({"params": params}, batch, train=False)
    return float(jnp.mean(out["router_probs"].argmax(-1) == batch["skill_label"]))

  accs = {}
  for name in ("oracle", "skillplug_paper"):
    cfg = driver.variant_config(exp, next(v for v in driver.VARIANTS if v.name == name))
    params, metrics = driver.train(cfg, driver.init_params(cfg.model, jax.random.PRNGKey(0)), data,
                                   jax.random.PRNGKey(2), steps_per_call=100, progress=False)
    assert ("router_label" in metrics) == (name == "oracle")
    accs[name] = accuracy(name, params)
  assert accs["oracle"] > 0.8, accs
  assert accs["skillplug_paper"] < 0.6, accs  # reconstruction alone does not find that partition


def test_fewshot_overrides_change_the_fine_tune_alone():
  exp = driver.ToyExperiment()
  by_name = {v.name: v for v in driver.VARIANTS}
  for name, label_weight in (("oracle_cue_per_object_router", 1.0), ("oracle_cue_per_object_router_unlabelled", 0.0)):
    variant = by_name[name]
    cfg = driver.variant_config(exp, variant)
    assert cfg.loss.router_label == 1.0  # pretraining is told the primitive in both
    few = driver.fewshot_config(exp, cfg, variant)
    assert few.loss.router_label == label_weight and few.trainable == ("router",)
    assert few.max_steps == exp.fewshot_steps and few.model == cfg.model
