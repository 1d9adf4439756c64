"""The losses of OpticFusion (paper Sec. 3.4), each a small unweighted function.

Every loss is a masked mean: `mask` [R] selects the rays a term applies to (OM rays for colour and
residual, WLI rays with a measured depth for the WLI term), so one batch can hold both modalities.
The train step sums them as cfg.loss.lambda_<name> * loss and logs each as loss/<name>.
"""

from __future__ import annotations

import jax.numpy as jnp

from ofjax.fields import safe_norm


def masked_mean(x, mask):
  """Mean of x: [R] over mask: [R] (0 when the mask is empty)."""
  mask = mask.astype(x.dtype)
  return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def color(pred, target, mask):
  """L_c = 1/m sum ||C_hat - C||^2 over OM rays (paper Eq. 3). pred, target: [R, 3]."""
  return masked_mean(jnp.sum((pred - target) ** 2, -1), mask)


def residual(color_res, mask):
  """L_res = 1/m sum ||C_res||^2 over OM rays (paper Eq. 4). color_res: [R, 3]."""
  return masked_mean(jnp.sum(color_res**2, -1), mask)


def wli(depth, target, mask):
  """L_wli = 1/m sum (D_hat - D)^2 over WLI rays with a measured depth (paper Eq. 5). [R]."""
  return masked_mean((depth - target) ** 2, mask)


def wli_surface(sdf, mask):
  """L_surf = 1/m sum f(o + D d)^2 over WLI rays with a measured depth: the zero level set passes
  through every measured point (not in the paper; ofjax's config documents the weight). [R]."""
  return masked_mean(sdf**2, mask)


def eikonal(grad, mask):
  """L_reg = 1/(mn) sum (||n|| - 1)^2 over all samples of the masked rays (paper Eq. 6).

  grad: [R, N, 3] SDF gradients; mask: [R].
  """
  per_ray = jnp.mean((safe_norm(grad) - 1.0) ** 2, -1)
  return masked_mean(per_ray, mask)


def sparsity(sdf, mask, scale: float):
  """exp(-scale |sdf|) averaged over samples (reference code): discourages stray surfaces.

  sdf: [R, N]; mask: [R].
  """
  return masked_mean(jnp.mean(jnp.exp(-scale * jnp.abs(sdf)), -1), mask)
