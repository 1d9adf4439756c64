"""Multiresolution hash encoding (instant-ngp / tiny-cuda-nn) with an analytic spatial Jacobian.

Conventions (L levels, F features per level, T = 2**log2_table_size entries per level):
  x         [..., 3] point in the normalised box [-1, 1]^3; u = (x + 1) / 2 in [0, 1]^3.
            Points outside the box are clipped to it: their features are those of the nearest
            box point and their Jacobian is zero along every clipped axis (nothing crashes and no
            table entry is aliased by out-of-range coordinates).
  scale_l   N_min * b**l - 1 (tiny-cuda-nn's `grid_scale`), b = per_level_scale.
  pos       u * scale_l + 0.5; the cell is floor(pos), the trilinear fraction is pos - floor(pos),
            so d frac / d x = scale_l / 2 along each axis.
  side_l    floor(scale_l + 0.5) + 2: grid points per axis, so that the highest corner of the
            highest cell (floor(scale_l + 0.5) + 1) is on the grid. (tiny-cuda-nn's ceil(scale) + 1
            is one short whenever frac(scale) >= 0.5 or scale is an integer; its extra corner layer
            then wraps onto other entries.) `level_resolutions` returns side_l.
  index     dense (one-to-one) c_x + side c_y + side^2 c_z when side_l^3 <= T (the rest of that
            level's table is unused), else the spatial hash
            (c_x * 1) xor (c_y * 2654435761) xor (c_z * 805459861) mod T in uint32 arithmetic.
  tables    [L, T, F] float32; feature l * F + f of the output is level l's feature f.
  jac       [..., L*F, 3] = d feats / d x in [-1, 1] coordinates, from the derivative of the
            trilinear weights (the gathered table entries do not depend on x).

All levels and corners are gathered by one advanced index into the table viewed as [L*T, F] rows
(level offsets l*T), so the reverse-mode gradient w.r.t. the tables is one scatter-add, shared by
the feature and the Jacobian cotangents (HashConfig.gather_groups > 1 splits the levels into that
many such gathers and scatters, independent ops for a multi-core CPU). Layout (measured on XLA
CPU, benchmarks/encoding.py): the gather yields [8 corners, N, L, F] and the corner sum is 8
explicit adds, so features and Jacobian come out point-major with no transpose; reductions over a
non-minor axis, transposes fused into the interpolation, and gathering F scalars instead of one
F-row were each slower.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from ofjax.config import HashConfig

# The spatial-hash primes of instant-ngp (one per axis; the first is 1 for cache coherence).
HASH_PRIMES = (1, 2654435761, 805459861)
# The 8 corners of a cell as (x, y, z) bits, x fastest.
_CORNERS = tuple(tuple((c >> d) & 1 for d in range(3)) for c in range(8))


def level_scales(cfg: HashConfig) -> np.ndarray:
  """[L] float64: scale_l = N_min * b**l - 1, the grid spacing count across [0, 1] of each level."""
  levels = np.arange(cfg.n_levels, dtype=np.float64)
  return cfg.base_resolution * np.exp2(levels * np.log2(cfg.per_level_scale)) - 1.0


def level_resolutions(cfg: HashConfig) -> np.ndarray:
  """[L] int64: grid points per axis of each level, side_l = floor(scale_l + 0.5) + 2."""
  return np.floor(level_scales(cfg) + 0.5).astype(np.int64) + 2


def level_is_dense(cfg: HashConfig) -> np.ndarray:
  """[L] bool: whether the level's grid fits in its table (one-to-one indexing, no hash)."""
  return level_resolutions(cfg) ** 3 <= 2 ** cfg.log2_table_size


def init_tables(key: jax.Array, cfg: HashConfig) -> jax.Array:
  """[L, T, F] float32 table entries, uniform in (-init_scale, init_scale)."""
  shape = (cfg.n_levels, 2 ** cfg.log2_table_size, cfg.n_features)
  return jax.random.uniform(key, shape, jnp.float32, -cfg.init_scale, cfg.init_scale)


def _gather(tables: jax.Array, x: jax.Array, cfg: HashConfig):
  """Gathers the 8 corners of every level.

  Args:
    tables: [L, T, F] table entries.
    x: [N, 3] points in [-1, 1]^3.
  Returns:
    vals: 8 x [N, L, F] table entries at the corners.
    frac: [3, N, L] trilinear fractions in [0, 1).
    inside: [3, N] 1 where x was not clipped along that axis, else 0.
  """
  n_levels, table_size, n_features = tables.shape
  groups = cfg.gather_groups  # divides n_levels (HashConfig checks it)
  if n_levels * table_size >= 2 ** 31:
    raise ValueError(f"{n_levels} x {table_size} hash-table rows exceed int32 gather indices; "
                     "lower log2_table_size")
  u = (x.T + 1.0) * 0.5  # [3, N]
  inside = ((u >= 0.0) & (u <= 1.0)).astype(x.dtype)
  scale = jnp.asarray(level_scales(cfg), x.dtype)  # [L]
  pos = jnp.clip(u, 0.0, 1.0)[:, :, None] * scale + 0.5  # [3, N, L]
  cell = jnp.floor(pos)
  frac = pos - cell
  lower = cell.astype(jnp.uint32)
  # Per axis and level, a corner coordinate is multiplied by the dense stride (1, side, side^2) or
  # by the hash prime; dense levels add the three terms, hashed levels xor them. uint32 products
  # wrap mod 2^32 as instant-ngp's do, and T is a power of two, so `mod T` is a bit mask (dense
  # sums are already below T). The mask also keeps every index in range for any input (even
  # NaN), which the unchecked ("promise_in_bounds") gather below relies on.
  dense = level_is_dense(cfg)  # [L] static
  strides = level_resolutions(cfg)[None, :] ** np.arange(3)[:, None]  # [3, L]
  mult = np.where(dense[None, :], strides, np.array(HASH_PRIMES)[:, None]).astype(np.uint32)
  terms = (lower * mult[:, None, :], (lower + np.uint32(1)) * mult[:, None, :])  # 2 x [3, N, L]
  index = []
  for bits in _CORNERS:
    tx, ty, tz = (terms[b][d] for d, b in enumerate(bits))
    index.append(jnp.where(dense, tx + ty + tz, tx ^ ty ^ tz) & np.uint32(table_size - 1))
  # Each group of n_levels / groups consecutive levels is one gather from its [levels*T, F] rows.
  per_group = n_levels // groups
  level_offset = np.arange(per_group, dtype=np.uint32) * np.uint32(table_size)
  entry = jnp.stack(index).reshape(8, -1, groups, per_group) + level_offset  # row in its group
  vals = jnp.concatenate([
      part.reshape(per_group * table_size, n_features).at[entry[:, :, g].astype(jnp.int32)].get(
          mode="promise_in_bounds")
      for g, part in enumerate(jnp.split(jnp.asarray(tables), groups))], axis=2)  # [8, N, L, F]
  # One split, not 8 slices: the transpose of a split is one concatenate, whereas each slice's
  # transpose is a zero-padded full-size array that XLA then sums (32 of them with the Jacobian).
  return [jnp.squeeze(v, 0) for v in jnp.split(vals, 8)], frac, inside


def _weights(frac: jax.Array) -> tuple[list[jax.Array], list[list[jax.Array]]]:
  """frac: [3, N, L] -> w: 8 x [N, L] corner weights, dw: 8 x 3 x [N, L] their d / d frac."""
  # Per-axis factor: 1 - frac for the lower corner, frac for the upper one; derivative -1 or +1.
  factor = (1.0 - frac, frac)
  w, dw = [], []
  for bits in _CORNERS:
    fx, fy, fz = (factor[b][d] for d, b in enumerate(bits))
    sx, sy, sz = (2.0 * b - 1.0 for b in bits)
    w.append(fx * fy * fz)
    dw.append([sx * fy * fz, fx * sy * fz, fx * fy * sz])
  return w, dw


def _interpolate(weights: list[jax.Array], vals: list[jax.Array]) -> jax.Array:
  """weights: 8 x [N, L]; vals: 8 x [N, L, F] -> [N, L, F], the weighted sum over the corners."""
  return sum(wc[..., None] * vc for wc, vc in zip(weights, vals))


def _encode_plain(tables: jax.Array, x: jax.Array, cfg: HashConfig) -> jax.Array:
  """The encoding as plain JAX (what `encode` computes, without its custom derivative)."""
  vals, frac, _ = _gather(tables, x.reshape(-1, 3), cfg)
  w, _ = _weights(frac)
  return _interpolate(w, vals).reshape(*x.shape[:-1], tables.shape[0] * tables.shape[2])


def encode_with_jacobian(tables: jax.Array, x: jax.Array,
                         cfg: HashConfig) -> tuple[jax.Array, jax.Array]:
  """Features and their analytic Jacobian w.r.t. x.

  Args:
    tables: [L, T, F] table entries.
    x: [..., 3] points in [-1, 1]^3 (clipped to it).
    cfg: the encoding's configuration (static).
  Returns:
    feats: [..., L*F] features.
    jac: [..., L*F, 3] d feats / d x.
  """
  vals, frac, inside = _gather(tables, x.reshape(-1, 3), cfg)
  w, dw = _weights(frac)
  # d frac / d x = scale_l / 2 inside the box, 0 along clipped axes.
  dfrac_dx = inside[:, :, None] * jnp.asarray(level_scales(cfg) * 0.5, x.dtype)  # [3, N, L]
  feats = _interpolate(w, vals)  # [N, L, F]
  jac = jnp.stack([_interpolate([dwc[d] for dwc in dw], vals) * dfrac_dx[d][..., None]
                   for d in range(3)], axis=-1)  # [N, L, F, 3]
  n_out = tables.shape[0] * tables.shape[2]
  return feats.reshape(*x.shape[:-1], n_out), jac.reshape(*x.shape[:-1], n_out, 3)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def encode(tables: jax.Array, x: jax.Array, cfg: HashConfig) -> jax.Array:
  """Features of points.

  Args:
    tables: [L, T, F] table entries.
    x: [..., 3] points in [-1, 1]^3 (clipped to it).
    cfg: the encoding's configuration (static, hashable).
  Returns:
    [..., L*F] features. Derivatives w.r.t. x use the analytic Jacobian (no autodiff through the
    gather); the tangent is linear in (tables_dot, x_dot), so reverse mode works by transposition.
  """
  return _encode_plain(tables, x, cfg)


def _encode_jvp(cfg, primals, tangents):
  tables, x = primals
  tables_dot, x_dot = tangents
  # Symbolic zeros skip the work for an input that is not differentiated (e.g. the tables
  # inside jax.grad w.r.t. x): no gather of zero tables, no Jacobian when x is fixed.
  if isinstance(x_dot, SymbolicZero):
    feats = _encode_plain(tables, x, cfg)
    out_dot = jnp.zeros_like(feats)
  else:
    feats, jac = encode_with_jacobian(tables, x, cfg)
    out_dot = jnp.einsum("...kd,...d->...k", jac, x_dot)
  if not isinstance(tables_dot, SymbolicZero):
    # The features are linear in the tables, so their tangent is the encoding of tables_dot.
    out_dot = out_dot + encode(tables_dot, x, cfg)
  return feats, out_dot


encode.defjvp(_encode_jvp, symbolic_zeros=True)
