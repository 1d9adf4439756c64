"""Mesh export: an analytic sphere SDF comes out as a sphere in um with the colour function's colours."""

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from skimage import measure

from ofjax import export, meshfile
from ofjax import scene as scene_lib
from ofjax.errors import UserError

RADIUS = 0.6  # normalised units
NORM = scene_lib.Normalization(center=(100.0, -50.0, 20.0), scale=250.0)  # um


def sdf_fn(x):
  return jnp.linalg.norm(x, axis=-1) - RADIUS


def color_fn(x):
  """A colour that varies over the sphere: (x, y, z) mapped from [-1, 1] to [0, 1]."""
  return (x + 1.0) / 2.0


def test_sphere_sdf_exports_a_sphere_in_um_with_its_colours(tmp_path):
  mesh = export.surface_mesh(sdf_fn, color_fn, (-1, -1, -1), (1, 1, 1), 96, NORM)
  v = np.asarray(mesh.vertices)
  r_um = np.linalg.norm(v - np.asarray(NORM.center), axis=1)
  spacing_um = 2.0 / 96 * NORM.scale
  # Marching cubes interpolates linearly between grid nodes: its radial error is a small fraction
  # of a cell on a sphere this well resolved.
  np.testing.assert_allclose(r_um, RADIUS * NORM.scale, atol=0.05 * spacing_um)
  assert mesh.is_watertight
  # Faces point outwards (the SDF grows outwards): the enclosed volume is positive.
  assert mesh.volume > 0
  np.testing.assert_allclose(mesh.volume, 4 / 3 * np.pi * (RADIUS * NORM.scale)**3, rtol=0.01)
  rgb = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0
  expected = (NORM.to_norm(v) + 1.0) / 2.0
  np.testing.assert_allclose(rgb, expected, atol=1.0 / 255 + 1e-6)

  path = export.write_mesh(mesh, tmp_path / "sphere.ply")
  assert meshfile.PLY_UNITS_COMMENT in path.read_bytes()[:400]
  back = trimesh.load(path, process=False)
  np.testing.assert_allclose(np.asarray(back.vertices), v, rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(back.visual.vertex_colors)[:, :3],
                                np.asarray(mesh.visual.vertex_colors)[:, :3])


def two_spheres(x):
  big = jnp.linalg.norm(x - jnp.array([-0.3, 0.0, 0.0]), axis=-1) - 0.5
  small = jnp.linalg.norm(x - jnp.array([0.75, 0.0, 0.0]), axis=-1) - 0.08
  return jnp.minimum(big, small)


def test_small_floating_components_are_dropped():
  mesh = export.surface_mesh(two_spheres, color_fn, (-1, -1, -1), (1, 1, 1), 64, NORM,
                             min_component=0.05)
  centre = NORM.to_norm(np.asarray(mesh.vertices)).mean(0)
  assert len(trimesh.graph.connected_components(mesh.face_adjacency)) == 1
  np.testing.assert_allclose(centre, [-0.3, 0.0, 0.0], atol=0.01)


def test_dropped_components_are_not_refined():
  """Dropping before the refinement gives the kept component's refined vertices as refining all
  and dropping after would, and evaluates the SDF on no edge of the dropped sphere."""
  queried = []

  def recording(x):
    queried.append(np.asarray(x))
    return two_spheres(x)

  args = ((-1, -1, -1), (1, 1, 1), 64)
  kept = export.marching_cubes(recording, *args, min_component=0.05)
  near_small = [np.abs(np.linalg.norm(q - [0.75, 0.0, 0.0], axis=1) - 0.08) < 0.05
                for q in queried]
  # The calls that sampled the grid: as many as sdf_grid makes on it alone.
  shape, spacing = export.grid_layout(*args)
  grid_queries = []
  export.sdf_grid(lambda x: grid_queries.append(1) or two_spheres(x), np.asarray(args[0], float),
                  spacing, shape)
  grid_calls = len(grid_queries)
  assert np.concatenate(near_small[:grid_calls]).any()  # the grid samples it
  assert not np.concatenate(near_small[grid_calls:]).any()  # the bisection does not
  everything = export.marching_cubes(two_spheres, *args)
  assert len(kept.vertices) < len(everything.vertices)
  after = export.drop_small_components(everything, 0.05)
  np.testing.assert_array_equal(kept.faces, after.faces)
  np.testing.assert_array_equal(kept.vertices, after.vertices)


def test_no_surface_gives_an_empty_mesh():
  mesh = export.surface_mesh(lambda x: jnp.ones(x.shape[:-1]), color_fn, (-1, -1, -1), (1, 1, 1),
                             16, NORM)
  assert len(mesh.faces) == 0


def test_refinement_puts_the_vertices_of_a_bent_sdf_on_its_zero():
  """exp(k (r - R)) - 1 is zero on the sphere r = R but far from linear across a cell: marching
  cubes' linear interpolation puts vertices a visible fraction of a cell inside; bisection on each
  vertex's grid edge puts them on the sphere."""
  cells = 48
  cell = 2.0 / cells  # normalised units
  k = 3.0 / cell

  def bent(x):
    return jnp.expm1(k * (jnp.linalg.norm(x, axis=-1) - RADIUS))

  def radial_error_cells(steps):
    mesh = export.marching_cubes(bent, (-1, -1, -1), (1, 1, 1), cells, refine_steps=steps)
    return (np.linalg.norm(np.asarray(mesh.vertices), axis=1) - RADIUS) / cell, mesh

  plain, plain_mesh = radial_error_cells(0)
  refined, refined_mesh = radial_error_cells(export.REFINE_STEPS)
  assert np.abs(plain).mean() > 0.05  # the bias the refinement exists for (measured 0.11 cell)
  assert np.abs(refined).max() < 0.001  # measured 9e-5 cell
  # Same topology, and every vertex stays on its grid edge (two coordinates on grid planes).
  np.testing.assert_array_equal(refined_mesh.faces, plain_mesh.faces)
  g = (np.asarray(refined_mesh.vertices) + 1.0) / cell
  off_grid = np.abs(g - np.round(g)) > 1e-4
  assert (off_grid.sum(1) <= 1).all()
  moved = np.abs(np.asarray(refined_mesh.vertices) - np.asarray(plain_mesh.vertices)).max(1)
  assert (moved <= cell + 1e-9).all()


def test_exported_describes_the_grid_and_the_dropped_share():
  """What export and train print: the path and the grid's cell (finer detail is not in the mesh),
  with the share of the faces no camera sees when some were dropped (a user reading holes in the
  mesh finds why)."""
  assert export.Exported(Path("m.ply"), 0.0, 0.7039, "um").describe() == (
      "m.ply (grid cell 0.704 um)")
  assert export.Exported(Path("m.ply"), 0.0475, 2.25, "um").describe() == (
      "m.ply (grid cell 2.25 um; 4.8% of the faces, seen by no camera, dropped)")


def _poses(pixel_sizes, n_om=1):
  """A poses file's contents with WLI cameras of these pixel sizes and some OM cameras."""
  wli = [{"name": f"wli/{i}", "modality": "wli", "intrinsics": {"model": "orthographic",
          "pixel_size": [p, p]}} for i, p in enumerate(pixel_sizes)]
  om = [{"name": f"om/{i}", "modality": "om", "intrinsics": {"model": "pinhole"}}
        for i in range(n_om)]
  return {"cameras": wli + om}


def test_automatic_grid_has_cells_of_half_a_wli_pixel():
  box = ((-0.8, -0.6, -0.2), (0.8, 0.6, 0.3))  # normalised; longest side 1.6 = 400 um
  assert export.wli_pixel_um(_poses([1.0, 1.4, 2.0])) == 1.4  # the median scan's
  assert export.wli_pixel_um(_poses([])) is None
  res = export.grid_resolution(0, box, NORM, _poses([1.4]))
  assert res == int(np.ceil(400.0 / 0.7)) == 572
  assert 400.0 / res <= 0.7 < 400.0 / (res - 1)  # the coarsest grid whose cell is <= 0.5 px
  assert export.grid_resolution(96, box, NORM, None) == 96  # an explicit count needs no camera
  # A fine pixel over a wide box: capped (memory), the cell then coarser than half a pixel.
  assert export.grid_resolution(0, box, NORM, _poses([0.05])) == export.MAX_AUTO_RESOLUTION
  for poses in (None, _poses([])):
    with pytest.raises(UserError, match="--resolution N"):
      export.grid_resolution(0, box, NORM, poses)


def test_node_values_match_the_dense_grid():
  """The grid's values, made one chunk of nodes at a time, against all nodes at once in float64
  (a chunk that does not divide the node count, so the last one is partial)."""
  lo, spacing, shape = np.array([-1.0, -0.5, 0.2]), np.array([0.1, 0.05, 0.3]), (7, 5, 4)
  fn = lambda x: jnp.sin(3 * x[:, 0]) + x[:, 1] * x[:, 2]
  got = export.node_values(fn, lo, spacing, shape, np.arange(np.prod(shape)), chunk=9)
  axes = [lo[i] + np.arange(shape[i]) * spacing[i] for i in range(3)]
  x, y, z = np.meshgrid(*axes, indexing="ij")
  assert got.shape == (np.prod(shape),) and got.dtype == np.float32
  np.testing.assert_allclose(got.reshape(shape), np.sin(3 * x) + y * z, atol=1e-5)


def test_narrow_band_grid_gives_the_dense_grids_mesh():
  """Only blocks near the zero level are evaluated at every node; the mesh is the dense grid's,
  face for face, for an SDF that grows 1.8x as fast as the distance (BAND allows 2x; a trained
  one is near 1x), with two spheres, a plate under a quarter of a block thick, and a sphere of
  one cell's radius at a block's centre (the point farthest from its corners), on node counts
  no block size divides."""
  lo, hi = np.array([-1.0, -0.8, -0.7]), np.array([1.0, 0.8, 0.7])
  shape, spacing = export.grid_layout(lo, hi, 101)
  centre = jnp.asarray(lo + (4 * np.array([2, 2, 14]) + 2) * spacing)  # block (2, 2, 14)'s

  def sdf(x):
    spheres = jnp.minimum(jnp.linalg.norm(x - jnp.array([0.4, 0.0, 0.0]), axis=-1) - 0.3,
                          jnp.linalg.norm(x + jnp.array([0.45, 0.1, 0.0]), axis=-1) - 0.25)
    plate = jnp.abs(x[:, 2] + 0.5) - 0.02  # 0.04 thick: under a quarter of a block
    tiny = jnp.linalg.norm(x - centre, axis=-1) - spacing.max()
    return 1.8 * jnp.minimum(jnp.minimum(spheres, tiny),
                             jnp.maximum(plate, jnp.abs(x[:, 0]) - 0.6))

  dense, share_dense = export.sdf_grid(sdf, lo, spacing, shape, block=1)
  band, share = export.sdf_grid(sdf, lo, spacing, shape)
  assert share_dense == 1.0 and share < 0.5
  np.testing.assert_array_equal(np.sign(band), np.sign(dense))
  near = np.abs(dense) < 1.8 * np.linalg.norm(spacing)  # every node within a cell of the surface
  np.testing.assert_array_equal(band[near], dense[near])
  meshes = [measure.marching_cubes(v, 0.0, spacing=tuple(spacing)) for v in (dense, band)]
  np.testing.assert_array_equal(meshes[0][1], meshes[1][1])
  np.testing.assert_allclose(meshes[0][0], meshes[1][0], atol=1e-6)


def test_export_refuses_a_negative_or_tiny_resolution(tmp_path, capsys):
  """Checked before the run is read: one line naming the option, exit 2 (0 means automatic)."""
  for bad in ("-3", "5"):
    assert export.main([str(tmp_path / "no_run"), "--resolution", bad]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--resolution {bad}: use at least 8 cells" in err[0], err


def test_poses_of_the_training_keep_the_part_in_sight_and_others_are_refused(tmp_path):
  """A freshly initialised field (a sphere of radius 50 um) seen by one 64 um scan from above:
  the cap under the scan, 16% of the faces, in sight. Poses given for a run (the CLI) with so
  little in sight are not the run's: refused with one line naming the poses file. The poses the
  run was just trained with (train's own export) keep the faces in sight and report the rest as
  dropped; a surface none of their cameras sees is refused with a line naming the mesh and the
  run's export that keeps every face."""
  from test_visibility import _look_down, _poses  # a 64 x 64 scan of 1 um pixels

  from ofjax import fields
  from ofjax.config import Config, HashConfig

  cfg = Config(hash=HashConfig(n_levels=4, log2_table_size=10, base_resolution=4))
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  norm = scene_lib.Normalization(center=(0.0, 0.0, 0.0), scale=100.0)
  box = ((-0.7, -0.7, -0.7), (0.7, 0.7, 0.7))
  poses = _poses(("wli", _look_down(1000.0)))
  path = tmp_path / "mesh.ply"
  with pytest.raises(UserError, match=r"^given\.json: only [0-9]+% of the mesh's faces"):
    export.export_run(params, cfg, norm, box, path, 32, poses=poses, poses_path="given.json")
  assert not path.exists()
  run_dir = tmp_path / "run"
  exported = export.export_run(params, cfg, norm, box, path, 32, poses=poses, trained_in=run_dir)
  kept = trimesh.load(path, process=False)
  assert 1.0 - export.MIN_SEEN < exported.hidden < 1.0 and len(kept.faces) > 0
  # Only the cap under the scan: within its footprint and above the equator (the footprint's
  # corners reach down to it), each up to a face's reach.
  assert (kept.vertices[:, 2] > -2 * exported.cell).all()
  assert (np.abs(kept.vertices[:, :2]) <= 32.0 + 2 * exported.cell).all()
  aside = _look_down(1000.0)
  aside[0, 3] = 500.0  # the scan's field, 64 um wide, ends ~420 um beside the sphere
  with pytest.raises(UserError, match=r"^\S+off\.ply: none of the trained surface is in sight.*"
                     rf"`python -m ofjax\.export {re.escape(str(run_dir))} --keep-hidden`"):
    export.export_run(params, cfg, norm, box, tmp_path / "off.ply", 32,
                      poses=_poses(("wli", aside)), trained_in=run_dir)
  assert not (tmp_path / "off.ply").exists()
