"""Each loss term against numbers worked out by hand."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from skillplug_jax import losses


def test_reconstruction_l1_averages_valid_steps_only():
  pred = jnp.zeros((2, 3, 2))
  target = jnp.array([[[1., 2.], [3., -1.], [100., 100.]],
                      [[2., 0.], [50., 50.], [50., 50.]]])
  mask = jnp.array([[True, True, False], [True, False, False]])
  # valid |errors|: 1+2+3+1 and 2+0, over 4+2 steps x 2 dims
  assert float(losses.reconstruction_l1(pred, target, mask)) == pytest.approx(9 / 6)
  # padded steps get no gradient
  grad = jax.grad(losses.reconstruction_l1)(pred + 0.5, target, mask)
  assert np.all(np.asarray(grad)[~np.asarray(mask)] == 0)
  assert np.all(np.asarray(grad)[np.asarray(mask)] != 0)


def test_reconstruction_l1_without_padding_is_plain_mean():
  pred = jnp.arange(12.).reshape(1, 4, 3)
  target = jnp.zeros_like(pred)
  assert float(losses.reconstruction_l1(pred, target, jnp.ones((1, 4), bool))) == pytest.approx(5.5)


def test_kl_zero_at_prior_and_hand_values():
  assert float(losses.kl_standard_normal(jnp.zeros((3, 4, 8)), jnp.zeros((3, 4, 8)))) == 0.0
  # sum over latent dims: 0.5 * (1 + 4)
  kl = losses.kl_standard_normal(jnp.array([[1., 2.]]), jnp.zeros((1, 2)))
  assert float(kl) == pytest.approx(2.5)
  # variance 2: 0.5 * (2 - 1 - ln 2)
  assert float(losses.kl_standard_normal(jnp.zeros((1, 1)), jnp.full((1, 1), math.log(2.)))) \
      == pytest.approx(0.5 * (1 - math.log(2.)))
  # mean over [B, K]: entries 2.5 and 0
  mu = jnp.array([[[1., 2.], [0., 0.]]])
  assert float(losses.kl_standard_normal(mu, jnp.zeros_like(mu))) == pytest.approx(1.25)


def test_bsa_hand_values():
  # one-hot target, uniform scores: log 2
  assert float(losses.behaviour_skill_alignment(jnp.array([[1., 0.]]), jnp.zeros((1, 2)))) \
      == pytest.approx(math.log(2.))
  # scores whose softmax equals the target: the target's entropy
  r = jnp.array([[0.25, 0.75]])
  entropy = -(0.25 * math.log(0.25) + 0.75 * math.log(0.75))
  assert float(losses.behaviour_skill_alignment(r, jnp.log(r))) == pytest.approx(entropy, rel=1e-6)


def test_bsa_gives_router_no_gradient():
  r = jax.nn.softmax(jnp.array([[0.3, -1.0, 2.0, 0.1], [1.0, 1.0, 0.0, -2.0]]))
  logits = jnp.array([[1.0, 0.0, -1.0, 0.5], [0.0, 2.0, 0.0, 1.0]])
  g_r, g_logits = jax.grad(losses.behaviour_skill_alignment, argnums=(0, 1))(r, logits)
  assert np.all(np.asarray(g_r) == 0)
  # d/dlogits of the batch-mean cross-entropy: (softmax - target) / B
  np.testing.assert_allclose(g_logits, (jax.nn.softmax(logits) - r) / 2, atol=1e-6)


def test_skill_diversity_orthogonal_identical_and_hand_value():
  assert float(losses.skill_diversity(jnp.eye(4)[None] * 3.0)) == pytest.approx(0.0, abs=1e-7)
  same = jnp.tile(jnp.array([[1.0, -2.0, 0.5]]), (4, 1))[None]
  assert float(losses.skill_diversity(same)) == pytest.approx(1.0)
  assert float(losses.skill_diversity(jnp.array([[[1., 0.], [-2., 0.]]]))) == pytest.approx(-1.0)
  # cosines 0, 1/sqrt2, 1/sqrt2 (each counted twice) over K(K-1) = 6; scale-free
  u = jnp.array([[[1., 0.], [0., 5.], [2., 2.]]])
  assert float(losses.skill_diversity(u)) == pytest.approx(math.sqrt(2) / 3, rel=1e-6)
  batch = jnp.stack([jnp.eye(4), jnp.ones((4, 4))])  # averaged over the batch
  assert float(losses.skill_diversity(batch)) == pytest.approx(0.5)


def test_skill_diversity_floor_is_reached_by_any_outputs_whose_directions_cancel():
  """L_SD = (|sum_k u_k/|u_k||^2 - K) / (K(K-1)): its floor -1/(K-1) holds for every library whose
  normalised outputs sum to zero, a regular simplex and two antipodal pairs (two skills, each
  duplicated) alike, which is the state the cpu runs reach (docs/results/paper_cpu/skill_probes.md)."""
  rng = np.random.default_rng(0)
  m, d = rng.normal(size=8), 20.0 * rng.normal(size=8)
  pairs = jnp.asarray(np.stack([m + d, m + d, m - d, m - d]))[None]  # u_k = m +- d, |d| >> |m|
  simplex = jnp.asarray(np.eye(4) - 0.25)[None]
  for u in (pairs, simplex):
    unit = u / jnp.linalg.norm(u, axis=-1, keepdims=True)
    identity = (jnp.sum(unit.sum(1) ** 2) - 4) / 12
    assert float(losses.skill_diversity(u)) == pytest.approx(float(identity), abs=1e-6)
  assert float(losses.skill_diversity(simplex)) == pytest.approx(-1 / 3, abs=1e-6)
  assert float(losses.skill_diversity(pairs)) == pytest.approx(-1 / 3, abs=2e-3)
  # and their uniform mixture is the small common part m: the skills cancel
  assert float(jnp.linalg.norm(pairs[0].mean(0) - m)) < 1e-5


def _outputs(skillplug: bool):
  out = dict(pred_actions=jnp.zeros((1, 2, 1)), cvae_mu=jnp.array([[1., 0.]]),
             cvae_logvar=jnp.zeros((1, 2)))
  if skillplug:
    out.update(router_probs=jnp.array([[1., 0.]]), traj_logits=jnp.zeros((1, 2)),
               skill_features=jnp.array([[[1., 0.], [1., 0.]]]),
               posterior_mu=jnp.array([[[2.], [0.]]]), posterior_logvar=jnp.zeros((1, 2, 1)))
  return out


def test_total_loss_weights_each_term():
  batch = dict(actions=jnp.array([[[1.], [7.]]]), action_mask=jnp.array([[True, False]]))
  w = losses.LossWeights(rec=1.0, kl=0.5, bsa=2.0, sd=3.0, cvae_kl=10.0)
  loss, m = losses.total_loss(_outputs(False), batch, w)
  assert set(m) == {"loss", "rec", "cvae_kl"}
  assert float(m["rec"]) == pytest.approx(1.0) and float(m["cvae_kl"]) == pytest.approx(0.5)
  assert float(loss) == pytest.approx(1.0 + 10 * 0.5)

  loss, m = losses.total_loss(_outputs(True), batch, w)
  assert {k for k in m if not k.startswith("diag_")} == {"loss", "rec", "cvae_kl", "kl", "bsa", "sd"}
  assert float(m["kl"]) == pytest.approx(1.0)  # mean over k of 2 and 0
  assert float(m["bsa"]) == pytest.approx(math.log(2.))
  assert float(m["sd"]) == pytest.approx(1.0)
  assert float(loss) == pytest.approx(1.0 + 5.0 + 0.5 * 1.0 + 2.0 * math.log(2.) + 3.0 * 1.0)
  assert float(m["loss"]) == float(loss)


def test_default_weights_give_acts_objective():
  """Without weights, ACT's loss is ACT's own: L1 + 10 KL (its CVAE weight)."""
  batch = dict(actions=jnp.array([[[1.], [7.]]]), action_mask=jnp.array([[True, False]]))
  loss, m = losses.total_loss(_outputs(False), batch)
  assert float(m["rec"]) == pytest.approx(1.0) and float(m["cvae_kl"]) == pytest.approx(0.5)
  assert float(loss) == pytest.approx(1.0 + 10.0 * 0.5)


def test_router_label_loss_hand_values_and_labels_outside_the_library_left_out():
  probs = jnp.array([[0.5, 0.25, 0.25], [0.1, 0.8, 0.1], [0.2, 0.2, 0.6]])
  assert float(losses.router_label_loss(probs, jnp.array([0, 1, 2]))) == pytest.approx(
      -(math.log(0.5) + math.log(0.8) + math.log(0.6)) / 3, rel=1e-5)
  # -1 (an episode's end) and 3 (no such skill) are not counted, in the sum or the mean
  assert float(losses.router_label_loss(probs, jnp.array([-1, 1, 3]))) == pytest.approx(-math.log(0.8), rel=1e-5)
  assert float(losses.router_label_loss(probs, jnp.array([-1, -1, 5]))) == 0.0


def test_router_label_term_needs_labels_and_is_weighted():
  batch = dict(actions=jnp.array([[[1.], [7.]]]), action_mask=jnp.array([[True, False]]))
  w = losses.LossWeights(rec=1.0, kl=0.0, bsa=0.0, sd=0.0, cvae_kl=0.0, router_label=2.0)
  out = dict(_outputs(True), router_probs=jnp.array([[0.25, 0.75]]))
  with pytest.raises(ValueError, match="skill_label"):
    losses.total_loss(out, batch, w)
  loss, m = losses.total_loss(out, dict(batch, skill_label=jnp.array([1])), w)
  assert float(m["router_label"]) == pytest.approx(-math.log(0.75), rel=1e-5)
  assert float(loss) == pytest.approx(float(m["rec"]) + 2.0 * -math.log(0.75), rel=1e-5)
  _, m0 = losses.total_loss(out, batch, dataclasses.replace(w, router_label=0.0))
  assert "router_label" not in m0  # off by default: the paper's objective is unchanged
