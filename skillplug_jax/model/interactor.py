"""Skill interactor: u_k = Interactor(h, s_k), one copy of the scene tokens per skill.

Every interactor maps scene tokens h [B, N, D] and (per-sample) skill vectors
s [B, K, D] to u [B, K, N, D], given the tokens' positions (None when they
are already in the contents: `ModelConfig.positions`). `Policy` picks one by
name from `INTERACTORS` (`PlugConfig.interactor`), so a new reading of the
paper's "cross-attention" is a new class here and one dictionary entry.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from skillplug_jax.model.attention import MultiHeadAttention
from skillplug_jax.model.dropout import Dropout
from skillplug_jax.model.transformer import FeedForward, with_pos


class QueryOffsetInteractor(nn.Module):
  """The scene tokens attend to themselves with queries offset by P s_k.

  DESIGN's reading of the paper: the skill shifts what every token looks for,
  so each skill gathers different scene content; a residual keeps h and a
  pre-normed FF block follows, as in a transformer layer. Positions go into
  the queries and keys, as in the encoder.
  """
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, h, skills, deterministic: bool = True, pos=None):
    h, skills = h.astype(self.dtype), skills.astype(self.dtype)
    hn = nn.LayerNorm(dtype=self.dtype, name="norm1")(h)[:, None]  # [B, 1, N, D]
    keys = with_pos(hn, pos)
    offset = nn.Dense(self.hidden, dtype=self.dtype, name="skill_proj")(skills)
    # queries keys + offset_k [B, K, N, D]; keys and values are the same for
    # every skill, so they are projected once and broadcast over k
    y = MultiHeadAttention(
        num_heads=self.heads, dropout_rate=self.dropout, dtype=self.dtype, name="attn")(
            keys, keys, hn, deterministic=deterministic, query_offset=offset[:, :, None, :])
    u = h[:, None] + Dropout(self.dropout)(y, deterministic=deterministic)
    y = nn.LayerNorm(dtype=self.dtype, name="norm2")(u)
    y = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")(y, deterministic)
    return u + Dropout(self.dropout)(y, deterministic=deterministic)


class SkillTokenInteractor(nn.Module):
  """Another reading of the paper's cross-attention (issue 27): the skill is a
  token the scene tokens attend to.

  Each scene token attends over [scene tokens; the skill's token], so keys
  and values see the skill and a skill can write content of its own into
  every token. Under query offsets (above) a skill can only reweight the
  scene's own values: with three state tokens, a mixture of three vectors.
  The skill token has no position; the rest is the query-offset layer
  (residual, pre-normed FF block).
  """
  hidden: int
  heads: int
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, h, skills, deterministic: bool = True, pos=None):
    h, skills = h.astype(self.dtype), skills.astype(self.dtype)
    hn = nn.LayerNorm(dtype=self.dtype, name="norm1")(h)[:, None]  # [B, 1, N, D]
    token = nn.Dense(self.hidden, dtype=self.dtype, name="skill_proj")(skills)
    token = nn.LayerNorm(dtype=self.dtype, name="skill_norm")(token)[:, :, None]  # [B, K, 1, D]
    scene = jnp.broadcast_to(hn, token.shape[:2] + hn.shape[2:])  # [B, K, N, D]
    keys = jnp.concatenate([with_pos(scene, pos), token], axis=2)
    values = jnp.concatenate([scene, token], axis=2)
    y = MultiHeadAttention(
        num_heads=self.heads, dropout_rate=self.dropout, dtype=self.dtype, name="attn")(
            with_pos(hn, pos), keys, values, deterministic=deterministic)
    u = h[:, None] + Dropout(self.dropout)(y, deterministic=deterministic)
    y = nn.LayerNorm(dtype=self.dtype, name="norm2")(u)
    y = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")(y, deterministic)
    return u + Dropout(self.dropout)(y, deterministic=deterministic)


class FiLMInteractor(nn.Module):
  """A cheaper alternative: the skill scales and shifts the normalised tokens
  (FiLM), then an FF block writes the result back onto h."""
  hidden: int
  heads: int  # unused; same constructor as every interactor
  ff: int
  dropout: float = 0.0
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, h, skills, deterministic: bool = True, pos=None):
    del pos  # token-wise: positions play no part
    h, skills = h.astype(self.dtype), skills.astype(self.dtype)
    gamma, beta = jnp.split(
        nn.Dense(2 * self.hidden, dtype=self.dtype, name="film")(skills), 2, axis=-1)
    hn = nn.LayerNorm(dtype=self.dtype, name="norm")(h)[:, None]
    y = hn * (1.0 + gamma[:, :, None]) + beta[:, :, None]
    y = FeedForward(self.hidden, self.ff, self.dropout, self.dtype, name="ff")(y, deterministic)
    return h[:, None] + Dropout(self.dropout)(y, deterministic=deterministic)


INTERACTORS = {"query_offset": QueryOffsetInteractor, "film": FiLMInteractor,
               "skill_tokens": SkillTokenInteractor}
