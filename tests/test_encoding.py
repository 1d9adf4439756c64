"""Tests of ofjax.encoding against an independent float64 NumPy hash grid written here.

Thresholds: in float64 the JAX encoding and the reference do the same arithmetic in a different
order, so values agree to ~1e-12; we allow 1e-9. In float32 with table entries of size 1 and
scales below 16, the position is exact to ~1e-6 and a feature sums 8 products, so 1e-5 is ample.
Central differences with step h = 1e-6 (float64) have truncation error 0 for the multilinear
weights inside a cell and rounding error ~1e-16 / h ~ 1e-10 per unit of value; we allow 1e-6.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import enable_x64
from jax.test_util import check_grads

from ofjax import encoding
from ofjax.config import HashConfig

# 4 levels of sides 5, 7, 10, 15 with T = 2^10: levels 0-2 dense (side^3 <= 1024), level 3 hashed;
# scale 12.5 has frac >= 0.5, the case where tiny-cuda-nn's ceil(scale) + 1 grid is one short.
SMALL = HashConfig(n_levels=4, n_features=2, log2_table_size=10, base_resolution=4,
                   per_level_scale=1.5)
# The paper's levels with a small table: 3 dense levels, then hashed with coordinates up to ~4097.
PAPER_LEVELS = HashConfig(log2_table_size=12)
# The same levels gathered as 4 groups of 4 (HashConfig.gather_groups): the features must not change.
GROUPED = dataclasses.replace(PAPER_LEVELS, gather_groups=4)
FD_STEP = 1e-6  # central-difference step in [-1, 1] units (float64)
MARGIN = 0.05  # keep finite-difference points this far (in cell fractions) from cell faces


def ref_corners(x: np.ndarray, cfg: HashConfig):
  """Yields (level, idx [N], w [N]) for every level and cell corner; explicit loops, float64."""
  table_size = 2 ** cfg.log2_table_size
  u = np.clip((np.asarray(x, np.float64) + 1.0) / 2.0, 0.0, 1.0)
  for level in range(cfg.n_levels):
    scale = cfg.base_resolution * cfg.per_level_scale ** level - 1.0
    side = int(np.floor(scale + 0.5)) + 2
    pos = u * scale + 0.5
    cell = np.floor(pos).astype(np.int64)
    frac = pos - cell
    for corner in itertools.product((0, 1), repeat=3):
      c = cell + np.array(corner)
      w = np.prod(np.where(np.array(corner) == 1, frac, 1.0 - frac), axis=1)
      if side ** 3 <= table_size:
        idx = c[:, 0] + side * c[:, 1] + side * side * c[:, 2]
      else:
        idx = np.array([(int(a) * 1) ^ (int(b) * 2654435761) ^ (int(d) * 805459861)
                        for a, b, d in c]) % table_size
      yield level, idx, w


def ref_encode(tables: np.ndarray, x: np.ndarray, cfg: HashConfig) -> np.ndarray:
  """Float64 reference: tables [L, T, F], x [N, 3] -> [N, L*F]."""
  out = np.zeros((len(x), cfg.n_levels, cfg.n_features))
  for level, idx, w in ref_corners(x, cfg):
    out[:, level] += w[:, None] * tables[level, idx]
  return out.reshape(len(x), -1)


def ref_fracs(x: np.ndarray, cfg: HashConfig) -> np.ndarray:
  """[N, L, 3] float64 cell fractions of the reference (for keeping away from cell faces)."""
  u = (np.asarray(x, np.float64) + 1.0) / 2.0
  scales = cfg.base_resolution * cfg.per_level_scale ** np.arange(cfg.n_levels) - 1.0
  pos = u[:, None, :] * scales[:, None] + 0.5
  return pos - np.floor(pos)


def interior_points(rng: np.random.Generator, n: int, cfg: HashConfig) -> np.ndarray:
  """[n, 3] points in (-1, 1)^3 whose fractions at every level are MARGIN away from cell faces."""
  pts = []
  while sum(len(p) for p in pts) < n:
    x = rng.uniform(-0.98, 0.98, (8 * n, 3))
    f = ref_fracs(x, cfg)
    pts.append(x[np.all((f > MARGIN) & (f < 1 - MARGIN), axis=(1, 2))])
  return np.concatenate(pts)[:n]


def random_tables(seed: int, cfg: HashConfig, dtype=np.float64) -> np.ndarray:
  rng = np.random.default_rng(seed)
  shape = (cfg.n_levels, 2 ** cfg.log2_table_size, cfg.n_features)
  return rng.uniform(-1.0, 1.0, shape).astype(dtype)


def ref_jacobian_fd(tables: np.ndarray, x: np.ndarray, cfg: HashConfig) -> np.ndarray:
  """[N, L*F, 3] central differences of the reference encoding."""
  cols = []
  for d in range(3):
    e = np.zeros(3)
    e[d] = FD_STEP
    cols.append((ref_encode(tables, x + e, cfg) - ref_encode(tables, x - e, cfg)) / (2 * FD_STEP))
  return np.stack(cols, axis=-1)


def test_level_layout():
  np.testing.assert_array_equal(encoding.level_resolutions(SMALL), [5, 7, 10, 15])
  np.testing.assert_array_equal(encoding.level_is_dense(SMALL), [True, True, True, False])
  paper = encoding.level_resolutions(HashConfig())
  assert paper.dtype.kind == "i" and paper.shape == (16,)
  # The finest paper level spans 16 * 1.447269^15 - 1 ~ 4095 cells across the box.
  assert 4090 < paper[-1] < 4100


def test_init_tables():
  cfg = HashConfig(n_levels=3, log2_table_size=8, init_scale=1e-4)
  t = encoding.init_tables(jax.random.PRNGKey(0), cfg)
  chex.assert_shape(t, (3, 256, 2))
  chex.assert_type(t, jnp.float32)
  assert float(jnp.max(jnp.abs(t))) <= 1e-4 and float(jnp.std(t)) > 1e-5


class EncodingVariantsTest(chex.TestCase):
  """Float32 values and shapes, with and without jit."""

  @chex.variants(with_jit=True, without_jit=True)
  def test_values_and_shapes(self):
    rng = np.random.default_rng(1)
    tables = random_tables(2, SMALL, np.float32)
    x = rng.uniform(-1.0, 1.0, (2, 5, 3)).astype(np.float32)
    feats = self.variant(lambda t, p: encoding.encode(t, p, SMALL))(tables, x)
    feats2, jac = self.variant(lambda t, p: encoding.encode_with_jacobian(t, p, SMALL))(tables, x)
    chex.assert_shape(feats, (2, 5, 8))
    chex.assert_shape(jac, (2, 5, 8, 3))
    chex.assert_type([feats, feats2, jac], jnp.float32)
    want = ref_encode(tables.astype(np.float64), x.reshape(-1, 3), SMALL).reshape(2, 5, 8)
    np.testing.assert_allclose(feats, want, atol=1e-5)
    np.testing.assert_allclose(feats2, want, atol=1e-5)

  @chex.variants(with_jit=True, without_jit=True)
  def test_jacobian_float32(self):
    x = interior_points(np.random.default_rng(3), 20, SMALL).astype(np.float32)
    tables = random_tables(4, SMALL, np.float32)
    _, jac = self.variant(lambda t, p: encoding.encode_with_jacobian(t, p, SMALL))(tables, x)
    want = ref_jacobian_fd(tables.astype(np.float64), x.astype(np.float64), SMALL)
    # |jac| ~ scale ~ 10, float32 relative error ~1e-6.
    np.testing.assert_allclose(jac, want, atol=1e-4)


@pytest.mark.parametrize("cfg", [SMALL, PAPER_LEVELS, GROUPED],
                         ids=["small", "paper_levels", "grouped"])
def test_values_float64(cfg):
  x = np.random.default_rng(5).uniform(-1.0, 1.0, (64, 3))
  x[:3] = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0]]  # the box's corners
  tables = random_tables(6, cfg)
  with enable_x64():
    got = encoding.encode(jnp.asarray(tables), jnp.asarray(x), cfg)
    got_j, _ = encoding.encode_with_jacobian(jnp.asarray(tables), jnp.asarray(x), cfg)
  np.testing.assert_allclose(got, ref_encode(tables, x, cfg), rtol=0, atol=1e-9)
  np.testing.assert_allclose(got_j, got, rtol=0, atol=1e-12)


@pytest.mark.parametrize("cfg", [SMALL, PAPER_LEVELS, GROUPED],
                         ids=["small", "paper_levels", "grouped"])
def test_jacobian_matches_finite_differences(cfg):
  x = interior_points(np.random.default_rng(7), 16, cfg)
  tables = random_tables(8, cfg)
  with enable_x64():
    t, p = jnp.asarray(tables), jnp.asarray(x)
    _, jac = encoding.encode_with_jacobian(t, p, cfg)
    enc = jax.jit(lambda q: encoding.encode(t, q, cfg))
    fd_jax = jnp.stack([(enc(p + e) - enc(p - e)) / (2 * FD_STEP)
                        for e in FD_STEP * jnp.eye(3)], axis=-1)
  # The finest paper level has scale/2 ~ 2048: the Jacobian is that large, so compare relatively.
  tol = 1e-6 * max(1.0, float(np.max(np.abs(jac))))
  np.testing.assert_allclose(jac, ref_jacobian_fd(tables, x, cfg), rtol=0, atol=tol)
  np.testing.assert_allclose(jac, fd_jax, rtol=0, atol=tol)


def test_outside_box_is_clipped():
  tables = random_tables(9, SMALL)
  x = np.array([[1.5, 0.2, -0.3], [-3.0, -2.0, 7.0], [0.1, 0.2, 0.3]])
  with enable_x64():
    feats, jac = jax.jit(lambda t, p: encoding.encode_with_jacobian(t, p, SMALL))(
        jnp.asarray(tables), jnp.asarray(x))
  np.testing.assert_allclose(feats, ref_encode(tables, np.clip(x, -1, 1), SMALL), atol=1e-9)
  np.testing.assert_array_equal(jac[0, :, 0], 0.0)
  assert np.all(np.asarray(jac[0, :, 1:]) != 0.0)
  np.testing.assert_array_equal(jac[1], 0.0)
  assert np.all(np.isfinite(np.asarray(feats)))


def test_batch_shapes_and_nan_inputs():
  tables = jnp.asarray(random_tables(16, SMALL, np.float32))
  enc = jax.jit(lambda p: encoding.encode(tables, p, SMALL))
  chex.assert_shape(enc(jnp.zeros(3)), (8,))
  chex.assert_shape(jax.jit(lambda p: encoding.encode_with_jacobian(tables, p, SMALL))(
      jnp.zeros((2, 0, 3)))[1], (2, 0, 8, 3))
  # A NaN coordinate gives NaN features for that point only (indices stay in range).
  feats = enc(jnp.array([[np.nan, 0.0, 0.0], [0.5, 0.0, 0.0]]))
  assert np.all(np.isnan(feats[0])) and np.all(np.isfinite(feats[1]))


def test_custom_jvp_matches_analytic_jacobian():
  x = interior_points(np.random.default_rng(10), 6, SMALL).astype(np.float32)
  tables = jnp.asarray(random_tables(11, SMALL, np.float32))
  _, jac = encoding.encode_with_jacobian(tables, x, SMALL)
  per_point = lambda p: encoding.encode(tables, p, SMALL)
  for jacobian in (jax.jacfwd, jax.jacrev):
    got = jax.jit(jax.vmap(jacobian(per_point)))(jnp.asarray(x))
    # |jac| <= ~2 * scale / 2 ~ 12 here; float32 sums of 8 terms in another order differ ~1e-6.
    np.testing.assert_allclose(got, jac, rtol=1e-5, atol=1e-5)
  # Plain autodiff through the gather (the path `encode` avoids) agrees away from cell faces.
  plain_enc = lambda p: encoding._encode_plain(tables, p, SMALL)
  plain = jax.jit(jax.vmap(jax.jacfwd(plain_enc)))(jnp.asarray(x))
  np.testing.assert_allclose(plain, jac, rtol=1e-5, atol=1e-5)


def _loss_both(feats, jac, a, b):
  """A scalar that uses both features and Jacobian non-linearly (like colour + eikonal terms)."""
  grad_like = jnp.einsum("nkd,k->nd", jac, b)
  return jnp.sum(jnp.sin(feats) * a) + jnp.sum((jnp.linalg.norm(grad_like, axis=-1) - 1.0) ** 2)


def test_table_gradient_matches_numeric_reference():
  """d loss / d tables through feats and jac vs central differences of the float64 reference."""
  cfg = SMALL
  rng = np.random.default_rng(12)
  x = interior_points(rng, 4, cfg)
  tables = random_tables(13, cfg)
  a = rng.normal(size=(len(x), cfg.n_levels * cfg.n_features))
  b = rng.normal(size=cfg.n_levels * cfg.n_features)

  def loss_np(t):
    jac = ref_jacobian_fd(t, x, cfg)
    return float(_loss_both(jnp.asarray(ref_encode(t, x, cfg)), jnp.asarray(jac), a, b))

  with enable_x64():  # the reference loss below is evaluated in float64 too
    grad = jax.grad(lambda t: _loss_both(*encoding.encode_with_jacobian(t, jnp.asarray(x), cfg),
                                         a, b))(jnp.asarray(tables))
    grad = np.asarray(grad)
    # Entries no corner of any point touches get no gradient; check a sample of the touched ones
    # (up to 4 points x 4 levels x 8 corners x 2 features) against central differences.
    touched = np.zeros(tables.shape[:2], bool)
    for level, idx, _ in ref_corners(x, cfg):
      touched[level, idx] = True
    np.testing.assert_array_equal(grad[~touched], 0.0)
    entries = [(lv, i, f) for lv, i in np.argwhere(touched) for f in range(cfg.n_features)]
    step = 1e-5
    for k in rng.choice(len(entries), size=min(48, len(entries)), replace=False):
      tp, tm = tables.copy(), tables.copy()
      tp[entries[k]] += step
      tm[entries[k]] -= step
      numeric = (loss_np(tp) - loss_np(tm)) / (2 * step)
      # Rounding error ~1e-10 of the reference's finite-difference Jacobian becomes ~1e-5 here.
      assert abs(grad[entries[k]] - numeric) < 1e-4 * max(1.0, abs(numeric)), (
          entries[k], grad[entries[k]], numeric)


def test_table_gradient_through_custom_jvp():
  """An eikonal loss built with jax.grad of `encode` w.r.t. x (the mixed second derivative through
  the custom JVP rule) gives the same table gradient as the explicit Jacobian, and passes JAX's
  own numerical forward/reverse checks."""
  cfg = SMALL
  rng = np.random.default_rng(14)
  x_np = interior_points(rng, 4, cfg)
  head_np = rng.normal(size=cfg.n_levels * cfg.n_features)

  def eikonal_autodiff(t):
    grad_x = jax.vmap(jax.grad(lambda p: jnp.dot(jnp.tanh(encoding.encode(t, p, cfg)), head)))(x)
    return jnp.sum((jnp.linalg.norm(grad_x, axis=-1) - 1.0) ** 2)

  def eikonal_explicit(t):
    feats, jac = encoding.encode_with_jacobian(t, x, cfg)
    grad_x = jnp.einsum("nk,nkd->nd", head * (1.0 - jnp.tanh(feats) ** 2), jac)
    return jnp.sum((jnp.linalg.norm(grad_x, axis=-1) - 1.0) ** 2)

  with enable_x64():
    tables = jnp.asarray(random_tables(15, cfg))
    x, head = jnp.asarray(x_np), jnp.asarray(head_np)
    np.testing.assert_allclose(jax.jit(eikonal_autodiff)(tables), jax.jit(eikonal_explicit)(tables),
                               rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.grad(eikonal_autodiff))(tables),
                               jax.jit(jax.grad(eikonal_explicit))(tables), rtol=1e-9, atol=1e-9)
    check_grads(jax.jit(eikonal_autodiff), (tables,), order=1, modes=("fwd", "rev"))
    check_grads(jax.jit(lambda t, p: encoding.encode(t, p, cfg)), (tables, x), order=1,
                modes=("fwd", "rev"))


def test_grouped_gather_gives_the_same_table_gradient():
  """gather_groups splits the gather and its scatter-add; the gradient must be the same sum."""
  rng = np.random.default_rng(16)
  x = jnp.asarray(rng.uniform(-1.0, 1.0, (256, 3)), jnp.float32)
  tables = jnp.asarray(random_tables(17, PAPER_LEVELS), jnp.float32)
  a = jnp.asarray(rng.normal(size=(256, 32)), jnp.float32)

  def loss(t, cfg):
    feats, jac = encoding.encode_with_jacobian(t, x, cfg)
    return jnp.sum(a * feats) + jnp.sum(jnp.einsum("nk,nkd->nd", a, jac) ** 2)

  np.testing.assert_allclose(jax.grad(loss)(tables, GROUPED), jax.grad(loss)(tables, PAPER_LEVELS),
                             rtol=1e-6, atol=1e-6)
  with pytest.raises(ValueError, match="must divide"):
    dataclasses.replace(PAPER_LEVELS, gather_groups=3)
