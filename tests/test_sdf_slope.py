"""experiments/sdf_slope.py: the SDF and its slope at the truth against a plane in closed form."""

import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import sdf_slope  # noqa: E402

from ofjax import checkpoint, config, fields, train  # noqa: E402

SCALE = 10.0  # um per normalised unit
LEVEL = 0.2  # the run's SDF is the plane z = LEVEL (normalised), z = 2 um


def _run(tmp_path, dead: bool) -> Path:
  """A run whose SDF is exactly sdf(x) = z - LEVEL (the "plane" init); `dead` turns every hidden
  unit of the SDF network off (a bias far below any input), so its slope is 0 everywhere."""
  cfg = config.resolve("cpu", model={"init_shape": "plane"}, optim={"ema_fraction": 0.0})
  params = fields.init_params(jax.random.PRNGKey(0), cfg, substrate=((0.0, 0.0, 1.0), LEVEL))
  if dead:
    params["sdf"]["Dense_0"]["bias"] = params["sdf"]["Dense_0"]["bias"] * 0.0 - 1e3
  run = tmp_path / ("dead" if dead else "plane")
  run.mkdir()
  checkpoint.save(run, 1, params, train.make_optimizer(cfg).init(params), keep=1)
  (run / "config.json").write_text(json.dumps({
      "config": cfg.to_dict(), "normalization": {"center": [0.0, 0.0, 0.0], "scale": SCALE},
      "observed_box": [[-1, -1, -1], [1, 1, 1]]}))
  return run


def _scene(tmp_path, z_um: float) -> Path:
  """A scene directory whose truth is the square |x|, |y| <= 5 um at height z_um."""
  gt = tmp_path / f"scene{z_um}" / "ground_truth"
  gt.mkdir(parents=True)
  trimesh.Trimesh([[-5, -5, z_um], [5, -5, z_um], [5, 5, z_um], [-5, 5, z_um]],
                  [[0, 1, 2], [0, 2, 3]]).export(gt / "mesh.ply")
  return gt.parent


# Off the plane's own level: the plane init's two hidden units are both at their kink there (ReLU's
# derivative at 0 is 0), so the slope exactly at the zero level is 0 by construction.
@pytest.mark.parametrize("z_um", [1.0, 3.5])
def test_a_plane_sdf_reads_its_offset_and_unit_slope(tmp_path, z_um):
  s = sdf_slope.slope_stats(_run(tmp_path, dead=False), _scene(tmp_path, z_um), n_points=500)
  assert s["points"] == 500
  # sdf(z) = z / SCALE - LEVEL in normalised units, times SCALE in um.
  want = z_um - LEVEL * SCALE
  np.testing.assert_allclose([s["sdf_median_um"], s["sdf_abs_mean_um"]], [want, abs(want)],
                             atol=1e-4)
  np.testing.assert_allclose([s["slope_p10"], s["slope_median"], s["slope_p90"]], 1.0, atol=1e-5)
  assert s["flat_share"] == 0.0


def test_a_network_with_every_unit_off_is_flat(tmp_path, capsys):
  run = _run(tmp_path, dead=True)
  s = sdf_slope.slope_stats(run, _scene(tmp_path, 2.0), n_points=300)
  assert s["flat_share"] == 1.0 and s["slope_median"] == 0.0
  assert sdf_slope.main([str(_scene(tmp_path, 3.0)), str(run), "--points", "50"]) == 0
  assert "flat (slope 0) 100.0%" in capsys.readouterr().out
