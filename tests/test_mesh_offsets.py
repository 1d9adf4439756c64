"""experiments/mesh_offsets.py: lines of sight and the printed offsets against closed forms."""

import json
import sys
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import mesh_offsets  # noqa: E402

from ofjax.meshquery import MeshQuery  # noqa: E402


def _floor_and_roof() -> trimesh.Trimesh:
  """A floor at z = 0 and a roof at z = 10 over |x|, |y| <= 5, both facing up."""
  floor = trimesh.Trimesh([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]],
                          [[0, 1, 2], [0, 2, 3]])
  roof = trimesh.Trimesh([[-5, -5, 10], [5, -5, 10], [5, 5, 10], [-5, 5, 10]],
                         [[0, 1, 2], [0, 2, 3]])
  return trimesh.util.concatenate([floor, roof])


def test_seen_by_counts_lines_of_sight_blocked_by_a_roof():
  """The floor and roof; cameras above, looking down."""
  gt = MeshQuery.of(_floor_and_roof())
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


def _roof_scene(tmp_path):
  """A scene directory: a floor at z = 0 under a roof at z = 10 (|x|, |y| <= 5), GT points on the
  floor over [-20, 20]^2, one OM camera and one WLI scan 100 um above, looking down."""
  gt_dir = tmp_path / "scene" / "ground_truth"
  gt_dir.mkdir(parents=True)
  _floor_and_roof().export(gt_dir / "mesh.ply")
  g = np.linspace(-20, 20, 21)
  pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
  trimesh.PointCloud(np.column_stack([pts, np.zeros(len(pts))])).export(gt_dir / "surface_points.ply")
  c2w = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 100], [0, 0, 0, 1]]
  (gt_dir / "poses.json").write_text(json.dumps({"cameras": [
      {"name": "om/0", "modality": "om", "width": 100, "height": 100, "c2w": c2w,
       "intrinsics": {"model": "pinhole", "fx": 100.0, "fy": 100.0, "cx": 50.0, "cy": 50.0}},
      {"name": "wli/0", "modality": "wli", "width": 64, "height": 64, "c2w": c2w,
       "intrinsics": {"model": "orthographic", "pixel_size": [1.0, 1.0]}}]}))
  return tmp_path / "scene"


def test_cli_crops_to_the_evaluated_region_and_counts_the_views(tmp_path, capsys):
  scene = _roof_scene(tmp_path)
  # The prediction: a sheet 3 um over the floor on a half-integer grid, wider than the GT points.
  g = np.linspace(-29.5, 29.5, 60)
  xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
  faces = [[i, i + 1, i + 60] for i in range(60 * 59) if i % 60 != 59]  # every vertex in a face
  trimesh.Trimesh(np.column_stack([xy, np.full(len(xy), 3.0)]), faces,
                  process=False).export(tmp_path / "pred.ply")
  assert mesh_offsets.main([str(scene), str(tmp_path / "pred.ply"), "--cameras"]) == 0
  out = capsys.readouterr().out
  # 40 x 40 vertices lie in the GT points' [-20, 20]^2, all 3 um above the floor; the 10 x 10
  # under the roof are hidden from both cameras: 1,500 of 1,600 seen.
  assert "100.0% of vertices beyond 1.5 um, 100% of them outside, median +3.00 um" in out
  assert "OM cameras (1): 93.8% by at least one" in out
  assert "WLI cameras (1): 93.8% by at least one" in out
