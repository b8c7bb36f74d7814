"""Multi-head attention with flax's parameters, laid out for XLA:CPU.

Same parameters as `flax.linen.MultiHeadDotProductAttention` (query, key,
value: kernel [D, heads, D/heads] and bias [heads, D/heads]; out: kernel
[heads, D/heads, D] and bias [D]; the same initialisers), the same
arithmetic (queries scaled by 1/sqrt(D/heads), masked logits at the float
minimum, softmax, dropout on the weights shared across the batch and the
heads), so runs and checkpoints written with flax's module load unchanged.

What differs is the layout. Each projection is one 2-D product with the
kernel seen as [D, D] (a free reshape), and the heads are moved next to the
batch once, before the two attention products, as torch's attention does.
flax contracts the 3-D kernels with einsums, for which XLA:CPU transposes
and copies every kernel and every head-major gradient again in each step.
Measured on this project's 2-core CPU (issue 14, paper shapes, ACT): those
copies took about 130 ms of the step's thread time.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from skillplug_jax.model.dropout import keep_mask

_kernel_init = nn.initializers.lecun_normal()


class _HeadsProjection(nn.Module):
  """x [..., D_in] -> [..., heads, head_dim] with a [D_in, heads, head_dim] kernel."""
  heads: int
  head_dim: int
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x, offset=None):
    """offset (broadcastable to x): project x + offset, as x's projection plus
    the offset's, so a small offset need not be added to a large x first."""
    d_in, width = x.shape[-1], self.heads * self.head_dim
    # initialised flat, as flax's DenseGeneral does: fan-in d_in
    kernel = self.param("kernel", lambda k, s: _kernel_init(k, (d_in, width)).reshape(s),
                        (d_in, self.heads, self.head_dim))
    bias = self.param("bias", nn.initializers.zeros, (self.heads, self.head_dim))
    x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
    kernel = kernel.reshape(d_in, width)
    y = x @ kernel + bias.reshape(width)
    if offset is not None:
      y = y + offset.astype(self.dtype) @ kernel
    return y.reshape(*y.shape[:-1], self.heads, self.head_dim)


class _OutProjection(nn.Module):
  """[..., heads, head_dim] -> [..., D] with a [heads, head_dim, D] kernel."""
  features: int
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x):
    heads, head_dim = x.shape[-2:]
    width = heads * head_dim
    kernel = self.param("kernel", lambda k, s: _kernel_init(k, (width, self.features)).reshape(s),
                        (heads, head_dim, self.features))
    bias = self.param("bias", nn.initializers.zeros, (self.features,))
    x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
    return x.reshape(*x.shape[:-2], width) @ kernel.reshape(width, self.features) + bias


class MultiHeadAttention(nn.Module):
  """attn(inputs_q [..., Tq, D], inputs_k [..., Tk, D], inputs_v [..., Tk, D],
  mask broadcastable to [..., heads, Tq, Tk] (True = attend)) -> [..., Tq, D].

  The leading axes broadcast against each other, so keys and values shared
  by several query sets are projected once. `query_offset` (broadcastable to
  inputs_q) is added to the queries' inputs.

  Dropout on the attention weights uses the 'dropout' rng, one mask per
  (query, key) pair shared by the batch and the heads (flax's default).
  """
  num_heads: int
  dropout_rate: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, inputs_q, inputs_k, inputs_v, mask=None, deterministic: bool = True,
               query_offset=None):
    features = inputs_q.shape[-1]
    if features % self.num_heads:
      raise ValueError(f"width {features} is not divisible by {self.num_heads} heads")
    head_dim = features // self.num_heads
    proj = lambda name: _HeadsProjection(self.num_heads, head_dim, self.dtype, name=name)
    # [..., T, H, d] -> [..., H, T, d]: the heads become a batch axis of both products
    heads_first = lambda y: jnp.swapaxes(y, -3, -2)
    q = heads_first(proj("query")(inputs_q, query_offset)) / jnp.sqrt(head_dim).astype(self.dtype)
    k = heads_first(proj("key")(inputs_k))
    v = heads_first(proj("value")(inputs_v))
    logits = q @ jnp.swapaxes(k, -1, -2)  # [..., H, Tq, Tk]
    if mask is not None:
      logits = jnp.where(mask, logits, jnp.finfo(logits.dtype).min)
    weights = jax.nn.softmax(logits).astype(self.dtype)
    if not deterministic and self.dropout_rate > 0.0:
      keep_prob = 1.0 - self.dropout_rate
      keep = keep_mask(self.make_rng("dropout"), keep_prob, weights.shape[-2:])
      weights = weights * (keep.astype(self.dtype) / jnp.asarray(keep_prob, self.dtype))
    y = jnp.swapaxes(weights @ v, -3, -2)  # [..., Tq, H, d]
    return _OutProjection(features, self.dtype, name="out")(y)
