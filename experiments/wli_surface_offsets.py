"""Where a trained SDF's surface lies against the WLI's measured depth, and why.

`python experiments/wli_surface_offsets.py SCENE_DIR RUN_DIR [RUN_DIR ...]` takes the first WLI
scan's rays (every `--stride`th pixel, true poses from SCENE_DIR/ground_truth/poses.json) and, per
run, prints median (p10, p90) in um against the measured depth D of:
  - the SDF's zero crossing on a dense window of +-WINDOW_UM around D;
  - NeuS's expected depth with its weights composited densely on that window, and its offset from
    the crossing (rendering bias) and the weight before the crossing (0.5 when centred);
  - the depth the renderer gives with training's own samples (no jitter): what the depth loss sees;
  - |grad f| per um just above and below the crossing.
Only rays whose crossing lies within NEAR_UM of D are counted (the rest are holes or flanks).

Names: `t` [R, n] offsets along the ray from D in um (the window), `f` [R, n] the SDF in um.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ofjax import cameras, export, fields, render, train
from ofjax import scene as scene_lib

WINDOW_UM = 4.0  # half-width of the dense window around the measured depth
WINDOW_POINTS = 801  # 0.01 um apart
NEAR_UM = 3.0  # rays whose crossing is farther than this from D are not counted
SLOPE_UM = 0.5  # |grad f| is the mean slope over this distance beside the crossing
# Guards of the alpha ratio where the CDF vanishes. Not the renderer's 1e-5: that floor of opacity
# per sample, harmless over a training ray's 72 samples, would put ~0.4% of the weight in the empty
# part of an 801-point window and move its expectation by ~0.01 um.
CDF_EPS = 1e-12


def crossing_offsets(t, f, s_per_um: float) -> dict[str, np.ndarray]:
  """Per-ray zero crossing, dense NeuS expectation and slopes.

  Args:
    t: [n] float64 window offsets from the measured depth, um, ascending.
    f: [R, n] SDF along each ray in um (positive outside).
    s_per_um: NeuS's inverse standard deviation per um.
  Returns [R] arrays: has (a + -> - crossing exists), crossing, expected, acc, before (fraction of
  the weight before the crossing), slope_above, slope_below.
  """
  rows = np.arange(len(f))
  down = (f[:, :-1] > 0) & (f[:, 1:] <= 0)
  i = np.argmax(down, 1)
  f0, f1 = f[rows, i], f[rows, i + 1]
  step = t[1] - t[0]
  crossing = t[i] + step * f0 / (f0 - f1)
  k = max(1, int(round(SLOPE_UM / step)))
  above, below = np.clip(i - k, 0, len(t) - 1), np.clip(i + 1 + k, 0, len(t) - 1)
  slope_above = (f[rows, above] - f0) / np.maximum(t[i] - t[above], step)
  slope_below = (f1 - f[rows, below]) / np.maximum(t[below] - t[i + 1], step)
  # NeuS Eq. 13 between consecutive window points (the ray's own SDF values, no section estimate).
  cdf = 1.0 / (1.0 + np.exp(-np.clip(f * s_per_um, -60.0, 60.0)))
  alpha = np.clip((cdf[:, :-1] - cdf[:, 1:]) / (cdf[:, :-1] + CDF_EPS), 0.0, 1.0)
  trans = np.cumprod(np.concatenate([np.ones((len(f), 1)), 1.0 - alpha[:, :-1]], 1), 1)
  w = alpha * trans
  mid = (t[:-1] + t[1:]) / 2
  acc = w.sum(1)
  expected = (w * mid).sum(1) / np.maximum(acc, 1e-12)
  before = np.where(mid[None] < crossing[:, None], w, 0.0).sum(1) / np.maximum(acc, 1e-12)
  return {"has": down.any(1), "crossing": crossing, "expected": expected, "acc": acc,
          "before": before, "slope_above": slope_above, "slope_below": slope_below}


def run_offsets(scene_dir: Path, run_dir: Path, stride: int) -> dict[str, np.ndarray | float]:
  """crossing_offsets of one trained run on the first scan, plus the renderer's depth - D."""
  params, cfg, norm, *_ = export.load_run(run_dir)
  scene = scene_lib.load_scene(scene_dir, poses=scene_dir / "ground_truth" / "poses.json")
  unit = float(train.reference_scale(train.prepare_data(scene, norm), cfg))
  s_norm = unit * float(fields.inv_s(params))  # per normalised unit, as training renders
  scan = scene.wli[0]
  o, d = scene_lib.wli_rays(scan, stride)
  depth = scan.depth[::stride, ::stride].astype(np.float64)
  ok = np.isfinite(depth)
  o, d, depth = norm.to_norm(o[ok]), d[ok], depth[ok] / norm.scale  # normalised units
  t = np.linspace(-WINDOW_UM, WINDOW_UM, WINDOW_POINTS)
  x = o[:, None] + d[:, None] * (depth[:, None] + t[None] / norm.scale)[..., None]
  sdf = jax.jit(lambda p, x: fields.sdf_value(p, x, cfg))
  f = np.asarray(sdf(params, jnp.asarray(x, jnp.float32)), np.float64) * norm.scale
  out = crossing_offsets(t, f, s_norm / norm.scale)
  oj, dj = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
  near, far, _ = cameras.box_near_far(oj, dj)
  rendered = render.render_rays(*fields.field_fns(params, cfg), oj, dj, near, far,
                                jax.random.PRNGKey(0), s_norm, 1.0, cfg.render,
                                guide=jnp.asarray(depth, jnp.float32),
                                has_guide=jnp.ones(len(depth), bool), randomize=False,
                                n_uncolored=len(depth))
  out["rendered"] = (np.asarray(rendered["depth"], np.float64) - depth) * norm.scale
  out["s_per_um"] = s_norm / norm.scale
  return out


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("scene_dir", type=Path)
  p.add_argument("runs", type=Path, nargs="+")
  p.add_argument("--stride", type=int, default=6, help="every Nth WLI pixel (default 6)")
  args = p.parse_args(argv)
  rows = [("zero crossing - D", "crossing"), ("dense E[t] - D", "expected"),
          ("rendered depth - D", "rendered"), ("weight before crossing", "before"),
          ("|grad f| above", "slope_above"), ("|grad f| below", "slope_below")]
  for run in args.runs:
    r = run_offsets(args.scene_dir, run, args.stride)
    keep = r["has"] & (np.abs(r["crossing"]) < NEAR_UM)
    print(f"{run}: s = {r['s_per_um']:.2f} per um, {keep.sum()} of {len(keep)} rays")
    q = lambda a: f"{np.median(a):+.3f} ({np.percentile(a, 10):+.3f}, {np.percentile(a, 90):+.3f})"
    for label, key in rows:
      print(f"  {label:24s} {q(r[key][keep])}")
    print(f"  {'dense E[t] - crossing':24s} {q((r['expected'] - r['crossing'])[keep])}")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
