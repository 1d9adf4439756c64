"""Which surface points some WLI scan measured, decided inside the jitted step.

The WLI is blind on smooth steep specular surfaces (the `lenses` flanks): there its pixels are
voids, and only the OM photos see the surface. The colour term can then weigh more on the OM rays
whose surface no scan measured (LossConfig.lambda_color_blind) without pulling the surface off the
heights the WLI did measure elsewhere.

A point x counts as measured when, for some scan, it projects inside the frame onto a pixel with
a depth and lies within `tolerance` of that depth along the scan's axis: the scan saw a surface
there, and it is this one (not a nearer one that hides x, nor a farther one that x hides). The
point of an OM ray is its rendered expected depth's point, so the test follows the model's surface
as it trains. ofjax.eval.wli_coverage asks the same question of the ground truth with a 3-D radius.

Names: x = points in normalised coordinates; the scans' arrays are TrainData's (wli_depth,
wli_valid, wli_c2w, wli_pixel, wli_hw), padded to the largest scan.
"""

from __future__ import annotations

import jax.numpy as jnp


def wli_measured(x, wli_depth, wli_valid, wli_c2w, wli_pixel, wli_hw, tolerance_px: float):
  """[N] bool: some scan measured a surface within tolerance_px of its pixel size of x.

  Args:
    x: [N, 3] points (normalised).
    wli_depth: [S, H, W] depth along each scan's axis from its image plane (0 where void).
    wli_valid: [S, H, W] bool, where the scan measured a depth.
    wli_c2w: [S, 4, 4] camera-to-world; wli_pixel: [S, 2] (sx, sy); wli_hw: [S, 2] (H, W), each
      scan's own size (the arrays are padded beyond it).
    tolerance_px: how far along the axis x may lie from the measured depth, in the scan's sx.
  """
  rot = wli_c2w[:, :3, :3]
  rot = rot / jnp.linalg.norm(rot, axis=1, keepdims=True)  # unit camera axes as columns
  local = jnp.einsum("snk,skj->snj", x[None] - wli_c2w[:, None, :3, 3], rot)  # [S, N, 3]
  col = jnp.floor(local[..., 0] / wli_pixel[:, None, 0] + wli_hw[:, None, 1] / 2)
  row = jnp.floor(local[..., 1] / wli_pixel[:, None, 1] + wli_hw[:, None, 0] / 2)
  inside = (col >= 0) & (col < wli_hw[:, None, 1]) & (row >= 0) & (row < wli_hw[:, None, 0])
  scan = jnp.arange(wli_depth.shape[0])[:, None]
  r = jnp.clip(row, 0, wli_depth.shape[1] - 1).astype(jnp.int32)
  c = jnp.clip(col, 0, wli_depth.shape[2] - 1).astype(jnp.int32)
  near = jnp.abs(wli_depth[scan, r, c] - local[..., 2]) <= tolerance_px * wli_pixel[:, None, 0]
  return jnp.any(inside & wli_valid[scan, r, c] & near, axis=0)
