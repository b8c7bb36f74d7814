"""Transformer layers shared by ACT's encoder, decoder and CVAE encoder.

Pre-norm (LayerNorm before each sublayer, one final LayerNorm after the
stack) rather than ACT's post-norm: it trains stably from scratch without
learning-rate warmup, which matters for the short CPU presets, and it leaves
the residual stream un-normalised so SkillPlug's interactor can add to it.
Positions are added to the tokens once at the input (ViT style), not to the
queries and keys of every layer as DETR/ACT do.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp
import numpy as np


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
    x = nn.Dropout(self.dropout)(x, deterministic=deterministic)
    return nn.Dense(self.hidden, dtype=self.dtype, name="fc2")(x)


def _attention(heads, dropout, dtype, name):
  return nn.MultiHeadDotProductAttention(
      num_heads=heads, dropout_rate=dropout, dtype=dtype, name=name)


class EncoderLayer(nn.Module):
  """Self-attention and FF, each pre-normed with a residual."""
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x, deterministic: bool, mask=None):
    y = nn.LayerNorm(dtype=self.dtype, name="norm1")(x)
    y = _attention(self.heads, self.dropout, self.dtype, "self_attn")(
        y, y, mask=mask, deterministic=deterministic)
    x = x + nn.Dropout(self.dropout)(y, deterministic=deterministic)
    y = nn.LayerNorm(dtype=self.dtype, name="norm2")(x)
    y = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")(y, deterministic)
    return x + nn.Dropout(self.dropout)(y, deterministic=deterministic)


class DecoderLayer(nn.Module):
  """Self-attention among the queries, cross-attention to the memory, FF."""
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x, memory, deterministic: bool):
    drop = lambda y: nn.Dropout(self.dropout)(y, deterministic=deterministic)
    y = nn.LayerNorm(dtype=self.dtype, name="norm1")(x)
    x = x + drop(_attention(self.heads, self.dropout, self.dtype, "self_attn")(
        y, y, deterministic=deterministic))
    y = nn.LayerNorm(dtype=self.dtype, name="norm2")(x)
    x = x + drop(_attention(self.heads, self.dropout, self.dtype, "cross_attn")(
        y, memory, deterministic=deterministic))
    y = nn.LayerNorm(dtype=self.dtype, name="norm3")(x)
    return x + drop(FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")(
        y, deterministic))


class TransformerEncoder(nn.Module):
  """A stack of `EncoderLayer`s and the final pre-norm LayerNorm."""
  layers: int
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x, deterministic: bool, mask=None):
    for i in range(self.layers):
      x = EncoderLayer(self.hidden, self.heads, self.ff, self.dropout, self.dtype,
                       name=f"layer{i + 1}")(x, deterministic, mask)
    return nn.LayerNorm(dtype=self.dtype, name="final_norm")(x)
