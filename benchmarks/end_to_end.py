"""Seconds per stage of the demo pipeline, and Chamfer distance reached against training wall time.

Stages (each timed by wall clock, in this order, in WORK_DIR):
  synth      python -m ofjax.synth --scene seed --resolution quick --out WORK/scene   (subprocess)
  associate  python -m ofjax.associate WORK/scene                                     (subprocess)
  train      ofjax.train.train on the associated scene, cpu preset (in process, so that it can
             keep `--points` checkpoints for the curve; the step and loop are the CLI's)
  export     python -m ofjax.export WORK/run --out WORK/run/mesh.ply                  (in process)
  eval       python -m ofjax.eval --pred WORK/run/mesh.ply --gt WORK/scene --poses WORK/scene/poses.json
             --json (subprocess; the mesh is moved from the association's frame into the truth's)
The curve: every kept checkpoint is exported and evaluated against the synthetic ground truth;
its time is the training wall time at that step (metrics.jsonl, compile included). Written to
WORK/end_to_end.json and WORK/chamfer_vs_time.png.

  python benchmarks/end_to_end.py [--work DIR] [--steps N] [--points K] [--mesh-resolution R]
                                 [--set COMPONENT.FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from ofjax import (checkpoint, compile_cache, eval as eval_lib, export, fields, fileio, metrics,
                   plots, train)
from ofjax.errors import UserError, cli
from ofjax.meshquery import load_mesh
from ofjax.scene import load_poses


def _subprocess(*args: str) -> str:
  """Runs `python -m ...args`, returns its stdout; a failure stops the benchmark with its stderr."""
  proc = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)
  if proc.returncode:
    raise RuntimeError(f"python -m {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
  return proc.stdout


def _timed(fn):
  t0 = time.perf_counter()
  out = fn()
  return out, time.perf_counter() - t0


def train_stage(scene_dir: Path, run_dir: Path, steps: int | None, points: int,
                mesh_resolution: int | None, sets: list[str]):
  """Trains like `python -m ofjax.train --data scene_dir --out run_dir [--set ...]`, keeping
  `points` checkpoints."""
  argv = ["--data", str(scene_dir), "--out", str(run_dir), "--quiet"]
  for s in sets:
    argv += ["--set", s]
  if steps:
    argv += ["--steps", str(steps)]
  if mesh_resolution:
    argv += ["--mesh-resolution", str(mesh_resolution)]
  args = train.build_parser().parse_args(argv)
  cfg = train.config_from_args(args)
  every = max(cfg.train.steps // points, 1)
  cfg = dataclasses.replace(cfg, train=dataclasses.replace(
      cfg.train, checkpoint_every=every, keep_checkpoints=points + 1))
  scene = train.load_scene_for_training(args)
  return train.train(scene, cfg, run_dir, progress=False), scene


def curve(run_dir: Path, scene_dir: Path, result, skip: set[int]) -> list[dict]:
  """Chamfer (um) of every kept checkpoint but those in `skip`, with the wall time at its step."""
  log = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
  log_steps = np.array([r["step"] + 1 for r in log], float)  # steps done when the line was written
  log_times = np.array([r["time_s"] for r in log], float)
  cfg = result.cfg
  template = fields.init_params(jax.random.PRNGKey(0), cfg)
  opt_template = train.make_optimizer(cfg).init(template)
  gt, meta = eval_lib.load_ground_truth(scene_dir)
  poses = load_poses(run_dir / export.POSES)  # the final mesh's cleanup (ofjax.export) on each
  points = []
  for step in checkpoint.list_steps(run_dir):
    if step in skip:
      continue
    _, params, _ = checkpoint.restore(run_dir, template, opt_template, step)
    mesh_path = run_dir / "curve" / f"mesh_{step:06d}.ply"
    export.export_run(params, cfg, result.norm, result.box, mesh_path, poses=poses,
                      trained_in=run_dir)
    mesh = load_mesh(mesh_path)
    eval_lib.to_truth_frame(mesh, scene_dir / "poses.json", scene_dir, meta)
    ev = metrics.evaluate(mesh, gt)
    points.append({"step": step, "train_s": float(np.interp(step, log_steps, log_times)),
                   "chamfer_um": ev.summary["chamfer_um"]})
  return points


def plot_curve(points: list[dict], path: Path, title: str) -> Path:
  from matplotlib.figure import Figure

  fig = Figure(figsize=(6, 4), constrained_layout=True)
  ax = fig.add_subplot()
  t = [p["train_s"] for p in points]
  c = [p["chamfer_um"] for p in points]
  ax.plot(t, c, "o-")
  for p in points:
    ax.annotate(f"{p['step']}", (p["train_s"], p["chamfer_um"]), textcoords="offset points",
                xytext=(4, 4), fontsize=8)
  ax.set_xlabel("training wall time (s, compile included)")
  ax.set_ylabel("Chamfer distance (um)")
  ax.set_yscale("log")
  ax.set_title(title)
  ax.grid(True, which="both", alpha=0.3)
  return plots.save(fig, path)


def run(work: Path, steps: int | None, points: int, mesh_resolution: int | None,
        sets: list[str]) -> dict:
  scene_dir, run_dir = work / "scene", work / "run"
  stages = {}
  _, stages["synth"] = _timed(lambda: _subprocess(
      "ofjax.synth", "--scene", "seed", "--resolution", "quick", "--out", str(scene_dir)))
  _, stages["associate"] = _timed(lambda: _subprocess("ofjax.associate", str(scene_dir)))
  (result, _), stages["train"] = _timed(
      lambda: train_stage(scene_dir, run_dir, steps, points, mesh_resolution, sets))
  mesh_path = run_dir / "mesh.ply"
  _, stages["export"] = _timed(lambda: export.main([str(run_dir), "--out", str(mesh_path)]))
  out, stages["eval"] = _timed(lambda: _subprocess(
      "ofjax.eval", "--pred", str(mesh_path), "--gt", str(scene_dir), "--poses",
      str(scene_dir / "poses.json"), "--json"))
  final = json.loads(out.strip().splitlines()[-1])
  last = result.cfg.train.steps
  pts = curve(run_dir, scene_dir, result, skip={last})
  pts.append({"step": last, "train_s": result.seconds, "chamfer_um": final["chamfer_um"]})
  summary = {"stages_s": stages, "total_s": sum(stages.values()), "steps": last,
             "preset": result.cfg.preset, "set": sets,
             "fingerprint": result.cfg.fingerprint(), "train_s_per_step": result.seconds / last,
             "curve": pts, "jax": jax.__version__, "backend": jax.default_backend()}
  variant = "+".join([result.cfg.preset, *sets])
  plot_curve(pts, work / "chamfer_vs_time.png", f"ofjax {variant}, seed scene: Chamfer vs time")
  fileio.write_json(work / "end_to_end.json", metrics.json_ready(summary))
  return summary


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python benchmarks/end_to_end.py",
                              description="Seconds per demo stage and Chamfer against wall time.")
  p.add_argument("--work", type=Path, default=Path("runs/bench_end_to_end"),
                 help="working directory (created; must not hold a previous run)")
  p.add_argument("--steps", type=int, help="training steps (default: the cpu preset's)")
  p.add_argument("--points", type=int, default=4, help="checkpoints on the Chamfer curve")
  p.add_argument("--mesh-resolution", type=int, help="marching-cubes resolution (default: preset's)")
  p.add_argument("--set", dest="sets", action="append", default=[], metavar="COMPONENT.FIELD=VALUE",
                 help="override a field of the cpu preset, as the train CLI's --set (repeatable)")
  args = p.parse_args(argv)
  # Cold compiles, as a first run of the demo has them: the export (in process) and the tools run
  # as subprocesses would otherwise load what an earlier run compiled. An explicit setting wins.
  os.environ.setdefault(compile_cache.ENV, "off")
  if args.points < 1:
    raise UserError(f"--points {args.points}: must be positive")
  if (args.work / "scene").exists() or (args.work / "run").exists():
    raise UserError(f"{args.work}: holds a previous benchmark; pass another --work or delete it")
  summary = run(args.work, args.steps, args.points, args.mesh_resolution, args.sets)
  for name, seconds in summary["stages_s"].items():
    print(f"{name:<10} {seconds:8.1f} s")
  print(f"{'total':<10} {summary['total_s']:8.1f} s  ({summary['steps']} steps, "
        f"{summary['train_s_per_step']:.3f} s/step)")
  for pt in summary["curve"]:
    print(f"step {pt['step']:>6}  {pt['train_s']:8.1f} s  chamfer {pt['chamfer_um']:.3g} um")
  print(f"curve: {args.work / 'chamfer_vs_time.png'}; numbers: {args.work / 'end_to_end.json'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
