"""make paper-cpu   (python -m experiments.pipeline --config cpu --out results/paper_cpu)

The paper's protocol at CPU scale: state only (joint positions and object
state), ACT and ACT+SkillPlug (K=4) on discoverse7, 3 training seeds, 50
paired trials per task; few-shot adaptation of every seed to each of the 4
unseen tasks from 10 demonstrations. One pretraining run takes about 10
minutes on one core of this project's 2-core CPU, and the two workers run two
of them side by side.

How it was sized (ACT, seed 0, discoverse7, 50 paired trials per task, one
core each; docs/results/cpu_preset_search/): the quick preset (hidden 64, 10
demos, 1,500 steps) averages 41.9 ± 0.5% over 3 seeds. With 100 demos per
task and a cosine decay, hidden 64 for 11k steps reached 73.4% (384 s),
hidden 128 / FF 512 for 6k steps 74.6% (622 s), hidden 64 for 16k steps
77.1% (528 s): that one, the cheapest at its success. Few-shot fine-tunes
for the paper's 6000 ACT epochs (fewshot.steps=0: 1,875 steps of batch 32
over 10 demonstrations).
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig


def get_config() -> Experiment:
  model = ModelConfig(use_images=False, hidden=64, heads=4, ff=256, enc_layers=2, dec_layers=2,
                      cvae_enc_layers=1, plug=PlugConfig(num_skills=4, skill_latent_dim=16, alignment_dim=32))
  train = TrainConfig(preset="cpu", model=model, demos=100, batch_size=32, lr=1e-3, warmup_steps=200,
                      lr_schedule="cosine", max_steps=16_000, log_every=100, ckpt_every=2000)
  return Experiment(train=train, seeds=(0, 1, 2), trials=50, fewshot=FewShot(demos=10, steps=0))
