"""Experiment configs and the pipeline that runs them: loading, overrides, the few-shot
protocol they carry, a whole (tiny) protocol end to end, resuming it, its routing arrays,
and what its runs record of their config (so that editing it later renames nothing)."""

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import optax
import pytest

from experiments import pipeline, publish
from skillplug_jax import experiment, fewshot
from skillplug_jax.evaluate import groups, protocol
from skillplug_jax.model.policy import Policy
from skillplug_jax.train import config as train_config
from skillplug_jax.train import loop, run_files


def test_every_config_loads_names_its_command_and_its_preset():
  assert {"quick", "cpu", "budget", "paper"} <= set(experiment.names())
  for name in experiment.names():
    exp = experiment.get(name)
    assert exp.command, name  # the docstring's first line: how to run it
    assert exp.train.preset in experiment.names(), name
    # a preset's training settings are what `skillplug pretrain --config NAME` trains
    base = experiment.get(exp.train.preset)
    assert experiment.preset(exp.train.preset, "act") == base.train_config("act", 0)
  assert experiment.get("paper").train.model.hidden == 512 and experiment.get("paper").fewshot.steps == 0
  assert experiment.get("quick").fewshot.steps == 500 and experiment.get("quick").trials == 10
  cpu = experiment.get("cpu")
  assert not cpu.train.model.use_images and cpu.seeds == (0, 1, 2) and cpu.trials == 50
  # a config file named by its path: its train.preset is read beside it
  path = experiment.configs_dir() / "k_sweep.py"
  assert experiment.get(str(path)) == experiment.get("k_sweep") and experiment.directory(str(path)) == path.parent


def test_overrides_reach_every_level_and_bad_ones_are_named():
  exp = experiment.get("cpu", ["seeds=0,1", "train.model.hidden=32", "train.lr=3e-4", "fewshot.steps=7",
                            "fewshot.trainable.skillplug=router", "run_fewshot=false"])
  assert exp.seeds == (0, 1) and exp.train.model.hidden == 32 and exp.train.lr == 3e-4
  assert exp.fewshot.steps == 7 and exp.fewshot.trainable.of("skillplug") == ("router",)
  assert exp.fewshot.trainable.of("act") == ("action_head",) and not exp.run_fewshot
  cfg = exp.train_config("act", 2)
  assert (cfg.model.policy, cfg.seed, cfg.model.hidden) == ("act", 2, 32)
  with pytest.raises(ValueError, match="unknown config 'cpuu'.*quick"):
    experiment.get("cpuu")
  with pytest.raises(ValueError, match="unknown setting 'train.model.hiden'"):
    experiment.get("cpu", ["train.model.hiden=3"])
  with pytest.raises(ValueError, match="unknown config 'huge'"):
    experiment.preset("huge")
  with pytest.raises(ValueError, match="lr_schedule must be one of"):
    dataclasses.replace(exp.train, lr_schedule="linear")


def test_a_variant_may_set_its_own_seeds():
  arms = {v.name: e for v, e in experiment.expand(experiment.get("routing_remedies"))}
  assert arms["film"].seeds == (0, 1, 2) and arms["film"].train.model.plug.interactor == "film"
  assert arms["temp0.1"].seeds == (0,) and arms["sd0.01"].train.loss.sd == 0.01
  # a command-line seeds override reaches the other arms; the variant's own setting wins
  arms = {v.name: e for v, e in experiment.expand(experiment.get("routing_remedies", ["seeds=1"]))}
  assert arms["film"].seeds == (0, 1, 2) and arms["sd0.01"].seeds == (1,)


def test_fewshot_protocol_comes_from_the_source_runs_record(tmp_path):
  quick = experiment.preset("quick", "skillplug")
  plan = experiment.record(experiment.get("quick"), "skillplug").fewshot
  few = fewshot.fewshot_config(quick, tmp_path / "src", "block_place", plan)
  assert (few.max_steps, few.trainable, few.demos) == (500, ("action_head", "router"), 10)
  assert few.data_taskset == "discoverse_fewshot4" and few.taskset == "block_place"
  act = fewshot.fewshot_config(experiment.preset("quick", "act"), tmp_path / "src", "block_place", plan)
  assert act.trainable == ("action_head",) and act.init_from == str(tmp_path / "src")
  # a run without a record, of a config that is gone: its protocol is unknown
  gone = dataclasses.replace(quick, preset="removed_config", workdir=str(tmp_path / "old"))
  run_files.write_run_files(gone.run_dir, gone, {})
  with pytest.raises(ValueError, match="'removed_config' is not in experiments/configs"):
    experiment.read_record(gone.run_dir)
  # a protocol chosen by the caller needs no config
  mine = fewshot.fewshot_config(gone, tmp_path / "src", "block_place",
                                experiment.FewShot(steps=3, trainable=experiment.Trainable(skillplug=("router",))))
  assert (mine.max_steps, mine.trainable) == (3, ("router",))


def test_fewshot_without_the_marginal_terms_zeroes_them_alone_in_its_own_folder(tmp_path):
  source = train_config.override(experiment.preset("quick", "skillplug"),
                                 ["loss.usage=0.5", "loss.router_label=0.2"])
  kept = fewshot.fewshot_config(source, tmp_path / "src", "block_place", experiment.FewShot())
  assert kept.loss == source.loss  # the default protocol: the source's loss as it was
  dropped = fewshot.fewshot_config(source, tmp_path / "src", "block_place",
                                   experiment.FewShot(marginal_terms=False))
  assert dropped.loss.usage == 0.0 and dropped.loss.router_label == 0.2  # a per-query term stays
  assert dataclasses.replace(dropped.loss, usage=0.5) == source.loss  # nothing else
  assert dropped.workdir != kept.workdir and Path(dropped.workdir).name == "block_place"
  assert dataclasses.replace(dropped, loss=kept.loss, workdir=kept.workdir) == kept


def test_fewshot_with_other_trainable_groups_trains_those_in_their_own_folder(tmp_path, monkeypatch):
  source = dataclasses.replace(experiment.preset("quick", "skillplug"), workdir=str(tmp_path / "src"))
  run_files.write_run_files(source.run_dir, source, {})
  trained = []
  monkeypatch.setattr(loop, "train", lambda cfg, **k: trained.append(cfg) or Path(cfg.workdir))
  monkeypatch.setattr(fewshot, "load_controller", lambda run: (None, None))
  monkeypatch.setattr(protocol, "warn_if_other_renderer", lambda *a: None)
  monkeypatch.setattr(protocol, "evaluate_task", lambda task, *a, **k: dict(task=task))
  monkeypatch.setattr(fewshot.tables, "summarise", lambda results, tasks: {})
  out = fewshot.adapt_and_evaluate([source.run_dir], "block_place", progress=False,
                                   trainable=["router", "interactor", "action_head"])
  [cfg] = trained
  assert cfg.trainable == ("action_head", "interactor", "router")
  assert Path(cfg.workdir).parent.name == "src_fewshot_train-action_head+interactor+router"
  assert out["results"][0]["trainable"] == ["action_head", "interactor", "router"]
  trained.clear()  # the recorded groups: the recorded protocol's folder
  fewshot.adapt_and_evaluate([source.run_dir], "block_place", progress=False, trainable=["router", "action_head"])
  assert Path(trained[0].workdir).parent.name == "src_fewshot"
  with pytest.raises(ValueError, match="trainable"):
    fewshot.adapt_and_evaluate([source.run_dir], "block_place", progress=False, trainable=["head"])


def test_a_jobs_fewshot_follows_the_runs_record_not_the_experiment(tmp_path, monkeypatch):
  """pipeline.job fine-tunes by the protocol the run recorded (as `skillplug fewshot` does): a resumed
  run keeps the record it started with, whatever this experiment's fewshot says now."""
  exp = experiment.get("quick", ["seeds=0", "policies=skillplug"])
  recorded = dataclasses.replace(experiment.record(exp, "skillplug"), fewshot=experiment.FewShot(
      taskset="block_place", steps=3, trainable=experiment.Trainable(skillplug=("interactor", "router"))))
  trained = []

  def train(cfg, progress=True, record=None):
    trained.append((cfg, record))
    if not cfg.init_from:  # the pretraining run, started earlier with `recorded`
      run_files.write_run_files(cfg.run_dir, cfg, {}, recorded)
    return cfg.run_dir

  monkeypatch.setattr(loop, "train", train)
  monkeypatch.setattr(pipeline, "evaluated", lambda *a, **k: [])
  pipeline.job(exp, "skillplug", 0, tmp_path, record=experiment.record(exp, "skillplug"))
  [(few, few_record)] = trained[1:]
  assert (few.taskset, few.max_steps, few.trainable) == ("block_place", 3, ("interactor", "router"))
  assert few_record == recorded
  # a variant's groups are in the record its runs start with
  arms = {v.name: a for v, a in experiment.expand(experiment.get("skill_library"))}
  assert experiment.record(arms["decoder"], "act").fewshot.trainable.of("act") == ("action_proj",)
  assert experiment.record(arms["decoder"], "skillplug").fewshot.trainable.of("skillplug") == ("action_proj", "router")


def test_cosine_schedule_warms_up_then_decays_to_zero():
  cfg = train_config.override(experiment.preset("quick"), ["lr=1e-3", "warmup_steps=10", "lr_schedule=cosine"])
  lr = loop.learning_rate(cfg, 110)
  assert float(lr(0)) == 0.0 and float(lr(10)) == pytest.approx(1e-3)
  assert float(lr(60)) == pytest.approx(5e-4, rel=1e-3) and float(lr(110)) == pytest.approx(0.0, abs=1e-9)
  const = loop.learning_rate(dataclasses.replace(cfg, lr_schedule="constant"), 110)
  assert float(const(5)) == pytest.approx(5e-4) and float(const(100)) == pytest.approx(1e-3)
  assert isinstance(loop.optimizer(cfg, {"w": np.zeros(2)}, 110), optax.GradientTransformation)


TINY = ["train.taskset=jujube_pick,drawer_open", "train.demos=2", "train.max_steps=4", "train.batch_size=4",
        "train.warmup_steps=1", "train.log_every=2", "train.ckpt_every=2", "train.model.hidden=32",
        "train.model.heads=2", "train.model.ff=64", "train.model.enc_layers=1", "train.model.dec_layers=1",
        "train.model.plug.num_skills=3", "train.model.plug.skill_latent_dim=8", "train.model.plug.alignment_dim=16",
        "train.model.chunk=10", "trials=3", "eval_batch=3", "fewshot.taskset=mouse_push", "fewshot.demos=2",
        "fewshot.steps=2", "workers=1"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
  """The quick config at a smoke size through the whole pipeline, published for the notebooks."""
  out = tmp_path_factory.mktemp("pipeline")
  exp = experiment.get("quick", TINY)
  summary = pipeline.run(exp, out)
  publish.publish(summary, publish.report(summary), out / "published")
  return exp, out, summary


@pytest.mark.slow
def test_pipeline_runs_the_protocol_and_writes_routing_arrays(tiny_run):
  _, out, summary = tiny_run
  pre, few = summary["pretrain"], summary["fewshot"]
  assert list(pre["rows"]) == ["ACT+SkillPlug", "ACT"] and pre["rows"]["ACT"]["seeds"] == [0]
  assert pre["table"]["tasks"] == ["jujube_pick", "drawer_open"] and few["table"]["tasks"] == ["mouse_push"]
  assert len(pre["results"]) == 4 and len(few["results"]) == 2
  sp = [r for r in pre["results"] if r["policy"] == "ACT+SkillPlug"]
  for r in sp:  # every query's weights, trial by trial, beside the outcome
    z = protocol.read_routing(r["routing_file"])
    assert z["task"] == r["task"] and z["routing"].shape[0] == 3 and z["routing"].shape[2] == 3
    assert z["success"].tolist() == r["trial_success"] and z["queries"].tolist() == r["trial_queries"]
    queried = ~np.isnan(z["routing"][..., 0])
    assert (queried.sum(axis=1) == z["queries"]).all()  # one row per query, NaN elsewhere
    np.testing.assert_allclose(z["routing"][queried].sum(-1), 1.0, atol=2e-3)  # float16 on disk
    np.testing.assert_allclose(np.nanmean(z["routing"].reshape(-1, 3), axis=0), r["mean_weights"], atol=2e-3)
  assert all(r["routing_file"] is None for r in pre["results"] if r["policy"] == "ACT")
  few_sp = next(r for r in few["results"] if r["policy"] == "ACT+SkillPlug")
  assert few_sp["trainable"] == ["action_head", "router"] and few_sp["steps"] == 2
  assert few_sp["source"].endswith("jujube_pick,drawer_open_skillplug_quick_seed0")
  text = publish.report(summary)
  assert text.count("| ACT+SkillPlug |") == 6 and "Wall time:" in text
  assert "ACT+SkillPlug minus ACT, success points, multi-task: J.P. " in text
  assert "2 demos, 2 fine-tuning steps, 3 paired trials" in text
  # published: the summary, and the routing arrays with an index (ACT+SkillPlug only)
  index = json.loads((out / "published" / "routing" / "index.json").read_text())
  assert sorted((e["stage"], e["task"]) for e in index) == [("fewshot", "mouse_push"), ("pretrain", "drawer_open"),
                                                            ("pretrain", "jujube_pick")]
  for e in index:
    assert (out / "published" / "routing" / e["file"]).exists() and e["policy"] == "ACT+SkillPlug"
  published = json.loads((out / "published" / "summary.json").read_text())
  assert published["pretrain"]["table"] == json.loads(json.dumps(pre["table"]))  # tuples as JSON lists


@pytest.mark.slow
def test_pipeline_resumes_without_training_or_evaluating_again(tiny_run, monkeypatch):
  exp, out, summary = tiny_run
  monkeypatch.setattr(protocol, "evaluate_task", lambda *a, **k: pytest.fail("evaluated again"))
  again = pipeline.run(exp, out)
  assert again["pretrain"]["table"] == summary["pretrain"]["table"]
  assert again["fewshot"]["table"] == summary["fewshot"]["table"]
  assert all(loop.load_params(r["run"])[2] == 4 for r in summary["pretrain"]["results"])


def _skillplug_run(summary: dict) -> Path:
  return Path(next(r["run"] for r in summary["pretrain"]["results"] if r["policy"] == "ACT+SkillPlug"))


def _edited_configs(dest: Path) -> Path:
  """The configs with quick.py edited as a later commit might: the model the tiny runs override
  (hidden 32, 3 skills) becomes its default, and its few-shot protocol trains 7 steps."""
  dest.mkdir()
  text = (experiment.configs_dir() / "quick.py").read_text()
  for old, new in (("hidden=64", "hidden=32"), ("num_skills=4", "num_skills=3"),
                   ("FewShot(steps=500)", "FewShot(steps=7)")):
    assert old in text
    text = text.replace(old, new)
  (dest / "quick.py").write_text(text)
  return dest


def _rows_of(run: Path) -> dict:
  """The run's row beside a K=2 run of the same record, named as evaluation names them."""
  cfg, record = run_files.read_config(run), experiment.read_record(run)
  other = train_config.override(cfg, ["model.plug.num_skills=2"])
  return groups.group_rows([groups.row_fields(c, record) for c in (cfg, other)])


@pytest.mark.slow
def test_a_run_records_its_fewshot_protocol_and_overrides(tiny_run):
  _, _, summary = tiny_run
  run = _skillplug_run(summary)
  saved = json.loads((run / "config.json").read_text())
  record = saved["experiment"]
  assert record["config"] == "quick" and record["fewshot"]["steps"] == 2  # the experiment's, overrides included
  assert record["fewshot"]["trainable"]["skillplug"] == ["action_head", "router"]
  assert record["defaults"]["model"]["hidden"] == 64 and record["defaults"]["model"]["policy"] == "skillplug"
  # the TrainConfig's fields are as they always were, the record beside them
  cfg = run_files.read_config(run)
  assert cfg == train_config.from_dict({k: v for k, v in saved.items() if k != "experiment"})
  overrides = groups.row_fields(cfg, experiment.read_record(run))["overrides"]
  assert overrides["model.hidden"] == 32 and overrides["model.plug.num_skills"] == 3 and "lr" not in overrides
  # every result carries them, and a few-shot run keeps its source's record
  assert all(r["overrides"] == overrides for r in summary["pretrain"]["results"] + summary["fewshot"]["results"]
             if r["policy"] == "ACT+SkillPlug")
  few_run = next(Path(r["run"]) for r in summary["fewshot"]["results"] if r["policy"] == "ACT+SkillPlug")
  assert run_files.stored_record(few_run) == run_files.stored_record(run)


@pytest.mark.slow
def test_editing_the_config_afterwards_changes_neither_row_nor_fewshot(tiny_run, tmp_path, monkeypatch):
  run = _skillplug_run(tiny_run[2])
  before = _rows_of(run)
  assert list(before) == ["ACT+SkillPlug (num_skills=3)", "ACT+SkillPlug (num_skills=2)"]
  edited = _edited_configs(tmp_path / "configs")
  monkeypatch.setattr(experiment, "configs_dir", lambda: edited)  # today's file is the edited one
  key = groups.training_key(run_files.read_config(run))
  assert "model.hidden" not in groups.todays_overrides(key)  # what reading today's file would say
  assert _rows_of(run) == before  # names and overrides as recorded
  source, plan = run_files.read_config(run), experiment.read_record(run).fewshot
  few = fewshot.fewshot_config(source, run, "mouse_push", plan)
  assert (few.max_steps, few.trainable) == (2, ("action_head", "router"))
  # a resumed run keeps the record it started with
  loop.train(source, progress=False, record=experiment.record(experiment.get("quick"), "skillplug"))
  assert experiment.read_record(run).fewshot == plan
  # and with no config file to read at all, the run is still named and adapted
  monkeypatch.setattr(experiment, "get", lambda *a, **k: pytest.fail("read a config file"))
  assert _rows_of(run) == before and experiment.read_record(run).fewshot == plan


@pytest.mark.slow
def test_a_run_or_result_without_a_record_falls_back_to_todays_config(tiny_run, tmp_path, monkeypatch, capsys):
  run = _skillplug_run(tiny_run[2])
  saved = json.loads((run / "config.json").read_text())
  del saved["experiment"]  # config.json as runs wrote it before the record
  old = tmp_path / "old_run"
  old.mkdir()
  (old / "config.json").write_text(json.dumps(saved))
  assert run_files.read_config(old) == run_files.read_config(run) and run_files.stored_record(old) is None
  edited = _edited_configs(tmp_path / "configs")
  monkeypatch.setattr(experiment, "configs_dir", lambda: edited)
  capsys.readouterr()
  assert experiment.read_record(old).fewshot.steps == 7  # today's file
  assert "records no experiment config" in capsys.readouterr().err
  # a result without overrides (an older evaluation or summary): named against today's file, with a warning
  key = groups.training_key(run_files.read_config(old))
  (row,) = groups.group_rows([dict(config=key, train_seed=0)]).values()
  assert row["overrides"] == groups.todays_overrides(key) and "model.hidden" not in row["overrides"]
  assert "record no overrides" in capsys.readouterr().err


def test_published_summaries_from_before_the_record_still_tabulate(capsys):
  """A committed summary's results carry no overrides: as a reference they take their published rows'."""
  path = experiment.get("k_sweep").reference
  published = json.loads(Path(path).read_text())["pretrain"]
  ref = publish.reference_results(path, "pretrain")
  assert ref and all("overrides" in r and r["reference"] == path for r in ref)
  merged = publish.merged_summary([], "pretrain", published["table"]["tasks"], ref)
  assert list(merged["rows"]) == list(published["rows"])
  assert json.loads(json.dumps(merged["table"])) == published["table"]
  assert "record no overrides" not in capsys.readouterr().err


@pytest.mark.parametrize("name", ["success_tables.ipynb", "routing.ipynb", "skill_similarity.ipynb",
                                  "fixed_skills.ipynb"])
@pytest.mark.slow
def test_notebooks_execute_on_a_published_run(tiny_run, name, monkeypatch, tmp_path):
  """The committed notebooks run top to bottom on a (smoke-size) published pipeline run and draw;
  `--into` writes them elsewhere and leaves the committed notebook as it is."""
  import importlib.util
  import nbformat
  from pathlib import Path
  from experiments import skill_probes
  published = tiny_run[1] / "published"
  if name in ("skill_similarity.ipynb", "fixed_skills.ipynb") and not (published / "skill_probes.json").exists():
    args = ["--config", "quick", "--out", str(tiny_run[1]), "--publish", str(published)]
    assert skill_probes.main(args + [a for o in TINY for a in ("--set", o)]) == 0
  monkeypatch.setenv("SKILLPLUG_KSWEEP", str(tiny_run[1] / "no_k_sweep"))  # only the tiny run's probes
  monkeypatch.setenv("SKILLPLUG_MIXED", str(tiny_run[1] / "no_mixed"))
  root = Path(__file__).resolve().parents[1] / "notebooks"
  spec = importlib.util.spec_from_file_location("nb_execute", root / "execute.py")
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  committed = (root / name).read_bytes()
  assert mod.main([str(root / name), "--results", str(published), "--into", str(tmp_path / "nb")]) == 0
  assert (root / name).read_bytes() == committed
  nb = nbformat.read(tmp_path / "nb" / name, as_version=4)
  outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
  assert not [o for o in outputs if o.output_type == "error"]
  assert sum("image/png" in o.get("data", {}) for o in outputs) >= 2
  printed = "".join(o.get("text", "") for o in outputs)
  assert "config 'quick'" in printed


@pytest.mark.slow
def test_variants_run_in_their_own_folders_and_join_the_reference_rows(tiny_run):
  """An ablation-style config: each variant's runs under OUT/<name>, datasets shared, its row
  named by what it changed, read beside the rows of a published reference summary."""
  _, ref_out, ref = tiny_run
  exp = dataclasses.replace(
      experiment.get("quick", TINY), policies=("skillplug",), reference=str(ref_out / "published" / "summary.json"),
      variants=(experiment.Variant("nosd", ("train.loss.sd=0",), "-SD"),
                experiment.Variant("k2", ("train.model.plug.num_skills=2", "run_fewshot=false"), "K=2")))
  out = ref_out / "variants"
  summary = pipeline.run(exp, out)
  assert sorted(p.name for p in out.iterdir()) == ["datasets", "k2", "nosd"]
  assert (out / "nosd" / "runs" / "jujube_pick,drawer_open_skillplug_quick_seed0" / "config.json").exists()
  rows = summary["pretrain"]["rows"]
  assert list(rows) == ["ACT+SkillPlug (loss.sd=0.1, num_skills=3)", "ACT",
                        "ACT+SkillPlug (loss.sd=0.0, num_skills=3)", "ACT+SkillPlug (loss.sd=0.1, num_skills=2)"]
  # the reference's rows are its own numbers, read back
  ref_sp = ref["pretrain"]["table"]["rows"]["ACT+SkillPlug"]["cells"]["Avg."]
  assert list(summary["pretrain"]["table"]["rows"]["ACT+SkillPlug (loss.sd=0.1, num_skills=3)"]["cells"]["Avg."]) == list(ref_sp)
  assert {r["variant"] for r in summary["pretrain"]["results"] if "reference" not in r} == {"nosd", "k2"}
  # few-shot: the reference's rows and the one variant that adapts
  assert len(summary["fewshot"]["rows"]) == 3
  labels = {v["label"]: v["rows"]["pretrain"] for v in summary["variants"]}
  assert labels["-SD"] == "ACT+SkillPlug (loss.sd=0.0, num_skills=3)" and labels["K=2"] == "ACT+SkillPlug (loss.sd=0.1, num_skills=2)"
  assert "ACT (reference)" in labels and len(summary["variants"]) == 4
  few_rows = {v["label"]: v["rows"]["fewshot"] for v in summary["variants"]}
  assert few_rows["-SD"] == "ACT+SkillPlug (loss.sd=0.0)" and few_rows["K=2"] is None  # named beside the few-shot rows
  text = publish.report(summary)
  assert "| -SD | ACT+SkillPlug (loss.sd=0.0, num_skills=3) | 0 |" in text
  ent = {v["label"]: v["routing_entropy_per_query"] for v in summary["variants"]}
  assert ent["ACT (reference)"] is None and 0.0 < ent["-SD"] <= 1.0 + 1e-6
  assert 0.0 < ent["ACT+SkillPlug (loss.sd=0.1, num_skills=3) (reference)"] <= 1.0 + 1e-6  # from its published arrays
  publish.publish(summary, text, out / "published")
  index = json.loads((out / "published" / "routing" / "index.json").read_text())
  assert sorted(e["file"] for e in index if e["stage"] == "fewshot") == ["nosd_skillplug_seed0_fewshot_mouse_push.npz"]
  assert {e["variant"] for e in index} == {"nosd", "k2"}  # the reference's arrays stay where it published them
  with pytest.raises(ValueError, match="distinct folder names"):
    experiment.expand(dataclasses.replace(exp, variants=(experiment.Variant("a"), experiment.Variant("a"))))
  assert pipeline.main(["--config", "loss_ablation", "--variants", "rec,nope", "--out", str(out)]) == 2


@pytest.mark.slow
def test_arms_that_adapt_another_arms_runs_train_none_and_fine_tune_beside_them(tiny_run):
  """Issue 43's arms: several few-shot protocols on one arm's pretrained runs (`Variant.adapts`).
  They train no run of their own and tabulate no multi-task row; each fine-tunes into its own
  folder beside the source's, and each protocol is a few-shot row of its own. The router-frozen
  arm leaves the router as pretrained, the adapter arm adds a group the source never had, and the
  uniform arm evaluates with weights 1/K."""
  _, ref_out, _ = tiny_run
  dec = ("train.model.plug.site=decoder", "policies=skillplug")
  exp = dataclasses.replace(
      experiment.get("quick", TINY), policies=("skillplug",),
      variants=(experiment.Variant("base", dec + ("fewshot.trainable.skillplug=action_proj,router",)),
                experiment.Variant("frozen", dec + ("fewshot.trainable.skillplug=action_proj",), adapts="base"),
                experiment.Variant("adapter", dec + ("fewshot.trainable.skillplug=action_proj,adapter",
                                                     "fewshot.train_overrides=model.adapter_width=4"), adapts="base"),
                experiment.Variant("uniform", dec + ("fewshot.trainable.skillplug=action_proj",
                                                     "fewshot.train_overrides=model.plug.fusion_weights=uniform"),
                                   adapts="base")))
  out = ref_out / "adapting"
  summary = pipeline.run(exp, out)
  assert sorted(p.name for p in out.iterdir()) == ["base", "datasets"]
  run = out / "base" / "runs" / "jujube_pick,drawer_open_skillplug_quick_seed0"
  assert sorted(p.name for p in run.parent.iterdir()) == sorted(
      [run.name] + [f"{run.name}_fewshot{s}" for s in ("", "_frozen", "_adapter", "_uniform")])
  assert {r["variant"] for r in summary["pretrain"]["results"]} == {"base"}
  few = {r["variant"]: r for r in summary["fewshot"]["results"]}
  assert len(summary["fewshot"]["rows"]) == 4 and set(few) == {"base", "frozen", "adapter", "uniform"}
  assert few["frozen"]["config"]["fewshot.trainable"] == ["action_proj"]
  assert few["adapter"]["config"]["fewshot.train_overrides"] == ["model.adapter_width=4"]
  rows = {v["variant"]: v["rows"] for v in summary["variants"]}
  assert rows["frozen"]["pretrain"] is None and rows["base"]["pretrain"] is not None
  _, before, _ = loop.load_params(run)
  for arm, trained in (("frozen", {"action_proj"}), ("adapter", {"action_proj", "adapter"})):
    _, after, _ = loop.load_params(Path(few[arm]["run"]))
    assert set(after) - set(before) == ({"adapter"} if arm == "adapter" else set())
    same = {g for g in before if all(np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(before[g]), jax.tree.leaves(after[g])))}
    assert set(before) - same == trained - {"adapter"}, arm
  np.testing.assert_allclose(few["uniform"]["mean_weights"], [1 / 3] * 3, atol=2e-3)
  assert "| frozen | " in publish.report(summary)
  bad = dataclasses.replace(exp, variants=exp.variants[:1] + (
      experiment.Variant("other", dec + ("train.loss.sd=0",), adapts="base"),))
  with pytest.raises(ValueError, match="'other' adapts 'base' but trains otherwise.*loss.sd"):
    experiment.expand(bad)
  assert [v.name for v in experiment.only(exp, "frozen").variants] == ["base", "frozen"]


def test_pipeline_cli_rejects_bad_configs(capsys):
  assert pipeline.main(["--config", "nope"]) == 2
  assert "unknown config 'nope'" in capsys.readouterr().err
  assert pipeline.main(["--config", "quick", "--set", "seeds="]) == 2
  assert "seeds must be a non-empty tuple of distinct integers >= 0, got ()" in capsys.readouterr().err
  assert pipeline.main(["--config", "k_sweep", "--set", "train.model.plug.num_skills=0"]) == 2
  assert "train.model.plug.num_skills must be an integer >= 1, got 0" in capsys.readouterr().err


def test_routing_statistics_tell_uniform_from_specialised(tmp_path):
  from skillplug_jax.evaluate import routing
  nan = np.full((2, 5, 4), np.nan, np.float32)
  uniform = nan.copy()
  uniform[:, :3] = 0.25  # 3 queries per trial, then the episode ended
  onehot = nan.copy()
  onehot[0, :4] = [0, 1, 0, 0]
  onehot[1, :2] = [[1, 0, 0, 0], [0, 0, 1, 0]]  # switches skill within the episode
  paths = []
  for name, arr in (("uniform", uniform), ("onehot", onehot)):
    paths.append(tmp_path / f"{name}.npz")
    protocol.write_routing(paths[-1], name, [arr.transpose(1, 0, 2)], 2, np.array([True, False]),
                           np.array([2, -1]), (~np.isnan(arr[..., 0])).sum(1))
  u, o = routing.summarise_files(paths)
  assert u["queries"] == 6 and o["queries"] == 6
  assert u["routing_entropy_per_query"] == pytest.approx(1.0, abs=1e-3) and u["within_episode_std"] == pytest.approx(0.0)
  assert o["routing_entropy_per_query"] == pytest.approx(0.0, abs=1e-6) and o["max_weight"] == 1.0
  assert o["within_episode_std"] > 0.1 and o["usage_entropy"] > o["routing_entropy_per_query"]
  assert o["mean_weights_success"] == [0, 1, 0, 0] and o["mean_weights_failure"] == [0.5, 0, 0.5, 0]
  d = routing.between_task_distance([u, o])
  # mean weights: uniform 1/4 each; one-hot 6 queries: [1, 4, 1, 0] / 6
  assert d[0, 0] == 0 and d[0, 1] == pytest.approx(0.5 * (2 * (0.25 - 1 / 6) + (4 / 6 - 0.25) + 0.25))


def test_linear_cka_is_one_for_rotations_and_low_for_unrelated_features():
  from experiments.skill_probes import linear_cka
  rng = np.random.default_rng(0)
  x = rng.normal(size=(200, 8))
  q, _ = np.linalg.qr(rng.normal(size=(8, 8)))
  assert linear_cka(x, 3.0 * x @ q) == pytest.approx(1.0)
  assert linear_cka(x, rng.normal(size=(200, 5))) < 0.2


@pytest.mark.slow
def test_skill_probes_replace_the_routing_and_measure_the_skills(tiny_run, capsys):
  from experiments import skill_probes
  _, out, summary = tiny_run
  args = ["--config", "quick", "--out", str(out)] + [a for o in TINY for a in ("--set", o)]
  assert skill_probes.main(args) == 0
  result = json.loads((out / "skill_probes.json").read_text())
  assert result["modes"] == ["router", "uniform", "skill0", "skill1", "skill2"]
  probe = result["seeds"]["0"]
  # the router's own weights: the pipeline's evaluation, read back; evaluated again without it,
  # the same trials give the same outcomes
  sp = [r for r in summary["pretrain"]["results"] if r["policy"] == "ACT+SkillPlug"]
  for r in sp:
    assert probe["closed_loop"]["router"][r["task"]]["trial_success"] == r["trial_success"]
  run = Path(sp[0]["run"])
  exp = experiment.get("quick", TINY)
  own = run / "eval" / f"{exp.train.taskset}_trials{exp.trials}_seed{exp.eval_seed}.json"
  own.rename(own.with_suffix(".aside"))
  try:
    again = skill_probes.closed_loop(run, exp, [sp[0]["task"]], 3)
  finally:
    own.with_suffix(".aside").rename(own)
  assert again["router"][sp[0]["task"]]["trial_success"] == sp[0]["trial_success"]
  g = probe["geometry"]
  # the geometry against the same quantities recomputed here, in numpy, from the run's weights and
  # the probes' demonstration states
  cfg, params, _ = loop.load_params(run)
  policy = Policy(cfg.model)
  unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
  emb = unit(np.asarray(policy.apply({"params": params}, method=lambda mod: mod.plug.skills())))
  np.testing.assert_allclose(g["skill_cosine"], emb @ emb.T, atol=1e-4)
  states = skill_probes.demo_states(run, list(g["tasks"]))
  chosen = []
  for task, row in g["tasks"].items():
    obs = {k: v for k, v in states[task].items() if k != "mined_phase"}
    f = policy.apply({"params": params}, obs, method=Policy.features)
    um = unit(np.asarray(f["skill_tokens"]).mean(axis=2))  # [B, K, D], token-averaged u_k
    np.testing.assert_allclose(row["interactor_cosine"], np.einsum("bkd,bld->kl", um, um) / len(um), atol=1e-4)
    assert row["states"] == len(um) == 8  # 2 demos x 4
    assert 0.0 < row["cka_fused_vs_act"] <= 1.0 + 1e-6 and row["interactor_spread"] >= 0.0
    np.testing.assert_allclose(row["router_mean"], np.asarray(f["routing"]).mean(0), atol=1e-5)
    chosen.append(np.asarray(f["routing"]).argmax(-1))
  # every demonstration state counted once under its mined phase and the skill the router chose
  counts = np.asarray(g["phase_skill_counts"])
  assert counts.shape == (4, 3) and counts.sum() == sum(row["states"] for row in g["tasks"].values())
  np.testing.assert_array_equal(counts.sum(0), np.bincount(np.concatenate(chosen), minlength=3))
  assert 0.0 <= g["phase_skill_nmi"] <= 1.0
  assert "| uniform |" in capsys.readouterr().out
  # mixed-skill rollouts: each pair half and half, only the modes asked for
  assert skill_probes.modes(3, pairs=True)["mix02"] == (0.5, 0.0, 0.5) and "mix12" in skill_probes.modes(3, True)
  assert skill_probes.modes(3, drops=True)["drop1"] == (0.5, 0.0, 0.5) and "mix01" not in skill_probes.modes(3, drops=True)
  assert skill_probes.main(args + ["--pairs", "--modes", "router,mix01"]) == 0
  mixed = json.loads((out / "skill_probes.json").read_text())
  assert mixed["modes"] == ["router", "mix01"] and set(mixed["seeds"]["0"]["closed_loop"]) == {"router", "mix01"}
  assert (run / "eval" / f"probe_mix01_trials{exp.trials}_seed{exp.eval_seed}.json").exists()
  assert "| mix01 |" in capsys.readouterr().out
  assert skill_probes.main(args + ["--modes", "mix01"]) == 2  # pairs not asked for


def test_comparison_gives_the_difference_and_its_standard_error():
  table = {"tasks": ["jujube_pick"], "abbr": ["J.P."], "rows": {
      "ACT": {"cells": {"jujube_pick": (50.0, 3.0), "Avg.": (50.0, 3.0)}},
      "ACT+SkillPlug": {"cells": {"jujube_pick": (58.0, 4.0), "Avg.": (58.0, None)}}}}
  line = publish.comparison(table, "multi-task")
  assert line == "ACT+SkillPlug minus ACT, multi-task: J.P. +8.0 ± 5.0 (+1.6 SE), Avg. +8.0"
  for row in table["rows"].values():
    row["seeds"] = 1
  one_seed = publish.comparison(table, "multi-task")
  assert one_seed.startswith(line) and "cannot separate the methods" in one_seed and "3-seed" in one_seed
  for row in table["rows"].values():
    row["seeds"] = 3
  assert publish.comparison(table, "multi-task") == line  # 3 seeds: the difference and its SE stand alone
  del table["rows"]["ACT"]
  assert publish.comparison(table, "multi-task") == ""


def test_fewshot_units_are_tasks_or_whole_suites():
  """`FewShot.per`: one fine-tune per task (DISCOVERSE's protocol), or one per comma-separated part
  of the taskset on all its tasks (the paper's LIBERO protocol: adapt to a suite)."""
  per_task = experiment.FewShot(taskset="libero_object:0,libero_goal:3")
  assert fewshot.units(per_task) == [("libero_object:0", ("libero_object:0",)), ("libero_goal:3", ("libero_goal:3",))]
  per_suite = experiment.FewShot(taskset="libero_object,libero_goal", per="taskset")
  (obj, obj_tasks), (goal, goal_tasks) = fewshot.units(per_suite)
  assert (obj, goal) == ("libero_object", "libero_goal")
  assert obj_tasks == tuple(f"libero_object:{i}" for i in range(10)) and len(goal_tasks) == 10
  source = experiment.preset("libero_quick", "skillplug")
  cfg = fewshot.fewshot_config(source, Path("/tmp/src"), obj, per_suite)
  # the fine-tune trains on the whole suite's demonstrations, read from the dataset of every target
  assert (cfg.taskset, cfg.data_taskset, cfg.workdir) == ("libero_object", "libero_object,libero_goal",
                                                          "/tmp/src_fewshot/libero_object")
  with pytest.raises(ValueError, match="fewshot.per"):
    experiment.FewShot(per="suite")


def test_an_evaluation_read_back_names_where_its_run_is_now(tmp_path):
  # a results folder moved after its runs were evaluated: the read-back results point at the
  # run's folder and routing arrays where they are now, so that publishing copies them
  exp = experiment.get("quick")
  run = tmp_path / "moved" / "runs" / "r"
  (run / "eval").mkdir(parents=True)
  stale = "/elsewhere/runs/r/eval/quickstart3_trials5_seed1000_jujube_pick.routing.npz"
  (run / "eval" / f"quickstart3_trials{exp.trials}_seed{exp.eval_seed}.json").write_text(json.dumps(
      dict(results=[dict(task="jujube_pick", run="/elsewhere/runs/r", routing_file=stale, success_rate=1.0),
                    dict(task="drawer_open", run="/elsewhere/runs/r", routing_file=None, success_rate=0.0)])))
  got = pipeline.evaluated(run, ["jujube_pick", "drawer_open"], exp, "quickstart3", run)
  assert got[0]["run"] == str(run) and got[0]["routing_file"] == str(run / "eval" / Path(stale).name)
  assert got[1]["routing_file"] is None and got[1]["success_rate"] == 0.0
