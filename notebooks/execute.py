"""Execute the notebooks, in place (as they are committed) or into memory (the tests).

    make notebooks                                    # on docs/results/paper_cpu
    python notebooks/execute.py --results DIR a.ipynb # on another published pipeline run
    python notebooks/execute.py --results DIR --into DIR/notebooks   # keep the committed ones as they are

A notebook reads the folder `python -m experiments.pipeline --publish DIR`
writes; SKILLPLUG_RESULTS tells it which.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent
NOTEBOOKS = ("success_tables.ipynb", "routing.ipynb", "skill_similarity.ipynb", "fixed_skills.ipynb")


def execute(path: str | Path, results: str | Path | None = None, timeout: int = 600):
  """The executed notebook (nbformat node); raises nbclient's CellExecutionError on a failing cell."""
  path = Path(path)
  nb = nbformat.read(path, as_version=4)
  env = dict(os.environ)
  if results is not None:
    os.environ["SKILLPLUG_RESULTS"] = str(Path(results).resolve())  # the kernel inherits this process's env
  try:
    NotebookClient(nb, timeout=timeout, kernel_name="python3",
                   resources={"metadata": {"path": str(path.parent)}}).execute()
  finally:
    os.environ.clear()
    os.environ.update(env)
  return nb


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("notebooks", nargs="*", help=f"default: {', '.join(NOTEBOOKS)}")
  p.add_argument("--results", default=None, help="published pipeline folder (default: each notebook's own)")
  p.add_argument("--into", default=None, metavar="DIR",
                 help="write the executed notebooks here (default: in place, over the committed ones)")
  args = p.parse_args(argv)
  for name in args.notebooks or [HERE / n for n in NOTEBOOKS]:
    nb = execute(name, args.results)
    target = Path(args.into) / Path(name).name if args.into else Path(name)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(str(target) + ".tmp")
    nbformat.write(nb, tmp)
    os.replace(tmp, target)
    print(f"executed {name} -> {target}")
  return 0


if __name__ == "__main__":
  from skillplug_jax import startup
  startup.prepare_process()  # the kernels inherit this process's environment: make's allocator setting
  sys.exit(main())
