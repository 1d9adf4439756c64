"""Triangle meshes for analysis: loading them, and ray casts / closest-point queries on them.

Names:
  vertices  [V, 3] float64 um.      faces  [F, 3] int, counter-clockwise seen from outside.
  bary      [N, 3] barycentric weights of a point in its face's vertices (v0, v1, v2).
  t         distance along a unit ray direction (um); inf where the ray misses the mesh.

The queries run on open3d's RaycastingScene, which computes in float32. Micrometre meshes can sit
far from the origin (a stage position of 1e4 um leaves ~1e-3 um of float32 resolution), so a
`MeshQuery` shifts everything by the mesh's bounding-box centre: the float32 error then scales with
the mesh's size, not its position.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from ofjax.errors import UserError

RAY_CLEARANCE = 1.0  # um: rays cast from outside a mesh start this far beyond its extent


def load_mesh(path: str | Path) -> trimesh.Trimesh:
  """Reads a triangle mesh (PLY/OBJ/GLB/...) in um, keeping its vertex order and colours."""
  path = Path(path)
  if not path.is_file():
    raise UserError(f"{path}: mesh file not found; check the path")
  try:
    mesh = trimesh.load(path, force="mesh", process=False)
  except Exception as e:  # noqa: BLE001 - trimesh raises many kinds on corrupt or foreign files
    raise UserError(f"{path}: cannot read the mesh ({type(e).__name__}: {e}); pass a PLY, OBJ or "
                    "GLB triangle mesh") from None
  if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
    raise UserError(f"{path}: holds no triangles; pass a triangle mesh (not a point cloud)")
  if not np.all(np.isfinite(mesh.vertices)):
    raise UserError(f"{path}: has non-finite vertex coordinates; re-export the mesh")
  return mesh


def vertex_rgb(mesh: trimesh.Trimesh) -> np.ndarray | None:
  """[V, 3] float64 RGB in [0, 1] of the mesh's vertex colours, or None when it has none."""
  if mesh.visual.kind != "vertex":
    return None
  return np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3] / 255.0


def barycentric(uv: np.ndarray) -> np.ndarray:
  """[N, 3] weights from open3d's [N, 2] primitive_uvs, which weight vertices 1 and 2:
  p = (1 - u - v) v0 + u v1 + v v2."""
  uv = np.asarray(uv, np.float64)
  return np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)


class MeshQuery:
  """Ray casts and closest points on one triangle mesh (um)."""

  def __init__(self, vertices: np.ndarray, faces: np.ndarray, shift: np.ndarray | None = None):
    """vertices: [V, 3] um; faces: [F, 3] vertex indices; shift: [3] um subtracted from every
    coordinate before the float32 casts, the bounding-box centre when None."""
    vertices = np.asarray(vertices, np.float64)
    self.faces = np.asarray(faces, np.int64)
    self.shift = (vertices.min(0) + vertices.max(0)) / 2 if shift is None else np.asarray(
        shift, np.float64)
    self.scene = o3d.t.geometry.RaycastingScene()
    self.scene.add_triangles(o3d.core.Tensor((vertices - self.shift).astype(np.float32)),
                             o3d.core.Tensor(self.faces.astype(np.uint32)))

  @classmethod
  def of(cls, mesh: trimesh.Trimesh) -> "MeshQuery":
    return cls(mesh.vertices, mesh.faces)

  def cast(self, origins: np.ndarray, dirs: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits of rays.

    Args:
      origins: [N, 3] um.
      dirs: [N, 3] unit directions.
    Returns:
      t: [N] float64 um to the first hit, inf where the ray misses.
      face: [N] int64 index of the hit face, -1 where the ray misses.
      bary: [N, 3] barycentric weights of the hit point in that face.
    """
    rays = np.concatenate([np.asarray(origins, np.float64) - self.shift,
                           np.asarray(dirs, np.float64)], -1).astype(np.float32)
    hit = self.scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    face = hit["primitive_ids"].numpy().astype(np.int64)
    face[~np.isfinite(t)] = -1
    return t, face, barycentric(hit["primitive_uvs"].numpy())

  def closest(self, points: np.ndarray) -> dict[str, np.ndarray]:
    """The nearest surface point of every query point.

    Args:
      points: [N, 3] um.
    Returns a dict of
      points: [N, 3] um, the nearest point on the mesh;
      distance: [N] um, unsigned distance to it;
      face: [N] int64, the face it lies on;
      bary: [N, 3] its barycentric weights in that face;
      normal: [N, 3] the face's unit normal (from its winding).
    """
    q = np.asarray(points, np.float64) - self.shift
    r = self.scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
    near = r["points"].numpy().astype(np.float64)
    return {"points": near + self.shift, "distance": np.linalg.norm(near - q, axis=-1),
            "face": r["primitive_ids"].numpy().astype(np.int64),
            "bary": barycentric(r["primitive_uvs"].numpy()),
            "normal": r["primitive_normals"].numpy().astype(np.float64)}

  def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances to the mesh along the nearest face's normal.

    Args:
      points: [N, 3] um.
    Returns:
      signed: [N] um, + on the side the nearest face's normal points to (outside a closed mesh
        wound outward).
      normal: [N, 3] that face's unit normal.
    """
    near = self.closest(points)
    return np.einsum("ij,ij->i", np.asarray(points, np.float64) - near["points"],
                     near["normal"]), near["normal"]

  def clear(self, origins: np.ndarray, points: np.ndarray, rel_slack: float = 0.0,
            abs_slack: float = 0.0) -> np.ndarray:
    """[N] bool: nothing of the mesh lies between each origin and its point (a line of sight).

    The ray from the origin towards the point may meet the mesh first at distance t; the sight is
    clear when t >= dist * (1 - rel_slack) - abs_slack, dist = |point - origin| (the slacks let a
    point on the mesh see past its own face despite float32 ray casts), and when it meets nothing.

    Args:
      origins: [N, 3] or [3] um, e.g. a camera centre.
      points: [N, 3] um.
    """
    ray = np.asarray(points, np.float64) - origins
    dist = np.linalg.norm(ray, axis=-1)
    t, _, _ = self.cast(np.broadcast_to(origins, ray.shape), ray / dist[:, None])
    return t >= dist * (1 - rel_slack) - abs_slack

  def interpolate(self, values: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """[N, C] per-vertex `values` [V, C] interpolated at points given by `face` [N], `bary` [N, 3]."""
    return np.einsum("nk,nkc->nc", bary, np.asarray(values)[self.faces[face]])
