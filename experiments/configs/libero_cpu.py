"""make libero-cpu   (python -m experiments.pipeline --config libero_cpu --out results/libero_cpu)

The paper's LIBERO protocol (issue 42) at CPU scale, with the backbone this
project has (ACT, hidden 64) where the paper's is OpenVLA-OFT (7B, a frozen
pretrained language model). State: LIBERO's proprioception (16 numbers) and
the 64-wide object state (privileged: every object's pose and the fixtures'
joints), the instruction as an encoder token learned from scratch
(data/language.py), K = 8 as the paper's LIBERO runs; the `cpu` preset's
transformer. Not the paper's modality (cameras): on this CPU a 64x64 LIBERO
image costs about 38 ms of software GL, which makes the image protocol
(`libero_cpu_image`) hours per suite and arm. Demonstrations are our
scripted experts', 50 per task as LIBERO's count (LIBERO's own are human
teleoperations, on a hub we cannot reach: ours are smoother and more alike
than a person's). 3 seeds; 50 paired trials per task (the benchmark's init
states, as LIBERO's protocol).

Arms (each trains its own runs unless it adapts another's):
  long     multi-task on LIBERO-10 (the paper's "Long"), then the paper's
           few-shot step: per target suite (Object, Goal, Spatial) one
           fine-tune on all its tasks from 5 demonstrations per task
           (`fewshot.per=taskset`), 2,000 steps: ACT+SkillPlug its router
           and action head, ACT its action head
  object, goal, spatial   multi-task on that suite alone (no few-shot)
  long_act_adapter   (ours) ACT's runs of `long`, fine-tuned with its action
           head and an adapter of the router's size (width 35: 4,707
           parameters against the router's 4,680 at K = 8), so that a gain
           of the plug can be told from extra tuned capacity
  goal_act_adapter   (ours) multi-task ACT on LIBERO-Goal with an adapter of
           the plug's size between encoder and decoder, where the plug sits
           (width 459: 59,403 parameters against the skills', interactor's
           and router's 59,336; the posterior's 32,544 act in training only),
           trained from scratch: whether the plug's multi-task gain on Goal
           (docs/measurements/libero.md) is more than extra capacity

Run one arm at a time with `make libero-cpu VARIANTS=long` (it resumes).
"""

from skillplug_jax.experiment import Experiment, FewShot, Variant
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig

# 40k steps, not the 10k first set: on LIBERO-Spatial (seed 0, the first 10 init states a task) ACT
# went from 27% at 10k steps to 52% at 40k, its loss from 0.108 to 0.074 (docs/measurements/libero.md);
# about 40 steps/s on one of the 2 cores, 17-25 min a run
STEPS = 40_000
LIBERO_PROPRIO = ("joint_pos", "gripper_qpos", "eef_pos", "eef_quat")
ADAPTER = "model.adapter_width=35"  # 129 w + 192 parameters at hidden 64: 4,707 (the router: 4,680)
PLUG_SIZED_ADAPTER = 459  # 59,403 parameters: the plug's skills, interactor and router have 59,336


def get_config() -> Experiment:
  model = ModelConfig(use_images=False, proprio=LIBERO_PROPRIO, joint_dim=16, instruction_vocab=128,
                      hidden=64, heads=4, ff=256, enc_layers=2, dec_layers=2, cvae_enc_layers=1,
                      plug=PlugConfig(num_skills=8, skill_latent_dim=16, alignment_dim=32))
  train = TrainConfig(preset="libero_cpu", model=model, taskset="libero_10", demos=50, backend="mujoco",
                      batch_size=32, lr=1e-3, warmup_steps=200, lr_schedule="cosine", max_steps=STEPS,
                      log_every=100, ckpt_every=1000, weight_decay=1e-4)
  fewshot = FewShot(taskset="libero_object,libero_goal,libero_spatial", per="taskset", demos=5, steps=2000)
  return Experiment(
      train=train, seeds=(0, 1, 2), trials=50, eval_batch=50, fewshot=fewshot,
      variants=(
          Variant("long", (), "multi-task on LIBERO-10, then 5-shot per suite"),
          Variant("object", ("train.taskset=libero_object", "run_fewshot=false"), "multi-task on LIBERO-Object"),
          Variant("goal", ("train.taskset=libero_goal", "run_fewshot=false"), "multi-task on LIBERO-Goal"),
          Variant("spatial", ("train.taskset=libero_spatial", "run_fewshot=false"), "multi-task on LIBERO-Spatial"),
          Variant("long_act_adapter", ("policies=act", "fewshot.trainable.act=action_head,adapter",
                                       f"fewshot.train_overrides={ADAPTER}"),
                  "ACT, action head + adapter of the router's size (ours)", adapts="long"),
          Variant("goal_act_adapter", ("train.taskset=libero_goal", "run_fewshot=false", "policies=act",
                                       f"train.model.adapter_width={PLUG_SIZED_ADAPTER}"),
                  "ACT with an adapter of the plug's size, multi-task on LIBERO-Goal (ours)"),
      ))
