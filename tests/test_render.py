"""NeuS rendering against float64 NumPy references and an analytic sphere."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import parameterized

from ofjax import cameras, render
from ofjax.config import RenderConfig


def _np_sigmoid(x):
  return 1.0 / (1.0 + np.exp(-x))


def np_alpha(prev_sdf, next_sdf, inv_s):
  """NeuS Eq. 13, written independently in float64."""
  p, n = _np_sigmoid(prev_sdf * inv_s), _np_sigmoid(next_sdf * inv_s)
  return np.clip((p - n + 1e-5) / (p + 1e-5), 0.0, 1.0)


def np_weights(alpha):
  """w_i = alpha_i prod_{j<i}(1 - alpha_j + 1e-7), an explicit loop."""
  w = np.zeros_like(alpha)
  for r in range(alpha.shape[0]):
    trans = 1.0
    for i in range(alpha.shape[1]):
      w[r, i] = alpha[r, i] * trans
      trans *= 1.0 - alpha[r, i] + 1e-7
  return w


class CompositingTest(chex.TestCase):

  @chex.variants(with_jit=True, without_jit=True)
  def test_weights_match_numpy_loop(self):
    rng = np.random.default_rng(0)
    alpha = rng.uniform(0, 1, (5, 17))
    got = self.variant(render.composite_weights)(jnp.asarray(alpha, jnp.float32))
    chex.assert_shape(got, (5, 17))
    chex.assert_trees_all_close(np.asarray(got), np_weights(alpha), atol=1e-6)

  @chex.variants(with_jit=True, without_jit=True)
  def test_alpha_matches_numpy(self):
    rng = np.random.default_rng(1)
    prev, nxt = rng.normal(0, 0.1, (2, 4, 9))
    got = self.variant(render.alpha_from_sdf_pair)(jnp.asarray(prev), jnp.asarray(nxt), 37.0)
    chex.assert_trees_all_close(np.asarray(got), np_alpha(prev, nxt, 37.0), atol=1e-6)


def test_sample_pdf_follows_the_weights():
  # Bins [0,1], [1,2], [2,3] with weights 0, 1, 0: every sample must land in [1, 2], evenly.
  t = jnp.array([[0.0, 1.0, 2.0, 3.0]])
  w = jnp.array([[0.0, 1.0, 0.0]])
  s = np.asarray(render.sample_pdf(t, w, 8))[0]
  assert np.all((s > 0.99) & (s < 2.01))
  np.testing.assert_allclose(np.sort(s), 1.0 + (np.arange(8) + 0.5) / 8, atol=0.01)


def test_box_near_far_matches_slab_reference():
  rng = np.random.default_rng(2)
  o = rng.uniform(-3, 3, (200, 3))
  d = rng.normal(size=(200, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  near, far, hit = map(np.asarray, cameras.box_near_far(jnp.asarray(o), jnp.asarray(d)))
  for i in range(200):
    # Brute force: march densely along the ray and find where it is inside the box.
    ts = np.linspace(0, 12, 24001)
    inside = np.all(np.abs(o[i] + ts[:, None] * d[i]) <= 1.0, axis=1)
    assert bool(inside.any()) == bool(hit[i]), i
    if inside.any():
      assert abs(ts[inside][0] - near[i]) < 2e-3 and abs(ts[inside][-1] - far[i]) < 2e-3


@pytest.mark.parametrize("radius", [0.3, 0.6])
def test_rendering_an_analytic_sphere_gives_its_depth(radius):
  """A perfect SDF |x| - r, sharp s and annealed cosine: the depth is the ray-sphere hit."""
  def geometry_fn(x):
    n = jnp.linalg.norm(x, axis=-1, keepdims=True)
    return n[..., 0] - radius, x / n, jnp.zeros(x.shape[:-1] + (0,))

  def color_fn(x, n, f, view):
    rgb = jnp.full(x.shape, 0.5)
    return rgb, jnp.zeros_like(rgb)

  sdf_fn = lambda x: jnp.linalg.norm(x, axis=-1) - radius
  rng = np.random.default_rng(3)
  # Rays from outside the box through points of the sphere's disc (off-centre too).
  xy = rng.uniform(-0.6 * radius, 0.6 * radius, (32, 2))
  o = np.concatenate([xy, np.full((32, 1), -2.5)], 1)
  d = np.tile([0.0, 0.0, 1.0], (32, 1))
  near, far, _ = cameras.box_near_far(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32))
  rc = RenderConfig(n_samples=64, n_importance=64, n_importance_steps=4)
  out = render.render_rays(geometry_fn, color_fn, sdf_fn, jnp.asarray(o, jnp.float32),
                           jnp.asarray(d, jnp.float32), near, far, jax.random.PRNGKey(0),
                           inv_s=4000.0, anneal=1.0, rc=rc, randomize=False)
  expected = 2.5 - np.sqrt(radius**2 - np.sum(xy**2, 1))
  np.testing.assert_array_less(np.abs(np.asarray(out["depth"]) - expected), 1e-3 * radius)
  np.testing.assert_allclose(np.asarray(out["acc"]), 1.0, atol=1e-3)
  np.testing.assert_allclose(np.asarray(out["color"]), 0.5, atol=1e-3)


def test_cos_anneal_is_a_function_of_the_step():
  rc = RenderConfig(cos_anneal_steps=100)
  assert float(render.cos_anneal_ratio(0, rc)) == 0.0
  assert float(render.cos_anneal_ratio(50, rc)) == pytest.approx(0.5)
  assert float(render.cos_anneal_ratio(500, rc)) == 1.0


def test_uncolored_rays_change_nothing_the_colour_losses_see():
  """Skipping the colour networks on the first k rays (training's WLI rays) leaves every output and
  every gradient of a loss on the other rays' colours exactly as rendering all rays would."""
  k, n_rays = 5, 12
  rng = np.random.default_rng(4)
  o = jnp.asarray(np.concatenate([rng.uniform(-0.5, 0.5, (n_rays, 2)), np.full((n_rays, 1), -2.5)],
                                 1), jnp.float32)
  d = jnp.asarray(np.tile([0.0, 0.0, 1.0], (n_rays, 1)), jnp.float32)
  near, far, _ = cameras.box_near_far(o, d)
  target = jnp.asarray(rng.uniform(0, 1, (n_rays, 3)), jnp.float32)
  rc = RenderConfig(n_samples=16, n_importance=8, n_importance_steps=2)

  def render_with(theta, n_uncolored):
    # A sphere of radius theta[0] whose colour depends on theta[1:] and on the normal and feature.
    geometry_fn = lambda x: (jnp.linalg.norm(x, axis=-1) - theta[0], x * (1.0 + theta[0]),
                             x[..., :1] * theta[1])
    color_fn = lambda x, n, f, v: (jax.nn.sigmoid(n * theta[2] + f), jnp.tanh(v * theta[3]))
    sdf_fn = lambda x: jnp.linalg.norm(x, axis=-1) - jax.lax.stop_gradient(theta[0])
    return render.render_rays(geometry_fn, color_fn, sdf_fn, o, d, near, far,
                              jax.random.PRNGKey(1), 50.0, 0.5, rc, n_uncolored=n_uncolored)

  def loss(theta, n_uncolored):
    out = render_with(theta, n_uncolored)
    return (jnp.sum((out["color"][k:] - target[k:]) ** 2) + jnp.sum(out["color_res"][k:] ** 2)
            + jnp.sum(out["depth"]) + jnp.sum(out["grad"] ** 2))

  theta = jnp.asarray([0.4, 0.7, 1.3, 0.9], jnp.float32)
  full, skipped = render_with(theta, 0), render_with(theta, k)
  for name in full:
    want = full[name][k:] if name.startswith("color") else full[name]
    got = skipped[name][k:] if name.startswith("color") else skipped[name]
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=name)
  for name in ("color", "color_res", "color_global"):
    np.testing.assert_array_equal(np.asarray(skipped[name][:k]), 0.0, err_msg=name)
  np.testing.assert_allclose(np.asarray(jax.grad(loss)(theta, k)),
                             np.asarray(jax.grad(loss)(theta, 0)), rtol=1e-6, atol=1e-7)
