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

All levels and all 8 corners are gathered by one advanced index into the table flattened to
[L*T, F] (per-level offsets l*T), so the reverse-mode gradient w.r.t. the tables is one scatter-add,
shared by the feature and the Jacobian cotangents.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ofjax.config import HashConfig

# The spatial-hash primes of instant-ngp (one per axis; the first is 1 for cache coherence).
HASH_PRIMES = (1, 2654435761, 805459861)
# The 8 corners of a cell as offsets [8, 3] in (x, y, z), x fastest.
_CORNERS = np.array([[(c >> d) & 1 for d in range(3)] for c in range(8)], np.uint32)


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


def _corners(tables: jax.Array, x: jax.Array, cfg: HashConfig):
  """Gathers the 8 corners of every level.

  Args:
    tables: [L, T, F] table entries.
    x: [N, 3] points in [-1, 1]^3.
  Returns:
    vals: [N, L, 8, F] table entries at the corners.
    frac: [N, L, 3] trilinear fractions in [0, 1).
    inside: [N, 3] float 1 where x was not clipped along that axis, else 0.
  """
  n_levels, table_size, n_features = tables.shape
  scale = jnp.asarray(level_scales(cfg), x.dtype)  # [L]
  side = level_resolutions(cfg).astype(np.uint32)  # [L]
  u = (x + 1.0) * 0.5
  inside = ((u >= 0.0) & (u <= 1.0)).astype(x.dtype)
  pos = jnp.clip(u, 0.0, 1.0)[:, None, :] * scale[:, None] + 0.5  # [N, L, 3]
  cell = jnp.floor(pos)
  frac = pos - cell
  coords = cell.astype(jnp.uint32)[:, :, None, :] + _CORNERS  # [N, L, 8, 3]
  dense = coords[..., 0] + jnp.asarray(side)[:, None] * (
      coords[..., 1] + jnp.asarray(side)[:, None] * coords[..., 2])
  hashed = (coords[..., 0] * np.uint32(HASH_PRIMES[0])) ^ (
      coords[..., 1] * np.uint32(HASH_PRIMES[1])) ^ (coords[..., 2] * np.uint32(HASH_PRIMES[2]))
  # T is a power of two, so `mod T` is a mask of the low bits.
  hashed = hashed & np.uint32(table_size - 1)
  local = jnp.where(jnp.asarray(level_is_dense(cfg))[:, None], dense, hashed)
  offsets = (np.arange(n_levels, dtype=np.uint32) * np.uint32(table_size))[:, None]
  index = (local + offsets).astype(jnp.int32)  # [N, L, 8]
  flat = jnp.asarray(tables).reshape(n_levels * table_size, n_features)
  vals = flat.at[index].get(mode="promise_in_bounds")
  return vals, frac, inside


def _weights(frac: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Trilinear weights and their derivatives.

  Args:
    frac: [N, L, 3] fractions in the cell.
  Returns:
    w: [N, L, 8] weight of each corner.
    dw: [N, L, 8, 3] d w / d frac along each axis.
  """
  corner = jnp.asarray(_CORNERS, frac.dtype)  # [8, 3]
  f = frac[:, :, None, :]  # [N, L, 1, 3]
  # Per-axis factor: frac for the upper corner, 1 - frac for the lower one; its derivative is +-1.
  factor = corner * f + (1.0 - corner) * (1.0 - f)  # [N, L, 8, 3]
  sign = 2.0 * corner - 1.0
  fx, fy, fz = factor[..., 0], factor[..., 1], factor[..., 2]
  w = fx * fy * fz
  dw = jnp.stack([sign[:, 0] * fy * fz, fx * sign[:, 1] * fz, fx * fy * sign[:, 2]], axis=-1)
  return w, dw


def _flatten(x: jax.Array) -> tuple[jax.Array, tuple[int, ...]]:
  return x.reshape(-1, 3), x.shape[:-1]


def _encode_plain(tables: jax.Array, x: jax.Array, cfg: HashConfig) -> jax.Array:
  """The encoding as plain JAX (what `encode` computes, without its custom derivative)."""
  pts, batch = _flatten(x)
  vals, frac, _ = _corners(tables, pts, cfg)
  w, _ = _weights(frac)
  feats = jnp.einsum("nlc,nlcf->nlf", w, vals)
  return feats.reshape(*batch, -1)


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
  pts, batch = _flatten(x)
  vals, frac, inside = _corners(tables, pts, cfg)
  w, dw = _weights(frac)
  # d frac / d x = scale_l / 2 inside the box, 0 along clipped axes.
  dpos_dx = jnp.asarray(level_scales(cfg) * 0.5, x.dtype)[:, None] * inside[:, None, :]
  feats = jnp.einsum("nlc,nlcf->nlf", w, vals)
  jac = jnp.einsum("nlcd,nlcf->nlfd", dw, vals) * dpos_dx[:, :, None, :]
  n_out = tables.shape[0] * tables.shape[2]
  return feats.reshape(*batch, n_out), jac.reshape(*batch, n_out, 3)


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


@encode.defjvp
def _encode_jvp(cfg, primals, tangents):
  tables, x = primals
  tables_dot, x_dot = tangents
  feats, jac = encode_with_jacobian(tables, x, cfg)
  # The features are linear in the tables, so their tangent is the encoding of tables_dot.
  out_dot = encode(tables_dot, x, cfg) + jnp.einsum("...kd,...d->...k", jac, x_dot)
  return feats, out_dot
