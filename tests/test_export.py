"""Mesh export: an analytic sphere SDF comes out as a sphere in um with the colour function's colours."""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import trimesh

from ofjax import export, meshfile
from ofjax import scene as scene_lib

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
  grid_calls = -(-np.prod(export.grid_shape(*args)) // export.CHUNK)
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


def test_exported_describes_the_dropped_share():
  """What export and train print: the path alone when every face was kept, else with the share
  of the faces no camera sees (a user reading holes in the mesh finds why)."""
  assert export.Exported(Path("m.ply"), 0.0).describe() == "m.ply"
  assert export.Exported(Path("m.ply"), 0.0475).describe() == (
      "m.ply (4.8% of the faces, seen by no camera, dropped)")
