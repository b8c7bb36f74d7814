"""make plug-readings   (python -m experiments.pipeline --config plug_readings --out results/plug_readings --publish docs/results/plug_readings/<date>)

Issue 43: the two readings of the paper never run on discoverse7, and a
capacity-matched few-shot baseline. The `cpu` preset, one token per object
for every arm (the strongest ACT of issue 27), 3 seeds, 50 paired trials,
multi-task and few-shot (10 demonstrations per unseen task). Every arm also
loads the mined phase of each step (train.skill_labels=tabletop_phases) at
weight 0 (loss.router_label stays 0): a diagnostic only, so that the training
log holds the routing's information about the phase (diag/label_skill_mi_norm)
beside its entropy, effective skills and task NMI at every logged step.

Pretrained arms (each trains its own runs):
  act           ACT with the split head (f_act = the final norm and projection alone,
                group action_proj); few-shot: the heavy head (the whole decoder:
                action_head + action_proj)
  plug_encoder  ACT+SkillPlug in the paper's configuration as first built: the plug on
                the encoder's tokens; few-shot: heavy head + router (the paper's groups)
  plug_decoder  ACT+SkillPlug on the decoder's per-step outputs (the literal reading of
                the paper's temporal average); few-shot: light head + router
  plug_decoder_4x  the same at 4x the steps (64k, its own cosine schedule), seed 0,
                multi-task only: is a router that ends uniform under-trained?
Arms that adapt another arm's runs (`Variant.adapts`: no training of their own; their
fine-tunes go beside the source's, RUN_fewshot_<arm>/):
  act_light                   ACT, light head (action_proj) alone
  act_adapter                 ACT, light head + a residual bottleneck adapter of the
                              router's size before f_act (ours: model.adapter_width=32,
                              4,320 parameters against the router's 4,420), added at
                              the fine-tune with its output at zero
  plug_decoder_frozen_router  the plug_decoder runs, light head alone (router frozen)
  plug_decoder_uniform        the same with the routing replaced by 1/K (fine-tune and
                              evaluation: model.plug.fusion_weights=uniform)

The decision rule, fixed before the runs (docs/measurements/skill_library.md,
"Issue 43"): the plug's mechanism helps few-shot if plug_decoder minus
act_light exceeds 2 SE of the paired difference over seeds, plug_decoder
beats plug_decoder_frozen_router, and plug_decoder_uniform scores below
plug_decoder.
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load

# Every arm: one token per object, and the mined phase loaded as a diagnostic (weight 0).
COMMON = ("train.model.object_tokens=per_object", "train.skill_labels=tabletop_phases")
DECODER = "train.model.plug.site=decoder"


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu", Path(__file__).parent), seeds=(0, 1, 2),
      variants=(
          Variant("act", COMMON + (DECODER, "policies=act", "fewshot.trainable.act=action_head,action_proj"),
                  "ACT, heavy head"),
          Variant("plug_encoder", COMMON + ("policies=skillplug",),
                  "ACT+SkillPlug at the encoder, heavy head + router"),
          Variant("plug_decoder", COMMON + (DECODER, "policies=skillplug",
                                            "fewshot.trainable.skillplug=action_proj,router"),
                  "ACT+SkillPlug at the decoder, light head + router"),
          Variant("plug_decoder_4x", COMMON + (DECODER, "policies=skillplug", "seeds=0", "train.max_steps=64000",
                                               "run_fewshot=false"),
                  "ACT+SkillPlug at the decoder, 4x the steps (routing over training; seed 0, multi-task)"),
          Variant("act_light", COMMON + (DECODER, "policies=act", "fewshot.trainable.act=action_proj"),
                  "ACT, light head", adapts="act"),
          Variant("act_adapter", COMMON + (DECODER, "policies=act", "fewshot.trainable.act=action_proj,adapter",
                                           "fewshot.train_overrides=model.adapter_width=32"),
                  "ACT, light head + adapter of the router's size (ours)", adapts="act"),
          Variant("plug_decoder_frozen_router", COMMON + (DECODER, "policies=skillplug",
                                                          "fewshot.trainable.skillplug=action_proj"),
                  "ACT+SkillPlug at the decoder, light head (router frozen)", adapts="plug_decoder"),
          Variant("plug_decoder_uniform", COMMON + (DECODER, "policies=skillplug",
                                                    "fewshot.trainable.skillplug=action_proj",
                                                    "fewshot.train_overrides=model.plug.fusion_weights=uniform"),
                  "ACT+SkillPlug at the decoder, light head, uniform routing", adapts="plug_decoder"),
      ))
