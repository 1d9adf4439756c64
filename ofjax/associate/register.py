"""Point-cloud registration building blocks shared by both association steps (open3d).

Conventions: a transform `T` is a [4, 4] float64 matrix that maps the *source* cloud into the
*target* cloud's frame (open3d's convention); `voxel` is the working resolution in the clouds' own
unit. Every cloud handed to these functions carries normals (point-to-plane ICP and FPFH need them).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

reg = o3d.pipelines.registration

NORMAL_RADIUS_VOXELS = 3.0  # normals from neighbours within this many voxels (>= 2 for a stable plane)
FPFH_RADIUS_VOXELS = 5.0  # FPFH support radius in voxels (open3d's global registration tutorial)
RANSAC_DISTANCE_VOXELS = 1.5  # inlier distance of RANSAC correspondences, in voxels
RANSAC_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999
RANSAC_EDGE_SIMILARITY = 0.9  # CorrespondenceCheckerBasedOnEdgeLength: rigid edges keep 90% of length


def to_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
  """points: [N, 3], normals: [N, 3] or None -> an open3d cloud (float64)."""
  pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
  if normals is not None:
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
  return pcd


def downsample(pcd: o3d.geometry.PointCloud, voxel: float, towards: np.ndarray | None = None,
               keep_points: bool = False) -> o3d.geometry.PointCloud:
  """Voxel-downsamples `pcd` and (re-)estimates normals, oriented along `towards` ([3]) if given.

  Normals are estimated after downsampling so that their support matches the working resolution.
  With `keep_points` the points stay as they are (`voxel` then only sets the normals' support):
  voxel centroids leave the surface where it curves, which costs accuracy at the finest level.
  """
  down = o3d.geometry.PointCloud(pcd) if keep_points else pcd.voxel_down_sample(voxel)
  down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * voxel,
                                                             max_nn=30))
  if towards is not None:
    down.orient_normals_to_align_with_direction(np.asarray(towards, np.float64))
  return down


def fpfh(pcd: o3d.geometry.PointCloud, voxel: float) -> reg.Feature:
  return reg.compute_fpfh_feature(
      pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel, max_nn=100))


def global_register(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
                    voxel: float, seed: int = 0) -> reg.RegistrationResult:
  """FPFH + RANSAC rigid registration of two clouds downsampled at `voxel` (with normals)."""
  o3d.utility.random.seed(seed)  # RANSAC is random; a fixed seed makes association reproducible
  dist = RANSAC_DISTANCE_VOXELS * voxel
  return reg.registration_ransac_based_on_feature_matching(
      source, target, fpfh(source, voxel), fpfh(target, voxel), True, dist,
      reg.TransformationEstimationPointToPoint(False), 3,
      [reg.CorrespondenceCheckerBasedOnEdgeLength(RANSAC_EDGE_SIMILARITY),
       reg.CorrespondenceCheckerBasedOnDistance(dist)],
      reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE))


def _criteria(max_iterations: int) -> reg.ICPConvergenceCriteria:
  """Run to `max_iterations` unless fitness and RMSE stop changing (relative 1e-9)."""
  return reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                    max_iteration=max_iterations)


def icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray,
        max_distance: float, max_iterations: int = 50) -> reg.RegistrationResult:
  """One rigid point-to-plane ICP run (target needs normals)."""
  return reg.registration_icp(source, target, max_distance, np.asarray(init, np.float64),
                              reg.TransformationEstimationPointToPlane(), _criteria(max_iterations))


def gicp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray,
         max_distance: float, max_iterations: int = 100) -> reg.RegistrationResult:
  """Generalized ICP (plane-to-plane: both clouds' local covariances, from open3d's default 20
  neighbours). Point-to-plane slides along flat parts where only a few edges hold the pose;
  matching the two clouds' surface patches holds it: on the synthetic circuit board the WLI scan
  rotation error goes from 0.097 to 0.016 deg."""
  return reg.registration_generalized_icp(
      source, target, max_distance, np.asarray(init, np.float64),
      reg.TransformationEstimationForGeneralizedICP(), _criteria(max_iterations))
