"""The training objective: each term a pure function, then their weighted sum.

  total = rec + kl * L_KL + bsa * L_BSA + sd * L_SD + cvae_kl * ACT's CVAE KL
          + sum of the auxiliary terms (`AUX_TERMS`, ours, each zero by default: usage;
            router_label, the router supervised with a label: the toy's primitive (an oracle)
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
best case. The squared and Gram variants (`SD_KINDS`) make them the worst
case. The usage term comes from mixture-of-experts practice: nothing in the
paper's loss asks the router to be informative.
The training metrics also carry diagnostics (`diag_*`, diagnostics.py),
computed on stopped gradients: they never change the loss.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Mapping

import jax
import jax.numpy as jnp

from skillplug_jax import diagnostics, validation


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


def _cosines(skill_features, centred):
  """The paper's: cosine similarities of the K token-averaged u_k."""
  v = _unit(skill_features.astype(jnp.float32))
  return jnp.einsum("...kd,...jd->...kj", v, v)


def _squared_cosines(skill_features, centred):
  """Ours: squared cosines, 0 only for orthogonal features, 1 for identical or antipodal ones."""
  return _cosines(skill_features, centred) ** 2


def _gram(skill_features, centred):
  """Ours: the squared Gram matrix of the normalised skill-dependent parts u_k - h, each flattened
  over its tokens, so what a skill adds must differ from what the others add, token by token."""
  if centred is None:
    raise ValueError("sd_kind='gram' needs the centred features u_k - h")
  c = centred.astype(jnp.float32)
  v = _unit(c.reshape(*c.shape[:-2], -1))
  return jnp.einsum("...kd,...jd->...kj", v, v) ** 2


# loss.sd_kind -> the pairwise similarity [..., K, K] whose off-diagonal mean L_SD is.
SD_KINDS: dict[str, Callable] = {"cosine": _cosines, "squared": _squared_cosines, "gram": _gram}


def skill_diversity(skill_features: jnp.ndarray, kind: str = "cosine",
                    centred: jnp.ndarray | None = None,
                    usage: jnp.ndarray | None = None) -> jnp.ndarray:
  """Disentanglement of the K interactor outputs, averaged over the batch: the mean off-diagonal
  entry of `SD_KINDS[kind]` (skill_features [B, K, D], the token-averaged u_k; centred
  [B, K, N, D] = u_k - h, for 'gram').

  kind='cosine' (the paper): 0 for mutually orthogonal features, 1 when all K are identical
  (down to -1/(K-1) at best, which any set of directions summing to zero reaches, antipodal
  pairs included). usage [K] (ours, `sd_usage_weighted`): weight pair (k, j) by usage_k usage_j
  (no gradient), so skills the router does not use cannot satisfy the term; equal usage gives
  the unweighted mean.
  """
  if kind not in SD_KINDS:
    raise ValueError(f"sd_kind must be one of {tuple(SD_KINDS)}, got {kind!r}")
  if skill_features.shape[-2] < 2:
    return jnp.zeros((), jnp.float32)
  sim = SD_KINDS[kind](skill_features, centred)
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


@dataclasses.dataclass(frozen=True)
class AuxTerm:
  """A term of ours beside the paper's four: its value from the forward pass's outputs and the
  batch, and the batch keys it needs (a weight > 0 without them is an error, not a silent skip)."""
  value: Callable[[Mapping[str, jnp.ndarray], Mapping[str, jnp.ndarray]], jnp.ndarray]
  needs: tuple[str, ...] = ()
  why_missing: str = ""


# loss.<name> weighs AUX_TERMS[name]; total_loss adds each whose weight is not 0, in this order.
AUX_TERMS: dict[str, AuxTerm] = {
    "usage": AuxTerm(lambda out, batch: mutual_information_usage(out["router_probs"])),
    "router_label": AuxTerm(
        lambda out, batch: router_label_loss(out["router_probs"], batch["skill_label"]), ("skill_label",),
        "the toy problem's primitive, or train.skill_labels naming a labeller"),
}

# A weight of 0 turns its term off; a negative one would reward what the term penalises.
_WEIGHT_RULES = dict({name: validation.number(0) for name in ("rec", "kl", "bsa", "sd", "cvae_kl", *AUX_TERMS)},
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
  # the auxiliary terms' weights (AUX_TERMS)
  usage: float = 0.0  # weight of -(H(mean r) - mean H(r)): `mutual_information_usage`
  router_label: float = 0.0  # -log r_label of the batch's `skill_label` (toy oracle, or train.skill_labels)

  def __post_init__(self):
    validation.check(self, "loss.", _WEIGHT_RULES)


def total_loss(outputs: Mapping[str, jnp.ndarray], batch: Mapping[str, jnp.ndarray],
               weights: LossWeights = LossWeights()) -> tuple[jnp.ndarray, dict]:
  """Weighted sum of the terms `Policy.__call__`'s outputs allow.

  SkillPlug outputs (they carry 'router_probs') get the paper's four terms
  and each auxiliary term whose weight is not 0 (`AUX_TERMS`); ACT's get rec
  and cvae_kl. Returns (loss, metrics) with every unweighted term, the total
  under 'loss', and the `diag_*` diagnostics (no gradient) where the
  outputs allow them.
  """
  metrics = {
      "rec": reconstruction_l1(outputs["pred_actions"], batch["actions"], batch["action_mask"]),
      "cvae_kl": kl_standard_normal(outputs["cvae_mu"], outputs["cvae_logvar"]),
  }
  loss = weights.rec * metrics["rec"] + weights.cvae_kl * metrics["cvae_kl"]
  if "router_probs" in outputs:
    centred = None
    if "skill_tokens" in outputs and "plug_input" in outputs:
      centred = outputs["skill_tokens"] - outputs["plug_input"][:, None]
    metrics["kl"] = kl_standard_normal(outputs["posterior_mu"], outputs["posterior_logvar"])
    metrics["bsa"] = behaviour_skill_alignment(outputs["router_probs"], outputs["traj_logits"])
    usage = outputs["router_probs"].mean(axis=0) if weights.sd_usage_weighted else None
    metrics["sd"] = skill_diversity(outputs["skill_features"], weights.sd_kind, centred, usage)
    loss = loss + (weights.kl * metrics["kl"] + weights.bsa * metrics["bsa"]
                   + weights.sd * metrics["sd"])
    for name, term in AUX_TERMS.items():
      w = getattr(weights, name)
      if not w:
        continue
      missing = [k for k in term.needs if k not in batch]
      if missing:
        raise ValueError(f"loss.{name} > 0 needs batches with {', '.join(repr(k) for k in missing)} "
                         f"({term.why_missing}); these batches have none")
      metrics[name] = term.value(outputs, batch)
      loss = loss + w * metrics[name]
    metrics.update(diagnostics.training_metrics(outputs, batch.get("task_id"), batch.get("skill_label")))
  metrics["loss"] = loss
  return loss, metrics
