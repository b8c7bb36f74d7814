"""The skill probes' GIFs of one task as one PNG: a row per routing mode, frames left to right.

    python -m figures.probe_sheet --videos results/paper_cpu_image/probe_videos/seed0 --task drawer_open --out /tmp/sheet.png

`experiments.skill_probes --videos N` writes VIDEOS/<mode>/<task>_trialNN.gif
(the side camera of trial NN with the router's weights replaced: `router`,
`uniform`, `skill<k>`, ...). Read side by side, a row that moves unlike the
others is a skill that does something of its own.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np


def _mode_order(name: str) -> tuple:
  """router, uniform, then skill0, skill1, ..., then any other mode by name."""
  fixed = {"router": 0, "uniform": 1}
  m = re.fullmatch(r"skill(\d+)", name)
  return (fixed[name],) if name in fixed else (2, int(m.group(1))) if m else (3, name)


def probe_sheet(videos: Path, task: str, trial: int = 0, frames: int = 6) -> tuple[np.ndarray, list[str]]:
  """([modes * H, frames * W, 3] uint8, the modes top to bottom): `frames` evenly spaced frames of
  each mode's GIF of `task`, trial `trial` (an episode shorter than `frames` repeats its frames)."""
  if frames < 1:
    raise ValueError(f"frames must be at least 1, got {frames}")
  name = f"{task}_trial{trial:02d}.gif"
  modes = sorted((d.name for d in Path(videos).iterdir() if (d / name).exists()), key=_mode_order)
  if not modes:
    raise ValueError(f"no {name} under {videos}/<mode>/ (run experiments.skill_probes with --videos first)")
  rows = []
  for mode in modes:
    clip = iio.imread(Path(videos) / mode / name, index=None)[..., :3]
    pick = np.linspace(0, len(clip) - 1, frames).round().astype(int)
    rows.append(np.concatenate(list(clip[pick]), axis=1))
  return np.concatenate(rows, axis=0), modes


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--videos", required=True, help="a probe_videos/seed<S> folder (one subfolder per mode)")
  p.add_argument("--task", required=True)
  p.add_argument("--trial", type=int, default=0)
  p.add_argument("--frames", type=int, default=6, help="frames per row, evenly spaced over the episode")
  p.add_argument("--out", required=True, help="the PNG to write")
  args = p.parse_args(argv)
  try:
    sheet, modes = probe_sheet(Path(args.videos), args.task, args.trial, args.frames)
  except ValueError as e:
    p.error(str(e))
  iio.imwrite(args.out, sheet)
  print(f"wrote {args.out}: rows {', '.join(modes)}")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
