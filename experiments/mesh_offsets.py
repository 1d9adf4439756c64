"""Which side of the true surface a mesh's far vertices lie on.

`python experiments/mesh_offsets.py GT_MESH MESH [MESH ...] [--beyond 1.5]` prints, per mesh, the
share of its vertices farther than `--beyond` um from the true surface, how many of those lie
outside it (along the true surface's normal: above a substrate, off a flank) and their median
signed distance, and the median |n_z| of the true faces they are nearest to (1: a level face).
The accuracy heat maps of ofjax.eval show where a mesh is off; this says which way.

Names: `v` [N, 3] mesh vertices (um), `signed` [N] distance to the nearest true face along that
face's outward normal (um).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh

from ofjax.meshquery import MeshQuery, load_mesh

MAX_VERTICES = 40_000  # a random subset of each mesh (seed 0): enough for medians and shares


def signed_offsets(gt: trimesh.Trimesh, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(signed [N], |n_z| [N]) of points v [N, 3] against the nearest faces of gt."""
  near = MeshQuery.of(gt).closest(v)
  signed = np.einsum("ij,ij->i", v - near["points"], near["normal"])
  return signed, np.abs(near["normal"][:, 2])


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("gt", type=Path, help="the true surface (e.g. SCENE/ground_truth/mesh.ply)")
  p.add_argument("meshes", type=Path, nargs="+")
  p.add_argument("--beyond", type=float, default=1.5, help="um (default 1.5)")
  args = p.parse_args(argv)
  gt = load_mesh(args.gt)
  for path in args.meshes:
    v = np.asarray(load_mesh(path).vertices)
    v = v[np.random.default_rng(0).choice(len(v), min(MAX_VERTICES, len(v)), replace=False)]
    signed, nz = signed_offsets(gt, v)
    far = np.abs(signed) > args.beyond
    if not far.any():
      print(f"{path}: no vertex beyond {args.beyond} um; median signed {np.median(signed):+.3f} um")
      continue
    print(f"{path}: {100 * far.mean():.1f}% of vertices beyond {args.beyond} um, "
          f"{100 * np.mean(signed[far] > 0):.0f}% of them outside, median {np.median(signed[far]):+.2f}"
          f" um, nearest true faces' |n_z| median {np.median(nz[far]):.2f}; all vertices: median "
          f"{np.median(signed):+.3f} um")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
