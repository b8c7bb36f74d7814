"""The toy skill problem (envs/toy_skills.py), run by the experiment pipeline (its config
experiments/configs/toy_skills.py, its data skillplug_jax/train/toy.py, its closed loop
skillplug_jax/evaluate/toy_rollout.py), and the routing statistics (evaluate/routing.py)."""

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import toy_skills as toy
from experiments import pipeline
from skillplug_jax import experiment, fewshot
from skillplug_jax.evaluate import routing, toy_rollout
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import loop, run_files
from skillplug_jax.train import toy as toy_train
from skillplug_jax.train.config import override

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


def _config(*overrides):
  return experiment.get("toy_skills", overrides)


TINY_MODEL = ["train.model.hidden=16", "train.model.heads=2", "train.model.ff=32", "train.model.enc_layers=1",
              "train.model.dec_layers=1", "train.model.plug.skill_latent_dim=4", "train.model.plug.alignment_dim=8"]


def test_observation_and_action_shapes_fit_the_model():
  cfg = _config().train
  model = cfg.model
  assert loop.object_state_dim(cfg) == toy.OBJECT_STATE_DIM and loop.is_toy(cfg)
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
    params = loop.init_params(cfg, jax.random.PRNGKey(0))  # the project's one init, shaped by the taskset
    return Policy(model).apply({"params": params}, obs, method=Policy.predict)
  pred, r = jax.eval_shape(predict)
  assert pred.shape == (toy.NUM_TASKS, model.chunk, model.action_dim)
  assert r.shape == (toy.NUM_TASKS, model.plug.num_skills)


def test_toy_tasksets_and_names():
  assert pipeline.tasks_of(toy.TASKSET) == tuple(toy.task_id(t) for t in toy.SEEN)
  assert pipeline.tasks_of(toy.FEWSHOT_TASKSET) == ("toy_BA", "toy_ATC", "toy_CBA")
  from skillplug_jax.evaluate import tables
  assert tables.abbr("toy_ATC") == "A>T>C"


def test_routing_statistics_on_constructed_arrays():
  """Hand values, through numpy (evaluation summaries, the toy, probes) and through jax (training
  logs: `diagnostics.routing_stats` under jit): one implementation, one set of names."""
  from skillplug_jax import diagnostics
  k = 4
  cases = dict(
      uniform=(np.full((100, k), 1.0 / k), dict(routing_entropy_per_query=1.0, usage_entropy=1.0, effective_skills=k)),
      one_skill=(np.tile(np.eye(k)[2], (100, 1)), dict(routing_entropy_per_query=0.0, usage_entropy=0.0,
                                                        effective_skills=1.0)),
      library=(np.tile(np.eye(k), (25, 1)), dict(routing_entropy_per_query=0.0, usage_entropy=1.0, effective_skills=k)),
      two=(np.tile([[0.5, 0.5, 0.0, 0.0]], (10, 1)), dict(routing_entropy_per_query=math.log(2) / math.log(k),
                                                           usage_entropy=0.5, effective_skills=2.0)))
  for name, (r, want) in cases.items():
    got = routing.routing_stats(r)
    in_jit = jax.jit(diagnostics.routing_stats)(jnp.asarray(r, jnp.float32))
    assert set(got) == {"routing_entropy_per_query", "usage_entropy", "effective_skills", "mean_weights"}
    assert got["mean_weights"] == pytest.approx(r.mean(0).tolist())
    for key, value in want.items():
      assert got[key] == pytest.approx(value, abs=1e-6), (name, key)
      assert float(in_jit[key]) == pytest.approx(value, abs=1e-5), (name, key)
  assert float(routing.entropy(np.array([0.5, 0.5]))) == pytest.approx(math.log(2))
  assert routing.entropy(jnp.array([0.5, 0.5])).dtype == jnp.float32  # jax in, jax out (jit-safe)


def test_nmi():
  rng = np.random.default_rng(0)
  y = rng.integers(0, 4, 20000)
  assert routing.nmi((y + 1) % 4 * 7, y) == pytest.approx(1.0)  # relabelled one-to-one
  assert routing.nmi(rng.integers(0, 4, 20000), y) < 0.01
  assert routing.nmi(np.zeros_like(y), y) == 0.0  # a router that always picks one skill
  assert 0.0 < routing.nmi(y // 2, y) < 1.0  # a coarser partition


def test_probe_classes():
  out = dict(landmarks=np.array([[[0.0, 0.0], [0.5, 0.5], [-0.5, 0.5]]] * 3),
             final_pos=np.array([[0.49, 0.5], [0.9, -0.9], [0.9, -0.9]]), toggled=np.array([True, True, False]))
  assert toy_rollout.probe_classes(out, 0.15).tolist() == [1, 3, 4]


def test_old_summaries_read_with_todays_names():
  """Published summaries keep the names they were written with; one mapping reads them."""
  root = Path(__file__).resolve().parents[1] / "docs" / "results"
  for name in ("skill_library_image/2026-12-06_phases_w01_seed0/summary.json",
               "skill_library_image/2026-12-06_phases_w01_seed0/routing_diagnostics.json"):
    old_text = (root / name).read_text()
    assert "query_entropy" in old_text and "mean_routing" in old_text  # written before today's names
    text = json.dumps(routing.renamed(json.loads(old_text)))
    for gone in ("query_entropy", "mean_routing", "routing_entropy_frac", "entropy_frac"):
      assert f'"{gone}"' not in text, (name, gone)
    assert text.count('"routing_entropy_per_query"') >= old_text.count('"query_entropy"')
  new = routing.renamed(json.loads((root / "skill_library_image/2026-12-06_phases_w01_seed0/summary.json").read_text()))
  diag = next(iter(new["pretrain"]["diagnostics"].values()))["mean"]
  assert set(diag) >= {"routing_entropy_per_query", "usage_entropy", "effective_skills"}
  first = next(r for r in new["pretrain"]["results"] if r.get("diagnostics"))
  assert "mean_weights" in first and "routing_entropy_per_query" in first["diagnostics"]
  # as a reference (rows read, not run), an old summary's results tabulate with today's diagnostics
  from experiments import publish
  from skillplug_jax.evaluate import tables
  ref = publish.reference_results(str(root / "skill_library_image/2026-12-06_phases_w01_seed0/summary.json"), "pretrain")
  tabled = tables.summarise(ref, sorted({r["task"] for r in ref}))
  assert all("routing_entropy_per_query" in d["mean"] for d in tabled["diagnostics"].values())
  toy_old = json.loads((root / "toy_skills" / "2026-12-03_v2_screen_seed0" / "summary.json").read_text())
  toy_new = routing.renamed(toy_old)  # the toy's summaries already used these names
  assert toy_new["variants"]["skillplug_paper"]["routing_entropy_per_query"] == \
      toy_old["variants"]["skillplug_paper"]["routing_entropy_per_query"]
  # an old routing summary's nats, as fractions of log K
  r = routing.renamed(dict(entropy=math.log(2), entropy_frac=0.5, entropy_of_mean=math.log(4),
                           mean_weights=[0.25] * 4))
  assert r == dict(routing_entropy_per_query=0.5, usage_entropy=pytest.approx(1.0), mean_weights=[0.25] * 4)


def test_variants_and_settings_that_do_not_exist_are_named():
  exp = _config()
  assert {"paper", "oracle", "oracle_cue_per_object_router_unlabelled", "mined", "decoder", "per_object"} <= \
      {v.name for v in exp.variants}
  assert not {"posterior", "top1", "top1_only", "load_balance", "router_z", "decoder_top1", "cue_top1",
              "cue_top1_router", "cue_per_object_top1"} & {v.name for v in exp.variants}
  with pytest.raises(ValueError, match=r"unknown variant\(s\) \['nope'\] of config 'toy_skills'"):
    experiment.only(exp, "paper,nope", "toy_skills")
  bad = dataclasses.replace(exp, variants=(experiment.Variant("x", ("train.model.no_such_field=1",)),))
  with pytest.raises(ValueError, match="'x'.*no_such_field"):
    experiment.expand(bad)
  assert pipeline.main(["--config", "toy_skills", "--variants", "nope", "--out", "/nonexistent"]) == 2


def test_fewshot_overrides_change_the_fine_tune_alone(tmp_path):
  arms = {v.name: arm for v, arm in experiment.expand(_config())}
  for name, label_weight in (("oracle_cue_per_object_router", 1.0), ("oracle_cue_per_object_router_unlabelled", 0.0)):
    arm = arms[name]
    cfg = arm.train_config("skillplug", 0)
    assert cfg.loss.router_label == 1.0  # pretraining is told the primitive in both
    few = fewshot.fewshot_config(cfg, tmp_path / "run", "toy_BA", arm.fewshot)
    assert few.loss.router_label == label_weight and few.trainable == ("router",)
    assert few.max_steps == arm.fewshot.steps == 300 and few.model == cfg.model
    assert few.taskset == "toy_BA" and few.data_taskset == toy.FEWSHOT_TASKSET and few.demos == 10
  # recorded like the rest of the protocol, so a run is adapted later as it was trained
  rec = experiment.record(arms["oracle_cue_per_object_router_unlabelled"], "skillplug")
  back = experiment.record_from_dict(json.loads(json.dumps(experiment.record_to_dict(rec))))
  assert back.fewshot.train_overrides == ("loss.router_label=0",) and back == rec
  assert experiment.FewShot().train_overrides == ()  # other configs: unchanged


def test_toy_demonstrations_for_the_pipeline():
  cfg = override(_config().train, ["demos=3"])
  seen = toy_train.data_of(cfg)
  assert seen["joint_pos"].shape[0] == 3 * len(toy.SEEN) and set(seen["task"]) == set(toy.SEEN)
  few = dataclasses.replace(cfg, taskset="toy_ATC", data_taskset=toy.FEWSHOT_TASKSET, demos=2)
  data = toy_train.data_of(few)
  assert data["joint_pos"].shape[0] == 2 and set(data["task"]) == {toy.TASK_IDS["toy_ATC"]}
  batch = toy_train.sample_batch({k: jnp.asarray(v) for k, v in seen.items()}, jax.random.PRNGKey(1), 32,
                                 cfg.model.chunk)
  like = loop.example_batch(cfg, 32)
  assert {k: v.shape for k, v in like.items()} == {k: batch[k].shape for k in like}


@pytest.mark.slow
def test_the_pipeline_runs_the_toy(tmp_path):
  """The toy through the pipeline at a tiny size: a run directory with the record, the tables of
  any config (toy tasks as columns), the toy's extras and report section; the same command
  again reads the evaluations back; other evaluation settings recompute them."""
  tiny = TINY_MODEL + ["train.demos=3", "fewshot.demos=2", "trials=2", "fewshot.steps=2", "train.max_steps=2",
                       "train.log_every=1", "train.warmup_steps=0"]
  argv = ["--config", "toy_skills", "--variants", "paper", "--out", str(tmp_path)]
  for s in tiny:
    argv += ["--set", s]
  t0 = time.time()
  assert pipeline.main(argv) == 0
  wall = time.time() - t0
  summary = json.loads((tmp_path / "summary.json").read_text())
  assert set(summary["pretrain"]["rows"]) == {"ACT", "ACT+SkillPlug"}
  assert summary["pretrain"]["table"]["abbr"] == [toy.task_name(t) for t in toy.SEEN]
  assert summary["fewshot"]["table"]["tasks"] == ["toy_BA", "toy_ATC", "toy_CBA"]
  plug = [r for r in summary["pretrain"]["results"] if r["policy"] == "ACT+SkillPlug"]
  assert len(plug) == len(toy.SEEN) and all(Path(r["routing_file"]).exists() for r in plug)
  for r in plug:
    assert 0.0 <= r["stage_progress"] <= 1.0 and r["variant"] == "paper"
    assert set(r["toy_routing"]) >= {"routing_entropy_per_query", "usage_entropy", "effective_skills", "nmi"}
  assert summary["pretrain"]["diagnostics"]["ACT+SkillPlug"]["mean"]["routing_entropy_per_query"] is not None
  assert all("trainable" in r for r in summary["fewshot"]["results"])
  toy_rows = summary["toy"]["rows"]
  assert toy_rows["ACT"]["routing"] is None and toy_rows["ACT"]["fixed_skill_probe"] is None
  plug_row = toy_rows["ACT+SkillPlug"]
  assert 0.0 <= plug_row["routing"]["routing_entropy_per_query"][0] <= 1.0 + 1e-6
  assert 1.0 - 1e-6 <= plug_row["routing"]["effective_skills"][0] <= 4.0 + 1e-6
  assert plug_row["routing"]["nmi_task"] is not None and plug_row["fewshot_progress"] is not None
  assert len(plug_row["fixed_skill_probe"]["per_seed"][0]) == 4
  assert summary["toy"]["mined_labels"]["labeller"] == "toy_targets"
  assert summary["variants"][0]["routing_entropy_per_query"] is not None
  text = (tmp_path / "summary.md").read_text()
  assert "Toy problem" in text and "A>T>B" in text
  # the run directory: the config, the record (few-shot reads its protocol from it), the checkpoint
  run = Path(summary["runs"][0])
  rec = experiment.read_record(run)
  assert rec.config == "toy_skills" and rec.fewshot.taskset == toy.FEWSHOT_TASKSET
  assert run_files.read_config(run).max_steps == 2 and (run / "metrics.jsonl").exists()
  assert "diag/routing_entropy_per_query" in (run / "metrics.jsonl").read_text()

  # the same command again reads every evaluation back (a marker planted in one survives)
  evals = sorted((run / "eval").glob(f"{toy.TASKSET}_trials2_seed1000.json"))
  assert evals
  stored = json.loads(evals[0].read_text())
  stored["results"][0]["marker"] = 1
  evals[0].write_text(json.dumps(stored))
  assert pipeline.main(argv) == 0
  again = json.loads((tmp_path / "summary.json").read_text())
  assert any(r.get("marker") == 1 for r in again["pretrain"]["results"])
  assert pipeline.main(argv + ["--set", "eval_seed=7"]) == 0
  other = json.loads((tmp_path / "summary.json").read_text())
  assert not any(r.get("marker") for r in other["pretrain"]["results"])
  print(f"tiny toy pipeline: {wall:.0f} s")


@pytest.mark.slow
def test_oracle_variant_routes_by_the_primitive_the_batches_carry(tmp_path):
  """The oracle diagnostic: batches carry each step's primitive and the router_label term
  teaches the router to choose skill = primitive, which the paper's loss never does."""
  small = ["train.model.hidden=32", "train.model.heads=2", "train.model.ff=64", "train.model.enc_layers=1",
           "train.model.dec_layers=1", "train.model.plug.skill_latent_dim=4", "train.model.plug.alignment_dim=8",
           "train.max_steps=300", "train.warmup_steps=20", "train.demos=20"]
  arms = {v.name: arm for v, arm in experiment.expand(_config(*small))}
  data = toy_train.data_of(arms["paper"].train)
  batch = toy_train.sample_batch({k: jnp.asarray(v) for k, v in data.items()}, jax.random.PRNGKey(1), 256,
                                 arms["paper"].train.model.chunk)
  assert batch["skill_label"].shape == (256,) and set(np.unique(batch["skill_label"])) <= set(range(4))
  accs = {}
  for name in ("oracle", "paper"):
    cfg = dataclasses.replace(arms[name].train_config("skillplug", 0), workdir=str(tmp_path / name))
    run = toy_train.train(cfg, progress=False)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert ("loss/router_label" in rows[-1]) == (name == "oracle")
    _, params, step = loop.load_params(run)
    assert step == 300
    out = Policy(cfg.model).apply({"params": params}, batch, train=False)
    accs[name] = float(jnp.mean(out["router_probs"].argmax(-1) == batch["skill_label"]))
  assert accs["oracle"] > 0.8, accs
  assert accs["paper"] < 0.6, accs  # reconstruction alone does not find that partition
