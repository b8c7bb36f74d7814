"""The diagnostics and the loss terms of issue 27 against values worked out by hand."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from skillplug_jax import diagnostics, losses
from skillplug_jax.evaluate import protocol, tables


# ---- disentanglement variants ------------------------------------------------------
def test_antipodal_pair_is_the_paper_losss_best_and_the_squared_losss_worst():
  """K=2: the paper's mean signed cosine is minimal (-1) at an antipodal pair, exactly where
  the squared and Gram variants are maximal (1); orthogonal features are their minimum (0)."""
  rng = np.random.default_rng(0)
  d, n = 8, 3
  a = rng.normal(size=d)
  h = jnp.asarray(rng.normal(size=(1, n, d)), jnp.float32)
  b = np.linalg.qr(np.stack([a, rng.normal(size=d)], 1))[0][:, 1] * 2.0  # orthogonal to a

  def sd(kind, x, y):
    feats = jnp.asarray(np.stack([x, y])[None], jnp.float32)  # [1, 2, D]
    centred = jnp.broadcast_to(feats[:, :, None], (1, 2, n, d))  # u_k - h, the same on every token
    return float(losses.skill_diversity(feats, kind, centred))

  assert sd("cosine", a, -a) == pytest.approx(-1.0, abs=1e-6)
  assert sd("squared", a, -a) == pytest.approx(1.0, abs=1e-6)
  assert sd("gram", a, -a) == pytest.approx(1.0, abs=1e-6)
  for kind in ("squared", "gram"):
    assert sd(kind, a, b) == pytest.approx(0.0, abs=1e-6)
    assert sd(kind, a, a) == pytest.approx(1.0, abs=1e-6)
    assert sd(kind, a, b) < sd(kind, a, 0.5 * a + b) < sd(kind, a, -a)  # worse as the pair turns antipodal
  # the paper's loss prefers the antipodal pair to the orthogonal one; ours the reverse
  assert sd("cosine", a, -a) < sd("cosine", a, b)
  # K=4, two antipodal pairs (the cancelling library measured at CPU scale): the paper's
  # floor -1/(K-1), with zero gradient; for the squared loss 1/3, against 0 for four
  # orthogonal skills, which the paper's loss rates worse (0)
  c = np.linalg.qr(rng.normal(size=(d, 4)))[0].T
  four = jnp.asarray(np.stack([c[0], -c[0], c[1], -c[1]])[None], jnp.float32)
  orthogonal = jnp.asarray(c[None], jnp.float32)
  assert float(losses.skill_diversity(four)) == pytest.approx(-1 / 3, abs=1e-6)
  assert float(jnp.abs(jax.grad(lambda x: losses.skill_diversity(x))(four)).max()) < 1e-6
  assert float(losses.skill_diversity(orthogonal)) == pytest.approx(0.0, abs=1e-6)
  assert float(losses.skill_diversity(four, "squared")) == pytest.approx(1 / 3, abs=1e-6)
  assert float(losses.skill_diversity(orthogonal, "squared")) == pytest.approx(0.0, abs=1e-6)
  with pytest.raises(ValueError, match="centred"):
    losses.skill_diversity(four, "gram")


def test_gram_reads_every_token_of_the_skill_dependent_part():
  """Two skills adding opposite per-token patterns have the same (zero) token mean: only the
  Gram variant, on u_k - h token by token, sees them as antipodal."""
  pattern = jnp.asarray([[1.0, 0.0], [-1.0, 0.0]])  # [N=2, D=2], token mean zero
  centred = jnp.stack([pattern, -pattern])[None]  # [1, K=2, N, D]
  feats = jnp.asarray([[[0.0, 1.0], [0.0, 1.0]]])  # both skills' token means: the same vector
  assert float(losses.skill_diversity(feats, "gram", centred)) == pytest.approx(1.0)
  rot = jnp.stack([pattern, pattern[:, ::-1]])[None]  # orthogonal per-token patterns
  assert float(losses.skill_diversity(feats, "gram", rot)) == pytest.approx(0.0)


def test_usage_weighted_sd_ignores_skills_the_router_does_not_use():
  e = np.eye(4)
  feats = jnp.asarray(np.stack([e[0], e[1], e[0]])[None], jnp.float32)  # skill 2 copies skill 0
  plain = float(losses.skill_diversity(feats, "squared"))
  assert plain == pytest.approx(2 / 6)  # the pair (0, 2), both ways, of 6 off-diagonal entries
  unused = float(losses.skill_diversity(feats, "squared", usage=jnp.asarray([0.5, 0.5, 0.0])))
  assert unused == pytest.approx(0.0, abs=1e-7)
  equal = float(losses.skill_diversity(feats, "squared", usage=jnp.full(3, 1 / 3)))
  assert equal == pytest.approx(plain, rel=1e-6)
  # the weights carry no gradient to the router
  g = jax.grad(lambda r: losses.skill_diversity(feats, "squared", usage=r))(jnp.asarray([0.2, 0.3, 0.5]))
  assert np.all(np.asarray(g) == 0)


# ---- routing terms ---------------------------------------------------------------
def test_usage_term_rewards_decisive_routing_that_uses_every_skill():
  k = 4
  confident = jnp.eye(k)[jnp.arange(8) % k]  # one-hot, every skill as often
  uniform = jnp.full((8, k), 1 / k)
  collapsed = jnp.eye(k)[jnp.zeros(8, int)]
  assert float(losses.mutual_information_usage(confident)) == pytest.approx(-math.log(k), rel=1e-6)
  assert float(losses.mutual_information_usage(uniform)) == pytest.approx(0.0, abs=1e-6)
  assert float(losses.mutual_information_usage(collapsed)) == pytest.approx(0.0, abs=1e-6)
  rng = np.random.default_rng(0)
  for _ in range(5):  # -log K is its minimum
    p = jax.nn.softmax(jnp.asarray(3 * rng.normal(size=(8, k)), jnp.float32))
    assert -math.log(k) - 1e-6 <= float(losses.mutual_information_usage(p)) <= 1e-6


def _outputs():
  rng = np.random.default_rng(1)
  b, k, n, d = 4, 3, 2, 5
  logits = jnp.asarray(rng.normal(size=(b, k)), jnp.float32)
  u = jnp.asarray(rng.normal(size=(b, k, n, d)), jnp.float32)
  return dict(pred_actions=jnp.zeros((b, 2, 1)), cvae_mu=jnp.zeros((b, 2)), cvae_logvar=jnp.zeros((b, 2)),
              router_probs=jax.nn.softmax(logits), router_logits=logits,
              skill_features=u.mean(2), skill_tokens=u, plug_input=jnp.asarray(rng.normal(size=(b, n, d)), jnp.float32),
              posterior_mu=jnp.zeros((b, k, 2)), posterior_logvar=jnp.zeros((b, k, 2)),
              traj_logits=jnp.asarray(rng.normal(size=(b, k)), jnp.float32))


BATCH = dict(actions=jnp.zeros((4, 2, 1)), action_mask=jnp.ones((4, 2), bool), task_id=jnp.asarray([0, 0, 1, 2]))


def test_new_terms_appear_with_their_weights_and_add_to_the_loss():
  out = _outputs()
  base_loss, base = losses.total_loss(out, BATCH)
  terms = {k for k in base if not k.startswith("diag_")}
  assert terms == {"loss", "rec", "cvae_kl", "kl", "bsa", "sd"}
  labelled = dict(BATCH, skill_label=jnp.asarray([0, 2, 1, 7]))  # 7: outside the library, left out
  w = losses.LossWeights(usage=0.5, router_label=0.25)
  loss, m = losses.total_loss(out, labelled, w)
  assert {k for k in m if not k.startswith("diag_")} == terms | set(losses.AUX_TERMS)
  assert float(m["usage"]) == pytest.approx(float(losses.mutual_information_usage(out["router_probs"])))
  p = np.asarray(out["router_probs"], np.float64)
  assert float(m["router_label"]) == pytest.approx(-np.mean(np.log([p[0, 0], p[1, 2], p[2, 1]])), rel=1e-5)
  assert float(loss) == pytest.approx(float(base_loss) + 0.5 * float(m["usage"]) + 0.25 * float(m["router_label"]),
                                      rel=1e-6)
  # a term whose batch key is missing is named, not skipped
  with pytest.raises(ValueError, match="loss.router_label > 0 needs batches with 'skill_label'"):
    losses.total_loss(out, BATCH, w)
  _, m2 = losses.total_loss(out, BATCH, losses.LossWeights(sd_kind="gram", sd_usage_weighted=True))
  assert float(m2["sd"]) != pytest.approx(float(base["sd"]))


def test_diagnostics_change_neither_loss_nor_gradients():
  out = _outputs()

  def loss_of(o, diag):
    loss, m = losses.total_loss(o, BATCH)
    return loss + (sum(v.sum() for k, v in m.items() if k.startswith("diag_")) if diag else 0.0)

  g_plain = jax.grad(loss_of)(out, False)
  g_diag = jax.grad(loss_of)(out, True)
  for k in out:
    np.testing.assert_array_equal(g_plain[k], g_diag[k], err_msg=k)
  _, m = losses.total_loss(out, BATCH)
  names = {k for k in m if k.startswith("diag_")}
  assert {"diag_usage_entropy", "diag_routing_entropy_per_query", "diag_effective_skills", "diag_task_skill_mi",
          "diag_abs_cos", "diag_fused_offset_ratio", "diag_token_spread"} <= names
  assert all(np.isfinite(float(m[k])) for k in names)


# ---- routing statistics --------------------------------------------------------------
def test_routing_stats_of_uniform_routing():
  k = 4
  s = diagnostics.routing_stats(jnp.full((12, k), 1 / k), jnp.arange(12) % 3)
  assert float(s["routing_entropy_per_query"]) == pytest.approx(1.0)
  assert float(s["usage_entropy"]) == pytest.approx(1.0)
  assert float(s["effective_skills"]) == pytest.approx(k)
  assert float(s["task_skill_mi"]) == pytest.approx(0.0, abs=1e-6)
  assert float(s["num_tasks"]) == 3


def test_routing_stats_of_one_skill_per_task():
  """K tasks routed one-hot to K different skills: decisive (query entropy 0), every skill
  used (usage 1, K effective), and the task tells the skill: I(T;S) = log K."""
  k = 4
  tasks = jnp.asarray([3, 1, 0, 2, 2, 1, 0, 3, 1, 2, 3, 0]) * 10  # any labels, relabelled inside
  probs = jax.nn.one_hot(tasks // 10, k)
  s = diagnostics.routing_stats(probs, tasks)
  assert float(s["routing_entropy_per_query"]) == pytest.approx(0.0, abs=1e-6)
  assert float(s["usage_entropy"]) == pytest.approx(1.0, abs=1e-6)
  assert float(s["effective_skills"]) == pytest.approx(k, rel=1e-5)
  assert float(s["task_skill_mi"]) == pytest.approx(math.log(k), rel=1e-5)
  assert float(s["task_skill_mi_norm"]) == pytest.approx(1.0, rel=1e-5)
  # dense task ids with their number: per-task routing rows
  dense = diagnostics.routing_stats(probs, tasks // 10, num_tasks=5)
  np.testing.assert_allclose(dense["task_routing"][:4], np.eye(k), atol=1e-7)
  assert float(dense["task_queries"][4]) == 0 and float(dense["num_tasks"]) == 4
  # one skill for every task: nothing to tell
  s = diagnostics.routing_stats(jax.nn.one_hot(jnp.zeros(12, int), k), tasks)
  assert float(s["task_skill_mi"]) == pytest.approx(0.0, abs=1e-6)
  assert float(s["effective_skills"]) == pytest.approx(1.0)
  # jit-safe
  jitted = jax.jit(diagnostics.routing_stats)(probs, tasks)
  assert float(jitted["task_skill_mi"]) == pytest.approx(math.log(k), rel=1e-5)


def test_label_skill_mi_reads_the_labelled_queries_only():
  """Each phase routed one-hot to its own skill: the routing tells the phase (normalised MI 1),
  and unlabelled queries (-1), routed anywhere, change nothing; routing that ignores the phase: 0."""
  k = 4
  labels = jnp.asarray([0, 1, 2, 3, 1, 2, 0, 3])
  probs = jax.nn.one_hot(labels, k)
  noise = jax.nn.one_hot(jnp.asarray([2, 2, 0]), k)  # unlabelled queries, routed at random
  s = diagnostics.label_skill_mi(jnp.concatenate([probs, noise]), jnp.concatenate([labels, jnp.full(3, -1)]))
  assert float(s["label_skill_mi"]) == pytest.approx(math.log(k), rel=1e-5)
  assert float(s["label_skill_mi_norm"]) == pytest.approx(1.0, rel=1e-5)
  s = jax.jit(diagnostics.label_skill_mi)(jnp.full((8, k), 1 / k), labels)
  assert float(s["label_skill_mi"]) == pytest.approx(0.0, abs=1e-6)
  # two phases present: normalised by log 2, not log K
  two = diagnostics.label_skill_mi(jax.nn.one_hot(jnp.asarray([0, 1, 0, 1]), k), jnp.asarray([0, 1, 0, 1]))
  assert float(two["label_skill_mi_norm"]) == pytest.approx(1.0, rel=1e-5)


def test_training_logs_the_phase_information_when_the_batch_has_labels():
  k, b = 4, 8
  labels = jnp.asarray([0, 1, 2, 3, 3, 2, 1, 0])
  out = dict(router_probs=jax.nn.one_hot(labels, k))
  assert "diag_label_skill_mi_norm" not in diagnostics.training_metrics(out)
  m = diagnostics.training_metrics(out, jnp.zeros(b, int), labels)
  assert float(m["diag_label_skill_mi_norm"]) == pytest.approx(1.0, rel=1e-5)


def test_combining_tasks_equals_the_stats_of_all_queries():
  rng = np.random.default_rng(0)
  parts = [jax.nn.softmax(jnp.asarray(rng.normal(size=(n, 3)) * 2 + rng.normal(size=3) * 2, jnp.float32))
           for n in (5, 9, 3)]
  per_task = [dict(diagnostics.as_json(diagnostics.routing_stats(p)), queries=p.shape[0]) for p in parts]
  combined = diagnostics.combine_tasks(per_task)
  ids = jnp.concatenate([jnp.full(p.shape[0], i) for i, p in enumerate(parts)])
  direct = diagnostics.routing_stats(jnp.concatenate(parts), ids, num_tasks=3)
  for k in ("usage_entropy", "routing_entropy_per_query", "effective_skills", "task_skill_mi", "task_skill_mi_norm"):
    assert combined[k] == pytest.approx(float(direct[k]), rel=1e-5, abs=1e-7), k


def test_evaluation_results_carry_routing_diagnostics():
  """protocol: a task's diagnostics from the recorded routing arrays (NaN where no query,
  padded trials dropped); tables: each seed's statistics over its tasks, and mean and SE."""
  k = 2
  nan = np.full(k, np.nan)
  part = np.asarray([[[1, 0], [0, 1], [1, 0]],  # step 0: three trials (the third one padding)
                     [nan, [0, 1], nan]], np.float32)  # [steps, envs, K]
  d = protocol.routing_diagnostics([part], trials=2)
  assert d["queries"] == 3 and d["routing_entropy_per_query"] == pytest.approx(0.0, abs=1e-6)
  assert d["mean_weights"] == pytest.approx([1 / 3, 2 / 3])
  assert protocol.routing_diagnostics([np.full((2, 1, k), np.nan, np.float32)], trials=1) == {"queries": 0}

  def result(skill):  # a task whose every query picks `skill`
    return {"diagnostics": dict(diagnostics.as_json(diagnostics.routing_stats(jnp.eye(k)[jnp.full(4, skill)])),
                                queries=4)}

  out = tables.routing_diagnostics({
      "ACT+SkillPlug": {0: [result(0), result(1)], 1: [result(0), result(0)]},
      "ACT": {0: [{}, {}]}}, ["a", "b"])
  assert list(out) == ["ACT+SkillPlug"]
  row = out["ACT+SkillPlug"]
  assert [s["train_seed"] for s in row["seeds"]] == [0, 1]
  assert row["seeds"][0]["task_skill_mi"] == pytest.approx(math.log(2), rel=1e-5)
  assert row["seeds"][1]["task_skill_mi"] == pytest.approx(0.0, abs=1e-6)
  mean, se = row["mean"]["task_skill_mi"]
  assert mean == pytest.approx(math.log(2) / 2, rel=1e-5) and se == pytest.approx(math.log(2) / 2, rel=1e-5)
  assert row["tasks"]["b"]["routing_entropy_per_query"][0] == pytest.approx(0.0, abs=1e-6)


# ---- geometry ----------------------------------------------------------------------
def test_skill_geometry_of_constructed_features():
  """u_k = h + a_k e on every token: cosines of the centred parts are the signs of a_k a_j,
  the skill-dependent part does not vary over tokens (spread 0), and the fused offset is
  |sum_k r_k a_k| |e| / |h|."""
  d, n = 4, 3
  e = np.eye(d)[0]
  h = np.zeros((1, n, d), np.float32)
  h[..., 1] = 2.0  # |h| = 2 per token, orthogonal to e
  a = np.asarray([1.0, -1.0, 0.5], np.float32)
  u = h[:, None] + a[None, :, None, None] * e
  r = np.asarray([[0.5, 0.25, 0.25]], np.float32)
  g = diagnostics.skill_geometry(u, h, r)
  signs = np.sign(a)[:, None] * np.sign(a)[None, :]
  np.testing.assert_allclose(g["cos_signed_centred"], signs, atol=1e-6)
  np.testing.assert_allclose(g["cos_abs_centred"], np.ones((3, 3)), atol=1e-6)
  assert float(g["signed_cos_centred"]) == pytest.approx((2 * (-1) + 2 * 1 + 2 * (-1)) / 6, abs=1e-6)
  # the raw features: u_k = (a_k, 2), cosines (a_k a_j + 4) / (|u_k| |u_j|)
  norms = np.sqrt(a**2 + 4)
  np.testing.assert_allclose(g["cos_signed"], (a[:, None] * a[None] + 4) / np.outer(norms, norms), rtol=1e-5)
  assert float(g["token_spread"]) == pytest.approx(0.0, abs=1e-6)
  assert float(g["fused_offset_ratio"]) == pytest.approx(abs(0.5 - 0.25 + 0.125) / 2.0, rel=1e-6)
  # a part that alternates over the tokens around its mean: spread / |mean| = 1 / 1
  alt = np.asarray([1.0, -1.0, 1.0, -1.0], np.float32)[:, None] * np.eye(d)[2] + e  # N=4
  u2 = (np.zeros((1, 4, d), np.float32) + alt)[:, None]
  g2 = diagnostics.skill_geometry(u2, np.zeros((1, 4, d), np.float32), np.ones((1, 1), np.float32))
  assert float(g2["token_spread"]) == pytest.approx(1.0, rel=1e-6)
