"""ofjax.visibility: the faces some camera sees, against geometry whose answer is known."""

import numpy as np
import pytest
import trimesh

from ofjax import scene as scn
from ofjax import visibility


def _look_down(height: float) -> np.ndarray:
  """[4, 4] c2w of a camera at (0, 0, height) looking down -z (x_cam = x, y_cam = -y)."""
  c2w = np.eye(4)
  c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
  c2w[2, 3] = height
  return c2w


def _poses(*cams: tuple[str, np.ndarray]) -> dict:
  """A poses file's contents: a 64 x 64 orthographic scan of 1 um pixels, or a 64 x 64 pinhole
  photo with a 45 deg field of view, per (modality, c2w)."""
  out = []
  for k, (modality, c2w) in enumerate(cams):
    if modality == "wli":
      intr = {"model": "orthographic", "pixel_size": [1.0, 1.0]}
    else:
      f = 32.0 / np.tan(np.radians(22.5))
      intr = {"model": "pinhole", "fx": f, "fy": f, "cx": 32.0, "cy": 32.0}
    out.append({"name": f"{modality}/{k:04d}", "modality": modality, "width": 64, "height": 64,
                "intrinsics": intr, "c2w": c2w.tolist()})
  return {"format": scn.POSES_FORMAT, "version": scn.VERSION, "units": "um", "cameras": out}


def _block_with_pocket() -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
  """A 40 x 40 x 10 um block (z in [0, 10]) with a closed 10 um pocket inside it (its walls
  facing inwards, as marching cubes makes them), and the face masks of the pocket and of the
  block's top."""
  block = trimesh.creation.box(extents=[40.0, 40.0, 10.0])
  block.apply_translation([0.0, 0.0, 5.0])
  pocket = trimesh.creation.box(extents=[10.0, 10.0, 4.0])
  pocket.apply_translation([3.0, -2.0, 5.0])
  pocket.invert()
  mesh = trimesh.util.concatenate([block, pocket])
  in_pocket = np.arange(len(mesh.faces)) >= len(block.faces)
  top = ~in_pocket & (mesh.face_normals[:, 2] > 0.99)
  return mesh, in_pocket, top


@pytest.mark.parametrize("modality", ["wli", "om"])
def test_a_pocket_inside_a_block_is_hidden_and_the_top_is_seen(modality):
  mesh, in_pocket, top = _block_with_pocket()
  seen = visibility.seen_faces(mesh, _poses((modality, _look_down(100.0))))
  assert seen.dtype == bool and seen.shape == (len(mesh.faces),)
  assert not seen[in_pocket].any()
  assert seen[top].all()
  bottom = mesh.face_normals[:, 2] < -0.99
  assert not seen[bottom & ~in_pocket].any()  # the block's underside, behind its top
  walls = ~in_pocket & (np.abs(mesh.face_normals[:, 2]) < 0.01)
  # A scan straight down sees the vertical walls edge-on (kept); a pinhole above the block's
  # middle sees them from behind their plane (dropped).
  assert seen[walls].all() if modality == "wli" else not seen[walls].any()


def test_a_face_outside_every_frame_is_hidden():
  """A camera far to the side: the block is outside its 64 um wide field, so nothing is seen."""
  mesh, _, _ = _block_with_pocket()
  off = _look_down(100.0)
  off[0, 3] = 500.0
  assert not visibility.seen_faces(mesh, _poses(("wli", off))).any()


def test_an_open_pit_is_seen_from_above_but_not_from_the_side():
  """A pit open at the top (a box with no lid) is in sight of a top view, floor included; a
  photo from the side (looking along +x at 5 um height) sees the outer wall facing it, not the
  pit's floor, which the near wall hides."""
  pit = trimesh.creation.box(extents=[10.0, 10.0, 10.0])
  pit.apply_translation([0.0, 0.0, 5.0])
  pit.update_faces(pit.face_normals[:, 2] < 0.99)  # no lid
  pit.invert()  # walls facing in, as the inside of a pit does
  floor = pit.face_normals[:, 2] > 0.99
  assert visibility.seen_faces(pit, _poses(("wli", _look_down(50.0))))[floor].all()
  side = np.eye(4)
  side[:3, :3] = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # z_cam = +x
  side[:3, 3] = [-60.0, 0.0, 5.0]
  seen = visibility.seen_faces(pit, _poses(("om", side)))
  assert not seen[floor].any()
  near_wall = np.isclose(pit.triangles_center[:, 0], -5.0)
  assert seen[near_wall].all()


def test_drop_hidden_keeps_the_seen_faces_and_their_colours():
  mesh, in_pocket, _ = _block_with_pocket()
  rgba = np.tile([[10, 20, 30, 255]], (len(mesh.vertices), 1)).astype(np.uint8)
  rgba[: len(mesh.vertices) // 2, 0] = 200
  mesh.visual.vertex_colors = rgba
  poses = _poses(("wli", _look_down(100.0)), ("om", _look_down(100.0)))
  seen = visibility.seen_faces(mesh, poses)
  out, share = visibility.drop_hidden(mesh, poses)
  assert share == pytest.approx(seen.mean()) and 0 < share < 1
  assert len(out.faces) == seen.sum()
  np.testing.assert_allclose(np.sort(out.triangles_center, 0),
                             np.sort(mesh.triangles_center[seen], 0))
  # every kept vertex keeps its colour: match kept vertices to the originals by position
  index = {tuple(v): i for i, v in enumerate(np.round(mesh.vertices, 9))}
  orig = [index[tuple(v)] for v in np.round(out.vertices, 9)]
  np.testing.assert_array_equal(out.visual.vertex_colors, rgba[orig])
  same, all_seen = visibility.drop_hidden(out, poses)
  assert all_seen == 1.0 and same is out
