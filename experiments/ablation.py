"""`python experiments/ablation.py`: the paper's ablation (Table 1) on ofjax's synthetic scenes.

For every scene (--scenes, default all five) and pose source (--poses: `associate`, poses estimated
by `ofjax.associate`, and `true`, the synthetic ground truth, as a second table), five variants:
  conventional  screened Poisson of the WLI cloud + projected OM colour (`ofjax.conventional`)
  om            OM photos only (`ofjax.train --modalities om`)
  wli           WLI height maps only (`--modalities wli`)
  fused_nores   WLI + OM without the residual colour branch (`--no-residual`)
  fused         WLI + OM, the full model
each evaluated against the scene's truth by `ofjax.eval` (Chamfer in um, F-score, albedo PSNR).
Seeds (--seeds) are training seeds of the default scene `seed`; the other scenes run with the
first of them; --true-seeds gives the true-pose table its own (fewer) seeds, since it is the
reference the associated table is read against, not a second spread. The synthetic scenes are always rendered with synth seed 0 (one scene, many
trainings), so a spread over seeds is the training's spread.

Stages run as subprocesses of the ofjax CLIs, jobs through `experiments/sweep.py` (processes with
--workers, or Ray with --ray ADDRESS). Everything large goes under --work (default runs/ablation/):
data_<resolution>/ holds the scenes and their association, steps<N>_<resolution>_cpu-<hash>/ the
run directories with meshes and heat maps, one record JSON per job, so an interrupted run resumes;
<hash> is a fingerprint of the preset the neural runs train with (--preset, default the cpu preset;
a variant such as cpu+loss.lambda_color=0.3 measures a candidate preset before it is adopted),
so runs trained with another preset are retrained, not reused, and a candidate's runs are kept
when it becomes the preset (the directory is named by the preset name and the fingerprint). The
summary goes to --out (default experiments/results/): ablation.json (every record, the machine,
the commit, the budget), ablation.md (the tables laid out like the paper's, ratios beside the
paper's, the issue's targets, wall times) and
figures/<poses>_<scene>.png (per method: top-view render, completeness and accuracy heat maps, one
colour scale per scene; every method's cross-section through the middle of the scene against the
truth's, whole and zoomed where the fused mesh is farthest from it).

--steps and --resolution reduce the budget (training steps; synth image sizes); both are recorded
and name the work directory, so runs of different budgets never mix.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # sweep.py beside this file
import sweep  # noqa: E402

from ofjax import config, export, fileio, machine  # noqa: E402
from ofjax.errors import UserError, cli  # noqa: E402

SCENES = ("seed", "circuit", "wing", "sensor", "lenses")
DEFAULT_SCENE = "seed"
VARIANTS = ("conventional", "om", "wli", "fused_nores", "fused")
LABELS = {"conventional": "Conventional (Poisson)", "om": "OM only", "wli": "WLI only",
          "fused_nores": "Fused w/o residual", "fused": "Fused"}
# OM only starts from the plane: the preset's WLI-fitted init needs WLI rays. It keeps the paper's
# colour weight: the cpu preset's 0.1 weighs the photos against the WLI terms, which OM only lacks,
# and would there only weaken its one data term against the regularisers.
TRAIN_FLAGS = {"om": ["--modalities", "om", "--set", "model.init_shape=plane",
                      "--set", "loss.lambda_color=1.0"],
               "wli": ["--modalities", "wli"],
               "fused_nores": ["--no-residual"], "fused": []}
POSE_SOURCES = ("associate", "true")
PAPER_CHAMFER = {"conventional": 0.793, "om": 0.538, "wli": 0.678, "fused_nores": 0.044,
                 "fused": 0.043}  # the paper's Table 1, average over its scenes (its units)
SYNTH_SEED = 0
FSCORE_INDEX = -1  # the F-score at the loosest threshold (1% of the GT diagonal) goes in the table
WITHIN = 0.10  # the "within 10%" for fused vs the best method, and nores vs fused
SECTION_ZOOM = 0.08  # the figures' zoomed cross-section: half its width, a share of the sample's
ROOT = Path(__file__).resolve().parents[1]
# ofjax.export's message when a trained SDF has no surface: the method failed at this budget, which
# is a result of the ablation (Chamfer infinite), not a broken job.
NO_SURFACE = "has no zero crossing"


class NoSurface(RuntimeError):
  pass


def run_cli(module: str, *args: str) -> tuple[str, float]:
  """Runs `python -m ofjax.<module> args`; returns its stdout and seconds; a failure raises."""
  t0 = time.time()
  proc = subprocess.run([sys.executable, "-m", f"ofjax.{module}", *args], capture_output=True,
                        text=True)
  if proc.returncode != 0:
    raise (NoSurface if NO_SURFACE in proc.stderr else RuntimeError)(f"ofjax.{module} {' '.join(args)}: exit {proc.returncode}: "
                       f"{proc.stderr.strip()[-sweep.STDOUT_TAIL_CHARS:]}")
  return proc.stdout, time.time() - t0


def synthesise(scene: str, resolution: str, scene_dir: str | Path) -> float:
  """`ofjax.synth` of `scene` (synth seed SYNTH_SEED) into scene_dir; returns its seconds.

  Written beside and renamed: a scene directory that exists is complete, even after a kill.
  """
  partial = f"{scene_dir}.partial"
  shutil.rmtree(partial, ignore_errors=True)
  _, seconds = run_cli("synth", "--scene", scene, "--resolution", resolution, "--seed",
                       str(SYNTH_SEED), "--out", partial)
  os.replace(partial, scene_dir)
  return seconds


def prepare(job: sweep.Job) -> dict:
  """Synth (and, for associated poses, associate) one scene into job.params['scene_dir']."""
  scene_dir, stages = job.params["scene_dir"], {}
  if not Path(scene_dir).exists():
    stages["synth"] = synthesise(job.scene, job.params["resolution"], scene_dir)
  if job.params["associate"] and not (Path(scene_dir) / "poses.json").exists():
    _, stages["associate"] = run_cli("associate", scene_dir, "--report", "--seed", str(SYNTH_SEED))
  if not job.params["associate"]:
    return {"stages_s": stages}
  from ofjax.associate.evaluate import scene_pose_errors
  return {"stages_s": stages, "pose_errors": scene_pose_errors(scene_dir)}


def association_table(data_records: list[dict], scenes: list[str]) -> str:
  """Issue 5's error table (ofjax.associate.evaluate) of the poses the associated table trained on."""
  errs = {r["job"]["scene"]: r["result"]["pose_errors"] for r in data_records
          if "pose_errors" in r.get("result", {})}
  lines = ["| scene | WLI max rot deg | WLI max trans px | OM registered | OM max rot deg | "
           "OM max centre % of scene | OM scale % |", "|---|---|---|---|---|---|---|"]
  for sc in scenes:
    if sc not in errs:
      continue
    w, o = errs[sc]["wli"], errs[sc]["om"]
    lines.append(f"| {sc} | {w['max_rot_deg']:.4f} | {w['max_trans_px']:.3f} | "
                 f"{o['registered']}/{o['cameras']} | {o['max_rot_deg']:.3f} | "
                 f"{100 * o.get('max_centre_rel', float('nan')):.2f} | "
                 f"{100 * o.get('scale_error', float('nan')):.3f} |")
  return "\n".join(lines)


def run_method(job: sweep.Job) -> dict:
  """One variant on one scene: reconstruct, evaluate, render; returns the metrics and timings."""
  p = job.params
  run_dir, stages, git = Path(p["run_dir"]), {}, git_state()  # the checkout is shared: per run
  if job.variant == "conventional":
    _, stages["conventional"] = run_cli("conventional", p["scene_dir"], "--out", str(run_dir),
                                     "--poses", p["poses"])
  else:
    steps = ["--steps", str(p["steps"])] if p["steps"] else []
    t0 = time.time()
    try:
      _, stages["train"] = run_cli("train", "--data", p["scene_dir"], "--out", str(run_dir), "--poses",
                                p["poses"], "--seed", str(job.seed), "--overwrite", "--quiet",
                                *steps, *preset_flags(p["preset"]), *TRAIN_FLAGS[job.variant])
    except NoSurface as e:
      return {"eval": None, "no_surface": str(e)[-sweep.STDOUT_TAIL_CHARS:],
              "stages_s": {"train": time.time() - t0}, "run_dir": str(run_dir), "git": git}
  return _evaluated(job, stages, git)


def eval_args(job: sweep.Job) -> list[str]:
  """ofjax.eval's pose argument for a run: associated poses are moved into the truth's frame."""
  return ["--poses", job.params["poses"]] if job.params["poses_source"] == "associate" else []


def _evaluated(job: sweep.Job, stages: dict, git: dict) -> dict:
  """Evaluates and renders a finished reconstruction in job's run directory; its record's result."""
  p, run_dir = job.params, Path(job.params["run_dir"])
  mesh = run_dir / "mesh.ply"
  out, stages["eval"] = run_cli("eval", "--pred", str(mesh), "--gt", p["scene_dir"], "--json",
                             "--out", str(run_dir), *eval_args(job))
  from ofjax import plots
  from ofjax.meshquery import load_mesh, vertex_rgb
  m = load_mesh(mesh)
  plots.mesh_preview(run_dir / "preview.png", np.asarray(m.vertices), np.asarray(m.faces),
                     vertex_rgb(m), f"{job.scene}: {LABELS[job.variant]}")
  extracted = {} if job.variant == "conventional" else {
      "export_refine_steps": export.REFINE_STEPS, "export_grid": mesh_grid(p["preset"])}
  return {"eval": json.loads(out.strip().splitlines()[-1]), "stages_s": stages,
          "run_dir": str(run_dir), "git": git, "eval_args": eval_args(job),
          "hidden_dropped": True, **extracted}


def preset_flags(preset: str) -> list[str]:
  """ofjax.train's options for a preset variant 'cpu+component.field=value+...' (parse_spec's
  form); they come before a method's own flags (TRAIN_FLAGS), which win over them."""
  name, *sets = preset.split("+")
  return ["--preset", name] + [arg for item in sets for arg in ("--set", item)]


def mesh_grid(preset: str = "cpu") -> dict:
  """The marching-cubes grid `preset` exports at (train.mesh_resolution; 0: cells of
  AUTO_CELL_PX WLI pixel)."""
  return {"mesh_resolution": config.resolve_spec(preset).train.mesh_resolution,
          "auto_cell_px": export.AUTO_CELL_PX}


# The grid of records older than `export_grid`: the cpu preset's 192 cells along the box.
OLD_GRID = {"mesh_resolution": 192, "auto_cell_px": None}


def reevaluate(records: list[dict], jobs: list[sweep.Job], log) -> list[dict]:
  """Re-runs the evaluation of finished runs that were evaluated with other arguments than
  eval_args gives now (records older than --poses count as none) or before the evaluation split
  completeness at the WLI-blind truth (no `wli_blind_share`), after making the mesh again
  when it predates this code's: a neural run's is exported again from its last checkpoint when the
  export's vertex refinement or grid differs (records older than them count as 0 steps and
  OLD_GRID) or it kept the faces no camera sees (records without `hidden_dropped`), a Poisson one
  reconstructed again in the latter case; the training is kept, the record says which commit
  made the mesh again (`mesh_git`) and which evaluated it (`eval_git`)."""
  by_result = {j.result: j for j in jobs}
  for r in records:
    res = r.get("result")
    if not res or res.get("eval") is None or "job" not in r:
      continue
    job = by_result[r["job"]["result"]]
    neural = job.variant != "conventional"
    grid = mesh_grid(job.params["preset"])
    stale_mesh = (not res.get("hidden_dropped")
                  or neural and (res.get("export_refine_steps", 0) != export.REFINE_STEPS
                                 or res.get("export_grid", OLD_GRID) != grid))
    if (res.get("eval_args", []) == eval_args(job) and not stale_mesh
        and "wli_blind_share" in res["eval"]):
      continue
    # A mesh kept from an earlier remaking keeps its export time and the commit that made it.
    stages = {k: v for k, v in res["stages_s"].items()
              if k != "eval" and (k != "export" or not stale_mesh)}
    made = remade_at(res)
    if stale_mesh and neural:
      log(f"ablation: exporting {r['name']} again ({export.REFINE_STEPS} refinement steps, "
          f"grid {grid}, hidden faces dropped)")
      _, stages["export"] = run_cli("export", res["run_dir"], "--resolution",
                                    str(grid["mesh_resolution"]))
    elif stale_mesh:
      log(f"ablation: reconstructing {r['name']} again (hidden faces dropped)")
      p = job.params
      _, stages["conventional"] = run_cli("conventional", p["scene_dir"], "--out", p["run_dir"],
                                          "--poses", p["poses"])
    log(f"ablation: re-evaluating {r['name']} {' '.join(eval_args(job))}")
    new = _evaluated(job, stages, res.get("git"))
    now = git_state()
    if stale_mesh:
      made = now
    r["result"] = {**new, "eval_git": now,
                   **({"mesh_remade": True, "mesh_git": made} if made is not None else {})}
    fileio.write_json(job.result, {k: v for k, v in r.items() if k != "skipped"})
  return records


def preset_fingerprint(preset: str = "cpu") -> str:
  """Config.fingerprint() of `preset` (a preset or variant): what every neural run trains with."""
  return config.resolve_spec(preset).fingerprint()


def git_state() -> dict:
  """The checkout's commit, and which of the code the records depend on has uncommitted changes."""
  return machine.git_state(("ofjax", "experiments/sweep.py", "experiments/ablation.py"))


def _mean_sd(values: list[float]) -> tuple[float, float, int]:
  a = np.asarray(values, np.float64)
  # No spread for a cell with a run that has no surface (inf) or no colour (nan).
  spread = len(a) > 1 and bool(np.all(np.isfinite(a)))
  return float(a.mean()), float(a.std(ddof=1)) if spread else float("nan"), len(a)


# A run without a surface: no point of the truth is reached (Chamfer infinite, F-score 0) and no
# colour is measured.
NO_SURFACE_METRICS = {"chamfer_um": float("inf"), "chamfer_px": float("inf"), "fscore": 0.0,
                      "albedo_psnr": None, "accuracy_um": float("inf"),
                      "completeness_um": float("inf"), "completeness_blind_um": float("inf"),
                      "wli_blind_share": None}


def summarise(records: list[dict]) -> dict:
  """{poses: {scene: {variant: {metric: (mean, sd, n)}}}} over the seeds of the finished runs."""
  metrics = {"chamfer_um": lambda e: e["chamfer_um"], "chamfer_px": lambda e: e["chamfer_px"],
             "fscore": lambda e: e["fscore"][FSCORE_INDEX]["fscore"],
             "albedo_psnr": lambda e: e["albedo_psnr"],
             # the two halves of the Chamfer (absent from records evaluated before they were kept)
             "accuracy_um": lambda e: e.get("accuracy_um"),
             "completeness_um": lambda e: e.get("completeness_um"),
             # completeness where no WLI scan measured the truth, and that region's share
             "completeness_blind_um": lambda e: e.get("completeness_blind_um"),
             "wli_blind_share": lambda e: e.get("wli_blind_share")}
  table: dict = {}
  for r in records:
    if "result" not in r or r["job"]["variant"] not in VARIANTS:
      continue
    j, ev = r["job"], r["result"]["eval"]
    cell = table.setdefault(j["params"]["poses_source"], {}).setdefault(j["scene"], {}) \
                .setdefault(j["variant"], {k: [] for k in metrics})
    for k, f in metrics.items():
      value = f(ev) if ev is not None else NO_SURFACE_METRICS[k]
      cell[k].append(float("nan") if value is None else float(value))
  return {ps: {sc: {v: {k: _mean_sd(vals) for k, vals in cell.items()} for v, cell in row.items()}
               for sc, row in rows.items()} for ps, rows in table.items()}


def _number(mean: float, digits: int = 3) -> str:
  """A table value: inf (a run without a surface) and nan (nothing measured) in words."""
  if np.isinf(mean):
    return "no surface"
  if np.isnan(mean):
    return "n/a"
  return f"{mean:.{digits}g}"


def _fmt(cell, key: str, digits: int = 3) -> str:
  if cell is None:
    return "-"
  mean, sd, n = cell[key]
  return _number(mean, digits) + (f" ± {sd:.2g} (n={n})" if n > 1 and np.isfinite(mean) else "")


def metric_table(rows: dict, scenes: list[str], key: str, digits: int = 3) -> str:
  """Methods down, scenes across, then the average over the scenes that have every method."""
  head = "| method | " + " | ".join(scenes) + " | average |"
  lines = [head, "|---" * (len(scenes) + 2) + "|"]
  for v in VARIANTS:
    cells = [rows.get(s, {}).get(v) for s in scenes]
    means = [c[key][0] for c in cells if c is not None]
    avg = _number(float(np.mean(means)), digits) if len(means) == len(scenes) else "-"
    lines.append(f"| {LABELS[v]} | " + " | ".join(_fmt(c, key, digits) for c in cells)
                 + f" | {avg} |")
  return "\n".join(lines)


def average(rows: dict, scenes: list[str], variant: str, key: str = "chamfer_um") -> float | None:
  cells = [rows.get(s, {}).get(variant) for s in scenes]
  return None if any(c is None for c in cells) else float(np.mean([c[key][0] for c in cells]))


def _ratio(x: float) -> str:
  return "inf (no surface)" if np.isinf(x) else f"{x:.2f}x"


def ratio_table(rows: dict, scenes: list[str]) -> str:
  lines = ["| ratio (Chamfer) | paper (Table 1 average) | ours, average | "
           + " | ".join(f"ours, {s}" for s in scenes) + " |",
           "|---" * (len(scenes) + 3) + "|"]
  for v in ("conventional", "om", "wli", "fused_nores"):
    ours_avg = average(rows, scenes, v), average(rows, scenes, "fused")
    per = []
    for s in scenes:
      a, b = rows.get(s, {}).get(v), rows.get(s, {}).get("fused")
      per.append(_ratio(a["chamfer_um"][0] / b["chamfer_um"][0]) if a and b else "-")
    avg = _ratio(ours_avg[0] / ours_avg[1]) if None not in ours_avg else "-"
    lines.append(f"| {LABELS[v]} / Fused | {PAPER_CHAMFER[v] / PAPER_CHAMFER['fused']:.1f}x | "
                 f"{avg} | " + " | ".join(per) + " |")
  return "\n".join(lines)


def _value(rows: dict, scene: str, variant: str, key: str = "chamfer_um") -> float | None:
  """One cell of the tables: `key`'s mean over the seeds, None where the job did not run."""
  c = rows.get(scene, {}).get(variant)
  return None if c is None else c[key][0]


def _finite_value(rows: dict, scene: str, variant: str, key: str = "chamfer_um") -> float | None:
  """`_value`, with a non-finite mean (a run without a surface, nothing measured) as None."""
  x = _value(rows, scene, variant, key)
  return x if x is not None and np.isfinite(x) else None


def blind_share(rows: dict, scene: str) -> float | None:
  """The share of a scene's truth no WLI scan measured (the same for every method: it is the
  scene's), from the first method evaluated with it; None when none was."""
  return next((x for v in VARIANTS
               if (x := _finite_value(rows, scene, v, "wli_blind_share")) is not None), None)


def blind_lines(rows: dict, scenes: list[str]) -> list[str]:
  """The WLI-blind section: each scene's blind share, then the completeness there per method."""
  shares = {s: blind_share(rows, s) for s in scenes}
  known = [f"{s} {100 * x:.1f}%" for s, x in shares.items() if x is not None]
  if not known:
    return ["Not measured: these runs were evaluated before `ofjax.eval` split completeness by WLI "
            "coverage; `make reproduce` evaluates them again."]
  return ["Where the fusion earns its margin in the paper: the truth no WLI scan measured (no "
          "measured point of any scan within one WLI pixel, true poses; `ofjax.metrics`), where "
          "the photos are the only data. Share of each scene's truth that is WLI-blind: "
          + ", ".join(known) + ". Completeness over those points (um; the average column weighs "
          "the scenes equally):", "", metric_table(rows, scenes, "completeness_blind_um")]


def targets(rows: dict, scenes: list[str]) -> list[str]:
  """The issue's 'done when' conditions, each met / missed (with the numbers) / not measured."""
  out = []
  def ch(s, v):
    return _value(rows, s, v)

  avgs = {v: average(rows, scenes, v) for v in VARIANTS}
  if None in avgs.values():
    out.append("- Fused lowest average Chamfer: NOT MEASURED (some variant is missing)")
  else:
    best = min(avgs, key=avgs.get)
    out.append(f"- Fused lowest average Chamfer: {'MET' if best == 'fused' else 'MISSED'} "
               f"(fused {avgs['fused']:.3g} um; best {LABELS[best]} {avgs[best]:.3g} um; "
               f"averaged over {', '.join(scenes)})")
  for s in scenes:
    vals = {v: ch(s, v) for v in VARIANTS}
    if None in vals.values():
      out.append(f"- {s}: fused within 10% of the best: NOT MEASURED")
      continue
    best = min(vals, key=vals.get)
    ok = vals["fused"] <= (1 + WITHIN) * vals[best]
    out.append(f"- {s}: fused within 10% of the best: {'MET' if ok else 'MISSED'} (fused "
               f"{vals['fused']:.3g} um, best {LABELS[best]} {vals[best]:.3g} um, ratio "
               f"{vals['fused'] / vals[best]:.2f})")
    nores_ok = abs(vals["fused_nores"] / vals["fused"] - 1) <= WITHIN
    out.append(f"- {s}: fused w/o residual geometry within 10% of fused: "
               f"{'MET' if nores_ok else 'MISSED'} ({vals['fused_nores']:.3g} vs {vals['fused']:.3g}"
               f" um); albedo PSNR w/o residual {rows[s]['fused_nores']['albedo_psnr'][0]:.2f} dB "
               f"vs fused {rows[s]['fused']['albedo_psnr'][0]:.2f} dB")
  if ch("lenses", "fused") is None or None in (ch("lenses", "conventional"), ch("lenses", "wli")):
    out.append("- lenses: fused >= 5x better than conventional and >= 3x better than WLI only: "
               "NOT MEASURED")
  else:
    rc, rw = ch("lenses", "conventional") / ch("lenses", "fused"), ch("lenses", "wli") / ch(
        "lenses", "fused")
    out.append(f"- lenses: conventional/fused {rc:.2f}x (target >= 5x: {'MET' if rc >= 5 else 'MISSED'}),"
               f" WLI-only/fused {rw:.2f}x (target >= 3x: {'MET' if rw >= 3 else 'MISSED'})")
    blind = {v: _finite_value(rows, "lenses", v, "completeness_blind_um")
             for v in ("conventional", "wli", "fused")}
    if None not in blind.values():
      bc, bw = blind["conventional"] / blind["fused"], blind["wli"] / blind["fused"]
      out.append(f"- lenses, read on its WLI-blind truth alone (completeness there): "
                 f"conventional/fused {bc:.2f}x (>= 5x: {'MET' if bc >= 5 else 'MISSED'}), "
                 f"WLI-only/fused {bw:.2f}x (>= 3x: {'MET' if bw >= 3 else 'MISSED'})")
  if set(SCENES) <= set(scenes) and avgs["om"] and avgs["fused"]:
    r = avgs["om"] / avgs["fused"]
    out.append("- average over the five scenes: OM-only/fused infinite: OM only formed no surface "
               "(target >= 3x: met only in that sense, no OM-only surface was measured)"
               if np.isinf(r) else f"- average over the five scenes: OM-only/fused {r:.2f}x "
               f"(target >= 3x: {'MET' if r >= 3 else 'MISSED'})")
  else:
    out.append("- average over the five scenes: OM-only/fused >= 3x: NOT MEASURED (not all five "
               "scenes ran)")
  return out


def blind_sentence(rows: dict, scenes: list[str]) -> str:
  """What the WLI-blind truth says about the fusion's margin, from its completeness there."""
  shares = {s: blind_share(rows, s) for s in scenes}
  if None in shares.values():
    return ""
  most = max(shares, key=shares.get)
  vals = {v: _finite_value(rows, most, v, "completeness_blind_um")
          for v in ("conventional", "wli", "fused")}
  if None in vals.values():
    return ""
  others = [x for s, x in shares.items() if s != most]
  return (f" No WLI scan measured {100 * shares[most]:.0f}% of the truth of `{most}`"
          + (f" ({100 * min(others):.1f}-{100 * max(others):.1f}% of the others')" if others
             else "")
          + f"; there Poisson is {vals['conventional']:.2f} um from it, WLI only "
          f"{vals['wli']:.2f} um and fused {vals['fused']:.2f} um (Poisson / fused "
          f"{vals['conventional'] / vals['fused']:.2f}x, WLI only / fused "
          f"{vals['wli'] / vals['fused']:.2f}x, where the paper's fusion earns its margin): at "
          "this budget the photos add little where the WLI is blind (experiments/README.md, "
          "'Where the WLI is blind').")


def differences(rows: dict, scenes: list[str], steps) -> list[str]:
  """Where our ratios differ from the paper's, stated from the rows (bullets with the numbers)."""
  def val(s, v, key="chamfer_um"):  # "no surface" counts as missing here
    return _finite_value(rows, s, v, key)

  out, budget = [], f"{steps} training steps" if steps else "the cpu preset's training steps"
  poisson = [val(s, "conventional", "chamfer_px") for s in scenes]
  fused = [val(s, "fused", "chamfer_px") for s in scenes]
  if None not in poisson + fused:
    out.append(f"- Conventional / fused is {min(p / f for p, f in zip(poisson, fused)):.2f}-"
               f"{max(p / f for p, f in zip(poisson, fused)):.2f}x (paper 18.4x): screened Poisson on "
               f"the merged WLI cloud is within {max(poisson):.2f} WLI px on every scene, while "
               f"the fused SDF is at {min(fused):.2f}-{max(fused):.2f} px after {budget}: where some "
               "WLI scan measured the surface, the gap is the neural model's error at this budget, "
               "not the data's." + blind_sentence(rows, scenes))
  no_surface = [s for s in scenes if rows.get(s, {}).get("om") is not None and val(s, "om") is None]
  # A cell is "no surface" when any of its seeds formed none; F-score > 0 shows another one did.
  partly = [s for s in no_surface if (_value(rows, s, "om", "fscore") or 0.0) > 0.0]
  if no_surface:
    out.append(f"- OM only formed no surface (no zero level set in the box) on {len(no_surface)} of "
               f"{len(scenes)} scenes ({', '.join(no_surface)}) after {budget}"
               + (f" (on {', '.join(partly)} in some of the seeds only: the others' meshes score "
                  "F > 0, the cell is still no surface)" if partly else "")
               + "; the paper's OM-only row (12.5x) has a surface to measure.")
  wli_better = [s for s in scenes if None not in (val(s, "wli"), val(s, "fused"))
                and val(s, "wli") < val(s, "fused")]
  if wli_better:
    out.append(f"- WLI only beats fused on {', '.join(wli_better)} (paper: fused 15.8x better on "
               "average): with the same rays per step the fused model fits the heights from half "
               "as many WLI rays (the other half are OM rays); at equal WLI rays per step it is at "
               "or below WLI only on four of the five scenes and on average (1,200 steps, with the "
               "SDF network's feature shared, before the colour's own table; "
               "experiments/README.md, 'Fused against WLI only at equal WLI rays per step').")
  same_geo = [s for s in scenes if None not in (val(s, "fused_nores"), val(s, "fused"))
              and abs(val(s, "fused_nores") / val(s, "fused") - 1) <= WITHIN]
  psnr_up = [s for s in scenes if None not in (val(s, "fused_nores", "albedo_psnr"),
                                               val(s, "fused", "albedo_psnr"))
             and val(s, "fused", "albedo_psnr") > val(s, "fused_nores", "albedo_psnr")]
  out.append(f"- The residual branch: geometry within 10% of the model without it on "
             f"{', '.join(same_geo) or 'no scene'} (paper: 1.0x on average); albedo PSNR higher with "
             f"it on {', '.join(psnr_up) or 'no scene'}. These are single trainings; the seed "
             "spread of the default scene (--seeds) says how much of such differences is noise.")
  return out


def pose_source_table(summary: dict, scenes: list[str]) -> str:
  """Chamfer on associated poses / on true poses, per variant and scene (issue 5 asks <= 1.5x)."""
  est, true = summary.get("associate", {}), summary.get("true", {})
  lines = ["| method | " + " | ".join(scenes) + " |", "|---" * (len(scenes) + 1) + "|"]
  for v in VARIANTS:
    cells = []
    for sc in scenes:
      a, b = _value(est, sc, v), _value(true, sc, v)
      cells.append("-" if None in (a, b) else "no surface" if not np.isfinite(a / b) else
                   f"{a / b:.2f}x ({a:.3g} / {b:.3g})")
    lines.append(f"| {LABELS[v]} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def section(mesh, y: float) -> np.ndarray:
  """[n, 2, 2] segments (x, z um) where the plane y = `y` cuts `mesh` (a trimesh)."""
  import trimesh
  seg = trimesh.intersections.mesh_plane(mesh, plane_normal=[0.0, 1.0, 0.0],
                                         plane_origin=[0.0, y, 0.0])
  return np.asarray(seg, np.float64).reshape(-1, 2, 3)[..., [0, 2]]


def farthest_point(truth: np.ndarray, cut: np.ndarray) -> np.ndarray:
  """[2] (x, z um): the point of `cut` ([n, 2, 2] segments) farthest from `truth` ([m, 2, 2]),
  both in the (x, z) plane of one section."""
  from scipy.spatial import cKDTree

  def dense(segments):  # points along every segment, so long segments count along their length
    t = np.linspace(0.0, 1.0, 9)[:, None, None]
    return (segments[None, :, 0] * (1 - t) + segments[None, :, 1] * t).reshape(-1, 2)

  points = dense(cut)
  return points[np.argmax(cKDTree(dense(truth)).query(points)[0])]


def sections(scene_dir: Path, runs: dict[str, dict]
             ) -> tuple[float, tuple[float, float], dict[str, np.ndarray]]:
  """The y (um) of the cut through the middle of the sample's box (the truth's meta.json), the
  box's x interval (um), and each method's segments ([n, 2, 2], x and z um) in the truth's frame,
  the truth's under "truth"; `runs` maps a variant to its record. No segments when the scene's
  truth is not on this machine."""
  from ofjax import eval as ev
  from ofjax.meshquery import load_mesh
  gt = Path(scene_dir) / "ground_truth"
  if not (gt / "mesh.ply").is_file():
    return 0.0, (0.0, 0.0), {}
  meta = json.loads((gt / "meta.json").read_text())
  box = np.asarray(meta["bbox_um"], np.float64)
  y = float(box[:, 1].mean())
  out = {"truth": section(load_mesh(gt / "mesh.ply"), y)}
  for v, r in runs.items():
    mesh_path = Path(r["result"]["run_dir"]) / "mesh.ply"
    if not mesh_path.is_file():
      continue
    mesh = load_mesh(mesh_path)
    if r["job"]["params"]["poses_source"] == "associate":
      ev.to_truth_frame(mesh, Path(r["job"]["params"]["poses"]), Path(scene_dir), meta)
    out[v] = section(mesh, y)
  return y, (float(box[0, 0]), float(box[1, 0])), out


def figure(path: Path, scene: str, records: list[dict]):
  """Per method (the first seed): the top-view render, the completeness and the accuracy heat
  maps; below, every method's cross-section through the middle of the scene against the truth's,
  whole and zoomed where the fused mesh is farthest from the truth. Returns the matplotlib Figure
  (saved to `path`)."""
  import matplotlib.image as mpimg
  from matplotlib.collections import LineCollection
  from matplotlib.figure import Figure

  from ofjax import plots
  finished = {r["job"]["variant"]: r for r in records if r["result"]["eval"] is not None}
  runs = {v: Path(r["result"]["run_dir"]) for v, r in finished.items()}
  methods = [v for v in VARIANTS if v in runs]
  images = ("preview.png", "mesh_completeness.png", "mesh_accuracy.png")
  fig = Figure(figsize=(4.2 * len(methods), 14.0))
  grid = fig.add_gridspec(len(images) + 1, 2 * len(methods))
  for col, v in enumerate(methods):
    for row, name in enumerate(images):
      ax = fig.add_subplot(grid[row, 2 * col:2 * col + 2])
      if (runs[v] / name).is_file():
        ax.imshow(mpimg.imread(runs[v] / name))
      else:  # a record kept from an earlier run (`reused_from`) whose directory is not here
        ax.text(0.5, 0.5, f"kept from an earlier run:\n{runs[v].name}\nnot on this machine",
                ha="center", va="center", wrap=True)
      ax.set_axis_off()
      if row == 0:
        ax.set_title(LABELS[v])
  y, (lo, hi), cuts = (sections(Path(records[0]["job"]["params"]["scene_dir"]), finished)
                       if records else (0.0, (0.0, 0.0), {}))
  if "truth" in cuts:
    whole = fig.add_subplot(grid[len(images), :len(methods)])
    zoom = fig.add_subplot(grid[len(images), len(methods):])
    probe = next((v for v in ("fused", *reversed(methods)) if v in cuts), None)
    on_sample = (lambda c: c[((c[..., 0] >= lo) & (c[..., 0] <= hi)).all(-1)])  # noqa: E731
    half = SECTION_ZOOM * (hi - lo)
    centre = (farthest_point(cuts["truth"], on_sample(cuts[probe]))
              if probe and on_sample(cuts[probe]).size else np.array([(lo + hi) / 2, 0.0]))
    palette = dict(zip(("truth", *VARIANTS), ("black", "C1", "C4", "C2", "C0", "C3")))
    for v in ("truth", *methods):
      if v in cuts:
        for ax in (whole, zoom):
          ax.add_collection(LineCollection(cuts[v], colors=palette[v], linewidths=1.0,
                                           label=LABELS.get(v, "truth")))
    z = np.concatenate([c[..., 1].ravel() for c in map(on_sample, cuts.values()) if c.size])
    pad = 0.05 * max(z.max() - z.min(), 1e-3)
    y_label = float(np.round(y)) + 0.0  # + 0.0: a cut at y = -0.2 um is labelled 0, not -0
    for ax, xlim, ylim, title in (
        (whole, (lo, hi), (z.min() - pad, z.max() + pad),
         f"cross-section at y = {y_label:.0f} um (z stretched)"),
        (zoom, centre[0] + np.array([-half, half]), centre[1] + np.array([-half, half]),
         f"zoom where {LABELS.get(probe, '')} is farthest from the truth (true shape)")):
      ax.set_xlim(*xlim)
      ax.set_ylim(*ylim)
      ax.set_xlabel("x (um)")
      ax.set_ylabel("z (um)")
      ax.set_title(title)
      ax.grid(alpha=0.3)
    zoom.set_aspect("equal", adjustable="box")
    zoom.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=9)
  fig.suptitle(f"{scene}: renders, completeness (truth -> mesh) and accuracy (mesh -> truth) heat "
               "maps (one colour scale for the scene: 0 .. 2% of the GT diagonal), cross-sections")
  fig.tight_layout()
  plots.save(fig, path)
  return fig


def remade_at(res: dict) -> dict | None:
  """The git state of the commit that made a result's mesh again after its run (`reevaluate`),
  None when the run's own mesh is kept. Records from before `mesh_git` was kept name only the
  commit that evaluated them again, which then also made the mesh."""
  if "export" in res.get("stages_s", {}) or res.get("mesh_remade"):
    return res.get("mesh_git") or res.get("eval_git")
  return None


def commits_line(records: list[dict]) -> str:
  """Which commits the runs ran at: the sweep keeps a finished run while its job (scene, variant,
  seed, config fingerprint) is unchanged, so a table can hold runs of several commits."""
  by_commit: dict[str, dict[str, int]] = {}
  for r in records:
    commit = r.get("result", {}).get("git", {}).get("commit")
    if commit:
      variants = by_commit.setdefault(commit[:7], {})
      variants[r["job"]["variant"]] = variants.get(r["job"]["variant"], 0) + 1
  parts = [f"`{c}` {sum(v.values())} (" + ", ".join(f"{LABELS.get(k, k)} {n}" for k, n in v.items())
           + ")" for c, v in by_commit.items()]
  again: dict[str, int] = {}  # meshes made again (`reevaluate`), by the commit that made them
  evaluated: dict[str, int] = {}  # runs evaluated again (`reevaluate`), by commit
  for r in records:
    res = r.get("result", {})
    if "eval_git" not in res:
      continue
    c = res["eval_git"]["commit"][:7]
    evaluated[c] = evaluated.get(c, 0) + 1
    made = remade_at(res)
    if made is not None:
      again[made["commit"][:7]] = again.get(made["commit"][:7], 0) + 1
  return ("Runs by the commit they ran at (a finished run is kept while its config fingerprint is "
          "unchanged): " + "; ".join(parts) + "."
          + "".join(f" {n} of their meshes made again at `{c}` (neural ones exported from the "
                    "runs' last checkpoints, Poisson ones reconstructed)."
                    for c, n in again.items())
          + "".join(f" {n} runs evaluated again at `{c}`." for c, n in evaluated.items())
          + (" A mesh is made again when the mesh making changed after its run: the vertex "
             "refinement (a0effaf), the faces no camera sees dropped (216466f), the grid of half "
             "a WLI pixel (42e29fa)." if again else "")
          + (" A run is evaluated again when its mesh is made again, when it was evaluated "
             "without moving associated poses into the truth's frame, and when it was evaluated "
             "before the completeness at the WLI-blind truth (875abd2)." if evaluated else ""))


def provenance(res: dict) -> str:
  """' (mesh made again at C, evaluated again at D)' for a run `reevaluate` touched, else ''."""
  if "eval_git" not in res:
    return ""
  made = remade_at(res)
  mesh = f"mesh made again at {made['commit'][:10]}, " if made is not None else ""
  return f" ({mesh}evaluated again at {res['eval_git']['commit'][:10]})"


def report(settings: dict, records: list[dict], summary: dict, figures: dict) -> str:
  scenes_all = settings["scenes"]
  lines = ["# Ablation (OpticFusion Table 1) on ofjax's synthetic scenes", "",
           f"Generated by `python experiments/ablation.py {' '.join(settings['argv'])}` at commit "
           f"`{settings['git']['commit']}`"
           + (f" (uncommitted changes: {settings['git']['uncommitted_code']})"
              if settings["git"]["uncommitted_code"] else "") + "."
           + ("" if settings["git_at_end"] == settings["git"] else
              f" The checkout changed during the run (at the end: `{settings['git_at_end']['commit']}`"
              f", uncommitted {settings['git_at_end']['uncommitted_code']}); stages that started "
              "later ran the later code.") + "", "", commits_line(records), "",
           f"Budget: training steps {settings['steps'] or 'the preset default'}, synth "
           f"resolution `{settings['resolution']}`, preset `{settings['preset']}` "
           f"(fingerprint `{settings.get('preset_fingerprint', '-')}`)"
           + ("" if settings["full_budget"] else " - **REDUCED BUDGET: not the issue's full run**")
           + ".", "",
           f"Machine: {machine.line(settings['machine'])} (load average at start "
           f"{settings['load_average']}); workers {settings['workers']}"
           + (f", Ray at {settings['ray']}" if settings["ray"] else "") + ".", "",
           "Chamfer = mean of accuracy (mesh -> truth) and completeness (truth -> mesh) in um "
           "(lower is better); F-score at 1% of the GT diagonal (higher is better); albedo PSNR "
           "of the vertex colours against the true albedo in dB. Cells with several seeds are mean ± sample std (n seeds).", ""]
  for ps, rows in summary.items():
    scenes = [s for s in scenes_all if s in rows]
    lines += [f"## Poses: {ps}", ""]
    if ps == "associate":
      lines += ["Pose errors of `ofjax.associate` against the truth (issue 5's targets: WLI <= 0.05 "
                "deg and 0.5 px; OM <= 0.2 deg, centre <= 0.5%, scale <= 0.5%):", "",
                association_table(records, scenes), ""]
    lines += ["### Chamfer (um)", "", metric_table(rows, scenes, "chamfer_um"), "",
              "### Accuracy (mesh -> truth, um)", "",
              "The Chamfer's two halves: a method that leaves out the surface it has no data for "
              "(Poisson trims its low-density vertices) pays in completeness only; one that "
              "guesses it (the neural SDF closes every void) pays in accuracy where the guess is "
              "off.", "", metric_table(rows, scenes, "accuracy_um"), "",
              "### Completeness (truth -> mesh, um)", "",
              metric_table(rows, scenes, "completeness_um"), "",
              "### Completeness where no WLI scan measured the truth (um)", "",
              *blind_lines(rows, scenes),
              "", "### Chamfer (WLI pixels)", "", metric_table(rows, scenes, "chamfer_px"), "",
              "### F-score @ 1% of the diagonal", "", metric_table(rows, scenes, "fscore"), "",
              "### Albedo PSNR (dB)", "", metric_table(rows, scenes, "albedo_psnr", 4), "",
              "### Ratios to fused, beside the paper's", "",
              "The paper's Table 1: conventional 0.793, OM-only 0.538, WLI-only 0.678, fused w/o "
              "residual 0.044, fused 0.043 (average Chamfer over its scenes).", "",
              ratio_table(rows, scenes), "", "### Where and why ours differ from the paper", "",
              *differences(rows, scenes, settings["steps"]), "", "### The issue's targets", "",
              *targets(rows, scenes), "", "### Figures", ""]
    lines += [f"![{s}]({figures[(ps, s)]})" for s in scenes if (ps, s) in figures] + [""]
  if {"associate", "true"} <= set(summary):
    lines += ["## Associated against true poses", "",
              "Chamfer on the poses `ofjax.associate` estimated / on the true poses (um in brackets; "
              "on the default scene the means over its seeds):", "",
              pose_source_table(summary, [s for s in scenes_all if s in summary["associate"]]), ""]
  lines += ["## Runs", "", "| poses | scene | variant | seed | wall s | stages (s) | machine | "
            "commit at start |", "|---|---|---|---|---|---|---|---|"]
  for r in records:
    j = r["job"]
    if "result" not in r:
      lines.append(f"| {j['params'].get('poses_source', '-')} | {j['scene']} | {j['variant']} | "
                   f"{j['seed']} | {r.get('wall_s', 0):.0f} | FAILED: {r.get('error', '')[:120]} | "
                   f"{r['machine']['host']} | |")
      continue
    st = ", ".join(f"{k} {v:.0f}" for k, v in r["result"]["stages_s"].items()) + (
        " (no surface)" if r["result"].get("no_surface") else "")
    lines.append(f"| {j['params'].get('poses_source', '-')} | {j['scene']} | {j['variant']} | "
                 f"{j['seed']} | {r['wall_s']:.0f} | {st} | {r['machine']['host']} | "
                 f"{(r['result'].get('git') or {}).get('commit', '-')[:10]}"
                 + provenance(r["result"]) + " |")
  return "\n".join(lines) + "\n"


def _list(text: str, allowed: tuple[str, ...], option: str) -> list[str]:
  items = [t.strip() for t in text.split(",") if t.strip()]
  bad = [t for t in items if t not in allowed]
  if not items or bad:
    raise UserError(f"{option} {text}: unknown {bad or 'empty list'}; choose from {', '.join(allowed)}")
  return items


def _seeds(text: str, option: str) -> list[int]:
  try:
    return [int(s) for s in text.split(",")]
  except ValueError:
    raise UserError(f"{option} {text}: give integers separated by commas, e.g. 0,1,2") from None


@cli
def main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else list(argv)
  p = argparse.ArgumentParser(prog="python experiments/ablation.py", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenes", default=",".join(SCENES), help="comma list (default: all five)")
  p.add_argument("--variants", default=",".join(VARIANTS), help="comma list (default: all five)")
  p.add_argument("--seeds", default="0", help="training seeds of the default scene `seed`, e.g. "
                 "0,1,2; the other scenes use the first")
  p.add_argument("--true-seeds", help="seeds of the default scene in the true-pose table "
                 "(default: --seeds)")
  p.add_argument("--poses", default=",".join(POSE_SOURCES),
                 help="associate (ofjax.associate), true (ground truth), or both (default)")
  p.add_argument("--true-poses", action="store_true", help="same as --poses true")
  p.add_argument("--steps", type=int, help="training steps (default: the preset's)")
  p.add_argument("--preset", default="cpu", help="the neural runs' preset, or a variant of it "
                 "such as cpu+loss.lambda_color=0.3 (default cpu)")
  p.add_argument("--resolution", default="quick", choices=("tiny", "quick", "full"),
                 help="synth resolution (default quick)")
  p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
  p.add_argument("--ray", metavar="ADDRESS", help="run the jobs as Ray tasks ('local' or an address)")
  p.add_argument("--work", type=Path, default=ROOT / "runs" / "ablation",
                 help="scenes, run directories and job records (default runs/ablation)")
  p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results",
                 help="ablation.json, ablation.md, figures/ (default experiments/results)")
  args = p.parse_args(argv)
  scenes = _list(args.scenes, SCENES, "--scenes")
  variants = _list(args.variants, VARIANTS, "--variants")
  poses = ["true"] if args.true_poses else _list(args.poses, POSE_SOURCES, "--poses")
  seeds = _seeds(args.seeds, "--seeds")
  seeds_of = {"associate": seeds, "true": _seeds(args.true_seeds or args.seeds, "--true-seeds")}
  if args.steps is not None and args.steps < 1 or args.workers < 1:
    raise UserError("--steps and --workers must be positive")

  # The checkout is shared and the stages run from it: the code state is taken before the first job
  # and again after the last, and the report says when they differ.
  git_start = git_state()
  data_work = args.work / f"data_{args.resolution}"
  try:
    fingerprint = preset_fingerprint(args.preset)
  except ValueError as e:
    raise UserError(f"--preset {e}") from None
  preset_name = args.preset.split("+")[0]
  work = args.work / f"steps{args.steps or 'preset'}_{args.resolution}_{preset_name}-{fingerprint}"
  log = lambda m: print(m, flush=True)  # noqa: E731
  t0 = time.time()
  # A scene synthesised for true poses only is not a finished data job of an associated table.
  data_tag = "_associated" if "associate" in poses else ""
  prep = [sweep.Job(scene=s, variant="data", seed=SYNTH_SEED,
                    result=str(data_work / "records" / f"data_{s}{data_tag}.json"),
                    params={"scene_dir": str(data_work / "scenes" / s), "resolution": args.resolution,
                            "associate": "associate" in poses}) for s in scenes]
  prep_records = sweep.run_jobs(prep, prepare, workers=args.workers, ray_address=args.ray, log=log)
  ready = {r["job"]["scene"] for r in prep_records if "result" in r}
  jobs = []
  for ps in poses:
    for s in sorted(ready, key=scenes.index):
      scene_dir = data_work / "scenes" / s
      pose_file = scene_dir / ("poses.json" if ps == "associate" else "ground_truth/poses.json")
      for v in variants:
        # Poisson is deterministic: one run, whatever the seeds.
        for seed in (seeds_of[ps][:1] if v == "conventional" or s != DEFAULT_SCENE else seeds_of[ps]):
          name = f"{ps}_{s}_{v}_seed{seed}"
          jobs.append(sweep.Job(scene=s, variant=v, seed=seed,
                                result=str(work / "records" / f"{name}.json"),
                                params={"poses_source": ps, "scene_dir": str(scene_dir),
                                        "poses": str(pose_file), "run_dir": str(work / "runs" / name),
                                        "steps": args.steps, "preset": args.preset}))
  records = reevaluate(sweep.run_jobs(jobs, run_method, workers=args.workers,
                                     ray_address=args.ray, log=log), jobs, log)

  summary = summarise(records)
  figures = {}
  for ps in poses:
    for s in scenes:
      done = [r for r in records if "result" in r and r["job"]["scene"] == s
              and r["job"]["params"]["poses_source"] == ps and r["job"]["seed"] == seeds_of[ps][0]]
      if done:
        path = args.out / "figures" / f"{ps}_{s}.png"
        figure(path, s, done)
        figures[(ps, s)] = str(path.relative_to(args.out))
  settings = {"argv": argv, "scenes": scenes, "variants": variants, "seeds": seeds,
              "true_seeds": seeds_of["true"], "poses": poses,
              "steps": args.steps, "resolution": args.resolution, "preset": args.preset,
              "preset_fingerprint": fingerprint,
              "full_budget": args.steps is None and args.resolution == "quick"
              and scenes == list(SCENES) and variants == list(VARIANTS) and poses == list(POSE_SOURCES),
              "workers": args.workers, "ray": args.ray, "work": str(work), "machine": machine.describe(),
              "load_average": [round(x, 2) for x in os.getloadavg()], "git": git_start,
              "git_at_end": git_state(),
              "total_wall_s": time.time() - t0}
  fileio.write_json(args.out / "ablation.json", {"settings": settings, "summary": summary,
                                                 "data_records": prep_records, "records": records})
  fileio.write_text(args.out / "ablation.md", report(settings, prep_records + records, summary, figures))
  failed = [r["name"] for r in prep_records + records if "error" in r]
  print(f"ablation: {len(records) - len(failed)} runs in {time.time() - t0:.0f} s; wrote "
        f"{args.out / 'ablation.md'} and {args.out / 'ablation.json'}"
        + (f"; FAILED: {', '.join(failed)}" if failed else ""))
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
