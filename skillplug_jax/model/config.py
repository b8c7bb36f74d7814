"""Model configuration: one frozen dataclass whose defaults are the paper's model.

The presets (quick, cpu, budget, paper) are experiment configs in
experiments/configs/: each names the few fields it changes.
"""

from __future__ import annotations

import dataclasses
from typing import Tuple

import jax.numpy as jnp

from envs.names import CAMERAS, LIBERO_CAMERAS, LIBERO_PROPRIO  # cheap: not the suite (envs/__init__.py)
from skillplug_jax import validation
from skillplug_jax.model.plug import PlugConfig

POLICIES = ("act", "skillplug")
# The cameras a policy may read: our tabletop's and LIBERO's (envs/libero/layout.py).
CAMERA_NAMES = CAMERAS + LIBERO_CAMERAS
# The proprioception fields a policy may read and their widths: DISCOVERSE datasets hold joint_pos
# (7: six joints and the gripper), LIBERO's joint_pos (the arm's 7 joints) and the rest.
PROPRIO_WIDTHS = dict(LIBERO_PROPRIO)
POSITIONS = ("input", "qk")
# A reading of the paper's text (issue 27); the first value is the paper's configuration as first
# built, and the default.
OBJECT_TOKENS = ("one", "per_object")
DTYPES = ("float32", "bfloat16")

# What a run recorded before a field existed meant: config.json files written
# before issue 12 lack these keys and must load as the model they trained.
LEGACY_DEFAULTS = dict(positions="input", embed_init_std=1.0, pre_norm=True,
                       cvae_zero_init=True, normalize_object_state=False)
# Runs written before the plug had its own config (issue 40) hold its settings flat in `model`:
# old name -> the field of `PlugConfig` it is now.
LEGACY_PLUG_FIELDS = dict(num_skills="num_skills", skill_latent_dim="skill_latent_dim",
                          alignment_dim="alignment_dim", interactor="interactor",
                          router_temperature="router_temperature", plug_site="site",
                          skill_offset="skill_offset", router_input="router_input",
                          router_cue_slots="router_cue_slots")
# Arms removed in the house clean-up (issue 40), measured dead: an old run that recorded one of
# them at this value trained what today's code builds; any other value cannot be rebuilt here.
# Their results keep the commit that made them (docs/training.md).
REMOVED_ARMS = {"model.routing": "soft", "model.fusion_source": "router", "loss.load_balance": 0.0,
                "loss.router_z": 0.0}
REMOVED_AT = "5dddeed"  # the last commit with those arms, router_input='zero_style' and dtype='float16'
# What a few-shot fine-tune may change in its source's model (dotted, under `model.`), at its
# source's value when the source has none: an adapter added with its output at zero, and routing
# replaced by fixed weights. Parameter groups they add start from their initialisation.
FINE_TUNE_ADDITIONS = {"adapter_width": 0, "plug.fusion_weights": "router"}  # the last commit with those arms, router_input='zero_style' and dtype='float16'


_count, _number, _one_of = validation.count, validation.number, validation.one_of
# What each field allows (layer counts may be 0 where the stack handles none: the encoder's
# tokens are then their projections; the decoder needs a layer to read).
_RULES = dict(
    policy=_one_of(POLICIES), use_images=validation.flag(),
    cameras=validation.each(_one_of(CAMERA_NAMES), nonempty=True, distinct=True),
    proprio=validation.each(_one_of(tuple(PROPRIO_WIDTHS)), nonempty=True, distinct=True),
    image_size=validation.each(_count(1), length=2), joint_dim=_count(1), action_dim=_count(1),
    chunk=_count(1), hidden=_count(1), heads=_count(1), ff=_count(1), enc_layers=_count(0),
    dec_layers=_count(1), decoder_first_layer_only=validation.flag(), dropout=_number(0, 1),
    positions=_one_of(POSITIONS), embed_init_std=_number(0), pre_norm=validation.flag(),
    cvae_zero_init=validation.flag(), normalize_object_state=validation.flag(), latent_dim=_count(1),
    cvae_enc_layers=_count(0), backbone_width=_count(1),
    backbone_stages=validation.each(_count(1), nonempty=True), object_tokens=_one_of(OBJECT_TOKENS),
    adapter_width=_count(0), dtype=_one_of(DTYPES), instruction_vocab=_count(0), instruction_words=_count(1))
_RELATIONS = (
    validation.Relation("joint_dim", lambda c: c.proprio == ("joint_pos",)
                        or c.joint_dim == sum(PROPRIO_WIDTHS[k] for k in c.proprio),
                        lambda c: f"the width of proprio {c.proprio} "
                                  f"({sum(PROPRIO_WIDTHS.get(k, 0) for k in c.proprio)})"),
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
  and 7 decoder layers, 32-D CVAE style latent, chunk 25) with K=4 skills
  (`plug`: the SkillPlug's own settings, model/plug.py).
  """
  policy: str = "skillplug"  # 'act' | 'skillplug'
  use_images: bool = True  # False: the state-only variant (object_state token)
  cameras: Tuple[str, ...] = ("side", "wrist")  # batch keys are f"{cam}_rgb"
  image_size: Tuple[int, int] = (64, 64)  # (H, W) of the rendered images
  # The proprioception the joint token reads, concatenated in this order (joint_dim wide): our
  # tabletop's joint_pos; LIBERO policies read ("joint_pos", "gripper_qpos", "eef_pos", "eef_quat"), 16.
  proprio: Tuple[str, ...] = ("joint_pos",)
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
  # State-only scenes: the object state as 'one' token (an MLP of all of it)
  # or one token 'per_object' (a shared MLP of each object's 7 numbers plus a
  # learned per-slot position: act.py).
  object_tokens: str = "one"
  # Ours (issue 43): > 0 adds a residual bottleneck of this width before f_act (group 'adapter',
  # model/act.py's Adapter): with plug.site='decoder' on the decoder's steps, at the encoder site
  # (issue 42) on the tokens the whole action head reads. A few-shot fine-tune may add it to a
  # source that has none (`FINE_TUNE_ADDITIONS`). 32 at hidden 64: 4,320 parameters, the router's
  # 4,420 at K = 4.
  adapter_width: int = 0
  # The task's instruction as one more encoder token (ours; issue 42: LIBERO-Goal's tasks share a
  # scene): 0 reads none; > 0 is the rows of a word-embedding table learned from scratch
  # (data/language.py: the run's vocabulary must fit), the words mean-pooled and projected.
  # ACT+SkillPlug's router pools the encoder's tokens, so it sees the instruction too.
  instruction_vocab: int = 0
  instruction_words: int = 24  # the longest instruction it reads, in words (LIBERO's: 19)
  plug: PlugConfig = PlugConfig()
  dtype: str = "float32"  # compute dtype ('bfloat16' on GPUs); params stay float32

  def __post_init__(self):
    validation.check(self, "model.", _RULES, _RELATIONS)

  @property
  def compute_dtype(self):
    return jnp.dtype(self.dtype)

  @property
  def is_skillplug(self) -> bool:
    return self.policy == "skillplug"

  @property
  def split_head(self) -> bool:
    """Whether f_act is the final norm and action projection alone (group 'action_proj'), for
    both policies: with the plug on the decoder's steps (`plug.site`), so that ACT's light-head
    arm fine-tunes what the plug's does."""
    return self.plug.site == "decoder"


def _tuples(d: dict) -> dict:
  return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def from_dict(d: dict) -> ModelConfig:
  """A ModelConfig as a run's config.json holds it, written by this version or an older one:
  fields added since take the values that reproduce what was trained (LEGACY_DEFAULTS), the plug's
  flat fields of before issue 40 move into `plug` (LEGACY_PLUG_FIELDS), and a removed arm is
  named (`check_removed`)."""
  d = {**LEGACY_DEFAULTS, **d}
  plug = dict(d.pop("plug", {}))
  for old, new in LEGACY_PLUG_FIELDS.items():
    if old in d:
      plug[new] = d.pop(old)
  check_removed({f"model.{k}": d.pop(k) for k in ("routing", "fusion_source") if k in d})
  if plug.get("router_input") == "zero_style" or d.get("dtype") == "float16":
    raise ValueError(f"this run was trained with an arm removed in issue 40 (model.router_input="
                     f"{plug.get('router_input')!r}, model.dtype={d.get('dtype')!r}); load it with the code "
                     f"at commit {REMOVED_AT}")
  return ModelConfig(**_tuples(d), plug=PlugConfig(**plug))


def check_removed(settings: dict) -> None:
  """Raise, naming the commit to use, for a removed arm (REMOVED_ARMS) set to anything but the
  value that today's code reproduces; `settings`: dotted name -> recorded value."""
  used = {k: v for k, v in settings.items() if k in REMOVED_ARMS and v != REMOVED_ARMS[k]}
  if used:
    raise ValueError(f"this run was trained with an arm removed in issue 40 ("
                     f"{', '.join(f'{k}={v!r}' for k, v in used.items())}); load it with the code at "
                     f"commit {REMOVED_AT}")


def legacy_name(name: str) -> str:
  """A dotted setting's name as today's configs spell it ('model.num_skills' -> 'model.plug.num_skills')."""
  head, _, field = name.partition(".")
  if head == "model" and field in LEGACY_PLUG_FIELDS:
    return f"model.plug.{LEGACY_PLUG_FIELDS[field]}"
  return name
