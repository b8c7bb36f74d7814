"""Instructions as word ids (skillplug_jax/data/language.py) and the encoder's instruction token
(model.instruction_vocab): known words read as themselves, unseen ones as UNK, and the policy
(its router too) reads the instruction, so two LIBERO-Goal tasks of one scene can be told apart."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from skillplug_jax.data import language
from skillplug_jax.model import ModelConfig, Policy
from skillplug_jax.model.act import Encoder, num_tokens
from synthetic import model_batch, model_config

TINY = ModelConfig(use_images=False, hidden=32, heads=2, ff=64, enc_layers=1, dec_layers=1, cvae_enc_layers=1,
                   chunk=5)

GOAL_0 = "open the middle drawer of the cabinet"
GOAL_7 = "turn on the stove"


def test_the_benchmark_vocabulary_holds_every_instruction_word_after_the_reserved_ids():
  vocab = language.benchmark_vocabulary()
  assert vocab[:2] == language.RESERVED and list(vocab[2:]) == sorted(vocab[2:])
  assert {"drawer", "stove", "alphabet", "soup", "microwave"} <= set(vocab)
  ids = language.encode([GOAL_0, GOAL_7], vocab, 8)
  assert [vocab[i] for i in ids[0][:7]] == language.words(GOAL_0) and ids[0][7] == language.PAD
  assert [vocab[i] for i in ids[1] if i] == ["turn", "on", "the", "stove"]


def test_unseen_words_read_as_unk_and_long_instructions_are_refused():
  vocab = language.vocabulary([GOAL_0, GOAL_7])
  ids = language.encode(["open the fridge", "open the oven", "Turn ON the stove!"], vocab, 6)
  assert ids[0][2] == language.UNK and np.array_equal(ids[0], ids[1])  # two unseen words, one input
  assert np.array_equal(ids[2], language.encode([GOAL_7], vocab, 6)[0])  # case and punctuation ignored
  with pytest.raises(ValueError, match="has 7 words; the model reads at most 6"):
    language.encode([GOAL_0], vocab, 6)
  with pytest.raises(ValueError, match="starts with"):
    language.encode([GOAL_0], ("stove",), 8)


@pytest.mark.parametrize("policy", ["act", "skillplug"])
def test_the_policy_and_its_router_read_the_instruction(policy):
  vocab = language.vocabulary([GOAL_0, GOAL_7])
  cfg = model_config(TINY, policy=policy, instruction_vocab=len(vocab), instruction_words=8, num_skills=3,
                     skill_latent_dim=8, alignment_dim=16)
  batch = model_batch(cfg)
  b = batch["joint_pos"].shape[0]
  assert num_tokens(cfg) == num_tokens(dataclasses.replace(cfg, instruction_vocab=0)) + 1
  ids = language.encode([GOAL_0, GOAL_7, "open the fridge", "open the oven"], vocab, 8)
  params = Policy(cfg).init({"params": jax.random.key(0), "dropout": jax.random.key(1), "sample": jax.random.key(2)},
                            {**batch, "instruction": jnp.zeros((b, 8), jnp.int32)}, train=True)["params"]
  assert params["encoder"]["instruction_embed"]["embedding"].shape == (len(vocab), cfg.hidden)
  leaves, tree = jax.tree.flatten(params)  # away from the initialisation's zeros (the router's head)
  keys = jax.random.split(jax.random.key(3), len(leaves))
  params = jax.tree.unflatten(tree, [p + 0.2 * jax.random.normal(k, p.shape) for p, k in zip(leaves, keys)])
  obs = {k: v[:1] for k, v in batch.items() if k not in ("actions", "action_mask", "task_id")}

  apply = jax.jit(lambda words: Policy(cfg).apply({"params": params}, {**obs, "instruction": words},
                                                  method=Policy.predict))
  (a0, r0), (a7, r7), (fridge, rf), (oven, ro) = (apply(jnp.asarray(ids[i:i + 1])) for i in range(4))
  assert not np.allclose(a0, a7)  # the same scene, another instruction: another action
  np.testing.assert_array_equal(fridge, oven)  # unseen words: the same input, so the same action
  if policy == "skillplug":
    assert not np.allclose(r0, r7)  # the router sees the instruction's token
    np.testing.assert_array_equal(rf, ro)


def test_an_instruction_of_padding_only_is_a_zero_pool_not_an_error():
  cfg = model_config(TINY, policy="act", instruction_vocab=4, instruction_words=3)
  batch = model_batch(cfg)
  b = batch["joint_pos"].shape[0]
  tokens, _ = jax.eval_shape(lambda: Encoder(cfg).init_with_output(
      jax.random.key(0), {**batch, "instruction": jnp.zeros((b, 3), jnp.int32)}, jnp.zeros((b, cfg.latent_dim)))[0])
  assert tokens.shape[1] == num_tokens(cfg)


def test_a_model_that_reads_instructions_refuses_a_dataset_without_them():
  from pathlib import Path

  from skillplug_jax import experiment
  from skillplug_jax.data import loader
  from skillplug_jax.train import config, loop
  cfg = config.override(experiment.preset("quick", "act"), ["model.instruction_vocab=128"])
  demos = loader.Demonstrations(path=Path("discoverse_demos"), tasks=("jujube_pick",), image_size=None, steps={},
                                start=np.zeros(1, np.int64), length=np.ones(1, np.int64),
                                task_id=np.zeros(1, np.int32), episode_id=("e",), stats={})
  with pytest.raises(ValueError, match="discoverse_demos has none"):
    loop.instruction_ids(cfg, demos)
  small = config.override(cfg, ["model.instruction_vocab=10"])
  with pytest.raises(ValueError, match="cannot hold the vocabulary's 81 words"):
    loop.instruction_ids(small, dataclasses.replace(demos, language=("turn on the stove",)))
