"""`python -m ofjax.eval --pred MESH --gt SCENE_DIR [--json] [--out DIR]`: a mesh against the truth.

Reads SCENE_DIR/ground_truth/ as `ofjax.synth` writes it: mesh.ply (the true surface, um),
surface_points.ply (points on its visible part with true albedo colours and normals) and
meta.json (used for the WLI pixel size, so errors are also given in WLI pixels). Computes the
metrics of `ofjax.metrics` (Chamfer accuracy / completeness / mean in um, relative to the GT
points' bounding-box diagonal and in WLI pixels; F-scores; normal consistency; albedo MAE / RMSE /
PSNR), prints a table or, with --json, one JSON object, and writes into --out (default: beside the
mesh) <mesh>_eval.json and two top-view heat maps: <mesh>_completeness.png (every GT point coloured
by its distance to the mesh) and <mesh>_accuracy.png (every evaluated mesh sample coloured by its
distance to the true surface).

When SCENE_DIR is a native bundle (scene.json, as `ofjax.synth` writes by default), its WLI scans,
placed with the true poses (ground_truth/poses.json), tell which GT points no scan measured:
completeness is then also given over those WLI-blind points and over the rest (ofjax.metrics).

--poses POSES.json names the poses the mesh was reconstructed with. Poses that `ofjax.associate`
estimated live in its own world frame (scan 0's, sample up, origin at scan 0's median point),
which differs from the generator's frame by a rigid motion no data can fix (the gauge). With
--poses the mesh is first moved into the truth's frame by that motion, fitted over the WLI
cameras of POSES.json and ground_truth/poses.json (`ofjax.associate.evaluate.gauge`: the WLI
scans define the um frame), so the metrics measure the reconstruction, not the choice of origin.
Without it the mesh is taken to be in the truth's frame already (true poses).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

from ofjax import fileio, metrics, plots
from ofjax.errors import UserError, cli
from ofjax.meshquery import load_mesh

LENGTH_KEYS = ("accuracy", "completeness", "chamfer")


def load_ground_truth(scene_dir: str | Path) -> tuple[metrics.GroundTruth, dict]:
  """The ground truth of a synthetic scene directory, and its meta.json contents."""
  gt_dir = Path(scene_dir) / "ground_truth"
  if not gt_dir.is_dir():
    raise UserError(f"{gt_dir}: not found; --gt must be a scene made by `python -m ofjax.synth`, "
                    "which writes ground truth")
  mesh = load_mesh(gt_dir / "mesh.ply")
  path = gt_dir / "surface_points.ply"
  if not path.is_file():
    raise UserError(f"{path}: not found; regenerate the scene with `python -m ofjax.synth`")
  cloud = o3d.io.read_point_cloud(str(path))
  if not cloud.has_points():
    raise UserError(f"{path}: holds no points; regenerate the scene with `python -m ofjax.synth`")
  meta_path = gt_dir / "meta.json"
  try:
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
  except (json.JSONDecodeError, UnicodeDecodeError):
    raise UserError(f"{meta_path}: not valid JSON; regenerate the scene") from None
  points = np.asarray(cloud.points, np.float64)
  gt = metrics.GroundTruth(
      mesh, points, np.asarray(cloud.colors, np.float64) if cloud.has_colors() else None,
      np.asarray(cloud.normals, np.float64) if cloud.has_normals() else None,
      wli_coverage(Path(scene_dir), points))
  return gt, meta


def wli_coverage(scene_dir: Path, points: np.ndarray) -> np.ndarray | None:
  """[N] int: how many of the scene's WLI scans measured each GT point (within one WLI pixel,
  true poses), or None when SCENE_DIR is not a native bundle with true poses."""
  poses = scene_dir / "ground_truth" / "poses.json"
  if not (scene_dir / "scene.json").is_file() or not poses.is_file():
    return None
  from ofjax.scene import load_scene, wli_points
  scans = load_scene(scene_dir, poses=poses).wli
  radius = max(max(s.pixel_size) for s in scans)
  return metrics.measured_counts(points, [wli_points(s) for s in scans], radius)


def to_truth_frame(mesh, poses_path: Path, scene_dir: Path, meta: dict) -> np.ndarray:
  """Moves `mesh` (trimesh, in place) from the frame of poses_path into the truth's; returns the
  [4, 4] rigid transform applied (module docstring, --poses)."""
  from ofjax.associate.evaluate import gauge
  from ofjax.scene import load_poses
  gt_file = Path(scene_dir) / "ground_truth" / "poses.json"
  size = meta.get("size_um")
  if not size:
    raise UserError(f"{Path(scene_dir) / 'ground_truth' / 'meta.json'}: has no size_um; regenerate "
                    "the scene with `python -m ofjax.synth`")
  try:
    transform = gauge(load_poses(poses_path), load_poses(gt_file), float(size))
  except ValueError:
    raise UserError(f"{poses_path}: shares no WLI camera name with {gt_file}; --poses needs the "
                    "poses.json written by `python -m ofjax.associate` for this scene") from None
  mesh.apply_transform(transform)
  return transform


def with_pixels(summary: dict, meta: dict) -> dict:
  """Adds the Chamfer terms in WLI pixels when the scene's meta gives the pixel size."""
  px = meta.get("wli_pixel_size_um")
  if not px:
    return summary
  return {**summary, "wli_pixel_size_um": px,
          **{f"{k}_px": summary[f"{k}_um"] / px for k in LENGTH_KEYS}}


def table(s: dict) -> str:
  px = "wli_pixel_size_um" in s
  lines = [f"{'':20s}{'um':>12s}{'% diag':>10s}" + (f"{'WLI px':>10s}" if px else "")]
  for k in LENGTH_KEYS:
    row = f"{k:20s}{s[f'{k}_um']:12.4g}{100 * s[f'{k}_rel']:10.4f}"
    lines.append(row + (f"{s[f'{k}_px']:10.4f}" if px else ""))
  for f in s["fscore"]:
    lines.append(f"F-score @{100 * f['threshold_rel']:g}% ({f['threshold_um']:.3g} um)"
                 f"  {f['fscore']:.4f}  (precision {f['precision']:.4f}, recall {f['recall']:.4f})")
  lines.append(f"normal consistency  {s['normal_consistency']:.4f}")
  if s.get("wli_blind_share"):
    lines.append(f"WLI-blind truth     {100 * s['wli_blind_share']:.1f}% of the GT points: "
                 f"completeness {s['completeness_blind_um']:.4g} um there, "
                 f"{s['completeness_measured_um']:.4g} um on the measured rest")
  elif "wli_blind_share" in s:
    lines.append("WLI-blind truth     none: some WLI scan measured every GT point")
  if "albedo_psnr" in s:
    lines.append(f"albedo              MAE {s['albedo_mae']:.4f}, RMSE {s['albedo_rmse']:.4f}, "
                 f"PSNR {s['albedo_psnr']:.2f} dB (after per-channel gain "
                 f"{', '.join(f'{g:.3f}' for g in s['albedo_gain'])}: "
                 f"{s['albedo_psnr_gain']:.2f} dB)")
  else:
    lines.append("albedo              n/a (the mesh has no vertex colours)")
  lines.append(f"{s['n_gt_points']} GT points; {s['n_pred_evaluated']} of {s['n_pred_samples']} "
               f"mesh samples in the evaluated region; diagonal {s['diagonal_um']:.4g} um")
  return "\n".join(lines)


def parse_thresholds(text: str) -> tuple[float, ...]:
  try:
    values = tuple(float(v) for v in text.split(","))
  except ValueError:
    values = ()
  if not values or not all(0 < v < 1 for v in values):
    raise UserError(f"--thresholds {text!r}: expected comma-separated fractions of the diagonal in "
                    "(0, 1), e.g. 0.005,0.01")
  return values


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m ofjax.eval", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--pred", required=True, type=Path, help="predicted mesh in um (PLY/OBJ/GLB)")
  p.add_argument("--gt", required=True, type=Path, help="synthetic scene directory")
  p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
  p.add_argument("--out", type=Path, help="where the PNGs and <mesh>_eval.json go (default: "
                 "the mesh's directory)")
  p.add_argument("--thresholds", default=",".join(str(t) for t in metrics.THRESHOLDS),
                 help="F-score thresholds as fractions of the GT diagonal (default 0.005,0.01)")
  p.add_argument("--samples", type=int, default=metrics.N_SAMPLES,
                 help=f"points sampled on the mesh (default {metrics.N_SAMPLES})")
  p.add_argument("--poses", type=Path, help="the poses the mesh was reconstructed with, when not "
                 "the true ones (e.g. SCENE/poses.json from ofjax.associate): the mesh is moved "
                 "into the truth's frame first")
  return p


@cli
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  thresholds = parse_thresholds(args.thresholds)
  if args.samples < 1:
    raise UserError(f"--samples {args.samples}: must be positive")
  pred = load_mesh(args.pred)
  gt, meta = load_ground_truth(args.gt)
  frame = {}
  if args.poses is not None:
    g = to_truth_frame(pred, args.poses, args.gt, meta)
    frame = {"poses": str(args.poses), "to_truth_frame": g.tolist()}
  ev = metrics.evaluate(pred, gt, thresholds=thresholds, n_samples=args.samples)
  summary = with_pixels(ev.summary, meta)
  if summary["n_pred_evaluated"] == 0:
    print(f"ofjax: warning: {args.pred} has no surface over the ground truth's region; accuracy "
          "is undefined", file=sys.stderr)
  out = args.out or args.pred.parent
  stem = args.pred.stem
  vmax = 2 * thresholds[-1] * summary["diagonal_um"]  # a shared scale: twice the loosest tau
  pngs = {
      "completeness_png": plots.scatter_map(
          out / f"{stem}_completeness.png", ev.gt_points[:, :2], ev.completeness,
          f"{args.pred.name}: completeness (GT point -> mesh), mean "
          f"{summary['completeness_um']:.3g} um", "distance (um)", vmax=vmax),
      "accuracy_png": plots.scatter_map(
          out / f"{stem}_accuracy.png", ev.pred_points[:, :2], ev.accuracy,
          f"{args.pred.name}: accuracy (mesh -> GT surface), mean "
          f"{summary['accuracy_um']:.3g} um", "distance (um)", vmax=vmax),
  }
  result = metrics.json_ready({"pred": str(args.pred), "gt": str(args.gt), "units": "um", **frame,
                               **summary, **{k: str(v) for k, v in pngs.items()}})
  fileio.write_json(out / f"{stem}_eval.json", result)
  if args.json:
    print(json.dumps(result))
  else:
    print(f"ofjax.eval: {args.pred} vs {args.gt}")
    print(table(summary))
    print(f"heat maps: {pngs['completeness_png']}, {pngs['accuracy_png']}; "
          f"numbers: {out / f'{stem}_eval.json'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
