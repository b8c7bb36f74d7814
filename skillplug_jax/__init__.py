"""SkillPlug-JAX: skill mining for few-shot adaptation, in JAX/Flax, with an MJX benchmark."""
