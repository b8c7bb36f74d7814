"""An evaluation's report, one writer for `skillplug eval` and `skillplug fewshot`: what they
print, and the files beside it (each written by one rename, so a reader never sees half)."""

from __future__ import annotations

from pathlib import Path

from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.evaluate import protocol, tables


def rows_legend(rows: dict) -> str:
  """One line per table row: its training seeds and the settings it overrides (the JSON has them all)."""
  lines = []
  for name, row in rows.items():
    changed = ", ".join(f"{k}={v}" for k, v in row["overrides"].items()) or "none"
    lines.append(f"{name}: {row['config']['preset']} preset, seeds {row['seeds']}; overridden: {changed}")
  return "\n".join(lines)


def write(out: dict, what: str, dest: str | Path = "") -> str:
  """The report's text: the three tables (`tables.report`, `what` says what was run), a legend
  of their rows and the solver line. With `dest`, also DEST.json (everything), DEST.md (the
  tables), DEST.csv (success), DEST.queries.csv and DEST.queries_paired.csv."""
  md = tables.report(out, what)
  text = "\n".join(["", md, "", rows_legend(out["rows"]), protocol.solver_limit_summary(out["results"])])
  if dest:
    base = Path(dest)
    write_json_atomic(base.with_suffix(".json"), out)
    write_text_atomic(base.with_suffix(".md"), md + "\n")
    write_text_atomic(base.with_suffix(".csv"), tables.csv(out["table"]))
    write_text_atomic(base.with_suffix(".queries.csv"), tables.csv(out["queries"]))
    write_text_atomic(base.with_suffix(".queries_paired.csv"), tables.csv(out["queries_paired"]))
    text += f"\nwrote {base.with_suffix('.json')}, .md, .csv, .queries.csv, .queries_paired.csv"
  return text
