"""The association report: one JSON of numbers and one PNG (all lengths in um).

JSON keys: wli.pairs (ICP fitness / RMSE per scan pair, whether it is a pose-graph edge),
om (photos registered, mean reprojection error, P_om size, intrinsics), align (estimated OM scale in
um per SfM unit, fitness, height cost, footprint coverage and turn margin - null when no turned
solution was scored - of ofjax.associate.align, residual WLI-to-OM distances: distance of every
aligned P_om point to the nearest P_wli point), ground (photos re-posed on the WLI surface,
snapped points, rotation change per photo in degrees, and the bundle adjustment on the WLI
surface: keypoints used, photos adjusted, median reprojection error before and after, anchors
used and whether the result was mapped back to step 2's similarity), anchor (null when no scan
carries an intensity image: the photos anchored on the WLI intensity images, keypoints of the
scans with a 3-D point, matches and anchors per photo, each anchored photo's rotation between its
anchors' pose and its step-2 pose), seconds.
The PNG shows the pair-fitness matrix, the residual histogram and a top view of P_wli, the
aligned P_om and all cameras.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ofjax import fileio, plots
from ofjax.associate import align
from ofjax.associate.evaluate import rotation_deg
from ofjax.associate.pipeline import Association

TOP_VIEW_POINTS = 20_000  # P_wli points drawn in the top view (subsampled for a light PNG)


def _finite(x: float) -> float | None:
  """x, or None (JSON null) where it is not finite: strict JSON has no Infinity or NaN."""
  return float(x) if np.isfinite(x) else None


def _stats(x: np.ndarray) -> dict[str, float]:
  if len(x) == 0:
    return {}
  return {"mean": float(np.mean(x)), "median": float(np.median(x)),
          "p90": float(np.percentile(x, 90)), "p99": float(np.percentile(x, 99)),
          "max": float(np.max(x))}


def report_dict(a: Association, min_overlap: float) -> dict:
  names = [s.name for s in a.scene.wli]
  k = a.sfm.K
  return {
      "units": "um",
      "wli": {"scans": names, "merged_points": int(len(a.wli.points)),
              "pairs": [{"source": names[p.source], "target": names[p.target],
                         "fitness": p.fitness, "rmse_um": p.rmse_um, "seed": p.init,
                         "edge": p.fitness >= min_overlap} for p in a.wli.pairs]},
      "om": {"photos": len(a.scene.om), "registered": len(a.sfm.c2w), "missing": a.sfm.missing,
             "mean_reprojection_error_px": a.sfm.mean_reprojection_error_px,
             "sparse_points": a.sfm.num_points_total, "p_om_points": int(len(a.sfm.points)),
             "intrinsics": {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]),
                            "cy": float(k[1, 2])}},
      "align": {"scale_um_per_sfm_unit": a.align.scale, "initial_scale": a.align.initial_scale,
                "seed": a.align.seed, "fitness": a.align.fitness, "rmse_um": a.align.rmse_um,
                "height_cost": a.align.height_cost, "coverage": a.align.coverage,
                "turn_margin": _finite(a.align.turn_margin),
                "turn_runner_up_deg": _finite(a.align.turn_runner_up_deg),
                "turn_source": a.align.turn_source, "prior_deg": _finite(a.align.prior_deg),
                "residual_um": _stats(a.align.residuals_um)},
      "ground": {"reposed": len(a.ground.reposed), "snapped_points": a.ground.snapped,
                 "max_change_deg": max(a.ground.change_deg.values(), default=0.0),
                 "change_deg": a.ground.change_deg, "adjustment": a.ground.adjustment},
      "anchor": _anchor_dict(a),
      "seconds": a.seconds,
  }


def _anchor_dict(a: Association) -> dict | None:
  an = a.anchoring
  if an is None:
    return None
  counts = np.array([len(xy) for xy, _, _ in an.anchors.values()])
  step2 = {n: align.om_c2w_um(a.sfm.c2w[n], a.align.S) for n in an.c2w}
  return {"scans_with_intensity": sum(s.intensity is not None for s in a.scene.wli),
          "wli_keypoints": an.wli_keypoints, "anchored_photos": len(an.anchors),
          "matches": an.matches, "anchors": {n: len(xy) for n, (xy, _, _) in an.anchors.items()},
          "anchors_per_photo": _stats(counts),
          "step2_change_deg": _stats(np.array(
              [rotation_deg(an.c2w[n][:3, :3], step2[n][:3, :3]) for n in an.c2w]))}


def figure(a: Association) -> Figure:
  fig = Figure(figsize=(15, 4.8))
  ax0, ax1, ax2 = fig.subplots(1, 3)
  n = len(a.scene.wli)
  fit = np.full((n, n), np.nan)
  for p in a.wli.pairs:
    fit[p.source, p.target] = fit[p.target, p.source] = p.fitness
  im = ax0.imshow(fit, vmin=0, vmax=1, cmap="viridis")
  names = [s.name for s in a.scene.wli]
  ax0.set(xticks=range(n), yticks=range(n), xticklabels=names, yticklabels=names,
          title="WLI pair ICP fitness")
  for p in a.wli.pairs:
    ax0.text(p.target, p.source, f"{p.fitness:.2f}\n{p.rmse_um:.2g} um", ha="center",
             va="center", fontsize=7, color="w")
  fig.colorbar(im, ax=ax0, shrink=0.8)
  r = a.align.residuals_um
  ax1.hist(r[r <= np.percentile(r, 99)] if len(r) else r, bins=60, color="tab:blue")
  ax1.set(title=f"P_om to P_wli distance (median {np.median(r):.3g} um)",
          xlabel="distance (um)", ylabel="SfM points")
  w = a.wli.points[np.random.default_rng(0).permutation(len(a.wli.points))[:TOP_VIEW_POINTS]]
  ax2.scatter(w[:, 0], w[:, 1], s=0.3, c="0.7", label="P_wli")
  om = (a.sfm.points @ a.align.S[:3, :3].T) + a.align.S[:3, 3]
  ax2.scatter(om[:, 0], om[:, 1], s=1, c="tab:red", label="P_om (aligned)")
  oc = np.array([o.c2w[:3, 3] for o in a.scene.om if o.c2w is not None])
  ax2.scatter(oc[:, 0], oc[:, 1], marker="^", c="tab:green", s=14, label="OM cameras")
  wc = np.array([s.c2w[:3, 3] for s in a.scene.wli])
  ax2.scatter(wc[:, 0], wc[:, 1], marker="s", c="tab:purple", s=20, label="WLI scan origins")
  ax2.set(title=f"top view; OM scale {a.align.scale:.4g} um/unit", xlabel="x (um)",
          ylabel="y (um)", aspect="equal")
  ax2.legend(fontsize=7, loc="best")
  fig.suptitle(f"association: {len(a.sfm.c2w)}/{len(a.scene.om)} photos registered, "
               f"reprojection {a.sfm.mean_reprojection_error_px:.2f} px, "
               f"alignment fitness {a.align.fitness:.2f}")
  return fig


def write_report(a: Association, directory: str | Path, min_overlap: float) -> tuple[Path, Path]:
  """Writes DIR/report.json and DIR/report.png (atomically); returns their paths."""
  directory = Path(directory)
  js, png = directory / "report.json", directory / "report.png"
  fileio.write_json(js, report_dict(a, min_overlap))
  plots.save(figure(a), png)
  return js, png
