"""Evaluation: closed-loop batched rollouts, policy controllers, success tables."""
