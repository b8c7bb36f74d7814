"""The policy: ACT, optionally with the SkillPlug module (model/plug.py) between its halves.

One module and one code path for both policies; `config.policy` decides
whether the plug is built, and the plug is called once per pass (training
and inference). Top-level parameter groups (what `freeze.py`
masks by name):

  encoder      backbone, input projections, transformer encoder (f_enc)
  cvae         ACT's CVAE encoder (training only)
  skills       the skill library s_1..s_K                       (skillplug)
  interactor   u_k = Interactor(h, s_k)                          (skillplug)
  router       r = softmax(MLP(pool(h)) / T)                     (skillplug)
  posterior    f_tau, q(z_k | f_tau, s_k), W, g_tau, g_s         (skillplug)
  action_head  decoder queries, decoder, action projection (f_act)
  action_proj  with plug.site='decoder' only (both policies): the final norm
               and action projection leave action_head and are f_act alone
  adapter      with adapter_width > 0 only (ours): a residual bottleneck before
               f_act (split head: on the decoder's steps; the encoder site: on
               the tokens the action head reads), added by a few-shot fine-tune
               (issues 42-43's capacity-matched baseline)

Where the plug sits (`PlugConfig.site`). 'encoder' (the default):
h~ = sum_k r_k Interactor(h, s_k) over the encoder's scene tokens, decoded by
the whole action head. 'decoder': the interactor reads the decoder's
per-step outputs d [B, chunk, D] (the paper's u_{t,k}, indexed by the step
t of the chunk), h~_t = sum_k r_k u_{t,k}, and f_act is the final norm and
projection. The router stays chunk-level (one r per chunk from the scene
tokens, as the paper's "chunk-level routing weights r_tau ... shared across
all timesteps within the chunk"), so routing arrays are [B, K] everywhere.

Randomness goes in through `apply(..., rngs={'dropout': k1, 'sample': k2})`
when `train=True`; `train=False` and `predict` need no rng.
"""

from __future__ import annotations

from typing import Mapping, Optional

import flax.linen as nn
import jax.numpy as jnp

from skillplug_jax.model.act import (OBJECT_SLOT_DIM, ActionHead, ActionProjection, Adapter, CVAEEncoder, Encoder,
                                    proprioception)
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.plug import SkillPlug
from skillplug_jax.model.posterior import reparameterise


class Policy(nn.Module):
  config: ModelConfig

  def setup(self):
    cfg = self.config
    self.encoder = Encoder(cfg)
    self.cvae = CVAEEncoder(cfg)
    self.action_head = ActionHead(cfg, project=not cfg.split_head)
    if cfg.split_head:
      self.action_proj = ActionProjection(cfg)
    if cfg.adapter_width:
      self.adapter = Adapter(cfg)
    if cfg.is_skillplug:
      self.plug = SkillPlug(cfg)
      nn.share_scope(self, self.plug)  # its groups (skills, interactor, router, posterior) stay top-level

  def __call__(self, batch: Mapping[str, jnp.ndarray], train: bool = False) -> dict:
    """Training/validation forward pass on a batch with `actions` and `action_mask`.

    train=True: dropout on, latents sampled (rngs 'dropout' and 'sample').
    train=False: dropout off, latents at their posterior means (a
    deterministic validation loss). Returns everything `losses.total_loss` reads:
      pred_actions [B, chunk, A], cvae_mu / cvae_logvar [B, latent_dim], and
      for skillplug router_probs [B, K] (the router's softmax, which weights
      the u_k), router_logits [B, K] (what the softmax reads), skill_features
      [B, K, D] (token-averaged u_k), skill_tokens [B, K, N, D] (u_k) and
      plug_input [B, N, D] (what the interactor read: scene tokens, or
      decoder steps with N = chunk), posterior_mu / posterior_logvar [B, K, z],
      traj_logits [B, K].
    """
    cfg, deterministic = self.config, not train
    actions, mask = batch["actions"], batch["action_mask"]
    cvae_mu, cvae_logvar = self.cvae(proprioception(batch, cfg), actions, mask, deterministic)
    style_z = reparameterise(self.make_rng("sample"), cvae_mu, cvae_logvar) if train else cvae_mu
    batch, cue = self._split_cue(batch)
    h, pos = self.encoder(batch, style_z, deterministic)
    out = dict(cvae_mu=cvae_mu, cvae_logvar=cvae_logvar)
    if not cfg.is_skillplug:
      out["pred_actions"] = self.act(h, pos, train)
      return out
    x, x_pos = self._plug_input(h, pos, deterministic)
    p = self.plug(x, x_pos, h, cue, actions, mask, train=train)
    u = p["skill_tokens"]
    out.update(router_probs=p["router_probs"], router_logits=p["router_logits"],
               skill_features=u.mean(axis=2).astype(jnp.float32), skill_tokens=u.astype(jnp.float32),
               plug_input=x.astype(jnp.float32), posterior_mu=p["posterior_mu"],
               posterior_logvar=p["posterior_logvar"], traj_logits=p["traj_logits"],
               pred_actions=self._actions(p["fused"], pos, deterministic))
    return out

  def predict(self, obs: Mapping[str, jnp.ndarray],
              routing: Optional[jnp.ndarray] = None) -> tuple[jnp.ndarray, Optional[jnp.ndarray]]:
    """Inference: obs -> (action chunk [B, chunk, A], routing weights [B, K] or None).

    No actions are read: the CVAE latent is zero and each skill enters as s_k
    (the posterior is not called). `routing` ([K] or [B, K]) replaces the
    router's weights, for fixed-skill and mixed-skill rollouts.
    """
    if not self.config.is_skillplug:
      h, pos = self.encode(obs)
      return self.act(h, pos), None
    f = self.features(obs, routing)
    return f["pred_actions"], f["routing"]

  def features(self, obs: Mapping[str, jnp.ndarray], routing: Optional[jnp.ndarray] = None) -> dict:
    """The inference path's plug, for diagnostics (skillplug only): plug_input
    [B, N, D], skill_tokens u [B, K, N, D], routing [B, K], fused [B, N, D] and
    pred_actions [B, chunk, A]."""
    obs, cue = self._split_cue(obs)
    h, pos = self.encode(obs)
    x, x_pos = self._plug_input(h, pos, True)
    p = self.plug(x, x_pos, h, cue, routing=routing)
    return dict(plug_input=x, skill_tokens=p["skill_tokens"], routing=p["routing"], fused=p["fused"],
                pred_actions=self._actions(p["fused"], pos, True))

  def encode(self, obs, style_z=None, train: bool = False):
    """f_enc alone: (scene tokens h [B, N, hidden], their positions [1, N, hidden]
    or None), with the style latent zero by default."""
    if style_z is None:
      style_z = jnp.zeros((obs["joint_pos"].shape[0], self.config.latent_dim), jnp.float32)
    return self.encoder(obs, style_z, not train)

  def act(self, h, pos=None, train: bool = False):
    """The decoder without the plug: tokens [B, N, hidden] (and positions) -> action chunk [B, chunk, A]."""
    if self.config.split_head:
      return self._project(self.action_head(h, pos, not train)[0])
    return self.action_head(self._adapt(h), pos, not train)

  def _plug_input(self, h, pos, deterministic):
    """What the interactor reads, and its positions: the scene tokens, or the decoder's steps."""
    if self.config.split_head:
      return self.action_head(h, pos, deterministic)
    return h, pos

  def _actions(self, fused, pos, deterministic):
    """f_act of the fused feature."""
    if self.config.split_head:
      return self._project(fused)
    return self.action_head(self._adapt(fused), pos, deterministic)

  def _project(self, d):
    """f_act of decoder steps d [B, chunk, D] (split head), through the adapter where there is one."""
    return self.action_proj(self._adapt(d))

  def _adapt(self, x):
    """x through the adapter where there is one (`adapter_width`), else x."""
    return self.adapter(x) if self.config.adapter_width else x

  def _split_cue(self, obs):
    """(obs with the router's cue zeroed, the cue [B, slots * 7]) under
    `plug.router_cue_slots`; (obs, None) without one."""
    n = self.config.plug.router_cue_slots if self.config.is_skillplug else 0
    if not n:
      return obs, None
    state = obs["object_state"]
    width = n * OBJECT_SLOT_DIM
    if state.shape[-1] < width:
      raise ValueError(f"model.plug.router_cue_slots={n} needs an object state of at least {width} numbers, "
                       f"got {state.shape[-1]}")
    hidden = state.at[..., state.shape[-1] - width:].set(0.0)
    return dict(obs, object_state=hidden), state[..., state.shape[-1] - width:]
