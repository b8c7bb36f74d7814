"""ACT (Zhao et al., 2023) split into the two halves SkillPlug plugs between.

`Encoder`    : obs + style latent -> scene tokens h [B, N, hidden]   (f_enc)
`ActionHead` : tokens [B, N, hidden] -> action chunk [B, chunk, A]   (f_act)
`CVAEEncoder`: ACT's training-only encoder of the demonstrated chunk into the
               32-D style latent; at inference the latent is zero.

`ActionProjection`: f_act's last step alone (final norm and the action
               projection), its own parameter group with `plug.site='decoder'`.

Token layout of h: [style, joint_pos, then either every camera's feature map
cells (camera-major, row-major) or the object state: one token, or one per
object slot (`object_tokens`)]. One ResNet-18 is shared by all cameras, as in
ACT's code; a learned per-camera embedding tells them apart.

Object slots (`object_tokens='per_object'`): a task's object state is each
object's position and quaternion (7 numbers), then its articulation angles,
zero-padded to envs.OBJECT_STATE_DIM = 28 (envs/env.py `object_state`), so
the padded vector is 4 slots of 7: slot i is object i's pose, the slot after
the last object holds the angles (laptop lid, drawer) and their padding,
later slots are zeros. A slot's meaning is the task's own object order (slot
0 is the jujube in one task, the cup in another); the learned per-slot
position only tells the slots apart.

How positions and learned queries enter (issue 12). ACT, after DETR, adds
its positions (learned for the style and joint tokens, sinusoidal for image
cells and the CVAE's steps) to the attention queries and keys of every layer,
never to the values, and starts its decoder from zero contents with the
learned queries as query positions; torch draws the learned tables from
N(0, 1). That is `ModelConfig.positions='qk'`. Our default, 'input', adds
every position and query once to the token contents (ViT style), with the
learned tables drawn from N(0, 0.02). Measured in closed loop (quick preset,
ACT, 50 paired trials per task, mean over 3 training seeds; jujube_pick is
the task that separates them; docs/measurements/act_parity.md):
- before issue 12 we added N(0, 1) tables to the contents beside the raw
  object state: J.P. 22%. At N(0, 0.02), 43%; 'qk' at N(0, 1), ACT's own
  wiring, 47%, as LeRobot's ACT trained on the same batches (47%);
- normalising the object state (`normalize_object_state`) lifted every
  wiring: 'input' at N(0, 0.02) 73%, 'qk' at N(0, 1) 69% (57% at N(0, 0.02)),
  LeRobot's ACT 71%;
- trained on all 7 discoverse7 tasks, 'input' reached 80% on J.P. and 'qk'
  37%, the other tasks alike.
So we keep 'input'; 'qk' stays an option.
`Encoder` returns the tokens and their positions (None in 'input' mode, where
they are already in the contents); in 'qk' mode the action head's
cross-attention adds them to the memory's keys.
"""

from __future__ import annotations

from typing import Mapping

import flax.linen as nn
import jax.numpy as jnp

from envs.names import OBJECT_STATE_DIM  # cheap: not the suite
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.resnet import ResNet18
from skillplug_jax.model.transformer import (DecoderLayer, TransformerEncoder,
                                             sinusoidal_1d, sinusoidal_2d)

OBJECT_SLOT_DIM = 7  # one object's pose in the object state: position (3) and quaternion (4)


def _embed_init(config: ModelConfig):
  return nn.initializers.normal(stddev=config.embed_init_std)


def feature_map_size(config: ModelConfig) -> tuple[int, int]:
  """Spatial size of the backbone's output: the stem and its pool halve the
  input, each stage after the first halves it again (five times for ResNet-18)."""
  h, w = config.image_size
  for _ in range(1 + len(config.backbone_stages)):
    h, w = -(-h // 2), -(-w // 2)
  return h, w


def object_slots(width: int) -> int:
  """How many object tokens `object_tokens='per_object'` makes of an object state this wide."""
  if width % OBJECT_SLOT_DIM:
    raise ValueError(f"object_tokens='per_object' needs an object state of whole {OBJECT_SLOT_DIM}-number "
                     f"slots (position and quaternion per object); got width {width}")
  return width // OBJECT_SLOT_DIM


def num_tokens(config: ModelConfig, object_width: int = OBJECT_STATE_DIM) -> int:
  """N, the number of scene tokens the encoder emits (object_width: the object
  state's width, envs.names.OBJECT_STATE_DIM unless given)."""
  first = 3 if config.instruction_vocab else 2  # style, joint (and the instruction)
  if not config.use_images:
    if config.object_tokens == "per_object":
      return first + object_slots(object_width)
    return first + 1
  h, w = feature_map_size(config)
  return first + len(config.cameras) * h * w


def proprioception(obs: Mapping[str, jnp.ndarray], config: ModelConfig) -> jnp.ndarray:
  """The fields of `config.proprio`, concatenated [B, joint_dim]: what the joint token reads."""
  if len(config.proprio) == 1:
    return obs[config.proprio[0]]
  return jnp.concatenate([obs[k] for k in config.proprio], axis=-1)


class Encoder(nn.Module):
  """f_enc: backbone, input projections and the transformer encoder.

  Returns (tokens h [B, N, hidden], positions [1, N, hidden] or None).
  """
  config: ModelConfig

  @nn.compact
  def __call__(self, obs: Mapping[str, jnp.ndarray], style_z: jnp.ndarray,
               deterministic: bool = True):
    cfg, dt = self.config, self.config.compute_dtype
    batch = style_z.shape[0]
    style = nn.Dense(cfg.hidden, dtype=dt, name="style_proj")(style_z.astype(dt))
    joint = nn.Dense(cfg.hidden, dtype=dt, name="joint_proj")(proprioception(obs, cfg).astype(dt))
    first = [style, joint]
    if cfg.instruction_vocab:
      first.append(self._instruction_token(obs["instruction"]))
    contents = [jnp.stack(first, axis=1)]
    pos = [self.param("token_pos", _embed_init(cfg), (len(first), cfg.hidden)).astype(dt)]
    if cfg.use_images:
      x, image_pos = self._image_tokens(obs, batch)
    elif cfg.object_tokens == "per_object":
      x, image_pos = self._object_tokens(obs["object_state"].astype(dt))
    else:
      x = obs["object_state"].astype(dt)
      x = nn.relu(nn.Dense(cfg.hidden, dtype=dt, name="state_fc1")(x))
      x = nn.Dense(cfg.hidden, dtype=dt, name="state_fc2")(x)[:, None, :]
      image_pos = self.param("state_pos", _embed_init(cfg), (cfg.hidden,)).astype(dt)[None]
    contents.append(x)
    pos.append(image_pos)
    x, pos = jnp.concatenate(contents, axis=1), jnp.concatenate(pos, axis=0)[None]
    if cfg.positions == "input":
      x, pos = x + pos, None
    x = TransformerEncoder(cfg.enc_layers, cfg.hidden, cfg.heads, cfg.ff, cfg.dropout, dt,
                           cfg.pre_norm, name="transformer")(x, deterministic, pos=pos)
    return x, pos

  def _instruction_token(self, ids):
    """[B, hidden]: the instruction's word embeddings (ids [B, words], PAD = 0 left out) averaged
    and projected. An id past the table is an error of the caller (language.encode fits it)."""
    cfg, dt = self.config, self.config.compute_dtype
    emb = nn.Embed(cfg.instruction_vocab, cfg.hidden, dtype=dt, embedding_init=_embed_init(cfg),
                   name="instruction_embed")(ids)
    mask = (ids != 0).astype(dt)[..., None]
    pooled = (emb * mask).sum(axis=1) / jnp.maximum(mask.sum(axis=1), 1.0)
    return nn.Dense(cfg.hidden, dtype=dt, name="instruction_proj")(pooled)

  def _object_tokens(self, state):
    """One token per object slot [B, slots, hidden] (one MLP shared by the
    slots) and the slots' learned positions [slots, hidden]."""
    cfg, dt = self.config, self.config.compute_dtype
    slots = object_slots(state.shape[-1])
    x = state.reshape(*state.shape[:-1], slots, OBJECT_SLOT_DIM)
    x = nn.relu(nn.Dense(cfg.hidden, dtype=dt, name="object_fc1")(x))
    x = nn.Dense(cfg.hidden, dtype=dt, name="object_fc2")(x)
    return x, self.param("object_pos", _embed_init(cfg), (slots, cfg.hidden)).astype(dt)

  def _image_tokens(self, obs, batch):
    """Feature-map cells [B, cameras * h * w, hidden] and their positions."""
    cfg, dt = self.config, self.config.compute_dtype
    n_cam = len(cfg.cameras)
    images = jnp.concatenate([obs[f"{cam}_rgb"] for cam in cfg.cameras], axis=0)
    fmap = ResNet18(cfg.backbone_width, tuple(cfg.backbone_stages), dtype=dt, name="backbone")(images)
    _, h, w, _ = fmap.shape
    x = nn.Dense(cfg.hidden, dtype=dt, name="image_proj")(fmap)  # ACT's 1x1 conv
    x = x.reshape(n_cam, batch, h * w, cfg.hidden).transpose(1, 0, 2, 3)
    camera_embed = self.param("camera_embed", _embed_init(cfg), (n_cam, 1, cfg.hidden))
    pos = jnp.asarray(sinusoidal_2d(h, w, cfg.hidden), dt) + camera_embed.astype(dt)
    return x.reshape(batch, n_cam * h * w, cfg.hidden), pos.reshape(n_cam * h * w, cfg.hidden)


class CVAEEncoder(nn.Module):
  """ACT's style-latent encoder over [CLS, joint_pos, a_1..a_T], training only.

  Padded steps (past the episode end) are masked out as attention keys.
  Returns (mu, logvar), each [B, latent_dim], in float32.
  """
  config: ModelConfig

  @nn.compact
  def __call__(self, joint_pos, actions, action_mask, deterministic: bool = True):
    cfg, dt = self.config, self.config.compute_dtype
    batch = actions.shape[0]
    cls = self.param("cls", _embed_init(cfg), (cfg.hidden,))
    joint = nn.Dense(cfg.hidden, dtype=dt, name="joint_proj")(joint_pos.astype(dt))
    acts = nn.Dense(cfg.hidden, dtype=dt, name="action_proj")(actions.astype(dt))
    x = jnp.concatenate([
        jnp.broadcast_to(cls.astype(dt), (batch, 1, cfg.hidden)), joint[:, None], acts], axis=1)
    pos = jnp.asarray(sinusoidal_1d(x.shape[1], cfg.hidden), dt)[None]
    if cfg.positions == "input":
      x, pos = x + pos, None
    valid = jnp.concatenate([jnp.ones((batch, 2), bool), action_mask.astype(bool)], axis=1)
    # only the CLS token is read: the last layer computes its output alone
    x = TransformerEncoder(cfg.cvae_enc_layers, cfg.hidden, cfg.heads, cfg.ff, cfg.dropout, dt,
                           cfg.pre_norm, name="transformer")(
                               x, deterministic, valid[:, None, None, :], pos, outputs=1)
    # Zero-initialised by default (ACT: torch's default init): the latent
    # starts at the prior, so the KL term (weight 10) does not dominate the
    # first steps (a random start costs ~30 nats).
    init = nn.initializers.zeros if cfg.cvae_zero_init else nn.initializers.lecun_normal()
    stats = nn.Dense(2 * cfg.latent_dim, dtype=jnp.float32, kernel_init=init,
                     name="latent_proj")(x[:, 0])
    mu, logvar = jnp.split(stats.astype(jnp.float32), 2, axis=-1)
    return mu, logvar


def project_actions(config: ModelConfig, x: jnp.ndarray) -> jnp.ndarray:
  """Decoder steps [B, chunk, hidden] -> actions [B, chunk, A]: the final norm
  and the action projection, built in the calling module's scope (so the
  default head keeps its parameter names)."""
  x = nn.LayerNorm(dtype=config.compute_dtype, name="final_norm")(x)
  return nn.Dense(config.action_dim, dtype=jnp.float32, name="action_proj")(x).astype(jnp.float32)


class ActionHead(nn.Module):
  """f_act: `chunk` learned queries decode the tokens into an action chunk.

  'qk' positions: ACT's decoder, zero contents with the learned queries as
  query positions; 'input': the learned queries are the contents.
  project=False (`plug.site='decoder'`): stop before the final norm and
  return (decoder steps [B, chunk, hidden], their positions [1, chunk,
  hidden] or None); `ActionProjection` does the rest.
  """
  config: ModelConfig
  project: bool = True

  @nn.compact
  def __call__(self, memory: jnp.ndarray, memory_pos=None, deterministic: bool = True):
    cfg, dt = self.config, self.config.compute_dtype
    queries = self.param("queries", _embed_init(cfg), (cfg.chunk, cfg.hidden)).astype(dt)
    shape = (memory.shape[0], cfg.chunk, cfg.hidden)
    if cfg.positions == "qk":
      x, query_pos = jnp.zeros(shape, dt), queries[None]
    else:
      x, query_pos = jnp.broadcast_to(queries, shape), None
    memory = memory.astype(dt)
    outputs = []
    for i in range(cfg.dec_layers):
      x = DecoderLayer(cfg.hidden, cfg.heads, cfg.ff, cfg.dropout, dt, cfg.pre_norm,
                       name=f"layer{i + 1}")(x, memory, deterministic, query_pos, memory_pos)
      outputs.append(x)
    # ACT's bug, kept as an option: every layer runs, only the first is read.
    x = outputs[0] if cfg.decoder_first_layer_only else outputs[-1]
    if not self.project:
      return x, query_pos
    return project_actions(cfg, x)


class ActionProjection(nn.Module):
  """f_act when the plug sits on the decoder's steps: final norm and projection."""
  config: ModelConfig

  @nn.compact
  def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
    return project_actions(self.config, x)


class Adapter(nn.Module):
  """Ours (issue 43): a residual bottleneck before f_act, d + W2 relu(W1 LN(d)), for a few-shot
  baseline that tunes as many parameters as the plug's router (`ModelConfig.adapter_width`).
  W2 starts at zero, so a fine-tune that adds it starts from its source's function."""
  config: ModelConfig

  @nn.compact
  def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
    cfg, dt = self.config, self.config.compute_dtype
    y = nn.LayerNorm(dtype=dt, name="norm")(x)
    y = nn.relu(nn.Dense(cfg.adapter_width, dtype=dt, name="down")(y))
    return x + nn.Dense(x.shape[-1], dtype=dt, kernel_init=nn.initializers.zeros, name="up")(y)
