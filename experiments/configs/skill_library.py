"""python -m experiments.pipeline --config skill_library --variants NAMES --out results/skill_library --publish docs/results/skill_library/<date>

Issue 27's screen on the `cpu` preset: readings of the paper's text and remedies
of ours against the degenerate library of `make paper-cpu` (uniform routing,
skills that cancel), each one named variant, seed 0, multi-task and few-shot,
read beside the committed `cpu` runs (docs/results/paper_cpu/summary.json:
ACT and the paper's configuration, seeds 0-2). The toy problem
(`make toy-skills`) screens first, in minutes; the variants that route there
run here. Finalists then run seeds 0-2 (`--set seeds=0,1,2`).

Readings within the paper's text:
  per_object  the object state as one token per object, ACT and ACT+SkillPlug
              (act_per_object: its ACT arm alone)
  tokens      the skill as a key/value token (interactor=skill_tokens), s_k without the
              posterior's sampled offset (plug.skill_offset=none), the router blind to the
              training-only style token (plug.router_input=no_style)
  decoder     the plug on the decoder's per-step outputs, f_act the action projection;
              few-shot retrains a light head in both arms (ACT: action_proj; ACT+SkillPlug:
              action_proj and router), so this variant runs its own ACT arm
Remedies of ours (not the paper's; the screen's posterior-fusion and top-1 arms were removed in
issue 40, their results reproducible at commit 5dddeed: docs/training.md):
  usage       + 0.5 (H(mean r) - mean H(r)) penalty: routing that is used and decisive
  usage_sq    usage, with L_SD on squared cosines weighted by r_k r_j (antipodal pairs
              become the worst case, and unused skills cannot satisfy it)
  per_object_usage  one token per object (a reading; its own ACT arm is variant
              per_object) with the usage term: on the toy problem (seed 0) the one
              skill-library variant that routed decisively over ~4 skills and kept
              its ACT arm's multi-task success within a few points
  per_object_phases  one token per object, the router trained (cross-entropy, weight 1)
              to predict the manipulation phase mined from each demonstration
              (data/segments.py: free motion, grasp, transport, release); on the
              toy, the same training with the primitive (the oracle) made each
              skill one primitive and the router alone adaptable
  per_object_phases_sd0, per_object_phases_sq  the same without the SD term, and with
              it on squared cosines weighted by r_k r_j (per_object_phases, seed 0:
              u_k at the cosine floor -1/3, the fused feature dominated by the skills)
  per_object_phases_w01  the phase term at weight 0.1 (routing less decisive, so that the
              decoder keeps deciding from the scene where the router errs)
"""

import dataclasses
from pathlib import Path

from skillplug_jax.experiment import Experiment, Variant, load

USAGE = ("train.loss.usage=0.5",)
PER_OBJECT = "train.model.object_tokens=per_object"
# the router trained to predict each step's manipulation phase, mined from the demonstrations
# (data/segments.py tabletop_phases: free motion, grasp, transport, release)
PHASES = ("train.loss.router_label=1.0", "train.skill_labels=tabletop_phases")


def get_config() -> Experiment:
  return dataclasses.replace(
      load("cpu", Path(__file__).parent), policies=("skillplug",), seeds=(0,),
      reference="docs/results/paper_cpu/summary.json",
      variants=(
          Variant("tokens", ("train.model.plug.interactor=skill_tokens", "train.model.plug.skill_offset=none",
                             "train.model.plug.router_input=no_style"), "skill tokens, no z offset, no style"),
          Variant("decoder", ("train.model.plug.site=decoder", "policies=act,skillplug",
                              "fewshot.trainable.act=action_proj",
                              "fewshot.trainable.skillplug=action_proj,router"), "plug on the decoder"),
          Variant("usage", USAGE, "usage 0.5 (ours)"),
          Variant("usage_sq", USAGE + ("train.loss.sd_kind=squared", "train.loss.sd_usage_weighted=true"),
                  "usage 0.5 + squared SD (ours)"),
          Variant("per_object", (PER_OBJECT, "policies=act,skillplug"), "one token per object"),
          Variant("act_per_object", (PER_OBJECT, "policies=act"), "ACT, one token per object"),
          Variant("per_object_usage", (PER_OBJECT,) + USAGE, "one token per object + usage 0.5 (ours)"),
          Variant("per_object_phases", (PER_OBJECT,) + PHASES, "one token per object, router trained on "
                  "mined phases (ours)"),
          Variant("per_object_phases_w01", (PER_OBJECT, "train.loss.router_label=0.1",
                                             "train.skill_labels=tabletop_phases"),
                  "one token per object, router on mined phases at weight 0.1 (ours)"),
          Variant("per_object_phases_sd0", (PER_OBJECT,) + PHASES + ("train.loss.sd=0",),
                  "one token per object, router on mined phases, no SD term (ours)"),
          Variant("per_object_phases_sq", (PER_OBJECT,) + PHASES + ("train.loss.sd_kind=squared",
                                                                     "train.loss.sd_usage_weighted=true"),
                  "one token per object, router on mined phases, squared SD r-weighted (ours)"),
      ))
