"""The training objective: each term a pure function, then their weighted sum.

  total = rec + kl * L_KL + bsa * L_BSA + sd * L_SD + cvae_kl * ACT's CVAE KL
          (+ usage, load_balance, router_z, distill: ours, zero by default;
           + router_label: the router supervised with a label: the toy's primitive (an oracle)
             or one mined from the demonstrations, data/segments.py)
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

Beyond the paper (issue 27; `LossWeights` says which is which). The paper's
L_SD, a mean signed cosine, equals (|sum_k u_k/|u_k||^2 - K) / (K(K-1)):
every set of directions that sums to zero is at its floor with zero
gradient, so antipodal pairs, which a uniform mixture cancels, are its
best case. The squared and Gram variants make them the worst case. The
routing terms (usage, load balance, z-loss) come from mixture-of-experts
practice: nothing in the paper's loss asks the router to be informative.
The training metrics also carry diagnostics (`diag_*`, diagnostics.py),
computed on stopped gradients: they never change the loss.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import jax
import jax.numpy as jnp

from skillplug_jax import diagnostics, validation

SD_KINDS = ("cosine", "squared", "gram")


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


def _unit(x: jnp.ndarray) -> jnp.ndarray:
  return x / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), 1e-8)


def _off_diagonal_mean(sim: jnp.ndarray, pair_weights: jnp.ndarray | None = None) -> jnp.ndarray:
  """Mean over the batch of the (weighted) mean of the off-diagonal entries of sim [..., K, K]."""
  num_skills = sim.shape[-1]
  if pair_weights is None:
    off_diagonal = sim.sum(axis=(-2, -1)) - jnp.trace(sim, axis1=-2, axis2=-1)
    return (off_diagonal / (num_skills * (num_skills - 1))).mean()
  w = (1.0 - jnp.eye(num_skills, dtype=sim.dtype)) * pair_weights
  return ((sim * w).sum(axis=(-2, -1)) / jnp.maximum(w.sum(axis=(-2, -1)), 1e-12)).mean()


def skill_diversity(skill_features: jnp.ndarray, kind: str = "cosine",
                    centred: jnp.ndarray | None = None,
                    usage: jnp.ndarray | None = None) -> jnp.ndarray:
  """Disentanglement of the K interactor outputs, averaged over the batch.

  kind='cosine' (the paper): mean off-diagonal cosine similarity of the K
  token-averaged u_k, skill_features [B, K, D]. 0 for mutually orthogonal
  features, 1 when all K are identical (down to -1/(K-1) at best, which any
  set of directions summing to zero reaches, antipodal pairs included).
  kind='squared' (ours): the mean off-diagonal squared cosine: 0 only for
  orthogonal features, 1 for identical or antipodal ones.
  kind='gram' (ours): the same on `centred` [B, K, N, D] = u_k - h, each
  flattened over its tokens: ||G - I||^2 over the off-diagonal of the Gram
  matrix of the normalised skill-dependent parts, so what a skill adds must
  differ from what the others add, token by token.
  usage [K] (ours, `sd_usage_weighted`): weight pair (k, j) by usage_k
  usage_j (no gradient), so skills the router does not use cannot satisfy
  the term; equal usage gives the unweighted mean.
  """
  if kind not in SD_KINDS:
    raise ValueError(f"sd_kind must be one of {SD_KINDS}, got {kind!r}")
  num_skills = skill_features.shape[-2]
  if num_skills < 2:
    return jnp.zeros((), jnp.float32)
  if kind == "gram":
    if centred is None:
      raise ValueError("sd_kind='gram' needs the centred features u_k - h")
    c = centred.astype(jnp.float32)
    v = _unit(c.reshape(*c.shape[:-2], -1))
  else:
    v = _unit(skill_features.astype(jnp.float32))
  sim = jnp.einsum("...kd,...jd->...kj", v, v)
  if kind != "cosine":
    sim = sim**2
  pair = None
  if usage is not None:
    r = jax.lax.stop_gradient(usage.astype(jnp.float32))
    pair = r[:, None] * r[None, :]
  return _off_diagonal_mean(sim, pair)


def mutual_information_usage(probs: jnp.ndarray) -> jnp.ndarray:
  """-(H(mean_b r_b) - mean_b H(r_b)), probs [B, K]: minus the mutual
  information between a query and its skill under the batch's routing.

  Zero for routing that is the same for every query (uniform, or collapsed
  on one skill); -log K, its minimum, for confident routing (one-hot per
  query) that uses every skill equally across the batch.
  """
  p = probs.astype(jnp.float32)
  return -(diagnostics.entropy(p.mean(axis=0)) - diagnostics.entropy(p).mean())


def load_balance(probs: jnp.ndarray) -> jnp.ndarray:
  """Switch Transformer's auxiliary loss K sum_k f_k P_k (Fedus et al., 2021):
  f_k the fraction of queries whose argmax is k (no gradient), P_k the mean
  probability of k. 1 at perfect balance, K when one skill takes everything."""
  p = probs.astype(jnp.float32)
  num_skills = p.shape[-1]
  f = jax.nn.one_hot(jnp.argmax(p, axis=-1), num_skills).mean(axis=0)
  return num_skills * jnp.sum(f * p.mean(axis=0))


def router_z_loss(logits: jnp.ndarray) -> jnp.ndarray:
  """ST-MoE's router z-loss (Zoph et al., 2022): mean logsumexp(logits)^2,
  which keeps the logits small without changing the softmax's shape."""
  return jnp.mean(jax.nn.logsumexp(logits.astype(jnp.float32), axis=-1) ** 2)


def router_distillation(router_probs: jnp.ndarray, assignment: jnp.ndarray) -> jnp.ndarray:
  """-sum_k sg(q_k) log r_k averaged over the batch: the router learns to
  predict, from the observation, the skill the posterior assigned from the
  demonstrated actions (fusion_source='posterior')."""
  target = jax.lax.stop_gradient(assignment.astype(jnp.float32))
  log_r = jnp.log(jnp.clip(router_probs.astype(jnp.float32), 1e-12, 1.0))
  return -(target * log_r).sum(axis=-1).mean()


def router_label_loss(router_probs: jnp.ndarray, labels: jnp.ndarray) -> jnp.ndarray:
  """-log r_label averaged over the queries whose label names a skill (0 <= label < K).

  With the toy's ground-truth primitive, an oracle (not a method) that measures what the
  library would do if the router found that partition; with labels mined from the
  demonstrations (train.skill_labels, data/segments.py), ours. Queries with a label
  outside [0, K) are left out; 0 when there are none.
  """
  p = router_probs.astype(jnp.float32)
  labels = labels.astype(jnp.int32)
  valid = (labels >= 0) & (labels < p.shape[-1])
  picked = jnp.take_along_axis(p, jnp.clip(labels, 0, p.shape[-1] - 1)[:, None], axis=-1)[:, 0]
  nll = -jnp.log(jnp.clip(picked, 1e-12, 1.0))
  return jnp.sum(jnp.where(valid, nll, 0.0)) / jnp.maximum(valid.sum(), 1)


# A weight of 0 turns its term off; a negative one would reward what the term penalises.
_WEIGHT_RULES = dict({name: validation.number(0) for name in (
    "rec", "kl", "bsa", "sd", "cvae_kl", "usage", "load_balance", "router_z", "distill", "router_label")},
    sd_kind=validation.one_of(SD_KINDS), sd_usage_weighted=validation.flag())


@dataclasses.dataclass(frozen=True)
class LossWeights:
  """Loss weights. The paper gives no lambdas: these are placeholders for the
  sweep, chosen by the scale of each term against L_rec (a mean L1 on
  normalised actions: ~0.5 at the start, a few 0.01 once trained).

  Sweep (recorded in docs/results/loss_weights/sweep_loss_weights_quick_cpu.json; `python -m
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
  # Ours (issue 27); the defaults are the paper's objective.
  sd_kind: str = "cosine"  # 'cosine' (paper) | 'squared' | 'gram': `skill_diversity`
  sd_usage_weighted: bool = False  # SD pairs weighted by r_k r_j (batch-mean routing)
  usage: float = 0.0  # weight of -(H(mean r) - mean H(r)): `mutual_information_usage`
  load_balance: float = 0.0  # weight of Switch's K sum_k f_k P_k
  router_z: float = 0.0  # weight of ST-MoE's router z-loss
  distill: float = 1.0  # router -> posterior assignment; only with fusion_source='posterior'
  router_label: float = 0.0  # -log r_label of the batch's `skill_label` (toy oracle, or train.skill_labels)

  def __post_init__(self):
    validation.check(self, "loss.", _WEIGHT_RULES)


def total_loss(outputs: Mapping[str, jnp.ndarray], batch: Mapping[str, jnp.ndarray],
               weights: LossWeights = LossWeights()) -> tuple[jnp.ndarray, dict]:
  """Weighted sum of the terms `Policy.__call__`'s outputs allow.

  SkillPlug outputs (they carry 'router_probs') get all five terms, and
  ours where their weights are nonzero (distill: where the outputs carry a
  posterior assignment); ACT's get rec and cvae_kl. The routing terms read
  the distribution the fusion follows in training: the router's, or the
  posterior's assignment with fusion_source='posterior'. Returns (loss,
  metrics) with every unweighted term, the total under 'loss', and the
  `diag_*` diagnostics (no gradient) where the outputs allow them.
  """
  metrics = {
      "rec": reconstruction_l1(outputs["pred_actions"], batch["actions"], batch["action_mask"]),
      "cvae_kl": kl_standard_normal(outputs["cvae_mu"], outputs["cvae_logvar"]),
  }
  loss = weights.rec * metrics["rec"] + weights.cvae_kl * metrics["cvae_kl"]
  if "router_probs" in outputs:
    assignment = outputs.get("posterior_assignment", outputs["router_probs"])
    centred = None
    if "skill_tokens" in outputs and "plug_input" in outputs:
      centred = outputs["skill_tokens"] - outputs["plug_input"][:, None]
    metrics["kl"] = kl_standard_normal(outputs["posterior_mu"], outputs["posterior_logvar"])
    metrics["bsa"] = behaviour_skill_alignment(outputs["router_probs"], outputs["traj_logits"])
    metrics["sd"] = skill_diversity(outputs["skill_features"], weights.sd_kind, centred,
                                    assignment.mean(axis=0) if weights.sd_usage_weighted else None)
    loss = loss + (weights.kl * metrics["kl"] + weights.bsa * metrics["bsa"]
                   + weights.sd * metrics["sd"])
    extra = {}
    if weights.usage:
      extra["usage"] = (weights.usage, mutual_information_usage(assignment))
    if weights.load_balance:
      extra["load_balance"] = (weights.load_balance, load_balance(assignment))
    if weights.router_z:
      extra["router_z"] = (weights.router_z, router_z_loss(outputs["router_logits"]))
    if weights.router_label:
      if "skill_label" not in batch:
        raise ValueError("loss.router_label > 0 needs batches with a 'skill_label' (the toy problem's "
                         "primitive, or train.skill_labels naming a labeller); these batches have none")
      extra["router_label"] = (weights.router_label, router_label_loss(outputs["router_probs"],
                                                                       batch["skill_label"]))
    if "posterior_assignment" in outputs:
      extra["distill"] = (weights.distill, router_distillation(outputs["router_probs"],
                                                               outputs["posterior_assignment"]))
    for name, (w, value) in extra.items():
      metrics[name] = value
      loss = loss + w * value
    metrics.update(diagnostics.training_metrics(outputs, batch.get("task_id")))
  metrics["loss"] = loss
  return loss, metrics
