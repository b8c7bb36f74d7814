"""The policy: ACT split into encoder and action head, with the SkillPlug
module (skill library, interactor, router, training-only posterior) between."""

from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.freeze import GROUPS, masked_optimizer, param_groups, trainable_mask
from skillplug_jax.model.plug import PlugConfig, SkillPlug
from skillplug_jax.model.policy import Policy

__all__ = ["ModelConfig", "PlugConfig", "Policy", "SkillPlug", "GROUPS",
           "param_groups", "trainable_mask", "masked_optimizer"]
