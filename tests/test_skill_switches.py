"""Each switch of issue 27 does what it says, and the defaults are the model as it was.

The switches of the plug are `model.plug.*` (model/plug.py); those removed in issue 40 (top-1
routing, posterior fusion, router_input='zero_style', load balance, router z-loss) are gone
from here with them.

One tiny state-only model (hidden 32, K=3), compiled without XLA's
optimisation passes; parameters are drawn on the host so that routing and
latents are away from their zero starts.
"""

import dataclasses
import functools
import hashlib
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import envs
from skillplug_jax import losses
from skillplug_jax.model import GROUPS, ModelConfig, PlugConfig, Policy, masked_optimizer, param_groups
from skillplug_jax.model.act import Encoder, num_tokens
from skillplug_jax.model.interactor import INTERACTORS
from skillplug_jax.model.posterior import TrajectorySkillPosterior
from synthetic import model_batch as make_batch
from synthetic import model_config, rngs

FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
TINY = dict(hidden=32, heads=2, ff=64, enc_layers=1, dec_layers=2, cvae_enc_layers=1, chunk=6,
            latent_dim=8, skill_latent_dim=8, alignment_dim=16, num_skills=3)
B = 2


def tiny(policy="skillplug", **kw) -> ModelConfig:
  """The reference model of the defaults test; the other tests take one decoder layer
  (`small`), which compiles faster. Plug settings may be given flat (num_skills=3)."""
  return model_config(ModelConfig(policy=policy, use_images=False), **{**TINY, **kw})


def small(policy="skillplug", **kw) -> ModelConfig:
  return tiny(policy, **{"dec_layers": 1, **kw})


def host_params(cfg: ModelConfig, scale=0.2, seed=0):
  """Parameters drawn on the host (shapes from tracing init): routing and latents away from zero."""
  rng = np.random.default_rng(seed)
  model = Policy(cfg)
  abstract = jax.eval_shape(model.init, jax.random.key(0), make_batch(cfg))
  return jax.tree.map(lambda s: jnp.asarray(scale * rng.standard_normal(s.shape), s.dtype), abstract)


@functools.lru_cache(maxsize=None)
def _forward_fn(cfg: ModelConfig, train: bool):
  model = Policy(cfg)
  return jax.jit(lambda v, b, key: model.apply(v, b, train=train, rngs=_rngs(key) if train else None),
                 compiler_options=FAST_COMPILE)


def _rngs(key):
  k1, k2 = jax.random.split(key)
  return {"dropout": k1, "sample": k2}


def forward(cfg, variables, batch, train=True, seed=0, intercept=None):
  """The training (or validation) pass; `intercept` (flax's method interceptor) is applied
  while tracing, so it must not depend on the call (its function is cached with cfg)."""
  if intercept is None:
    return _forward_fn(cfg, train)(variables, batch, jax.random.key(seed))
  model = Policy(cfg)

  def fn(v, b, key):
    with nn.intercept_methods(intercept):
      return model.apply(v, b, train=train, rngs=_rngs(key) if train else None)
  return jax.jit(fn, compiler_options=FAST_COMPILE)(variables, batch, jax.random.key(seed))


@functools.lru_cache(maxsize=None)
def _predict_fn(cfg: ModelConfig):
  model = Policy(cfg)
  return jax.jit(lambda v, b: model.apply(v, b, method=Policy.predict), compiler_options=FAST_COMPILE)


def predict(cfg, variables, batch):
  return _predict_fn(cfg)(variables, batch)


def grads_of(cfg, variables, batch, weights=losses.LossWeights(), term="loss"):
  """Gradients of the total loss (or of one metric) at rngs(0), and the metrics."""
  model = Policy(cfg)

  def objective(v):
    loss, m = losses.total_loss(model.apply(v, batch, train=True, rngs=rngs()), batch, weights)
    return (loss if term == "loss" else m[term]), m
  return jax.jit(jax.grad(objective, has_aux=True), compiler_options=FAST_COMPILE)(variables)


# ---- defaults: the model and loss as before issue 27 ----------------------------
def _tree_digest(params) -> tuple[int, int, str]:
  leaves = jax.tree_util.tree_leaves_with_path(params)
  lines = sorted(f"{'/'.join(str(p.key) for p in path)}:{'x'.join(map(str, x.shape))}" for path, x in leaves)
  return len(lines), sum(math.prod(x.shape) for _, x in leaves), hashlib.sha256("\n".join(lines).encode()).hexdigest()[:16]


# Recorded with the code before the switches existed (same config, rngs and perturbation).
BEFORE = {
    "skillplug": dict(tree=(146, 64458, "ab6f729f079a4e2c"), pred_sum=81.65373229980469,
                      grad_abs_sum=5940.25390625,
                      metrics=dict(bsa=3.083522081375122, cvae_kl=1.6404736042022705, kl=0.9889165163040161,
                                   loss=18.966289520263672, rec=1.1874704360961914, sd=0.768165111541748)),
    "act": dict(tree=(110, 47063, "fb676fc668d6816e"), pred_sum=89.13853454589844,
                grad_abs_sum=5467.73095703125,
                metrics=dict(cvae_kl=1.6404736042022705, loss=17.795900344848633, rec=1.391164779663086)),
}


@pytest.mark.parametrize("policy", ["skillplug", "act"])
def test_defaults_reproduce_the_model_and_loss_from_before(policy):
  """Existing configs and checkpoints load and train as before: the same parameter tree, the
  same forward pass, loss terms and gradients, at a fixed seed (diagnostics come on top)."""
  cfg = tiny(policy)
  model, batch = Policy(cfg), make_batch(cfg)
  v = jax.jit(lambda b: model.init({"params": jax.random.key(0), **rngs(5)}, b, train=True),
              compiler_options=FAST_COMPILE)(batch)
  assert _tree_digest(v["params"]) == BEFORE[policy]["tree"]
  leaves, tdef = jax.tree.flatten(v)
  noise = np.random.default_rng(7)
  v = jax.tree.unflatten(tdef, [x + jnp.asarray(0.1 * noise.standard_normal(x.shape), x.dtype) for x in leaves])
  objective = lambda v, b: losses.total_loss(model.apply(v, b, train=True, rngs=rngs(1)), b)  # noqa: E731
  grads, m = jax.jit(jax.grad(objective, has_aux=True), compiler_options=FAST_COMPILE)(v, batch)
  chunk, _ = predict(cfg, v, batch)
  want = BEFORE[policy]
  assert {k for k in m if not k.startswith("diag_")} == set(want["metrics"])
  for k, x in want["metrics"].items():
    assert float(m[k]) == pytest.approx(x, rel=1e-4, abs=1e-6), k
  assert float(sum(jnp.abs(g).sum() for g in jax.tree.leaves(grads))) == pytest.approx(want["grad_abs_sum"], rel=1e-4)
  assert float(jnp.abs(chunk).sum()) == pytest.approx(want["pred_sum"], rel=1e-4)


def test_switch_values_are_checked():
  for name in ("site", "skill_offset", "router_input", "object_tokens", "interactor"):
    with pytest.raises(ValueError, match=name):
      small(**{name: "nonsense"})
  with pytest.raises(ValueError, match="state-only"):
    ModelConfig(use_images=True, object_tokens="per_object")
  with pytest.raises(ValueError, match="model.plug.site"):
    PlugConfig(site="middle")
  with pytest.raises(ValueError, match="sd_kind"):
    losses.LossWeights(sd_kind="cos")


# ---- readings of the paper's text ----------------------------------------------
@functools.lru_cache(maxsize=None)
def _interactor_codes_fn(cfg: ModelConfig):
  """A jitted training pass returning the skill codes the interactor receives and the
  posterior's offset W z."""
  model = Policy(cfg)
  interactors = tuple(INTERACTORS.values())

  def fn(v, b, key):
    seen = {}

    def intercept(next_fun, args, kwargs, context):
      out = next_fun(*args, **kwargs)
      if context.method_name == "__call__" and isinstance(context.module, interactors):
        seen["skills"] = args[1]
      if context.method_name == "__call__" and isinstance(context.module, TrajectorySkillPosterior):
        seen["offset"] = out["offset"]
      return out

    with nn.intercept_methods(intercept):
      model.apply(v, b, train=True, rngs=_rngs(key))
    return seen
  return jax.jit(fn, compiler_options=FAST_COMPILE)


def test_skill_offset_sample_mean_none():
  """'sample': the interactor's skill codes change with the posterior's draw; 'mean': they do
  not, and are s_k + W mu_k; 'none': they are s_k whatever the posterior says."""
  cfg = small()
  batch = make_batch(cfg)
  variables = host_params(cfg)
  skills = variables["params"]["skills"]["embeddings"]
  codes = {}
  for mode in ("sample", "mean", "none"):
    c = model_config(cfg, skill_offset=mode)
    codes[mode] = [_interactor_codes_fn(c)(variables, batch, jax.random.key(seed)) for seed in (0, 1)]
  a, b = codes["sample"]
  assert not np.allclose(a["skills"], b["skills"])
  a, b = codes["mean"]
  np.testing.assert_allclose(a["skills"], b["skills"])
  np.testing.assert_allclose(a["skills"], skills[None] + a["offset"], rtol=1e-6)
  assert np.abs(a["offset"]).max() > 1e-3  # W mu is not zero here
  for seen in codes["none"]:
    np.testing.assert_array_equal(seen["skills"], jnp.broadcast_to(skills, (B,) + skills.shape))


@functools.lru_cache(maxsize=None)
def _routing_with_style_token(cfg: ModelConfig):
  """Router weights of a validation pass whose encoder's style token (h[:, 0]) is moved by `shift`."""
  model = Policy(cfg)

  def fn(v, b, shift):
    def intercept(next_fun, args, kwargs, context):
      out = next_fun(*args, **kwargs)
      if isinstance(context.module, Encoder) and context.method_name == "__call__":
        h, pos = out
        return h.at[:, 0].add(shift), pos
      return out
    with nn.intercept_methods(intercept):
      return model.apply(v, b, train=False)["router_probs"]
  return jax.jit(fn, compiler_options=FAST_COMPILE)


def test_router_input_no_style_does_not_read_the_style_token():
  cfg = small()
  batch = make_batch(cfg)
  variables = host_params(cfg)
  for mode, moves in (("all", True), ("no_style", False)):
    c = model_config(cfg, router_input=mode)
    r0 = _routing_with_style_token(c)(variables, batch, 0.0)
    r1 = _routing_with_style_token(c)(variables, batch, 5.0)
    assert (not np.allclose(r0, r1, atol=1e-5)) == moves, mode


def test_router_cue_reaches_the_router_alone():
  """router_cue_slots=2: the last 2 object slots move the routing (training and inference
  paths) but, with the routing fixed, not the actions; without the switch they move both."""
  batch = make_batch(small())
  moved = dict(batch, object_state=batch["object_state"].at[:, -14:].add(3.0))
  for n, cue_moves_actions in ((0, True), (2, False)):
    cfg = small(router_cue_slots=n)
    variables = host_params(cfg)
    fixed = jnp.full((cfg.plug.num_skills,), 1.0 / cfg.plug.num_skills)
    (a0, r0), (a1, r1) = (_predict_fixed_fn(cfg)(variables, b, fixed) for b in (batch, moved))
    assert not np.allclose(r0, r1, atol=1e-5), n  # the router reads the cue either way
    assert (not np.allclose(a0, a1, atol=1e-5)) == cue_moves_actions, n
    t0, t1 = (forward(cfg, variables, b, train=False)["router_probs"] for b in (batch, moved))
    assert not np.allclose(t0, t1, atol=1e-5), n
  with pytest.raises(ValueError, match="router_cue_slots"):
    PlugConfig(router_cue_slots=-1)


@functools.lru_cache(maxsize=None)
def _predict_fixed_fn(cfg: ModelConfig):
  """(actions with the routing fixed, the router's own routing)."""
  model = Policy(cfg)

  def fn(v, b, routing):
    actions, _ = model.apply(v, b, routing, method=Policy.predict)
    _, own = model.apply(v, b, method=Policy.predict)
    return actions, own
  return jax.jit(fn, compiler_options=FAST_COMPILE)


def test_skill_tokens_let_a_skill_write_content():
  """Scene tokens of equal content: attention over them returns that content whatever the
  query, so query offsets cannot tell skills apart; a skill token among the keys and values can."""
  rng = np.random.default_rng(0)
  K, N, D = 3, 4, 32
  h = jnp.asarray(np.tile(rng.normal(size=(B, 1, D)), (1, N, 1)), jnp.float32)
  skills = jnp.asarray(rng.normal(size=(B, K, D)), jnp.float32)
  spread = {}
  jit = lambda f: jax.jit(f, compiler_options=FAST_COMPILE)  # noqa: E731
  for name in ("query_offset", "skill_tokens"):
    module = INTERACTORS[name](D, 2, 64)
    v = jit(module.init)(jax.random.key(1), h, skills)
    u = jit(module.apply)(v, h, skills)
    assert u.shape == (B, K, N, D)
    spread[name] = float(jnp.abs(u - u[:, :1]).max())
  assert spread["query_offset"] < 1e-5 and spread["skill_tokens"] > 1e-2
  # the skill reaches u through the value projection: its gradient there is not zero
  g = jit(jax.grad(lambda v: module.apply(v, h, skills).var(axis=1).sum()))(v)
  assert np.abs(g["params"]["attn"]["value"]["kernel"]).max() > 0
  assert np.abs(g["params"]["skill_proj"]["kernel"]).max() > 0


def test_per_object_tokens():
  """One scene token per object slot: 2 + 28 / 7 = 6 tokens; a shared projection of each
  slot's 7 numbers with a learned slot position; moving one object moves the tokens."""
  cfg = small(object_tokens="per_object")
  slots = envs.OBJECT_STATE_DIM // 7
  assert num_tokens(cfg) == 2 + slots == 6 and num_tokens(small()) == 3
  batch = make_batch(cfg)
  enc = Encoder(cfg)
  v = jax.eval_shape(enc.init, jax.random.key(0), batch, jnp.zeros((B, cfg.latent_dim)))
  rng = np.random.default_rng(0)
  v = jax.tree.map(lambda s: jnp.asarray(0.3 * rng.standard_normal(s.shape), s.dtype), v)
  encode = jax.jit(lambda v, b: enc.apply(v, b, jnp.zeros((B, cfg.latent_dim))), compiler_options=FAST_COMPILE)
  p = v["params"]
  assert p["object_fc1"]["kernel"].shape == (7, cfg.hidden) and p["object_pos"].shape == (slots, cfg.hidden)
  assert "state_fc1" not in p
  h, _ = encode(v, batch)
  assert h.shape == (B, 6, cfg.hidden)
  moved = dict(batch, object_state=batch["object_state"].at[:, 7:14].add(1.0))  # the second object
  assert not np.allclose(encode(v, moved)[0], h, atol=1e-4)
  with pytest.raises(ValueError, match="whole 7-number"):
    jax.eval_shape(enc.init, jax.random.key(0), dict(batch, object_state=batch["object_state"][:, :27]),
                   jnp.zeros((B, cfg.latent_dim)))


def _to_decoder_layout(params):
  """Default-layout parameters regrouped for plug.site='decoder' (the same values)."""
  params = dict(params)
  head = dict(params["action_head"])
  params["action_proj"] = {k: head.pop(k) for k in ("final_norm", "action_proj")}
  params["action_head"] = head
  return params


@pytest.mark.parametrize("policy", ["act", "skillplug"])
def test_decoder_site_groups_and_light_head(policy):
  """plug.site='decoder': the head splits into action_head (queries, decoder) and action_proj
  (final norm, projection) for both policies; ACT's forward is unchanged by the split; the
  plug reads the decoder's steps; freezing all but router and action_proj trains only those."""
  cfg = small(policy, site="decoder")
  batch = make_batch(cfg)
  variables = host_params(cfg)
  groups = param_groups(variables)
  assert "action_proj" in groups and groups <= set(GROUPS)
  assert set(variables["params"]["action_proj"]) == {"final_norm", "action_proj"}
  assert "final_norm" not in variables["params"]["action_head"]
  if policy == "act":
    default = small(policy)
    v0 = host_params(default)
    chunk0, _ = predict(default, v0, batch)
    chunk1, _ = predict(cfg, {"params": _to_decoder_layout(v0["params"])}, batch)
    np.testing.assert_allclose(chunk1, chunk0, rtol=1e-6, atol=1e-6)
    trainable = {"action_proj"}
  else:
    out = forward(cfg, variables, batch)
    assert out["plug_input"].shape == (B, cfg.chunk, cfg.hidden)
    assert out["skill_tokens"].shape == (B, cfg.plug.num_skills, cfg.chunk, cfg.hidden)
    assert out["router_probs"].shape == (B, cfg.plug.num_skills)  # chunk-level routing
    _, routing = predict(cfg, variables, batch)
    assert routing.shape == (B, cfg.plug.num_skills)
    trainable = {"router", "action_proj"}
  grads = jax.tree.map(jnp.ones_like, variables)  # what is masked, not what the loss gives
  opt = masked_optimizer(optax.adam(1e-2), variables, trainable)
  updates, _ = opt.update(grads, opt.init(variables), variables)
  new = optax.apply_updates(variables, updates)
  for name in groups:
    changed = any(np.any(a != b) for a, b in zip(jax.tree.leaves(new["params"][name]),
                                                 jax.tree.leaves(variables["params"][name])))
    assert changed == (name in trainable), name


@pytest.mark.parametrize("kw", [dict(interactor="skill_tokens", site="decoder", positions="qk"),
                                dict(object_tokens="per_object", skill_offset="mean", router_input="no_style",
                                     router_cue_slots=1)])
def test_switches_combine_and_train_finite(kw):
  cfg = small(**kw)
  batch = dict(make_batch(cfg), skill_label=jnp.array([0, 2], jnp.int32))
  variables = host_params(cfg)
  model = Policy(cfg)
  w = losses.LossWeights(sd_kind="gram", sd_usage_weighted=True, usage=0.5, router_label=0.1)
  loss, m = jax.jit(lambda v: losses.total_loss(model.apply(v, batch, train=True, rngs=rngs()), batch, w),
                    compiler_options=FAST_COMPILE)(variables)
  assert {"usage", "router_label"} <= set(m)
  assert np.isfinite(float(loss)) and all(np.isfinite(np.asarray(x)).all() for x in m.values())


@pytest.mark.parametrize("kw", [dict(), dict(site="decoder")])
def test_plug_geometry_of_a_model_reads_the_inference_path(kw):
  from skillplug_jax import diagnostics
  cfg = small(**kw)
  batch = make_batch(cfg)
  variables = host_params(cfg)
  g = diagnostics.plug_geometry(cfg, variables["params"], batch)
  k = cfg.plug.num_skills
  assert g["cos_signed"].shape == g["cos_abs_centred"].shape == (k, k)
  # the cosines of the inference path's token-averaged u_k, computed here by hand
  f = jax.jit(lambda v, o: Policy(cfg).apply(v, o, method=Policy.features),
              compiler_options=FAST_COMPILE)(variables, batch)
  mean_u = np.asarray(f["skill_tokens"], np.float64).mean(axis=2)
  unit = mean_u / np.linalg.norm(mean_u, axis=-1, keepdims=True)
  np.testing.assert_allclose(g["cos_signed"], np.einsum("bkd,bjd->bkj", unit, unit).mean(0), rtol=1e-4, atol=1e-5)
  assert float(g["fused_offset_ratio"]) > 0 and np.isfinite(float(g["token_spread"]))
  _, routing = predict(cfg, variables, batch)
  np.testing.assert_allclose(g["routing"]["mean_weights"], np.asarray(routing).mean(0), rtol=1e-5)
