"""ResNet-18 image backbone, trained from scratch.

GroupNorm replaces BatchNorm: the backbone is trained from scratch on small
batches (16 in the paper) where batch statistics are noisy, and without a
mutable `batch_stats` collection `Policy.apply` stays a pure function of the
parameters, so train, evaluation and the jitted closed-loop rollout all share
one call signature and freezing is a parameter mask and nothing more.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax.numpy as jnp

STAGE_SIZES = (2, 2, 2, 2)  # ResNet-18


def _norm(channels: int, dtype, zero_scale: bool = False) -> nn.GroupNorm:
  # 32 groups as in Wu & He (2018), fewer when narrow test backbones need it.
  return nn.GroupNorm(
      num_groups=math.gcd(32, channels), dtype=dtype,
      scale_init=nn.initializers.zeros if zero_scale else nn.initializers.ones)


class BasicBlock(nn.Module):
  """Two 3x3 convs with a residual; the last norm starts at zero scale so
  each block begins as the identity (trains from scratch more reliably)."""
  channels: int
  strides: int = 1
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x):
    conv = lambda c, k, s, name: nn.Conv(
        c, (k, k), (s, s), padding="SAME" if k > 1 else "VALID", use_bias=False,
        dtype=self.dtype, name=name)
    y = conv(self.channels, 3, self.strides, "conv1")(x)
    y = nn.relu(_norm(self.channels, self.dtype)(y))
    y = conv(self.channels, 3, 1, "conv2")(y)
    y = _norm(self.channels, self.dtype, zero_scale=True)(y)
    if x.shape[-1] != self.channels or self.strides != 1:
      x = conv(self.channels, 1, self.strides, "shortcut")(x)
      x = _norm(self.channels, self.dtype)(x)
    return nn.relu(x + y)


class ResNet18(nn.Module):
  """uint8 images [B, H, W, 3] -> feature map [B, H/32, W/32, 8 * width]."""
  width: int = 64
  stage_sizes: Sequence[int] = STAGE_SIZES
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, images):
    # No pretrained weights, so no ImageNet statistics: scale to [-1, 1].
    x = images.astype(self.dtype) / 127.5 - 1.0
    x = nn.Conv(self.width, (7, 7), (2, 2), padding=[(3, 3), (3, 3)],
                use_bias=False, dtype=self.dtype, name="stem")(x)
    x = nn.relu(_norm(self.width, self.dtype)(x))
    x = nn.max_pool(x, (3, 3), (2, 2), padding="SAME")
    for i, n_blocks in enumerate(self.stage_sizes):
      for j in range(n_blocks):
        x = BasicBlock(self.width * 2**i, strides=2 if (i > 0 and j == 0) else 1,
                       dtype=self.dtype, name=f"stage{i + 1}_block{j + 1}")(x)
    return x
