"""Trajectory-skill posterior (training only) and the BSA projection heads.

From the demonstrated action chunk alone (never the observation):
  f_tau = MLP(masked, flattened, normalised chunk)
  q(z_k | f_tau, s_k) = N(mu_k, diag exp(logvar_k)) from an MLP of [f_tau, s_k]
  offset_k = W z_k (no bias: z = 0, the prior mean, gives back s_k exactly,
             which is what the interactor receives at inference)
  traj_logits_k = g_tau(f_tau) . g_s(s_k)   (the BSA scores)
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


def reparameterise(rng, mu, logvar):
  """A sample of N(mu, exp(logvar)) differentiable in mu and logvar."""
  return mu + jnp.exp(0.5 * logvar) * jax.random.normal(rng, mu.shape, mu.dtype)


class TrajectorySkillPosterior(nn.Module):
  """Returns a dict: f_tau [B, D], mu/logvar [B, K, z], offset [B, K, D],
  traj_logits [B, K]. With `sample`, z is drawn using the 'sample' rng;
  without, z = mu (deterministic validation)."""
  hidden: int
  latent_dim: int
  alignment_dim: int

  @nn.compact
  def __call__(self, actions, action_mask, skills, sample: bool = False):
    batch = actions.shape[0]
    num_skills = skills.shape[0]
    mask = action_mask.astype(jnp.float32)
    # Padded steps are zeroed, and the mask itself is an input so the MLP
    # can tell "episode ended" from "action at the normalised mean".
    x = jnp.concatenate([(actions * mask[..., None]).reshape(batch, -1), mask], axis=-1)
    x = nn.relu(nn.Dense(self.hidden, name="traj_fc1")(x))
    f_tau = nn.Dense(self.hidden, name="traj_fc2")(x)

    pair = jnp.concatenate([
        jnp.broadcast_to(f_tau[:, None], (batch, num_skills, self.hidden)),
        jnp.broadcast_to(skills[None].astype(jnp.float32), (batch, num_skills, skills.shape[1]))],
        axis=-1)
    y = nn.relu(nn.Dense(self.hidden, name="q_fc1")(pair))
    # zero-initialised, as ACT's CVAE head here: q starts at the prior N(0, I)
    stats = nn.Dense(2 * self.latent_dim, kernel_init=nn.initializers.zeros, name="q_fc2")(y)
    mu, logvar = jnp.split(stats, 2, axis=-1)
    z = reparameterise(self.make_rng("sample"), mu, logvar) if sample else mu
    offset = nn.Dense(skills.shape[1], use_bias=False, name="lift")(z)  # W

    v_tau = nn.Dense(self.alignment_dim, name="g_tau")(f_tau)
    v_skill = nn.Dense(self.alignment_dim, name="g_s")(skills.astype(jnp.float32))
    traj_logits = v_tau @ v_skill.T
    return dict(f_tau=f_tau, mu=mu, logvar=logvar, offset=offset, traj_logits=traj_logits)
