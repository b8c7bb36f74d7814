"""The documentation: links resolve, every committed result is indexed, the README stays short.

- Every relative link in README.md and docs/**/*.md (markdown `[text](path)`,
  images, and `<img src=...>`) names a file or folder that exists; http(s):,
  mailto: and pure #anchors are skipped, #fragments stripped. Links inside
  code (fenced blocks, `inline`) are not links.
- Every file under docs/results/ is listed in docs/results/README.md: by its
  own path, or by a listed folder (an entry ending in `/`) that contains it.
  Entries are the first cell of the index's table rows, in backticks,
  relative to docs/results/; each must exist.
- README.md is at most 200 lines (docs/, not the README, holds the reference
  text and the measurement log).
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
RESULTS_INDEX = RESULTS / "README.md"
README_MAX_LINES = 200

FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")
MD_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+[\"'][^)]*[\"'])?\s*\)")
IMG_SRC = re.compile(r"<img\b[^>]*\bsrc\s*=\s*[\"']([^\"']+)[\"']", re.I)
SKIP = ("http://", "https://", "mailto:", "#")


def markdown_files() -> list[Path]:
  return [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))


def links(text: str) -> list[str]:
  """The link targets of a markdown text, code removed first."""
  text = INLINE_CODE.sub("", FENCE.sub("", text))
  return MD_LINK.findall(text) + IMG_SRC.findall(text)


def broken_links(path: Path) -> list[str]:
  broken = []
  for target in links(path.read_text(encoding="utf-8")):
    if target.startswith(SKIP):
      continue
    rel = unquote(target.split("#", 1)[0].split("?", 1)[0])
    if not rel:
      continue
    resolved = (ROOT / rel.lstrip("/")) if rel.startswith("/") else (path.parent / rel)
    resolved = resolved.resolve()
    if not resolved.is_relative_to(ROOT) or not resolved.exists():
      broken.append(f"{path.relative_to(ROOT)}: {target}")
  return broken


def index_entries(text: str) -> list[str]:
  """Backticked paths in the first cell of each table row of the results index."""
  entries = []
  for line in text.splitlines():
    cells = line.split("|")
    if len(cells) > 2 and line.lstrip().startswith("|"):
      entries += re.findall(r"`([^`]+)`", cells[1])
  return entries


def unlisted_results(entries: list[str]) -> list[str]:
  files = {p.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("*") if p.is_file() and p != RESULTS_INDEX}
  folders = {e for e in entries if e.endswith("/")}
  listed = set(entries)

  def covered(f: str) -> bool:
    parts = f.split("/")
    return f in listed or any("/".join(parts[:i]) + "/" in folders for i in range(1, len(parts)))

  return sorted(f for f in files if not covered(f))


def test_links_resolve():
  broken = [b for path in markdown_files() for b in broken_links(path)]
  assert not broken, "links to nothing:\n" + "\n".join(broken)


def test_link_check_sees_links():
  # The checks above pass vacuously if the patterns find nothing.
  text = "[a](x.md) ![b](img/y.png) <img src='z.gif'> [c](http://e.org) `[d](no.md)`\n```\n[e](no2.md)\n```\n"
  assert links(text) == ["x.md", "img/y.png", "http://e.org", "z.gif"]
  assert sum(len(links(p.read_text(encoding="utf-8"))) for p in markdown_files()) > 50


def test_every_result_file_is_indexed():
  entries = index_entries(RESULTS_INDEX.read_text(encoding="utf-8"))
  assert entries, "docs/results/README.md lists nothing"
  missing = [e for e in entries if not (RESULTS / e).exists()]
  assert not missing, "docs/results/README.md lists paths that do not exist:\n" + "\n".join(missing)
  unlisted = unlisted_results(entries)
  assert not unlisted, ("files under docs/results/ that docs/results/README.md does not list "
                        "(by path, or by a folder entry ending in '/'):\n" + "\n".join(unlisted))


def test_readme_is_short():
  lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
  assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES})"
