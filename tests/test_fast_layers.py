"""The layers rewritten for speed (issue 14) compute what they replace.

Each is compared, values and gradients, with the library computation it
stands for: `patch_conv` with `lax.conv_general_dilated`, `max_pool` with
flax's, our attention with flax's `MultiHeadDotProductAttention` on the same
parameters, the CVAE's CLS-only last layer with the full stack, and the
interactor's shared keys with keys broadcast over the skills.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from skillplug_jax.model import resnet
from skillplug_jax.model.attention import MultiHeadAttention
from skillplug_jax.model.resnet import ResNet18, max_pool, patch_conv
from skillplug_jax.model.transformer import TransformerEncoder

DN = ("NHWC", "HWIO", "NHWC")


def _close(a, b, tol=1e-5):
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=tol, atol=tol * max(1.0, float(np.abs(y).max())))


@pytest.mark.parametrize("hw,cin,cout,k,stride,padding", [
    (4, 8, 16, 3, 1, "SAME"),  # 4x4 output: a product
    (4, 8, 16, 3, 2, "SAME"),  # 2x2, strided
    (2, 16, 16, 3, 1, "SAME"),  # the last stage's shape at 64x64 images
    (4, 8, 16, 1, 2, "VALID"),  # the 1x1 shortcut
    (7, 3, 8, 7, 2, [(3, 3), (3, 3)]),  # the stem's padding, 4x4 output
    (16, 4, 8, 3, 1, "SAME"),  # 16x16 output: stays a convolution
])
def test_patch_conv_equals_the_convolution(hw, cin, cout, k, stride, padding):
  kx, kw = jax.random.split(jax.random.key(0))
  x = jax.random.normal(kx, (2, hw, hw, cin))
  w = jax.random.normal(kw, (k, k, cin, cout))
  ref = lambda x, w: lax.conv_general_dilated(x, w, (stride, stride), padding, dimension_numbers=DN)
  ours = lambda x, w: patch_conv(x, w, (stride, stride), padding,
                                 dimension_numbers=lax.conv_dimension_numbers(x.shape, w.shape, DN))
  _close(ours(x, w), ref(x, w))
  loss = lambda f: lambda x, w: jnp.sum(jnp.sin(f(x, w)))
  _close(jax.grad(loss(ours), argnums=(0, 1))(x, w), jax.grad(loss(ref), argnums=(0, 1))(x, w), 1e-4)
  # small output maps really are one product, larger ones stay a convolution
  out_cells = ref(x, w).shape[1] * ref(x, w).shape[2]
  uses_conv = "conv_general_dilated" in str(jax.make_jaxpr(ours)(x, w))
  assert uses_conv == (out_cells > resnet.PATCH_CONV_MAX_CELLS)


def test_resnet_with_patch_conv_equals_plain_convolutions(monkeypatch):
  images = jax.random.randint(jax.random.key(1), (2, 64, 64, 3), 0, 256).astype(jnp.uint8)
  net = ResNet18(width=8)
  params = net.init(jax.random.key(0), images)
  # traced afresh on each call: the threshold is read while tracing
  value_and_grad = lambda: jax.jit(jax.value_and_grad(lambda p: jnp.sum(net.apply(p, images) ** 2)))(params)
  ours = value_and_grad()
  monkeypatch.setattr(resnet, "PATCH_CONV_MAX_CELLS", 0)  # every layer a convolution
  _close(ours, value_and_grad(), 1e-3)


@pytest.mark.parametrize("hw", [(32, 32), (7, 9), (2, 2)])
def test_max_pool_equals_flax_max_pool(hw):
  x = jax.random.normal(jax.random.key(0), (3, *hw, 5))  # continuous: no ties
  ref = lambda v: nn.max_pool(v, (3, 3), (2, 2), padding="SAME")
  _close(max_pool(x, 3, 2), ref(x), 0)
  loss = lambda pool: lambda v: jnp.sum(jnp.sin(pool(v)))
  _close(jax.grad(loss(lambda v: max_pool(v, 3, 2)))(x), jax.grad(loss(ref))(x), 1e-6)


@pytest.mark.parametrize("q_shape,kv_shape", [((3, 5, 32), (3, 7, 32)), ((2, 3, 6, 32), (2, 3, 6, 32))])
def test_attention_equals_flax_attention(q_shape, kv_shape):
  kq, kk, km = jax.random.split(jax.random.key(0), 3)
  q, kv = jax.random.normal(kq, q_shape), jax.random.normal(kk, kv_shape)
  mask = jax.random.bernoulli(km, 0.6, kv_shape[:-2] + (1, 1, kv_shape[-2])).at[..., 0].set(True)
  ref, ours = nn.MultiHeadDotProductAttention(num_heads=4), MultiHeadAttention(num_heads=4)
  p_ref = ref.init(jax.random.key(3), q, kv, kv, mask=mask)
  p_ours = ours.init(jax.random.key(3), q, kv, kv, mask=mask)
  # the same parameter tree and initial values: checkpoints from before load unchanged
  assert jax.tree.structure(p_ref) == jax.tree.structure(p_ours)
  _close(p_ours, p_ref, 0)
  _close(ours.apply(p_ref, q, kv, kv, mask=mask), ref.apply(p_ref, q, kv, kv, mask=mask))
  loss = lambda m: lambda p: jnp.sum(m.apply(p, q, kv, kv, mask=mask) ** 2)
  _close(jax.grad(loss(ours))(p_ref), jax.grad(loss(ref))(p_ref), 1e-4)
  # dropout on the weights: a training pass differs from the deterministic one
  drop = MultiHeadAttention(num_heads=4, dropout_rate=0.5)
  train = drop.apply(p_ref, q, kv, kv, mask=mask, deterministic=False, rngs={"dropout": jax.random.key(4)})
  assert not np.allclose(train, ours.apply(p_ref, q, kv, kv, mask=mask))


def test_shared_keys_and_query_offset_equal_broadcast_inputs():
  kh, ko = jax.random.split(jax.random.key(0))
  h = jax.random.normal(kh, (2, 1, 5, 32))  # [B, 1, N, D]: one copy of the tokens
  offset = jax.random.normal(ko, (2, 3, 1, 32))  # [B, K, 1, D]: one offset per skill
  attn = MultiHeadAttention(num_heads=4)
  params = attn.init(jax.random.key(1), h, h, h)
  shared = attn.apply(params, h, h, h, query_offset=offset)
  full = jnp.broadcast_to(h, (2, 3, 5, 32))
  assert shared.shape == (2, 3, 5, 32)
  _close(shared, attn.apply(params, full + offset, full, full))


@pytest.mark.parametrize("pre_norm", [True, False])
@pytest.mark.parametrize("with_pos", [False, True])
def test_cls_only_last_layer_equals_the_full_stack(pre_norm, with_pos):
  kx, kp, km = jax.random.split(jax.random.key(0), 3)
  x = jax.random.normal(kx, (3, 9, 32))
  pos = jax.random.normal(kp, (1, 9, 32)) if with_pos else None
  mask = jax.random.bernoulli(km, 0.7, (3, 1, 1, 9)).at[..., :2].set(True)
  enc = TransformerEncoder(layers=2, hidden=32, heads=4, ff=64, pre_norm=pre_norm)
  params = enc.init(jax.random.key(1), x, True, mask, pos)
  full = enc.apply(params, x, True, mask, pos)
  first = enc.apply(params, x, True, mask, pos, outputs=1)
  assert first.shape == (3, 1, 32)
  _close(first, full[:, :1])
  loss = lambda n: lambda p: jnp.sum(enc.apply(p, x, True, mask, pos, outputs=n)[:, 0] ** 2)
  _close(jax.grad(loss(1))(params), jax.grad(loss(None))(params), 1e-4)
