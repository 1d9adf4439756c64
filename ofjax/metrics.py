"""Geometry and colour errors of a predicted mesh against a synthetic scene's ground truth, in um.

Ground truth (a synthetic scene's ground_truth/): the true mesh, and points sampled on the part of
its surface the instruments can see (the visible top), each with its albedo.

Definitions (all distances are to surfaces, through open3d's RaycastingScene, not to samples):
  pred samples   `n_samples` points drawn uniformly by area on the predicted mesh (trimesh, seed
                 fixed), each with its face normal.
  evaluated region  the GT points only cover the visible top surface, and a prediction may close
                 itself underneath or extend past the scanned area, where nothing can be judged.
                 Accuracy therefore uses only the pred samples inside the GT points' XY bounding
                 box and no lower than the lowest GT point minus `crop_margin` x diagonal. Samples
                 above the surface (floaters) stay in and count against the prediction.
  diagonal       the diagonal of the GT points' bounding box: the scale of relative errors.
  accuracy       mean distance of the evaluated pred samples to the GT mesh.
  completeness   mean distance of the GT points to the predicted mesh.
  chamfer        (accuracy + completeness) / 2.
  F-score at tau precision = share of evaluated pred samples within tau of the GT mesh, recall =
                 share of GT points within tau of the prediction, F = 2 P R / (P + R); tau is a
                 fraction of the diagonal (`thresholds`).
  normal consistency  mean |n_pred . n_gt| over both directions (pred samples vs. the GT face
                 they are nearest to; GT points, with their own normals where given, vs. the
                 predicted face they are nearest to);
                 orientation-blind, as meshes from different tools wind their faces differently.
  albedo         at every GT point, the predicted colour is the barycentric interpolation of the
                 predicted vertex colours at the nearest predicted surface point; MAE, RMSE and
                 PSNR (dB, colours in [0, 1]). Shading baked into a colour scales it, so PSNR is
                 also reported after the least-squares gain per channel (`albedo_psnr_gain`).
  WLI-blind region  the GT points no WLI scan measured: no measured point of any scan (its valid
                 depths back-projected with the true pose) lies within one WLI pixel of them
                 (`measured_counts`). This is where the paper's fusion earns its margin (the OM
                 photos are the only data there), so completeness is also reported over the
                 blind points and over the rest (`completeness_blind_um`,
                 `completeness_measured_um`) with the blind points' share (`wli_blind_share`),
                 when the ground truth carries the counts.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ofjax.meshquery import MeshQuery, vertex_rgb

N_SAMPLES = 200_000  # pred samples: sets the Monte-Carlo error of accuracy to well below 1%
SEED = 0
THRESHOLDS = (0.005, 0.01)  # F-score thresholds as fractions of the GT diagonal
CROP_MARGIN = 0.05  # how far below the lowest GT point pred samples are still evaluated (x diag)
MSE_FLOOR = 1e-10  # caps the PSNR of identical colours at 100 dB instead of infinity


@dataclasses.dataclass
class GroundTruth:
  mesh: trimesh.Trimesh  # the true surface, um
  points: np.ndarray  # [N, 3] um, samples of its visible part
  albedo: np.ndarray | None = None  # [N, 3] RGB in [0, 1] at `points`
  normals: np.ndarray | None = None  # [N, 3] unit surface normals at `points`
  # [N] int: how many WLI scans measured each point (`measured_counts`); None: not known
  wli_scans: np.ndarray | None = None

  @property
  def diagonal(self) -> float:
    return float(np.linalg.norm(self.points.max(0) - self.points.min(0)))


@dataclasses.dataclass
class Evaluation:
  summary: dict  # scalar metrics (module docstring), JSON-ready
  gt_points: np.ndarray  # [N, 3] um
  completeness: np.ndarray  # [N] um, distance of each GT point to the prediction
  pred_points: np.ndarray  # [M, 3] um, the evaluated pred samples
  accuracy: np.ndarray  # [M] um, distance of each to the GT mesh


def sample_surface(mesh: trimesh.Trimesh, n: int = N_SAMPLES, seed: int = SEED
                   ) -> tuple[np.ndarray, np.ndarray]:
  """Points drawn uniformly by area on a mesh: points [n, 3] um and their unit face normals [n, 3]."""
  points, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
  return np.asarray(points), np.asarray(mesh.face_normals[face])


def evaluated_region(points: np.ndarray, gt_points: np.ndarray, margin: float) -> np.ndarray:
  """[N] bool: which `points` [N, 3] lie in the evaluated region (module docstring).

  margin: um below the lowest GT point that still counts.
  """
  lo, hi = gt_points.min(0), gt_points.max(0)
  return (np.all((points[:, :2] >= lo[:2]) & (points[:, :2] <= hi[:2]), axis=-1)
          & (points[:, 2] >= lo[2] - margin))


def json_ready(value):
  """NaN -> None, recursively through dicts and lists (JSON has no NaN)."""
  if isinstance(value, float) and np.isnan(value):
    return None
  if isinstance(value, dict):
    return {k: json_ready(v) for k, v in value.items()}
  if isinstance(value, list):
    return [json_ready(v) for v in value]
  return value


def psnr(mse: float) -> float:
  """dB of a mean squared error of colours in [0, 1]."""
  return float(-10.0 * np.log10(max(mse, MSE_FLOOR)))


def albedo_errors(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
  """MAE, RMSE, PSNR and gain-aligned PSNR of colours pred, gt: [N, 3] in [0, 1]."""
  err = pred - gt
  mse = float(np.mean(err ** 2))
  gain = np.sum(pred * gt, 0) / np.maximum(np.sum(pred * pred, 0), MSE_FLOOR)
  return {"albedo_mae": float(np.mean(np.abs(err))), "albedo_rmse": float(np.sqrt(mse)),
          "albedo_psnr": psnr(mse),
          "albedo_psnr_gain": psnr(float(np.mean((pred * gain - gt) ** 2))),
          "albedo_gain": [float(g) for g in gain]}


def measured_counts(points: np.ndarray, clouds: list[np.ndarray], radius: float) -> np.ndarray:
  """[N] int: for each of `points` [N, 3], how many of `clouds` (each [M_k, 3], one scan's
  measured points, um) hold a point within `radius` um of it."""
  count = np.zeros(len(points), np.int64)
  for cloud in clouds:
    if len(cloud):
      count += np.isfinite(cKDTree(cloud).query(points, distance_upper_bound=radius)[0])
  return count


def region_split(completeness: np.ndarray, wli_scans: np.ndarray) -> dict[str, float]:
  """Completeness [N] um over the WLI-blind GT points (wli_scans [N] == 0) and over the rest."""
  blind = wli_scans == 0
  mean = lambda sel: float(completeness[sel].mean()) if sel.any() else float("nan")
  return {"wli_blind_share": float(blind.mean()), "completeness_blind_um": mean(blind),
          "completeness_measured_um": mean(~blind)}


def fscores(accuracy: np.ndarray, completeness: np.ndarray, diagonal: float,
            thresholds: tuple[float, ...]) -> list[dict[str, float]]:
  """Precision, recall and F-score at each threshold (a fraction of `diagonal`).

  accuracy: [M] um, completeness: [N] um.
  """
  rows = []
  for t in thresholds:
    tau = t * diagonal
    p = float(np.mean(accuracy < tau)) if len(accuracy) else 0.0
    r = float(np.mean(completeness < tau))
    rows.append({"threshold_rel": t, "threshold_um": tau, "precision": p, "recall": r,
                 "fscore": 2 * p * r / (p + r) if p + r > 0 else 0.0})
  return rows


def evaluate(pred: trimesh.Trimesh, gt: GroundTruth, thresholds: tuple[float, ...] = THRESHOLDS,
             n_samples: int = N_SAMPLES, seed: int = SEED,
             crop_margin: float = CROP_MARGIN) -> Evaluation:
  """All metrics of the module docstring for one predicted mesh (um)."""
  diagonal = gt.diagonal
  pred_query, gt_query = MeshQuery.of(pred), MeshQuery.of(gt.mesh)
  samples, sample_normals = sample_surface(pred, n_samples, seed)
  keep = evaluated_region(samples, gt.points, crop_margin * diagonal)
  samples, sample_normals = samples[keep], sample_normals[keep]
  to_gt = gt_query.closest(samples)
  to_pred = pred_query.closest(gt.points)
  gt_normals = gt.normals if gt.normals is not None else gt_query.closest(gt.points)["normal"]
  acc, comp = to_gt["distance"], to_pred["distance"]
  accuracy = float(acc.mean()) if len(acc) else float("nan")
  completeness = float(comp.mean())
  chamfer = (accuracy + completeness) / 2
  consistency = np.concatenate([np.abs(np.sum(sample_normals * to_gt["normal"], -1)),
                                np.abs(np.sum(gt_normals * to_pred["normal"], -1))])
  summary = {
      "accuracy_um": accuracy, "completeness_um": completeness, "chamfer_um": chamfer,
      "accuracy_rel": accuracy / diagonal, "completeness_rel": completeness / diagonal,
      "chamfer_rel": chamfer / diagonal, "diagonal_um": diagonal,
      "fscore": fscores(acc, comp, diagonal, thresholds),
      "normal_consistency": float(consistency.mean()),
      "n_pred_samples": int(n_samples), "n_pred_evaluated": int(keep.sum()),
      "n_gt_points": int(len(gt.points)),
  }
  if gt.wli_scans is not None:
    summary.update(region_split(comp, gt.wli_scans))
  rgb = vertex_rgb(pred)
  if gt.albedo is not None and rgb is not None:
    colours = pred_query.interpolate(rgb, to_pred["face"], to_pred["bary"])
    summary.update(albedo_errors(colours, gt.albedo))
  return Evaluation(summary, gt.points, comp, samples, acc)
