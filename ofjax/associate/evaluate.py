"""Pose errors of an association against ground truth, after fixing the gauge.

The association's world frame is scan 0's (sample up); a synthetic scene's truth lives in its own
frame. Both are in um, so they differ by a rigid motion (the gauge). `gauge` fits it (open3d's
Umeyama, TransformationEstimationPointToPoint) over the WLI cameras only - their centres and
points one scene size along each of their axes, so rotations weigh as much as positions - because
the WLI scans define the um frame; the OM cameras are then compared in that same gauge, so their
errors include step 2's. Errors per camera: rotation angle of R_gt^T R_est (degrees) and distance
between camera origins (um; WLI also in pixels; OM also split into its part along the true optical
axis and the lateral rest). The OM scale error is |s - 1| of a similarity fitted from the
gauge-aligned OM camera centres to the true ones; that similarity's rotation angle and the largest
centre error left after it separate what the OM block shares (step 2's scale and turn) from each
camera's own error (the SfM's).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

reg = o3d.pipelines.registration


def fit_transform(src: np.ndarray, dst: np.ndarray, with_scaling: bool) -> np.ndarray:
  """[4, 4] transform mapping src [N, 3] onto dst [N, 3] in least squares (Umeyama)."""
  corr = o3d.utility.Vector2iVector(np.stack([np.arange(len(src))] * 2, 1).astype(np.int32))
  return np.asarray(reg.TransformationEstimationPointToPoint(with_scaling).compute_transformation(
      o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
      o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst)), corr))


def _pose_points(c2ws: list[np.ndarray], length: float) -> np.ndarray:
  """[4 N, 3]: every camera's origin and the tips of its three axes, `length` long."""
  return np.concatenate([np.vstack([m[:3, 3], m[:3, 3] + length * m[:3, :3].T]) for m in c2ws])


def rotation_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
  c = (np.trace(r_gt.T @ r_est) - 1) / 2
  return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _cams(poses: dict) -> dict[str, dict]:
  return {c["name"]: c for c in poses["cameras"]}


def gauge(est: dict, gt: dict, scene_size: float) -> np.ndarray:
  """[4, 4] rigid gt_from_est fitted over the WLI cameras of two poses files' contents."""
  e, g = _cams(est), _cams(gt)
  names = [n for n, c in g.items() if c["modality"] == "wli" and n in e]
  if not names:
    raise ValueError("the two poses files share no WLI camera name, so the gauge is undefined")
  src = _pose_points([np.asarray(e[n]["c2w"]) for n in names], scene_size)
  dst = _pose_points([np.asarray(g[n]["c2w"]) for n in names], scene_size)
  return fit_transform(src, dst, with_scaling=False)


def pose_errors(est: dict, gt: dict, scene_size: float) -> dict:
  """Per-camera and summary errors of poses file contents `est` against `gt` (module docstring).

  scene_size: the sample's size in um (e.g. the diagonal of the WLI points' bounding box); it
  sets the gauge's rotation weight and the relative OM centre error.
  """
  G = gauge(est, gt, scene_size)
  e, g = _cams(est), _cams(gt)
  rows = []
  for name, cg in g.items():
    if name not in e:
      rows.append({"name": name, "modality": cg["modality"], "registered": False})
      continue
    m = G @ np.asarray(e[name]["c2w"])
    mg = np.asarray(cg["c2w"])
    row = {"name": name, "modality": cg["modality"], "registered": True,
           "rot_deg": rotation_deg(m[:3, :3], mg[:3, :3]),
           "trans_um": float(np.linalg.norm(m[:3, 3] - mg[:3, 3]))}
    if cg["modality"] == "wli":
      row["trans_px"] = row["trans_um"] / float(np.mean(cg["intrinsics"]["pixel_size"]))
    else:
      row["centre_rel"] = row["trans_um"] / scene_size
      along = float(np.dot(m[:3, 3] - mg[:3, 3], mg[:3, 2]))  # + : behind the true camera
      row["centre_along_um"] = along
      row["centre_lateral_um"] = float(np.sqrt(max(row["trans_um"] ** 2 - along ** 2, 0.0)))
    rows.append(row)
  summary = {"scene_size_um": scene_size}
  for mod in ("wli", "om"):
    rs = [r for r in rows if r["modality"] == mod]
    ok = [r for r in rs if r["registered"]]
    summary[mod] = {"cameras": len(rs), "registered": len(ok),
                    "max_rot_deg": max((r["rot_deg"] for r in ok), default=float("nan")),
                    "max_trans_um": max((r["trans_um"] for r in ok), default=float("nan"))}
    if mod == "wli":
      summary[mod]["max_trans_px"] = max((r["trans_px"] for r in ok), default=float("nan"))
  om_rows = [r for r in rows if r["modality"] == "om" and r["registered"]]
  om = [r["name"] for r in om_rows]
  if om:
    summary["om"]["max_centre_rel"] = max(r["centre_rel"] for r in om_rows)
    summary["om"]["median_centre_along_um"] = float(np.median(
        [abs(r["centre_along_um"]) for r in om_rows]))
  if len(om) >= 3:
    src = np.array([(G @ np.asarray(e[n]["c2w"]))[:3, 3] for n in om])
    dst = np.array([np.asarray(g[n]["c2w"])[:3, 3] for n in om])
    sim = fit_transform(src, dst, True)
    scale = float(np.cbrt(np.linalg.det(sim[:3, :3])))
    summary["om"]["scale_error"] = abs(scale - 1.0)
    summary["om"]["similarity_rot_deg"] = rotation_deg(sim[:3, :3] / scale, np.eye(3))
    left = src @ sim[:3, :3].T + sim[:3, 3] - dst
    summary["om"]["max_centre_rel_after_similarity"] = float(np.linalg.norm(left, axis=1).max()
                                                             / scene_size)
  return {"summary": summary, "cameras": rows}


def scene_pose_errors(scene_dir) -> dict:
  """pose_errors' summary of SCENE_DIR/poses.json against the synthetic scene's ground truth.

  The scene size is the diagonal of the true WLI points' bounding box (every 4th pixel).
  """
  from pathlib import Path

  from ofjax import scene as scene_lib
  d = Path(scene_dir)
  gt_file = d / "ground_truth" / "poses.json"
  truth = scene_lib.load_scene(d, poses=gt_file)
  size = float(np.linalg.norm(np.ptp(truth.wli_points(stride=4), axis=0)))
  return pose_errors(scene_lib.load_poses(d / "poses.json"), scene_lib.load_poses(gt_file),
                     size)["summary"]
