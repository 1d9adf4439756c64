"""`python -m ofjax.associate SCENE_DIR [--report] [--workdir DIR]`: pose every camera of a scene.

Reads the scene's raw WLI maps and OM photos (never ground_truth/), runs the two-step association
and writes SCENE_DIR/poses.json (um, OpenCV camera-to-world; ofjax.scene.poses_to_json schema).
With --report it also writes SCENE_DIR/association/report.json and report.png. A failure (too few
photos registered, scans that do not overlap, a poor alignment) exits with code 2 and one line,
writing nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ofjax import fileio
from ofjax import scene as scene_lib
from ofjax.associate import align, report, sfm
from ofjax.associate.pipeline import associate
from ofjax.errors import UserError, cli


def _fraction(text: str) -> float:
  v = float(text)
  if not 0.0 <= v <= 1.0:
    raise argparse.ArgumentTypeError(f"{text} is not a fraction in [0, 1]")
  return v


def parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m ofjax.associate", description=__doc__.split("\n")[0])
  p.add_argument("scene_dir", type=Path, help="native ofjax scene directory (has scene.json)")
  p.add_argument("--report", action="store_true",
                 help="also write SCENE_DIR/association/report.json and report.png")
  p.add_argument("--workdir", type=Path, default=None,
                 help="keep pycolmap's images, database and sparse model here (default: temporary)")
  p.add_argument("--min-overlap", type=_fraction, default=0.2,
                 help="ICP fitness for two WLI scans to count as overlapping (default 0.2)")
  p.add_argument("--min-fitness", type=_fraction, default=0.3,
                 help="share of SfM points that must land on the WLI surface (default 0.3)")
  p.add_argument("--min-registered", type=_fraction, default=1.0,
                 help="share of OM photos SfM must register (default 1.0: all)")
  p.add_argument("--max-image-size", type=int, default=sfm.MAX_IMAGE_SIZE,
                 help=f"SIFT image size limit in pixels (default {sfm.MAX_IMAGE_SIZE})")
  p.add_argument("--max-features", type=int, default=sfm.MAX_NUM_FEATURES,
                 help=f"SIFT features per photo (default {sfm.MAX_NUM_FEATURES})")
  p.add_argument("--seed", type=int, default=0, help="seed of RANSAC and the SfM mapper")
  return p


# Stage priors more than this far from the alignment are reported (the priors' own error is a
# few degrees: a stage's azimuth scale, a sample placed by hand).
PRIOR_DISAGREE_DEG = 20.0


@cli
def main(argv: list[str] | None = None) -> int:
  args = parser().parse_args(argv)
  for opt in ("max_image_size", "max_features"):
    if getattr(args, opt) <= 0:
      raise UserError(f"--{opt.replace('_', '-')}: must be positive")
  # Poses of an earlier run are not inputs: read the raw data only.
  scene = scene_lib.load_scene(args.scene_dir, poses=False)
  a = associate(scene, args.workdir, args.min_overlap, args.min_fitness, args.min_registered,
                args.seed, args.max_image_size, args.max_features, str(args.scene_dir))
  fileio.write_json(args.scene_dir / "poses.json", scene_lib.poses_to_json(a.scene))
  print(f"ofjax: wrote {args.scene_dir / 'poses.json'}: {len(a.scene.wli)} WLI scans, "
        f"{len(a.sfm.c2w)}/{len(scene.om)} OM photos, OM scale {a.align.scale:.5g} um/unit, "
        f"{a.seconds['total']:.1f} s")
  if a.anchoring is not None:
    print(f"ofjax: {len(a.anchoring.anchors)}/{len(a.sfm.c2w)} photos anchored on the WLI "
          "intensity images")
  al = a.align
  if al.turn_source == "priors":
    print(f"ofjax: the OM photos fit the WLI scans about as well turned by "
          f"{al.turn_runner_up_deg:.0f} deg (fit costs {100 * abs(al.turn_margin):.1f}% apart); "
          f"the photos' stage priors chose the turn ({al.prior_deg:.1f} deg from them)")
  elif al.turn_margin < align.TURN_WARN_MARGIN:
    print(f"ofjax: warning: the OM photos fit the WLI scans almost as well turned by "
          f"{al.turn_runner_up_deg:.0f} deg (height cost {al.height_cost:.3f}, "
          f"{100 * al.turn_margin:.1f}% apart); the sample looks symmetric to the data: give the "
          "photos' stage tilt/azimuth as \"prior\" in scene.json to decide, and check the colours "
          "of the trained mesh", file=sys.stderr)
  if al.prior_deg > PRIOR_DISAGREE_DEG:
    print(f"ofjax: warning: the alignment turns the photos {al.prior_deg:.0f} deg from their "
          "stage priors; the data chose it clearly, so the priors were kept out (was the sample "
          "mounted turned on the two instruments, or do the stage conventions differ?)",
          file=sys.stderr)
  if args.report:
    js, png = report.write_report(a, args.scene_dir / "association", args.min_overlap)
    print(f"ofjax: wrote {js} and {png}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
