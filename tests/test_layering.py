"""The library stands on its own: nothing under skillplug_jax/ or envs/ imports the packages
built on it (experiments, benchmarks, figures, tools), not even inside a function. Within it,
training (skillplug_jax/train/) does not import the experiment configs built on it, and the
configs and the model read only the suite's names (envs.names), not the suite."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ("skillplug_jax", "envs")
ABOVE = frozenset({"experiments", "benchmarks", "figures", "tools"})


def imports_above(path: Path, root: Path = ROOT) -> list[str]:
  """'file:line: module' for each import in `path` of a package above the library: import and
  from-import statements anywhere in the file, and importlib.import_module / __import__ of a
  constant name."""
  found = []

  def check(name: str, node: ast.AST) -> None:
    if name.split(".")[0] in ABOVE:
      found.append(f"{path.relative_to(root)}:{node.lineno}: {name}")

  for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
    if isinstance(node, ast.Import):
      for alias in node.names:
        check(alias.name, node)
    elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
      check(node.module, node)
    elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
          and isinstance(node.args[0].value, str)
          and ((isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
               or (isinstance(node.func, ast.Name) and node.func.id == "__import__"))):
      check(node.args[0].value, node)
  return found


def imported(path: Path) -> list[tuple[int, str]]:
  """(line, module) of every import in `path`, anywhere in it; `from a import b` counts as
  both a and a.b (b may be a module)."""
  found = []
  for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
    if isinstance(node, ast.Import):
      found += [(node.lineno, alias.name) for alias in node.names]
    elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
      found += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
  return found


def test_training_does_not_import_the_experiment_configs():
  files = sorted((ROOT / "skillplug_jax" / "train").glob("*.py"))
  assert len(files) > 5
  found = [f"{p.relative_to(ROOT)}:{line}: {name}" for p in files for line, name in imported(p)
           if name == "skillplug_jax.experiment" or name.startswith("skillplug_jax.experiment.")]
  assert not found, "skillplug_jax/train imports skillplug_jax.experiment:\n" + "\n".join(found)


# Built wherever a config is read: of envs they import the names alone, not the suite (MuJoCo, the tasks).
CHEAP = ["skillplug_jax/validation.py", "skillplug_jax/losses.py", "skillplug_jax/experiment.py",
         "skillplug_jax/train/config.py", "skillplug_jax/train/run_record.py", "skillplug_jax/data/segments.py",
         *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "skillplug_jax" / "model").glob("*.py"))]


def test_configs_and_the_model_read_only_the_suites_names():
  found = [f"{path}:{line}: {name}" for path in CHEAP for line, name in imported(ROOT / path)
           if name.split(".")[0] == "envs" and name not in ("envs.names",) and not name.startswith("envs.names.")]
  assert not found, "these import the environment suite, not envs.names:\n" + "\n".join(found)
  code = ("import sys; from skillplug_jax import experiment; from skillplug_jax.model import act; "
          "exp = experiment.get('skill_library'); experiment.expand(exp); "
          "act.num_tokens(exp.train.model); "
          "print(sorted(m for m in ('mujoco', 'envs.suite', 'envs.env', 'warp') if m in sys.modules))")
  out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
  assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_library_imports_nothing_built_on_it():
  files = [p for package in LIBRARY for p in sorted((ROOT / package).rglob("*.py"))]
  assert len(files) > 40  # every module was parsed, not an empty glob
  found = [hit for p in files for hit in imports_above(p)]
  assert not found, "the library imports packages built on it:\n" + "\n".join(found)


def test_the_check_sees_imports_anywhere(tmp_path):
  planted = tmp_path / "planted.py"
  planted.write_text("import os\n\ndef f():\n  from experiments import configs\n  import tools.x as t\n"
                     "  return __import__('figures')\n")
  assert imports_above(planted, tmp_path) == ["planted.py:4: experiments", "planted.py:5: tools.x",
                                              "planted.py:6: figures"]
