"""Transformer layers shared by ACT's encoder, decoder and CVAE encoder.

Positions, when given (`pos`, broadcastable to the tokens), are added to the
attention queries and keys of every layer and never to the values, as in DETR
and ACT (`ModelConfig.positions='qk'`). The default wiring adds them to the
tokens once, before the first layer, and passes `pos=None` here (act.py says
why, with the measurements).

`pre_norm=True` (our default) puts a LayerNorm before each sublayer and one
after the stack: it trains stably from scratch and leaves the residual stream
un-normalised for SkillPlug's interactor to add to. `False` is ACT's
post-norm (LayerNorm after each residual add, none after an encoder stack).
Measured in closed loop, post-norm cost our quick ACT 38 points on
jujube_pick over 6 seeds (docs/measurements/act_parity.md).
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp
import numpy as np

from skillplug_jax.model.attention import MultiHeadAttention
from skillplug_jax.model.dropout import Dropout


def sinusoidal_1d(length: int, dim: int) -> np.ndarray:
  """Fixed [length, dim] position table (Vaswani et al.)."""
  pos = np.arange(length)[:, None]
  freq = np.exp(-np.log(10000.0) * np.arange(0, dim, 2) / dim)
  table = np.zeros((length, dim), np.float32)
  table[:, 0::2] = np.sin(pos * freq)
  table[:, 1::2] = np.cos(pos * freq)[:, : dim // 2]
  return table


def sinusoidal_2d(height: int, width: int, dim: int) -> np.ndarray:
  """Fixed [height * width, dim] table: half the channels encode the row,
  half the column (DETR's image position encoding), row-major order."""
  half = dim // 2
  rows = sinusoidal_1d(height, half)
  cols = sinusoidal_1d(width, dim - half)
  grid = np.concatenate([
      np.repeat(rows[:, None, :], width, axis=1),
      np.repeat(cols[None, :, :], height, axis=0)], axis=-1)
  return grid.reshape(height * width, dim)


class FeedForward(nn.Module):
  """Dense -> ReLU -> dropout -> Dense (ACT's FF block)."""
  hidden: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x, deterministic: bool):
    x = nn.relu(nn.Dense(self.ff, dtype=self.dtype, name="fc1")(x))
    x = Dropout(self.dropout)(x, deterministic=deterministic)
    return nn.Dense(self.hidden, dtype=self.dtype, name="fc2")(x)


def _attention(heads, dropout, dtype, name):
  return MultiHeadAttention(num_heads=heads, dropout_rate=dropout, dtype=dtype, name=name)


def with_pos(x, pos):
  return x if pos is None else x + pos.astype(x.dtype)


class EncoderLayer(nn.Module):
  """Self-attention and FF, each with a residual (pre- or post-normed).

  `outputs=n` computes only the first n tokens' outputs (every token is
  still a key and a value): what a stack's last layer needs when only its
  first token is read, as ACT's CVAE reads its CLS token.
  """
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32
  pre_norm: bool = True

  @nn.compact
  def __call__(self, x, deterministic: bool, mask=None, pos=None, outputs=None):
    drop = lambda y: Dropout(self.dropout)(y, deterministic=deterministic)
    norm1 = nn.LayerNorm(dtype=self.dtype, name="norm1")
    norm2 = nn.LayerNorm(dtype=self.dtype, name="norm2")
    attn = _attention(self.heads, self.dropout, self.dtype, "self_attn")
    ff = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")
    first = (lambda y: y) if outputs is None else (lambda y: y if y is None else y[:, :outputs])
    if self.pre_norm:
      y = norm1(x)
      x = first(x) + drop(attn(with_pos(first(y), first(pos)), with_pos(y, pos), y, mask=mask,
                               deterministic=deterministic))
      return x + drop(ff(norm2(x), deterministic))
    x = norm1(first(x) + drop(attn(with_pos(first(x), first(pos)), with_pos(x, pos), x, mask=mask,
                                   deterministic=deterministic)))
    return norm2(x + drop(ff(x, deterministic)))


class DecoderLayer(nn.Module):
  """Self-attention among the queries, cross-attention to the memory, FF.

  query_pos goes into the queries' queries and keys, memory_pos into the
  memory's keys (DETR's decoder layer).
  """
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32
  pre_norm: bool = True

  @nn.compact
  def __call__(self, x, memory, deterministic: bool, query_pos=None, memory_pos=None):
    drop = lambda y: Dropout(self.dropout)(y, deterministic=deterministic)
    norms = [nn.LayerNorm(dtype=self.dtype, name=f"norm{i}") for i in (1, 2, 3)]
    self_attn = _attention(self.heads, self.dropout, self.dtype, "self_attn")
    cross_attn = _attention(self.heads, self.dropout, self.dtype, "cross_attn")
    ff = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")
    keys = with_pos(memory, memory_pos)
    if self.pre_norm:
      y = norms[0](x)
      x = x + drop(self_attn(with_pos(y, query_pos), with_pos(y, query_pos), y,
                             deterministic=deterministic))
      y = norms[1](x)
      x = x + drop(cross_attn(with_pos(y, query_pos), keys, memory, deterministic=deterministic))
      return x + drop(ff(norms[2](x), deterministic))
    x = norms[0](x + drop(self_attn(with_pos(x, query_pos), with_pos(x, query_pos), x,
                                    deterministic=deterministic)))
    x = norms[1](x + drop(cross_attn(with_pos(x, query_pos), keys, memory,
                                     deterministic=deterministic)))
    return norms[2](x + drop(ff(x, deterministic)))


class TransformerEncoder(nn.Module):
  """A stack of `EncoderLayer`s; pre-norm ends with one more LayerNorm.

  `outputs=n`: return only the first n tokens, and let the last layer
  compute only those (the same values; less work).
  """
  layers: int
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32
  pre_norm: bool = True

  @nn.compact
  def __call__(self, x, deterministic: bool, mask=None, pos=None, outputs=None):
    for i in range(self.layers):
      last = i == self.layers - 1
      x = EncoderLayer(self.hidden, self.heads, self.ff, self.dropout, self.dtype, self.pre_norm,
                       name=f"layer{i + 1}")(x, deterministic, mask, pos, outputs if last else None)
    if outputs is not None and self.layers == 0:
      x = x[:, :outputs]
    return nn.LayerNorm(dtype=self.dtype, name="final_norm")(x) if self.pre_norm else x
