"""Step 1, OM: structure-from-motion of the OM photos with pycolmap -> camera poses and P_om.

Conventions: poses are camera-to-world [4, 4] in the SfM frame (OpenCV axes, arbitrary scale and
gauge; step 2 maps them to um). COLMAP puts pixel centres at (u + 0.5, v + 0.5), as ofjax.scene
does, so COLMAP's K is ofjax's K. All photos share one PINHOLE camera (one microscope, one zoom);
when the Scene carries intrinsics for every photo they are taken as given and held fixed,
otherwise COLMAP starts from its default focal prior and refines the focal length.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from ofjax import scene as scene_lib
from ofjax.errors import UserError

log = logging.getLogger(__name__)

MAX_IMAGE_SIZE = 1600  # SIFT on at most this many pixels along the longest side (speed)
MAX_NUM_FEATURES = 4096  # SIFT keypoints per photo; enough for hundreds of matches per pair
MIN_TRACK_LENGTH = 3  # P_om keeps points seen in at least this many photos ...
MAX_POINT_ERROR_PX = 1.0  # ... with a mean reprojection error of at most this (pixels)
SFM_THREADS = 1  # deterministic SfM (see _reconstruct)
QUIET_LOG_LEVEL = 1  # glog level while pycolmap runs: warnings and errors only
SAME_K_RTOL = 1e-6  # photos whose intrinsics differ by more than this do not share one camera
POSE_MAX_ERROR_PX = 2.0  # inlier threshold of a photo's absolute pose from 2-D/3-D matches (the
# anchors' and the re-posing's); the SfM's own points keep a mean error <= MAX_POINT_ERROR_PX


Observations = dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]  # photo name -> (xy [k, 2]
# pixel coordinates of its keypoints, [k] index of each one's point in P_om, [k] each keypoint's
# SIFT scale in pixels, `keypoint_scale`)


@dataclasses.dataclass
class SfMResult:
  c2w: dict[str, np.ndarray]  # photo name -> [4, 4] camera-to-world, SfM frame
  K: np.ndarray  # [3, 3] shared intrinsics (pixels)
  points: np.ndarray  # [N, 3] P_om: filtered sparse points, SfM frame
  colors: np.ndarray  # [N, 3] uint8 RGB of P_om
  observations: Observations  # of the keypoints that belong to P_om
  missing: list[str]  # photos the reconstruction did not register
  mean_reprojection_error_px: float  # over all points of the reconstruction
  num_points_total: int  # sparse points before filtering
  seconds: float


def keypoint_scale(shape: np.ndarray) -> np.ndarray:
  """SIFT scale in pixels of keypoints with affine shapes [k, 4] (a11, a12, a21, a22, COLMAP's
  keypoint layout after x, y) -> [k]: the mean length of the shape's two columns, as COLMAP's
  FeatureKeypoint::ComputeScale."""
  shape = np.asarray(shape, np.float64).reshape(-1, 4)
  return 0.5 * (np.hypot(shape[:, 0], shape[:, 2]) + np.hypot(shape[:, 1], shape[:, 3]))


def _shared_K(images: list[scene_lib.OMImage], scene_dir: str) -> np.ndarray | None:
  ks = [o.K for o in images]
  if any(k is None for k in ks):
    return None
  if not all(np.allclose(k, ks[0], rtol=SAME_K_RTOL) for k in ks):
    raise UserError(f"{scene_dir}/scene.json: the OM photos have different intrinsics; ofjax "
                    "assumes one microscope setting - split the photos into separate scenes")
  return ks[0]


def run_sfm(images: list[scene_lib.OMImage], workdir: str | Path, scene_dir: str = "SCENE_DIR",
            seed: int = 0, max_image_size: int = MAX_IMAGE_SIZE,
            max_num_features: int = MAX_NUM_FEATURES) -> SfMResult:
  """SIFT features, exhaustive matching and incremental mapping; the largest model wins.

  `workdir` receives images/, database.db and sparse/ (it is emptied first).
  """
  t0 = time.perf_counter()
  if len(images) < 3:
    raise UserError(f"{scene_dir}/scene.json: {len(images)} OM photo(s); structure-from-motion "
                    "needs at least 3 overlapping photos")
  shapes = {o.shape for o in images}
  if len(shapes) != 1:
    raise UserError(f"{scene_dir}/om: photos have different sizes {sorted(shapes)}; one camera "
                    "setting is assumed - resize or split them")
  K = _shared_K(images, scene_dir)
  workdir = Path(workdir)
  for sub in ("images", "sparse"):
    shutil.rmtree(workdir / sub, ignore_errors=True)
  (workdir / "images").mkdir(parents=True)
  (workdir / "sparse").mkdir()
  db = workdir / "database.db"
  db.unlink(missing_ok=True)
  for o in images:
    Image.fromarray(np.round(np.clip(o.image, 0, 1) * 255).astype(np.uint8), "RGB").save(
        workdir / "images" / f"{o.name}.png")
  reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE")
  if K is not None:
    reader.camera_params = ",".join(str(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
  extraction = pycolmap.FeatureExtractionOptions()
  extraction.max_image_size = max_image_size
  extraction.sift.max_num_features = max_num_features
  quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, QUIET_LOG_LEVEL
  try:
    recs = _reconstruct(db, workdir, K, reader, extraction, seed)
  finally:
    pycolmap.logging.minloglevel = quiet
  if not recs:
    raise UserError(f"{scene_dir}/om: structure-from-motion found no model (too few matching "
                    "features); take photos with more overlap and texture")
  rec = max(recs.values(), key=lambda r: r.num_reg_images())
  by_name = {im.name: im for im in rec.images.values() if im.has_pose}
  c2w, cams = {}, set()
  for o in images:
    im = by_name.get(f"{o.name}.png")
    if im is None:
      continue
    w2c = np.eye(4)
    w2c[:3] = im.cam_from_world().matrix()
    c2w[o.name] = np.linalg.inv(w2c)
    cams.add(im.camera_id)
  missing = [o.name for o in images if o.name not in c2w]
  K_est = np.asarray(rec.cameras[next(iter(cams))].calibration_matrix(), np.float64)
  pts, cols, seen = [], [], {}
  for p in rec.points3D.values():
    if p.track.length() >= MIN_TRACK_LENGTH and p.error <= MAX_POINT_ERROR_PX:
      for el in p.track.elements:
        seen.setdefault(el.image_id, []).append((el.point2D_idx, len(pts)))
      pts.append(p.xyz)
      cols.append(p.color)
  observations = {}
  database = pycolmap.Database.open(db)
  try:
    for o in images:
      im = by_name.get(f"{o.name}.png")
      if im is not None:
        obs = seen.get(im.image_id, [])
        kp = np.array([j for j, _ in obs], np.int64)  # the keypoints' indices in the image
        # The database's keypoint rows are the image's points2D, in order (x, y, affine shape).
        scale = keypoint_scale(np.asarray(database.read_keypoints(im.image_id))[kp, 2:6])
        xy = np.array([im.points2D[j].xy for j in kp], np.float64).reshape(-1, 2)
        observations[o.name] = (xy, np.array([i for _, i in obs], np.int64), scale)
  finally:
    database.close()
  log.info("SfM: %d/%d photos, %d points (%d kept), %.1f s", len(c2w), len(images),
           rec.num_points3D(), len(pts), time.perf_counter() - t0)
  return SfMResult(c2w, K_est, np.asarray(pts, np.float64).reshape(-1, 3),
                   np.asarray(cols, np.uint8).reshape(-1, 3), observations, missing,
                   float(rec.compute_mean_reprojection_error()), int(rec.num_points3D()),
                   time.perf_counter() - t0)


def absolute_pose(xy: np.ndarray, X: np.ndarray, K: np.ndarray, image_size: tuple[int, int],
                  seed: int, max_error_px: float = POSE_MAX_ERROR_PX
                  ) -> tuple[np.ndarray, np.ndarray] | None:
  """A photo's pose from 2-D/3-D matches: pycolmap's LO-RANSAC absolute pose and its refinement
  with the intrinsics held -> (c2w [4, 4], inlier mask [k] bool), or None when RANSAC finds none.

  xy: [k, 2] pixels; X: [k, 3] points; K: [3, 3]; image_size: (width, height); seed: RANSAC's
  (COLMAP's default, -1, draws a new one every call, and the pose then moves run to run by what
  the inliers at the threshold's edge change); max_error_px: the inlier threshold.
  """
  camera = pycolmap.Camera(model="PINHOLE", width=int(image_size[0]), height=int(image_size[1]),
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
  estimation = pycolmap.AbsolutePoseEstimationOptions()
  estimation.ransac.max_error = max_error_px
  estimation.ransac.random_seed = seed
  refinement = pycolmap.AbsolutePoseRefinementOptions()
  refinement.refine_focal_length = False
  refinement.refine_extra_params = False
  res = pycolmap.estimate_and_refine_absolute_pose(xy, X, camera, estimation, refinement)
  if res is None:
    return None
  w2c = np.eye(4)
  w2c[:3] = res["cam_from_world"].matrix()
  return np.linalg.inv(w2c), np.asarray(res["inlier_mask"], bool)


def _reconstruct(db: Path, workdir: Path, K: np.ndarray | None,
                 reader: pycolmap.ImageReaderOptions,
                 extraction: pycolmap.FeatureExtractionOptions,
                 seed: int) -> dict[int, pycolmap.Reconstruction]:
  """pycolmap's three stages: features, exhaustive matches, incremental mapping."""
  # One thread and fixed RANSAC seeds in every stage: the same photos give the same model, so an
  # association (and the tests' pose errors) repeat exactly run to run.
  extraction.num_threads = SFM_THREADS
  pycolmap.extract_features(db, workdir / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                            reader_options=reader, extraction_options=extraction,
                            device=pycolmap.Device.cpu)
  matching = pycolmap.FeatureMatchingOptions()
  matching.num_threads = SFM_THREADS
  verification = pycolmap.TwoViewGeometryOptions()
  verification.ransac.random_seed = seed
  pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                            device=pycolmap.Device.cpu)
  opts = pycolmap.IncrementalPipelineOptions()
  opts.num_threads = SFM_THREADS
  opts.random_seed = seed
  opts.mapper.random_seed = seed
  opts.triangulation.random_seed = seed
  if K is not None:  # known intrinsics: keep them, the poses then carry all the freedom
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.mapper.abs_pose_refine_focal_length = False
  return pycolmap.incremental_mapping(db, workdir / "images", workdir / "sparse", options=opts)
