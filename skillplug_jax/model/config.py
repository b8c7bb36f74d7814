"""Model configuration: one frozen dataclass whose defaults are the paper's model.

The presets (quick, cpu, budget, paper) are experiment configs in
experiments/configs/: each names the few fields it changes.
"""

from __future__ import annotations

import dataclasses
from typing import Tuple

import jax.numpy as jnp

from skillplug_jax.model.interactor import INTERACTORS

POLICIES = ("act", "skillplug")
POSITIONS = ("input", "qk")
# Readings of the paper's text and remedies beyond it (issue 27); the first
# value of each is the paper's configuration as first built, and the default.
PLUG_SITES = ("encoder", "decoder")
SKILL_OFFSETS = ("sample", "mean", "none")
ROUTER_INPUTS = ("all", "no_style", "zero_style")
OBJECT_TOKENS = ("one", "per_object")
ROUTINGS = ("soft", "top1")
FUSION_SOURCES = ("router", "posterior")

# What a run recorded before a field existed meant: config.json files written
# before issue 12 lack these keys and must load as the model they trained.
LEGACY_DEFAULTS = dict(positions="input", embed_init_std=1.0, pre_norm=True,
                       cvae_zero_init=True, normalize_object_state=False)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """Everything `Policy` needs to build itself.

  The defaults are the paper's ACT (hidden 512, 8 heads, FF 3200, 4 encoder
  and 7 decoder layers, 32-D CVAE style latent, chunk 25) with K=4 skills.
  """
  policy: str = "skillplug"  # 'act' | 'skillplug'
  use_images: bool = True  # False: the state-only variant (object_state token)
  cameras: Tuple[str, ...] = ("side", "wrist")  # batch keys are f"{cam}_rgb"
  image_size: Tuple[int, int] = (64, 64)  # (H, W) of the rendered images
  joint_dim: int = 7
  action_dim: int = 7
  chunk: int = 25
  hidden: int = 512
  heads: int = 8
  ff: int = 3200
  enc_layers: int = 4
  dec_layers: int = 7
  # The original ACT code stacks every decoder layer's output and then reads
  # only the first; True reproduces that (all layers still run and hold
  # parameters, as in ACT's checkpoints). False uses the whole stack.
  decoder_first_layer_only: bool = False
  dropout: float = 0.1
  # How positions and learned queries enter the transformer (act.py's
  # docstring): 'input' adds them once to the token contents (ViT style);
  # 'qk' adds them to the attention queries and keys of every layer and
  # starts the decoder from zero contents, as ACT does.
  positions: str = "input"
  # Std of the learned tables (token and state positions, camera embeddings,
  # decoder queries, the CVAE's CLS token). torch's nn.Embedding, which ACT
  # uses, draws N(0, 1); 0.02 is BERT/ViT's.
  embed_init_std: float = 0.02
  pre_norm: bool = True  # False: ACT's post-norm layers (transformer.py)
  cvae_zero_init: bool = True  # the CVAE's latent head starts at zero (act.py)
  # Inputs: z-score the object state with the dataset's statistics, as the
  # joint positions are (data/normalization.py). Read raw (metres, a few cm
  # of spread), it cost ACT 30 points on jujube_pick (act.py).
  normalize_object_state: bool = True
  latent_dim: int = 32  # ACT's CVAE style latent
  cvae_enc_layers: int = 4
  backbone_width: int = 64  # ResNet-18 stem width; stages are 1x, 2x, 4x, 8x
  num_skills: int = 4  # K
  # Size of the per-skill posterior latent z_k. Kept small (ACT's style latent
  # size) so the posterior is a real bottleneck: W lifts it to `hidden`.
  skill_latent_dim: int = 32
  # Width of the shared space where g_tau(f_tau) and g_s(s_k) are compared (BSA).
  alignment_dim: int = 128
  interactor: str = "query_offset"  # see interactor.INTERACTORS
  # Softmax temperature of the router (1: the paper's softmax; below 1: sharper routing).
  router_temperature: float = 1.0
  # Where the plug sits (policy.py). 'encoder': between encoder and decoder,
  # h~ = sum_k r_k Interactor(h, s_k) feeds the whole decoder. 'decoder': on
  # the decoder's per-step outputs, with f_act the final norm and action
  # projection alone (parameter group 'action_proj', for ACT too), so few-shot
  # can retrain a light head in both arms. The router stays chunk-level.
  plug_site: str = "encoder"
  # What the interactor receives in training: s_k + W z_k with z 'sample'd
  # (the paper), z at its posterior 'mean', or s_k alone ('none': the posterior
  # serves only its KL and BSA terms). Inference always gives s_k.
  skill_offset: str = "sample"
  # What the router pools: 'all' scene tokens, 'no_style' (without the
  # training-only CVAE style token, index 0; the other tokens still saw it in
  # the encoder's attention), or 'zero_style' (the strict form: the tokens of a
  # second encoder pass with the style latent at zero, as at inference; one
  # more encoder pass per training step).
  router_input: str = "all"
  # State-only scenes: the object state as 'one' token (an MLP of all of it)
  # or one token 'per_object' (a shared MLP of each object's 7 numbers plus a
  # learned per-slot position: act.py).
  object_tokens: str = "one"
  # Ours: 'top1' routes to the argmax skill alone, in training (straight-
  # through: one-hot forward, softmax gradient) and at inference.
  routing: str = "soft"
  # Ours: 'posterior' fuses, in training, with a hard Gumbel-softmax sample of
  # the posterior's skill assignment softmax(traj_logits) (straight-through);
  # the router learns only by distillation to it (loss.distill) and routes at
  # inference.
  fusion_source: str = "router"
  dtype: str = "float32"  # compute dtype ('bfloat16' on GPUs); params stay float32

  def __post_init__(self):
    if self.policy not in POLICIES:
      raise ValueError(f"policy must be one of {POLICIES}, got {self.policy!r}")
    if self.positions not in POSITIONS:
      raise ValueError(f"positions must be one of {POSITIONS}, got {self.positions!r}")
    if self.hidden % self.heads:
      raise ValueError(f"hidden ({self.hidden}) must be divisible by heads ({self.heads})")
    if not self.router_temperature > 0:
      raise ValueError(f"router_temperature must be > 0, got {self.router_temperature}")
    if self.decoder_first_layer_only and self.dec_layers < 1:
      raise ValueError("decoder_first_layer_only needs at least one decoder layer")
    for name, valid in (("plug_site", PLUG_SITES), ("skill_offset", SKILL_OFFSETS),
                        ("router_input", ROUTER_INPUTS), ("object_tokens", OBJECT_TOKENS),
                        ("routing", ROUTINGS), ("fusion_source", FUSION_SOURCES)):
      if getattr(self, name) not in valid:
        raise ValueError(f"{name} must be one of {valid}, got {getattr(self, name)!r}")
    if self.object_tokens == "per_object" and self.use_images:
      raise ValueError("object_tokens='per_object' is for the state-only variant "
                       "(use_images=False): an image policy never reads the object state")
    if self.interactor not in INTERACTORS:
      raise ValueError(f"interactor must be one of {tuple(INTERACTORS)}, got {self.interactor!r}")

  @property
  def compute_dtype(self):
    return jnp.dtype(self.dtype)

  @property
  def is_skillplug(self) -> bool:
    return self.policy == "skillplug"
