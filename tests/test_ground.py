"""Tests of ofjax.associate.ground: re-posing OM photos on the WLI surface.

The scene is built here: a bumpy height field z(x, y) (um) sampled densely as the WLI cloud,
sparse surface points seen by pinhole cameras looking down from rings, their exact projections as
keypoints. The step-2 input is then spoiled the way a weak SfM spoils it: cameras tilted by up to
2 degrees and moved, points bent off the surface in height.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ofjax.associate import ground, wli

K = np.array([[600.0, 0, 160], [0, 600.0, 120], [0, 0, 1]])
SIZE = (320, 240)  # width, height


def height(x, y):
  return 8 * np.sin(x / 23.0) * np.cos(y / 31.0) + 0.02 * x


def wli_cloud(spacing=1.0):
  g = np.arange(-120, 120, spacing)
  x, y = np.meshgrid(g, g, indexing="ij")
  p = np.stack([x.ravel(), y.ravel(), height(x, y).ravel()], 1)
  # normals of z = h(x, y): (-h_x, -h_y, 1), normalised
  hx = 8 / 23.0 * np.cos(x / 23.0) * np.cos(y / 31.0) + 0.02
  hy = -8 / 31.0 * np.sin(x / 23.0) * np.sin(y / 31.0)
  n = np.stack([-hx.ravel(), -hy.ravel(), np.ones(hx.size)], 1)
  return p, n / np.linalg.norm(n, axis=1, keepdims=True)


def look(tilt, azimuth, distance=500.0):
  rot = wli.prior_rotation({"tilt_deg": tilt, "azimuth_deg": azimuth})
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = rot, -distance * rot[:, 2]
  return m


def rot_deg(a, b):
  return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def scene():
  rng = np.random.default_rng(0)
  xy = rng.uniform(-100, 100, (1500, 2))
  pts = np.column_stack([xy, height(xy[:, 0], xy[:, 1])])
  views = [(0, 0)] + [(t, a) for t in (15, 30) for a in range(0, 360, 60)]
  cams = {f"{k:04d}": look(t, a) for k, (t, a) in enumerate(views)}
  obs = {}
  for name, c2w in cams.items():
    cam = (pts - c2w[:3, 3]) @ c2w[:3, :3]
    uv = cam[:, :2] / cam[:, 2:] * K[0, 0] + K[:2, 2]
    inside = np.all((uv >= 0) & (uv < SIZE), axis=1)
    obs[name] = (uv[inside], np.flatnonzero(inside), np.ones(int(inside.sum())))
  return pts, cams, obs


def test_snap_moves_points_onto_the_tangent_plane():
  p_wli, n_wli = wli_cloud()
  rng = np.random.default_rng(1)
  xy = rng.uniform(-90, 90, (200, 2))
  off = rng.normal(0, 1.0, 200)
  pts = np.column_stack([xy, height(xy[:, 0], xy[:, 1]) + off])
  pts[:5, 2] += 50.0  # far off the surface: not snapped
  out = ground.snap(pts, p_wli, n_wli, cKDTree(p_wli), gate=3.0)
  assert np.all(np.isnan(out[:5]))
  # float64 reference: projection onto the nearest sample's tangent plane, by a loop
  # and NaN beyond the gate
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


def test_triangulate_recovers_points_from_exact_cameras(scene):
  pts, cams, obs = scene
  tracks = ground.tracks_of(obs)
  out = ground.triangulate(tracks, cams, K, len(pts))
  ok = np.all(np.isfinite(out), axis=1)
  assert ok.mean() > 0.9
  np.testing.assert_allclose(out[ok], pts[ok], atol=1e-6)


def test_ground_cameras_removes_tilt_and_bend(scene):
  pts, cams, obs = scene
  p_wli, n_wli = wli_cloud()
  rng = np.random.default_rng(2)
  spoiled = {}
  for name, c2w in cams.items():
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(rng.uniform(0.5, 2.0))
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * kx @ kx
    m = c2w.copy()
    m[:3, :3] = r @ c2w[:3, :3]
    m[:3, 3] += rng.normal(0, 5.0, 3)
    spoiled[name] = m
  bent = pts.copy()
  bent[:, 2] += 1e-4 * (pts[:, 0] ** 2 + pts[:, 1] ** 2) - 1.0  # up to ~1 um bend
  g = ground.ground_cameras(spoiled, bent, obs, K, SIZE, p_wli, n_wli, 1.0)
  assert sorted(g.reposed) == sorted(cams)
  before = max(rot_deg(spoiled[n][:3, :3], cams[n][:3, :3]) for n in cams)
  after = max(rot_deg(g.c2w[n][:3, :3], cams[n][:3, :3]) for n in cams)
  centre = max(np.linalg.norm(g.c2w[n][:3, 3] - cams[n][:3, 3]) for n in cams)
  assert before > 0.5
  assert after < 0.05, after
  assert centre < 0.5, centre  # um, of cameras 500 um away
  assert max(g.change_deg.values()) == pytest.approx(before, abs=0.05)
