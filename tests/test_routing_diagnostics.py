"""experiments/routing_diagnostics.py on constructed routing folders."""

import json

import numpy as np
import pytest

from experiments import routing_diagnostics as rd


def _folder(tmp_path, arrays):
  index = []
  for i, (task, routing) in enumerate(arrays.items()):
    name = f"skillplug_seed0_pretrain_{task}.npz"
    np.savez(tmp_path / name, routing=routing.astype(np.float16), task=task)
    index.append(dict(policy="ACT+SkillPlug", seed=0, stage="pretrain", task=task, file=name))
  (tmp_path / "index.json").write_text(json.dumps(index))
  return tmp_path


def _padded(episodes, width):
  out = np.full((len(episodes), width, episodes[0].shape[-1]), np.nan)
  for i, ep in enumerate(episodes):
    out[i, :len(ep)] = ep
  return out


def test_routing_by_phase_and_by_task(tmp_path):
  k, eye = 4, np.eye(4)
  # task a: skill 0 in the first half of every episode, skill 1 in the second; task b: skill 2 throughout
  phased = [np.concatenate([np.tile(eye[0], (n // 2, 1)), np.tile(eye[1], (n - n // 2, 1))]) for n in (8, 12, 16)]
  constant = [np.tile(eye[2], (n, 1)) for n in (8, 10, 12)]
  result = rd.run_diagnostics(_folder(tmp_path, {"a": _padded(phased, 20), "b": _padded(constant, 20)}))
  (run,) = result["runs"]
  a, b = run["tasks"]["a"], run["tasks"]["b"]
  assert a["queries"] == 36 and b["queries"] == 30  # the NaN padding is not a query
  assert a["routing_entropy_per_query"] == pytest.approx(0.0, abs=1e-3)
  assert a["within_episode_tv"] == pytest.approx(0.5, abs=1e-3) and b["within_episode_tv"] == pytest.approx(0.0, abs=1e-3)
  # phase quarters 0-1 use skill 0, 2-3 skill 1: one bit of the two-bit phase entropy
  assert a["phase_skill_mi_norm"] == pytest.approx(0.5, abs=1e-3)
  assert b["phase_skill_mi_norm"] == pytest.approx(0.0, abs=1e-6)
  assert run["task_skill_mi_norm"] > 0.5  # the tasks use disjoint skills
  assert run["effective_skills"] == pytest.approx(np.exp(-sum(p * np.log(p) for p in (18 / 66, 18 / 66, 30 / 66))), rel=1e-3)
  assert "| - | ACT+SkillPlug | 0 | pretrain | 2 |" in rd.markdown(result)


def test_uniform_routing_reads_as_uniform(tmp_path):
  result = rd.run_diagnostics(_folder(tmp_path, {"a": np.full((3, 9, 4), 0.25), "b": np.full((2, 5, 4), 0.25)}))
  (run,) = result["runs"]
  assert run["routing_entropy_per_query"] == pytest.approx(1.0, abs=1e-3) and run["usage_entropy"] == pytest.approx(1.0, abs=1e-3)
  assert run["task_skill_mi_norm"] == pytest.approx(0.0, abs=1e-3) and run["phase_skill_mi_norm"] == pytest.approx(0.0, abs=1e-3)


def test_missing_index_is_named(tmp_path):
  with pytest.raises(FileNotFoundError, match="index.json"):
    rd.run_diagnostics(tmp_path)


def test_routing_curves_read_every_logged_step_and_name_a_run_without_them(tmp_path, capsys):
  """experiments.routing_curves (issue 43): the training log's routing statistics, step by step,
  with the mined phase's where the run logged it; an ACT run's log (no routing) is an error."""
  from experiments import routing_curves
  from skillplug_jax import experiment
  from skillplug_jax.train import run_files
  run = tmp_path / "arm" / "runs" / "discoverse7_skillplug_cpu_seed0"
  run_files.write_run_files(run, experiment.preset("cpu", "skillplug"), {})
  rows = [{"step": s, "loss/rec": 1.0, "diag/routing_entropy_per_query": 1.0 - s / 1000,
           "diag/effective_skills": 4.0 - s / 500, "diag/task_skill_mi_norm": s / 1000,
           "diag/label_skill_mi_norm": s / 2000} for s in (100, 200, 300)]
  (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
  assert routing_curves.main([str(run), "--out", str(tmp_path / "curves"), "--every", "200"]) == 0
  out = json.loads((tmp_path / "curves.json").read_text())
  [c] = out["curves"]
  assert c["label"] == "arm/discoverse7_skillplug_cpu_seed0" and c["steps"] == [100, 200, 300]
  assert c["routing_entropy_per_query"] == [0.9, 0.8, 0.7] and c["label_skill_mi_norm"] == [0.05, 0.1, 0.15]
  md = (tmp_path / "curves.md").read_text()
  assert "| 100 | 0.900 | 3.800 | 0.100 | 0.050 |" in md and "| 200 | 0.800 |" in md
  assert (tmp_path / "curves.png").stat().st_size > 0
  act = tmp_path / "act_run"
  run_files.write_run_files(act, experiment.preset("cpu", "act"), {})
  (act / "metrics.jsonl").write_text(json.dumps({"step": 100, "loss/rec": 1.0}) + "\n")
  assert routing_curves.main([str(act), "--out", str(tmp_path / "x")]) == 2
  assert "no routing diagnostics" in capsys.readouterr().err
