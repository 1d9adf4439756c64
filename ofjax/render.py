"""NeuS volume rendering with fixed shapes (NeuS, Wang et al. 2021; OpticFusion Sec. 3.3.2).

Names (multinerf's): `t` [R, N] sorted sample distances along each ray; `dt` [R, N] interval
lengths; `mid` [R, N] = t + dt / 2, where the fields are evaluated; `alpha` [R, N] discrete
opacity; `w` [R, N] compositing weights; `near`, `far` [R] the ray's segment inside the box.

Every ray carries n_samples uniform + n_guided depth-guided + n_importance upsampled samples, so
shapes never depend on the data. Upsampling and guided placement carry no gradient (NeuS).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ofjax.config import RenderConfig
from ofjax.fields import unit

# NeuS's constants: keep the alpha ratio finite where the CDF vanishes, and transmittance > 0.
ALPHA_EPS = 1e-5
TRANSMITTANCE_EPS = 1e-7
# NeuS's fixed inverse standard deviations for the upsampling rounds: 64 * 2^i.
UPSAMPLE_BASE_INV_S = 64.0


def stratified(key, near, far, n: int, randomize: bool):
  """[R, n] sorted distances, one per equal sub-interval of [near, far] (jittered if randomize)."""
  u = jnp.arange(n, dtype=jnp.float32)
  if randomize:
    u = u + jax.random.uniform(key, near.shape + (n,))
  else:
    u = u + 0.5
  return near[:, None] + (far - near)[:, None] * (u / n)


def guided(key, guide, has_guide, near, far, n: int, width: float, randomize: bool):
  """[R, n] samples in guide +- width where `has_guide`, else stratified over [near, far]."""
  if n == 0:
    return jnp.zeros(near.shape + (0,), jnp.float32)
  band = stratified(key, guide - width, guide + width, n, randomize)
  return jnp.clip(jnp.where(has_guide[:, None], band, stratified(key, near, far, n, randomize)),
                  near[:, None], far[:, None])


def composite_weights(alpha):
  """w_i = alpha_i prod_{j<i} (1 - alpha_j) (NeuS Eq. 13). alpha: [R, N] -> w: [R, N]."""
  trans = jnp.cumprod(1.0 - alpha + TRANSMITTANCE_EPS, axis=-1)
  trans = jnp.concatenate([jnp.ones_like(trans[:, :1]), trans[:, :-1]], -1)
  return alpha * trans


def alpha_from_sdf_pair(prev_sdf, next_sdf, inv_s):
  """Discrete opacity between two SDF values (NeuS Eq. 13): max((Phi(prev) - Phi(next)) / Phi(prev), 0)."""
  prev_cdf = jax.nn.sigmoid(prev_sdf * inv_s)
  next_cdf = jax.nn.sigmoid(next_sdf * inv_s)
  return jnp.clip((prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS), 0.0, 1.0)


def sample_pdf(t, w, n: int):
  """Deterministic inverse-CDF sampling of n new distances from piecewise-constant weights.

  Args:
    t: [R, N] bin edges; w: [R, N - 1] non-negative weights of the bins.

  Returns:
    [R, n] new distances (no gradient).
  """
  pdf = (w + ALPHA_EPS) / jnp.sum(w + ALPHA_EPS, -1, keepdims=True)
  cdf = jnp.concatenate([jnp.zeros_like(pdf[:, :1]), jnp.cumsum(pdf, -1)], -1)  # [R, N]
  u = (jnp.arange(n, dtype=jnp.float32) + 0.5) / n
  u = jnp.broadcast_to(u, t.shape[:1] + (n,))
  idx = jnp.sum(u[:, :, None] >= cdf[:, None, :], -1)  # [R, n] in 1..N-1
  below = jnp.clip(idx - 1, 0, t.shape[-1] - 1)
  above = jnp.clip(idx, 0, t.shape[-1] - 1)
  cdf_b, cdf_a = jnp.take_along_axis(cdf, below, -1), jnp.take_along_axis(cdf, above, -1)
  t_b, t_a = jnp.take_along_axis(t, below, -1), jnp.take_along_axis(t, above, -1)
  denom = jnp.where(cdf_a - cdf_b < ALPHA_EPS, 1.0, cdf_a - cdf_b)
  return jax.lax.stop_gradient(t_b + (u - cdf_b) / denom * (t_a - t_b))


def upsample(sdf_fn, o, d, t, n_new: int, n_rounds: int):
  """NeuS hierarchical upsampling: n_rounds rounds of n_new / n_rounds samples each (no gradient).

  Args:
    sdf_fn: points [..., 3] -> SDF [...].
    o, d: [R, 3] rays; t: [R, N] sorted distances.

  Returns:
    [R, N + n_new] sorted distances.
  """
  if n_new == 0:
    return t
  per_round = n_new // n_rounds
  sdf = sdf_fn(o[:, None] + d[:, None] * t[..., None])
  for i in range(n_rounds):
    k = per_round if i < n_rounds - 1 else n_new - per_round * (n_rounds - 1)
    # NeuS up_sample: estimate the SDF slope per interval from its neighbours, bounded above by 0
    # so that only surfaces entered from outside attract samples.
    dt = t[:, 1:] - t[:, :-1]
    mid_sdf = 0.5 * (sdf[:, :-1] + sdf[:, 1:])
    cos = (sdf[:, 1:] - sdf[:, :-1]) / (dt + ALPHA_EPS)
    prev_cos = jnp.concatenate([jnp.zeros_like(cos[:, :1]), cos[:, :-1]], -1)
    cos = jnp.clip(jnp.minimum(cos, prev_cos), -1e3, 0.0)
    alpha = alpha_from_sdf_pair(mid_sdf - cos * dt * 0.5, mid_sdf + cos * dt * 0.5,
                                UPSAMPLE_BASE_INV_S * 2.0**i)
    new_t = sample_pdf(t, composite_weights(alpha), k)
    new_sdf = sdf_fn(o[:, None] + d[:, None] * new_t[..., None])
    order = jnp.argsort(jnp.concatenate([t, new_t], -1), axis=-1)
    t = jnp.take_along_axis(jnp.concatenate([t, new_t], -1), order, -1)
    sdf = jnp.take_along_axis(jnp.concatenate([sdf, new_sdf], -1), order, -1)
  return jax.lax.stop_gradient(t)


def cos_anneal_ratio(step, rc: RenderConfig):
  """NeuS cos-anneal: 0 -> 1 linearly over rc.cos_anneal_steps (a function of the step)."""
  if rc.cos_anneal_steps <= 0:
    return jnp.float32(1.0)
  return jnp.minimum(1.0, jnp.asarray(step, jnp.float32) / rc.cos_anneal_steps)


def render_rays(geometry_fn, color_fn, sdf_fn, o, d, near, far, key, inv_s, anneal,
                rc: RenderConfig, guide=None, has_guide=None, randomize: bool = True,
                n_uncolored: int = 0):
  """Renders rays with NeuS.

  Args:
    geometry_fn: x [R, N, 3] -> (sdf [R, N], grad [R, N, 3], f [R, N, F]); differentiable.
    color_fn: (x, n, f, view) [R', N, ...] -> (c_global [R', N, 3], c_res [R', N, 3]), n the unit
      normal and view the unit ray direction; differentiable.
    sdf_fn: x [..., 3] -> sdf [...], used without gradient to place samples.
    o, d: [R, 3] origins and unit directions (normalised box).
    near, far: [R] ray segment inside the box.
    key: PRNG key for sample jitter.
    inv_s: NeuS's inverse standard deviation s; anneal: the cos-anneal ratio in [0, 1].
    guide, has_guide: [R] optional depth prior (e.g. the WLI depth) and where it exists.
    n_uncolored: static; the first n_uncolored rays skip the colour networks and composite colour
      0. Training passes its WLI rays (the batch's first rays), which no colour loss sees: their
      colours cost a forward pass whose gradient is zero.

  Returns a dict:
    color, color_res, color_global: [R, 3] composited c, c_res and c_global; depth: [R] expected
    distance (residual transmittance lands on `far`); normal: [R, 3]; acc: [R] opacity;
    grad: [R, N, 3] SDF gradients at all samples (eikonal); sdf: [R, N]; w: [R, N]; mid: [R, N].
  """
  k_u, k_g = jax.random.split(key)
  t = stratified(k_u, near, far, rc.n_samples, randomize)
  if rc.wli_guided_samples:
    if guide is None:
      guide, has_guide = jnp.zeros_like(near), jnp.zeros(near.shape, bool)
    t_g = guided(k_g, guide, has_guide, near, far, rc.wli_guided_samples, rc.wli_guided_width,
                 randomize)
    t = jnp.sort(jnp.concatenate([t, t_g], -1), -1)
  t = upsample(sdf_fn, o, d, t, rc.n_importance, rc.n_importance_steps)

  last = ((far - near) / rc.n_samples)[:, None]
  dt = jnp.concatenate([t[:, 1:] - t[:, :-1], last], -1)
  mid = t + 0.5 * dt
  x = o[:, None] + d[:, None] * mid[..., None]
  view = jnp.broadcast_to(d[:, None], x.shape)
  sdf, grad, f = geometry_fn(x)
  c_global, c_res = color_fn(*(a[n_uncolored:] for a in (x, unit(grad), f, view)))
  pad = lambda c: jnp.concatenate([jnp.zeros((n_uncolored,) + c.shape[1:], c.dtype), c], 0)
  c_global, c_res = (c_global, c_res) if n_uncolored == 0 else (pad(c_global), pad(c_res))

  # NeuS's section SDF estimate: the cos-anneal blends a relaxed slope (start) into the true one.
  true_cos = jnp.sum(view * grad, -1)
  iter_cos = -(jax.nn.relu(-true_cos * 0.5 + 0.5) * (1.0 - anneal) + jax.nn.relu(-true_cos) * anneal)
  alpha = alpha_from_sdf_pair(sdf - iter_cos * dt * 0.5, sdf + iter_cos * dt * 0.5, inv_s)
  w = composite_weights(alpha)
  acc = jnp.sum(w, -1)
  return {
      "color": jnp.sum(w[..., None] * (c_global + c_res), -2),
      "color_res": jnp.sum(w[..., None] * c_res, -2),
      "color_global": jnp.sum(w[..., None] * c_global, -2),
      "depth": jnp.sum(w * mid, -1) + (1.0 - acc) * far,
      "normal": jnp.sum(w[..., None] * unit(grad), -2),
      "acc": acc,
      "grad": grad,
      "sdf": sdf,
      "w": w,
      "mid": mid,
  }
