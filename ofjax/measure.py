"""`python -m ofjax.measure`: roughness of a region and cross-section profiles of a mesh in um.

  roughness --mesh MESH --region X0,Y0,X1,Y1 [--grid N] [--json] [--out PNG]
      levels the region by a least-squares plane, samples heights perpendicular to it by ray
      casting (ofjax.metrology), prints Sa Sq Sp Sv Sz Ssk Sku (um; Ssk, Sku dimensionless) and
      writes a PNG height map (default MESH_DIR/<mesh>_roughness.png).
  profile --mesh MESH --from X,Y --to X,Y [--n N] [--out CSV]
      writes the topmost surface's height along the line as CSV (distance_um,x_um,y_um,z_um; z is
      nan where the line leaves the mesh) and a PNG plot beside it (default MESH_DIR/<mesh>_profile).
Coordinates are in um in the mesh's own frame. Write values that start with a minus sign with
"=", e.g. --region=-50,-50,50,50 (argparse would read "-50,..." as an option).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from ofjax import fileio, metrics, metrology, plots
from ofjax.errors import UserError, cli
from ofjax.meshquery import MeshQuery, load_mesh

MAX_MISSING_FRACTION = 0.5  # a region more than half off the mesh has no meaningful roughness


def parse_numbers(text: str, count: int, option: str, what: str) -> tuple[float, ...]:
  try:
    values = tuple(float(v) for v in text.split(","))
  except ValueError:
    values = ()
  if len(values) != count or not all(math.isfinite(v) for v in values):
    raise UserError(f"{option} {text!r}: expected {what} ({count} comma-separated numbers in um)")
  return values


def parse_region(text: str) -> tuple[float, float, float, float]:
  x0, y0, x1, y1 = parse_numbers(text, 4, "--region", "X0,Y0,X1,Y1")
  if not (x1 > x0 and y1 > y0):
    raise UserError(f"--region {text!r}: needs X1 > X0 and Y1 > Y0 (the rectangle's corners in um)")
  return x0, y0, x1, y1


def default_output(mesh_path: Path, suffix: str) -> Path:
  return mesh_path.with_name(f"{mesh_path.stem}_{suffix}")


def roughness(args: argparse.Namespace) -> int:
  region = parse_region(args.region)
  if args.grid < 2:
    raise UserError(f"--grid {args.grid}: needs at least 2 samples along the region's longer side")
  mesh = load_mesh(args.mesh)
  lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
  bounds = f"x {lo[0]:.6g}..{hi[0]:.6g}, y {lo[1]:.6g}..{hi[1]:.6g} um"
  try:
    grid = metrology.sample_region(mesh.vertices, mesh.faces, region, n=args.grid)
  except ValueError:
    raise UserError(f"--region {args.region!r}: the mesh has no surface there (its extent is "
                    f"{bounds}); choose a region inside it") from None
  n_missing = int(np.isnan(grid.z).sum())
  if n_missing > MAX_MISSING_FRACTION * grid.z.size:
    raise UserError(f"--region {args.region!r}: {n_missing} of {grid.z.size} samples miss the mesh "
                    f"(its extent is {bounds}); choose a region inside it")
  params = metrology.areal_parameters(grid.z)
  png = Path(args.out) if args.out else default_output(Path(args.mesh), "roughness.png")
  plots.height_map(png, grid.z, grid.extent,
                   f"{Path(args.mesh).name}: levelled heights, Sa {params['Sa']:.4g} um, "
                   f"Sq {params['Sq']:.4g} um", axis_names=("u", "v"))
  meta = {"region_um": list(region), "grid": list(grid.z.shape), "step_um": grid.step,
          "n_samples": int(grid.z.size - n_missing), "n_missing": n_missing,
          "tilt_deg": grid.tilt_deg, "units": "um", "mesh": str(args.mesh), "png": str(png)}
  if args.json:
    print(json.dumps(metrics.json_ready({**params, **meta})))  # a flat region's Ssk, Sku: null
  else:
    for k in metrology.PARAMETERS:
      unit = "" if k in ("Ssk", "Sku") else " um"
      print(f"{k:4s} {params[k]:12.6g}{unit}")
    print(f"{meta['n_samples']} samples, step {grid.step:.4g} um, plane tilt "
          f"{grid.tilt_deg:.3g} deg; height map: {png}")
  if n_missing:
    print(f"ofjax: warning: {n_missing} samples missed the mesh and were left out", file=sys.stderr)
  return 0


def profile(args: argparse.Namespace) -> int:
  start = parse_numbers(args.start, 2, "--from", "X,Y")
  end = parse_numbers(args.end, 2, "--to", "X,Y")
  if start == end:
    raise UserError("--from and --to are the same point; give the line's two different ends")
  if args.n < 2:
    raise UserError(f"--n {args.n}: needs at least 2 samples")
  mesh = load_mesh(args.mesh)
  s, xyz = metrology.profile(mesh.vertices, mesh.faces, start, end, n=args.n,
                             query=MeshQuery.of(mesh))
  if np.isnan(xyz[:, 2]).all():
    raise UserError(f"--from {args.start} --to {args.end}: the line never crosses the mesh; pick "
                    "ends within the mesh's XY extent")
  csv = Path(args.out) if args.out else default_output(Path(args.mesh), "profile.csv")
  rows = "\n".join(f"{d:.6f},{x:.6f},{y:.6f},{z:.6f}" for d, (x, y, z) in zip(s, xyz))
  fileio.write_text(csv, "distance_um,x_um,y_um,z_um\n" + rows + "\n")
  png = plots.line_plot(csv.with_suffix(".png"), s, {"height": xyz[:, 2]},
                        f"{Path(args.mesh).name}: ({start[0]:g}, {start[1]:g}) -> "
                        f"({end[0]:g}, {end[1]:g}) um", "distance along the line (um)",
                        "z (um)")
  ok = np.isfinite(xyz[:, 2])
  print(f"profile: {args.n} samples over {s[-1]:.6g} um, z {np.nanmin(xyz[:, 2]):.6g} .. "
        f"{np.nanmax(xyz[:, 2]):.6g} um ({int((~ok).sum())} off the mesh); wrote {csv} and {png}")
  return 0


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m ofjax.measure", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  sub = p.add_subparsers(dest="command", required=True)
  r = sub.add_parser("roughness", help="ISO 25178-2 height parameters of a region")
  r.add_argument("--mesh", required=True, help="mesh file in um (PLY/OBJ/GLB)")
  r.add_argument("--region", required=True, help="X0,Y0,X1,Y1: the rectangle in um")
  r.add_argument("--grid", type=int, default=256, help="samples along the longer side (256)")
  r.add_argument("--json", action="store_true", help="print one JSON object")
  r.add_argument("--out", help="height-map PNG (default MESH_DIR/<mesh>_roughness.png)")
  r.set_defaults(run=roughness)
  q = sub.add_parser("profile", help="cross-section along a line, as CSV and PNG")
  q.add_argument("--mesh", required=True, help="mesh file in um (PLY/OBJ/GLB)")
  q.add_argument("--from", dest="start", required=True, help="X,Y: the line's start in um")
  q.add_argument("--to", dest="end", required=True, help="X,Y: the line's end in um")
  q.add_argument("--n", type=int, default=512, help="samples along the line (512)")
  q.add_argument("--out", help="CSV path (default MESH_DIR/<mesh>_profile.csv); PNG beside it")
  q.set_defaults(run=profile)
  return p


@cli
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  return args.run(args)


if __name__ == "__main__":
  sys.exit(main())
