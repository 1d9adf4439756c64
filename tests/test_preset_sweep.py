"""experiments/preset_sweep.py: variants of a preset trained, exported and scored on one scene."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import preset_sweep  # noqa: E402

# A small engine for a tiny scene: the sweep's machinery is under test, not the accuracy.
SMALL = "cpu+hash.log2_table_size=12+train.n_rays=64+train.mesh_resolution=48"


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
  out = tmp_path_factory.mktemp("sweep") / "scene"
  subprocess.run([sys.executable, "-m", "ofjax.synth", "--scene", "seed", "--resolution", "tiny",
                  "--out", str(out)], check=True, capture_output=True)
  return out


@pytest.mark.slow
def test_sweep_scores_each_variant_and_skips_finished_ones(tiny_scene, tmp_path, capsys):
  variants = f"{SMALL},{SMALL}+optim.lr_inv_s=0.05"
  argv = ["--scene-dir", str(tiny_scene), "--variants", variants, "--steps", "12", "--quiet",
          "--work", str(tmp_path)]
  assert preset_sweep.main(argv) == 0
  records = json.loads((tmp_path / "preset_sweep.json").read_text())["records"]
  assert [r["job"]["variant"] for r in records] == variants.split(",")
  res = [r["result"] for r in records]
  assert res[0]["fingerprint"] != res[1]["fingerprint"]
  for r in res:
    assert r["steps"] == 12 and Path(r["run_dir"], "mesh.ply").exists()
    assert np.isfinite(r["eval"]["chamfer_um"]) and r["eval"]["chamfer_um"] > 0
  # The variance's rate is what differs: a 50x rate moves s further from its start in 12 steps.
  s0 = np.exp(10 * 0.3)
  assert abs(res[1]["inv_s"] - s0) > abs(res[0]["inv_s"] - s0)
  table = (tmp_path / "preset_sweep.md").read_text()
  assert table.count(f"| `{SMALL}") == 2
  capsys.readouterr()
  assert preset_sweep.main(argv) == 0  # everything finished: nothing retrains
  assert "2 finished before, 0 to run" in capsys.readouterr().out


def test_unknown_variant_field_is_a_user_error(tiny_scene, tmp_path, capsys):
  argv = ["--scene-dir", str(tiny_scene), "--variants", "cpu+optim.no_such=1", "--work",
          str(tmp_path)]
  assert preset_sweep.main(argv) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "no_such" in err
  assert not (tmp_path / "records").exists()


def test_bad_variant_is_refused_before_any_scene_is_made(tmp_path, capsys):
  assert preset_sweep.main(["--variants", "cpu,cpu+hash.nosuch=1", "--work", str(tmp_path)]) == 2
  assert "nosuch" in capsys.readouterr().err
  assert list(tmp_path.iterdir()) == []


def test_steps_shorten_a_variant_as_the_train_cli_does():
  from ofjax import train
  args = train.build_parser().parse_args(["--data", "scene", "--out", "run", "--steps", "600",
                                          "--seed", "3"])
  assert preset_sweep.variant_config("cpu", 3, 600) == train.config_from_args(args)
  assert preset_sweep.variant_config("cpu", 3, 600).render.cos_anneal_steps == 600
