"""Flat square test meshes shared by the metric and baseline tests."""

import numpy as np
import trimesh


def grid_plate(x0: float, x1: float, z: float, cells: int) -> trimesh.Trimesh:
  """The square [x0, x1]^2 at height z, split into cells^2 quads (two triangles each), facing +z."""
  g = np.linspace(x0, x1, cells + 1)
  gx, gy = np.meshgrid(g, g)
  verts = np.stack([gx, gy, np.full_like(gx, z)], -1).reshape(-1, 3)
  i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
  a = (i * (cells + 1) + j).ravel()
  faces = np.concatenate([np.stack([a, a + 1, a + cells + 2], -1),
                          np.stack([a, a + cells + 2, a + cells + 1], -1)])
  return trimesh.Trimesh(verts, faces, process=False)
