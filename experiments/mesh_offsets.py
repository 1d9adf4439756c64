"""Which side of the true surface a mesh's far vertices lie on, and whether the data saw them.

`python experiments/mesh_offsets.py SCENE MESH [MESH ...] [--beyond 1.5] [--cameras]` prints, per
mesh (in the truth's frame), the share of its vertices in the evaluated region (where ofjax.eval
judges accuracy, `ofjax.metrics.evaluated_region`) farther than `--beyond` um from the true surface
(SCENE/ground_truth/mesh.ply), how many of those lie outside it (along the true surface's normal:
above a substrate, off a flank) and their median signed distance, and the median |n_z| of the true
faces they are nearest to (1: a level face). The accuracy heat maps of ofjax.eval show where a mesh
is off; this says which way.

`--cameras` also says whether the data could have removed the far vertices outside the truth
(those inside it are hidden from every camera by the true surface in front of them, which the
cameras do see): per such vertex, the number of OM cameras and of WLI scans of
SCENE/ground_truth/poses.json that see it through free space in the true scene (it projects into
the image, and the line of sight from the camera - for a WLI scan, along its axis from above -
meets no true surface before it). A vertex that no camera sees through free space lies in space no
instrument observed (an undercut, a wedge under an overhang): every surface through it is a
guess. A WLI scan that sees it may still have a void there (a steep or specular surface behind
it); the OM photos see it in colour whatever the slope.

Names: `v` [N, 3] mesh vertices (um), `signed` [N] distance to the nearest true face along that
face's outward normal (um), `c2w` [4, 4] camera-to-world (OpenCV axes, ofjax/cameras.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ofjax import metrics
from ofjax.eval import load_ground_truth
from ofjax.meshquery import MeshQuery, load_mesh
from ofjax.scene import K_from_json, load_poses, project_orthographic, project_pinhole

MAX_VERTICES = 40_000  # a random subset of each mesh (seed 0): enough for medians and shares
# A line of sight counts as blocked when it meets the true surface this far (um) before the vertex:
# above the float32 ray-cast error at the scenes' ~1,000 um distances, below the 1.5 um the far
# vertices are off by, so the true surface a far vertex hovers over does not block its own view.
OCCLUSION_TOL_UM = 0.5
# WLI lines of sight start this far (um) above the vertex along the scan's axis: beyond any sample.
WLI_STANDOFF_UM = 1.0e4


def seen_by(gt: MeshQuery, v: np.ndarray, camera: dict) -> np.ndarray:
  """[N] bool: which points v [N, 3] (um) `camera` (a poses.json entry) sees through free space."""
  c2w = np.asarray(camera["c2w"], np.float64)
  shape = (camera["height"], camera["width"])
  if camera["intrinsics"]["model"] == "orthographic":
    *_, inside = project_orthographic(v, c2w, camera["intrinsics"]["pixel_size"], shape)
    origins = v - WLI_STANDOFF_UM * c2w[:3, 2]
  else:
    _, _, inside = project_pinhole(v, K_from_json(camera["intrinsics"]), c2w, shape)
    origins = c2w[:3, 3]
  return inside & gt.clear(origins, v, abs_slack=OCCLUSION_TOL_UM)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("scene", type=Path, help="a synthetic scene (its ground_truth/ is read)")
  p.add_argument("meshes", type=Path, nargs="+", help="meshes in the truth's frame")
  p.add_argument("--beyond", type=float, default=1.5, help="um (default 1.5)")
  p.add_argument("--cameras", action="store_true",
                 help="count the true cameras that see each far vertex outside the truth through "
                      "free space")
  args = p.parse_args(argv)
  truth, _ = load_ground_truth(args.scene)
  gt = MeshQuery.of(truth.mesh)  # one ray-casting scene for every mesh and camera
  cameras = load_poses(args.scene / "ground_truth" / "poses.json")["cameras"] if args.cameras else []
  for path in args.meshes:
    v = np.asarray(load_mesh(path).vertices)
    v = v[metrics.evaluated_region(v, truth.points, metrics.CROP_MARGIN * truth.diagonal)]
    v = v[np.random.default_rng(0).choice(len(v), min(MAX_VERTICES, len(v)), replace=False)]
    signed, normal = gt.signed_distance(v)
    nz = np.abs(normal[:, 2])
    far = np.abs(signed) > args.beyond
    if not far.any():
      print(f"{path}: no vertex beyond {args.beyond} um; median signed {np.median(signed):+.3f} um")
      continue
    print(f"{path}: {100 * far.mean():.1f}% of vertices beyond {args.beyond} um, "
          f"{100 * np.mean(signed[far] > 0):.0f}% of them outside, median {np.median(signed[far]):+.2f}"
          f" um, nearest true faces' |n_z| median {np.median(nz[far]):.2f}; all vertices: median "
          f"{np.median(signed):+.3f} um")
    outside = signed > args.beyond
    for modality in ("om", "wli") if cameras and outside.any() else ():
      views = [seen_by(gt, v[outside], c) for c in cameras if c["modality"] == modality]
      count = np.sum(views, axis=0)
      print(f"  far vertices outside the truth seen through free space by {modality.upper()} "
            f"cameras ({len(views)}): {100 * np.mean(count > 0):.1f}% by at least one, median "
            f"{np.median(count):.0f}")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
