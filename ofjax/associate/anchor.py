"""Step 2c: anchor the OM photos on the WLI scans' intensity images, when the scans carry them.

A WLI instrument records an intensity image on the same pixels as each height map. Its texture is
the sample's, and every pixel of it has an exact 3-D point: the height map posed by step 1. SIFT
keypoints of those images, lifted to 3-D and matched to each photo's SIFT keypoints, give 2-D-3-D
correspondences (the photo's *anchors*) that do not pass through the SfM's points. Those points
are biased where the surface slopes (0.5-1 um inside it on the synthetic scenes, through the true
cameras; benchmarks/README.md) and a nearly flat sample pins the turn about its normal and the
scale of P_om only weakly, so step 2's similarity keeps errors that no fit of P_om to P_wli can
remove. Anchors measure the turn and the scale of every photo directly against the WLI's texture.

Per photo: its keypoints are matched to those of each scan in turn (`match`: mutual nearest
neighbours that pass Lowe's ratio test, the rule of COLMAP's and scikit-image's matchers; scan by
scan, because a surface point seen by two scans would fail the ratio test against itself), then
LO-RANSAC absolute pose with
the intrinsics fixed (pycolmap) keeps the matches consistent with one camera; a photo with at
least MIN_ANCHORS inliers is anchored, with that pose and those inliers. The bundle adjustment of
ofjax.associate.ground then holds the anchored photos on their anchors.

Names: `xy` [k, 2] pixel coordinates with pixel centres at +0.5 (COLMAP's and ofjax's
convention); `X` [k, 3] points in um in the WLI world frame; `desc` [k, 128] float32 SIFT
descriptors, L2-normalised.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pycolmap
from scipy import ndimage

from ofjax import scene as scene_lib
from ofjax.associate import sfm

MAX_NUM_FEATURES = 8192  # SIFT keypoints per image (a 1,024 px scan holds more texture than 4,096)
MATCH_MAX_RATIO = 0.8  # Lowe's ratio test: nearest / second-nearest descriptor distance
THREADS = 1  # one SIFT extraction thread: the same keypoints in every run
MIN_ANCHORS = 30  # a photo with fewer pose-consistent matches is not anchored
MIN_ANCHORED_PHOTOS = 3  # fewer anchored photos cannot fix the OM block's turn and scale
DEPTH_STEP_PIXELS = 2.0  # a keypoint whose 2 x 2 depth neighbourhood spans more than this many
# pixel sizes straddles a depth edge (the heights of two surfaces): no 3-D point for it
INTENSITY_PERCENTILES = (0.5, 99.5)  # the intensity range stretched to [0, 1] for SIFT (any unit)
LUMINANCE = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601: photo -> grey for SIFT


@dataclasses.dataclass
class Anchoring:
  anchors: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]  # photo name -> (xy [k, 2],
  # X [k, 3] um, scale [k]: the photo keypoint's SIFT scale in pixels)
  c2w: dict[str, np.ndarray]  # anchored photo -> [4, 4] camera-to-world from its anchors alone
  wli_keypoints: int  # scan keypoints with a 3-D point, all scans together
  matches: dict[str, int]  # photo name -> descriptor matches before the pose's RANSAC


def _extractor() -> pycolmap.FeatureExtractor:
  options = pycolmap.FeatureExtractionOptions()
  options.sift.max_num_features = MAX_NUM_FEATURES
  options.num_threads = THREADS
  return pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)


def sift(extractor: pycolmap.FeatureExtractor, grey: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """SIFT of a grey image [H, W] in [0, 1] -> (xy [k, 2] float64, desc [k, 128] float32,
  scale [k] float64 pixels)."""
  keypoints, descriptors = extractor.extract_from_float32_array(
      np.ascontiguousarray(grey, np.float32))
  desc = np.asarray(descriptors.data, np.float32)
  desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1.0)
  rows = np.array([[k.x, k.y, k.a11, k.a12, k.a21, k.a22] for k in keypoints],
                  np.float64).reshape(-1, 6)
  return rows[:, :2], desc, sfm.keypoint_scale(rows[:, 2:])


def match(desc_a: np.ndarray, desc_b: np.ndarray, max_ratio: float = MATCH_MAX_RATIO
          ) -> np.ndarray:
  """[m, 2] index pairs (i in a, j in b): mutual nearest neighbours in Euclidean distance whose
  distance is below max_ratio times that of the second-nearest in b (Lowe's test).

  scikit-image's match_descriptors (cross_check, max_ratio) computes the same pairs, but through
  scipy's cdist, and COLMAP's CPU matcher likewise takes ~0.35 s per photo-scan pair here; with
  unit descriptors, |a - b|^2 = 2 - 2 a.b is one BLAS product (~0.01 s).
  """
  if len(desc_a) == 0 or len(desc_b) < 2:
    return np.zeros((0, 2), np.int64)
  sq = np.maximum(2.0 - 2.0 * (desc_a @ desc_b.T), 0.0)  # [ka, kb] squared distances
  best2 = np.argpartition(sq, 1, axis=1)[:, :2]  # [ka, 2] the two nearest in b, unordered
  d2 = np.take_along_axis(sq, best2, axis=1)
  order = np.argsort(d2, axis=1)
  nearest = np.take_along_axis(best2, order[:, :1], axis=1)[:, 0]
  d_first, d_second = np.sqrt(np.take_along_axis(d2, order, axis=1)).T
  mutual = np.argmin(sq, axis=0)[nearest] == np.arange(len(desc_a))
  ok = mutual & (d_first < max_ratio * d_second)
  return np.column_stack([np.flatnonzero(ok), nearest[ok]]).astype(np.int64)


def stretch(intensity: np.ndarray) -> np.ndarray:
  """[H, W] intensity in any linear unit (NaN = not recorded) -> [H, W] float32 in [0, 1]."""
  finite = np.isfinite(intensity)
  if not finite.any():
    return np.zeros(intensity.shape, np.float32)
  lo, hi = np.percentile(intensity[finite], INTENSITY_PERCENTILES)
  out = (np.where(finite, intensity, lo) - lo) / max(hi - lo, np.finfo(np.float32).tiny)
  return np.clip(out, 0.0, 1.0).astype(np.float32)


def lift(scan: scene_lib.WLIScan, c2w: np.ndarray, xy: np.ndarray) -> np.ndarray:
  """The 3-D points (um) of a scan's pixel positions xy [k, 2] -> [k, 3], NaN where the depth is
  a void or straddles a depth edge (bilinear depth from the 2 x 2 pixels around each position)."""
  h, w = scan.shape
  col, row = xy[:, 0] - 0.5, xy[:, 1] - 0.5  # pixel index coordinates (centre of pixel 0 at 0)
  c0 = np.clip(np.floor(col).astype(int), 0, w - 2)
  r0 = np.clip(np.floor(row).astype(int), 0, h - 2)
  corners = np.stack([scan.depth[r0 + dr, c0 + dc] for dr in (0, 1) for dc in (0, 1)], -1)
  span = np.ptp(corners, axis=-1)  # NaN where any corner is a void
  ok = np.isfinite(span) & (span <= DEPTH_STEP_PIXELS * min(scan.pixel_size))
  depth = ndimage.map_coordinates(np.nan_to_num(scan.depth.astype(np.float64)), [row, col],
                                  order=1, mode="nearest")
  sx, sy = scan.pixel_size
  local = np.stack([(col + 0.5 - w / 2) * sx, (row + 0.5 - h / 2) * sy, depth], -1)
  return np.where(ok[:, None], local @ c2w[:3, :3].T + c2w[:3, 3], np.nan)


def anchor_photos(scans: list[scene_lib.WLIScan], scan_c2w: list[np.ndarray],
                  photos: list[scene_lib.OMImage], K: np.ndarray, seed: int = 0
                  ) -> Anchoring | None:
  """Anchors of every photo on the scans' intensity images (module docstring).

  scans, scan_c2w: the WLI scans and their registered camera-to-world (um); photos: the OM
  photos; K: [3, 3] their shared intrinsics; seed: the poses' RANSAC (`sfm.absolute_pose`).
  Returns None when no scan carries an intensity image or fewer than MIN_ANCHORED_PHOTOS photos
  could be anchored.
  """
  with_intensity = [(s, c) for s, c in zip(scans, scan_c2w) if s.intensity is not None]
  if not with_intensity:
    return None
  extractor = _extractor()
  lifted = []  # per scan: (X [k, 3], desc [k, 128]) of its keypoints with a 3-D point
  for scan, c2w in with_intensity:
    xy, desc, _ = sift(extractor, stretch(scan.intensity))
    X = lift(scan, c2w, xy)
    ok = np.all(np.isfinite(X), axis=1)
    if ok.any():
      lifted.append((X[ok], desc[ok]))
  n_lifted = sum(len(X) for X, _ in lifted)
  if n_lifted < MIN_ANCHORS:
    return None
  anchors, c2w_out, matches = {}, {}, {}
  for photo in photos:
    xy, desc, scale = sift(extractor, np.clip(photo.image, 0.0, 1.0) @ LUMINANCE)
    pairs = [(xy[m[:, 0]], X[m[:, 1]], scale[m[:, 0]]) for X, scan_desc in lifted
             for m in [match(desc, scan_desc)]]
    xy_m, X_m, scale_m = (np.concatenate(a) for a in zip(*pairs))
    matches[photo.name] = len(xy_m)
    if len(xy_m) < MIN_ANCHORS:
      continue
    found = sfm.absolute_pose(xy_m, X_m, K, photo.shape[::-1], seed)
    if found is None or found[1].sum() < MIN_ANCHORS:
      continue
    c2w_out[photo.name], inliers = found
    anchors[photo.name] = (xy_m[inliers], X_m[inliers], scale_m[inliers])
  if len(anchors) < MIN_ANCHORED_PHOTOS:
    return None
  return Anchoring(anchors, c2w_out, n_lifted, matches)
