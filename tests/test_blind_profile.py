"""experiments/blind_profile.py: signed offsets against concentric spheres, and the CLI on a scene."""

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import blind_profile  # noqa: E402

from ofjax import synth  # noqa: E402
from ofjax.meshquery import MeshQuery  # noqa: E402

R = 30.0  # um, radius of the true sphere


def test_profile_of_spheres_inside_and_outside_the_truth():
  """Points on a sphere of radius R; meshes are spheres of radius R -+ delta: signed +-delta
  everywhere (the tessellation's error aside), and the bands split the points by slope."""
  rng = np.random.default_rng(3)
  n = rng.normal(size=(3000, 3))
  n /= np.linalg.norm(n, axis=1, keepdims=True)
  n[:, 2] = np.abs(n[:, 2])  # the upper half: outward normals point up
  p = R * n
  delta = 0.8
  signed = {k: blind_profile.signed_to(MeshQuery.of(trimesh.creation.icosphere(6, R + s)), p, n)
            for k, s in (("inner", -delta), ("outer", delta))}
  np.testing.assert_allclose(signed["inner"], delta, atol=0.02)
  np.testing.assert_allclose(signed["outer"], -delta, atol=0.02)
  rows = blind_profile.profile(p, n, signed, bands=(0.0, 30.0, 60.0, 90.0))
  slope = np.degrees(np.arccos(n[:, 2]))  # float64 reference
  want = [np.mean(slope < 30), np.mean((slope >= 30) & (slope < 60)), np.mean(slope >= 60)]
  np.testing.assert_allclose([r["share"] for r in rows], want)
  for r, lo in zip(rows, (0, 30, 60)):
    assert r["band"][0] == lo
    assert r["inner"][0] == pytest.approx(delta, abs=0.02)
    assert r["inner"][1] == pytest.approx(delta, abs=0.02)
    assert r["outer"][1] == pytest.approx(-delta, abs=0.02)
  steep = (slope >= 60)
  assert rows[2]["height_um"] == pytest.approx(p[steep, 2].mean())
  text = blind_profile.table(rows, ["inner", "outer"])
  assert "| 60-90 |" in text and "+0.80" in text and "-0.80" in text


def test_cli_on_a_synthetic_scene(tmp_path, capsys):
  """The true mesh of tiny `lenses` lies on every blind point (signed 0); bad bands are one
  line and exit code 2."""
  scene, gt = synth.make_scene("lenses", seed=0, resolution="tiny")
  synth.write(scene, gt, tmp_path, "native")
  gt.mesh.export(tmp_path / "truth.ply")
  assert blind_profile.main([str(tmp_path), f"truth={tmp_path / 'truth.ply'}"]) == 0
  out = capsys.readouterr().out
  rows = [line for line in out.splitlines() if line.startswith("| ") and "slope" not in line]
  assert len(rows) >= 2 and all("0.00 / +0.00" in r or "0.00 / -0.00" in r for r in rows)
  assert "no WLI scan measured" in out.splitlines()[0]
  assert blind_profile.main([str(tmp_path), str(tmp_path / "truth.ply"), "--bands", "50,10"]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "--bands" in err
