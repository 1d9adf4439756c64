"""Association accuracy and time on the synthetic scenes: prints one table row per scene.

Usage: python benchmarks/associate.py [--scenes seed circuit ...] [--resolution quick] [--out DIR]
       python benchmarks/associate.py --score SCENE_DIR [SCENE_DIR ...]
Each scene is generated with ofjax.synth, associated with `python -m ofjax.associate`, and its
poses compared with ground_truth/poses.json after the rigid gauge fit (ofjax.associate.evaluate);
`--score` only compares the poses.json already in synthetic scene directories (e.g. those of
experiments/ablation.py). Targets (issue 5): WLI <= 0.05 deg and <= 0.5 px; OM 37/37, <= 0.2 deg,
centre <= 0.5% of the scene size, scale <= 0.5%. `sim deg` is the rotation of the best similarity
of the OM camera centres onto the true ones (scale% is its scale), `left%` the largest centre
error after it, and `along um` the median centre error along the true optical axis: what the OM
block shares against what each camera has on its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ofjax import synth
from ofjax.associate import evaluate
from ofjax.associate.__main__ import main as associate_main


def run(name: str, resolution: str, out: Path) -> dict:
  d = out / f"{name}-{resolution}"
  if not (d / "scene.json").exists():
    synth.main(["--scene", name, "--out", str(d), "--resolution", resolution])
  t0 = time.perf_counter()
  rc = associate_main([str(d), "--report"])
  seconds = time.perf_counter() - t0
  if rc != 0:
    return {"scene": name, "rc": rc, "seconds": seconds}
  return {"scene": name, "rc": rc, "seconds": seconds, **evaluate.scene_pose_errors(d)}


def score(scene_dir: Path) -> dict:
  """run()'s row for a scene directory associated before (its seconds: NaN)."""
  return {"scene": scene_dir.name, "rc": 0, "seconds": float("nan"),
          **evaluate.scene_pose_errors(scene_dir)}


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--scenes", nargs="+", default=["seed"])
  p.add_argument("--resolution", default="quick")
  p.add_argument("--out", type=Path, default=Path("runs/bench_associate"))
  p.add_argument("--score", type=Path, nargs="+", metavar="SCENE_DIR",
                 help="score these associated synthetic scenes instead of running (no json written)")
  args = p.parse_args(argv)
  print(f"{'scene':10s} {'WLI deg':>8s} {'WLI px':>7s} {'OM reg':>6s} {'OM deg':>7s} "
        f"{'centre%':>8s} {'scale%':>7s} {'sim deg':>7s} {'left%':>6s} {'along um':>8s} "
        f"{'time s':>7s}")
  rows = []
  for name in args.score or args.scenes:
    r = score(name) if args.score else run(name, args.resolution, args.out)
    rows.append(r)
    if r["rc"] != 0:
      print(f"{r['scene']:10s} association failed (exit {r['rc']})")
      continue
    w, o = r["wli"], r["om"]
    print(f"{r['scene']:10s} {w['max_rot_deg']:8.4f} {w['max_trans_px']:7.3f} "
          f"{o['registered']:>3d}/{o['cameras']:<2d} {o['max_rot_deg']:7.3f} "
          f"{100 * o.get('max_centre_rel', np.nan):8.3f} {100 * o.get('scale_error', np.nan):7.3f} "
          f"{o.get('similarity_rot_deg', np.nan):7.3f} "
          f"{100 * o.get('max_centre_rel_after_similarity', np.nan):6.2f} "
          f"{o.get('median_centre_along_um', np.nan):8.2f} {r['seconds']:7.1f}", flush=True)
  if not args.score:
    (args.out / "associate.json").write_text(json.dumps(rows, indent=2))
  return 0


if __name__ == "__main__":
  sys.exit(main())
