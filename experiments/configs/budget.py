"""make pretrain CONFIG=budget   (about 10 minutes of one H100: not yet measured on one)

Images at a quarter of the paper's cost, for short GPU budgets. Half the
width (256) cuts attention and FF cost about 4x; a backbone of width 32 does
the same for the ResNet, which dominates at 64x64 images. The encoder keeps 4
layers because the plug reads its output tokens; the decoder drops to 4
because ACT's 7 were effectively 1 (the first-layer bug), so 4 used layers
are still deeper than what ACT was tuned with. The CVAE only summarises ~27
tokens into a latent held near the prior: 2 layers.
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model import ModelConfig, PlugConfig
from skillplug_jax.train.config import TrainConfig


def get_config() -> Experiment:
  model = ModelConfig(hidden=256, heads=8, ff=1024, backbone_width=32, enc_layers=4, dec_layers=4,
                      cvae_enc_layers=2, plug=PlugConfig(alignment_dim=64))
  train = TrainConfig(preset="budget", model=model, demos=100, batch_size=64, lr=3e-4, warmup_steps=500,
                      max_steps=20_000, ckpt_every=2000)
  return Experiment(train=train, seeds=(0, 1, 2), trials=50, fewshot=FewShot(steps=2000))
