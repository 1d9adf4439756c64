"""ofjax.associate.anchor: photos anchored on the WLI scans' intensity images.

Geometry is checked against closed forms (a tilted scan of a plane); the anchors themselves on the
blocks scene (tests/blocks.py), whose scans here carry intensity images, against the true poses.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.feature import match_descriptors

from blocks import MESH_GT, assert_within_targets, om_images, scene_size, unposed, wli_scans
from ofjax import scene as scene_lib
from ofjax import synth
from ofjax.associate import anchor, evaluate
from ofjax.associate.__main__ import main as associate_main
from ofjax.meshquery import MeshQuery

PLANE_N = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])  # world plane n.x = c
PLANE_C = 3.0
PLANE_TOL_UM = 0.1  # anchors on the blocks' true surface: a tenth of its 1 um WLI pixel


def plane_scan(shape=(40, 50), px=(1.5, 1.2)) -> scene_lib.WLIScan:
  """A scan 30 deg off the vertical of the plane n.x = c, its depth from the closed form."""
  c2w = np.eye(4)
  c2w[:3, :3] = synth.view_rotation(30.0, 40.0)
  c2w[:3, 3] = -200.0 * c2w[:3, 2] + (5.0, -3.0, 0.0)
  scan = scene_lib.WLIScan("plane", np.zeros(shape, np.float32), px, c2w=c2w)
  o, d = scene_lib.wli_rays(scan)
  scan.depth = ((PLANE_C - o @ PLANE_N) / (d @ PLANE_N)).astype(np.float32)
  return scan


def ray_hits(scan: scene_lib.WLIScan, xy: np.ndarray) -> np.ndarray:
  """[k, 3] where the scan's rays through sub-pixel positions xy (centres at +0.5) meet the plane."""
  h, w = scan.shape
  local = np.column_stack([(xy[:, 0] - w / 2) * scan.pixel_size[0],
                           (xy[:, 1] - h / 2) * scan.pixel_size[1], np.zeros(len(xy))])
  o = local @ scan.c2w[:3, :3].T + scan.c2w[:3, 3]
  d = scan.c2w[:3, 2]
  return o + ((PLANE_C - o @ PLANE_N) / (d @ PLANE_N))[:, None] * d


def test_lift_puts_keypoints_on_the_scanned_surface():
  scan = plane_scan()
  xy = np.random.default_rng(0).uniform([1.0, 1.0], [49.0, 39.0], (200, 2))
  # Depth is affine in the pixel position on a plane, so bilinear interpolation is exact there
  # (float32 depths: ~1e-5 um at 200 um).
  np.testing.assert_allclose(anchor.lift(scan, scan.c2w, xy), ray_hits(scan, xy), atol=1e-3)


def test_lift_drops_keypoints_at_voids_and_depth_edges():
  scan = plane_scan()
  scan.depth[10, 10] = np.nan
  scan.depth[:, 30:] += 20.0  # a 20 um step (13x the pixel size) between columns 29 and 30
  near_void = np.array([[10.9, 10.2], [11.4, 11.3]])  # pixel (row 10, col 10) among the four
  on_edge = np.array([[30.0, 20.5], [29.6, 5.5]])  # between columns 29 and 30
  clear = np.array([[20.5, 20.5], [40.5, 30.5]])
  X = anchor.lift(scan, scan.c2w, np.concatenate([near_void, on_edge, clear]))
  assert np.isnan(X[:4]).all() and np.isfinite(X[4:]).all()


def test_stretch_maps_the_robust_range_to_unit():
  img = np.linspace(10.0, 1010.0, 4000).reshape(40, 100)
  img[0, :5] = np.nan
  out = anchor.stretch(img)
  assert out.dtype == np.float32 and out.min() == 0.0 and out.max() == 1.0
  assert np.all(np.diff(out[1:].ravel()) >= 0)  # monotone in the intensity
  lo, hi = np.nanpercentile(img, anchor.INTENSITY_PERCENTILES)
  np.testing.assert_allclose(out[20, 50], (img[20, 50] - lo) / (hi - lo), rtol=1e-5)
  np.testing.assert_array_equal(anchor.stretch(np.full((8, 8), 3.0)), np.zeros((8, 8)))


def test_match_equals_scikit_images_mutual_ratio_matching():
  rng = np.random.default_rng(1)
  a = rng.normal(size=(300, 128)).astype(np.float32)
  b = np.concatenate([a[:150] + rng.normal(0, 0.3, (150, 128)), rng.normal(size=(250, 128))])
  a /= np.linalg.norm(a, axis=1, keepdims=True)
  b = (b / np.linalg.norm(b, axis=1, keepdims=True)).astype(np.float32)
  want = match_descriptors(a, b, cross_check=True, max_ratio=anchor.MATCH_MAX_RATIO)
  got = anchor.match(a, b)
  assert 50 < len(got) <= 150  # the test holds real and rejected candidates
  np.testing.assert_array_equal(got[np.lexsort(got.T[::-1])], want[np.lexsort(want.T[::-1])])
  assert anchor.match(a, b[:1]).shape == (0, 2)


@pytest.fixture(scope="module")
def blocks_with_intensity():
  scans = wli_scans(MESH_GT, intensity=True)
  return scans, om_images(MESH_GT), scene_size(scans)


def test_anchor_photos_recovers_every_photo_from_the_wli_alone(blocks_with_intensity):
  scans, photos, size = blocks_with_intensity
  an = anchor.anchor_photos(scans, [s.c2w for s in scans], photos, photos[0].K)
  assert an is not None and an.anchors.keys() == an.c2w.keys()
  again = anchor.anchor_photos(scans, [s.c2w for s in scans], photos, photos[0].K)
  for name in an.c2w:  # the same seed gives the same anchors and poses
    np.testing.assert_array_equal(again.c2w[name], an.c2w[name])
    np.testing.assert_array_equal(again.anchors[name][0], an.anchors[name][0])
  assert len(an.anchors) == len(photos)
  # Each photo from its anchors alone, against the targets (0.2 deg, 0.5% of the size).
  truth = {o.name: o.c2w for o in photos}
  deg = max(evaluate.rotation_deg(an.c2w[n][:3, :3], truth[n][:3, :3]) for n in an.c2w)
  centre = max(np.linalg.norm(an.c2w[n][:3, 3] - truth[n][:3, 3]) for n in an.c2w) / size
  assert deg <= 0.2 and centre <= 0.005, (deg, centre)
  # Anchors are exact WLI points (on the true surface) seen where the true camera sees them.
  xy, X, scale = (np.concatenate(a) for a in zip(*an.anchors.values()))
  assert np.all(scale >= 0.5) and np.all(np.isfinite(scale))  # SIFT's smallest blobs are ~0.8 px
  dist = np.abs(MeshQuery(MESH_GT.vertices, MESH_GT.faces).signed_distance(X)[0])
  assert np.median(dist) < PLANE_TOL_UM
  name = photos[0].name
  xy0, X0, _ = an.anchors[name]
  u, v, _ = scene_lib.project_pinhole(X0, photos[0].K, truth[name], photos[0].shape)
  assert np.median(np.hypot(u - xy0[:, 0], v - xy0[:, 1])) < 0.5


def test_anchor_photos_needs_intensity_images(blocks_with_intensity):
  scans, photos, _ = blocks_with_intensity
  bare = [scene_lib.WLIScan(s.name, s.depth, s.pixel_size, c2w=s.c2w) for s in scans]
  assert anchor.anchor_photos(bare, [s.c2w for s in bare], photos, photos[0].K) is None


@pytest.mark.slow
def test_cli_associates_the_scene_with_intensity_images_within_targets(blocks_with_intensity,
                                                                      tmp_path):
  scans, photos, size = blocks_with_intensity
  scene, gt = unposed(scene_lib.Scene(scans, photos, name="blocks"))
  scene_lib.save_scene(scene, tmp_path)
  assert associate_main([str(tmp_path), "--report"]) == 0
  s = evaluate.pose_errors(json.loads((tmp_path / "poses.json").read_text()), gt, size)["summary"]
  assert_within_targets(s)
  rep = json.loads((tmp_path / "association" / "report.json").read_text())
  assert rep["anchor"]["anchored_photos"] == 37 and rep["anchor"]["scans_with_intensity"] == 5
  adj = rep["ground"]["adjustment"]
  assert adj["anchored_photos"] == 37 and not adj["mapped_back"]
