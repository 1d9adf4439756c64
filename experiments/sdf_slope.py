"""The SDF's value and slope at the true surface: how far a run's zero level set is off there, and
whether its field is still a distance.

`python experiments/sdf_slope.py SCENE RUN [RUN ...] [--points N]` samples N points (seed 0) on
SCENE/ground_truth/mesh.ply inside each run's observed box and prints, per run, from the
parameters its mesh is made from (`export.load_run`: their average when the run keeps one): the
SDF there in um (median, mean of |sdf|), the slope |d sdf / d x| (10th percentile, median, 90th
percentile; 1 for a distance) and the share of points where the slope is 0. A zero slope means
every hidden ReLU of the SDF network is off at the point: no loss there moves those units, and
the zero level set nearby is wherever the constant output happens to cross zero. The accuracy
heat maps of ofjax.eval show where a mesh is off; this says whether the field under it has gone
flat (experiments/README.md, "The colour's own hash encoding").

Names: `x` [N, 3] points in the run's normalised box, `sdf` [N] in um, `slope` [N] = |d sdf / d x|.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ofjax import export, fields, metrics
from ofjax.meshquery import load_mesh

# A slope below this is zero: with every hidden unit off the network's input gradient is exactly
# 0; a live unit's contribution is orders of magnitude above it.
FLAT_SLOPE = 1e-6


def slope_stats(run_dir: Path, scene_dir: Path, n_points: int = 100_000) -> dict:
  """The SDF (um) and its slope at n_points sampled on the scene's true surface (seed 0) inside
  the run's observed box: {"points", "sdf_median_um", "sdf_abs_mean_um", "slope_p10",
  "slope_median", "slope_p90", "flat_share"}."""
  run = export.load_run(Path(run_dir))
  pts, _ = metrics.sample_surface(load_mesh(Path(scene_dir) / "ground_truth" / "mesh.ply"),
                                  n_points, seed=0)
  x = run.norm.to_norm(pts)
  lo, hi = np.asarray(run.box[0]), np.asarray(run.box[1])
  x = x[np.all((x > lo) & (x < hi), axis=1)]
  # Points and parameters are arguments, not constants closed over: XLA would fold the tables in.
  geometry = jax.jit(lambda p, q: fields.geometry(p, q, run.cfg)[:2])
  sdf, grad = geometry(run.params, jnp.asarray(x, jnp.float32))
  sdf_um = np.asarray(sdf, np.float64) * run.norm.scale
  slope = np.linalg.norm(np.asarray(grad, np.float64), axis=1)
  return {"points": int(len(x)), "sdf_median_um": float(np.median(sdf_um)),
          "sdf_abs_mean_um": float(np.abs(sdf_um).mean()),
          "slope_p10": float(np.percentile(slope, 10)), "slope_median": float(np.median(slope)),
          "slope_p90": float(np.percentile(slope, 90)),
          "flat_share": float(np.mean(slope < FLAT_SLOPE))}


def main(argv=None) -> int:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("scene", type=Path, help="synthetic scene directory (with ground_truth/)")
  ap.add_argument("runs", type=Path, nargs="+", help="run directories of python -m ofjax.train")
  ap.add_argument("--points", type=int, default=100_000, help="points sampled on the truth")
  args = ap.parse_args(argv)
  for run_dir in args.runs:
    s = slope_stats(run_dir, args.scene, args.points)
    print(f"{run_dir}: {s['points']} points; sdf median {s['sdf_median_um']:+.3f} um, "
          f"mean |sdf| {s['sdf_abs_mean_um']:.3f} um; slope p10 / median / p90 "
          f"{s['slope_p10']:.2f} / {s['slope_median']:.2f} / {s['slope_p90']:.2f}; "
          f"flat (slope 0) {100 * s['flat_share']:.1f}%")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
