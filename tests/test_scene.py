"""ofjax.scene's host-side camera geometry: projections invert the ray generators."""

import numpy as np
from scipy.spatial.transform import Rotation

from ofjax import scene as scn


def tilted_photo(h=30, w=40) -> scn.OMImage:
  c2w = np.eye(4)
  c2w[:3, :3] = Rotation.from_euler("xyz", [170.0, 20.0, 35.0], degrees=True).as_matrix()
  c2w[:3, 3] = [1.2e4, -3.0e3, 800.0]  # a stage far from the origin
  k = np.array([[55.0, 0.0, 21.0], [0.0, 52.0, 14.5], [0.0, 0.0, 1.0]])
  return scn.OMImage("0000", np.zeros((h, w, 3), np.float32), K=k, c2w=c2w)


def test_pixel_centres_project_back_to_their_coordinates():
  photo = tilted_photo()
  o, d = scn.om_rays(photo)
  depth = np.random.default_rng(0).uniform(10.0, 900.0, d.shape[:2])
  points = (o + depth[..., None] * d).reshape(-1, 3)
  u, v, inside = scn.project_pinhole(points, photo.K, photo.c2w, photo.shape)
  rows, cols = np.meshgrid(np.arange(30), np.arange(40), indexing="ij")
  np.testing.assert_allclose(u, cols.ravel() + 0.5, atol=1e-6)
  np.testing.assert_allclose(v, rows.ravel() + 0.5, atol=1e-6)
  assert inside.all()


def test_points_behind_beside_and_in_the_plane_of_the_camera_are_outside():
  photo = tilted_photo()
  o, d = scn.om_rays(photo)
  centre, axis = photo.c2w[:3, 3], photo.c2w[:3, 2]
  right = photo.c2w[:3, 0]
  points = np.stack([centre - 50.0 * d[15, 20],       # behind: projects into the frame, mirrored
                     centre + 100.0 * axis + 1e3 * right,  # in front, far right of the frame
                     centre + 10.0 * right,             # in the camera's plane
                     centre + 100.0 * d[0, 0],           # in front, the first pixel
                     centre + 100.0 * d[29, 39]])        # in front, the last pixel
  _, _, inside = scn.project_pinhole(points, photo.K, photo.c2w, photo.shape)
  np.testing.assert_array_equal(inside, [False, False, False, True, True])


def test_orthographic_projection_inverts_the_scan_rays():
  c2w = np.eye(4)
  c2w[:3, :3] = Rotation.from_euler("xyz", [160.0, -25.0, 70.0], degrees=True).as_matrix()
  c2w[:3, 3] = [-4.0e3, 9.0e3, 350.0]
  scan = scn.WLIScan("0000", np.zeros((20, 30), np.float32), (1.3, 0.9), c2w=c2w)
  o, d = scn.wli_rays(scan)
  depth = np.random.default_rng(1).uniform(-50.0, 50.0, d.shape[:2])
  points = (o + depth[..., None] * d).reshape(-1, 3)
  col, row, z, inside = scn.project_orthographic(points, c2w, scan.pixel_size, scan.shape)
  rows, cols = np.meshgrid(np.arange(20), np.arange(30), indexing="ij")
  np.testing.assert_allclose(col, cols.ravel() + 0.5, atol=1e-6)
  np.testing.assert_allclose(row, rows.ravel() + 0.5, atol=1e-6)
  np.testing.assert_allclose(z, depth.ravel(), atol=1e-6)
  assert inside.all()
  beside = o[0, 0] - 1.0 * scan.pixel_size[0] * c2w[:3, 0]  # one pixel left of the first column
  below = o[-1, 0] + 1.0 * scan.pixel_size[1] * c2w[:3, 1]  # one pixel below the last row
  *_, out = scn.project_orthographic(np.stack([beside, below]), c2w, scan.pixel_size, scan.shape)
  np.testing.assert_array_equal(out, [False, False])
