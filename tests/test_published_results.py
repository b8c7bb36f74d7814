"""Results published before the plug had its own config (issue 40) still read and tabulate as
they were published: their flat training keys map to `model.plug.*`, their rows keep their names
and their cells, and an old run directory's config.json loads."""

import json
from pathlib import Path

import pytest

from experiments import publish
from skillplug_jax.evaluate import groups
from skillplug_jax.train import run_files

DOCS = Path(__file__).resolve().parents[1] / "docs" / "results"


@pytest.mark.parametrize("name", ["paper_cpu", "k_sweep", "loss_ablation", "routing_remedies"])
def test_a_published_summary_tabulates_to_its_published_rows(name):
  path = DOCS / name / "summary.json"
  published = json.loads(path.read_text())
  for stage in ("pretrain", "fewshot"):
    if stage not in published:
      continue
    results = publish.reference_results(str(path), stage)
    assert all("model.plug.num_skills" in r["config"] and "model.num_skills" not in r["config"] for r in results)
    again = publish.merged_summary([], stage, published[stage]["table"]["tasks"], results)
    assert list(again["rows"]) == list(published[stage]["rows"]), stage
    for row, want in published[stage]["table"]["rows"].items():
      assert json.loads(json.dumps(again["table"]["rows"][row]["cells"])) == want["cells"], (stage, row)


def test_an_old_run_directory_loads_with_the_plug_nested():
  runs = sorted((DOCS / "act_parity" / "runs").glob("*skillplug*"))
  assert runs, "the committed act_parity runs"
  for run in runs:
    flat = json.loads((run / "config.json").read_text())
    flat = flat.get("train", flat)
    cfg = run_files.read_config(run)
    assert cfg.model.plug.num_skills == flat["model"]["num_skills"]
    assert cfg.model.plug.site == flat["model"].get("plug_site", "encoder")
    assert groups.normalised(groups.training_key(cfg)) == groups.training_key(cfg)


def test_a_published_arms_routing_arrays_are_found_when_it_is_a_reference():
  """An arm's arrays are published under its variant's name (`publish.publish`): a summary read
  back as a reference finds them, so the arm's routing entropy is tabulated across sessions."""
  path = DOCS / "libero" / "cpu_object_40k_seed0_2026-12-07" / "summary.json"
  results = publish.reference_results(str(path), "pretrain")
  plug = [r for r in results if r["config"]["model.policy"] == "skillplug"]
  assert len(plug) == 10 and all(r["variant"] == "object" for r in plug)
  files = [publish.routing_file(r) for r in plug]
  assert all(f is not None and f.name.startswith("object_skillplug_seed0_pretrain_") for f in files)
  published = json.loads(path.read_text())["variants"][0]["routing_entropy_per_query"]
  assert abs(publish.routing_entropy(plug) - published) < 1e-6
