"""Appearance shift (ours, issue 29): other colours and light for the cameras, the same physics.

The default appearance draws what the renderer drew before the option
existed; the shifted one changes every trial's pixels, the same way for a
trial at any batch size, and nothing the physics or the success check sees.
"""

import copy
import json

import jax
import mujoco
import numpy as np
import pytest

import envs
from envs import appearance, mujoco_batch
from envs import rollout as env_rollout
from envs.mujoco_batch import CameraRenderer
from envs.robot import CAMERAS
from skillplug_jax.evaluate import protocol

TASK = "stack_block"  # three objects told apart by colour alone
SIZE = (32, 32)
SEED = protocol.EVAL_SEED


def _images(state) -> dict:
  return {c: np.asarray(state.obs[f"{c}_rgb"]) for c in CAMERAS}


def _reference_images(model: mujoco.MjModel, qpos: np.ndarray) -> dict:
  """Both cameras drawn as CameraRenderer drew them before appearances existed: one
  mujoco.Renderer on a copy of the model, offscreen buffer the image size, no
  multisampling, the same effects off, kinematics and camera/light poses from qpos."""
  m = copy.copy(model)
  m.vis.global_.offwidth, m.vis.global_.offheight = SIZE[1], SIZE[0]
  m.vis.quality.offsamples = 0
  out = {c: np.zeros((len(qpos),) + SIZE + (3,), np.uint8) for c in CAMERAS}
  with mujoco.Renderer(m, *SIZE) as r:
    for flag in mujoco_batch._RENDER_FLAGS_OFF:
      r.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = 0
    d = mujoco.MjData(m)
    for i, q in enumerate(qpos):
      d.qpos[:] = q
      mujoco.mj_kinematics(m, d)
      mujoco.mj_camlight(m, d)
      for c in CAMERAS:
        r.update_scene(d, c)
        out[c][i] = r.render()
  return out


def test_default_appearance_draws_what_the_renderer_drew_before():
  """Bit for bit: the default environment, the renderer without looks, the renderer
  after it drew shifted looks, and a plain mujoco.Renderer drawing as before."""
  keys = env_rollout.reset_keys(SEED, 3)
  default = envs.make(TASK, num_envs=3, render=True, image_size=SIZE, backend="mujoco", appearance="default")
  plain = envs.make(TASK, num_envs=3, render=True, image_size=SIZE, backend="mujoco")
  assert default.appearance == plain.appearance == "default"
  s = default.reset(keys)
  assert "appearance" not in s.info
  got = _images(s)
  qpos = np.asarray(default._saved["qpos"])
  for c in CAMERAS:
    np.testing.assert_array_equal(got[c], _images(plain.reset(keys))[c], err_msg=c)
  ref = _reference_images(default.env.mj_model, qpos)
  cams = CameraRenderer(default.env.mj_model, SIZE, nthread=2)
  before = cams.render(qpos, np.arange(3))
  looks = jax.device_get(appearance.looks_fn(default.env.mj_model)(keys))
  shifted = {c: a.copy() for c, a in cams.render(qpos, np.arange(3), looks=looks).items()}
  after = cams.render(qpos, np.arange(3))  # the workers' models are back to the model's own look
  cams.close()
  for c in CAMERAS:
    np.testing.assert_array_equal(got[c], ref[c], err_msg=c)
    np.testing.assert_array_equal(before[c], ref[c], err_msg=c)
    np.testing.assert_array_equal(after[c], ref[c], err_msg=c)
    assert not np.array_equal(shifted[c], ref[c])
  assert ref["side"].std() > 5 and ref["wrist"].std() > 5  # not blank


def test_shifted_images_differ_for_the_same_state_and_trials_differ():
  keys = env_rollout.reset_keys(SEED, 3)
  default = envs.make(TASK, num_envs=3, render=True, image_size=SIZE, backend="mujoco")
  shifted = envs.make(TASK, num_envs=3, render=True, image_size=SIZE, backend="mujoco", appearance="shifted")
  a, b = default.reset(keys), shifted.reset(keys)
  np.testing.assert_array_equal(np.asarray(a.pipeline_state.qpos), np.asarray(b.pipeline_state.qpos))
  ia, ib = _images(a), _images(b)
  for c in CAMERAS:
    for i in range(3):  # every trial, both cameras: clearly, not a pixel or two
      assert np.abs(ia[c][i].astype(int) - ib[c][i].astype(int)).mean() > 5, (c, i)
  # two trials drawn from one state: their looks alone tell them apart
  cams = CameraRenderer(shifted.env.mj_model, SIZE, nthread=2)
  qpos = np.tile(np.asarray(shifted._saved["qpos"][:1]), (2, 1))
  two = cams.render(qpos, np.arange(2), looks=jax.device_get(b.info["appearance"]))
  cams.close()
  for c in CAMERAS:
    assert np.abs(two[c][0].astype(int) - two[c][1].astype(int)).mean() > 5, c


def test_a_trial_looks_the_same_at_any_batch_size():
  """Trial i's look comes from its reset key: trials 2 and 3 of a batch of 4 are drawn as in a batch of 2."""
  keys = env_rollout.reset_keys(SEED, 4)
  four = envs.make(TASK, num_envs=4, render=True, image_size=SIZE, backend="mujoco", appearance="shifted")
  two = envs.make(TASK, num_envs=2, render=True, image_size=SIZE, backend="mujoco", appearance="shifted")
  s4, s2 = four.reset(keys), two.reset(keys[2:])
  for f in appearance.LOOK_FIELDS:
    np.testing.assert_array_equal(np.asarray(s4.info["appearance"][f][2:]), np.asarray(s2.info["appearance"][f]))
  i4, i2 = _images(s4), _images(s2)
  for c in CAMERAS:
    np.testing.assert_array_equal(i4[c][2:], i2[c], err_msg=c)
  rgba = np.asarray(s4.info["appearance"]["geom_rgba"])
  table = envs.make(TASK).env.mj_model.geom("table").id
  assert len({tuple(np.round(rgba[i, table], 4)) for i in range(4)}) == 4  # every trial its own table


@pytest.mark.slow
def test_the_physics_is_the_same_with_and_without_the_shift():
  """Same actions, same states, bit for bit; the expert's evaluation (paired trials)
  has the same outcomes, and the result records the appearance."""
  keys = env_rollout.reset_keys(SEED, 2)
  runs = {}
  for name in appearance.APPEARANCES:
    benv = envs.make(TASK, num_envs=2, render=True, image_size=SIZE, backend="mujoco", appearance=name)
    s = benv.reset(keys)
    rng = np.random.default_rng(0)
    states = [s]
    for _ in range(4):
      action = envs.robot.HOME_QPOS + rng.normal(0, 0.2, (2, 7))
      s = benv.step(s, jax.numpy.asarray(action, jax.numpy.float32))
      states.append(s)
    runs[name] = states
  for a, b in zip(runs["default"], runs["shifted"]):
    np.testing.assert_array_equal(np.asarray(a.pipeline_state.qpos), np.asarray(b.pipeline_state.qpos))
    np.testing.assert_array_equal(np.asarray(a.pipeline_state.qvel), np.asarray(b.pipeline_state.qvel))
    for k in ("joint_pos", "object_state"):
      np.testing.assert_array_equal(np.asarray(a.obs[k]), np.asarray(b.obs[k]), err_msg=k)
    np.testing.assert_array_equal(np.asarray(a.done), np.asarray(b.done))
    assert not np.array_equal(np.asarray(a.obs["side_rgb"]), np.asarray(b.obs["side_rgb"]))
  controller = env_rollout.expert_controller(envs.make("jujube_pick", num_envs=1, backend="mujoco"))
  out = {name: protocol.evaluate_task("jujube_pick", controller, trials=2, batch=2, render=True, image_size=SIZE,
                                      backend="mujoco", appearance=name)
         for name in appearance.APPEARANCES}
  assert out["default"]["appearance"] == "default" and out["shifted"]["appearance"] == "shifted"
  assert out["default"]["successes"] == 2
  for k in ("trial_success", "trial_queries", "trial_success_step"):
    assert out["default"][k] == out["shifted"][k], k


@pytest.mark.slow
def test_shifted_on_mjx_warp_batches_the_looks_through_warps_renderer():
  """MJX-Warp's ray caster takes the looks as per-world model fields: the same physics,
  other pixels, and trial i drawn alike at two batch sizes."""
  keys = env_rollout.reset_keys(SEED, 3)
  # the batches stay referenced until their render calls finish: a context dies with its batch
  batches = [envs.make(TASK, num_envs=n, render=True, image_size=SIZE, backend="mjx-warp", appearance=name)
             for n, name in ((3, "default"), (3, "shifted"), (1, "shifted"))]
  a, b, c = (jax.jit(e.reset)(k) for e, k in zip(batches, (keys, keys, keys[2:])))
  jax.effects_barrier()
  np.testing.assert_array_equal(np.asarray(a.pipeline_state.qpos), np.asarray(b.pipeline_state.qpos))
  ia, ib, ic = _images(a), _images(b), _images(c)
  for cam in CAMERAS:
    for i in range(3):
      assert np.abs(ia[cam][i].astype(int) - ib[cam][i].astype(int)).mean() > 5, (cam, i)
    np.testing.assert_array_equal(ib[cam][2:], ic[cam], err_msg=cam)


@pytest.mark.slow
def test_looks_keep_the_task_readable():
  """Over many trials of every task: only the table and the objects are recoloured, the robot
  keeps its colours, objects keep their hue within the turn allowed, the table stands
  apart from everything on it, and the light stays within its range."""
  np.testing.assert_allclose(appearance.cielab(np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])),
                             [[53.24, 80.09, 67.20], [100.0, 0.0, 0.0]], atol=0.05)  # sRGB red, white (D65)
  keys = env_rollout.reset_keys(SEED, 64)
  for task in envs.TASKS:
    m = envs.make(task).env.mj_model
    p = appearance.parts(m)
    looks = jax.device_get(appearance.looks_fn(m)(keys))
    rgba = looks["geom_rgba"]
    robot = (p.object_of < 0) & (np.arange(m.ngeom) != p.table)
    np.testing.assert_array_equal(rgba[:, robot], np.broadcast_to(m.geom_rgba[robot], rgba[:, robot].shape))
    np.testing.assert_array_equal(rgba[..., 3], np.broadcast_to(m.geom_rgba[:, 3], rgba[..., 3].shape))
    hue = np.asarray(appearance.rgb_to_hsv(rgba[..., :3]))[..., 0]
    base = np.asarray(appearance.rgb_to_hsv(m.geom_rgba[:, :3]))
    coloured = (p.object_of >= 0) & (base[:, 1] > 0.2)  # a hue worth the name
    turn = (hue[:, coloured] - base[coloured, 0] + 0.5) % 1.0 - 0.5
    assert np.all(np.abs(turn) <= appearance.OBJECT_HUE_TURN + 1e-3), task
    others = np.arange(m.ngeom) != p.table
    lab = np.asarray(appearance.cielab(rgba[..., :3]))
    contrast = np.linalg.norm(lab[:, p.table, None] - lab[:, others], axis=-1).min(1)
    assert contrast.min() >= appearance.MIN_CONTRAST, task
    scale = looks["light_diffuse"][:, 0] / m.light_diffuse[0]
    assert scale.min() >= appearance.LIGHT_SCALE[0] * appearance.LIGHT_TINT[0] - 1e-6
    assert scale.max() <= appearance.LIGHT_SCALE[1] * appearance.LIGHT_TINT[1] + 1e-6
    assert len({tuple(np.round(rgba[i, p.table], 4)) for i in range(64)}) == 64  # every trial another table


def test_an_unknown_appearance_is_a_clear_error(capsys):
  from skillplug_jax import cli
  message = "unknown appearance 'neon'; valid appearances: default, shifted"
  with pytest.raises(ValueError, match=message):
    envs.make(TASK, render=True, backend="mujoco", appearance="neon")
  with pytest.raises(ValueError, match=message):
    protocol.evaluate_task(TASK, None, trials=1, appearance="neon")
  with pytest.raises(ValueError, match=message):  # before any run is loaded
    protocol.evaluate_runs(["no/such/run"], [TASK], 1, appearance="neon")
  parser = cli.build_parser()
  assert parser.parse_args(["eval", "--ckpt", "r"]).appearance == "default"
  for name in appearance.APPEARANCES:
    assert parser.parse_args(["eval", "--ckpt", "r", "--appearance", name]).appearance == name
  with pytest.raises(SystemExit):
    parser.parse_args(["eval", "--ckpt", "r", "--appearance", "neon"])
  assert "invalid choice: 'neon'" in capsys.readouterr().err


def test_the_eval_command_passes_the_appearance_and_the_summary_records_it(tmp_path, monkeypatch, capsys):
  """`skillplug eval --appearance shifted` reaches every evaluate_task, and the summary JSON says which."""
  from types import SimpleNamespace
  from skillplug_jax import atomic_json, cli
  from skillplug_jax.evaluate import report
  seen = []
  cfg = SimpleNamespace(model=SimpleNamespace(use_images=True, image_size=SIZE), seed=0, backend="mujoco")
  monkeypatch.setattr(protocol, "load_controller", lambda run, query_every: (None, cfg))
  monkeypatch.setattr(protocol.experiment, "read_record", lambda run: {})
  monkeypatch.setattr(protocol.groups, "row_fields", lambda cfg, record: {"policy": "ACT"})
  monkeypatch.setattr(protocol, "evaluate_task", lambda *a, **kw: seen.append(kw["appearance"]) or {"trials": 1})
  monkeypatch.setattr(protocol.tables, "summarise", lambda results, tasks: {})

  def write(out, what, dest):
    atomic_json.write_json_atomic(f"{dest}.json", out)
    return what

  monkeypatch.setattr(report, "write", write)
  assert cli.main(["eval", "--ckpt", "r", "--taskset", "jujube_pick,drawer_open", "--trials", "1",
                   "--backend", "mujoco", "--appearance", "shifted", "--out", str(tmp_path / "ev")]) == 0
  assert seen == ["shifted", "shifted"]
  assert json.loads((tmp_path / "ev.json").read_text())["appearance"] == "shifted"
  assert "appearance shifted" in capsys.readouterr().out
