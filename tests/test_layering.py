"""The library stands on its own: nothing under skillplug_jax/ or envs/ imports the packages
built on it (experiments, benchmarks, figures, tools), not even inside a function."""

import ast
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
