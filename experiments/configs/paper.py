"""make pretrain CONFIG=paper   (then make eval / make fewshot with the run directories)

The paper's protocol (DISCOVERSE part): ACT at its published sizes (hidden
512, 8 heads, FF 3200, 4 encoder and 7 decoder layers, ResNet-18 on two
64x64 cameras, chunk 25) plus SkillPlug with K=4; AdamW at 1e-4, batch 16,
6000 ACT epochs of 300 demonstrations per task; 3 seeds, 50 trials per task;
few-shot from 10 demonstrations for the same 6000 epochs.
"""

from skillplug_jax.experiment import Experiment, FewShot
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.train.config import TrainConfig


def get_config() -> Experiment:
  return Experiment(train=TrainConfig(preset="paper", model=ModelConfig()), seeds=(0, 1, 2), trials=50,
                    fewshot=FewShot(steps=0))
