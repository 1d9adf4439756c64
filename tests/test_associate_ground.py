"""ofjax.associate.ground: re-posing the OM photos on the WLI surface.

A known scene is built here: a bumpy height field (the WLI surface, sampled every um with its
analytic normals), 13 pinhole cameras around it, and points on it seen by every camera where they
fall in the frame. The step-2 input is then spoiled the way a weak SfM spoils it: cameras turned
and shifted, each on its own or all together, points bent off the surface, keypoints mismatched.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ofjax.associate import evaluate, ground, sfm

K = np.array([[700.0, 0, 160], [0, 700.0, 120], [0, 0, 1]])
SIZE = (320, 240)  # width, height in pixels
HALF = 150.0  # um: the surface spans [-HALF, HALF]^2


def height(x, y):
  return 12 * np.exp(-((x - 40) ** 2 + (y + 30) ** 2) / 2500) + 6 * np.sin(x / 23) * np.cos(y / 31)


def normals(x, y, eps=1e-4):
  gx = (height(x + eps, y) - height(x - eps, y)) / (2 * eps)
  gy = (height(x, y + eps) - height(x, y - eps)) / (2 * eps)
  n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
  return n / np.linalg.norm(n, axis=-1, keepdims=True)


def look_at(tilt_deg, azimuth_deg, distance=650.0):
  """c2w [4, 4] of an OpenCV camera on a sphere around the origin, looking at it."""
  t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
  c = distance * np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
  z = -c / np.linalg.norm(c)
  x = np.cross(z, [np.sin(a + 0.3), -np.cos(a + 0.3), 0.0] if tilt_deg else [0, -1.0, 0])
  x /= np.linalg.norm(x)
  m = np.eye(4)
  m[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
  m[:3, 3] = c
  return m


def scene(rng, noise_px=0.1):
  """-> WLI points [n, 3] and normals, c2w per camera, surface points [m, 3], keypoints per
  camera (xy [k, 2] with noise_px per axis, point indices [k], SIFT scales [k])."""
  xs = np.arange(-HALF, HALF + 1e-9, 1.0)
  gx, gy = np.meshgrid(xs, xs)
  wli = np.stack([gx, gy, height(gx, gy)], -1).reshape(-1, 3)
  wli_n = normals(gx, gy).reshape(-1, 3)
  cams = {"top": look_at(0, 0)}
  cams.update({f"r{tilt}-{az}": look_at(tilt, az) for tilt in (20, 35) for az in range(0, 360, 60)})
  xy = rng.uniform(-0.8 * HALF, 0.8 * HALF, (500, 2))
  pts = np.column_stack([xy, height(xy[:, 0], xy[:, 1])])
  obs = {}
  for name, c2w in cams.items():
    w2c = np.linalg.inv(c2w)
    cam_pts = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = cam_pts[:, :2] / cam_pts[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    inside = np.flatnonzero((uv[:, 0] > 0) & (uv[:, 0] < SIZE[0]) & (uv[:, 1] > 0)
                            & (uv[:, 1] < SIZE[1]))
    obs[name] = (uv[inside] + rng.normal(0, noise_px, (len(inside), 2)), inside,
                 np.ones(len(inside)))  # SIFT scale 1 px: one sigma is one pixel
  return wli, wli_n, cams, pts, obs


def perturbed(rng, cams, deg, um):
  out = {}
  for name, m in cams.items():
    m = m.copy()
    turn = Rotation.from_rotvec(rng.normal(size=3) * np.radians(deg) / np.sqrt(3))
    m[:3, :3] = turn.as_matrix() @ m[:3, :3]
    m[:3, 3] += rng.normal(size=3) * um / np.sqrt(3)
    out[name] = m
  return out


def resected(obs, points):
  """c2w of every photo re-posed from its keypoints and `points` (`sfm.absolute_pose`, seeded)."""
  out = {}
  for name, (xy, idx, _) in obs.items():
    ok = np.all(np.isfinite(points[idx]), axis=1)
    out[name] = sfm.absolute_pose(xy[ok], points[idx[ok]], K, SIZE, seed=0)[0]
  return out


def own_errors(est, true):
  """Largest rotation (deg) and centre (um) error per camera once the best similarity of the
  estimated centres onto the true ones is taken out: what each camera has on its own."""
  names = sorted(true)
  sim = evaluate.fit_transform(np.array([est[n][:3, 3] for n in names]),
                               np.array([true[n][:3, 3] for n in names]), True)
  rot = sim[:3, :3] / np.cbrt(np.linalg.det(sim[:3, :3]))
  deg = max(evaluate.rotation_deg(rot @ est[n][:3, :3], true[n][:3, :3]) for n in names)
  um = max(np.linalg.norm(sim[:3, :3] @ est[n][:3, 3] + sim[:3, 3] - true[n][:3, 3]) for n in names)
  return deg, um


def test_adjust_takes_out_each_cameras_own_error_and_keeps_the_common_part():
  rng = np.random.default_rng(3)
  wli, wli_n, cams, pts, obs = scene(rng)
  for name in ("top", "r20-0"):  # mismatched keypoints: 3% of two photos' are 40 px off
    xy, idx, _ = obs[name]
    bad = rng.choice(len(idx), max(1, len(idx) * 3 // 100), replace=False)
    xy[bad] += 40.0
  tracks = ground.tracks_of(obs)
  # The start is a state like ground_cameras' rounds leave: cameras each off on their own, points
  # triangulated from them, every camera re-posed from those points (as the rounds do), and the
  # points triangulated again, so that cameras and points agree to a fraction of a pixel.
  start = perturbed(rng, cams, deg=0.6, um=4.0)
  start = resected(obs, ground.triangulate(tracks, start, K, len(pts)))
  start_points = ground.triangulate(tracks, start, K, len(pts))
  start_points[::50] = np.nan  # points SfM did not keep
  deg0, um0 = own_errors(start, cams)
  assert deg0 > 0.5 and um0 > 5.0  # as far off as the synthetic circuit scene's photos
  out, stats = ground.adjust(start, start_points, obs, K, wli, wli_n, 1.0, cKDTree(wli))
  deg, um = own_errors(out, cams)
  assert deg < 0.05 and um < 0.5, (deg, um, deg0, um0, stats)
  # Keypoint noise is 0.1 px per axis: a median error of 0.118 px through the true cameras.
  assert stats["reprojection_px"][1] < min(0.13, stats["reprojection_px"][0])
  # Left out: the mismatched keypoints (0.5%) and those of points SfM did not keep (2%).
  assert stats["photos"] == 13 and 0.9 < stats["kept"] < 0.99
  # The common similarity is the start's: the adjusted centres map onto the start's by identity.
  names = sorted(start)
  back = evaluate.fit_transform(np.array([out[n][:3, 3] for n in names]),
                                np.array([start[n][:3, 3] for n in names]), True)
  np.testing.assert_allclose(back, np.eye(4), atol=1e-6)
  for m in out.values():  # proper rotations
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(m[:3, :3]), 1.0)


def test_adjust_leaves_fewer_than_three_photos_as_they_are():
  rng = np.random.default_rng(4)
  wli, wli_n, cams, pts, obs = scene(rng)
  two = {n: cams[n] for n in ("top", "r20-0")}
  out, stats = ground.adjust(two, pts, obs, K, wli, wli_n, 1.0, cKDTree(wli))
  assert stats["photos"] == 0 and out.keys() == two.keys()
  for n in two:
    np.testing.assert_array_equal(out[n], two[n])


def anchors_of(rng, cams, n=80, noise_px=0.2):
  """Per camera: n exact surface points (the WLI's, fixed) it sees, at noisy pixels."""
  out = {}
  for name, c2w in cams.items():
    w2c = np.linalg.inv(c2w)
    xy = rng.uniform(-0.7 * HALF, 0.7 * HALF, (4 * n, 2))
    X = np.column_stack([xy, height(xy[:, 0], xy[:, 1])])
    cam_pts = X @ w2c[:3, :3].T + w2c[:3, 3]
    uv = cam_pts[:, :2] / cam_pts[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    inside = np.flatnonzero((uv[:, 0] > 0) & (uv[:, 0] < SIZE[0]) & (uv[:, 1] > 0)
                            & (uv[:, 1] < SIZE[1]))[:n]
    out[name] = (uv[inside] + rng.normal(0, noise_px, (len(inside), 2)), X[inside],
                 np.ones(len(inside)))
  return out


def common_error_start(rng):
  """The scene with a start whose cameras share a similarity error (0.6 deg about the vertical,
  0.8% scale), as step 2 leaves on a flat sample, each camera also off on its own; cameras and
  points brought to agree as in the test above -> (scene, start c2w, start points)."""
  wli, wli_n, cams, pts, obs = scene(rng)
  tracks = ground.tracks_of(obs)
  common = np.eye(4)
  common[:3, :3] = 1.008 * Rotation.from_euler("z", 0.6, degrees=True).as_matrix()
  common[:3, 3] = (2.0, -1.5, 0.5)
  start = perturbed(rng, {n: common @ m for n, m in cams.items()}, deg=0.3, um=2.0)
  for m in start.values():  # back to proper camera-to-world rotations
    m[:3, :3] /= 1.008
  start = resected(obs, ground.triangulate(tracks, start, K, len(pts)))
  start_points = ground.triangulate(tracks, start, K, len(pts))
  return (wli, wli_n, cams, pts, obs), start, start_points


def worst(out, cams):
  """Largest rotation (deg) and centre (um) error of cameras `out` against `cams`."""
  deg = max(evaluate.rotation_deg(out[n][:3, :3], cams[n][:3, :3]) for n in cams)
  um = max(np.linalg.norm(out[n][:3, 3] - cams[n][:3, 3]) for n in cams)
  return deg, um


def test_adjust_with_anchors_also_takes_out_the_blocks_common_turn_and_scale():
  """Without anchors the adjustment keeps the start's common error (by design), with the photos
  anchored on exact WLI points it removes it."""
  rng = np.random.default_rng(5)
  (wli, wli_n, cams, pts, obs), start, start_points = common_error_start(rng)
  kept, kept_stats = ground.adjust(start, start_points, obs, K, wli, wli_n, 1.0, cKDTree(wli))
  assert kept_stats["mapped_back"] and kept_stats["anchors"] == 0
  assert worst(kept, cams)[0] > 0.5  # the common turn stays
  anchors = anchors_of(rng, cams)
  out, stats = ground.adjust(start, start_points, obs, K, wli, wli_n, 1.0, cKDTree(wli), anchors)
  deg, um = worst(out, cams)
  assert not stats["mapped_back"] and stats["anchored_photos"] == 13
  assert stats["anchors"] == sum(len(a[0]) for a in anchors.values())
  # From 0.63 deg and 9.2 um to within the targets (0.2 deg; 0.5% of the 300 um surface
  # is 1.5 um). What is left (0.045 deg, 0.53 um) is a turn about the surface that a narrow field
  # hardly sees (0.045 deg at 650 um is 0.51 um): 300 anchors per photo leave the same.
  assert deg < 0.1 and um < 1.0, (deg, um, worst(start, cams))
  # Anchor noise is 0.2 px per axis: a median error of ~0.24 px through the true cameras.
  assert stats["anchor_reprojection_px"] < 0.3


def test_adjust_weights_each_keypoint_by_its_sift_scale(monkeypatch):
  """Anchors whose position error grows with their SIFT scale, as measured on the synthetic scenes
  (benchmarks/README.md): half small blobs placed to 0.15 px, half six times wider and placed six
  times worse. Weighted by their scales, the adjustment gets closer to the truth than with every
  anchor at one pixel."""
  # Anchors at a track's weight, so that only the scales set the anchors' weights here.
  monkeypatch.setattr(ground, "ANCHOR_SIGMA_FACTOR", 1.0)
  rng = np.random.default_rng(6)
  (wli, wli_n, cams, pts, obs), start, start_points = common_error_start(rng)
  anchors = {}
  for name, (xy, X, _) in anchors_of(rng, cams, noise_px=0.0).items():
    scale = rng.choice([1.0, 6.0], len(xy))
    anchors[name] = (xy + rng.normal(0, 0.15, xy.shape) * scale[:, None], X, scale)
  flat = {n: (xy, X, np.ones(len(xy))) for n, (xy, X, _) in anchors.items()}
  tree = cKDTree(wli)
  weighted, _ = ground.adjust(start, start_points, obs, K, wli, wli_n, 1.0, tree, anchors)
  unweighted, _ = ground.adjust(start, start_points, obs, K, wli, wli_n, 1.0, tree, flat)
  deg, um = worst(weighted, cams)
  deg_flat, um_flat = worst(unweighted, cams)
  # Measured: 0.034 deg and 0.38 um against 0.050 deg and 0.57 um.
  assert deg < 0.8 * deg_flat and um < 0.8 * um_flat, (deg, um, deg_flat, um_flat)


def test_snap_moves_points_onto_the_tangent_plane():
  rng = np.random.default_rng(1)
  p_wli, n_wli = scene(rng)[:2]
  xy = rng.uniform(-90, 90, (200, 2))
  pts = np.column_stack([xy, height(xy[:, 0], xy[:, 1]) + rng.normal(0, 1.0, 200)])
  pts[:5, 2] += 50.0  # far off the surface: not snapped
  out = ground.snap(pts, p_wli, n_wli, cKDTree(p_wli), gate=3.0)
  assert np.all(np.isnan(out[:5]))
  # float64 reference by a loop: projection onto the nearest sample's tangent plane, NaN beyond
  # the gate
  for p, o in zip(pts[5:], out[5:]):
    d = np.linalg.norm(p_wli - p, axis=1)
    j = int(np.argmin(d))
    ref = p - n_wli[j] * (n_wli[j] @ (p - p_wli[j])) if d[j] <= 3.0 else np.full(3, np.nan)
    np.testing.assert_allclose(o, ref, atol=1e-9)
  ok = np.all(np.isfinite(out), axis=1)
  assert ok[5:].mean() > 0.9
  # on the surface to within the curvature over one sample spacing
  assert np.max(np.abs(out[ok, 2] - height(out[ok, 0], out[ok, 1]))) < 0.15


def test_on_level_faces_keeps_the_tracks_of_level_points():
  # ridges z = 10 sin(x / 12): level on their crests and troughs, up to 40 deg steep between
  g = np.arange(-60, 60, 0.5)
  x, y = np.meshgrid(g, g, indexing="ij")
  p_wli = np.stack([x.ravel(), y.ravel(), 10 * np.sin(x.ravel() / 12)], 1)
  n_wli = np.stack([-10 / 12 * np.cos(x.ravel() / 12), np.zeros(x.size), np.ones(x.size)], 1)
  n_wli /= np.linalg.norm(n_wli, axis=1, keepdims=True)
  rng = np.random.default_rng(5)
  xy = rng.uniform(-55, 55, (400, 2))
  pts = np.column_stack([xy, 10 * np.sin(xy[:, 0] / 12) + rng.normal(0, 0.2, 400)])
  pts[::40] = np.nan  # points SfM did not keep
  obs = {name: (rng.uniform(0, 300, (200, 2)), np.sort(rng.choice(400, 200, replace=False)),
                rng.uniform(0.8, 5.0, 200)) for name in ("a", "b", "c")}
  tree = cKDTree(p_wli)
  kept = ground.on_level_faces(obs, pts, n_wli, tree)
  # float64 reference by a loop: the normal of the nearest WLI sample, |n_z| against LEVEL_NZ
  level = np.zeros(len(pts), bool)
  for i, p in enumerate(pts):
    if np.all(np.isfinite(p)):
      level[i] = abs(n_wli[np.argmin(np.linalg.norm(p_wli - p, axis=1)), 2]) >= ground.LEVEL_NZ
  assert 0.3 < level.mean() < 0.8
  assert kept.keys() == obs.keys()
  for name, (xy, idx, scale) in obs.items():
    for got, want in zip(kept[name], (xy, idx, scale)):
      np.testing.assert_array_equal(got, want[level[idx]])
  # A photo left with fewer than MIN_POINTS level tracks: every track stays.
  xy, idx, scale = obs["a"]
  sloped = np.flatnonzero(~level[idx])
  few = {**obs, "a": (xy[sloped], idx[sloped], scale[sloped])}
  assert ground.on_level_faces(few, pts, n_wli, tree) is few


def test_triangulate_recovers_points_from_exact_cameras():
  _, _, cams, pts, obs = scene(np.random.default_rng(7), noise_px=0.0)
  out = ground.triangulate(ground.tracks_of(obs), cams, K, len(pts))
  ok = np.all(np.isfinite(out), axis=1)
  assert ok.mean() > 0.9
  np.testing.assert_allclose(out[ok], pts[ok], atol=1e-6)


def test_ground_cameras_removes_tilt_and_bend():
  rng = np.random.default_rng(2)
  wli, wli_n, cams, pts, obs = scene(rng, noise_px=0.0)
  spoiled = {}
  for name, c2w in cams.items():  # each camera turned by 0.5-2 deg and moved by ~9 um
    axis = rng.normal(size=3)
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.5, 2.0)))
    m = c2w.copy()
    m[:3, :3] = turn.as_matrix() @ m[:3, :3]
    m[:3, 3] += rng.normal(0, 5.0, 3)
    spoiled[name] = m
  bent = pts.copy()
  bent[:, 2] += 1e-4 * (pts[:, 0] ** 2 + pts[:, 1] ** 2) - 1.0  # up to ~1 um bend
  g = ground.ground_cameras(spoiled, bent, obs, K, SIZE, wli, wli_n, 1.0)
  assert sorted(g.reposed) == sorted(cams)
  before = worst(spoiled, cams)[0]
  after, centre = worst(g.c2w, cams)
  assert before > 0.5
  # Measured: from 1.97 deg and 18.3 um to 0.0035 deg and 0.074 um.
  assert after < 0.05, after
  assert centre < 0.5, centre  # um, of cameras 650 um away
  assert max(g.change_deg.values()) == pytest.approx(before, abs=0.05)
