"""ofjax.meshquery: ray casts, closest points and signed distances, lines of sight and colour
interpolation on meshes with closed forms."""

import numpy as np
import pytest
import trimesh

from ofjax.meshquery import MeshQuery, vertex_rgb
from plates import grid_plate

ROOF = 10.0  # um, height of the roof square over |x|, |y| <= ROOF_HALF
ROOF_HALF = 5.0


def floor_and_roof(offset=np.zeros(3)) -> MeshQuery:
  """A floor at z = 0 (|x|, |y| <= 50) and a roof at z = ROOF, both moved by `offset` (um)."""
  floor = grid_plate(-50.0, 50.0, 0.0, 4)
  roof = grid_plate(-ROOF_HALF, ROOF_HALF, ROOF, 2)
  mesh = trimesh.util.concatenate([floor, roof])
  return MeshQuery(mesh.vertices + offset, mesh.faces)


def roof_crossing(origins: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Float64 closed form of the open segments origin -> point [N, 3] against the roof:
  ([N] bool, the segment passes through it; [N] distance (um) of the segment's point at the
  roof's height from the roof's edge, in the max norm)."""
  s = (ROOF - origins[:, 2]) / (points[:, 2] - origins[:, 2])  # segment parameter at z = ROOF
  xy = origins[:, :2] + s[:, None] * (points[:, :2] - origins[:, :2])
  reach = np.abs(xy).max(-1)
  return (s > 0) & (s < 1) & (reach <= ROOF_HALF), np.abs(reach - ROOF_HALF)


@pytest.mark.parametrize("offset", [np.zeros(3), np.array([2.0e4, -1.5e4, 3.0e3])])
def test_clear_matches_the_closed_form_far_from_the_origin_too(offset):
  """Points between floor and roof seen from cameras above: blocked exactly where the segment
  crosses the roof (a stage offset of 2e4 um must not change that)."""
  rng = np.random.default_rng(3)
  n = 2000
  points = np.column_stack([rng.uniform(-8, 8, (n, 2)), rng.uniform(1.0, 9.0, n)])
  origins = np.column_stack([rng.uniform(-10, 10, (n, 2)), np.full(n, 60.0)])
  want, from_edge = roof_crossing(origins, points)
  # Segments that graze the roof's edge are decided by float32 rounding: leave them out.
  clear_of_edge = from_edge > 1e-3
  assert want[clear_of_edge].mean() > 0.1 and (~want[clear_of_edge]).mean() > 0.1
  got = floor_and_roof(offset).clear(origins + offset, points + offset)
  np.testing.assert_array_equal(got[clear_of_edge], ~want[clear_of_edge])


def test_clear_takes_one_origin_for_all_points_and_misses_count_as_clear():
  q = floor_and_roof()
  camera = np.array([0.0, 0.0, 100.0])
  points = np.array([[0.0, 0.0, 5.0],      # under the roof
                     [20.0, 0.0, 5.0],     # beside it
                     [0.0, 0.0, 200.0]])   # above the camera: the ray up meets nothing
  np.testing.assert_array_equal(q.clear(camera, points), [False, True, True])


def test_slacks_let_a_surface_point_see_past_its_own_face_and_no_further():
  q = floor_and_roof()
  camera = np.array([0.0, 0.0, 100.0])
  on_roof = np.array([[1.0, 2.0, ROOF]])
  assert q.clear(camera, on_roof, rel_slack=1e-5)[0]
  below_roof = on_roof - [0.0, 0.0, 0.5]  # the roof is 0.5 um in front of it
  assert not q.clear(camera, below_roof, abs_slack=0.2)[0]
  assert q.clear(camera, below_roof, abs_slack=0.6)[0]
  assert not q.clear(camera, below_roof, rel_slack=0.004)[0]  # 0.004 * 90.5 = 0.36 um < 0.5
  assert q.clear(camera, below_roof, rel_slack=0.006)[0]  # 0.54 um > 0.5


def test_ray_hits_interpolate_vertex_colours():
  size = 100.0
  mesh = grid_plate(0.0, size, 0.0, 20)
  linear = lambda p: np.stack([0.2 + 0.6 * p[:, 0] / size, 0.8 - 0.5 * p[:, 1] / size,  # noqa: E731
                               np.full(len(p), 0.4)], -1)
  mesh.visual.vertex_colors = np.round(linear(mesh.vertices) * 255).astype(np.uint8)
  rng = np.random.default_rng(7)
  xy = rng.uniform(0.0, size, size=(500, 2))
  q = MeshQuery.of(mesh)
  t, face, bary = q.cast(np.concatenate([xy, np.full((500, 1), 5.0)], -1),
                         np.tile([0.0, 0.0, -1.0], (500, 1)))
  np.testing.assert_allclose(t, 5.0, atol=1e-5)
  hit = np.concatenate([xy, np.zeros((500, 1))], -1)
  # 8-bit vertex colours of a linear albedo: interpolation is within 0.5/255 of it.
  np.testing.assert_allclose(q.interpolate(vertex_rgb(mesh), face, bary), linear(hit),
                             atol=0.5 / 255 + 1e-6)


def test_points_above_a_plane_and_beside_a_box_get_their_signed_distances():
  plane = trimesh.Trimesh([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]],
                          [[0, 1, 2], [0, 2, 3]])  # normal +z
  rng = np.random.default_rng(1)
  xy = rng.uniform(-5, 5, (50, 2))
  z = rng.uniform(-3, 3, 50)
  signed, normal = MeshQuery.of(plane).signed_distance(np.column_stack([xy, z]))
  np.testing.assert_allclose(signed, z, atol=1e-5)
  np.testing.assert_allclose(normal, np.tile([0.0, 0.0, 1.0], (50, 1)), atol=1e-6)
  box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))  # outward normals
  pts = np.array([[1.7, 0.1, 0.2], [0.2, -0.3, 0.5], [0.0, 0.0, -1.4]])
  signed, normal = MeshQuery.of(box).signed_distance(pts)
  np.testing.assert_allclose(signed, [0.7, -0.5, 0.4], atol=1e-5)
  np.testing.assert_allclose(normal, [[1, 0, 0], [0, 0, 1], [0, 0, -1]], atol=1e-6)
