"""make quickstart   (python -m experiments.quickstart: this config end to end, one seed)

State-only and small, for smoke runs: minutes on a laptop CPU. 10
demonstrations per task, 1,500 steps of batch 32 at lr 1e-3; one seed, 10
paired trials per task; few-shot 500 steps from 10 demonstrations.
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig


def get_config() -> Experiment:
  model = ModelConfig(use_images=False, hidden=64, heads=4, ff=256, enc_layers=2, dec_layers=2,
                      cvae_enc_layers=1, plug=PlugConfig(num_skills=4, skill_latent_dim=16, alignment_dim=32))
  train = TrainConfig(preset="quick", model=model, demos=10, batch_size=32, lr=1e-3, warmup_steps=100,
                      max_steps=1500, log_every=50, ckpt_every=500, weight_decay=1e-4)
  return Experiment(train=train, seeds=(0,), trials=10, fewshot=FewShot(steps=500))
