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
