"""The training objective: each term a pure function, then their weighted sum.

  total = rec + kl * L_KL + bsa * L_BSA + sd * L_SD + cvae_kl * ACT's CVAE KL
  (policy 'act': rec + cvae_kl * ACT's CVAE KL only)

Reductions, fixed here so the weights mean the same thing in every run:
  - L_rec: mean |pred - target| over the valid (unpadded) steps and all
    action dimensions. ACT zeroes padded steps but divides by every entry,
    which makes the loss scale depend on how much of the batch is padding; we
    divide by the number of valid entries instead.
  - KL terms: summed over latent dimensions (a KL of the whole latent, as
    ACT does), averaged over the batch and, for the skill posterior, over k.
  - L_BSA: cross-entropy summed over k, averaged over the batch.
  - L_SD: mean of the K(K-1) off-diagonal cosine similarities, averaged over
    the batch.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import jax
import jax.numpy as jnp


def reconstruction_l1(pred: jnp.ndarray, target: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
  """Mean L1 over valid steps. pred, target [B, T, A]; mask [B, T], True = real step."""
  valid = mask.astype(jnp.float32)[..., None]
  abs_err = jnp.abs(pred.astype(jnp.float32) - target.astype(jnp.float32)) * valid
  count = jnp.maximum(valid.sum() * pred.shape[-1], 1.0)
  return abs_err.sum() / count


def kl_standard_normal(mu: jnp.ndarray, logvar: jnp.ndarray) -> jnp.ndarray:
  """KL(N(mu, exp(logvar)) || N(0, I)): summed over the last (latent) axis,
  averaged over every leading axis ([B] for ACT's CVAE, [B, K] for the skills)."""
  mu, logvar = mu.astype(jnp.float32), logvar.astype(jnp.float32)
  kl = -0.5 * jnp.sum(1.0 + logvar - mu**2 - jnp.exp(logvar), axis=-1)
  return kl.mean()


def behaviour_skill_alignment(router_probs: jnp.ndarray, traj_logits: jnp.ndarray) -> jnp.ndarray:
  """-sum_k sg(r_k) log softmax_k(traj_logits), averaged over the batch.

  The router's weights are a fixed soft target: stop_gradient keeps the router
  trained by reconstruction alone, as the paper prescribes.
  """
  target = jax.lax.stop_gradient(router_probs.astype(jnp.float32))
  log_q = jax.nn.log_softmax(traj_logits.astype(jnp.float32), axis=-1)
  return -(target * log_q).sum(axis=-1).mean()


def skill_diversity(skill_features: jnp.ndarray) -> jnp.ndarray:
  """Mean off-diagonal cosine similarity of the K token-averaged u_k.

  skill_features [B, K, D]. 0 for mutually orthogonal features, 1 when all K
  are identical (down to -1/(K-1) at best).
  """
  u = skill_features.astype(jnp.float32)
  num_skills = u.shape[-2]
  if num_skills < 2:
    return jnp.zeros((), jnp.float32)
  u = u / jnp.maximum(jnp.linalg.norm(u, axis=-1, keepdims=True), 1e-8)
  sim = jnp.einsum("...kd,...jd->...kj", u, u)
  off_diagonal = sim.sum(axis=(-2, -1)) - jnp.trace(sim, axis1=-2, axis2=-1)
  return (off_diagonal / (num_skills * (num_skills - 1))).mean()


@dataclasses.dataclass(frozen=True)
class LossWeights:
  """Loss weights. The paper gives no lambdas: these are placeholders for the
  sweep, chosen by the scale of each term against L_rec (a mean L1 on
  normalised actions: ~0.5 at the start, a few 0.01 once trained).

  Sweep (recorded in docs/results/sweep_loss_weights_quick_cpu.json; `python -m
  experiments.sweep_loss_weights`): quick preset, discoverse7 state-only, 1500
  steps, one seed, criterion the held-out L1 of the inference path on 21
  unseen-start demonstrations. default 0.154; kl 0.1 / 10: 0.154 / 0.158;
  bsa 0.01 / 1: 0.146 / 0.159; sd 0.01 / 1: 0.145 / 0.173; bsa = sd = 0.01
  together: 0.152. Run-to-run noise is about +-0.005, so only the large
  values (sd 1, and marginally kl 10, bsa 1) are worse; the defaults below
  stay until a closed-loop sweep (success rates) can separate the rest.

  cvae_kl=10: ACT's value for its style latent.
  kl=1: z_k is, like ACT's latent, a path from the demonstrated actions into
    the decoder that is closed at inference (z = 0), so it must be priced
    near ACT's weight or the policy learns to lean on it; one decade below
    ACT's because it enters only through the router's convex mixture and is
    meant as a bottleneck, not to be forced to the prior. Sweep {0.1, 1, 10}.
  bsa=0.1: a cross-entropy over K=4 starts near log 4 = 1.4; at 0.1 it stays
    the size of the late reconstruction loss and shapes the skills without
    dominating them. Sweep {0.01, 0.1, 1}.
  sd=0.1: the similarity lies in [-1/(K-1), 1], so at 0.1 it can add at most
    0.1, again comparable to a trained L_rec. Sweep {0.01, 0.1, 1}.
  """
  rec: float = 1.0
  kl: float = 1.0
  bsa: float = 0.1
  sd: float = 0.1
  cvae_kl: float = 10.0


def total_loss(outputs: Mapping[str, jnp.ndarray], batch: Mapping[str, jnp.ndarray],
               weights: LossWeights = LossWeights()) -> tuple[jnp.ndarray, dict]:
  """Weighted sum of the terms `Policy.__call__`'s outputs allow.

  SkillPlug outputs (they carry 'router_probs') get all five terms; ACT's
  get rec and cvae_kl. Returns (loss, metrics) with every unweighted term
  and the total under 'loss'.
  """
  metrics = {
      "rec": reconstruction_l1(outputs["pred_actions"], batch["actions"], batch["action_mask"]),
      "cvae_kl": kl_standard_normal(outputs["cvae_mu"], outputs["cvae_logvar"]),
  }
  loss = weights.rec * metrics["rec"] + weights.cvae_kl * metrics["cvae_kl"]
  if "router_probs" in outputs:
    metrics["kl"] = kl_standard_normal(outputs["posterior_mu"], outputs["posterior_logvar"])
    metrics["bsa"] = behaviour_skill_alignment(outputs["router_probs"], outputs["traj_logits"])
    metrics["sd"] = skill_diversity(outputs["skill_features"])
    loss = loss + (weights.kl * metrics["kl"] + weights.bsa * metrics["bsa"]
                   + weights.sd * metrics["sd"])
  metrics["loss"] = loss
  return loss, metrics
