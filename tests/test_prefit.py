"""The "wli" init: the oriented WLI cloud, the far-field targets, the fit's gradient and result."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import enable_x64

import analytic_scene
from ofjax import fields, prefit, train
from ofjax import scene as scene_lib
from ofjax.config import resolve

SMALL = dict(hash={"log2_table_size": 14}, train={"n_rays": 128},
             model={"init_shape": "wli", "wli_fit_points": 2048})


@pytest.fixture(scope="module")
def cap():
  scene, _ = analytic_scene.make()
  norm = scene_lib.compute_normalization(scene)
  return scene, norm


def _true_normals(p_um: np.ndarray) -> np.ndarray:
  """Unit normals [N, 3] of the cap's surface at points on it (float64, um)."""
  r = analytic_scene.R
  on_cap = np.hypot(p_um[:, 0], p_um[:, 1]) < np.sqrt(r**2 - (r - analytic_scene.CAP_HEIGHT)**2)
  sphere = p_um + np.array([0.0, 0.0, r - analytic_scene.CAP_HEIGHT])
  return np.where(on_cap[:, None], sphere / r, np.array([0.0, 0.0, 1.0]))


def test_oriented_cloud_has_the_surface_normals_facing_the_objective(cap):
  scene, norm = cap
  p, n = prefit.oriented_cloud(scene, norm)
  chex.assert_type([p, n], np.float32)
  chex.assert_equal_shape([p, n])
  expect = np.concatenate([norm.to_norm(scene_lib.wli_points(s)) for s in scene.wli])
  np.testing.assert_allclose(p, expect, atol=1e-6)
  p_um = norm.to_um(p.astype(np.float64))
  # Away from the rim (a kink: PCA normals there mix the cap and the plane), within 3 degrees.
  rim = np.sqrt(analytic_scene.R**2 - (analytic_scene.R - analytic_scene.CAP_HEIGHT)**2)
  smooth = np.abs(np.hypot(p_um[:, 0], p_um[:, 1]) - rim) > 6.0
  cos = np.sum(n[smooth] * _true_normals(p_um[smooth]), -1)
  assert np.percentile(cos, 5) > np.cos(np.radians(3.0)), np.percentile(cos, 5)
  assert cos.min() > 0.0  # every normal on the objective's side


def test_box_targets_are_the_nearest_point_distance_signed_by_the_scans(cap):
  """Distances against a float64 brute-force nearest neighbour; signs against the cap's analytic
  height: above it (by 3 WLI pixels) is free space, below it is inside; NaN only where no scan
  measured the point's pixel, which the top scan does over the whole cap."""
  scene, norm = cap
  p, _ = prefit.oriented_cloud(scene, norm)
  p = p[::7]  # a few thousand points keep the brute force small
  r, s = prefit.box_targets(p, scene, norm, seed=3, count=3000)
  chex.assert_shape([r, s], [(3000, 3), (3000,)])
  chex.assert_type([r, s], np.float32)
  assert np.all(np.abs(r) <= 1.0)
  d = np.sqrt(np.min(np.sum((r[:, None].astype(np.float64) - p[None]) ** 2, -1), 1))
  known = np.isfinite(s)
  np.testing.assert_allclose(np.abs(s[known]), d[known], rtol=1e-5, atol=1e-6)
  r_um = norm.to_um(r.astype(np.float64))
  above = r_um[:, 2] - analytic_scene.height(r_um[:, 0], r_um[:, 1])
  top = scene.wli[0]  # looks straight down at the origin
  pixel = top.pixel_size[0]
  in_top = np.all(np.abs(r_um[:, :2]) < top.shape[1] * pixel / 2 - pixel, -1)
  clear = in_top & (np.abs(above) > 3 * pixel)
  assert clear.sum() > 100 and np.all(known[clear])
  np.testing.assert_array_equal(np.sign(s[clear]), np.sign(above[clear]))


def test_fit_loss_gradient_matches_finite_differences(cap):
  """The fit loss's gradient (through the encoding's analytic Jacobian, for the normal and eikonal
  terms) against central differences along a random direction, in float64 (ReLU kinks are then
  far from the 1e-6 steps)."""
  scene, norm = cap
  cfg = resolve("cpu", **SMALL)
  data = train.prepare_data(scene, norm)
  p, n = prefit.oriented_cloud(scene, norm)
  r, s = prefit.box_targets(p, scene, norm, seed=0, count=4096)
  with enable_x64():
    params = fields.init_params(jax.random.PRNGKey(0), cfg, substrate=(data.up, data.level))
    params = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), params)
    cloud = tuple(jnp.asarray(a, jnp.float64) for a in (p, n, r, s))
    geo = {k: params[k] for k in ("tables", "sdf")}
    rest = {k: v for k, v in params.items() if k not in geo}
    unit = float(train.reference_scale(data, cfg))
    loss = lambda g: prefit.fit_losses(g, rest, cloud, jax.random.PRNGKey(1), cfg, unit)[0]
    grad = jax.grad(loss)(geo)
    leaves = jax.tree.leaves(geo)
    direction = jax.tree.unflatten(jax.tree.structure(geo), [
        jax.random.normal(jax.random.PRNGKey(i), a.shape, jnp.float64)
        for i, a in enumerate(leaves)])
    analytic = sum(jnp.vdot(g, v)
                   for g, v in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))
    eps = 1e-6
    shifted = lambda e: jax.tree.map(lambda a, v: a + e * v, geo, direction)
    numeric = (loss(shifted(eps)) - loss(shifted(-eps))) / (2 * eps)
    assert grad["tables"].dtype == jnp.float64
  np.testing.assert_allclose(float(analytic), float(numeric), rtol=1e-5)


def test_fit_puts_the_zero_level_on_the_wli_points(cap):
  """After the fit, the SDF at the WLI points is a small fraction of a WLI pixel and has the right
  sign a few pixels off the surface; the plane init it starts from is pixels off on the cap."""
  scene, norm = cap
  cfg = resolve("cpu", **{**SMALL, "model": {**SMALL["model"], "wli_fit_steps": 200}})
  data = train.prepare_data(scene, norm)
  params = fields.init_params(jax.random.PRNGKey(0), cfg, substrate=(data.up, data.level))
  p, n = prefit.oriented_cloud(scene, norm)
  result = prefit.fit(params, scene, norm, cfg, train.reference_scale(data, cfg), seed=0,
                      progress=False)
  chex.assert_trees_all_equal_shapes_and_dtypes(result.params, params)
  for k in ("color", "residual", "variance"):
    chex.assert_trees_all_equal(result.params[k], params[k])
  pixel_um = scene.wli[0].pixel_size[0]
  um = lambda v: np.asarray(v) * norm.scale
  before = np.abs(um(fields.sdf_value(params, jnp.asarray(p), cfg)))
  after = np.abs(um(fields.sdf_value(result.params, jnp.asarray(p), cfg)))
  cap_top = norm.to_um(p.astype(np.float64))[:, 2] > analytic_scene.CAP_HEIGHT / 2
  assert np.median(before[cap_top]) > 3 * pixel_um  # the plane init is the substrate only
  assert np.median(after) < 0.1 * pixel_um, np.median(after)
  assert np.median(after[cap_top]) < 0.1 * pixel_um, np.median(after[cap_top])
  assert np.percentile(after, 95) < 0.5 * pixel_um, np.percentile(after, 95)
  offset = 2 * pixel_um / norm.scale
  above = um(fields.sdf_value(result.params, jnp.asarray(p + offset * n), cfg))
  below = um(fields.sdf_value(result.params, jnp.asarray(p - offset * n), cfg))
  assert np.mean(above > 0) > 0.99 and np.mean(below < 0) > 0.99
  assert set(result.losses) == {"loss/distance", "loss/normal", "loss/far", "loss/eikonal"}


def test_fit_total_weighs_the_distance_term_by_its_lambda(cap):
  """The fit's total is lambda_distance * distance + the other three terms, unweighted."""
  scene, norm = cap
  data = train.prepare_data(scene, norm)
  p, n = prefit.oriented_cloud(scene, norm)
  cloud = tuple(map(jnp.asarray, (p, n, *prefit.box_targets(p, scene, norm, seed=0, count=2048))))
  unit = train.reference_scale(data, resolve("cpu", **SMALL))
  for weight in (1.0, 30.0):
    cfg = resolve("cpu", **{**SMALL, "model": {**SMALL["model"],
                                               "wli_fit_lambda_distance": weight}})
    params = fields.init_params(jax.random.PRNGKey(0), cfg, substrate=(data.up, data.level))
    geo = {k: params[k] for k in ("tables", "sdf")}
    total, logs = prefit.fit_losses(geo, params, cloud, jax.random.PRNGKey(1), cfg, unit)
    expect = (weight * logs["loss/distance"] + logs["loss/normal"] + logs["loss/far"]
              + logs["loss/eikonal"])
    np.testing.assert_allclose(float(total), float(expect), rtol=1e-6)
    assert float(logs["loss/distance"]) > 0.0
