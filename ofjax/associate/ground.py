"""Step 2b: re-pose the OM cameras on the exact WLI surface after the similarity of step 2.

Structure-from-motion of a nearly flat sample through a narrow-field microscope is weakly
determined: camera tilt trades against a bend of the reconstructed surface, so after the best
similarity the SfM points lie near the WLI surface while cameras can still be degrees off (the
circuit scene: 5-19 degrees for the top and 15-degree photos). The WLI measured that surface, so
it is used as the 3-D truth: every SfM point within SNAP_GATE_VOXELS of P_wli moves onto the WLI
surface along the local WLI normal (the height the WLI knows is taken from it, the position along
the surface stays the SfM's), each photo is re-posed from its 2-D keypoints and those 3-D points
(pycolmap's LO-RANSAC absolute pose + refinement, intrinsics fixed), the points are triangulated
again from the new cameras (linear DLT), and this repeats ROUNDS times.

Conventions: c2w are [4, 4] camera-to-world in um (OpenCV axes); points [N, 3] in um; `tracks`
map a point index to its observations [(photo name, xy [2] pixels)].
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from ofjax.associate.evaluate import rotation_deg

ROUNDS = 3  # snap -> re-pose -> re-triangulate rounds (the change is < 0.1 degree after 3)
SNAP_GATE_VOXELS = 3.0  # SfM points farther than this from P_wli (voids, beyond the scans) are
# not snapped and take no part in re-posing
MIN_POINTS = 20  # a photo with fewer snapped points keeps its step-2 pose
RANSAC_MAX_ERROR_PX = 2.0  # absolute-pose inlier threshold (SfM keeps points with error <= 1 px)


@dataclasses.dataclass
class Grounding:
  c2w: dict[str, np.ndarray]  # photo name -> [4, 4] camera-to-world in um
  reposed: list[str]  # photos re-posed on the WLI surface (the others keep the step-2 pose)
  snapped: int  # SfM points on the WLI surface in the last round
  change_deg: dict[str, float]  # photo name -> rotation between its step-2 and final pose


def snap(points: np.ndarray, wli_points: np.ndarray, wli_normals: np.ndarray, tree: cKDTree,
         gate: float) -> np.ndarray:
  """points [N, 3] (NaN rows allowed) moved onto the tangent plane of their nearest WLI point
  -> [N, 3], NaN where no WLI point lies within `gate`."""
  out = np.full_like(points, np.nan)
  ok = np.all(np.isfinite(points), axis=1)
  d, j = tree.query(points[ok], distance_upper_bound=gate)
  hit = np.isfinite(d)
  p, q, n = points[ok][hit], wli_points[j[hit]], wli_normals[j[hit]]
  rows = np.flatnonzero(ok)[hit]
  out[rows] = p - n * np.einsum("ij,ij->i", n, p - q)[:, None]
  return out


def triangulate(tracks: dict[int, list], c2w: dict[str, np.ndarray], K: np.ndarray,
                n_points: int) -> np.ndarray:
  """Linear (DLT) triangulation of every track seen by >= 2 posed photos -> [n_points, 3], NaN
  for the others."""
  proj = {name: K @ np.linalg.inv(m)[:3] for name, m in c2w.items()}
  out = np.full((n_points, 3), np.nan)
  for i, obs in tracks.items():
    obs = [(proj[name], xy) for name, xy in obs if name in proj]
    if len(obs) < 2:
      continue
    rows = np.concatenate([[xy[0] * P[2] - P[0], xy[1] * P[2] - P[1]] for P, xy in obs])
    rows /= np.linalg.norm(rows[:, :3], axis=1, keepdims=True)  # equal weight per equation
    X = np.linalg.svd(rows)[2][-1]
    if abs(X[3]) > 0:
      out[i] = X[:3] / X[3]
  return out


def ground_cameras(c2w: dict[str, np.ndarray], points: np.ndarray,
                   observations: dict[str, tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                   image_size: tuple[int, int], wli_points: np.ndarray, wli_normals: np.ndarray,
                   wli_voxel_um: float) -> Grounding:
  """Re-poses the photos of `c2w` (step-2 poses, um) on P_wli (module docstring).

  points: [N, 3] P_om in um (after the similarity); observations: photo name -> (xy [k, 2],
  point index [k]) from ofjax.associate.sfm; K: [3, 3]; image_size: (width, height) in pixels.
  """
  tracks: dict[int, list] = {}
  for name, (xy, idx) in observations.items():
    for x, i in zip(xy, idx):
      tracks.setdefault(int(i), []).append((name, x))
  camera = pycolmap.Camera(model="PINHOLE", width=int(image_size[0]), height=int(image_size[1]),
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
  estimation = pycolmap.AbsolutePoseEstimationOptions()
  estimation.ransac.max_error = RANSAC_MAX_ERROR_PX
  refinement = pycolmap.AbsolutePoseRefinementOptions()
  refinement.refine_focal_length = False
  refinement.refine_extra_params = False
  tree = cKDTree(wli_points)
  gate = SNAP_GATE_VOXELS * wli_voxel_um
  poses, reposed, snapped = dict(c2w), set(), 0
  for _ in range(ROUNDS):
    on_wli = snap(points, wli_points, wli_normals, tree, gate)
    ok = np.all(np.isfinite(on_wli), axis=1)
    snapped = int(ok.sum())
    for name, (xy, idx) in observations.items():
      use = ok[idx]
      if name not in poses or use.sum() < MIN_POINTS:
        continue
      res = pycolmap.estimate_and_refine_absolute_pose(xy[use], on_wli[idx[use]], camera,
                                                       estimation, refinement)
      if res is None or res["num_inliers"] < MIN_POINTS:
        continue
      w2c = np.eye(4)
      w2c[:3] = res["cam_from_world"].matrix()
      poses[name] = np.linalg.inv(w2c)
      reposed.add(name)
    points = triangulate(tracks, poses, K, len(points))
  change = {name: rotation_deg(poses[name][:3, :3], c2w[name][:3, :3]) for name in poses}
  return Grounding(poses, sorted(reposed), snapped, change)
