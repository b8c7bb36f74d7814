"""Router: one softmax over the K skills per predicted chunk."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


class Router(nn.Module):
  """r = softmax(MLP(mean over tokens of h)) -> [B, K], float32.

  The output layer starts at zero so every skill gets weight 1/K at first
  and no skill wins by initialisation; it is also what few-shot adaptation
  retrains, together with the action head. `temperature` divides the
  logits: below 1 the same logits give sharper weights (a remedy tried
  against routing that stays uniform; 1 is the paper's plain softmax).
  with_logits: return (probs, the logits the softmax reads), which the
  training diagnostics log. cue [B, C]: what only the router reads
  (`PlugConfig.router_cue_slots`), added to the pooled tokens.
  """
  num_skills: int
  hidden: int
  dtype: jnp.dtype = jnp.float32
  temperature: float = 1.0

  @nn.compact
  def __call__(self, h: jnp.ndarray, with_logits: bool = False, cue=None):
    x = h.astype(self.dtype).mean(axis=1)
    if cue is not None:
      x = x + nn.Dense(x.shape[-1], dtype=self.dtype, name="cue")(cue.astype(self.dtype))
    x = nn.relu(nn.Dense(self.hidden, dtype=self.dtype, name="fc1")(x))
    logits = nn.Dense(self.num_skills, dtype=jnp.float32, kernel_init=nn.initializers.zeros,
                      name="fc2")(x)
    if self.temperature != 1.0:
      logits = logits / self.temperature
    logits = logits.astype(jnp.float32)
    probs = jax.nn.softmax(logits, axis=-1)
    return (probs, logits) if with_logits else probs
