"""LIBERO demonstrations: drawn starts apart from the benchmark's init states, the experts recorded
into our RLDS layout for LIBERO (proprioception, object state, both cameras, the instruction), read
back by the loader; names and mixes that cannot work refused with the reason."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

import envs
from envs.libero import layout, predicates, starts, suites
from envs.libero import scene as scenes
from skillplug_jax.data import demos, loader, rlds

TASK = "libero_object:0"  # pick up the alphabet soup and place it in the basket


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  cfg = demos.DemoConfig(taskset=TASK, demos=2, images=True, image_size=(32, 32), batch=2, backend="mujoco")
  return cfg, demos.make_demos(cfg, out=tmp_path_factory.mktemp("libero_ds"), progress=False)


def test_drawn_starts_are_new_placements_of_the_same_scene():
  drawn = starts.starts("libero_object", 0, 3, seed=0)
  bench = suites.init_states("libero_object", 0)
  assert drawn.shape == (3, bench.shape[1])
  assert starts.check_distinct("libero_object", 0, drawn) > 1e-3  # no drawn start is a benchmark one
  assert np.array_equal(starts.starts("libero_object", 0, 2, seed=0), drawn[:2])  # a seed's sequence
  s = scenes.scene("libero_object", 0)
  model = scenes.model(s)
  data = mujoco.MjData(model)
  goal = predicates.compile_goal(s, model)
  fixtures = {model.body(o["body"]).id for o in s.meta["objects"].values() if o["kind"] == "fixture"}
  movable = {model.body(o["body"]).id for o in s.meta["objects"].values() if o["kind"] == "object"}
  for state in drawn:
    scenes.set_init_state(model, data, state)
    assert not predicates.satisfied(goal, predicates.state_of(goal, data))[0]  # the task is still to do
    assert starts.penetration(model, data, movable, fixtures) <= starts.MAX_PENETRATION
  # The objects lie where LIBERO's samplers put them in the benchmark: within its spread of positions.
  adr = [o["joints"][0]["qposadr"] for o in s.meta["objects"].values() if o["kind"] == "object"]
  for a in adr:
    lo, hi = bench[:, 1 + a:3 + a].min(0) - 0.05, bench[:, 1 + a:3 + a].max(0) + 0.05
    assert np.all((drawn[:, 1 + a:3 + a] >= lo) & (drawn[:, 1 + a:3 + a] <= hi))


def test_a_libero_dataset_holds_successful_expert_episodes_with_their_instruction(dataset):
  cfg, path = dataset
  builder = rlds.open_dataset(path)
  assert rlds.spec_of(builder) == rlds.DatasetSpec((TASK,), (32, 32), "libero")
  d = loader.load_demonstrations(path, images=True)
  assert d.layout is rlds.LIBERO and d.num_episodes == 2
  assert d.language == ("pick up the alphabet soup and place it in the basket",)
  widths = {k: v.shape[1:] for k, v in d.steps.items()}
  assert widths == {"joint_pos": (7,), "gripper_qpos": (2,), "eef_pos": (3,), "eef_quat": (4,),
                    "object_state": (layout.OBJECT_STATE_DIM,), "agentview_rgb": (32, 32, 3),
                    "eye_in_hand_rgb": (32, 32, 3), "action": (7,)}
  s = scenes.scene("libero_object", 0)
  soup = layout.movable_objects(s.meta).index("alphabet_soup_1")
  for e in range(d.num_episodes):
    ep = d.episode(e)
    assert np.all(np.abs(ep["action"]) <= 1.0)
    # the can starts on the floor and ends in the basket, lower than it was carried, the fingers open
    z = ep["object_state"][:, 7 * soup + 2]
    assert z.max() > z[-1] + 0.05, "the can was lifted and put down"
    assert ep["gripper_qpos"][-1, 0] - ep["gripper_qpos"][-1, 1] > 0.06, "released: the fingers open"
    assert ep["agentview_rgb"].std() > 10 and not np.array_equal(ep["eye_in_hand_rgb"][0], ep["eye_in_hand_rgb"][-1])
    assert len(ep["action"]) < suites.TIME_LIMITS["libero_object"] + 10
  meta = builder.info.metadata
  assert meta["per_task"][TASK]["kept"] == 2 and meta["layout"] == "libero"
  batch = loader.ChunkLoader(d, 4, chunk=5, images=True).numpy_batch(0)
  assert {"gripper_qpos", "eef_pos", "eef_quat", "agentview_rgb", "eye_in_hand_rgb"} <= set(batch)
  assert batch["actions"].shape == (4, 5, 7)


def test_the_mined_phases_read_libero_demonstrations_in_order(dataset):
  """train.skill_labels=tabletop_phases on LIBERO (its gripper command is +-1, our labellers read an
  opening in metres: `layout.tabletop_gripper`): each demonstration runs free -> grasp ->
  transport -> release, as the expert did it."""
  from skillplug_jax.data import segments
  _, path = dataset
  d = loader.load_demonstrations(path)
  np.testing.assert_allclose(layout.tabletop_gripper(np.array([[0.3, -1.0], [0.3, 1.0]]))[:, -1], [0.04, 0.0])
  for e in range(d.num_episodes):
    ep = d.episode(e)
    labels = segments.tabletop_phases(ep["joint_pos"], ep["object_state"], layout.tabletop_gripper(ep["action"]))
    firsts = [int(np.flatnonzero(labels == q)[0]) for q in (1, 2, 3)]  # grasp, transport, release
    assert labels[0] == 0 and firsts == sorted(firsts), labels


def test_the_dataset_is_reused_and_one_of_another_layout_is_refused(dataset):
  cfg, path = dataset
  assert demos.make_demos(cfg, out=path.parent, progress=False) == path
  with pytest.raises(rlds.DatasetError, match="holds"):  # the same directory read as DISCOVERSE's
    demos._reused(dataclasses.replace(cfg, taskset="jujube_pick"), path, False)


def test_libero_names_and_mixes_that_cannot_work_are_refused():
  assert envs.taskset("libero_goal")[:2] == ("libero_goal:0", "libero_goal:1")
  assert envs.taskset("libero_10:9") == ("libero_10:9",)
  with pytest.raises(ValueError, match="unknown task 12 of LIBERO suite 'libero_object'"):
    envs.taskset("libero_object:12")
  with pytest.raises(ValueError, match="mixes LIBERO and DISCOVERSE"):
    demos.DemoConfig(taskset="libero_object,jujube_pick", backend="mujoco")
  with pytest.raises(ValueError, match="C engine"):
    demos.DemoConfig(taskset="libero_object", backend="mjx-warp")
  with pytest.raises(ValueError, match="runs on envs.libero's engine"):
    envs.make("libero_object:0", backend="mujoco")


@pytest.mark.slow
def test_the_libero_protocol_runs_end_to_end_through_the_pipeline(tmp_path):
  """The path a LIBERO experiment takes (experiments/configs/libero_quick.py, shrunk): demonstrations,
  ACT+SkillPlug reading LIBERO's proprioception (16 numbers), object state and instruction, trials on
  the benchmark's init states with its routing written, then the few-shot step on a whole unseen
  "suite" (`fewshot.per=taskset`: here one task) with the router and action head tuned."""
  from experiments import pipeline
  from skillplug_jax import experiment
  from skillplug_jax.data import language
  from skillplug_jax.evaluate import protocol
  from skillplug_jax.evaluate.policy_controller import load_controller
  from skillplug_jax.train import run_files

  exp = experiment.get("libero_quick", [
      "train.taskset=libero_object:1", "train.demos=1", "train.max_steps=4", "train.ckpt_every=4",
      "train.model.hidden=32", "train.model.heads=2", "train.model.ff=64", "train.model.enc_layers=1",
      "train.model.dec_layers=1", "train.model.chunk=10", "train.batch_size=4", "train.warmup_steps=1",
      "trials=2", "eval_batch=2", "fewshot.taskset=libero_object:0", "fewshot.demos=1", "fewshot.steps=2",
      "policies=skillplug", "workers=1"])
  pipeline.make_datasets(exp, tmp_path)
  part = pipeline.job(exp, "skillplug", 0, tmp_path)
  run = part["run"]
  controller, trained = load_controller(run)
  assert trained.model.proprio == ("joint_pos", "gripper_qpos", "eef_pos", "eef_quat")
  assert set(controller.weights["stats"]) == {"action", "joint_pos", "gripper_qpos", "eef_pos", "eef_quat",
                                              "object_state"}
  assert controller.weights["params"]["encoder"]["joint_proj"]["kernel"].shape == (16, 32)
  # it reads its instruction, in the vocabulary it trained with (kept in the run's statistics)
  assert tuple(run_files.read_stats(run)[language.VOCABULARY_KEY]) == language.benchmark_vocabulary()
  words = controller.instruction("pick up the alphabet soup and place it in the basket")
  assert words.shape == (24,) and (words > language.UNK).sum() == 11
  (pre,) = part["pretrain"]
  assert pre["task"] == "libero_object:1" and pre["trials"] == 2 and len(pre["trial_libero_success"]) == 2
  # four steps of training do not solve the task: both rules agree there is no success
  assert pre["success_rate"] == 0.0 and pre["libero_success_rate"] == 0.0
  routing = protocol.read_routing(pre["routing_file"])
  assert routing["routing"].shape[0] == 2 and routing["routing"].shape[2] == 8  # K = 8, a row per trial
  assert pre["diagnostics"]["queries"] == sum(pre["trial_queries"]) > 0
  (few,) = part["fewshot"]
  assert few["task"] == "libero_object:0" and sorted(few["trainable"]) == ["action_head", "router"]
  assert few["run"].endswith("_fewshot/libero_object:0") and few["source"] == run
  # the skill probes' geometry reads a LIBERO run's demonstrations (its +-1 gripper command mined into
  # phases), on the run's own tasks; tasks its dataset lacks are named
  from pathlib import Path

  from experiments import skill_probes
  geo = skill_probes.geometry(Path(run), None, ("libero_object:1",))
  assert set(geo["tasks"]) == {"libero_object:1"} and len(geo["skill_cosine"]) == 8
  assert sum(map(sum, geo["phase_skill_counts"])) == geo["tasks"]["libero_object:1"]["states"] == 4
  with pytest.raises(ValueError, match="none of the tasks libero_goal:0"):
    skill_probes.geometry(Path(run), None, ("libero_goal:0",))
