"""experiments/mesh_offsets.py: signed distances to the true surface against closed forms."""

import sys
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import mesh_offsets  # noqa: E402


def test_points_above_a_plane_and_beside_a_box_get_their_signed_distances():
  plane = trimesh.Trimesh([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]],
                          [[0, 1, 2], [0, 2, 3]])  # normal +z
  rng = np.random.default_rng(1)
  xy = rng.uniform(-5, 5, (50, 2))
  z = rng.uniform(-3, 3, 50)
  signed, nz = mesh_offsets.signed_offsets(plane, np.column_stack([xy, z]))
  np.testing.assert_allclose(signed, z, atol=1e-5)
  np.testing.assert_allclose(nz, 1.0, atol=1e-6)
  box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))  # outward normals
  pts = np.array([[1.7, 0.1, 0.2], [0.2, -0.3, 0.5], [0.0, 0.0, -1.4]])
  signed, nz = mesh_offsets.signed_offsets(box, pts)
  np.testing.assert_allclose(signed, [0.7, -0.5, 0.4], atol=1e-5)
  np.testing.assert_allclose(nz, [0.0, 1.0, 1.0], atol=1e-6)


def test_seen_by_counts_lines_of_sight_blocked_by_a_roof():
  """A floor at z = 0 and a roof at z = 10 over |x|, |y| <= 5; cameras above, looking down."""
  floor = trimesh.Trimesh([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]],
                          [[0, 1, 2], [0, 2, 3]])
  roof = trimesh.Trimesh([[-5, -5, 10], [5, -5, 10], [5, 5, 10], [-5, 5, 10]],
                         [[0, 1, 2], [0, 2, 3]])
  gt = mesh_offsets.MeshQuery.of(trimesh.util.concatenate([floor, roof]))
  down = np.diag([1.0, -1.0, -1.0])  # OpenCV axes: z forward = -z of the world
  c2w = np.eye(4)
  c2w[:3, :3], c2w[:3, 3] = down, [0.0, 0.0, 100.0]
  pinhole = {"modality": "om", "width": 100, "height": 100, "c2w": c2w.tolist(),
             "intrinsics": {"model": "pinhole", "fx": 100.0, "fy": 100.0, "cx": 50.0, "cy": 50.0}}
  ortho = {"modality": "wli", "width": 40, "height": 40, "c2w": c2w.tolist(),
           "intrinsics": {"model": "orthographic", "pixel_size": [1.0, 1.0]}}
  pts = np.array([[0.0, 0.0, 5.0],     # under the roof: hidden from above
                  [12.0, 0.0, 5.0],    # beside it: seen
                  [0.0, 0.0, 0.3],     # just over the floor, under the roof: hidden
                  [15.0, 3.0, 0.3],    # just over the floor in the open: its own floor does not block
                  [45.0, 0.0, 5.0],    # outside the orthographic scan (20 um half-width), in the photo
                  [0.0, 0.0, 150.0]])  # behind the pinhole camera
  np.testing.assert_array_equal(mesh_offsets.seen_by(gt, pts, pinhole),
                                [False, True, False, True, True, False])
  np.testing.assert_array_equal(mesh_offsets.seen_by(gt, pts, ortho),
                                [False, True, False, True, False, True])
  # A tilted pinhole camera at the roof's height looks under it from the side.
  side = np.eye(4)
  side[:3, :3] = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # looks -x
  side[:3, 3] = [40.0, 0.0, 5.0]
  cam = dict(pinhole, c2w=side.tolist())
  np.testing.assert_array_equal(mesh_offsets.seen_by(gt, pts[:1], cam), [True])
