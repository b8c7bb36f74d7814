"""The SkillPlug: skill library, interactor, router and trajectory-skill posterior as one module.

    u_k = Interactor(x, s_k (+ W z_k in training))     x: scene tokens, or decoder steps
    r   = softmax(MLP(pool(scene tokens)) / T)          one r per chunk
    h~  = sum_k r_k u_k                                 what f_act decodes

`Policy` calls it once, in training (actions given: the posterior runs and
its offsets enter the codes) and at inference (no actions: s_k alone, and
`routing` may replace the router's weights for fixed- and mixed-skill
rollouts). Its settings are `PlugConfig` (`model.plug.*`); the choices that
have more than one reading are looked up by name (`INTERACTORS`), or are
one line each here.

Its parameters keep the top-level groups the paper names (skills,
interactor, router, posterior: what `freeze.py` masks), because the module
shares its parent's scope (`nn.share_scope`): checkpoints and few-shot
masks read the same tree as before the module existed.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import flax.linen as nn
import jax.numpy as jnp

from skillplug_jax import validation
from skillplug_jax.model.interactor import INTERACTORS
from skillplug_jax.model.posterior import TrajectorySkillPosterior
from skillplug_jax.model.router import Router
from skillplug_jax.model.skills import SkillLibrary

# Readings of the paper's text (issue 27); the first value of each is the paper's configuration
# as first built, and the default.
SITES = ("encoder", "decoder")
SKILL_OFFSETS = ("sample", "mean", "none")
ROUTER_INPUTS = ("all", "no_style")
FUSION_WEIGHTS = ("router", "uniform")

_count, _one_of = validation.count, validation.one_of
_RULES = dict(num_skills=_count(1), skill_latent_dim=_count(1), alignment_dim=_count(1),
              interactor=_one_of(INTERACTORS), router_temperature=validation.number(above=0),
              site=_one_of(SITES), skill_offset=_one_of(SKILL_OFFSETS), router_input=_one_of(ROUTER_INPUTS),
              router_cue_slots=_count(0), fusion_weights=_one_of(FUSION_WEIGHTS))


@dataclasses.dataclass(frozen=True)
class PlugConfig:
  """What the plug is made of; read only when `ModelConfig.policy` is 'skillplug' (but `site`,
  which also decides ACT's light head: `ModelConfig.split_head`)."""
  num_skills: int = 4  # K
  # Size of the per-skill posterior latent z_k. Kept small (ACT's style latent size) so the
  # posterior is a real bottleneck: W lifts it to `hidden`.
  skill_latent_dim: int = 32
  # Width of the shared space where g_tau(f_tau) and g_s(s_k) are compared (BSA).
  alignment_dim: int = 128
  interactor: str = "query_offset"  # see interactor.INTERACTORS
  # Softmax temperature of the router (1: the paper's softmax; below 1: sharper routing).
  router_temperature: float = 1.0
  # Where the plug sits. 'encoder': between encoder and decoder, h~ = sum_k r_k Interactor(h,
  # s_k) feeds the whole decoder. 'decoder': on the decoder's per-step outputs (the paper's
  # u_{t,k}), with f_act the final norm and action projection alone (parameter group
  # 'action_proj', for ACT too), so few-shot can retrain a light head in both arms. The router
  # stays chunk-level (one r per chunk, as the paper's r_tau), so routing arrays are [B, K].
  site: str = "encoder"
  # What the interactor receives in training: s_k + W z_k with z 'sample'd (the paper), z at its
  # posterior 'mean', or s_k alone ('none': the posterior serves only its KL and BSA terms).
  # Inference always gives s_k.
  skill_offset: str = "sample"
  # What the router pools: 'all' scene tokens, or 'no_style' (without the training-only CVAE
  # style token, index 0; the other tokens still saw it in the encoder's attention).
  router_input: str = "all"
  # Ours: the last N object-state slots (7 numbers each) are a cue that only the router reads
  # (added to its pooled input through a Dense layer); the encoder sees them zeroed, so the
  # decoder learns what the cue says only through the routing (the toy's oracle diagnostic,
  # docs/measurements/skill_library.md). 0: the paper's (both read everything). ACT, which has
  # no router, reads everything either way.
  router_cue_slots: int = 0
  # What weighs the u_k: the 'router' (the paper), or 'uniform' 1/K whatever the router says (ours,
  # issue 43: a few-shot arm that asks whether the routing matters; its router still runs, and its
  # outputs report the weights used).
  fusion_weights: str = "router"

  def __post_init__(self):
    validation.check(self, "model.plug.", _RULES)


class SkillPlug(nn.Module):
  """The plug of a `ModelConfig` (its `plug` settings and the transformer's sizes)."""
  config: "ModelConfig"  # noqa: F821 (model/config.py imports this module)

  def setup(self):
    cfg, plug = self.config, self.config.plug
    self.skills = SkillLibrary(plug.num_skills, cfg.hidden)
    self.interactor = INTERACTORS[plug.interactor](cfg.hidden, cfg.heads, cfg.ff, cfg.dropout, cfg.compute_dtype)
    self.router = Router(plug.num_skills, cfg.hidden, cfg.compute_dtype, plug.router_temperature)
    self.posterior = TrajectorySkillPosterior(cfg.hidden, plug.skill_latent_dim, plug.alignment_dim)

  def __call__(self, x, x_pos, scene, cue=None, actions=None, action_mask=None, train: bool = False,
               routing: Optional[jnp.ndarray] = None) -> dict:
    """x [B, N, D] (and its positions x_pos, or None): what the interactor reads; scene [B, M, D]:
    the encoder's tokens, which the router pools; cue [B, C] or None: what only the router reads.

    Training pass (actions [B, T, A] and action_mask [B, T] given): the posterior q(z_k | tau)
    runs, its offsets W z_k enter the codes (`skill_offset`), and its outputs come back
    (posterior_mu / posterior_logvar [B, K, z], traj_logits [B, K]). Inference (no actions): s_k
    alone. `routing` ([K] or [B, K]) replaces the router's weights. Returns also skill_tokens u
    [B, K, N, D], routing [B, K] (what weighted the u_k), fused h~ [B, N, D], and where the
    router ran, router_probs and router_logits [B, K].
    """
    plug = self.config.plug
    skills = self.skills()
    out, codes = {}, skills[None]
    if actions is not None:
      post = self.posterior(actions, action_mask, skills, sample=train and plug.skill_offset == "sample")
      if plug.skill_offset != "none":  # 'sample' and 'mean': s_k + W z_k
        codes = codes + post["offset"].astype(skills.dtype)
      out.update(posterior_mu=post["mu"], posterior_logvar=post["logvar"], traj_logits=post["traj_logits"])
    batch = x.shape[0]
    u = self.interactor(x, jnp.broadcast_to(codes, (batch,) + skills.shape), not train, x_pos)
    if routing is None:
      routing, logits = self.router(scene[:, 1:] if plug.router_input == "no_style" else scene,
                                    with_logits=True, cue=cue)
      if plug.fusion_weights == "uniform":
        routing, logits = jnp.full_like(routing, 1.0 / plug.num_skills), jnp.zeros_like(logits)
      out.update(router_probs=routing, router_logits=logits)
    routing = jnp.broadcast_to(jnp.asarray(routing, jnp.float32), (batch, plug.num_skills))
    fused = jnp.einsum("bk,bknd->bnd", routing.astype(u.dtype), u)  # h~ = sum_k r_k u_k
    return dict(out, skill_tokens=u, routing=routing, fused=fused)
