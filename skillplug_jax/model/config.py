"""Model configuration: one frozen dataclass whose defaults are the paper's model.

The presets (quick, cpu, budget, paper) are experiment configs in
experiments/configs/: each names the few fields it changes.
"""

from __future__ import annotations

import dataclasses
from typing import Tuple

import jax.numpy as jnp

from envs.names import CAMERAS  # cheap: not the suite (envs/__init__.py)
from skillplug_jax import validation
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
DTYPES = ("float32", "bfloat16", "float16")

# What a run recorded before a field existed meant: config.json files written
# before issue 12 lack these keys and must load as the model they trained.
LEGACY_DEFAULTS = dict(positions="input", embed_init_std=1.0, pre_norm=True,
                       cvae_zero_init=True, normalize_object_state=False)


_count, _number, _one_of = validation.count, validation.number, validation.one_of
# What each field allows (layer counts may be 0 where the stack handles none: the encoder's
# tokens are then their projections; the decoder needs a layer to read).
_RULES = dict(
    policy=_one_of(POLICIES), use_images=validation.flag(),
    cameras=validation.each(_one_of(CAMERAS), nonempty=True, distinct=True),
    image_size=validation.each(_count(1), length=2), joint_dim=_count(1), action_dim=_count(1),
    chunk=_count(1), hidden=_count(1), heads=_count(1), ff=_count(1), enc_layers=_count(0),
    dec_layers=_count(1), decoder_first_layer_only=validation.flag(), dropout=_number(0, 1),
    positions=_one_of(POSITIONS), embed_init_std=_number(0), pre_norm=validation.flag(),
    cvae_zero_init=validation.flag(), normalize_object_state=validation.flag(), latent_dim=_count(1),
    cvae_enc_layers=_count(0), backbone_width=_count(1),
    backbone_stages=validation.each(_count(1), nonempty=True), num_skills=_count(1),
    skill_latent_dim=_count(1), alignment_dim=_count(1), interactor=_one_of(INTERACTORS),
    router_temperature=_number(above=0), plug_site=_one_of(PLUG_SITES),
    skill_offset=_one_of(SKILL_OFFSETS), router_input=_one_of(ROUTER_INPUTS),
    object_tokens=_one_of(OBJECT_TOKENS), routing=_one_of(ROUTINGS),
    fusion_source=_one_of(FUSION_SOURCES), router_cue_slots=_count(0), dtype=_one_of(DTYPES))
_RELATIONS = (
    validation.Relation("hidden", lambda c: c.hidden % c.heads == 0,
                        lambda c: f"divisible by heads ({c.heads})"),
    validation.Relation("object_tokens", lambda c: not (c.use_images and c.object_tokens == "per_object"),
                        lambda c: "'one' for an image policy (it never reads the object state; "
                                  "'per_object' is for the state-only variant, use_images=False)"),
)


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
  # Basic blocks per ResNet stage; (2, 2, 2, 2) is ResNet-18. Fewer stages keep a finer
  # map (64x64 images: 2x2 cells with 4 stages, 4x4 with 3), fewer blocks cost less.
  backbone_stages: Tuple[int, ...] = (2, 2, 2, 2)
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
  # Ours: the last N object-state slots (7 numbers each) are a cue that only
  # the router reads (added to its pooled input through a Dense layer); the
  # encoder sees them zeroed. The decoder can then learn what the cue says only
  # through the routing: a bottleneck that makes the routing carry behaviour
  # (docs/measurements/skill_library.md). 0: the paper's (both read everything).
  # ACT, which has no router, reads everything either way.
  router_cue_slots: int = 0
  dtype: str = "float32"  # compute dtype ('bfloat16' on GPUs); params stay float32

  def __post_init__(self):
    validation.check(self, "model.", _RULES, _RELATIONS)

  @property
  def compute_dtype(self):
    return jnp.dtype(self.dtype)

  @property
  def is_skillplug(self) -> bool:
    return self.policy == "skillplug"
