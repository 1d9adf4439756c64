"""`python -m ofjax.demo --out runs/demo`: the whole pipeline on the embedded synthetic default.

synth (the `seed` scene, quick) -> associate (poses from the raw data) -> train (cpu preset,
writes mesh.ply) -> eval (against the scene's ground truth) -> roughness of one region (beside
the same region's on the true surface) and one cross-section profile -> RUN/report.md, with the
pictures beside it. Each stage is the same code as its own CLI; the report says how long each
took.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

from ofjax import fileio, machine, metrology, plots
from ofjax.errors import UserError, cli
from ofjax.meshquery import load_mesh


def _run(stage: str, main, argv: list[str], timings: dict[str, float], capture: bool = False):
  """Runs one stage's CLI in-process; a failing stage stops the demo with its own message."""
  print(f"\n== {stage}: python -m ofjax.{stage} {' '.join(argv)}", flush=True)
  t0 = time.time()
  out = io.StringIO()
  with contextlib.redirect_stdout(out) if capture else contextlib.nullcontext():
    code = main(argv)
  timings[stage] = timings.get(stage, 0.0) + time.time() - t0
  if code != 0:
    raise UserError(f"the demo's {stage} stage failed (exit {code}); see the message above")
  return out.getvalue()


def _table(rows: list[tuple[str, ...]], header: tuple[str, ...] = ("quantity", "value")) -> str:
  return "\n".join([f"| {' | '.join(header)} |", "|---" * len(header) + "|"] +
                   [f"| {' | '.join(r)} |" for r in rows])


def truth_roughness(scene_dir: Path, poses_path: Path, region: tuple[float, ...], n: int) -> dict:
  """ISO 25178-2 parameters of `region` (x0, y0, x1, y1 um in the frame of poses_path) on the
  scene's true surface, sampled like `measure roughness` with n samples along the longer side:
  what the reconstruction's should read."""
  from ofjax.associate.evaluate import gauge
  from ofjax.scene import load_poses
  gt_dir = scene_dir / "ground_truth"
  meta = json.loads((gt_dir / "meta.json").read_text())
  to_truth = gauge(load_poses(poses_path), load_poses(gt_dir / "poses.json"),
                   float(meta["size_um"]))
  truth = load_mesh(gt_dir / "mesh.ply")
  truth.apply_transform(np.linalg.inv(to_truth))
  grid = metrology.sample_region(np.asarray(truth.vertices), np.asarray(truth.faces), region, n=n)
  return metrology.areal_parameters(grid.z)


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m ofjax.demo", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", default="runs/demo", help="demo directory (scene/ and run/ inside)")
  p.add_argument("--scene", default="seed", help="synthetic scene (python -m ofjax.synth --list)")
  p.add_argument("--steps", type=int, help="training steps (default: the cpu preset's)")
  p.add_argument("--seed", type=int, default=0)
  args = p.parse_args(argv)

  from ofjax import eval as eval_cli, measure, synth, train
  from ofjax.associate import __main__ as associate_cli
  from ofjax.associate.evaluate import pose_errors

  out = Path(args.out)
  scene_dir, run_dir = out / "scene", out / "run"
  timings: dict[str, float] = {}
  t_start = time.time()
  _run("synth", synth.main, ["--scene", args.scene, "--resolution", "quick", "--seed",
                             str(args.seed), "--out", str(scene_dir)], timings)
  _run("associate", associate_cli.main, [str(scene_dir), "--report"], timings)
  train_argv = ["--data", str(scene_dir), "--out", str(run_dir), "--seed", str(args.seed),
                "--overwrite"]
  if args.steps:
    train_argv += ["--steps", str(args.steps)]
  _run("train", train.main, train_argv, timings)
  mesh_path = run_dir / "mesh.ply"
  # The mesh is in the association's frame; eval moves it into the truth's (--poses).
  _run("eval", eval_cli.main, ["--pred", str(mesh_path), "--gt", str(scene_dir), "--poses",
                               str(scene_dir / "poses.json")], timings)
  ev = json.loads((run_dir / "mesh_eval.json").read_text())

  # Metrology on the reconstruction: a square on the sample's top and a line across it.
  mesh = load_mesh(mesh_path)
  v = np.asarray(mesh.vertices)
  lo, hi = v.min(0), v.max(0)
  c = (lo + hi) / 2
  half = 0.08 * (hi - lo)[:2].min()
  region = f"{c[0] - half:.2f},{c[1] - half:.2f},{c[0] + half:.2f},{c[1] + half:.2f}"
  rough = json.loads(_run("measure", measure.main, ["roughness", "--mesh", str(mesh_path),
                                                    f"--region={region}", "--json"], timings,
                          capture=True))
  true_rough = truth_roughness(scene_dir, scene_dir / "poses.json",
                               measure.parse_region(region), max(rough["grid"]))
  start, end = f"{lo[0]:.2f},{c[1]:.2f}", f"{hi[0]:.2f},{c[1]:.2f}"
  _run("measure", measure.main, ["profile", "--mesh", str(mesh_path), f"--from={start}",
                                 f"--to={end}"], timings)
  preview = plots.mesh_preview(run_dir / "mesh_preview.png", v, np.asarray(mesh.faces),
                               np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0,
                               "ofjax reconstruction (top view)")

  fmt = lambda x, d=4: f"{x:.{d}g}"
  gt_poses = json.loads((scene_dir / "ground_truth" / "poses.json").read_text())
  est_poses = json.loads((scene_dir / "poses.json").read_text())
  meta = json.loads((scene_dir / "ground_truth" / "meta.json").read_text())
  pe = pose_errors(est_poses, gt_poses, float(meta["size_um"]))["summary"]
  pose_rows = [(f"{mod} {k}", fmt(v) if isinstance(v, float) else str(v))
               for mod in ("wli", "om") for k, v in pe[mod].items()]
  total = time.time() - t_start
  report = f"""# ofjax demo report

Scene `{args.scene}` (synthetic, quick resolution, seed {args.seed}) in `{scene_dir}`; training run
in `{run_dir}`. Machine: {machine.line(machine.describe())}. Total wall time {total:.0f} s.

**Mesh (um, vertex colours):** `{mesh_path}` - open it in MeshLab.

![reconstruction]({preview.name})

## Seconds per stage
{_table([(k, f"{s:.1f}") for k, s in timings.items()])}

## Association (estimated poses vs. the generator's truth)
{_table(pose_rows)}

## Accuracy against the ground truth
{_table([(k, fmt(ev[k])) for k in ("chamfer_um", "chamfer_rel", "chamfer_px", "accuracy_um",
                                   "completeness_um", "normal_consistency", "albedo_psnr",
                                   "albedo_psnr_gain") if k in ev] +
        [(f"F-score @ {f['threshold_um']:.3g} um", fmt(f["fscore"])) for f in ev["fscore"]])}

Error heat maps: `{Path(ev['completeness_png']).name}`, `{Path(ev['accuracy_png']).name}`.

## Roughness (ISO 25178-2) of region {region} um
The same region on the true surface (moved into the mesh's frame by the poses' gauge, sampled
alike) for comparison. Heights in um; Ssk and Sku have no unit.
{_table([(k, fmt(rough[k]), fmt(true_rough[k])) for k in metrology.PARAMETERS],
        ("parameter", "mesh", "true surface"))}

Height map: `{Path(rough['png']).name}`. Profile from ({start}) to ({end}) um: `mesh_profile.csv`,
`mesh_profile.png`.
"""
  fileio.write_text(run_dir / "report.md", report)
  print(f"\nofjax demo done in {total:.0f} s. Look at:\n  {run_dir / 'report.md'}\n  {mesh_path}"
        f" (MeshLab)\n  {preview}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
