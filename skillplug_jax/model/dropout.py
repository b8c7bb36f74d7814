"""Dropout whose mask is a hash of each element's index, not a threefry draw.

`flax.linen.Dropout` draws its mask with `jax.random.bernoulli`, which runs
threefry2x32 (20 rounds) for every element. XLA:CPU does not vectorise it
well: on this project's 2-core CPU, dropout on 10.2M activations took 120
ms this way against 13 ms for only scaling them, and dropout cost 12% of
the paper-shape ACT train step (issue 14; docs/measurements/speed.md). Here threefry is run once per dropout site, for a 64-bit
seed; each element's keep bit is then a two-round integer hash of (its flat
index, the seed) compared with keep * 2**32, a dozen vector integer ops that
XLA fuses into the surrounding elementwise work (16 ms for the same dropout).

The hash is Wellons' "lowbias32" finaliser (a bijection on 32 bits with low
avalanche bias), applied to index ^ seed0 and again after adding seed1, so two
seeds do not give shifted copies of one stream. It is a mask generator for
regularisation, not a cryptographic or statistical-test-grade RNG; the tests
check the keep rate, independence between neighbouring elements and between
seeds, and that a key always gives the same mask.

Same interface and semantics as flax's module otherwise: rate = the dropped
fraction, kept elements scaled by 1 / (1 - rate), the 'dropout' rng,
`broadcast_dims` share one mask along those axes, rate 0 or deterministic is
the identity.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import lax


def _lowbias32(x):
  x = x ^ (x >> 16)
  x = x * jnp.uint32(0x7FEB352D)
  x = x ^ (x >> 15)
  x = x * jnp.uint32(0x846CA68B)
  return x ^ (x >> 16)


def keep_mask(key: jax.Array, keep_prob: float, shape: Sequence[int]) -> jax.Array:
  """bool[shape], each element True with probability keep_prob (to 2**-32)."""
  shape = tuple(shape)
  if keep_prob >= 1.0:
    return jnp.ones(shape, bool)
  seed = jax.random.bits(key, (2,), jnp.uint32)
  size = math.prod(shape)
  if size >= 2**32:
    raise ValueError(f"a dropout mask of {size} elements exceeds the 2**32 hash indices")
  index = lax.iota(jnp.uint32, size).reshape(shape)
  bits = _lowbias32(_lowbias32(index ^ seed[0]) + seed[1])
  return bits < jnp.uint32(min(int(round(keep_prob * 2.0**32)), 2**32 - 1))


def dropout(key: jax.Array, rate: float, x: jax.Array, broadcast_dims: Sequence[int] = ()) -> jax.Array:
  """x with a fraction `rate` of its elements zeroed and the rest scaled up."""
  if rate <= 0.0:
    return x
  if rate >= 1.0:
    return jnp.zeros_like(x)
  keep_prob = 1.0 - rate
  shared = {d % x.ndim for d in broadcast_dims}
  shape = [1 if d in shared else n for d, n in enumerate(x.shape)]
  keep = jnp.broadcast_to(keep_mask(key, keep_prob, shape), x.shape)
  return jnp.where(keep, x / jnp.asarray(keep_prob, x.dtype), jnp.zeros((), x.dtype))


class Dropout(nn.Module):
  """Drop-in for `flax.linen.Dropout` (rate, broadcast_dims, deterministic)."""
  rate: float
  broadcast_dims: Sequence[int] = ()
  deterministic: bool | None = None

  @nn.compact
  def __call__(self, x, deterministic: bool | None = None):
    deterministic = nn.merge_param("deterministic", self.deterministic, deterministic)
    if deterministic or self.rate <= 0.0:
      return x
    return dropout(self.make_rng("dropout"), self.rate, x, self.broadcast_dims)
