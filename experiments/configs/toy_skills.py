"""python -m experiments.pipeline --config toy_skills --out results/toy_skills

The skill library's fast screen and regression test (issue 27, `make toy-skills`): ACT and
ACT+SkillPlug variants on the toy point-robot problem (envs/toy_skills.py), whose four
behaviour primitives are known, in minutes on a CPU. The pipeline runs it as any config
(every variant; `--variants paper` for ACT and the paper's ACT+SkillPlug alone, what
`make toy-skills` runs by default; `--set seeds=0,1,2`); what differs is the data and the evaluator: the
demonstrations are made in memory (skillplug_jax/train/toy.py: 500 per seen task, the 6 seen
tasks multi-task, 10 per unseen task few-shot) and the evaluation is the toy's jitted closed
loop (skillplug_jax/evaluate/toy_rollout.py), whose results carry the routing statistics
against the primitive label (NMI against the primitive, task, stage, quadrant), the stage
progress, and per run the fixed-skill probe and zero-shot; the report adds a toy section.

Few-shot: from the multi-task parameters, one fine-tune per unseen task of the paper's groups
(ACT: action_head; ACT+SkillPlug: action_head + router; with model.plug.site=decoder:
action_proj, and action_proj + router), 300 steps (about 80 epochs of its 10 demos).

Variants (each this config with its overrides; `paper`, `decoder` and `per_object` run ACT and
ACT+SkillPlug, the others ACT+SkillPlug alone). Results of variants since removed with their
arms (posterior, top1, top1_only, load_balance, router_z, decoder_top1, cue_top1,
cue_top1_router, cue_per_object_top1) are in docs/results/toy_skills/ (commit 5dddeed).
The oracle variants are a diagnostic, not a method: they read the primitive label, in
pretraining and in the few-shot fine-tune (the `_unlabelled` one in pretraining only).
"""

from envs import toy_skills as toy
from skillplug_jax.experiment import Experiment, FewShot, Variant
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig

BOTH = "policies=act,skillplug"
PLUG = "policies=skillplug"
USAGE = ("train.loss.usage=0.5",)
ORACLE = "train.loss.router_label=1.0"
MINED = "train.skill_labels=toy_targets"
CUE = f"train.model.plug.router_cue_slots={toy.OBJECT_STATE_DIM // toy.SLOT - 3}"  # the slots after the 3 landmarks
PER_OBJECT = "train.model.object_tokens=per_object"
DECODER = ("train.model.plug.site=decoder", "fewshot.trainable.act=action_proj",
           "fewshot.trainable.skillplug=action_proj,router")
TOKENS = ("train.model.plug.interactor=skill_tokens", "train.model.plug.skill_offset=none",
          "train.model.plug.router_input=no_style")
ROUTER_ONLY = "fewshot.trainable.skillplug=router"


def toy_train_config() -> TrainConfig:
  """The toy's model and optimisation: the quick preset's sizes (FF 128), chunk 8, no dropout, raw inputs.

  3000 steps of batch 64: ACT reaches 85-90% multi-task (held-out position L1 0.05); batch 128
  or FF 256 gained a few points for twice the time. 500 demonstrations per seen task, not 50:
  with 50 (300 landmark layouts) ACT memorised the layouts (train L1 0.02, closed loop 8%);
  with 500 held-out L1 equals train L1. log_every: training steps per jitted call (one lax.scan).

  Dropout 0: the reaches need targets within 0.1, and at dropout 0.1 ACT's position L1 after
  3000 steps was 0.1 (0.04 without).

  Inputs and actions are not normalised: they already lie in [-1, 1] (gripper
  {0, 1}, the task's program and stage one-hot), and z-scoring one-hot bits that are rare in the
  seen demos (std clipped to 0.01) would feed the frozen encoder values of up to 100.
  """
  model = ModelConfig(use_images=False, joint_dim=toy.JOINT_DIM, action_dim=toy.ACTION_DIM, chunk=8,
                      hidden=64, heads=4, ff=128, enc_layers=2, dec_layers=2, cvae_enc_layers=1,
                      plug=PlugConfig(num_skills=4, skill_latent_dim=16, alignment_dim=32),
                      normalize_object_state=False, dropout=0.0)
  return TrainConfig(preset="toy_skills", model=model, taskset=toy.TASKSET, demos=500, batch_size=64, lr=1e-3,
                     warmup_steps=100, lr_schedule="cosine", max_steps=3000, weight_decay=1e-4, log_every=100)


VARIANTS = (
    Variant("paper", (BOTH,), "ACT and ACT+SkillPlug (paper)"),
    # readings within the paper's text
    Variant("decoder", (BOTH,) + DECODER, "plug on the decoder (ACT: light head, action_proj)"),
    Variant("tokens", (PLUG,) + TOKENS, "skill tokens, no z offset, no style"),
    Variant("skill_tokens", (PLUG, "train.model.plug.interactor=skill_tokens"), "skill-token interactor"),
    Variant("film", (PLUG, "train.model.plug.interactor=film"), "FiLM interactor"),
    Variant("z_mean", (PLUG, "train.model.plug.skill_offset=mean"), "z at its mean"),
    Variant("z_none", (PLUG, "train.model.plug.skill_offset=none"), "no z offset"),
    Variant("no_style", (PLUG, "train.model.plug.router_input=no_style"), "router without style"),
    Variant("per_object", (BOTH, PER_OBJECT), "token per object"),
    # remedies beyond the paper (ours)
    Variant("usage", (PLUG,) + USAGE, "usage 0.5 (ours)"),
    Variant("usage_sq", (PLUG,) + USAGE + ("train.loss.sd_kind=squared", "train.loss.sd_usage_weighted=true"),
            "usage 0.5 + squared SD, r-weighted (ours)"),
    Variant("sd_squared", (PLUG, "train.loss.sd_kind=squared"), "SD on squared cosines (ours)"),
    Variant("sd_gram", (PLUG, "train.loss.sd_kind=gram"), "SD on the Gram matrix (ours)"),
    Variant("sd_gram_usage", (PLUG, "train.loss.sd_kind=gram", "train.loss.sd_usage_weighted=true"),
            "SD Gram, r-weighted (ours)"),
    Variant("decoder_usage", (PLUG,) + DECODER + USAGE, "decoder + usage 0.5 (ours)"),
    Variant("tokens_usage", (PLUG,) + TOKENS + USAGE, "skill tokens, no z, no style + usage 0.5 (ours)"),
    Variant("per_object_usage", (PLUG, PER_OBJECT) + USAGE, "token per object + usage 0.5 (ours)"),
    # the task cue (program and stage) read by the router alone: the decoder learns what to do
    # next only through the routing (ours)
    Variant("cue", (PLUG, CUE), "cue to the router only (ours)"),
    # ... with one token per landmark, so that a skill's query offset can pick which one to reach
    Variant("cue_per_object", (PLUG, CUE, PER_OBJECT), "cue to the router only, token per object (ours)"),
    Variant("cue_per_object_sq", (PLUG, CUE, PER_OBJECT, "train.loss.sd_kind=squared"),
            "cue to the router only, token per object, squared SD (ours)"),
    Variant("cue_tokens", (PLUG, CUE, PER_OBJECT, "train.model.plug.interactor=skill_tokens",
                           "train.model.plug.skill_offset=none"),
            "cue to the router only, token per object, skill tokens (ours)"),
    # oracle routing: what the library does when the router has the partition the unsupervised
    # variants never find
    Variant("oracle", (PLUG, ORACLE), "router told the primitive (oracle)"),
    Variant("oracle_per_object", (PLUG, ORACLE, PER_OBJECT), "router told the primitive, token per object (oracle)"),
    Variant("oracle_cue_per_object", (PLUG, ORACLE, CUE, PER_OBJECT),
            "router told the primitive, cue to the router only, token per object (oracle)"),
    Variant("oracle_cue_per_object_router", (PLUG, ORACLE, CUE, PER_OBJECT, ROUTER_ONLY),
            "router told the primitive, cue to the router only, token per object; few-shot: router (oracle)"),
    # ... and the few-shot router trained by reconstruction alone: the unseen tasks' labels unused
    Variant("oracle_cue_per_object_router_unlabelled",
            (PLUG, ORACLE, CUE, PER_OBJECT, ROUTER_ONLY, "fewshot.train_overrides=loss.router_label=0"),
            "router told the primitive in pretraining only, cue to the router only, token per object; "
            "few-shot: router, no labels (oracle)"),
    # labels mined from the demonstrations (data/segments.py: the landmark the commanded target
    # is nearest, or the gripper while it is commanded to switch), no ground truth read (ours)
    Variant("mined", (PLUG, ORACLE, MINED), "router trained on mined labels (ours)"),
    Variant("mined_cue_per_object_router", (PLUG, ORACLE, MINED, CUE, PER_OBJECT, ROUTER_ONLY),
            "router trained on mined labels, cue to the router only, token per object; few-shot: router (ours)"),
)


def get_config() -> Experiment:
  return Experiment(
      train=toy_train_config(), policies=("act", "skillplug"), seeds=(0,), trials=50, eval_seed=1000,
      fewshot=FewShot(taskset=toy.FEWSHOT_TASKSET, demos=10, steps=300),
      workers=1,  # in this process: the jitted trainers and closed loops are shared by seeds and variants
      variants=VARIANTS)

