"""Which faces of a mesh some camera of the scene can see; the exported surfaces keep only those.

A neural SDF is unconstrained where no ray reaches: inside a solid part (a pillar, a seed) it may
turn positive and leave closed pockets and tunnels whose walls marching cubes extracts with the
outer surface. No WLI scan or OM photo could have measured them, yet they enter every cross-section,
volume and mesh -> truth distance. A screened Poisson surface can hold such pockets too. A face is
kept when a point just in front of it (its centre moved SIGHT_OFFSET along its outward normal)
lies inside some camera's frame with a clear line of sight to it: towards the centre of an OM
photo's pinhole, or against the axis of an orthographic WLI scan. The offset keeps the walls a
scan sees edge-on: a ray down a vertical wall would graze the rim above it.

Cameras come as a poses file's contents (`ofjax.scene.poses_to_json`: per camera its modality,
width, height, intrinsics and c2w in um), the file every run directory keeps beside config.json.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

from ofjax import scene as scn
from ofjax.meshquery import MeshQuery

# How far in front of a face its line of sight starts, as a share of the mesh's bounding-box
# diagonal: 0.48 um on a 480 um scene, a quarter of a marching-cubes cell at 192^3 there (so past
# the cell-scale ripples of a steep wall) and well below the pockets' depth (microns).
SIGHT_OFFSET = 1e-3
# Slack for float32 ray casting at the sight's end, as a share of the diagonal (0.05 um there).
SIGHT_SLACK = 1e-4
# Beyond this many mesh diagonals an orthographic scan's ray starts: outside everything.
ORTHO_REACH = 2.0


def seen_faces(mesh: trimesh.Trimesh, poses: dict[str, Any]) -> np.ndarray:
  """[F] bool: the point just in front of the face is inside some camera's frame and nothing of
  the mesh occludes it.

  Args:
    mesh: the surface, in the poses' units (um), its faces' normals pointing out of the solid.
    poses: a poses file's contents (`ofjax.scene.poses_to_json`).
  """
  seen = np.zeros(len(mesh.faces), bool)
  if len(seen) == 0:
    return seen
  diagonal = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
  centres = (np.asarray(mesh.triangles_center, np.float64)
             + SIGHT_OFFSET * diagonal * np.asarray(mesh.face_normals, np.float64))
  query = MeshQuery.of(mesh)
  for cam in poses["cameras"]:
    todo = np.flatnonzero(~seen)
    if len(todo) == 0:
      break
    c2w, shape, intr = np.asarray(cam["c2w"], np.float64), (cam["height"], cam["width"]), \
        cam["intrinsics"]
    if intr["model"] == "orthographic":
      todo = todo[scn.project_orthographic(centres[todo], c2w, tuple(intr["pixel_size"]), shape)[3]]
      axis = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
      origins = centres[todo] - ORTHO_REACH * diagonal * axis
    else:
      todo = todo[scn.project_pinhole(centres[todo], scn.K_from_json(intr), c2w, shape)[2]]
      origins = c2w[:3, 3]
    seen[todo[query.clear(origins, centres[todo], abs_slack=SIGHT_SLACK * diagonal)]] = True
  return seen


def drop_hidden(mesh: trimesh.Trimesh, poses: dict[str, Any]) -> tuple[trimesh.Trimesh, float]:
  """The mesh without the faces no camera sees (`seen_faces`), vertex colours kept, and the share
  of the faces that were seen."""
  seen = seen_faces(mesh, poses)
  if seen.all():
    return mesh, 1.0
  out = mesh.copy()
  out.update_faces(seen)
  out.remove_unreferenced_vertices()
  return out, float(seen.mean())
