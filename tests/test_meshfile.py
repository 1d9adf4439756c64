"""ofjax.meshfile: mesh files that other tools open, with their unit."""

import numpy as np
import open3d as o3d
import pytest
import trimesh

from ofjax import meshfile
from ofjax.errors import UserError


@pytest.fixture
def box():
  mesh = trimesh.creation.box(extents=(3.0, 2.0, 1.0))
  mesh.visual.vertex_colors = np.tile([[10, 200, 30, 255]], (len(mesh.vertices), 1))
  return mesh


@pytest.mark.parametrize("units,comment", [("um", meshfile.PLY_UNITS_COMMENT),
                                           ("mm", b"comment units: mm")])
def test_ply_header_keeps_the_grammars_order_and_open3d_reads_it_whole(box, tmp_path, units,
                                                                       comment):
  path = meshfile.write_mesh(box, tmp_path / "box.ply", units)
  header = path.read_bytes().split(b"end_header")[0].split(b"\n")
  assert header[0] == b"ply" and header[1].startswith(b"format ")
  assert comment in header
  # RPly (Open3D's reader) refuses a header whose second line is not `format`.
  back = o3d.io.read_triangle_mesh(str(path))
  np.testing.assert_allclose(np.asarray(back.vertices), box.vertices, rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(back.triangles), box.faces)
  np.testing.assert_allclose(np.asarray(back.vertex_colors), box.visual.vertex_colors[:, :3] / 255)


@pytest.mark.parametrize("fmt", ["obj", "glb"])
def test_other_formats_round_trip(box, tmp_path, fmt):
  path = meshfile.write_mesh(box, tmp_path / f"box.{fmt}")
  back = trimesh.load(path, force="mesh", process=False)
  assert len(back.faces) == len(box.faces)
  np.testing.assert_allclose(np.sort(back.vertices, 0), np.sort(box.vertices, 0), atol=1e-6)


def test_an_unknown_suffix_is_a_user_error_and_writes_nothing(box, tmp_path):
  with pytest.raises(UserError, match="unknown mesh format 'stl'"):
    meshfile.write_mesh(box, tmp_path / "box.stl")
  assert not list(tmp_path.iterdir())
