"""Training: config and presets, the loop, checkpoints, scalars."""
