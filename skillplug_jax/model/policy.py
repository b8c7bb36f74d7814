"""The policy: ACT, optionally with the SkillPlug module between its halves.

One module and one code path for both policies; `config.policy` decides
whether the plug is built. Top-level parameter groups (what `freeze.py`
masks by name):

  encoder      backbone, input projections, transformer encoder (f_enc)
  cvae         ACT's CVAE encoder (training only)
  skills       the skill library s_1..s_K                       (skillplug)
  interactor   u_k = Interactor(h, s_k)                          (skillplug)
  router       r = softmax(MLP(pool(h)) / T)                     (skillplug)
  posterior    f_tau, q(z_k | f_tau, s_k), W, g_tau, g_s         (skillplug)
  action_head  decoder queries, decoder, action projection (f_act)

Randomness goes in through `apply(..., rngs={'dropout': k1, 'sample': k2})`
when `train=True`; `train=False` and `predict` need no rng.
"""

from __future__ import annotations

from typing import Mapping, Optional

import flax.linen as nn
import jax.numpy as jnp

from skillplug_jax.model.act import ActionHead, CVAEEncoder, Encoder
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.interactor import INTERACTORS
from skillplug_jax.model.posterior import TrajectorySkillPosterior, reparameterise
from skillplug_jax.model.router import Router
from skillplug_jax.model.skills import SkillLibrary


class Policy(nn.Module):
  config: ModelConfig

  def setup(self):
    cfg = self.config
    self.encoder = Encoder(cfg)
    self.cvae = CVAEEncoder(cfg)
    self.action_head = ActionHead(cfg)
    if cfg.is_skillplug:
      dt = cfg.compute_dtype
      self.skills = SkillLibrary(cfg.num_skills, cfg.hidden)
      self.interactor = INTERACTORS[cfg.interactor](
          cfg.hidden, cfg.heads, cfg.ff, cfg.dropout, dt)
      self.router = Router(cfg.num_skills, cfg.hidden, dt, cfg.router_temperature)
      self.posterior = TrajectorySkillPosterior(
          cfg.hidden, cfg.skill_latent_dim, cfg.alignment_dim)

  def __call__(self, batch: Mapping[str, jnp.ndarray], train: bool = False) -> dict:
    """Training/validation forward pass on a batch with `actions` and `action_mask`.

    train=True: dropout on, latents sampled (rngs 'dropout' and 'sample').
    train=False: dropout off, latents at their posterior means (a
    deterministic validation loss). Returns everything `losses.total_loss` reads:
      pred_actions [B, chunk, A], cvae_mu / cvae_logvar [B, latent_dim], and
      for skillplug router_probs [B, K], skill_features [B, K, hidden]
      (token-averaged u_k), posterior_mu / posterior_logvar [B, K, z],
      traj_logits [B, K].
    """
    cfg, deterministic = self.config, not train
    actions, mask = batch["actions"], batch["action_mask"]
    cvae_mu, cvae_logvar = self.cvae(batch["joint_pos"], actions, mask, deterministic)
    style_z = reparameterise(self.make_rng("sample"), cvae_mu, cvae_logvar) if train else cvae_mu
    h, pos = self.encoder(batch, style_z, deterministic)
    out = dict(cvae_mu=cvae_mu, cvae_logvar=cvae_logvar)
    if cfg.is_skillplug:
      skills = self.skills()
      post = self.posterior(actions, mask, skills, sample=train)
      u = self.interactor(h, skills[None] + post["offset"].astype(skills.dtype), deterministic, pos)
      routing = self.router(h)
      h = self._fuse(routing, u)
      out.update(router_probs=routing,
                 skill_features=u.mean(axis=2).astype(jnp.float32),
                 posterior_mu=post["mu"], posterior_logvar=post["logvar"],
                 traj_logits=post["traj_logits"])
    out["pred_actions"] = self.action_head(h, pos, deterministic)
    return out

  def predict(self, obs: Mapping[str, jnp.ndarray],
              routing: Optional[jnp.ndarray] = None) -> tuple[jnp.ndarray, Optional[jnp.ndarray]]:
    """Inference: obs -> (action chunk [B, chunk, A], routing weights [B, K] or None).

    No actions are read: the CVAE latent is zero and each skill enters as s_k
    (the posterior is not called). `routing` ([K] or [B, K]) replaces the
    router's weights, for fixed-skill and mixed-skill rollouts.
    """
    cfg = self.config
    batch = obs["joint_pos"].shape[0]
    h, pos = self.encode(obs)
    if not cfg.is_skillplug:
      return self.action_head(h, pos, True), None
    skills = self.skills()
    u = self.interactor(h, jnp.broadcast_to(skills, (batch,) + skills.shape), True, pos)
    if routing is None:
      routing = self.router(h)
    routing = jnp.broadcast_to(jnp.asarray(routing, jnp.float32), (batch, cfg.num_skills))
    return self.action_head(self._fuse(routing, u), pos, True), routing

  def encode(self, obs, style_z=None, train: bool = False):
    """f_enc alone: (scene tokens h [B, N, hidden], their positions [1, N, hidden]
    or None), with the style latent zero by default."""
    if style_z is None:
      style_z = jnp.zeros((obs["joint_pos"].shape[0], self.config.latent_dim), jnp.float32)
    return self.encoder(obs, style_z, not train)

  def act(self, h, pos=None, train: bool = False):
    """f_act alone: tokens [B, N, hidden] (and positions) -> action chunk [B, chunk, A]."""
    return self.action_head(h, pos, not train)

  @staticmethod
  def _fuse(routing, u):
    """h~ = sum_k r_k u_k."""
    return jnp.einsum("bk,bknd->bnd", routing.astype(u.dtype), u)
