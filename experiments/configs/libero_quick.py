"""make libero-quick   (python -m experiments.pipeline --config libero_quick --out results/libero_quick)

The paper's LIBERO protocol (issue 42) at smoke size: minutes on the 2-core
CPU, for the pipeline and CI-sized checks, not for a result. State-only
(LIBERO's proprioception, 16 numbers, and the 64-wide object state) with the
task's instruction as an encoder token, K = 8 as the paper's LIBERO runs.
Pretraining on LIBERO-Spatial from 2 scripted demonstrations per task, 500
steps; 5 paired trials per task (the benchmark's init states 0-4); then the
paper's cross-suite few-shot step at its smallest: one fine-tune on all of
LIBERO-Object (`fewshot.per=taskset`) from 2 demonstrations per task, 200
steps, router and action head (ACT: action head). One seed. The paper
pretrains on LIBERO-10 (`libero_cpu` does); the smoke run takes the suite
with the shortest episodes (220 steps against 520) and experts at 98-100%.
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig

# LIBERO's proprioception as the joint token reads it (envs/libero/layout.py), and the instruction's
# word table: LIBERO's vocabulary (81 ids with PAD and UNK, data/language.py) fits in 128 rows.
LIBERO_PROPRIO = ("joint_pos", "gripper_qpos", "eef_pos", "eef_quat")


def get_config() -> Experiment:
  model = ModelConfig(use_images=False, proprio=LIBERO_PROPRIO, joint_dim=16, instruction_vocab=128,
                      hidden=64, heads=4, ff=256, enc_layers=2, dec_layers=2, cvae_enc_layers=1,
                      plug=PlugConfig(num_skills=8, skill_latent_dim=16, alignment_dim=32))
  train = TrainConfig(preset="libero_quick", model=model, taskset="libero_spatial", demos=2, backend="mujoco",
                      batch_size=32, lr=1e-3, warmup_steps=50, max_steps=500, log_every=50, ckpt_every=250,
                      weight_decay=1e-4)
  return Experiment(train=train, seeds=(0,), trials=5, eval_batch=5,
                    fewshot=FewShot(taskset="libero_object", per="taskset", demos=2, steps=200))
