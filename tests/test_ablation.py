"""experiments/ablation.py: re-evaluation of finished runs, and the tables it adds to the report."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import ablation  # noqa: E402
import sweep  # noqa: E402


def _job(tmp_path: Path, source: str, variant: str = "fused") -> sweep.Job:
  name = f"{source}_seed_{variant}_seed0"
  return sweep.Job(scene="seed", variant=variant, seed=0, result=str(tmp_path / f"{name}.json"),
                   params={"poses_source": source, "scene_dir": str(tmp_path / "scene"),
                           "poses": str(tmp_path / f"{source}.json"),
                           "run_dir": str(tmp_path / name), "steps": 600, "preset": "cpu"})


def _finished(job: sweep.Job, **result) -> dict:
  record = {"job": {"scene": job.scene, "variant": job.variant, "seed": job.seed,
                    "result": job.result, "params": job.params},
            "name": job.name, "seed": job.seed, "wall_s": 1.0, "machine": {"host": "h"},
            "result": {"eval": {"chamfer_um": 9.0, "wli_blind_share": 0.1}, "stages_s": {"train": 5.0, "eval": 1.0},
                       "run_dir": job.params["run_dir"], "git": {"commit": "a" * 40}, **result}}
  Path(job.result).write_text(json.dumps(record))
  return {**record, "skipped": True}


def test_committed_results_were_trained_with_the_committed_preset():
  """The fingerprint the committed results name is the one ablation.py trains with now, so `make
  reproduce` keeps their runs instead of training them again."""
  committed = Path(__file__).resolve().parents[1] / "experiments/results/ablation.json"
  recorded = json.loads(committed.read_text())
  assert recorded["settings"]["preset_fingerprint"] == ablation.preset_fingerprint()


def test_reevaluate_redoes_only_runs_evaluated_with_other_arguments(tmp_path, monkeypatch):
  """An associated run evaluated before --poses is re-evaluated (its training kept, both commits
  recorded, its record file rewritten); a neural run whose mesh was extracted with another vertex
  refinement or with the hidden faces is exported again first, a Poisson run with the hidden faces
  reconstructed again; a run evaluated before the WLI-blind split is evaluated again as it is;
  true-pose runs and up-to-date ones are left alone."""
  calls, exported = [], []

  def fake_evaluated(job, stages, git):
    calls.append(job.name)
    return {"eval": {"chamfer_um": 1.0, "wli_blind_share": 0.2}, "stages_s": {**stages, "eval": 2.0},
            "run_dir": job.params["run_dir"], "git": git, "eval_args": ablation.eval_args(job),
            "export_refine_steps": ablation.export.REFINE_STEPS, "hidden_dropped": True,
            "export_grid": ablation.mesh_grid()}

  def fake_cli(module, *args):
    exported.append((module, args))
    return "", 3.0

  monkeypatch.setattr(ablation, "_evaluated", fake_evaluated)
  monkeypatch.setattr(ablation, "run_cli", fake_cli)
  old, true, current, stale = (_job(tmp_path, "associate"), _job(tmp_path, "true"),
                               _job(tmp_path, "associate", "wli"), _job(tmp_path, "true", "om"))
  hidden, poisson, poisson_now = (_job(tmp_path, "true", "fused_nores"),
                                  _job(tmp_path, "true", "conventional"),
                                  _job(tmp_path, "associate", "conventional"))
  now = {"export_refine_steps": ablation.export.REFINE_STEPS, "hidden_dropped": True,
         "export_grid": ablation.mesh_grid()}
  coarse = _job(tmp_path, "associate", "fused_nores")  # meshed on the grid before export_grid
  now_but_grid = {k: v for k, v in now.items() if k != "export_grid"}
  unsplit = _job(tmp_path, "true", "wli")  # up to date but for the blind split
  records = [_finished(old, **now), _finished(true, eval_args=[], **now),
             _finished(current, eval_args=ablation.eval_args(current), **now),
             _finished(stale, eval_args=[]),  # exported before the refinement: 0 steps
             {"job": {"result": "x"}, "name": "failed", "error": "boom"},
             _finished(hidden, eval_args=[], export_refine_steps=ablation.export.REFINE_STEPS),
             _finished(poisson, eval_args=[]),
             _finished(poisson_now, eval_args=ablation.eval_args(poisson_now), hidden_dropped=True),
             _finished(coarse, eval_args=ablation.eval_args(coarse), **now_but_grid),
             _finished(unsplit, eval_args=[], **now)]
  records[-1]["result"]["eval"] = {"chamfer_um": 9.0}
  out = ablation.reevaluate(records, [old, true, current, stale, hidden, poisson, poisson_now,
                                      coarse, unsplit], log=lambda m: None)
  assert calls == [old.name, stale.name, hidden.name, poisson.name, coarse.name, unsplit.name]
  p = poisson.params
  grid = ("--resolution", str(ablation.mesh_grid()["mesh_resolution"]))
  assert grid == ("--resolution", "0")  # the cpu preset's: cells of half a WLI pixel
  assert exported == [("export", (stale.params["run_dir"], *grid)),
                      ("export", (hidden.params["run_dir"], *grid)),
                      ("conventional",
                       (p["scene_dir"], "--out", p["run_dir"], "--poses", p["poses"])),
                      ("export", (coarse.params["run_dir"], *grid))]
  assert ablation.eval_args(old) == ["--poses", old.params["poses"]]
  assert ablation.eval_args(true) == []
  assert out[0]["result"]["eval"] == {"chamfer_um": 1.0, "wli_blind_share": 0.2}
  assert out[0]["result"]["stages_s"] == {"train": 5.0, "eval": 2.0}
  assert out[3]["result"]["stages_s"] == {"train": 5.0, "export": 3.0, "eval": 2.0}
  assert [r["result"].get("mesh_remade", False) for r in (out[0], out[3], out[5], out[6], out[8],
                                                           out[9])] == [False, True, True, True,
                                                                        True, False]
  assert out[3]["result"]["mesh_git"] == out[3]["result"]["eval_git"]
  assert out[0]["result"]["git"]["commit"] == "a" * 40 and "commit" in out[0]["result"]["eval_git"]
  stored = json.loads(Path(old.result).read_text())
  assert stored["result"]["eval"]["chamfer_um"] == 1.0 and "skipped" not in stored
  assert json.loads(Path(true.result).read_text())["result"]["eval"]["chamfer_um"] == 9.0


def test_pose_source_table_gives_the_ratio_per_method_and_scene():
  cell = lambda v: {"chamfer_um": (v, float("nan"), 1)}  # noqa: E731
  summary = {"associate": {"seed": {"fused": cell(3.0), "om": cell(float("inf"))}},
             "true": {"seed": {"fused": cell(2.0), "om": cell(float("inf"))}}}
  rows = {line.split(" | ")[0].strip("| "): line for line in
          ablation.pose_source_table(summary, ["seed"]).splitlines()}
  assert "1.50x (3 / 2)" in rows["Fused"]
  assert "no surface" in rows["OM only"]
  assert rows["WLI only"].endswith("| - |")


def test_mean_and_spread_of_seeds():
  assert ablation._mean_sd([1.0, 2.0, 3.0]) == (2.0, 1.0, 3)
  mean, sd, n = ablation._mean_sd([1.0, float("inf")])
  assert np.isinf(mean) and np.isnan(sd) and n == 2


def test_no_surface_note_says_when_only_some_seeds_had_none():
  def rec(scene, seed, ev):
    return {"job": {"scene": scene, "variant": "om", "seed": seed,
                    "params": {"poses_source": "true"}}, "result": {"eval": ev}}
  ev = {"chamfer_um": 47.0, "chamfer_px": 39.0, "fscore": [{"fscore": 0.07}], "albedo_psnr": 15.5}
  rows = ablation.summarise([rec("seed", 0, None), rec("seed", 1, ev), rec("wing", 0, None)])["true"]
  assert np.isinf(rows["seed"]["om"]["chamfer_um"][0])
  note = [b for b in ablation.differences(rows, ["seed", "wing"], 600) if "OM only" in b]
  assert len(note) == 1 and "on 2 of 2 scenes (seed, wing)" in note[0]
  assert "on seed in some of the seeds only" in note[0]


def test_accuracy_and_completeness_tables_carry_the_chamfers_halves():
  def rec(scene, seed, ev):
    return {"job": {"scene": scene, "variant": "fused", "seed": seed,
                    "params": {"poses_source": "true"}}, "result": {"eval": ev}}
  ev = lambda acc, comp: {"chamfer_um": (acc + comp) / 2, "chamfer_px": 1.0,  # noqa: E731
                          "fscore": [{"fscore": 0.9}], "albedo_psnr": 20.0, "accuracy_um": acc,
                          "completeness_um": comp}
  old = {"chamfer_um": 1.0, "chamfer_px": 1.0, "fscore": [{"fscore": 0.9}], "albedo_psnr": 20.0}
  rows = ablation.summarise([rec("seed", 0, ev(0.9, 0.3)), rec("seed", 1, ev(1.1, 0.5)),
                             rec("wing", 0, old)])["true"]
  assert rows["seed"]["fused"]["accuracy_um"][:1] == (1.0,)
  assert rows["seed"]["fused"]["completeness_um"][0] == pytest.approx(0.4)
  assert np.isnan(rows["wing"]["fused"]["accuracy_um"][0])  # evaluated before: not measured
  line = next(x for x in ablation.metric_table(rows, ["seed", "wing"], "accuracy_um").splitlines()
              if x.startswith("| Fused |"))
  assert "| 1 ± 0.14 (n=2) | n/a |" in line


def test_wli_blind_section_and_the_lenses_reading_on_it():
  """The blind share comes from whichever method was evaluated with it; the completeness table
  over the blind truth, the ratios there in the targets and the differences follow the rows."""
  def rec(scene, variant, comp_blind, share):
    ev = {"chamfer_um": 1.0, "chamfer_px": 1.0, "fscore": [{"fscore": 0.9}], "albedo_psnr": 20.0,
          "accuracy_um": 1.0, "completeness_um": 1.0, "completeness_blind_um": comp_blind,
          "wli_blind_share": share}
    return {"job": {"scene": scene, "variant": variant, "seed": 0,
                    "params": {"poses_source": "true"}}, "result": {"eval": ev}}
  records = [rec("lenses", "conventional", 2.5, 0.356), rec("lenses", "wli", 1.6, 0.356),
             rec("lenses", "fused", 1.25, 0.356), rec("lenses", "om", 9.0, 0.356),
             rec("lenses", "fused_nores", 2.0, 0.356), rec("wing", "fused", 0.3, 0.003)]
  rows = ablation.summarise(records)["true"]
  assert ablation.blind_share(rows, "wing") == pytest.approx(0.003)
  text = "\n".join(ablation.blind_lines(rows, ["lenses", "wing"]))
  assert "lenses 35.6%, wing 0.3%" in text
  assert "| Fused | 1.25 | 0.3 | 0.775 |" in text
  assert "| WLI only | 1.6 | - | - |" in text  # not run on wing: no average
  line = next(t for t in ablation.targets(rows, ["lenses"]) if "WLI-blind truth alone" in t)
  assert "conventional/fused 2.00x (>= 5x: MISSED)" in line and "WLI-only/fused 1.28x" in line
  sentence = ablation.blind_sentence(rows, ["lenses", "wing"])
  assert "No WLI scan measured 36% of the truth of `lenses` (0.3-0.3% of the others')" in sentence
  assert "Poisson / fused 2.00x, WLI only / fused 1.28x" in sentence
  unsplit = ablation.summarise([{**r, "result": {"eval": {
      k: v for k, v in r["result"]["eval"].items() if "blind" not in k}}} for r in records])["true"]
  assert ablation.blind_lines(unsplit, ["lenses"])[0].startswith("Not measured")
  assert ablation.blind_sentence(unsplit, ["lenses"]) == ""
  assert not any("blind truth alone" in t for t in ablation.targets(unsplit, ["lenses"]))


def test_figure_marks_a_kept_run_whose_directory_is_gone(tmp_path):
  """A record kept from an earlier run (its run directory on another machine) gets a text panel;
  the figure is still written with the other methods' images."""
  import matplotlib
  matplotlib.use("Agg")
  from matplotlib import pyplot as plt
  here, gone = _job(tmp_path, "associate", "fused"), _job(tmp_path, "associate", "om")
  Path(here.params["run_dir"]).mkdir()
  for name in ("preview.png", "mesh_completeness.png"):
    plt.imsave(Path(here.params["run_dir"]) / name, np.zeros((4, 4, 3)))
  records = [_finished(here), _finished(gone)]
  out = tmp_path / "figures" / "associate_seed.png"
  ablation.figure(out, "seed", records)
  assert plt.imread(out).shape[1] > plt.imread(out).shape[0]  # two methods side by side


def test_reevaluation_keeps_the_provenance_of_a_mesh_made_again_before(tmp_path, monkeypatch):
  """A run whose mesh an earlier commit exported again, evaluated again now for the blind split:
  its export time and the commit that made the mesh stay; the new evaluation's commit is added."""
  monkeypatch.setattr(ablation, "_evaluated", lambda job, stages, git: {
      "eval": {"chamfer_um": 1.0, "wli_blind_share": 0.2}, "stages_s": {**stages, "eval": 2.0},
      "run_dir": job.params["run_dir"], "git": git, "eval_args": ablation.eval_args(job),
      "export_refine_steps": ablation.export.REFINE_STEPS, "hidden_dropped": True,
      "export_grid": ablation.mesh_grid()})
  monkeypatch.setattr(ablation, "run_cli", lambda *a: pytest.fail(f"mesh made again: {a}"))
  job = _job(tmp_path, "true")
  rec = _finished(job, eval_args=[], export_refine_steps=ablation.export.REFINE_STEPS,
                  hidden_dropped=True, export_grid=ablation.mesh_grid(),
                  eval_git={"commit": "b" * 40})
  rec["result"]["stages_s"] = {"train": 5.0, "export": 3.0, "eval": 1.0}
  rec["result"]["eval"] = {"chamfer_um": 9.0}  # evaluated before the blind split
  (res,) = [r["result"] for r in ablation.reevaluate([rec], [job], log=lambda m: None)]
  assert res["stages_s"] == {"train": 5.0, "export": 3.0, "eval": 2.0}
  assert res["mesh_remade"] and res["mesh_git"] == {"commit": "b" * 40}
  assert res["eval_git"]["commit"] != "b" * 40
  assert ablation.provenance(res) == (f" (mesh made again at bbbbbbbbbb, evaluated again at "
                                      f"{res['eval_git']['commit'][:10]})")
  assert ablation.provenance({"stages_s": {}}) == ""
  line = ablation.commits_line([{**rec, "result": res}])
  assert "1 of their meshes made again at `bbbbbbb`" in line
  assert f"1 runs evaluated again at `{res['eval_git']['commit'][:7]}`" in line


def test_commits_line_counts_runs_and_the_meshes_exported_again(tmp_path):
  fused, wli = _job(tmp_path, "true"), _job(tmp_path, "true", "wli")
  records = [_finished(fused), _finished(wli)]
  records[1]["result"]["stages_s"]["export"] = 3.0
  records[1]["result"]["eval_git"] = {"commit": "b" * 40}
  line = ablation.commits_line(records)
  assert "`aaaaaaa` 2 (Fused 1, WLI only 1)" in line
  assert "1 of their meshes made again at `bbbbbbb`" in line
  assert "1 runs evaluated again at `bbbbbbb`" in line
  assert "made again" not in ablation.commits_line(records[:1])
  records[0]["result"].update(mesh_remade=True, eval_git={"commit": "b" * 40})  # a Poisson remade
  assert "2 of their meshes made again at `bbbbbbb`" in ablation.commits_line(records)
  records[0]["result"].update(mesh_git={"commit": "c" * 40})  # remade at c, evaluated at b
  line = ablation.commits_line(records)
  assert "1 of their meshes made again at `ccccccc`" in line and "2 runs evaluated again" in line


def test_section_of_a_sphere_is_the_circle_of_its_plane():
  """The plane y = 3 cuts a sphere of radius 5 in the circle of radius 4 around (x, z) = (1, 2);
  every segment end lies on it to the mesh's facet error, and the segments go all round."""
  import trimesh
  sphere = trimesh.creation.icosphere(subdivisions=5, radius=5.0)
  sphere.apply_translation([1.0, 0.0, 2.0])
  seg = ablation.section(sphere, 3.0)
  assert seg.ndim == 3 and seg.shape[1:] == (2, 2) and seg.dtype == np.float64
  radius = np.linalg.norm(seg.reshape(-1, 2) - [1.0, 2.0], axis=-1)
  np.testing.assert_allclose(radius, 4.0, rtol=5e-3)
  angle = np.arctan2(*(seg.reshape(-1, 2) - [1.0, 2.0]).T[::-1])
  assert np.ptp(angle) > 0.99 * 2 * np.pi
  assert ablation.section(sphere, 6.0).shape == (0, 2, 2)  # above the sphere: no cut


def test_farthest_point_finds_the_bump():
  """A flat truth and a cut with a 2 um bump at x = 3: the farthest point is the bump's top, also
  when the truth is drawn with segments far longer than the cut's."""
  xs = np.linspace(-10.0, 10.0, 201)
  z = 2.0 * np.exp(-((xs - 3.0) / 0.5) ** 2)
  cut = np.stack([np.stack([xs[:-1], z[:-1]], -1), np.stack([xs[1:], z[1:]], -1)], 1)
  truth = np.array([[[-10.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [10.0, 0.0]]])
  np.testing.assert_allclose(ablation.farthest_point(truth, cut), [3.0, 2.0], atol=0.06)


def test_figure_draws_the_cross_sections_against_the_truth(tmp_path):
  """With the truth and a method's mesh on this machine the figure gains the cross-section row,
  in the truth's frame for true poses; without the truth it has none."""
  import matplotlib
  matplotlib.use("Agg")
  import trimesh
  from matplotlib import pyplot as plt
  gt = tmp_path / "scene" / "ground_truth"
  gt.mkdir(parents=True)
  trimesh.creation.box(extents=[40.0, 40.0, 10.0]).export(gt / "mesh.ply")
  (gt / "meta.json").write_text(json.dumps({"bbox_um": [[-20, -20, -5], [20, 20, 5]]}))
  job = _job(tmp_path, "true", "fused")
  Path(job.params["run_dir"]).mkdir()
  moved = trimesh.creation.box(extents=[40.0, 40.0, 10.0])
  moved.apply_translation([0.0, 0.0, 1.0])
  moved.export(Path(job.params["run_dir"]) / "mesh.ply")
  y, (lo, hi), cuts = ablation.sections(tmp_path / "scene", {"fused": _finished(job)})
  assert y == 0.0 and (lo, hi) == (-20.0, 20.0) and set(cuts) == {"truth", "fused"}
  np.testing.assert_allclose(cuts["fused"][..., 1].max() - cuts["truth"][..., 1].max(), 1.0)
  fig = ablation.figure(tmp_path / "with.png", "seed", [_finished(job)])
  assert len(fig.axes) == 3 + 2  # render and two heat maps for the one method, whole and zoom
  zoom = fig.axes[-1]
  assert [c.get_label() for c in zoom.collections] == ["truth", "Fused"]
  np.testing.assert_allclose(zoom.collections[1].get_segments()[0], cuts["fused"][0])
  elsewhere = _job(tmp_path / "scene", "true", "fused")  # its scene_dir holds no truth
  Path(elsewhere.params["run_dir"]).mkdir()
  assert len(ablation.figure(tmp_path / "without.png", "seed", [_finished(elsewhere)]).axes) == 3


def test_preset_variant_reaches_the_training_and_names_its_fingerprint():
  """--preset's variant becomes ofjax.train options that resolve to the config the work directory
  is named by; a method's own flags come after it and win (OM only's colour weight), and the
  default is the cpu preset itself."""
  from ofjax import config, train
  variant = "cpu+model.color_features=own+loss.lambda_color=0.3"

  def trained(preset, method):
    flags = [*ablation.preset_flags(preset), *ablation.TRAIN_FLAGS[method]]
    args = train.build_parser().parse_args(["--data", "d", "--out", "o", "--seed", "0", *flags])
    return train.config_from_args(args)

  assert ablation.preset_flags("cpu") == ["--preset", "cpu"]
  fused = trained(variant, "fused")
  assert fused.model.color_features == "own" and fused.loss.lambda_color == 0.3
  assert fused.fingerprint() == ablation.preset_fingerprint(variant) != ablation.preset_fingerprint()
  om = trained(variant, "om")
  assert om.loss.lambda_color == 1.0 and om.model.init_shape == "plane"
  assert om.model.color_features == "own"
  assert trained("cpu", "fused").fingerprint() == config.resolve("cpu").fingerprint()
  assert ablation.mesh_grid(variant) == ablation.mesh_grid()


def test_unknown_preset_field_is_a_user_error(tmp_path, capsys):
  """A --preset naming a field the config lacks exits 2 with one line, before any job runs."""
  code = ablation.main(["--preset", "cpu+model.no_such_field=1", "--work", str(tmp_path / "w"),
                        "--out", str(tmp_path / "out")])
  err = capsys.readouterr().err.strip()
  assert code == 2 and err.startswith("ofjax: error: --preset") and "no_such_field" in err
  assert len(err.splitlines()) == 1 and not (tmp_path / "w").exists()
