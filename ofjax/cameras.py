"""Ray generation for orthographic WLI cameras and pinhole OM cameras, inside jit.

Conventions (see ofjax/scene.py): c2w is camera-to-world with OpenCV axes (x right, y down,
z forward); pixel (row r, col c) has its centre at (c + 0.5, r + 0.5).
  WLI: origin = t + R ((c + 0.5 - W/2) sx, (r + 0.5 - H/2) sy, 0), direction = R e_z.
  OM:  origin = t, direction = normalise(R K^-1 (c + 0.5, r + 0.5, 1)).
Names: `o` ray origins, `d` unit directions, `t` distances along a ray.
"""

from __future__ import annotations

import jax.numpy as jnp


def orthographic_rays(c2w, pixel_size, hw, rows, cols):
  """Rays of orthographic (WLI) cameras.

  Args:
    c2w: [..., 4, 4] camera-to-world.
    pixel_size: [..., 2] (sx, sy) world units per pixel along columns and rows.
    hw: [..., 2] (H, W) image size in pixels.
    rows, cols: [...] integer pixel indices.

  Returns:
    o: [..., 3] origins on the image plane; d: [..., 3] unit directions.
  """
  h, w = hw[..., 0], hw[..., 1]
  x = (cols + 0.5 - w / 2) * pixel_size[..., 0]
  y = (rows + 0.5 - h / 2) * pixel_size[..., 1]
  local = jnp.stack([x, y, jnp.zeros_like(x)], -1)
  rot = c2w[..., :3, :3]
  o = jnp.einsum("...ij,...j->...i", rot, local) + c2w[..., :3, 3]
  d = rot[..., :, 2] / jnp.linalg.norm(rot[..., :, 2], axis=-1, keepdims=True)
  return o, d


def pinhole_rays(c2w, K, rows, cols):
  """Rays of pinhole (OM) cameras.

  Args:
    c2w: [..., 4, 4] camera-to-world.
    K: [..., 3, 3] intrinsics in pixels.
    rows, cols: [...] integer pixel indices.

  Returns:
    o: [..., 3] camera centres; d: [..., 3] unit directions.
  """
  x = (cols + 0.5 - K[..., 0, 2]) / K[..., 0, 0]
  y = (rows + 0.5 - K[..., 1, 2]) / K[..., 1, 1]
  cam = jnp.stack([x, y, jnp.ones_like(x)], -1)
  d = jnp.einsum("...ij,...j->...i", c2w[..., :3, :3], cam)
  d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
  o = jnp.broadcast_to(c2w[..., :3, 3], d.shape)
  return o, d


# A ray parallel to a slab gets 1 / (d + tiny) -> a huge but finite t, which the min/max discard.
_SLAB_EPS = 1e-9


def box_near_far(o, d, lo=-1.0, hi=1.0):
  """Entry and exit distances of rays through the axis-aligned box [lo, hi]^3 (slab method).

  Args:
    o: [..., 3] origins; d: [..., 3] unit directions.

  Returns:
    near: [...] entry distance (>= 0); far: [...] exit distance; hit: [...] bool, far > near.
  """
  inv = 1.0 / jnp.where(jnp.abs(d) < _SLAB_EPS, _SLAB_EPS, d)
  t0 = (lo - o) * inv
  t1 = (hi - o) * inv
  near = jnp.maximum(jnp.max(jnp.minimum(t0, t1), -1), 0.0)
  far = jnp.min(jnp.maximum(t0, t1), -1)
  return near, far, far > near
