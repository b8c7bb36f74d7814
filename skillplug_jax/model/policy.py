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
  action_proj  with plug_site='decoder' only (both policies): the final norm
               and action projection leave action_head and are f_act alone

Where the plug sits (`ModelConfig.plug_site`). 'encoder' (the default):
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
import jax
import jax.numpy as jnp

from skillplug_jax.model.act import OBJECT_SLOT_DIM, ActionHead, ActionProjection, CVAEEncoder, Encoder
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.interactor import INTERACTORS
from skillplug_jax.model.posterior import TrajectorySkillPosterior, reparameterise
from skillplug_jax.model.router import Router, gumbel_top1, top1
from skillplug_jax.model.skills import SkillLibrary


def _one_hot_argmax(x):
  return jax.nn.one_hot(jnp.argmax(x, axis=-1), x.shape[-1], dtype=jnp.float32)


class Policy(nn.Module):
  config: ModelConfig

  def setup(self):
    cfg = self.config
    on_decoder = cfg.plug_site == "decoder"
    self.encoder = Encoder(cfg)
    self.cvae = CVAEEncoder(cfg)
    self.action_head = ActionHead(cfg, project=not on_decoder)
    if on_decoder:
      self.action_proj = ActionProjection(cfg)
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
      for skillplug router_probs [B, K] (the router's softmax), router_logits
      [B, K] (what the softmax reads), fusion_weights [B, K] (what weighted the
      u_k here: the router's probabilities, their top-1, or the posterior's
      sample), skill_features [B, K, D] (token-averaged u_k), skill_tokens
      [B, K, N, D] (u_k) and plug_input [B, N, D] (what the interactor read:
      scene tokens, or decoder steps with N = chunk), posterior_mu /
      posterior_logvar [B, K, z], traj_logits [B, K]; with
      fusion_source='posterior' also posterior_assignment [B, K] =
      softmax(traj_logits).
    """
    cfg, deterministic = self.config, not train
    actions, mask = batch["actions"], batch["action_mask"]
    cvae_mu, cvae_logvar = self.cvae(batch["joint_pos"], actions, mask, deterministic)
    style_z = reparameterise(self.make_rng("sample"), cvae_mu, cvae_logvar) if train else cvae_mu
    batch, cue = self._split_cue(batch)
    h, pos = self.encoder(batch, style_z, deterministic)
    out = dict(cvae_mu=cvae_mu, cvae_logvar=cvae_logvar)
    if not cfg.is_skillplug:
      out["pred_actions"] = self.act(h, pos, train)
      return out
    x, x_pos = self._plug_input(h, pos, deterministic)
    skills = self.skills()
    post = self.posterior(actions, mask, skills, sample=train and cfg.skill_offset == "sample")
    codes = skills[None]
    if cfg.skill_offset != "none":  # 'sample' and 'mean': s_k + W z_k
      codes = codes + post["offset"].astype(skills.dtype)
    codes = jnp.broadcast_to(codes, (h.shape[0],) + skills.shape)
    u = self.interactor(x, codes, deterministic, x_pos)
    probs, logits = self.router(self._router_tokens(batch, h, deterministic), with_logits=True, cue=cue)
    weights = top1(probs) if cfg.routing == "top1" else probs
    if cfg.fusion_source == "posterior":
      q = post["traj_logits"].astype(jnp.float32)
      weights = gumbel_top1(self.make_rng("sample"), q) if train else _one_hot_argmax(q)
      out["posterior_assignment"] = jax.nn.softmax(q, axis=-1)
    out.update(router_probs=probs, router_logits=logits, fusion_weights=weights,
               skill_features=u.mean(axis=2).astype(jnp.float32),
               skill_tokens=u.astype(jnp.float32), plug_input=x.astype(jnp.float32),
               posterior_mu=post["mu"], posterior_logvar=post["logvar"],
               traj_logits=post["traj_logits"])
    out["pred_actions"] = self._actions(self._fuse(weights, u), pos, deterministic)
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
    pred_actions [B, chunk, A]. With routing='top1' or fusion_source='posterior'
    the router's choice is hard, as the fusion was in training."""
    cfg = self.config
    batch = obs["joint_pos"].shape[0]
    obs, cue = self._split_cue(obs)
    h, pos = self.encode(obs)
    x, x_pos = self._plug_input(h, pos, True)
    skills = self.skills()
    u = self.interactor(x, jnp.broadcast_to(skills, (batch,) + skills.shape), True, x_pos)
    if routing is None:
      routing = self.router(self._router_tokens(None, h, True), cue=cue)
      if cfg.routing == "top1" or cfg.fusion_source == "posterior":
        routing = _one_hot_argmax(routing)
    routing = jnp.broadcast_to(jnp.asarray(routing, jnp.float32), (batch, cfg.num_skills))
    fused = self._fuse(routing, u)
    return dict(plug_input=x, skill_tokens=u, routing=routing, fused=fused,
                pred_actions=self._actions(fused, pos, True))

  def encode(self, obs, style_z=None, train: bool = False):
    """f_enc alone: (scene tokens h [B, N, hidden], their positions [1, N, hidden]
    or None), with the style latent zero by default."""
    if style_z is None:
      style_z = jnp.zeros((obs["joint_pos"].shape[0], self.config.latent_dim), jnp.float32)
    return self.encoder(obs, style_z, not train)

  def act(self, h, pos=None, train: bool = False):
    """The decoder without the plug: tokens [B, N, hidden] (and positions) -> action chunk [B, chunk, A]."""
    if self.config.plug_site == "decoder":
      return self.action_proj(self.action_head(h, pos, not train)[0])
    return self.action_head(h, pos, not train)

  def _plug_input(self, h, pos, deterministic):
    """What the interactor reads, and its positions: the scene tokens, or the decoder's steps."""
    if self.config.plug_site == "decoder":
      return self.action_head(h, pos, deterministic)
    return h, pos

  def _actions(self, fused, pos, deterministic):
    """f_act of the fused feature."""
    if self.config.plug_site == "decoder":
      return self.action_proj(fused)
    return self.action_head(fused, pos, deterministic)

  def _split_cue(self, obs):
    """(obs with the router's cue zeroed, the cue [B, slots * 7]) under
    `router_cue_slots`; (obs, None) without one."""
    n = self.config.router_cue_slots if self.config.is_skillplug else 0
    if not n:
      return obs, None
    state = obs["object_state"]
    width = n * OBJECT_SLOT_DIM
    if state.shape[-1] < width:
      raise ValueError(f"model.router_cue_slots={n} needs an object state of at least {width} numbers, "
                       f"got {state.shape[-1]}")
    hidden = state.at[..., state.shape[-1] - width:].set(0.0)
    return dict(obs, object_state=hidden), state[..., state.shape[-1] - width:]

  def _router_tokens(self, batch, h, deterministic):
    """The tokens the router pools (`ModelConfig.router_input`); the style token is h[:, 0].
    batch=None: the inference path, where the style latent is already zero."""
    cfg = self.config
    if cfg.router_input == "no_style":
      return h[:, 1:]
    if cfg.router_input == "zero_style" and batch is not None:
      zero = jnp.zeros((h.shape[0], cfg.latent_dim), jnp.float32)
      return self.encoder(batch, zero, deterministic)[0]
    return h

  @staticmethod
  def _fuse(routing, u):
    """h~ = sum_k r_k u_k."""
    return jnp.einsum("bk,bknd->bnd", routing.astype(u.dtype), u)
