"""Demonstrations: generation (`demos`), RLDS storage (`rlds`), statistics and the batch loader."""
