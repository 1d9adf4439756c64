"""The SDF / colour fields: analytic normals vs finite differences, SH basis, ranges, init."""

import dataclasses

import chex
import jax
from jax import enable_x64
import jax.numpy as jnp
import numpy as np
import pytest

from ofjax import encoding, fields
from ofjax.config import Config, HashConfig, ModelConfig

CFG = Config(hash=HashConfig(n_levels=6, log2_table_size=12, base_resolution=4))


def _params_with_live_encoding(seed=0, cfg=CFG):
  """Params whose hash tables (the colour's too, when cfg has one) and encoding weights are
  non-trivial (the init zeroes them)."""
  p = fields.init_params(jax.random.PRNGKey(seed), cfg)
  k1, k2 = jax.random.split(jax.random.PRNGKey(seed + 1))
  p["tables"] = jax.random.uniform(k1, p["tables"].shape, minval=-0.5, maxval=0.5)
  if "color_tables" in p:
    p["color_tables"] = jax.random.uniform(jax.random.fold_in(k1, 1), p["tables"].shape,
                                           minval=-0.5, maxval=0.5)
  k = p["sdf"]["Dense_0"]["kernel"]
  p["sdf"]["Dense_0"]["kernel"] = k + 0.3 * jax.random.normal(k2, k.shape)
  return p


def test_geometry_gradient_matches_finite_differences():
  p = _params_with_live_encoding()
  x = np.random.default_rng(0).uniform(-0.8, 0.8, (64, 3)).astype(np.float32)
  sdf, grad, feat = fields.geometry(p, jnp.asarray(x), CFG)
  chex.assert_shape([sdf, grad, feat], [(64,), (64, 3), (64, CFG.model.feature_dim)])
  chex.assert_type([sdf, grad], jnp.float32)
  with enable_x64():
    p64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), p)
    h = 1e-6
    fd = np.zeros((64, 3))
    for j in range(3):
      e = np.zeros(3)
      e[j] = h
      fd[:, j] = (np.asarray(fields.sdf_value(p64, jnp.asarray(x + e, jnp.float64), CFG)) -
                  np.asarray(fields.sdf_value(p64, jnp.asarray(x - e, jnp.float64), CFG))) / (2 * h)
  # A few points may sit within h of a cell face, where the trilinear gradient jumps.
  close = np.all(np.abs(np.asarray(grad) - fd) < 1e-3 * (1 + np.abs(fd)), axis=1)
  assert close.mean() > 0.95, np.abs(np.asarray(grad) - fd).max()
  np.testing.assert_allclose(np.asarray(sdf), np.asarray(fields.sdf_value(p, jnp.asarray(x), CFG)),
                             atol=1e-5)


def test_sphere_initialisation():
  p = fields.init_params(jax.random.PRNGKey(0), CFG)
  dirs = np.random.default_rng(1).normal(size=(500, 3))
  dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
  inside = fields.sdf_value(p, jnp.asarray(0.1 * dirs, jnp.float32), CFG)
  outside = fields.sdf_value(p, jnp.asarray(0.95 * dirs, jnp.float32), CFG)
  assert float(inside.max()) < 0 < float(outside.min())


def test_plane_initialisation_is_the_substrate_plane():
  # The "plane" init is exactly sdf(x) = up . x - level (a NumPy float64 reference), its gradient
  # is up (eikonal 0), and deeper SDF MLPs carry the plane through their extra layers.
  rng = np.random.default_rng(2)
  up = rng.normal(size=3)
  up /= np.linalg.norm(up)
  level = -0.23
  x = rng.uniform(-1, 1, (300, 3))
  for layers in (1, 2):
    cfg = dataclasses.replace(CFG, model=ModelConfig(init_shape="plane", sdf_layers=layers))
    p = fields.init_params(jax.random.PRNGKey(0), cfg, substrate=(up, level))
    sdf, grad, _ = fields.geometry(p, jnp.asarray(x, jnp.float32), cfg)
    np.testing.assert_allclose(np.asarray(sdf), x @ up - level, atol=1e-5)
    np.testing.assert_allclose(np.asarray(grad), np.broadcast_to(up, x.shape), atol=1e-5)
    sphere = fields.init_params(jax.random.PRNGKey(0), dataclasses.replace(cfg, model=ModelConfig(
        sdf_layers=layers)))
    chex.assert_trees_all_equal_shapes_and_dtypes(p, sphere)


def test_unknown_init_shape_is_refused():
  with pytest.raises(ValueError, match="init_shape"):
    ModelConfig(init_shape="cube")


def test_spherical_harmonics_are_orthonormal():
  # Fibonacci-sphere quadrature of <Y_i, Y_j> over the unit sphere: 4 pi mean(Y_i Y_j) = delta_ij.
  n = 40000
  k = np.arange(n) + 0.5
  z = 1 - 2 * k / n
  phi = np.pi * (1 + 5**0.5) * k
  r = np.sqrt(1 - z**2)
  v = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
  y = np.asarray(fields.sh_encode(jnp.asarray(v, jnp.float32), 4), np.float64)
  chex.assert_shape(y, (n, 16))
  gram = 4 * np.pi * (y.T @ y) / n
  np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)


def _colour_inputs(seed: int, count: int, half_width: float):
  """Random colour-network inputs: points x in [-half_width, half_width]^3, unit normals n and view
  directions v, and features f, each [count, k] float32."""
  rng = np.random.default_rng(seed)
  x = jnp.asarray(rng.uniform(-half_width, half_width, (count, 3)), jnp.float32)
  n = fields.unit(jnp.asarray(rng.normal(size=(count, 3)), jnp.float32))
  v = fields.unit(jnp.asarray(rng.normal(size=(count, 3)), jnp.float32))
  f = jnp.asarray(rng.normal(size=(count, CFG.model.feature_dim)), jnp.float32)
  return x, n, v, f


def test_colour_ranges_and_residual_switch():
  p = _params_with_live_encoding()
  x, n, v, f = _colour_inputs(2, 100, 1.0)
  c_global, c_res = fields.colors(p, x, n, f, v, CFG)
  assert float(c_global.min()) > 0 and float(c_global.max()) < 1
  assert float(c_res.min()) > -1 and float(c_res.max()) < 1 and float(jnp.abs(c_res).max()) > 0
  no_res = dataclasses.replace(CFG, model=ModelConfig(residual=False))
  c_global2, c_res2 = fields.colors(p, x, n, f, v, no_res)
  chex.assert_trees_all_close(c_global2, c_global)
  assert float(jnp.abs(c_res2).max()) == 0.0


def test_safe_norm_has_finite_gradient_at_zero():
  g = jax.grad(lambda v: fields.safe_norm(v).sum())(jnp.zeros((2, 3)))
  assert bool(jnp.all(jnp.isfinite(g)))


OWN = dataclasses.replace(CFG, model=ModelConfig(color_features="own"))
BOTH = dataclasses.replace(CFG, model=ModelConfig(color_features="both"))


@pytest.mark.parametrize("cfg,with_f", [(OWN, False), (BOTH, True)])
def test_own_colour_features_leave_the_shared_init_alone(cfg, with_f):
  shared = fields.init_params(jax.random.PRNGKey(3), CFG)
  own = fields.init_params(jax.random.PRNGKey(3), cfg)
  assert "color_tables" not in shared and set(own) == set(shared) | {"color_tables"}
  # The geometry draws the same values either way; the colour's table is its own.
  chex.assert_trees_all_equal(own["tables"], shared["tables"])
  chex.assert_trees_all_equal(own["sdf"], shared["sdf"])
  chex.assert_equal_shape([own["color_tables"], own["tables"]])
  assert not np.array_equal(np.asarray(own["color_tables"]), np.asarray(own["tables"]))
  n_in = 3 + 3 + CFG.hash.n_levels * CFG.hash.n_features + with_f * CFG.model.feature_dim
  chex.assert_shape(own["color"]["Dense_0"]["kernel"], (n_in, CFG.model.color_hidden))


def _colour_sum(cfg, params, x, n, v):
  """Sum of G + R at x with the normal n held fixed and f from the SDF network."""
  _, _, f = fields.geometry(params, x, cfg)
  c_global, c_res = fields.colors(params, x, n, f, v, cfg)
  return jnp.sum(c_global + c_res)


@pytest.mark.parametrize("cfg,reaches_geometry", [(CFG, True), (OWN, False), (BOTH, True)])
def test_colour_gradient_reaches_the_geometry_only_through_a_shared_f(cfg, reaches_geometry):
  p = _params_with_live_encoding(4, cfg)
  x, n, v, _ = _colour_inputs(6, 50, 0.8)
  g = jax.grad(lambda q: _colour_sum(cfg, q, x, n, v))(p)
  geometry_grad = max(float(jnp.abs(a).max()) for a in jax.tree.leaves((g["sdf"], g["tables"])))
  if reaches_geometry:
    assert geometry_grad > 1e-4
  else:
    assert geometry_grad == 0.0
  if "color_tables" in g:
    assert float(jnp.abs(g["color_tables"]).max()) > 1e-4


@pytest.mark.parametrize("cfg", [OWN, BOTH])
def test_own_colour_features_are_the_hash_encoding_of_x(cfg):
  # G's input is [x, n, (f,) hash(x)] with the colour's table: a float64 forward of G written here
  # (ReLU MLP, sigmoid) on the encoding of x agrees with fields.colors; "own" ignores f.
  p = _params_with_live_encoding(7, cfg)
  x, n, v, f = _colour_inputs(9, 40, 0.8)
  c_global, _ = fields.colors(p, x, n, f, v, cfg)
  parts = [x, n] + [f] * (cfg is BOTH) + [encoding.encode(p["color_tables"], x, cfg.hash)]
  h = np.concatenate([np.asarray(a, np.float64) for a in parts], -1)
  layers = p["color"]
  for i in range(cfg.model.color_layers):
    h = np.maximum(h @ np.asarray(layers[f"Dense_{i}"]["kernel"], np.float64) +
                   np.asarray(layers[f"Dense_{i}"]["bias"], np.float64), 0.0)
  out = h @ np.asarray(layers[f"Dense_{cfg.model.color_layers}"]["kernel"], np.float64) + \
      np.asarray(layers[f"Dense_{cfg.model.color_layers}"]["bias"], np.float64)
  np.testing.assert_allclose(np.asarray(c_global), 1.0 / (1.0 + np.exp(-out)), atol=1e-5)


def test_unknown_colour_features_are_refused():
  with pytest.raises(ValueError, match="color_features"):
    ModelConfig(color_features="separate")
