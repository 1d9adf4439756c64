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
