"""The policy: ACT split into encoder and action head, with the SkillPlug
module (skill library, interactor, router, training-only posterior) between."""

from skillplug_jax.model.config import ModelConfig, budget, paper, quick
from skillplug_jax.model.freeze import (FEWSHOT_TRAINABLE, GROUPS, masked_optimizer,
                                        param_groups, trainable_mask)
from skillplug_jax.model.policy import Policy

__all__ = ["ModelConfig", "paper", "budget", "quick", "Policy", "GROUPS", "FEWSHOT_TRAINABLE",
           "param_groups", "trainable_mask", "masked_optimizer"]
