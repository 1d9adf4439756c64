"""Where step 2's similarity error comes from: the SfM points against the true surface.

Usage: python benchmarks/associate_points.py SCENE_DIR [SCENE_DIR ...]   (synthetic scenes)

For each scene it runs the association (ofjax.associate.pipeline.associate, as
`python -m ofjax.associate` does), then, with the generator's truth:
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
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ofjax import scene as scene_lib
from ofjax.associate import align, evaluate, ground
from ofjax.associate.pipeline import associate
from ofjax.meshquery import MeshQuery, load_mesh

FACE_CLASSES = (("level", 0.9, 1.01), ("sloped", 0.5, 0.9), ("steep", 0.0, 0.5))  # |n_z| ranges


def _error(S: np.ndarray, S_true: np.ndarray) -> str:
  """Scale %, turn about up (deg) and rotation angle (deg) of S against S_true."""
  d = align._rotation(S) @ align._rotation(S_true).T
  return (f"scale {100 * (align._scale_of(S) / align._scale_of(S_true) - 1):+.3f}% "
          f"turn {np.degrees(np.arctan2(d[1, 0], d[0, 0])):+.3f} "
          f"rot {evaluate.rotation_deg(d, np.eye(3)):.3f} deg")


def scene_row(d: Path) -> None:
  a = associate(scene_lib.load_scene(d, poses=False), scene_dir=str(d))
  reg, rec = a.wli, a.sfm
  truth = scene_lib.load_poses(d / "ground_truth" / "poses.json")
  size = float(np.linalg.norm(np.ptp(reg.points, axis=0)))
  # est_from_true: the inverse of the gauge ofjax.associate.evaluate fits over the WLI cameras
  G = np.linalg.inv(evaluate.gauge(scene_lib.poses_to_json(a.scene), truth, size))
  true_c2w = {c["name"]: np.asarray(c["c2w"]) for c in truth["cameras"]}
  names = sorted(rec.c2w)
  cams = {n: G @ true_c2w[scene_lib.camera_key("om", n)] for n in names}
  S_true = evaluate.fit_transform(np.array([rec.c2w[n][:3, 3] for n in names]),
                                  np.array([cams[n][:3, 3] for n in names]), True)
  print(f"{d.name}: step 2 against the true similarity: {_error(a.align.S, S_true)}")
  X = ground.triangulate(ground.tracks_of(rec.observations), cams, rec.K, len(rec.points))
  X = X[np.all(np.isfinite(X), axis=1)]  # the SfM points, exactly posed, in the um frame
  mesh = load_mesh(d / "ground_truth" / "mesh.ply")
  gt = MeshQuery(mesh.vertices @ G[:3, :3].T + G[:3, 3], mesh.faces)
  for label, pts in (("SfM tracks, true cameras", X), ("P_wli", reg.points)):
    r, normal = gt.signed_distance(pts)
    nz = np.abs(normal[:, 2])
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
