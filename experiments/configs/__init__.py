"""Experiment configs: one small file per preset, table or figure (big_vision's pattern).

Each file here is pure data: it defines `get_config() -> Experiment` from
`skillplug_jax.experiment` and the model / training config classes, and its
docstring's first line names the command that runs it. The library loads these
files by path (`skillplug_jax.experiment.get`), never as this package:

    from skillplug_jax import experiment
    exp = experiment.get("cpu", ["seeds=0", "train.max_steps=200", "fewshot.steps=50"])

`skillplug pretrain --config NAME --set KEY=VALUE` overrides `train`'s fields
(`--set model.hidden=128`); the pipeline (`python -m experiments.pipeline
--config NAME --set KEY=VALUE`) overrides the whole experiment (`--set
train.model.hidden=128 --set seeds=0,1`).
"""
