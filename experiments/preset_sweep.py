"""`python experiments/preset_sweep.py`: accuracy of config variants of a preset on one scene.

Each variant (`--variants`, comma list of `preset+component.field=value+...` as in
benchmarks/train_step.py, e.g. `cpu,cpu+optim.lr_inv_s=0.01`) trains the same scene with the same
poses and seed in this process (`ofjax.train.train`, the CLI's loop), exports the mesh at the
preset's resolution and evaluates it against the scene's truth (`python -m ofjax.eval --poses`,
so estimated poses are scored in the truth's frame). Measured per variant: training wall time,
NeuS's final inverse std s, the last logged WLI depth loss, Chamfer (accuracy, completeness),
F-scores and albedo PSNR. `--steps` shortens every variant as the train CLI's `--steps` does
(`config.with_steps`: cos-anneal and warm-up shrink with the run), so a sweep at 600 steps trains
what the ablation's 600-step runs train. This is how a preset's numbers are chosen: a lever is
kept when its accuracy at equal training time is better, on the scene and then on the ablation's
others.

--scene-dir defaults to WORK/scene, synthesised (default scene, quick) when absent; --poses
defaults to the scene's true poses (ground_truth/poses.json), so pose errors do not mix in.
Jobs go through experiments/sweep.py (one record per variant under WORK/records, keyed by the
variant and a fingerprint of its resolved config, so a rerun skips what is finished and a changed
preset retrains); the table goes to WORK/preset_sweep.md and every record to
WORK/preset_sweep.json, with the machine and the commit.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # sweep.py, ablation.py beside this file
import ablation  # noqa: E402
import sweep  # noqa: E402

from ofjax import config, fileio, machine  # noqa: E402
from ofjax import scene as scene_lib  # noqa: E402
from ofjax.errors import UserError, cli  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def variant_config(spec: str, seed: int, steps: int | None) -> config.Config:
  """The resolved Config of a variant; `steps` shortens it as the train CLI's --steps does."""
  cfg = config.resolve_spec(spec, train={"seed": seed})
  return cfg if steps is None else config.with_steps(cfg, steps)


def run_variant(job: sweep.Job) -> dict:
  """Trains, exports and evaluates one variant (a module-level function: sweep pickles it)."""
  from ofjax import export, train
  from ofjax import io as ofio
  p = job.params
  cfg = variant_config(job.variant, p["seed"], p["steps"])
  scene = ofio.load(p["scene_dir"], poses=p["poses"])
  run_dir = Path(p["run_dir"])
  t0 = time.time()
  result = train.train(scene, cfg, run_dir, progress=p["progress"],
                       meta={"data": p["scene_dir"], "poses": p["poses"]})
  mesh = export.export_run(result.params, cfg, result.norm, result.box, run_dir / "mesh.ply",
                           units=scene.units, poses=scene_lib.poses_to_json(scene),
                           trained_in=run_dir).path
  out, _ = ablation.run_cli("eval", "--pred", str(mesh), "--gt", p["scene_dir"], "--poses",
                           p["poses"], "--json")
  ev = json.loads(out.strip().splitlines()[-1])
  last = json.loads((run_dir / train.METRICS).read_text().splitlines()[-1])
  return {"train_s": result.seconds, "wall_s": time.time() - t0, "steps": cfg.train.steps,
          "inv_s": last["inv_s"], "loss_wli": last["loss/wli"], "eval": ev,
          "fingerprint": cfg.fingerprint(), "commit": ablation.git_state()["commit"],
          "run_dir": str(run_dir)}


def table(records: list[dict]) -> str:
  lines = ["| variant | steps | train s | final s | Chamfer um | accuracy um | completeness um | "
           "F-score @ 0.5% / 1% | albedo PSNR dB |", "|---|---|---|---|---|---|---|---|---|"]
  for r in records:
    if "result" not in r:
      lines.append(f"| `{r['job']['variant']}` | failed: {r.get('error', '?')[:80]} |"
                   + " |" * 7)
      continue
    res, ev = r["result"], r["result"]["eval"]
    fs = " / ".join(f"{f['fscore']:.3f}" for f in ev["fscore"])
    lines.append(f"| `{r['job']['variant']}` | {res['steps']} | {res['train_s']:.1f} | "
                 f"{res['inv_s']:.0f} | {ev['chamfer_um']:.3f} | {ev['accuracy_um']:.3f} | "
                 f"{ev['completeness_um']:.3f} | {fs} | {ev['albedo_psnr']:.2f} |")
  return "\n".join(lines)


def ensure_scene(work: Path) -> Path:
  """WORK/scene, synthesised (default scene, quick, seed 0) when it does not exist yet."""
  scene_dir = work / "scene"
  if not scene_dir.exists():
    work.mkdir(parents=True, exist_ok=True)
    try:
      ablation.synthesise(ablation.DEFAULT_SCENE, "quick", scene_dir)
    except RuntimeError as e:
      raise UserError(f"{scene_dir}: synthesis failed ({e})") from None
  return scene_dir


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python experiments/preset_sweep.py", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--variants", default="cpu",
                 help="comma list of preset variants, e.g. cpu,cpu+optim.lr_inv_s=0.01")
  p.add_argument("--scene-dir", type=Path, help="scene to train (default: WORK/scene, synthesised)")
  p.add_argument("--poses", type=Path, help="poses file (default: SCENE/ground_truth/poses.json)")
  p.add_argument("--steps", type=int, help="training steps of every variant (default: its own)")
  p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
  p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
  p.add_argument("--work", type=Path, default=ROOT / "runs" / "preset_sweep",
                 help="run directories, records and the table (default runs/preset_sweep)")
  p.add_argument("--quiet", action="store_true", help="no progress bars")
  args = p.parse_args(argv)
  if args.steps is not None and args.steps < 1 or args.workers < 1:
    raise UserError("--steps and --workers must be positive")
  specs = [s for s in args.variants.split(",") if s]
  try:  # every variant checked before anything is synthesised or trained
    fingerprints = [variant_config(spec, args.seed, args.steps).fingerprint() for spec in specs]
  except ValueError as e:
    raise UserError(f"--variants {e}") from None
  scene_dir = args.scene_dir or ensure_scene(args.work)
  poses = args.poses or scene_dir / "ground_truth" / "poses.json"
  if not poses.exists():
    raise UserError(f"{poses}: no poses file; give --poses (e.g. SCENE/poses.json from "
                    "python -m ofjax.associate)")
  jobs = []
  for spec, fp in zip(specs, fingerprints):
    name = f"{fp}_{hashlib.sha256(spec.encode()).hexdigest()[:6]}"
    jobs.append(sweep.Job(scene=scene_dir.name, variant=spec, seed=args.seed,
                          result=str(args.work / "records" / f"{name}.json"),
                          params={"scene_dir": str(scene_dir), "poses": str(poses),
                                  "seed": args.seed, "steps": args.steps,
                                  "run_dir": str(args.work / "runs" / name),
                                  "progress": not args.quiet and args.workers == 1}))
  records = sweep.run_jobs(jobs, run_variant, workers=args.workers,
                           log=lambda m: print(m, flush=True))
  info = machine.describe()
  text = "\n".join([
      "# Preset sweep", "",
      f"`python experiments/preset_sweep.py {' '.join(sys.argv[1:] if argv is None else argv)}`, "
      f"commit `{ablation.git_state()['commit']}`; scene `{scene_dir}`, poses `{poses}`, "
      f"seed {args.seed}.", "",
      f"Machine: {machine.line(info)}; workers "
      f"{args.workers} (train s is wall time with the others running).", "",
      table(records), ""])
  fileio.write_json(args.work / "preset_sweep.json", {"machine": info, "records": records})
  fileio.write_text(args.work / "preset_sweep.md", text)
  print(text)
  failed = [r for r in records if "result" not in r]
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
