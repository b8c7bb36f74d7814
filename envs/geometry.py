"""Geometric predicates the tasks' resets and success checks are written with: pure functions of
positions and rotation matrices (one environment; batching is `jax.vmap`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def rests_on(p, target, height, tol=0.01):
  """Object origin `p` sits `height` above `target`'s origin, within `tol` (m)."""
  return jnp.abs(p[2] - target[2] - height) < tol


def upright(mat, threshold=0.99):
  """DISCOVERSE's 'upright': the body's z-axis within ~8 degrees of vertical (R[2,2] > 0.99)."""
  return mat[2, 2] > threshold


def xy_dist(a, b):
  return jnp.linalg.norm(a[:2] - b[:2])


def uniform_offset(key, half_range):
  """Uniform offset in [-x, x] x [-y, y] (DISCOVERSE's randomisation)."""
  h = jnp.asarray(half_range, jnp.float32)
  return jax.random.uniform(key, (2,), minval=-h, maxval=h)
