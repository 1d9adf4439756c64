"""How far, and on which side, meshes lie from the truth where no WLI scan measured it.

`python experiments/blind_profile.py SCENE LABEL=MESH [LABEL=MESH ...] [--bands 0,45,60,70,80,90]`
prints a Markdown table over the WLI-blind GT points of a synthetic scene (`ofjax.eval`: no
measured point of any scan within one WLI pixel, true poses), split by the true surface's slope:
per band its share of the blind points and their mean height, and per mesh the mean distance to it
and the mean signed distance. The meshes must be in the truth's frame (runs on the true poses).

Names: `p` [N, 3] blind GT points (um), `n` [N, 3] their true outward normals, `q` [N, 3] the
nearest point of a mesh, `signed` [N] = (p - q) . n: positive when the mesh lies inside the true
surface (under it, or behind a flank), negative when it lies outside.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ofjax import eval as evaluation  # noqa: E402
from ofjax.errors import UserError, cli  # noqa: E402
from ofjax.meshquery import MeshQuery, load_mesh  # noqa: E402

BANDS_DEG = (0.0, 45.0, 60.0, 70.0, 80.0, 90.0)  # slope band edges of the table


def slope_deg(normals: np.ndarray) -> np.ndarray:
  """[N] angle between each unit normal [N, 3] and the vertical, in degrees (0: level)."""
  return np.degrees(np.arccos(np.clip(np.abs(normals[:, 2]), 0.0, 1.0)))


def signed_to(mesh_query: MeshQuery, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
  """[N] signed distance (um) from each true point to a mesh along its true normal (module doc)."""
  q = mesh_query.closest(points)["points"]
  return np.einsum("ij,ij->i", points - q, normals)


def profile(points: np.ndarray, normals: np.ndarray, signed: dict[str, np.ndarray],
            bands=BANDS_DEG) -> list[dict]:
  """Rows per slope band: share of the points, their mean height, each mesh's mean |d| and d.

  Args:
    points: [N, 3] blind GT points (um); normals: [N, 3] their true unit normals.
    signed: label -> [N] signed distances of a mesh (`signed_to`).
  """
  slope = slope_deg(normals)
  rows = []
  for lo, hi in zip(bands[:-1], bands[1:]):
    sel = (slope >= lo) & ((slope < hi) if hi < bands[-1] else (slope <= hi))
    if sel.any():
      rows.append({"band": (lo, hi), "share": float(sel.mean()),
                   "height_um": float(points[sel, 2].mean()),
                   **{k: (float(np.abs(d[sel]).mean()), float(d[sel].mean()))
                      for k, d in signed.items()}})
  return rows


def table(rows: list[dict], labels: list[str]) -> str:
  lines = ["| slope deg | share of the blind points | mean height um | "
           + " | ".join(f"{k}: mean / signed um" for k in labels) + " |",
           "|---" * (3 + len(labels)) + "|"]
  for r in rows:
    lo, hi = r["band"]
    lines.append(f"| {lo:g}-{hi:g} | {r['share']:.3f} | {r['height_um']:.1f} | "
                 + " | ".join(f"{r[k][0]:.2f} / {r[k][1]:+.2f}" for k in labels) + " |")
  return "\n".join(lines)


def parse_args(argv):
  p = argparse.ArgumentParser(prog="python experiments/blind_profile.py",
                              description=__doc__.splitlines()[0])
  p.add_argument("scene", type=Path, help="synthetic scene directory (native bundle)")
  p.add_argument("meshes", nargs="+", help="LABEL=MESH, in the truth's frame")
  p.add_argument("--bands", default=",".join(f"{b:g}" for b in BANDS_DEG),
                 help="slope band edges in degrees (default %(default)s)")
  return p.parse_args(argv)


@cli
def main(argv=None) -> int:
  args = parse_args(argv)
  try:
    bands = tuple(float(b) for b in args.bands.split(","))
  except ValueError:
    bands = ()
  if len(bands) < 2 or list(bands) != sorted(bands) or bands[0] < 0 or bands[-1] > 90:
    raise UserError(f"--bands {args.bands!r}: give increasing degrees in [0, 90], e.g. 0,45,90")
  pairs = [m.split("=", 1) if "=" in m else (Path(m).stem, m) for m in args.meshes]
  gt, _ = evaluation.load_ground_truth(args.scene)
  if gt.wli_scans is None or gt.normals is None:
    raise UserError(f"{args.scene}: needs a native bundle (scene.json) with true poses and normals "
                    "in ground_truth/; make it with `python -m ofjax.synth`")
  blind = gt.wli_scans == 0
  if not blind.any():
    print(f"{args.scene}: some WLI scan measured every GT point; nothing to profile")
    return 0
  p, n = gt.points[blind], gt.normals[blind]
  signed = {label: signed_to(MeshQuery.of(load_mesh(path)), p, n) for label, path in pairs}
  print(f"{args.scene}: {blind.sum()} of {len(blind)} GT points ({100 * blind.mean():.1f}%) no WLI "
        "scan measured; signed > 0: the mesh lies inside the true surface")
  print(table(profile(p, n, signed, bands), [label for label, _ in pairs]))
  return 0


if __name__ == "__main__":
  sys.exit(main())
