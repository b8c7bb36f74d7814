"""The hashed dropout mask (issue 14) behaves as flax's Dropout does.

It replaces threefry-per-element with an index hash, so what must hold is
what training relies on: the keep rate, the 1/keep scaling, masks that are
fixed by the key and unrelated between neighbouring elements and between
keys (not shifted copies of one stream), and the module's interface.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from skillplug_jax.model.dropout import Dropout, dropout, keep_mask


def _corr(a, b):
  a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
  return float(np.corrcoef(a, b)[0, 1])


@pytest.mark.parametrize("keep", [0.9, 0.5, 0.02])
def test_keep_rate_matches_the_probability(keep):
  mask = np.asarray(keep_mask(jax.random.key(0), keep, (1000, 1000)))
  sd = np.sqrt(keep * (1 - keep) / mask.size)
  assert abs(mask.mean() - keep) < 6 * sd
  # every row and every column keeps about the same share: no structure along an axis
  assert np.abs(mask.mean(0) - keep).max() < 6 * np.sqrt(keep * (1 - keep) / 1000)
  assert np.abs(mask.mean(1) - keep).max() < 6 * np.sqrt(keep * (1 - keep) / 1000)


def test_masks_are_fixed_by_the_key_and_unrelated_otherwise():
  k1, k2 = jax.random.key(1), jax.random.key(2)
  m1 = np.asarray(keep_mask(k1, 0.5, (2000, 500)))
  np.testing.assert_array_equal(m1, np.asarray(keep_mask(k1, 0.5, (2000, 500))))
  m2 = np.asarray(keep_mask(k2, 0.5, (2000, 500)))
  flat1, flat2 = m1.ravel(), m2.ravel()
  bound = 6 / np.sqrt(flat1.size)  # 6 standard errors of a correlation of independent bits
  assert abs(_corr(flat1, flat2)) < bound
  for shift in (1, 2, 500, 4096):
    # neighbours within one mask, and the other key's stream shifted: both unrelated
    assert abs(_corr(flat1[shift:], flat1[:-shift])) < bound
    assert abs(_corr(flat1[shift:], flat2[:-shift])) < bound
    assert abs(_corr(flat2[shift:], flat1[:-shift])) < bound
  # keys split from one another (as flax derives each layer's) differ as much
  a, b = jax.random.split(jax.random.key(3))
  assert abs(_corr(keep_mask(a, 0.5, (1000, 1000)), keep_mask(b, 0.5, (1000, 1000)))) < 6e-3


def test_dropout_scales_the_kept_and_zeroes_the_rest():
  x = jax.random.normal(jax.random.key(0), (64, 256)) + 3.0
  y = np.asarray(dropout(jax.random.key(5), 0.25, x))
  kept = y != 0
  np.testing.assert_allclose(y[kept], np.asarray(x)[kept] / 0.75, rtol=1e-6)
  assert abs(kept.mean() - 0.75) < 0.02
  np.testing.assert_array_equal(np.asarray(dropout(jax.random.key(5), 0.0, x)), np.asarray(x))
  assert not np.asarray(dropout(jax.random.key(5), 1.0, x)).any()
  # gradients flow through the kept elements only, with the same scale
  g = np.asarray(jax.grad(lambda v: jnp.sum(dropout(jax.random.key(5), 0.25, v)))(x))
  np.testing.assert_allclose(g, kept / 0.75, rtol=1e-6)


def test_module_matches_flax_dropout_interface():
  x = jnp.ones((4, 6, 8))
  for module in (Dropout(0.5), nn.Dropout(0.5)):
    assert module.init({"params": jax.random.key(0)}, x, deterministic=True) == {}
    np.testing.assert_array_equal(module.apply({}, x, deterministic=True), x)
  y = np.asarray(Dropout(0.5, broadcast_dims=(1,)).apply({}, x, deterministic=False,
                                                         rngs={"dropout": jax.random.key(1)}))
  assert (y == y[:, :1]).all()  # one mask shared along axis 1
  assert 0 < (y != 0).mean() < 1
  with pytest.raises(Exception):  # a training pass needs the 'dropout' rng, as in flax
    Dropout(0.5).apply({}, x, deterministic=False)
