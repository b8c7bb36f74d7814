"""Shapes, parameter groups, freezing and inference paths of the policy.

Shapes come from `jax.eval_shape` (tracing only, no compile), so every
policy x observation variant is checked in well under a second; the few
numerical tests share one tiny state-only SkillPlug model, compiled without
XLA's optimisation passes (these tests check values, not speed).
"""

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import envs
from skillplug_jax import losses
from skillplug_jax.data import normalization
from skillplug_jax import experiment
from skillplug_jax.model import GROUPS, ModelConfig, Policy, masked_optimizer, param_groups, trainable_mask
from skillplug_jax.model.act import ActionHead, CVAEEncoder, Encoder, feature_map_size, num_tokens
from skillplug_jax.model.config import LEGACY_DEFAULTS


def paper() -> ModelConfig:
  return experiment.get("paper").train.model


def budget() -> ModelConfig:
  return experiment.get("budget").train.model


def quick() -> ModelConfig:
  return experiment.get("quick").train.model
from skillplug_jax.model.interactor import INTERACTORS
from skillplug_jax.model.posterior import TrajectorySkillPosterior
from skillplug_jax.model.resnet import ResNet18
from skillplug_jax.model.router import Router
from skillplug_jax.model.skills import SkillLibrary
from skillplug_jax.model.transformer import DecoderLayer, TransformerEncoder
from synthetic import model_batch as make_batch
from synthetic import model_config, rngs

FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
TINY = dict(hidden=32, heads=2, ff=64, enc_layers=1, dec_layers=2, cvae_enc_layers=1, chunk=6,
            latent_dim=8, skill_latent_dim=8, alignment_dim=16, num_skills=3)
B = 2


def tiny(policy="skillplug", images=False, **kw) -> ModelConfig:
  """The paper's (images) or the quick preset's model at a tiny size; plug settings may be flat."""
  base = paper() if images else quick()
  extra = dict(image_size=(32, 32), backbone_width=8) if images else {}
  return model_config(base, policy=policy, **{**TINY, **extra, **kw})


def random_params(module, *args, scale=0.2, seed=0):
  """Parameters of `module` drawn on the host: shapes from tracing `init`,
  values from numpy, so tests compile only the function they check."""
  rng = np.random.default_rng(seed)
  abstract = jax.eval_shape(module.init, jax.random.key(0), *args)
  draw = lambda s: jnp.asarray(scale * rng.standard_normal(s.shape), s.dtype)
  return jax.tree.map(draw, abstract)


def shapes(tree):
  return jax.tree.map(lambda x: (tuple(x.shape), jnp.dtype(x.dtype)), tree)


# ---- presets -----------------------------------------------------------------
def _built(cfg: ModelConfig) -> dict:
  """What a built model's parameter shapes say it is (eval_shape: no compile)."""
  p = jax.eval_shape(Policy(cfg).init, jax.random.key(0), make_batch(cfg))["params"]
  layers = lambda tree: sum(1 for k in tree if k.startswith("layer"))  # noqa: E731
  enc = p["encoder"]["transformer"]
  return dict(
      hidden=p["action_head"]["queries"].shape[1], chunk=p["action_head"]["queries"].shape[0],
      heads=enc["layer1"]["self_attn"]["query"]["kernel"].shape[1], ff=enc["layer1"]["ff"]["fc1"]["kernel"].shape[1],
      enc_layers=layers(enc), dec_layers=layers(p["action_head"]), cvae_enc_layers=layers(p["cvae"]["transformer"]),
      latent_dim=p["cvae"]["latent_proj"]["kernel"].shape[1] // 2,
      num_skills=p["skills"]["embeddings"].shape[0] if "skills" in p else None,
      backbone_width=p["encoder"]["backbone"]["stem"]["kernel"].shape[-1] if "backbone" in p["encoder"] else None)


def test_presets_build_the_models_they_describe():
  """The paper preset builds the paper's ACT (+ K=4); every preset's sizes reach the model."""
  assert _built(paper()) == dict(hidden=512, chunk=25, heads=8, ff=3200, enc_layers=4, dec_layers=7,
                                 cvae_enc_layers=4, latent_dim=32, num_skills=4, backbone_width=64)
  assert _built(budget()) == dict(hidden=256, chunk=25, heads=8, ff=1024, enc_layers=4, dec_layers=4,
                                  cvae_enc_layers=2, latent_dim=32, num_skills=4, backbone_width=32)
  assert _built(quick()) == dict(hidden=64, chunk=25, heads=4, ff=256, enc_layers=2, dec_layers=2,
                                 cvae_enc_layers=1, latent_dim=32, num_skills=4, backbone_width=None)
  assert _built(dataclasses.replace(quick(), policy="act"))["num_skills"] is None
  assert not paper().decoder_first_layer_only  # the whole decoder is read, not ACT's first layer
  with pytest.raises(ValueError, match="policy must be one of"):
    dataclasses.replace(quick(), policy="diffusion")
  with pytest.raises(ValueError, match="divisible by heads"):
    dataclasses.replace(quick(), heads=3)


# ---- how positions and object state enter (issue 12) --------------------------
LEARNED_TABLES = {("encoder", "token_pos"), ("encoder", "state_pos"), ("encoder", "camera_embed"),
                  ("cvae", "cls"), ("action_head", "queries")}


@pytest.mark.parametrize("images", [False, True])
def test_learned_tables_start_small(images):
  """Positions, camera embeddings, decoder queries and the CVAE's CLS start at
  N(0, 0.02): at torch's N(0, 1) they drowned the token contents and halved
  closed-loop success (issue 12)."""
  cfg = tiny(images=images, hidden=256)
  assert cfg.embed_init_std == quick().embed_init_std == paper().embed_init_std == 0.02
  assert cfg.positions == "input" and cfg.normalize_object_state
  params = Policy(cfg).init(jax.random.key(0), make_batch(cfg))["params"]  # the real initialisers
  found = 0
  for (group, name) in LEARNED_TABLES:
    if name in params[group]:
      x = np.asarray(params[group][name])
      assert 0.015 < x.std() < 0.025, (group, name, x.std())
      found += 1
  assert found == 4  # camera embeddings with images, else the state position


def test_runs_from_before_issue_12_load_as_they_were_trained():
  """A config.json written before these fields existed is the model it trained:
  N(0, 1) tables in the contents, raw object state (so its checkpoints still
  evaluate, and resuming it under the new defaults is refused by the diff)."""
  from skillplug_jax.train import config as train_config
  d = train_config.to_dict(experiment.preset("quick", "act"))
  for k in LEGACY_DEFAULTS:
    del d["model"][k]
  old = train_config.from_dict(d).model
  assert (old.positions, old.embed_init_std, old.normalize_object_state) == ("input", 1.0, False)
  assert experiment.preset("quick", "act").model.normalize_object_state


@pytest.mark.parametrize("memory", [False, True])
def test_qk_positions_stay_out_of_the_contents(memory):
  """'qk' (ACT's wiring): positions steer attention but never enter the values,
  so tokens of equal content leave the encoder equal, and a decoder reading a
  memory of equal tokens does not see the memory's positions. Added to the
  contents ('input'), the same positions make the tokens differ."""
  rng = np.random.default_rng(0)
  n, d = 5, 32
  same = jnp.asarray(np.tile(rng.normal(size=(1, 1, d)), (2, n, 1)), jnp.float32)
  pos = jnp.asarray(rng.normal(size=(1, n, d)), jnp.float32)
  if not memory:
    for pre_norm in (True, False):
      enc = TransformerEncoder(2, d, 2, 64, 0.0, pre_norm=pre_norm)
      v = enc.init(jax.random.key(1), same, True, None, pos)
      out = enc.apply(v, same, True, None, pos)
      np.testing.assert_allclose(out, jnp.broadcast_to(out[:, :1], out.shape), atol=1e-5)
      contents = enc.apply(v, same + pos, True)  # positions in the contents
      assert np.abs(contents - contents[:, :1]).max() > 1e-2
    return
  queries = jnp.asarray(rng.normal(size=(2, 4, d)), jnp.float32)
  layer = DecoderLayer(d, 2, 64, 0.0)
  v = layer.init(jax.random.key(2), queries, same, True, None, pos)
  out = layer.apply(v, queries, same, True, None, pos)
  np.testing.assert_allclose(out, layer.apply(v, queries, same, True, None, 10 * pos), atol=1e-5)
  assert np.abs(layer.apply(v, queries, same + pos, True) - out).max() > 1e-2


def test_a_centimetre_moves_the_scene_tokens():
  """At initialisation, moving one object 1 cm must change the encoder's scene
  tokens by at least 1% of the difference between two unrelated scenes. The
  wiring before issue 12 (raw object state beside N(0, 1) positions in the
  contents) gives about 0.2%: the object was nearly invisible to the policy."""
  rng = np.random.default_rng(3)
  n = 16
  scenes = 0.5 + 0.05 * rng.normal(size=(n, envs.OBJECT_STATE_DIM))  # metres, 5 cm spread
  moved = scenes + 0.01 * np.eye(envs.OBJECT_STATE_DIM)[0]
  stats = normalization.stats_of(np.zeros((n, 7)), np.zeros((n, 7)), scenes)
  joint = jnp.asarray(rng.normal(size=(n, 7)), jnp.float32)

  def change(cfg, seed):
    enc, style = Encoder(cfg), jnp.zeros((n, cfg.latent_dim))
    obs = lambda o: {"joint_pos": joint, "object_state": jnp.asarray(
        normalization.normalize(o, stats, "object_state") if cfg.normalize_object_state else o, jnp.float32)}
    v = enc.init(jax.random.key(seed), obs(scenes), style)
    h, _ = enc.apply(v, obs(scenes), style)
    h_moved, _ = enc.apply(v, obs(moved), style)
    return float(jnp.linalg.norm(h_moved - h) / jnp.linalg.norm(jnp.roll(h, 1, axis=0) - h))

  for seed in range(3):
    assert change(quick(), seed) > 0.01
    assert change(dataclasses.replace(quick(), **LEGACY_DEFAULTS), seed) < 0.005


# ---- shapes of every module (eval_shape: no compile) --------------------------
def test_resnet18_feature_map():
  for size, fmap in [((32, 32), (1, 1)), ((64, 64), (2, 2)), ((64, 96), (2, 3))]:
    out = jax.eval_shape(lambda x: ResNet18(width=8).init_with_output(jax.random.key(0), x)[0],
                         jax.ShapeDtypeStruct((3, *size, 3), jnp.uint8))
    assert out.shape == (3, *fmap, 64) and out.dtype == jnp.float32
  params = jax.eval_shape(ResNet18(width=8).init, jax.random.key(0),
                          jnp.zeros((1, 32, 32, 3), jnp.uint8))
  assert "batch_stats" not in params
  assert sum(1 for k in params["params"] if "block" in k) == 8  # [2, 2, 2, 2]
  # fewer stages keep a finer map (and fewer channels); fewer blocks, fewer parameters
  small = ResNet18(width=8, stage_sizes=(1, 1, 1))
  out = jax.eval_shape(lambda x: small.init_with_output(jax.random.key(0), x)[0],
                       jax.ShapeDtypeStruct((3, 64, 64, 3), jnp.uint8))
  assert out.shape == (3, 4, 4, 32)
  params = jax.eval_shape(small.init, jax.random.key(0), jnp.zeros((1, 64, 64, 3), jnp.uint8))
  assert sorted(k for k in params["params"] if "block" in k) == ["stage1_block1", "stage2_block1", "stage3_block1"]


def test_backbone_stages_reach_the_image_tokens():
  """model.backbone_stages sets the backbone the policy builds: 3 stages give 4x4 cells a camera."""
  cfg = dataclasses.replace(tiny(images=True), image_size=(64, 64), backbone_stages=(1, 1, 1))
  batch = make_batch(cfg)
  p = jax.eval_shape(Policy(cfg).init, jax.random.key(0), batch)["params"]
  assert sorted(k for k in p["encoder"]["backbone"] if "block" in k) == [
      "stage1_block1", "stage2_block1", "stage3_block1"]
  assert feature_map_size(cfg) == (4, 4) and num_tokens(cfg) == 2 + 2 * 16
  tokens, _ = jax.eval_shape(lambda: Encoder(cfg).init_with_output(
      jax.random.key(0), batch, jnp.zeros((B, cfg.latent_dim)))[0])
  assert tokens.shape[1] == num_tokens(cfg)


@pytest.mark.parametrize("positions", ["input", "qk"])
@pytest.mark.parametrize("images", [False, True])
def test_act_halves_shapes(images, positions):
  cfg = tiny(images=images, positions=positions)
  batch = make_batch(cfg)
  n = num_tokens(cfg)
  assert n == (2 + 2 * 1 * 1 if images else 3)
  h, pos = jax.eval_shape(lambda: Encoder(cfg).init_with_output(
      jax.random.key(0), batch, jnp.zeros((B, cfg.latent_dim)))[0])
  assert h.shape == (B, n, cfg.hidden)
  if positions == "input":  # already in the contents
    assert pos is None
  else:
    assert pos.shape == (1, n, cfg.hidden)
  mu, logvar = jax.eval_shape(lambda: CVAEEncoder(cfg).init_with_output(
      jax.random.key(0), batch["joint_pos"], batch["actions"], batch["action_mask"])[0])
  assert mu.shape == logvar.shape == (B, cfg.latent_dim)
  chunk = jax.eval_shape(lambda: ActionHead(cfg).init_with_output(
      jax.random.key(0), jnp.zeros((B, n, cfg.hidden)), jnp.zeros((1, n, cfg.hidden)))[0])
  assert chunk.shape == (B, cfg.chunk, cfg.action_dim) and chunk.dtype == jnp.float32


@pytest.mark.parametrize("name", sorted(INTERACTORS))
def test_plug_module_shapes(name):
  cfg = tiny()
  K, N, D = cfg.plug.num_skills, 5, cfg.hidden
  init = lambda m, *a, **kw: jax.eval_shape(
      lambda: m.init_with_output(jax.random.key(0), *a, **kw)[0])
  assert init(SkillLibrary(K, D)).shape == (K, D)
  u = init(INTERACTORS[name](D, cfg.heads, cfg.ff), jnp.zeros((B, N, D)), jnp.zeros((B, K, D)))
  assert u.shape == (B, K, N, D)
  assert init(Router(K, D), jnp.zeros((B, N, D))).shape == (B, K)
  post = jax.eval_shape(lambda: TrajectorySkillPosterior(D, 8, 16).init_with_output(
      {"params": jax.random.key(0), **rngs()}, jnp.zeros((B, cfg.chunk, 7)),
      jnp.ones((B, cfg.chunk), bool), jnp.zeros((K, D)), sample=True)[0])
  assert shapes(post) == {"f_tau": ((B, D), jnp.float32), "mu": ((B, K, 8), jnp.float32),
                          "logvar": ((B, K, 8), jnp.float32), "offset": ((B, K, D), jnp.float32),
                          "traj_logits": ((B, K), jnp.float32)}


def test_router_starts_uniform():
  h = jax.random.normal(jax.random.key(1), (B, 5, 16))
  probs, _ = Router(4, 16).init_with_output(jax.random.key(0), h)
  np.testing.assert_allclose(probs, 0.25)


def test_router_temperature_sharpens_the_same_logits():
  h = jax.random.normal(jax.random.key(1), (B, 5, 16))
  plain = Router(4, 16)
  params = plain.init(jax.random.key(0), h)
  params = jax.tree.map(lambda p: p + 0.3 * jax.random.normal(jax.random.key(2), p.shape), params)  # leave uniform
  p1 = plain.apply(params, h)
  p01 = Router(4, 16, temperature=0.1).apply(params, h)  # the same parameters: only the softmax differs
  logits = jnp.log(p1)
  np.testing.assert_allclose(p01, jax.nn.softmax(logits / 0.1, axis=-1), rtol=1e-4, atol=1e-6)
  ent = lambda p: float(-(p * jnp.log(p)).sum(-1).mean())  # noqa: E731
  assert ent(p01) < ent(p1)
  with pytest.raises(ValueError, match="router_temperature must be > 0"):
    tiny(router_temperature=0.0)


def test_latents_start_at_the_prior():
  cfg = tiny()
  batch = make_batch(cfg)
  init = lambda m, *a: jax.jit(lambda: m.init_with_output(
      {"params": jax.random.key(0), **rngs()}, *a)[0], compiler_options=FAST_COMPILE)()
  mu, logvar = init(CVAEEncoder(cfg), batch["joint_pos"], batch["actions"], batch["action_mask"])
  post = init(TrajectorySkillPosterior(cfg.hidden, 8, 16), batch["actions"], batch["action_mask"],
              jnp.ones((cfg.plug.num_skills, cfg.hidden)))
  for m, lv in ((mu, logvar), (post["mu"], post["logvar"])):
    assert float(losses.kl_standard_normal(m, lv)) == 0.0


@pytest.mark.parametrize("images", [False, True])
@pytest.mark.parametrize("policy", ["act", "skillplug"])
def test_policy_shapes_and_groups(policy, images):
  cfg = tiny(policy, images)
  model, batch = Policy(cfg), make_batch(cfg)
  variables = jax.eval_shape(model.init, jax.random.key(0), batch)
  expected = set(GROUPS) - {"action_proj", "adapter"} if policy == "skillplug" else {"encoder", "cvae", "action_head"}
  assert set(variables) == {"params"} and param_groups(variables) == expected
  assert ("backbone" in variables["params"]["encoder"]) == images
  out = jax.eval_shape(lambda v: model.apply(v, batch, train=True, rngs=rngs()), variables)
  K, z = cfg.plug.num_skills, cfg.plug.skill_latent_dim
  want = {"pred_actions": (B, cfg.chunk, cfg.action_dim),
          "cvae_mu": (B, cfg.latent_dim), "cvae_logvar": (B, cfg.latent_dim)}
  if policy == "skillplug":
    n = num_tokens(cfg)
    want.update(router_probs=(B, K), router_logits=(B, K),
                skill_tokens=(B, K, n, cfg.hidden), plug_input=(B, n, cfg.hidden),
                skill_features=(B, K, cfg.hidden), posterior_mu=(B, K, z),
                posterior_logvar=(B, K, z), traj_logits=(B, K))
  assert {k: v.shape for k, v in out.items()} == want
  assert all(v.dtype == jnp.float32 for v in out.values())
  # validation (train=False) needs no rng: latents at their means, no dropout
  val = jax.eval_shape(lambda v: model.apply(v, batch, train=False), variables)
  assert shapes(val) == shapes(out)
  chunk, routing = jax.eval_shape(lambda v: model.apply(v, batch, method=Policy.predict), variables)
  assert chunk.shape == (B, cfg.chunk, cfg.action_dim)
  h, pos = jax.eval_shape(lambda v: model.apply(v, batch, method=Policy.encode), variables)
  assert h.shape == (B, num_tokens(cfg), cfg.hidden)
  act = jax.eval_shape(lambda v, x, p: model.apply(v, x, p, method=Policy.act), variables, h, pos)
  assert act.shape == chunk.shape
  assert (routing is None) == (policy == "act")
  if routing is not None:
    assert routing.shape == (B, cfg.plug.num_skills)


def test_bfloat16_compute_keeps_float32_params_and_outputs():
  cfg = tiny(dtype="bfloat16")
  model, batch = Policy(cfg), make_batch(cfg)
  variables = jax.eval_shape(model.init, jax.random.key(0), batch)
  assert {x.dtype for x in jax.tree.leaves(variables)} == {jnp.dtype(jnp.float32)}
  out = jax.eval_shape(lambda v: model.apply(v, batch, train=True, rngs=rngs()), variables)
  assert {x.dtype for x in jax.tree.leaves(out)} == {jnp.dtype(jnp.float32)}


# ---- freezing -----------------------------------------------------------------
def test_trainable_mask_marks_exactly_the_requested_groups():
  cfg = tiny()
  variables = jax.eval_shape(Policy(cfg).init, jax.random.key(0), make_batch(cfg))
  trainable = {"router", "action_head"}
  for tree in (variables, variables["params"]):
    mask = trainable_mask(tree, trainable)
    assert jax.tree.structure(mask) == jax.tree.structure(tree)
    groups = mask["params"] if "params" in mask else mask
    for name, sub in groups.items():
      assert set(jax.tree.leaves(sub)) == {name in trainable}
  with pytest.raises(ValueError, match="posteriors"):
    trainable_mask(variables, {"posteriors"})


def test_decoder_first_layer_only_reads_layer_one():
  cfg = tiny(dec_layers=3)
  memory = jax.random.normal(jax.random.key(1), (B, 4, cfg.hidden))
  params = random_params(ActionHead(cfg), memory)
  run = lambda c, p: jax.jit(ActionHead(c).apply, compiler_options=FAST_COMPILE)(p, memory)
  full = run(cfg, params)
  first = run(dataclasses.replace(cfg, decoder_first_layer_only=True), params)
  # the same parameters with only the first layer kept, in a 1-layer decoder
  one_layer = {"params": {k: v for k, v in params["params"].items()
                          if k not in ("layer2", "layer3")}}
  single = run(dataclasses.replace(cfg, dec_layers=1), one_layer)
  np.testing.assert_allclose(first, single, rtol=1e-5, atol=1e-6)
  assert not np.allclose(first, full, atol=1e-3)


# ---- numerics on one tiny state-only SkillPlug model ----------------------------
@pytest.fixture(scope="module")
def tiny_model():
  cfg = tiny()
  model, batch = Policy(cfg), make_batch(cfg)
  variables = random_params(model, batch)
  forward = jax.jit(lambda v, b, r: model.apply(v, b, train=True, rngs=r),
                    compiler_options=FAST_COMPILE)
  predict = jax.jit(lambda v, o: model.apply(v, o, method=Policy.predict),
                    compiler_options=FAST_COMPILE)
  return cfg, model, batch, variables, forward, predict


def test_forward_is_deterministic_given_rngs(tiny_model):
  _, _, batch, variables, forward, _ = tiny_model
  a, b = forward(variables, batch, rngs(0)), forward(variables, batch, rngs(0))
  jax.tree.map(np.testing.assert_array_equal, a, b)
  c = forward(variables, batch, rngs(1))
  assert not np.allclose(a["pred_actions"], c["pred_actions"])
  assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(a))
  # each sample is routed from its own observation: the second sample alone routes as in the batch
  _, _, _, _, _, predict = tiny_model
  _, routing = predict(variables, batch)
  _, alone = predict(variables, jax.tree.map(lambda x: x[1:], batch))
  np.testing.assert_allclose(alone[0], routing[1], rtol=1e-5, atol=1e-6)
  assert not np.allclose(routing[0], routing[1], atol=1e-5)  # and the two samples' routings differ


def test_predict_ignores_actions_and_posterior(tiny_model):
  cfg, _, batch, variables, _, predict = tiny_model
  chunk, routing = predict(variables, batch)
  assert np.all(np.isfinite(chunk))
  # other demonstrated actions and a NaN posterior and CVAE change nothing
  poisoned = {"params": {k: (jax.tree.map(lambda x: jnp.full_like(x, jnp.nan), v)
                             if k in ("posterior", "cvae") else v)
                         for k, v in variables["params"].items()}}
  other = dict(batch, actions=batch["actions"] * 5 + 1,
               action_mask=jnp.zeros_like(batch["action_mask"]))
  chunk2, routing2 = predict(poisoned, other)
  np.testing.assert_array_equal(chunk, chunk2)
  np.testing.assert_array_equal(routing, routing2)


def test_fixed_routing_acts_as_the_router_would(tiny_model):
  """A one-hot routing on skill k gives skill k's chunk (different skills, different
  chunks), the same chunk as when the router itself outputs that one-hot."""
  cfg, model, batch, variables, _, _ = tiny_model
  K = cfg.plug.num_skills
  onehot = jnp.eye(K)
  fixed = jax.jit(lambda v, o, r: model.apply(v, o, r, method=Policy.predict), compiler_options=FAST_COMPILE)
  chunks = []
  for k in range(K):
    chunk, used = fixed(variables, batch, onehot[k])
    np.testing.assert_array_equal(used, jnp.broadcast_to(onehot[k], (B, K)))
    chunks.append(np.asarray(chunk))
  for j in range(K):
    for k in range(j + 1, K):
      assert not np.allclose(chunks[j], chunks[k], atol=1e-4), (j, k)

  def router_says(k):
    def intercept(next_fun, args, kwargs, context):
      if isinstance(context.module, Router) and context.method_name == "__call__":
        return jnp.broadcast_to(onehot[k], (args[0].shape[0], K))
      return next_fun(*args, **kwargs)
    with nn.intercept_methods(intercept):
      return jax.jit(lambda v, o: model.apply(v, o, method=Policy.predict), compiler_options=FAST_COMPILE)(
          variables, batch)

  for k in (0, K - 1):
    chunk, routing = router_says(k)
    np.testing.assert_array_equal(routing, jnp.broadcast_to(onehot[k], (B, K)))
    np.testing.assert_allclose(chunk, chunks[k], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("policy,site", [("act", "decoder"), ("skillplug", "decoder"), ("act", "encoder"),
                                         ("skillplug", "encoder")])
def test_an_adapter_starts_as_the_identity_and_adds_only_its_group(policy, site):
  """The few-shot baseline's adapter (issues 42-43) sits before f_act: of the split head (the
  decoder site), or before the whole action head (the encoder site). Added to a model, the same
  parameters elsewhere give the same chunk (its output layer starts at zero), its parameters are a
  group of their own, and a change to them changes the chunk (it is on the path)."""
  base = tiny(policy, site=site)
  batch = make_batch(base)
  params = random_params(Policy(base), batch)["params"]
  with_adapter = dataclasses.replace(base, adapter_width=5)
  fresh = jax.jit(lambda: Policy(with_adapter).init({"params": jax.random.key(1), **rngs()}, batch),
                  compiler_options=FAST_COMPILE)()["params"]
  assert set(fresh) - set(params) == {"adapter"}
  predict = lambda cfg, p: jax.jit(lambda p: Policy(cfg).apply({"params": p}, batch, method=Policy.predict),  # noqa: E731
                                   compiler_options=FAST_COMPILE)(p)[0]
  np.testing.assert_array_equal(predict(base, params), predict(with_adapter, {**params, "adapter": fresh["adapter"]}))
  rng = np.random.default_rng(0)  # a random change (a constant one the final norm would remove)
  nudged = jax.tree.map(lambda x: x + 0.1 * rng.standard_normal(x.shape).astype(np.float32), fresh["adapter"])
  assert not np.allclose(predict(base, params), predict(with_adapter, {**params, "adapter": nudged}))


def test_the_adapter_is_the_routers_size_at_the_cpu_preset():
  """What docs/measurements/skill_library.md states: at the cpu preset (hidden 64, K = 4) the
  adapter of width 32 has 4,320 parameters, the router 4,420."""
  cfg = experiment.preset("cpu", "skillplug").model
  cfg = model_config(cfg, site="decoder", adapter_width=32)
  p = jax.eval_shape(Policy(cfg).init, jax.random.key(0), make_batch(cfg))["params"]
  count = lambda tree: sum(int(np.prod(x.shape)) for x in jax.tree.leaves(tree))  # noqa: E731
  assert (count(p["adapter"]), count(p["router"])) == (4320, 4420)


def test_uniform_fusion_weights_ignore_the_router(tiny_model):
  """model.plug.fusion_weights='uniform' (a few-shot arm of issue 43): the u_k are weighted 1/K
  whatever the router says, in training and at inference, and the outputs report those weights."""
  cfg, _, batch, variables, _, _ = tiny_model
  K = cfg.plug.num_skills
  uniform = model_config(cfg, fusion_weights="uniform")
  model = Policy(uniform)
  chunk, routing = jax.jit(lambda v: model.apply(v, batch, method=Policy.predict),
                           compiler_options=FAST_COMPILE)(variables)
  np.testing.assert_allclose(routing, np.full((B, K), 1.0 / K))
  given, _ = jax.jit(lambda v: Policy(cfg).apply(v, batch, jnp.full(K, 1.0 / K), method=Policy.predict),
                     compiler_options=FAST_COMPILE)(variables)
  np.testing.assert_allclose(chunk, given, rtol=1e-6, atol=1e-6)
  out = jax.jit(lambda v: model.apply(v, batch, train=False), compiler_options=FAST_COMPILE)(variables)
  np.testing.assert_allclose(out["router_probs"], np.full((B, K), 1.0 / K))


@pytest.mark.parametrize("policy", ["skillplug", "act"])
def test_training_forward_with_zero_latents_equals_predict(policy):
  """The training pass (train=False: latents at their means) with the CVAE latent and
  every skill's z at zero is the inference path: same chunk, same routing."""
  cfg = tiny(policy)
  model, batch = Policy(cfg), make_batch(cfg)
  variables = random_params(model, batch, seed=3)
  forward = jax.jit(lambda v: model.apply(v, batch, train=False), compiler_options=FAST_COMPILE)
  chunk, routing = jax.jit(lambda v: model.apply(v, batch, method=Policy.predict),
                           compiler_options=FAST_COMPILE)(variables)
  # random latent heads put the latents away from zero: then the passes differ
  assert not np.allclose(forward(variables)["pred_actions"], chunk, atol=1e-4)
  zero = lambda tree: jax.tree.map(jnp.zeros_like, tree)  # noqa: E731
  params = dict(variables["params"])
  params["cvae"] = {**params["cvae"], "latent_proj": zero(params["cvae"]["latent_proj"])}  # mu = 0
  if policy == "skillplug":  # mu_k = 0, so z_k = 0 and the offset W z_k is zero
    params["posterior"] = {**params["posterior"], "q_fc2": zero(params["posterior"]["q_fc2"])}
  out = forward({"params": params})
  np.testing.assert_array_equal(out["cvae_mu"], 0.0)
  np.testing.assert_allclose(out["pred_actions"], chunk, rtol=1e-5, atol=1e-6)
  if policy == "skillplug":
    np.testing.assert_allclose(out["router_probs"], routing, rtol=1e-6, atol=1e-7)


def _group_grads(model, variables, batch):
  """Gradients of the whole loss and of L_BSA alone, for each parameter."""
  def term(v, name):
    loss, m = losses.total_loss(model.apply(v, batch, train=True, rngs=rngs()), batch)
    return loss if name == "loss" else m[name]
  return jax.jit(lambda v: (jax.grad(term)(v, "loss"), jax.grad(term)(v, "bsa")),
                 compiler_options=FAST_COMPILE)(variables)


def test_freezing_and_bsa_gradients(tiny_model):
  _, model, batch, variables, _, _ = tiny_model
  grads, bsa_grads = _group_grads(model, variables, batch)
  # every group is wired into the loss
  for name in param_groups(variables):
    assert any(np.any(x != 0) for x in jax.tree.leaves(grads["params"][name])), name
  # L_BSA reaches the skills and the posterior heads, never the router
  assert all(np.all(x == 0) for x in jax.tree.leaves(bsa_grads["params"]["router"]))
  assert any(np.any(x != 0) for x in jax.tree.leaves(bsa_grads["params"]["skills"]))
  assert any(np.any(x != 0) for x in jax.tree.leaves(grads["params"]["router"]))

  trainable = {"router", "action_head"}
  opt = masked_optimizer(optax.adam(1e-2), variables, trainable)

  def step(params, grads):
    updates, _ = opt.update(grads, opt.init(params), params)
    return optax.apply_updates(params, updates)

  new = jax.jit(step, compiler_options=FAST_COMPILE)(variables, grads)
  for name in param_groups(variables):
    before, after = jax.tree.leaves(variables["params"][name]), jax.tree.leaves(new["params"][name])
    if name in trainable:
      assert any(np.any(a != b) for a, b in zip(after, before)), name
    else:
      assert all(np.array_equal(a, b) for a, b in zip(after, before)), name


def test_image_policy_ignores_object_state():
  """The privileged object state never reaches an image policy; its images do."""
  cfg = tiny("skillplug", images=True, enc_layers=1, dec_layers=1)
  model, batch = Policy(cfg), make_batch(cfg)
  variables = random_params(model, batch)
  predict = jax.jit(lambda v, o: model.apply(v, o, method=Policy.predict), compiler_options=FAST_COMPILE)
  chunk, routing = predict(variables, batch)
  moved = dict(batch, object_state=batch["object_state"] * 10.0 + 3.0)
  chunk2, routing2 = predict(variables, moved)
  np.testing.assert_array_equal(chunk2, chunk)
  np.testing.assert_array_equal(routing2, routing)
  other_view = dict(batch, side_rgb=255 - batch["side_rgb"])
  assert not np.allclose(predict(variables, other_view)[0], chunk, atol=1e-4)


def test_image_policy_runs_and_losses_are_finite():
  cfg = tiny("skillplug", images=True, enc_layers=1, dec_layers=1)
  model, batch = Policy(cfg), make_batch(cfg)

  step = jax.jit(lambda v: losses.total_loss(model.apply(v, batch, train=True, rngs=rngs()), batch),
                 compiler_options=FAST_COMPILE)
  loss, metrics = step(random_params(model, batch))
  assert np.isfinite(loss) and all(np.isfinite(v) for v in metrics.values())


def test_libero_cpus_adapter_is_the_routers_size():
  """experiments/configs/libero_cpu.py's capacity-matched arm (issue 42): at K = 8 and hidden 64 the
  adapter of width 35 has 4,707 parameters, the router 4,680 (what its docstring states)."""
  exp = experiment.get("libero_cpu")
  # its hidden width and K; the inputs (which set neither size) as the synthetic batch has them
  cfg = dataclasses.replace(exp.train_config("skillplug", 0).model, adapter_width=35, use_images=False,
                            proprio=("joint_pos",), joint_dim=7, instruction_vocab=0)
  p = jax.eval_shape(Policy(cfg).init, jax.random.key(0), make_batch(cfg))["params"]
  count = lambda tree: sum(int(np.prod(x.shape)) for x in jax.tree.leaves(tree))  # noqa: E731
  assert (count(p["adapter"]), count(p["router"])) == (4707, 4680)


def test_libero_cpus_multi_task_adapter_is_the_plugs_size():
  """libero_cpu's goal_act_adapter arm: ACT with an adapter as large as what the plug adds at
  inference (skills, interactor, router; within 0.2%), trained multi-task from scratch."""
  from experiments.configs import libero_cpu
  exp = experiment.get("libero_cpu")
  arm = next(v for v in exp.variants if v.name == "goal_act_adapter")
  assert f"train.model.adapter_width={libero_cpu.PLUG_SIZED_ADAPTER}" in arm.overrides
  assert "policies=act" in arm.overrides and "train.taskset=libero_goal" in arm.overrides
  base = dataclasses.replace(exp.train_config("skillplug", 0).model, use_images=False, proprio=("joint_pos",),
                             joint_dim=7, instruction_vocab=0)
  count = lambda tree: sum(int(np.prod(x.shape)) for x in jax.tree.leaves(tree))  # noqa: E731
  shapes = lambda cfg: jax.eval_shape(Policy(cfg).init, jax.random.key(0), make_batch(cfg))["params"]  # noqa: E731
  plug = shapes(base)
  added = sum(count(plug[g]) for g in ("skills", "interactor", "router"))
  act = shapes(dataclasses.replace(base, policy="act", adapter_width=libero_cpu.PLUG_SIZED_ADAPTER))
  assert set(act) == {"cvae", "encoder", "action_head", "adapter"}
  assert abs(count(act["adapter"]) - added) / added < 0.002 and added == 59336
