"""Run directly, as on a machine without a display: what make exports is arranged by the code itself.

MUJOCO_GL: envs/headless.py picks EGL (else OSMesa) before MuJoCo is imported,
and a renderer that cannot start is a named error in the caller, not a hang
(issue 28: `skillplug demos` without MUJOCO_GL waited 11 minutes on a dead
renderer thread). GLIBC_TUNABLES: the entry points restart themselves with
the Makefile's value (skillplug_jax/startup.py). Each case runs in a
subprocess with the variable removed from its environment.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import envs
from envs import appearance, headless
from envs.mujoco_batch import CameraRenderer
from skillplug_jax import startup
from skillplug_jax.data import loader, rlds
from skillplug_jax.data.demos import DemoConfig
from skillplug_jax.train import loop
from synthetic import synthetic_episode, write_synthetic, write_two_task_demos
from test_malloc_tunables import glibc, makefile_tunables
from test_train import TASKS, tiny

ROOT = Path(__file__).resolve().parents[1]
SKILLPLUG = str(Path(sys.executable).parent / "skillplug")
TIMEOUT_S = 150  # imports and a checkpoint's restore on a busy 2-core machine; the bug hung for good
DISPLAYLESS = ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")


def run(cmd: list[str], drop=DISPLAYLESS, **extra) -> tuple[subprocess.CompletedProcess, float]:
  """`cmd` in the repository root, without the variables `drop`, plus `extra`; (result, seconds)."""
  env = {k: v for k, v in os.environ.items() if k not in drop}
  env.update(JAX_PLATFORMS="cpu", **extra)
  t0 = time.monotonic()
  out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
  return out, time.monotonic() - t0


# ---- MUJOCO_GL ----------------------------------------------------------------

@pytest.mark.slow
def test_demos_render_images_with_mujoco_gl_unset(tmp_path):
  """The README's `skillplug demos`, run directly without MUJOCO_GL or a display."""
  out, _ = run([SKILLPLUG, "demos", "--taskset", "jujube_pick", "--demos", "1", "--batch", "1",
                "--image-size", "16", "--backend", "mujoco", "--out", str(tmp_path)])
  assert out.returncode == 0, out.stderr[-3000:]
  cfg = DemoConfig(taskset="jujube_pick", demos=1, images=True, image_size=(16, 16), backend="mujoco")
  d = loader.load_demonstrations(tmp_path / cfg.name, images=True)
  for cam in ("side", "wrist"):
    assert d.steps[f"{cam}_rgb"].std() > 10, cam  # drawn scenes, not blank buffers
  recorded = json.loads((tmp_path / cfg.name / "metadata.json").read_text())["per_task"]["jujube_pick"]
  assert 0 < recorded["render_s"] < recorded["wall_s"]  # the rendering share of recording (issue 29)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """A tiny state policy and a tiny image policy (16x16), trained 2 steps each on random demos."""
  data = tmp_path_factory.mktemp("datasets")
  rng = np.random.default_rng(0)
  write_two_task_demos(data, rng, TASKS)
  size = (16, 16)
  name = DemoConfig(taskset=",".join(TASKS), demos=3, images=True, image_size=size, backend="mujoco").name
  records = [rlds.EpisodeRecord(task, 0, i, synthetic_episode(rng, int(rng.integers(12, 20)), images=size))
             for task in TASKS for i in range(3)]
  write_synthetic(data, name, rlds.DatasetSpec(TASKS, size), records)
  root = tmp_path_factory.mktemp("runs")
  short = ("max_steps=2", "ckpt_every=2", "backend=mujoco")
  state = loop.train(tiny(data, root / "state", "act", *short), progress=False)
  images = ("model.use_images=true", "model.image_size=16,16", "model.backbone_width=4")
  image = loop.train(tiny(data, root / "image", "act", *short, *images), progress=False)
  image_sp = loop.train(tiny(data, root / "image_skillplug", "skillplug", *short, *images), progress=False)
  assert not loop.load_params(state)[0].model.use_images and loop.load_params(image)[0].model.use_images
  return {"state": state, "image": image, "image_skillplug": image_sp}


@pytest.mark.slow
def test_an_image_policy_is_evaluated_on_its_own_cameras_whatever_the_caller_asks(runs):
  """A caller that does not ask for rendering (the skill probes did not) still shows an image
  policy its cameras at its own size; a different size is a named error, not a silent rescale."""
  from skillplug_jax.evaluate import protocol
  from skillplug_jax.evaluate.policy_controller import load_controller
  controller, _ = load_controller(runs["image"])
  assert controller.image_size == (16, 16) and load_controller(runs["state"])[0].image_size is None
  r = protocol.evaluate_task(TASKS[0], controller, trials=1, batch=1, backend="mujoco")
  assert r["renderer"] == "mujoco-opengl" and r["render_s"] > 0
  with pytest.raises(ValueError, match="reads 16x16 camera images; cannot evaluate it on 64x64 ones"):
    protocol.evaluate_task(TASKS[0], controller, trials=1, render=True, image_size=(64, 64), backend="mujoco")


@pytest.mark.slow
def test_skill_probe_geometry_reads_an_image_policys_cameras(runs):
  """The probes' demonstration states carry both cameras for an image policy, so that its
  skills' geometry (and CKA against the image ACT encoder) is computed, not a KeyError."""
  from experiments import skill_probes
  states = skill_probes.demo_states(runs["image_skillplug"], TASKS)
  assert set(states) == set(TASKS)
  for obs in states.values():
    assert obs["side_rgb"].shape[1:] == (16, 16, 3) and obs["wrist_rgb"].dtype == np.uint8
  geo = skill_probes.geometry(runs["image_skillplug"], runs["image"], TASKS)["tasks"]
  for task in TASKS:
    assert geo[task]["states"] == len(states[task]["side_rgb"])
    assert 0.0 <= geo[task]["cka_fused_vs_act"] <= 1.0 + 1e-6, geo[task]


@pytest.mark.parametrize("case", ["demos", "eval --videos", "image policy eval"])
@pytest.mark.slow
def test_a_renderer_that_cannot_start_is_a_named_error(case, runs, tmp_path):
  """GLFW without a display: a one-line error naming the cause and the fix, well within the timeout."""
  cmd = {"demos": ["demos", "--taskset", "jujube_pick", "--demos", "1", "--batch", "2", "--image-size", "16",
                   "--out", str(tmp_path)],
         "eval --videos": ["eval", "--runs", str(runs["state"]), "--videos", "1", "--video-dir", str(tmp_path)],
         "image policy eval": ["eval", "--runs", str(runs["image"])]}[case]
  if case != "demos":
    cmd += ["--taskset", "jujube_pick", "--trials", "2", "--batch", "2"]
  out, seconds = run([SKILLPLUG, *cmd, "--backend", "mujoco"], MUJOCO_GL="glfw")
  print(f"{case}: {seconds:.1f} s")
  assert out.returncode == 1, out.stderr[-3000:]
  assert "skillplug: error: MuJoCo's OpenGL renderer could not start (MUJOCO_GL=glfw; no DISPLAY" in out.stderr
  assert "MUJOCO_GL=egl" in out.stderr and "apt install libosmesa6" in out.stderr
  assert "Traceback" not in out.stderr, out.stderr[-3000:]


def test_a_renderer_thread_that_dies_is_an_error_not_a_wait():
  env = envs.make("jujube_pick", num_envs=2, backend="mujoco")
  cams = CameraRenderer(env.env.mj_model, (16, 16), nthread=2)
  qpos = np.tile(env.env.mj_model.qpos0, (2, 1))
  assert cams.render(qpos, np.arange(2))["side"].std() > 0
  cams._jobs[1].put(None)  # the second worker ends, as one that crashed
  cams._threads[1].join(10)
  t0 = time.monotonic()
  with pytest.raises(headless.RendererError, match="renderer thread died"):
    cams.render(qpos, np.arange(2))
  assert time.monotonic() - t0 < 10
  cams.close()


def test_render_processes_draw_what_threads_draw_with_and_without_looks():
  """processes=True (envs.render_process) is the same drawing in other processes: the same pixels,
  looks included, and back to the model's own look after a looked draw."""
  env = envs.make("jujube_pick", num_envs=3, backend="mujoco")
  model = env.env.mj_model
  qpos = np.tile(model.qpos0, (3, 1))
  looks = {f: np.repeat(np.asarray(getattr(model, f))[None], 3, 0) for f in appearance.LOOK_FIELDS}
  looks["geom_rgba"][1, :, :3] = 1.0 - looks["geom_rgba"][1, :, :3]  # trial 1 in other colours
  drawn = {}
  for processes in (False, True):
    cams = CameraRenderer(model, (16, 16), nthread=2, processes=processes)
    try:
      drawn[processes] = [{c: a.copy() for c, a in cams.render(qpos, ids, looks=lk).items()}
                          for ids, lk in ((np.arange(3), None), (np.arange(3), looks), (np.array([0, 2]), None))]
    finally:
      cams.close()
  for threads, procs in zip(drawn[False], drawn[True]):
    for c in threads:
      np.testing.assert_array_equal(procs[c], threads[c], err_msg=c)
  plain, looked, after = drawn[True]
  assert plain["side"].std() > 0 and np.abs(looked["side"][1].astype(int) - plain["side"][1]).mean() > 5
  for c in plain:
    np.testing.assert_array_equal(looked[c][[0, 2]], plain[c][[0, 2]], err_msg=c)
    np.testing.assert_array_equal(after[c][[0, 2]], plain[c][[0, 2]], err_msg=c)
    assert not after[c][1].any()  # not asked for: left as it was (zeros)


def test_a_render_process_that_dies_is_an_error_not_a_wait():
  env = envs.make("jujube_pick", num_envs=2, backend="mujoco")
  cams = CameraRenderer(env.env.mj_model, (16, 16), nthread=2, processes=True)
  qpos = np.tile(env.env.mj_model.qpos0, (2, 1))
  assert cams.render(qpos, np.arange(2))["side"].std() > 0
  proc, _ = cams._procs[1]
  proc.kill()  # as one that crashed
  proc.wait(10)
  t0 = time.monotonic()
  with pytest.raises(headless.RendererError, match="render process (died|closed its socket)"):
    cams.render(qpos, np.arange(2))
  assert time.monotonic() - t0 < 10
  cams.close()
  with pytest.raises(headless.RendererError, match="closed"):
    cams.render(qpos, np.arange(2))


def test_a_render_process_that_cannot_start_names_the_cause(monkeypatch):
  """GLFW with no display, in the render process: the caller gets the named error, not a wait."""
  env = envs.make("jujube_pick", num_envs=2, backend="mujoco")
  monkeypatch.setenv("MUJOCO_GL", "glfw")  # what the process inherits
  for name in ("DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM"):
    monkeypatch.delenv(name, raising=False)
  t0 = time.monotonic()
  with pytest.raises(headless.RendererError, match=r"could not start \(MUJOCO_GL=glfw; no DISPLAY.*in a render process"):
    CameraRenderer(env.env.mj_model, (16, 16), nthread=1, processes=True)
  assert time.monotonic() - t0 < 60


def test_choose_gl_picks_a_headless_platform(monkeypatch):
  """EGL first, then OSMesa; a user's MUJOCO_GL or PyOpenGL platform is kept; none found: GLFW,
  whose failure says what to install."""
  monkeypatch.delitem(sys.modules, "mujoco")  # as before `import mujoco` (restored afterwards)
  for name in DISPLAYLESS:
    monkeypatch.delenv(name, raising=False)

  def libraries(*found):
    monkeypatch.setattr(headless, "_loads", lambda names: any(n in found for n in names))

  libraries("libEGL.so.1", "libOSMesa.so.8")
  assert headless.choose_gl() == "egl" and os.environ["MUJOCO_GL"] == "egl"
  monkeypatch.delenv("MUJOCO_GL")
  libraries("libOSMesa.so.8")
  assert headless.choose_gl() == "osmesa" and os.environ["MUJOCO_GL"] == "osmesa"
  monkeypatch.setenv("MUJOCO_GL", "glfw")
  assert headless.choose_gl() == "glfw"
  monkeypatch.delenv("MUJOCO_GL")
  monkeypatch.setenv("PYOPENGL_PLATFORM", "egl")
  assert headless.choose_gl() == "egl"
  monkeypatch.delenv("MUJOCO_GL")
  monkeypatch.delenv("PYOPENGL_PLATFORM")
  libraries()
  assert headless.choose_gl() == "" and "MUJOCO_GL" not in os.environ
  msg = str(headless.renderer_error(RuntimeError("boom")))
  assert "MUJOCO_GL unset, so GLFW; no DISPLAY" in msg and "neither libEGL nor libOSMesa" in msg, msg
  assert "apt install libegl1" in msg and "apt install libosmesa6" in msg and "boom" in msg
  monkeypatch.setenv("MUJOCO_GL", "osmesa")  # else `import mujoco` fails deep inside PyOpenGL
  with pytest.raises(ImportError, match="libOSMesa is not installed: `apt install libosmesa6`"):
    headless.choose_gl()


# ---- GLIBC_TUNABLES -----------------------------------------------------------

def test_startup_sets_what_the_makefile_exports():
  assert startup.TUNABLES == makefile_tunables()


def tunables_seen(cmd: list[str], tmp_path: Path, **extra) -> str:
  """GLIBC_TUNABLES as the process that ran `cmd` to the end saw it: a sitecustomize prints it at exit
  (a process replaced by exec runs no exit handlers, so only the last one prints)."""
  (tmp_path / "sitecustomize.py").write_text(
      "import atexit, os, sys\n"
      "atexit.register(lambda: print('TUNABLES=' + repr(os.environ.get('GLIBC_TUNABLES')), file=sys.stderr))\n")
  out, seconds = run(cmd, drop=("GLIBC_TUNABLES", startup._RESTARTED), PYTHONPATH=str(tmp_path), **extra)
  print(f"{cmd[1:]}: {seconds:.1f} s")
  assert out.returncode == 0, out.stderr[-3000:]
  (line,) = [x for x in out.stderr.splitlines() if x.startswith("TUNABLES=")]
  return line.removeprefix("TUNABLES=")


@glibc
@pytest.mark.parametrize("cmd", [[SKILLPLUG, "--help"], [sys.executable, "-m", "skillplug_jax.cli", "--help"],
                                 [sys.executable, "-m", "experiments.configs.quick"]],
                         ids=["skillplug", "python -m skillplug_jax.cli", "python -m experiments..."])
@pytest.mark.slow
def test_entry_points_start_with_the_makefile_tunables(cmd, tmp_path):
  assert tunables_seen(cmd, tmp_path) == repr(startup.TUNABLES)


@glibc
@pytest.mark.slow
def test_a_users_tunables_are_kept_and_a_library_import_restarts_nothing(tmp_path):
  assert tunables_seen([SKILLPLUG, "--help"], tmp_path, GLIBC_TUNABLES="glibc.malloc.check=0") \
      == repr("glibc.malloc.check=0")
  assert tunables_seen([SKILLPLUG, "--help"], tmp_path, GLIBC_TUNABLES="") == repr("")
  assert tunables_seen([sys.executable, "-c", "import experiments, skillplug_jax.cli"], tmp_path) == "None"
