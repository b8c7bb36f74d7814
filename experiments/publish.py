"""A pipeline run's summary as tables and text, and its publication: what `experiments.pipeline`
writes once its jobs are done, and what a later run reads back as reference rows.

    merged_summary   one stage's results (the jobs', a reference's) and their tables
    variant_rows     each arm of an ablation or sweep: its rows, its routing entropy
    toy_summary      the toy problem's extras per row (routing against the primitives, probes)
    report           summary.md: variants, tables, ACT+SkillPlug minus ACT, stages
    publish          summary.{md,json} and the routing arrays, in a folder to commit
"""

from __future__ import annotations

import json
from pathlib import Path

from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate import groups, tables
from skillplug_jax.experiment import Experiment


def merged_summary(parts: list[dict], key: str, tasks, reference: list[dict] = (), row_tasks=None) -> dict:
  """The jobs' results of one stage (and the reference's) and their tables: rows group every job's runs.
  row_tasks: a row's training key -> its tasks, where arms train on different suites (`tables.summarise`).
  On LIBERO's tasks also the paper's per-suite tables, by LIBERO's rule and by ours (`libero`)."""
  results = [groups.normalised_result(r) for r in list(reference) + [r for part in parts for r in part[key]]]
  out = dict(results=results, **tables.summarise(results, tasks, row_tasks))
  if all("libero_success_rate" in r for r in results) and results:
    out["libero"] = libero_tables(out, tasks)
  return out


# What tells the paper's LIBERO rows apart is the policy, not the suite trained on: an arm per suite
# is a column of one row (its Multi-task table), so the suite is left out of the row's key.
SUITE_FIELDS = ("taskset", "data_taskset")


def libero_tables(stage: dict, tasks) -> dict:
  """A LIBERO stage's tables (`evaluate.libero.tables_of`) for both rules: a row per training
  key less the suite trained on (`SUITE_FIELDS`), so the arms of one policy, one per suite, are one row."""
  from skillplug_jax.evaluate import libero
  keys, changes = {}, {}
  for row in stage["rows"].values():
    k = {f: v for f, v in row["config"].items() if f not in SUITE_FIELDS}
    keys.setdefault(groups.key_id(k), k)
    changes.setdefault(groups.key_id(k), {f: v for f, v in row["overrides"].items() if f not in SUITE_FIELDS})
  name_of = dict(zip(keys, groups.row_names(list(keys.values()), [changes[i] for i in keys])))
  def policy(config):
    return name_of[groups.key_id({f: v for f, v in config.items() if f not in SUITE_FIELDS})]
  rows = [dict(r, policy=policy(r["config"]), seed=r["train_seed"]) for r in stage["results"]]
  progress = (libero.PROGRESS,) if all(f"{libero.PROGRESS}_rate" in r for r in rows) else ()
  return {m: libero.tables_of(rows, tasks, m) for m in libero.MEASURES + progress}


def libero_report(stage: dict, name: str) -> str:
  """The per-suite tables of a LIBERO stage (`name`: pretrain or fewshot), in the paper's layout, by
  both rules; the paper's rows of that stage beside LIBERO's rule, the one its numbers count."""
  from skillplug_jax.evaluate import libero
  t = stage["libero"]
  return "\n".join(["Per suite, LIBERO's rule (its goal at any step within the limit: what published LIBERO "
                    "numbers count), %; the paper's rows (OpenVLA-OFT on LIBERO's human demonstrations, "
                    "images) are its table's, not this run:", "",
                    libero.markdown(t["libero_success"]["per_suite"], paper=name), "",
                    "Per suite, our rule (placed, released, held 0.5 s: the tables above), %:", "",
                    libero.markdown(t["success"]["per_suite"])]
                   + (["", "How far the trials got: the goal's atoms (LIBERO-10's: mostly both objects placed) "
                       "that held at some step within the limit, each on its own, % of atoms and trials:", "",
                       libero.markdown(t[libero.PROGRESS]["per_suite"])] if libero.PROGRESS in t else []))


def reference_results(path: str, stage: str) -> list[dict]:
  """The results of one stage of a published summary, marked as read from it. A result from
  before results carried their overrides takes its published row's, so that the row is named
  as it was published, not against today's config file."""
  p = Path(path)
  if not p.exists():
    raise ValueError(f"reference summary {p} does not exist (a published pipeline summary.json)")
  from skillplug_jax.evaluate import routing
  part = routing.renamed(json.loads(p.read_text())).get(stage, {})  # written before today's key names too
  published = {groups.key_id(row["config"]): row["overrides"] for row in part.get("rows", {}).values()
               if "overrides" in row}
  out = []
  for r in part.get("results", []):
    r = dict(r, reference=str(p))
    if "overrides" not in r and groups.key_id(r["config"]) in published:
      r["overrides"] = published[groups.key_id(r["config"])]
    out.append(groups.normalised_result(r))
  return out


def variant_rows(exp: Experiment, summary: dict) -> list[dict]:
  """Each variant (and each reference row): its label, overrides, and its row's name in each
  stage's tables (names depend on the rows beside it, so a stage's may differ from another's)."""
  stages = [s for s in ("pretrain", "fewshot") if s in summary]

  def row_of(stage, match):
    return next((name for r in summary[stage]["results"] if match(r)
                 for name, row in summary[stage]["rows"].items() if row["config"] == r["config"]), None)

  out = [dict(variant=v.name, label=v.label or v.name, overrides=list(v.overrides),
              rows={s: row_of(s, lambda r, v=v: r.get("variant") == v.name) for s in stages},
              routing_entropy_per_query=routing_entropy([r for r in summary["pretrain"]["results"]
                                                    if r.get("variant") == v.name]))
         for v in exp.variants]
  if exp.reference:
    for name, row in summary["pretrain"]["rows"].items():
      mine = [r for r in summary["pretrain"]["results"] if r.get("reference") and r["config"] == row["config"]]
      if not mine:
        continue
      out.append(dict(variant="", label=f"{name} (reference)", overrides=[],
                      rows={s: row_of(s, lambda r, c=row["config"]: bool(r.get("reference")) and r["config"] == c)
                            for s in stages},
                      routing_entropy_per_query=routing_entropy(mine)))
  return out


def _in_name(task: str) -> str:
  """A task's name as part of a file name: LIBERO's `libero_object:3` as `libero_object_3`."""
  return task.replace(":", "_")


def routing_file(r: dict) -> Path | None:
  """Where a result's routing array is: beside its run, or (a reference's) where it was published."""
  if r.get("routing_file") and Path(r["routing_file"]).exists():
    return Path(r["routing_file"])
  if r.get("reference"):  # named as `publish` names it: an arm's with its variant first
    arm = f"{r['variant']}_" if r.get("variant") else ""
    published = Path(r["reference"]).parent / "routing" / (
        f"{arm}{r['config']['model.policy']}_seed{r['train_seed']}_pretrain_{_in_name(r['task'])}.npz")
    return published if published.exists() else None
  return None


def routing_entropy(results: list[dict]) -> float | None:
  """Mean per-query routing entropy as a fraction of log K over these (pretraining) results
  (1: uniform routing at every query); None without routing arrays (ACT)."""
  from skillplug_jax.evaluate import routing
  files = [f for f in map(routing_file, results) if f is not None]
  if not files:
    return None
  return float(sum(s["routing_entropy_per_query"] for s in routing.summarise_files(files)) / len(files))


TOY_ROUTING = ("routing_entropy_per_query", "usage_entropy", "effective_skills", "nmi", "nmi_task", "nmi_stage",
               "nmi_quadrant")


def _cell(values: list) -> list | None:
  """[mean, SE] (SE None for one value) of the values that exist; None if none does."""
  values = [v for v in values if v is not None]
  return list(tables.mean_se(values)) if values else None


def toy_summary(parts: list[dict], summary: dict) -> dict:
  """The toy problem's numbers per pretraining row (`evaluate.toy_rollout`), mean and SE over its
  seeds: stage progress (multi-task, zero-shot, few-shot), zero-shot success, the routing
  statistics of the seen tasks' closed-loop queries against the primitive label, and the
  fixed-skill probe (distinct pure primitives, mean purity, uniform-routing success; each
  seed's skill -> primitive)."""
  extras = [e for part in parts for e in part.get("toy", [])]
  out = {}
  for name, row in summary["pretrain"]["rows"].items():
    mine = sorted((e for e in extras if e["config"] == row["config"]), key=lambda e: e["train_seed"])
    if not mine:
      continue

    def progress(stage):
      per_seed = {}
      for r in summary.get(stage, {}).get("results", []):
        if r["config"] == row["config"] and "stage_progress" in r:
          per_seed.setdefault(r["train_seed"], []).append(r["stage_progress"])
      return _cell([sum(v) / len(v) for v in per_seed.values()])

    avg = lambda d: sum(d.values()) / len(d)  # noqa: E731
    entry = dict(seeds=[e["train_seed"] for e in mine], multitask_progress=progress("pretrain"),
                 zero_shot_success=_cell([avg(e["zero_shot"]) for e in mine]),
                 zero_shot_progress=_cell([avg(e["zero_shot_progress"]) for e in mine]),
                 fewshot_progress=progress("fewshot"))
    routed = [e["toy_routing"] for e in mine if "toy_routing" in e]
    entry["routing"] = {k: _cell([r.get(k) for r in routed]) for k in TOY_ROUTING} if routed else None
    probes = [e["fixed_skill_probe"] for e in mine if "fixed_skill_probe" in e]
    entry["fixed_skill_probe"] = dict(
        distinct_pure_primitives=_cell([p["distinct_pure_primitives"] for p in probes]),
        mean_purity=_cell([p["mean_purity"] for p in probes]),
        uniform_success=_cell([p["uniform_success"] for p in probes]),
        per_seed=[{k: [v["primitive"], round(v["purity"], 2)] for k, v in p["skills"].items()} for p in probes],
    ) if probes else None
    out[name] = entry
  return dict(rows=out)


def _fmt(cell, pct: bool = False, digits: int = 2) -> str:
  if cell is None:
    return "-"
  mean, se = cell
  scale, d = (100.0, 1) if pct else (1.0, digits)
  return f"{mean * scale:.{d}f}" + ("" if se is None else f" ± {se * scale:.{d}f}")


def toy_report(summary: dict) -> str:
  """The toy section of summary.md: per row, what the tables above do not show."""
  toy = summary["toy"]
  head = ["row", "seeds", "multi-task stages %", "zero-shot %", "zero-shot stages %", "few-shot stages %",
          "H(r)/log K", "H(mean r)/log K", "eff. skills", "NMI primitive", "NMI task", "NMI stage",
          "NMI quadrant", "pure skills", "uniform-routing %"]
  lines = ["Toy problem (envs/toy_skills.py): stage progress, zero-shot, and the routing of the closed-loop "
           "queries on the seen tasks against the primitive being executed (NMI of the argmax skill), "
           "the fixed-skill probe (each skill alone; uniform routing):", "",
           "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for name, v in toy["rows"].items():
    r, p = v["routing"] or {}, v["fixed_skill_probe"] or {}
    cells = [name, ",".join(map(str, v["seeds"])), _fmt(v["multitask_progress"], True),
             _fmt(v["zero_shot_success"], True), _fmt(v["zero_shot_progress"], True),
             _fmt(v["fewshot_progress"], True)]
    cells += [_fmt(r.get(k)) for k in TOY_ROUTING]
    cells += [_fmt(p.get("distinct_pure_primitives"), digits=1), _fmt(p.get("uniform_success"), True)]
    lines.append("| " + " | ".join(cells) + " |")
  probes = [(name, v) for name, v in toy["rows"].items() if v["fixed_skill_probe"]]
  if probes:
    lines += ["", "Fixed-skill probe (seed: skill -> what it does, purity):"]
    for name, v in probes:
      for seed, row in zip(v["seeds"], v["fixed_skill_probe"]["per_seed"]):
        lines.append(f"- {name} seed {seed}: " + ", ".join(f"{k} {prim} {q:.2f}" for k, (prim, q) in row.items()))
  if "mined_labels" in toy:
    m = toy["mined_labels"]
    lines += ["", f"Mined labels (train.skill_labels={m['labeller']}) against the primitive, every demonstration "
              f"step: NMI {m['nmi']:.3f}, equal {100 * m['equal']:.1f}%."]
  if summary.get("cpu"):
    lines += [f"CPU: {summary['cpu']}."]
  return "\n".join(lines)


def publish(summary: dict, text: str, dest: Path) -> None:
  """The summary and every routing array, in one folder that can be committed and read by the notebooks.

  dest/summary.{md,json}; dest/routing/[<variant>_]<policy>_seed<S>_<stage>_<task>.npz
  (stage: pretrain or fewshot) and dest/routing/index.json, a list of
  {policy, seed, stage, task, file, success_rate, config, variant}.
  """
  import shutil
  dest = Path(dest)
  (dest / "routing").mkdir(parents=True, exist_ok=True)
  index = []
  for stage in ("pretrain", "fewshot"):
    for r in summary.get(stage, {}).get("results", []):
      if not r.get("routing_file") or r.get("reference"):  # a reference's arrays are where it was published
        continue
      arm = f"{r['variant']}_" if r.get("variant") else ""
      name = f"{arm}{r['config']['model.policy']}_seed{r['train_seed']}_{stage}_{_in_name(r['task'])}.npz"
      tmp = dest / "routing" / (name + ".tmp")
      shutil.copyfile(r["routing_file"], tmp)
      tmp.replace(dest / "routing" / name)
      index.append(dict(policy=r["policy"], seed=r["train_seed"], stage=stage, task=r["task"], file=name,
                        success_rate=r["success_rate"], config=groups.key_id(r["config"]),
                        variant=r.get("variant", "")))
  write_json_atomic(dest / "routing" / "index.json", index)
  write_json_atomic(dest / "summary.json", summary)
  write_text_atomic(dest / "summary.md", text + "\n")


def comparison(table: dict, stage: str) -> str:
  """ACT+SkillPlug minus ACT on each task and on Avg., with the standard error of the difference
  (the seeds of the two rows are independent runs: SE = sqrt(SE_a^2 + SE_b^2))."""
  rows = table["rows"]
  if "ACT" not in rows or "ACT+SkillPlug" not in rows:
    return ""
  parts = []
  for key, name in zip(table["tasks"] + ["Avg."], table["abbr"] + ["Avg."]):
    a, b = rows["ACT+SkillPlug"]["cells"][key], rows["ACT"]["cells"][key]
    if a is None or b is None:
      continue
    diff = a[0] - b[0]
    if a[1] is None or b[1] is None:
      parts.append(f"{name} {diff:+.1f}")
      continue
    se = (a[1] ** 2 + b[1] ** 2) ** 0.5
    parts.append(f"{name} {diff:+.1f} ± {se:.1f}" + (f" ({diff / se:+.1f} SE)" if se > 0 else ""))
  line = f"ACT+SkillPlug minus ACT, {stage}: " + ", ".join(parts)
  counts = [rows[r].get("seeds") for r in ("ACT", "ACT+SkillPlug")]
  counts = [len(c) if isinstance(c, list) else c for c in counts if c is not None]
  seeds = min(counts, default=None)
  if seeds is not None and seeds < 3:
    line += (f"\n({seeds} training seed(s) per row: this difference cannot separate the methods. At small "
             "budgets ACT alone moves by tens of points between seeds (0, 16 and 36% on jujube_pick for "
             "quick-preset seeds 7, 0 and 8, docs/measurements/quickstart.md); the comparison is the 3-seed, 50-trial "
             "tables of docs/measurements/paper_protocol_cpu.md.)")
  return line


def _fewshot_steps(summary: dict) -> str:
  steps = sorted({r["steps"] for r in summary["fewshot"]["results"] if r.get("steps") is not None})
  return "/".join(map(str, steps)) or str(summary["experiment"]["fewshot"]["steps"])


def _avg(table: dict, row: str) -> str:
  cell = table["rows"].get(row, {}).get("cells", {}).get("Avg.")
  return "-" if cell is None else (f"{cell[0]:.1f}" if cell[1] is None else f"{cell[0]:.1f} ± {cell[1]:.1f}")


def per_seed_avg(summary: dict, stage: str, row: str) -> dict[int, float]:
  """{training seed: its success rate (%) averaged over the stage's tasks} of one row."""
  cfg = summary[stage]["rows"][row]["config"]
  rates = {}
  for r in summary[stage]["results"]:
    if r["config"] == cfg:
      rates.setdefault(r["train_seed"], []).append(100 * r["success_rate"])
  return {s: sum(v) / len(v) for s, v in sorted(rates.items())}


def variants_report(summary: dict) -> str:
  """One line per arm: its Avg. success in each stage, and each seed's, so that single-seed arms can
  be read against the same seed of the others."""
  stages = [s for s in ("pretrain", "fewshot") if s in summary]
  head = (["variant", "row", "seeds"] + [f"{'Multi-task' if s == 'pretrain' else 'Few-shot'} Avg. (per seed)"
                                          for s in stages] + ["routing entropy / log K"])
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for v in summary["variants"]:
    cells = []
    for s in stages:
      row = v["rows"].get(s)
      if row is None:
        cells.append("-")
        continue
      seeds = per_seed_avg(summary, s, row)
      cells.append(f"{_avg(summary[s]['table'], row)} ({', '.join(f's{k}: {x:.1f}' for k, x in seeds.items())})")
    # an arm that adapts another's runs has few-shot rows only (its pretraining is its source's)
    stage = next((s for s in stages if v["rows"].get(s)), "pretrain")
    row = v["rows"].get(stage)
    seeds = summary[stage]["rows"][row]["seeds"] if row else []
    ent = v.get("routing_entropy_per_query")
    cells.append("-" if ent is None else f"{ent:.3f}")
    lines.append(f"| {v['label']} | {row or '-'} | {','.join(map(str, seeds))} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def report(summary: dict) -> str:
  exp = summary["experiment"]
  t, d, seeds = exp["trials"], exp["train"]["demos"], exp["seeds"]
  seeds_text = ("training seeds per row as listed under Variants" if summary.get("variants")
                else f"{len(seeds)} training seed(s)")
  lines = []
  if summary.get("variants"):
    lines += ["Variants:", "", variants_report(summary), ""]
  lines += ["Multi-task:", "",
            tables.report(summary["pretrain"], f"`{summary['config']}` config, {d} demos per task, "
                          f"{seeds_text}, {t} paired trials per task"), "",
            comparison(summary["pretrain"]["table"], "success points, multi-task"), ""]
  if "libero" in summary["pretrain"]:
    lines += [libero_report(summary["pretrain"], "pretrain"), ""]
  if "fewshot" in summary:
    fs = exp["fewshot"]
    lines += ["Few-shot on the unseen tasks:", "",
              tables.report(summary["fewshot"], f"{fs['demos']} demos, {_fewshot_steps(summary)} fine-tuning "
                            f"steps, {t} paired trials"), "",
              comparison(summary["fewshot"]["table"], "success points, few-shot"), ""]
    if "libero" in summary["fewshot"]:
      lines += [libero_report(summary["fewshot"], "fewshot"), ""]
  if "toy" in summary:
    lines += [toy_report(summary), ""]
  lines += ["Stages (s): " + ", ".join(f"{k} {v:.0f}" for k, v in summary["stages_s"].items()),
            f"Runs: {', '.join(summary['runs'])}",
            f"Wall time: {summary['wall_s'] / 60:.1f} min on {summary['device']}, physics on {summary['backend']}."]
  return "\n".join(lines)
