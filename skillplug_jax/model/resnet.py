"""ResNet-18 image backbone, trained from scratch.

GroupNorm replaces BatchNorm: the backbone is trained from scratch on small
batches (16 in the paper) where batch statistics are noisy, and without a
mutable `batch_stats` collection `Policy.apply` stays a pure function of the
parameters, so train, evaluation and the jitted closed-loop rollout all share
one call signature and freezing is a parameter mask and nothing more.

Convolutions whose output map is small (at most 4x4 cells: the last two
stages at 64x64 images) run as one matrix product over their patches
(`patch_conv`), not as XLA:CPU's convolution. Measured on this project's
2-core CPU (issue 14), batch 32: the 3x3 512->512 convolution on a 2x2 map
took 366 ms forward and 569 ms with its gradient as a convolution, 4.5 and
13 ms as a product; ResNet-18's forward and backward on a paper batch (32
images of 64x64) went from 2.0 s to 0.34 s. The parameters and the
arithmetic are the same (same kernel, same sums, in another order); larger
maps keep the convolution, which is as fast or faster there.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax.numpy as jnp
from jax import lax

STAGE_SIZES = (2, 2, 2, 2)  # ResNet-18
PATCH_CONV_MAX_CELLS = 16  # output maps of at most this many cells use patch_conv


def patch_conv(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
               dimension_numbers=None, feature_group_count=1, precision=None):
  """`lax.conv_general_dilated` for NHWC inputs and HWIO kernels (what nn.Conv
  passes), as one dot of the flattened patches with the flattened kernel when
  the output map is small; the convolution itself otherwise."""
  kh, kw, cin, cout = rhs.shape
  if isinstance(padding, str):
    padding = lax.padtype_to_pads(lhs.shape[1:3], (kh, kw), window_strides, padding)
  (sh, sw), (ph, pw) = window_strides, padding
  oh = (lhs.shape[1] + sum(ph) - kh) // sh + 1
  ow = (lhs.shape[2] + sum(pw) - kw) // sw + 1
  dilated = any(d != 1 for d in tuple(lhs_dilation or ()) + tuple(rhs_dilation or ()))
  nhwc = dimension_numbers is not None and lax.conv_dimension_numbers(
      lhs.shape, rhs.shape, dimension_numbers) == lax.conv_dimension_numbers(
          lhs.shape, rhs.shape, ("NHWC", "HWIO", "NHWC"))
  if oh * ow > PATCH_CONV_MAX_CELLS or dilated or feature_group_count != 1 or not nhwc:
    return lax.conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                                    dimension_numbers, feature_group_count, precision=precision)
  x = jnp.pad(lhs, ((0, 0), tuple(ph), tuple(pw), (0, 0)))
  patches = [x[:, i:i + sh * (oh - 1) + 1:sh, j:j + sw * (ow - 1) + 1:sw]
             for i in range(kh) for j in range(kw)]
  patches = jnp.concatenate(patches, axis=-1)  # [B, oh, ow, kh * kw * cin], kernel order
  return jnp.dot(patches, rhs.reshape(kh * kw * cin, cout), precision=precision)


def max_pool(x, window: int = 3, stride: int = 2):
  """`nn.max_pool(x, (window,) * 2, (stride,) * 2, padding='SAME')` for NHWC x,
  as the maximum of window**2 strided slices.

  The values are the same. The gradient differs only where two cells of a
  window tie (jnp.maximum splits it, reduce_window gives it to one); the
  stem's input is a ReLU output, whose ties are at 0, where the ReLU passes
  no gradient anyway. XLA:CPU lowers reduce_window's gradient through
  int32 index maps of the whole padded map (5 ops, about 35 ms of a paper
  step's thread time, issue 14); the slices' gradient is elementwise.
  """
  (ph, pw) = lax.padtype_to_pads(x.shape[1:3], (window, window), (stride, stride), "SAME")
  oh = (x.shape[1] + sum(ph) - window) // stride + 1
  ow = (x.shape[2] + sum(pw) - window) // stride + 1
  x = jnp.pad(x, ((0, 0), tuple(ph), tuple(pw), (0, 0)), constant_values=-jnp.inf)
  out = None
  for i in range(window):
    for j in range(window):
      cell = x[:, i:i + stride * (oh - 1) + 1:stride, j:j + stride * (ow - 1) + 1:stride]
      out = cell if out is None else jnp.maximum(out, cell)
  return out


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
        dtype=self.dtype, conv_general_dilated=patch_conv, name=name)
    y = conv(self.channels, 3, self.strides, "conv1")(x)
    y = nn.relu(_norm(self.channels, self.dtype)(y))
    y = conv(self.channels, 3, 1, "conv2")(y)
    y = _norm(self.channels, self.dtype, zero_scale=True)(y)
    if x.shape[-1] != self.channels or self.strides != 1:
      x = conv(self.channels, 1, self.strides, "shortcut")(x)
      x = _norm(self.channels, self.dtype)(x)
    return nn.relu(x + y)


class ResNet18(nn.Module):
  """uint8 images [B, H, W, 3] -> feature map [B, H/2^(n+1), W/2^(n+1), 2^(n-1) * width]
  for n stages (ResNet-18 with the default four: H/32, 8 * width)."""
  width: int = 64
  stage_sizes: Sequence[int] = STAGE_SIZES
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, images):
    # No pretrained weights, so no ImageNet statistics: scale to [-1, 1].
    x = images.astype(self.dtype) / 127.5 - 1.0
    x = nn.Conv(self.width, (7, 7), (2, 2), padding=[(3, 3), (3, 3)],
                use_bias=False, dtype=self.dtype, conv_general_dilated=patch_conv, name="stem")(x)
    x = nn.relu(_norm(self.width, self.dtype)(x))
    x = max_pool(x, 3, 2)
    for i, n_blocks in enumerate(self.stage_sizes):
      for j in range(n_blocks):
        x = BasicBlock(self.width * 2**i, strides=2 if (i > 0 and j == 0) else 1,
                       dtype=self.dtype, name=f"stage{i + 1}_block{j + 1}")(x)
    return x
