"""The Makefile's GLIBC_TUNABLES: XLA:CPU's per-call buffers on huge pages.

XLA:CPU allocates each call's temporary buffer (640 MB in the paper-shape
train step) with malloc and frees it at the end. glibc serves a block that
large with a fresh mmap and returns it with munmap, so every call faults its
pages in again, 4 KB at a time: 166K page faults and 0.4-1.2 s of kernel
time per paper step on this project's CPU (docs/measurements/speed.md). With glibc.malloc.hugetlb=1 such blocks are madvised
onto transparent huge pages: about 900 faults per step. glibc ignores a
misspelt tunable without a word; these tests are what notice.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import pytest

MAKEFILE = Path(__file__).resolve().parents[1] / "Makefile"

# A jitted call with a 64 MB intermediate that two reductions read (so it
# is materialised), run until warm; prints the mean page faults of 3 calls.
PROBE = """
import resource
import jax, jax.numpy as jnp

@jax.jit
def f(x):
  y = jnp.exp(x[:, None] * x[None, :])
  return y.sum(0) + y.sum(1)

x = jnp.linspace(0.0, 1e-3, 4096)
for _ in range(2):
  jax.block_until_ready(f(x))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
  jax.block_until_ready(f(x))
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3)
"""

glibc = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                           reason="GLIBC_TUNABLES is read by glibc's malloc only")


def makefile_tunables() -> str:
  found = re.search(r"^export GLIBC_TUNABLES \?= (\S+)$", MAKEFILE.read_text(), re.M)
  assert found, "the Makefile no longer exports GLIBC_TUNABLES"
  return found.group(1)


def faults_per_call(tunables: str) -> float:
  env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
  if tunables:
    env["GLIBC_TUNABLES"] = tunables
  env["JAX_PLATFORMS"] = "cpu"
  env.pop("XLA_FLAGS", None)
  out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True,
                       timeout=300, check=True)
  return float(out.stdout.strip().splitlines()[-1])


def dynamic_loader() -> str:
  """This process's glibc dynamic loader (ld-linux*.so), from its memory map."""
  for line in Path("/proc/self/maps").read_text().splitlines():
    path = line.split()[-1]
    if "/ld-linux" in path:
      return path
  pytest.fail("no ld-linux*.so mapped in this process")


@glibc
def test_glibc_reads_every_makefile_tunable():
  """glibc takes each setting (it ignores a misspelt name without a word)."""
  tunables = makefile_tunables()
  out = subprocess.run([dynamic_loader(), "--list-tunables"], capture_output=True, text=True,
                       check=True, env={**os.environ, "GLIBC_TUNABLES": tunables}).stdout
  seen = dict(re.findall(r"^(glibc\.\S+): (\S+)", out, re.M))
  for item in tunables.split(":"):
    name, _, value = item.partition("=")
    assert name in seen, f"{name} is not a tunable of this glibc"
    assert int(seen[name], 0) == int(value), (name, seen[name], value)


def transparent_huge_pages() -> str:
  """The kernel's THP mode: 'always', 'madvise' or 'never' ('' if unknown)."""
  try:
    mode = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
  except OSError:
    return ""
  found = re.search(r"\[(\w+)\]", mode)
  return found.group(1) if found else ""


@glibc
@pytest.mark.skipif(transparent_huge_pages() != "madvise",
                    reason="hugetlb=1 acts where THP is 'madvise' ('always' already puts large "
                           "mappings on huge pages, 'never' has none)")
def test_makefile_tunables_cut_the_per_call_page_faults():
  # 64 MB in 4 KB pages is 16,384 faults per call (the control: the probe
  # does allocate afresh each call); on 2 MB pages, a few hundred.
  plain, tuned = faults_per_call(""), faults_per_call(makefile_tunables())
  assert plain > 8000
  assert tuned < plain / 8, (plain, tuned)
