"""experiments/paired_difference.py: B - A paired by seed and trial, from the files the CLI and pipeline write."""

import json
import math

import pytest

from experiments import paired_difference as pd


def _result(run, seed, task, successes):
  return dict(run=run, train_seed=seed, task=task, trial_success=successes)


def _write(path, results, section=""):
  path.write_text(json.dumps({section: {"results": results}} if section else {"results": results}))
  return str(path) + (f":{section}" if section else "")


def test_difference_per_seed_and_its_standard_error_over_seeds(tmp_path):
  # A solves 1 of 4 trials on both tasks at every seed; B solves 2, 3, 4 of 4 on task x, 1 of 4 on task y.
  a = [_result("a", s, t, [True, False, False, False]) for s in (0, 1, 2) for t in ("x", "y")]
  b = [_result("b", s, "x", [True] * (s + 2) + [False] * (2 - s)) for s in (0, 1, 2)]
  b += [_result("b", s, "y", [True, False, False, False]) for s in (0, 1, 2)]
  d = pd.paired_difference(pd.load_arm(_write(tmp_path / "a.json", a)), pd.load_arm(_write(tmp_path / "b.json", b)))
  diffs = [d["per_seed"][str(s)]["diff"] for s in (0, 1, 2)]
  assert diffs == pytest.approx([12.5, 25.0, 37.5])  # (k/4 - 1/4) * 100 / 2 tasks, k = 2, 3, 4
  assert d["diff"] == pytest.approx(25.0)
  assert d["se_over_seeds"] == pytest.approx(12.5 / math.sqrt(3))
  assert d["per_task"]["y"]["diff"] == 0.0 and d["per_task"]["x"]["b"] == pytest.approx(75.0)


def test_one_seed_gives_the_trial_level_error_only(tmp_path):
  a = [_result("a", 0, "x", [False, False, True, True])]
  b = [_result("b", 0, "x", [True, True, True, True])]
  d = pd.paired_difference(pd.load_arm(_write(tmp_path / "a.json", a)), pd.load_arm(_write(tmp_path / "b.json", b)))
  assert d["se_over_seeds"] is None
  assert d["se_over_trials"] == pytest.approx(100 * 0.5773502691896258 / 2)  # std(1,1,0,0) / sqrt(4)
  assert "one seed" in pd.markdown(d, "A", "B")


def test_a_summary_section_and_a_run_filter_pick_one_arm(tmp_path):
  results = [_result("out/act_x/run_seed0", 0, "x", [True, False]),
             _result("out/plug_x/run_seed0", 0, "x", [True, True])]
  spec = _write(tmp_path / "summary.json", results, section="fewshot")
  assert pd.load_arm(spec, "plug")[(0, "x")].tolist() == [1.0, 1.0]
  with pytest.raises(ValueError, match="two results for seed 0 on x"):
    pd.load_arm(spec)
  with pytest.raises(ValueError, match="no results whose run contains 'nothing'"):
    pd.load_arm(spec, "nothing")


def test_a_variant_filter_picks_one_of_the_protocols_on_the_same_runs(tmp_path):
  """Arms that adapt another's runs (Variant.adapts) share its run folders: the variant tells them."""
  results = [dict(_result("out/act/runs/r_seed0_fewshot/x", 0, "x", [True, False]), variant="act"),
             dict(_result("out/act/runs/r_seed0_fewshot_act_light/x", 0, "x", [False, False]), variant="act_light")]
  spec = _write(tmp_path / "summary.json", results, section="fewshot")
  assert pd.load_arm(spec, variant="act_light")[(0, "x")].tolist() == [0.0, 0.0]
  assert pd.load_arm(spec, "act/runs", variant="act")[(0, "x")].tolist() == [1.0, 0.0]
  with pytest.raises(ValueError, match="no results of variant 'act_lite'"):
    pd.load_arm(spec, variant="act_lite")


def test_unpaired_inputs_are_refused_by_name(tmp_path):
  a = pd.load_arm(_write(tmp_path / "a.json", [_result("a", 0, "x", [True, False])]))
  b = pd.load_arm(_write(tmp_path / "b.json", [_result("b", 0, "x", [True, False, True])]))
  with pytest.raises(ValueError, match="2 trials against 3"):
    pd.paired_difference(a, b)
  both = pd.load_arm(_write(tmp_path / "c.json", [_result("c", 0, "x", [True, False]), _result("c", 1, "y", [True, True])]))
  with pytest.raises(ValueError, match="missing"):
    pd.paired_difference(both, both)  # seed 0 lacks y, seed 1 lacks x
