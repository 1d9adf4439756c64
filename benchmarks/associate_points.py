"""Where step 2's similarity error comes from: the SfM points against the true surface.

Usage: python benchmarks/associate_points.py SCENE_DIR [SCENE_DIR ...]   (synthetic scenes)

For each scene it runs step 1 (WLI registration, SfM) and step 2 (the similarity,
ofjax.associate.align) as `python -m ofjax.associate` does, then, with the generator's truth:
- the error of step 2's similarity against the true one (the SfM camera centres fitted onto the
  true centres, in the association's frame): scale %, turn about up, rotation deg;
- every SfM track triangulated again with the *true* cameras (ofjax.associate.ground.triangulate)
  and P_wli, each as signed distances to the true mesh (+ outside), by the true face's |n_z|
  (level >= 0.9, sloped 0.5-0.9, steep < 0.5): median and median |distance|;
- step 2's polish (align._polish) of those true-camera points from the identity: how far the
  fit of exactly posed SfM points onto P_wli moves them (0 for an unbiased objective).
Nothing is written. It reads ground_truth/, so it is a benchmark, not part of the association.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ofjax import scene as scene_lib
from ofjax.associate import align, evaluate, ground, sfm, wli
from ofjax.associate.pipeline import stage_hint

FACE_CLASSES = (("level", 0.9, 1.01), ("sloped", 0.5, 0.9), ("steep", 0.0, 0.5))  # |n_z| ranges


def _scale(S: np.ndarray) -> float:
  return float(np.cbrt(np.linalg.det(S[:3, :3])))


def _error(S: np.ndarray, S_true: np.ndarray) -> str:
  """Scale %, turn about up (deg) and rotation angle (deg) of S against S_true."""
  d = (S[:3, :3] / _scale(S)) @ (S_true[:3, :3] / _scale(S_true)).T
  return (f"scale {100 * (_scale(S) / _scale(S_true) - 1):+.3f}% "
          f"turn {np.degrees(np.arctan2(d[1, 0], d[0, 0])):+.3f} "
          f"rot {evaluate.rotation_deg(d, np.eye(3)):.3f} deg")


def _to_mesh(points: np.ndarray, mesh: o3d.geometry.TriangleMesh):
  """Signed distances [N] of points [N, 3] to the mesh (+ outside) and |n_z| [N] of their face."""
  rs = o3d.t.geometry.RaycastingScene()
  rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
  ans = rs.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
  n = np.asarray(mesh.triangle_normals)[ans["primitive_ids"].numpy()]
  return np.einsum("ij,ij->i", n, points - ans["points"].numpy()), np.abs(n[:, 2])


def scene_row(d: Path) -> None:
  scene = scene_lib.load_scene(d, poses=False)
  reg = wli.register_scans(scene.wli, 0.2, str(d))
  with tempfile.TemporaryDirectory(prefix="ofjax-sfm-") as tmp:
    rec = sfm.run_sfm(scene.om, tmp, str(d))
  forward = np.array([c[:3, 2] for c in rec.c2w.values()])
  al = align.align_om_to_wli(rec.points, reg.points, reg.normals, reg.voxel_um, forward, 0.3,
                             str(d), turn_hint=stage_hint(scene.om, rec.c2w))
  truth = {c["name"]: np.asarray(c["c2w"])
           for c in scene_lib.load_poses(d / "ground_truth" / "poses.json")["cameras"]}
  size = float(np.linalg.norm(np.ptp(reg.points, axis=0)))
  # est_from_true gauge over the WLI cameras, as ofjax.associate.evaluate fits it
  G = evaluate.fit_transform(
      evaluate._pose_points([truth[f"wli/{s.name}"] for s in scene.wli], size),
      evaluate._pose_points(list(reg.c2w), size), with_scaling=False)
  names = sorted(rec.c2w)
  S_true = evaluate.fit_transform(np.array([rec.c2w[n][:3, 3] for n in names]),
                                  np.array([(G @ truth[f"om/{n}"])[:3, 3] for n in names]), True)
  print(f"{d.name}: step 2 against the true similarity: {_error(al.S, S_true)}")
  tracks: dict[int, list] = {}
  for name, (xy, idx) in rec.observations.items():
    for x, i in zip(xy, idx):
      tracks.setdefault(int(i), []).append((name, x))
  cams = {n: G @ truth[f"om/{n}"] for n in names}
  X = ground.triangulate(tracks, cams, rec.K, len(rec.points))
  X = X[np.all(np.isfinite(X), axis=1)]  # the SfM points, exactly posed, in the um frame
  mesh = o3d.io.read_triangle_mesh(str(d / "ground_truth" / "mesh.ply"))
  mesh.transform(G)
  mesh.compute_triangle_normals()
  for label, pts in (("SfM tracks, true cameras", X), ("P_wli", reg.points)):
    r, nz = _to_mesh(pts, mesh)
    cells = []
    for face, lo, hi in FACE_CLASSES:
      m = (nz >= lo) & (nz < hi)
      cells.append(f"{face} {m.sum()}: {np.median(r[m]) if m.any() else np.nan:+.3f} "
                   f"(|.| {np.median(np.abs(r[m])) if m.any() else np.nan:.3f})")
    print(f"  {label:25s} signed um to the truth by face, n: median (|median|): "
          + "; ".join(cells))
  hm = align.HeightMap(reg.points, align.FINE_CELL_VOXELS * reg.voxel_um)
  P = align._polish(X, np.eye(4), reg.points, reg.normals, cKDTree(reg.points), hm, reg.voxel_um)
  print(f"  polish of the true-camera points from the identity: {_error(P, np.eye(4))}",
        flush=True)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("scenes", type=Path, nargs="+", metavar="SCENE_DIR")
  for d in p.parse_args(argv).scenes:
    scene_row(d)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
