"""The skill library: K learnable embeddings s_k shared by every task."""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp


class SkillLibrary(nn.Module):
  """Returns the [K, dim] skill embeddings.

  Initialised N(0, 1) per entry (like an embedding table) so the K skills
  start distinct; a near-zero start would make every u_k alike and leave the
  disentanglement loss to break the symmetry alone.
  """
  num_skills: int
  dim: int

  @nn.compact
  def __call__(self) -> jnp.ndarray:
    return self.param("embeddings", nn.initializers.normal(stddev=1.0),
                      (self.num_skills, self.dim))
