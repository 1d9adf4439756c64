"""ofjax.associate.sfm's helpers: keypoint scales and the seeded absolute pose, against pycolmap's
own computation and a known camera."""

from __future__ import annotations

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from ofjax.associate import evaluate, sfm

K = np.array([[700.0, 0, 160], [0, 700.0, 120], [0, 0, 1]])
SIZE = (320, 240)  # width, height in pixels


def test_keypoint_scale_is_colmaps():
  rng = np.random.default_rng(2)
  shapes = rng.normal(0.0, 3.0, (50, 4))
  ref = [pycolmap.FeatureKeypoint(x=0.0, y=0.0, a11=a, a12=b, a21=c, a22=d).compute_scale()
         for a, b, c, d in shapes]
  np.testing.assert_allclose(sfm.keypoint_scale(shapes), ref, rtol=1e-6)  # COLMAP's float32


def noisy_matches(rng, n=300, noise_px=1.0, outliers=0.2):
  """A camera 650 um above a relief, looking down with a 10 deg tilt; its keypoints of n points
  with noise_px per axis (so that the inliers at the edge of sfm.POSE_MAX_ERROR_PX depend on
  RANSAC's draws), a share of them replaced by random pixels -> (c2w [4, 4], xy [n, 2], X [n, 3],
  outlier mask [n])."""
  c2w = np.eye(4)
  c2w[:3, :3] = Rotation.from_euler("xyz", (180.0 + 10.0, 4.0, 30.0), degrees=True).as_matrix()
  c2w[:3, 3] = -650.0 * c2w[:3, 2]
  X = np.column_stack([rng.uniform(-80, 80, (n, 2)), rng.uniform(-40, 40, n)])
  cam = (X - c2w[:3, 3]) @ c2w[:3, :3]
  xy = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2] + rng.normal(0, noise_px, (n, 2))
  bad = rng.random(n) < outliers
  xy[bad] = rng.uniform((0, 0), SIZE, (int(bad.sum()), 2))
  return c2w, xy, X, bad


def test_absolute_pose_repeats_with_its_seed_and_finds_the_camera():
  c2w, xy, X, bad = noisy_matches(np.random.default_rng(0))
  first = sfm.absolute_pose(xy, X, K, SIZE, seed=0)
  assert first is not None
  # COLMAP's default seed (-1) draws anew each call: on data like these the pose moved by 0.7-2.6
  # um and 0.06-0.23 deg between calls. With a seed, calls repeat exactly.
  for _ in range(3):
    again = sfm.absolute_pose(xy, X, K, SIZE, seed=0)
    np.testing.assert_array_equal(again[0], first[0])
    np.testing.assert_array_equal(again[1], first[1])
  est, inliers = first
  assert inliers.dtype == bool and inliers.shape == (len(X),)
  assert not np.any(inliers & bad) and inliers.sum() > 0.8 * (~bad).sum()
  # Measured 0.16 deg and 1.6 um: the narrow field's turn-shift ambiguity at 1 px noise.
  assert evaluate.rotation_deg(est[:3, :3], c2w[:3, :3]) < 0.5
  assert np.linalg.norm(est[:3, 3] - c2w[:3, 3]) < 5.0  # um, of a camera 650 um away
