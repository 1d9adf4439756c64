"""The export's SDF grid made in a narrow band against every node evaluated, on trained runs.

For each run directory: the grid `ofjax.export` would use (`--resolution`, default 0: cells of
half a WLI pixel), made by `export.sdf_grid` with its narrow band and with every node evaluated
(block 1), timed; then marching cubes on both. The table says the SDF evaluations per node, the
seconds of each, whether every node has the same sign, and whether the two meshes have the same
faces (they must: the band only skips blocks that hold no surface).

  python benchmarks/export_grid.py RUN_DIR [RUN_DIR ...] [--resolution N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from skimage import measure

from ofjax import export, fields, machine
from ofjax import scene as scene_lib
from ofjax.errors import cli


def compare(run_dir: Path, resolution: int) -> dict:
  """Both grids of one run, timed, and their marching-cubes faces compared."""
  run = export.load_run(run_dir)
  poses = scene_lib.load_poses(export.run_poses(run_dir, None, run.poses_named,
                                                "--resolution N"))
  res = export.grid_resolution(resolution, run.box, run.norm, poses)
  lo = np.asarray(run.box[0], np.float64)
  shape, spacing = export.grid_layout(lo, run.box[1], res)
  sdf = export.field_function(fields.sdf_value, run.params, run.cfg)
  sdf(np.zeros((export.CHUNK, 3), np.float32)).block_until_ready()  # compile outside the timing
  t0 = time.perf_counter()
  band, evaluations = export.sdf_grid(sdf, lo, spacing, shape)
  band_s = time.perf_counter() - t0
  t0 = time.perf_counter()
  dense, _ = export.sdf_grid(sdf, lo, spacing, shape, block=1)
  dense_s = time.perf_counter() - t0
  faces = [measure.marching_cubes(v, 0.0)[1] for v in (band, dense)]
  return {"run": str(run_dir), "shape": list(shape), "nodes": int(np.prod(shape)),
          "evaluations_per_node": evaluations, "band_s": band_s, "every_node_s": dense_s,
          "sign_differences": int((np.sign(band) != np.sign(dense)).sum()),
          "faces": [len(f) for f in faces],
          "same_faces": faces[0].shape == faces[1].shape and bool((faces[0] == faces[1]).all())}


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python benchmarks/export_grid.py", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("runs", nargs="+", help="run directories written by python -m ofjax.train")
  p.add_argument("--resolution", type=int, default=0,
                 help="cells along the box's longest side (0: half a WLI pixel)")
  p.add_argument("--json", action="store_true", help="one JSON object per run instead of a table")
  args = p.parse_args(argv)
  print(f"# {machine.line(machine.describe())}; block {export.BLOCK}, band {export.BAND} "
        f"diagonals, {export.CHUNK} points per call")
  if not args.json:
    print("| run | grid | nodes | evaluations per node | band s | every node s | sign differences "
          "| faces (band, every node) | same faces |\n|---|---|---|---|---|---|---|---|---|")
  for run_dir in args.runs:
    r = compare(Path(run_dir), args.resolution)
    if args.json:
      print(json.dumps(r), flush=True)
    else:
      grid = " x ".join(map(str, r["shape"]))
      print(f"| {Path(r['run']).name} | {grid} | {r['nodes'] / 1e6:.1f} M "
            f"| {r['evaluations_per_node']:.3f} | {r['band_s']:.1f} | {r['every_node_s']:.1f} | "
            f"{r['sign_differences']} | {r['faces'][0]:,}, {r['faces'][1]:,} | {r['same_faces']} |",
            flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())
