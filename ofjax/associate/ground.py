"""Step 2b: re-pose and adjust the OM cameras on the exact WLI surface after step 2's similarity.

Structure-from-motion of a nearly flat sample through a narrow-field microscope is weakly
determined: camera tilt trades against a bend of the reconstructed surface, so after the best
similarity the SfM points lie near the WLI surface while cameras can still be degrees off (the
circuit scene: 5-19 degrees for the top and 15-degree photos). The WLI measured that surface, so
it is used as the 3-D truth: every SfM point within SNAP_GATE_VOXELS of P_wli moves onto the WLI
surface along the local WLI normal (the height the WLI knows is taken from it, the position along
the surface stays the SfM's), each photo is re-posed from its 2-D keypoints and those 3-D points
(pycolmap's LO-RANSAC absolute pose + refinement, intrinsics fixed), the points are triangulated
again from the new cameras (linear DLT), and this repeats ROUNDS times.

Those rounds are coordinate descent (cameras, then points) and converge slowly: on the circuit
scene the cameras still moved 0.5 degree between rounds 3 and 10. A bundle adjustment then solves
cameras and points jointly (`adjust`): every photo's 6 pose parameters and every point's position,
against the reprojection errors of the SfM keypoints (one sigma = SIGMA_PX_PER_SCALE times the
keypoint's SIFT scale, soft-L1) and each point's distance to the tangent plane of its nearest WLI
point (one sigma = ADJUST_SURFACE_SIGMA_VOXELS). The WLI surface pins the points' heights, and
with them each camera's own pose. Along a nearly flat surface it pins the block's common turn
about the vertical and its scale only weakly, and the adjustment is free to drift there. So its
result is mapped back by the similarity that takes its camera centres onto the rounds' centres:
the common part stays what step 2 fitted over all of P_om, and each camera keeps what the
adjustment found for it alone. On circuit this halves the largest camera error (1.23 -> 0.62
degree; centre 3.7% -> 2.0% of the scene size; what is left after the best common similarity
3.8% -> 0.37%); on the other synthetic scenes, whose rounds had converged, nothing changes.

When the photos are anchored on the WLI intensity images (ofjax.associate.anchor: keypoints of the
photo matched to exact WLI points), each anchored photo starts the adjustment from its anchors'
pose and their reprojection errors join the residuals. The anchors pin the block's turn and scale
to the WLI directly, so with at least MIN_ANCHORED_PHOTOS of them nothing is mapped back (circuit:
0.047 degree, centre 0.17%, scale 0.003%; benchmarks/README.md).

Two things keep the keypoints' known errors out of the cameras. Each keypoint, SfM track or anchor,
is weighted by its SIFT scale: a wide blob's matched position is that much less certain (the wing
scene's anchors through the true cameras: 0.26 px median error at scale ~1, 0.98 px above 3). And
only the tracks of points on level WLI faces (`on_level_faces`) take part: on sloped faces the OM
shading moves the keypoints with the view, and the SfM points sit 0.5-1 um inside the surface. On
wing the two take the largest camera error from 0.21 to 0.14 degree (centre 0.79% -> 0.53%).
An anchor's sigma is ANCHOR_SIGMA_FACTOR times a track keypoint's of the same scale: it pairs two
modalities, whose shading differs (wing: centre 0.55% -> 0.47%).

Conventions: c2w are [4, 4] camera-to-world in um (OpenCV axes); points [N, 3] in um; `tracks`
map a point index to its observations [(photo name, xy [2] pixels)].
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ofjax.associate.anchor import MIN_ANCHORED_PHOTOS, Anchoring
from ofjax.associate.evaluate import fit_transform, rotation_deg
from ofjax.associate.sfm import Observations, absolute_pose

ROUNDS = 3  # snap -> re-pose -> re-triangulate rounds: they take the cameras most of the way
# (degrees on circuit); the joint adjustment after them finishes what they converge to slowly
SNAP_GATE_VOXELS = 3.0  # SfM points farther than this from P_wli (voids, beyond the scans) are
# not snapped and take no part in re-posing
MIN_POINTS = 20  # a photo with fewer snapped points keeps its step-2 pose
LEVEL_NZ = 0.9  # SfM tracks take part only where the WLI surface faces up at least this much
# (|n_z|; the level class of benchmarks/README.md's SfM point offsets, 25.8 deg from the vertical)
ADJUST_MAX_ERROR_PX = 3.0  # keypoints the rounds' cameras miss by more are left out of the
# adjustment: mismatched tracks (1.1% of circuit's keypoints; 124 px at the 99th percentile even
# through the true cameras), which would otherwise pull the cameras
ADJUST_SURFACE_SIGMA_VOXELS = 0.25  # one sigma of a point's distance to the WLI tangent plane,
# in P_wli voxels
SIGMA_PX_PER_SCALE = 1.0  # one sigma of a keypoint's reprojection error (SfM track or anchor), in
# pixels per pixel of its SIFT scale: a blob's matched position is as uncertain as the blob is
# wide (the wing scene's anchors through the true cameras: median error 0.26 px at scale ~1,
# 0.98 px at scale > 3; seed 0.14 -> 0.30 px)
ANCHOR_SIGMA_FACTOR = 2.0  # an anchor's sigma over an SfM track keypoint's of the same SIFT
# scale: an anchor pairs keypoints of two modalities (the scan's intensity, the photo's colour),
# whose shading differs, a track those of photos alike. Largest OM centre error over the five
# scenes at factor 1 / 2 / 4: 0.551 / 0.473 / 0.444% (wing), circuit 0.167 / 0.162 / 0.266%
# (benchmarks/README.md, "Anchors weighted below the tracks")
ADJUST_LOSS_SIGMAS = 1.0  # soft-L1 scale of the residuals, in their sigmas
ADJUST_ROUNDS = 2  # nearest-WLI-point (tangent plane) updates, one least-squares solve each
ADJUST_MAX_NFEV = 30  # residual evaluations per solve (it converges in ~15-30)


@dataclasses.dataclass
class Grounding:
  c2w: dict[str, np.ndarray]  # photo name -> [4, 4] camera-to-world in um
  reposed: list[str]  # photos re-posed on the WLI surface (the others keep the step-2 pose)
  snapped: int  # SfM points on the WLI surface in the last round
  change_deg: dict[str, float]  # photo name -> rotation between its step-2 and final pose
  adjustment: dict  # the bundle adjustment's "keypoints" (used), "kept" (their share),
  # "photos" (adjusted; the others keep their pose), "reprojection_px" (median before, after),
  # "change_deg" (largest camera turn it made)


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


def tracks_of(observations: Observations) -> dict[int, list]:
  """Point index -> [(photo name, xy [2])] of every photo that sees it."""
  tracks: dict[int, list] = {}
  for name, (xy, idx, _) in observations.items():
    for x, i in zip(xy, idx):
      tracks.setdefault(int(i), []).append((name, x))
  return tracks


def on_level_faces(observations: Observations, points: np.ndarray, wli_normals: np.ndarray,
                   tree: cKDTree) -> Observations:
  """The observations of the points [N, 3] (um, NaN rows allowed) whose nearest WLI point faces
  up (|n_z| >= LEVEL_NZ), or all of them when that would leave a photo with fewer than MIN_POINTS.

  SfM points sit inside sloped faces (the OM shading moves their keypoints with the view), while
  on level faces they lie on the WLI surface; their tracks would pull the cameras towards that
  bias (benchmarks/README.md, "Association")."""
  level = np.zeros(len(points), bool)
  ok = np.all(np.isfinite(points), axis=1)
  level[ok] = np.abs(wli_normals[tree.query(points[ok])[1], 2]) >= LEVEL_NZ
  kept = {name: (xy[level[idx]], idx[level[idx]], scale[level[idx]])
          for name, (xy, idx, scale) in observations.items()}
  if min((len(idx) for _, idx, _ in kept.values()), default=0) < MIN_POINTS:
    return observations
  return kept


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


def _project(R: np.ndarray, t: np.ndarray, X: np.ndarray, K: np.ndarray) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
  """Pixels [k, 2] and depths [k] of points X [k, 3] through w2c (R [k, 3, 3], t [k, 3])."""
  Y = np.einsum("kij,kj->ki", R, X) + t
  return Y[:, :2] / Y[:, 2:] * np.diag(K)[:2] + K[:2, 2], Y[:, 2]


def adjust(c2w: dict[str, np.ndarray], points: np.ndarray,
           observations: Observations, K: np.ndarray,
           wli_points: np.ndarray, wli_normals: np.ndarray, wli_voxel_um: float,
           tree: cKDTree,
           anchors: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
           ) -> tuple[dict[str, np.ndarray], dict]:
  """Bundle adjustment of cameras `c2w` (um) and points [N, 3] (NaN rows allowed) with the points
  held near the WLI surface -> (adjusted c2w, the Grounding's `adjustment` statistics).

  observations: photo name -> (xy [k, 2], point index [k], SIFT scale [k] pixels), as
  ofjax.associate.sfm gives them.
  anchors: photo name -> (xy [k, 2], X [k, 3] um, SIFT scale [k] pixels) fixed 3-D points of the
  WLI that the photo sees at xy (ofjax.associate.anchor); their reprojection errors join the
  keypoints', weighted alike by their scales. With at
  least MIN_ANCHORED_PHOTOS anchored photos in the block the anchors fix its common turn and
  scale; otherwise the result is mapped back to the common similarity of `c2w` (module docstring).
  """
  anchors = anchors or {}
  unchanged = dict(c2w), {"keypoints": 0, "kept": 0.0, "photos": 0, "reprojection_px": [],
                          "change_deg": 0.0, "anchors": 0, "anchored_photos": 0,
                          "mapped_back": True}
  names = sorted(n for n in c2w if n in observations and len(observations[n][1]))
  if len(names) < 3:  # no block to adjust (and no similarity to map it back by)
    return unchanged
  w2c = np.array([np.linalg.inv(c2w[n]) for n in names])
  cam = np.concatenate([np.full(len(observations[n][1]), k) for k, n in enumerate(names)])
  xy = np.concatenate([observations[n][0] for n in names])
  pt = np.concatenate([observations[n][1] for n in names])
  o_sigma = SIGMA_PX_PER_SCALE * np.concatenate([observations[n][2] for n in names])
  known = np.all(np.isfinite(points[pt]), axis=1)
  uv, depth = _project(w2c[cam, :3, :3], w2c[cam, :3, 3], np.nan_to_num(points[pt]), K)
  error = np.linalg.norm(uv - xy, axis=1)
  use = known & (depth > 0) & (error < ADJUST_MAX_ERROR_PX)
  # A photo left with too few keypoints would be free to wander: it keeps its pose, out of the
  # adjustment, and a point needs two views.
  for _ in range(2):
    use &= np.bincount(cam[use], minlength=len(names))[cam] >= MIN_POINTS
    use &= np.bincount(pt[use], minlength=len(points))[pt] >= 2
  adjusted = np.unique(cam[use])
  if len(adjusted) < 3:
    return unchanged
  before = float(np.median(error[use]))
  names = [names[k] for k in adjusted]
  cam = np.searchsorted(adjusted, cam[use])
  pt, xy, o_sigma = pt[use], xy[use], o_sigma[use]
  kept_points, pt = np.unique(pt, return_inverse=True)
  R, t, X = w2c[adjusted, :3, :3], w2c[adjusted, :3, 3], points[kept_points]
  anchored = [k for k, n in enumerate(names) if n in anchors]
  a_cam = np.concatenate([np.full(len(anchors[names[k]][0]), k) for k in anchored] + [
      np.zeros(0, int)])
  a_xy = np.concatenate([anchors[names[k]][0] for k in anchored] + [np.zeros((0, 2))])
  a_X = np.concatenate([anchors[names[k]][1] for k in anchored] + [np.zeros((0, 3))])
  a_sigma = ANCHOR_SIGMA_FACTOR * SIGMA_PX_PER_SCALE * np.concatenate(
      [anchors[names[k]][2] for k in anchored] + [np.zeros(0)])
  n_cam, n_pt, n_obs, n_anc = len(names), len(X), len(cam), len(a_cam)
  sigma = ADJUST_SURFACE_SIGMA_VOXELS * wli_voxel_um
  gate = SNAP_GATE_VOXELS * wli_voxel_um
  # Jacobian sparsity: a keypoint's two rows see its camera's 6 parameters and its point's 3 (the
  # same every round); a point's surface row sees the point's 3 (the points near P_wli, per round).
  seen = np.concatenate([np.stack([3 * cam + a, 3 * n_cam + 3 * cam + a, 6 * n_cam + 3 * pt + a],
                                  1) for a in range(3)], 1)  # [n_obs, 9] columns per keypoint
  obs_rows = np.repeat(np.arange(2 * n_obs), 9)
  obs_cols = np.repeat(seen, 2, axis=0).ravel()  # both rows of a keypoint
  # An anchor's two rows see only its camera's 6 parameters (its 3-D point is the WLI's, fixed).
  anc_rows = 2 * n_obs + np.repeat(np.arange(2 * n_anc), 6)
  anc_cols = np.repeat(np.concatenate([np.stack([3 * a_cam + a, 3 * n_cam + 3 * a_cam + a], 1)
                                       for a in range(3)], 1), 2, axis=0).ravel()
  for _ in range(ADJUST_ROUNDS):
    d, j = tree.query(X, distance_upper_bound=gate)
    near = np.flatnonzero(np.isfinite(d))  # points with a WLI tangent plane to stay on
    q, nrm = wli_points[j[near]], wli_normals[j[near]]
    R0, t0, X0 = R, t, X

    def unpack(v, R0=R0, t0=t0, X0=X0):
      turn = Rotation.from_rotvec(v[:3 * n_cam].reshape(n_cam, 3)).as_matrix()
      return (turn @ R0, t0 + v[3 * n_cam:6 * n_cam].reshape(n_cam, 3),
              X0 + v[6 * n_cam:].reshape(n_pt, 3))

    def residuals(v, q=q, nrm=nrm, near=near, unpack=unpack):
      Rv, tv, Xv = unpack(v)
      reprojection = (_project(Rv[cam], tv[cam], Xv[pt], K)[0] - xy) / o_sigma[:, None]
      on_anchors = (_project(Rv[a_cam], tv[a_cam], a_X, K)[0] - a_xy) / a_sigma[:, None]
      off_surface = np.einsum("ij,ij->i", nrm, Xv[near] - q) / sigma  # [n_near] sigmas
      return np.concatenate([reprojection.ravel(), on_anchors.ravel(), off_surface])

    surf_rows = 2 * (n_obs + n_anc) + np.repeat(np.arange(len(near)), 3)
    surf_cols = (6 * n_cam + 3 * near[:, None] + np.arange(3)).ravel()
    rows = np.concatenate([obs_rows, anc_rows, surf_rows])
    cols = np.concatenate([obs_cols, anc_cols, surf_cols])
    sparsity = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)),
                          shape=(2 * (n_obs + n_anc) + len(near), 6 * n_cam + 3 * n_pt)).tocsr()
    sol = least_squares(residuals, np.zeros(6 * n_cam + 3 * n_pt), jac_sparsity=sparsity,
                        loss="soft_l1", f_scale=ADJUST_LOSS_SIGMAS, x_scale="jac", method="trf",
                        tr_solver="lsmr", max_nfev=ADJUST_MAX_NFEV)
    R, t, X = unpack(sol.x)
  after = float(np.median(np.linalg.norm(_project(R[cam], t[cam], X[pt], K)[0] - xy, axis=1)))
  start = np.array([c2w[n][:3, 3] for n in names])
  centres = -np.einsum("kji,kj->ki", R, t)  # -R^T t
  map_back = len(anchored) < MIN_ANCHORED_PHOTOS
  # Without anchors, the common part goes back to the start (module docstring).
  back = fit_transform(centres, start, with_scaling=True) if map_back else np.eye(4)
  scale = np.cbrt(np.linalg.det(back[:3, :3]))
  out = dict(c2w)
  for k, name in enumerate(names):
    m = np.eye(4)
    m[:3, :3] = back[:3, :3] / scale @ R[k].T
    m[:3, 3] = back[:3, :3] @ centres[k] + back[:3, 3]
    out[name] = m
  stats = {"keypoints": int(n_obs), "kept": float(use.mean()), "photos": len(names),
           "reprojection_px": [before, after],
           "change_deg": max(rotation_deg(out[n][:3, :3], c2w[n][:3, :3]) for n in names),
           "anchors": int(n_anc), "anchored_photos": len(anchored), "mapped_back": map_back}
  if n_anc:
    stats["anchor_reprojection_px"] = float(np.median(np.linalg.norm(
        _project(R[a_cam], t[a_cam], a_X, K)[0] - a_xy, axis=1)))
  return out, stats


def ground_cameras(c2w: dict[str, np.ndarray], points: np.ndarray,
                   observations: Observations, K: np.ndarray,
                   image_size: tuple[int, int], wli_points: np.ndarray, wli_normals: np.ndarray,
                   wli_voxel_um: float, anchoring: Anchoring | None = None, seed: int = 0
                   ) -> Grounding:
  """Re-poses the photos of `c2w` (step-2 poses, um) on P_wli (module docstring).

  points: [N, 3] P_om in um (after the similarity); observations: the photos' keypoints and their
  points (`sfm.Observations`); K: [3, 3]; image_size: (width, height) in pixels.
  anchoring: the photos' anchors on the WLI intensity images (ofjax.associate.anchor), or None;
  after the rounds an anchored photo starts from its anchors' pose, and the adjustment holds it on
  its anchors. seed: the re-posing's RANSAC (`sfm.absolute_pose`).
  """
  tree = cKDTree(wli_points)
  observations = on_level_faces(observations, points, wli_normals, tree)
  tracks = tracks_of(observations)
  gate = SNAP_GATE_VOXELS * wli_voxel_um
  poses, reposed, snapped = dict(c2w), set(), 0
  for _ in range(ROUNDS):
    on_wli = snap(points, wli_points, wli_normals, tree, gate)
    ok = np.all(np.isfinite(on_wli), axis=1)
    snapped = int(ok.sum())
    for name, (xy, idx, _) in observations.items():
      use = ok[idx]
      if name not in poses or use.sum() < MIN_POINTS:
        continue
      found = absolute_pose(xy[use], on_wli[idx[use]], K, image_size, seed)
      if found is None or found[1].sum() < MIN_POINTS:
        continue
      poses[name] = found[0]
      reposed.add(name)
    points = triangulate(tracks, poses, K, len(points))
  if anchoring is not None:
    poses.update({name: m for name, m in anchoring.c2w.items() if name in poses})
    points = triangulate(tracks, poses, K, len(points))
  poses, adjustment = adjust(poses, points, observations, K, wli_points, wli_normals,
                             wli_voxel_um, tree, None if anchoring is None else anchoring.anchors)
  change = {name: rotation_deg(poses[name][:3, :3], c2w[name][:3, :3]) for name in poses}
  return Grounding(poses, sorted(reposed), snapped, change, adjustment)
