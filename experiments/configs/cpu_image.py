"""make paper-cpu-image   (python -m experiments.pipeline --config cpu_image --out results/paper_cpu_image)

The paper's modality at CPU scale: both cameras (side, wrist) at 64x64, a
small ResNet with GroupNorm shared by the cameras (stem width 16, three
stages of one basic block: a 4x4 map, 16 tokens a camera), the `cpu`
preset's transformer (hidden 64), 100 demonstrations per task rendered on
MuJoCo's C engine, 10k steps of batch 32. One pretraining run took 22 min on
one core of this project's 2-core CPU.

How it was sized (ACT, seed 0, discoverse7, 50 paired trials per task, one
core each, two candidates side by side; docs/measurements/images.md and
docs/results/cpu_image_search/): width 16 / stages 1,1,1 / 10k steps 50.6%
(1,318 s); ResNet-18 of width 16 (2x2 map) / 8k steps 52.3% (1,452 s);
width 16 / stages 2,2,2 / 7k steps 47.4% (1,241 s); width 8 / stages 1,1,1 /
13k steps 44.6% (1,427 s). The first is the cheapest at the target (50%);
the differences lie within one seed's noise.
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig


def get_config() -> Experiment:
  model = ModelConfig(use_images=True, cameras=("side", "wrist"), image_size=(64, 64), backbone_width=16,
                      backbone_stages=(1, 1, 1), hidden=64, heads=4, ff=256, enc_layers=2, dec_layers=2,
                      cvae_enc_layers=1, plug=PlugConfig(num_skills=4, skill_latent_dim=16, alignment_dim=32))
  train = TrainConfig(preset="cpu_image", model=model, demos=100, batch_size=32, lr=1e-3, warmup_steps=200,
                      lr_schedule="cosine", max_steps=10_000, log_every=100, ckpt_every=1000)
  return Experiment(train=train, seeds=(0, 1, 2), trials=50, fewshot=FewShot(demos=10, steps=0))
