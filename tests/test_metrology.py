"""Roughness and profiles against analytic surfaces, a float64 reference and surfalize."""

import json

import numpy as np
import pytest
import surfalize
import trimesh

from ofjax import metrology

A = 1.5  # um, sinusoid amplitude
WAVELENGTH = 20.0  # um
PERIODS = 8  # whole periods across the region: the least-squares plane of a whole-period
# sinusoid of any phase has a slope that shrinks Sq by only 3 / (pi^2 n^2) relative (0.5% at 8).


def heightfield_mesh(x: np.ndarray, y: np.ndarray, height) -> trimesh.Trimesh:
  """A triangulated grid z = height(x, y) over the 1-D coordinate arrays x [nx], y [ny]."""
  gx, gy = np.meshgrid(x, y)
  verts = np.stack([gx, gy, height(gx, gy)], -1).reshape(-1, 3)
  nx = len(x)
  i, j = np.meshgrid(np.arange(len(y) - 1), np.arange(nx - 1), indexing="ij")
  v00 = (i * nx + j).ravel()
  v01, v10, v11 = v00 + 1, v00 + nx, v00 + nx + 1
  faces = np.concatenate([np.stack([v00, v01, v11], -1), np.stack([v00, v11, v10], -1)])
  return trimesh.Trimesh(verts, faces, process=False)


def cosine(gx, gy):
  return A * np.cos(2 * np.pi * gx / WAVELENGTH)


def reference(z: np.ndarray) -> dict:
  """Float64 ISO 25178-2 definitions written out directly."""
  d = z - z.mean()
  sq = np.sqrt(np.mean(d * d))
  return {"Sa": np.mean(np.abs(d)), "Sq": sq, "Sp": d.max(), "Sv": -d.min(),
          "Sz": d.max() - d.min(), "Ssk": np.mean(d ** 3) / sq ** 3, "Sku": np.mean(d ** 4) / sq ** 4}


def analytic_cosine() -> dict:
  # mean |cos| = 2/pi, rms = 1/sqrt2, kurtosis of a sinusoid = 3/2.
  return {"Sa": 2 * A / np.pi, "Sq": A / np.sqrt(2), "Sp": A, "Sv": A, "Sz": 2 * A, "Ssk": 0.0,
          "Sku": 1.5}


def assert_close_to_analytic(p: dict, rel: float) -> None:
  want = analytic_cosine()
  for k in ("Sa", "Sq", "Sp", "Sv", "Sz", "Sku"):
    assert p[k] == pytest.approx(want[k], rel=rel), k
  assert abs(p["Ssk"]) < rel


def test_sinusoid_grid_whole_periods():
  n = 400
  x = (np.arange(n) + 0.5) / n * PERIODS * WAVELENGTH
  z = np.tile(A * np.sin(2 * np.pi * x / WAVELENGTH), (50, 1))
  assert_close_to_analytic(metrology.areal_parameters(z), rel=0.01)


def test_matches_float64_reference_and_surfalize():
  rng = np.random.default_rng(3)
  z = rng.gamma(2.0, 0.4, size=(60, 80)) + np.linspace(0, 1, 80)  # skewed, not centred
  got = metrology.areal_parameters(z)
  ref = reference(z)
  surf = surfalize.Surface(z, 0.5, 0.5)
  for k in metrology.PARAMETERS:
    assert got[k] == pytest.approx(ref[k], rel=1e-12), k
    assert got[k] == pytest.approx(getattr(surf, k)(), rel=1e-9), k


def test_nan_points_are_left_out():
  rng = np.random.default_rng(4)
  z = rng.normal(size=(30, 30))
  holes = z.copy()
  holes[rng.random(z.shape) < 0.2] = np.nan
  got = metrology.areal_parameters(holes)
  ref = reference(holes[np.isfinite(holes)])
  for k in metrology.PARAMETERS:
    assert got[k] == pytest.approx(ref[k], rel=1e-12), k


def test_tilted_plane_levels_to_zero():
  gx, gy = np.meshgrid(np.linspace(-50, 80, 64), np.linspace(10, 60, 40))
  z = 0.3 * gx - 0.7 * gy + 12.0
  p = metrology.areal_parameters(metrology.level(z, gx, gy))
  assert p["Sa"] < 1e-9 and p["Sq"] < 1e-9 and p["Sz"] < 1e-8


def test_levelling_removes_tilt_under_a_sinusoid():
  n = 256
  x = (np.arange(n) + 0.5) / n * PERIODS * WAVELENGTH
  gx, gy = np.meshgrid(x, np.linspace(0, 30, 20))
  z = cosine(gx, gy) + 0.2 * gx + 0.05 * gy
  assert_close_to_analytic(metrology.areal_parameters(metrology.level(z, gx, gy)), rel=0.01)


def sinusoid_mesh() -> trimesh.Trimesh:
  half = PERIODS * WAVELENGTH  # twice the region, so tilted rays still land on the mesh
  return heightfield_mesh(np.linspace(-half, half, 2 * PERIODS * 40 + 1),
                          np.linspace(-40, 40, 21), cosine)


REGION = (-PERIODS * WAVELENGTH / 2, -15.0, PERIODS * WAVELENGTH / 2, 15.0)


def test_mesh_route_matches_analytic():
  mesh = sinusoid_mesh()
  grid = metrology.sample_region(mesh.vertices, mesh.faces, REGION, n=320)
  assert np.isfinite(grid.z).all() and grid.tilt_deg < 0.1
  assert grid.z.shape == (60, 320)
  assert_close_to_analytic(metrology.areal_parameters(grid.z), rel=0.015)


def test_mesh_route_levels_a_tilted_mesh():
  tilt = np.radians(10.0)
  mesh = sinusoid_mesh()
  rot = trimesh.transformations.rotation_matrix(tilt, [0, 1, 0])
  mesh.apply_transform(rot)
  mesh.apply_translation([1e4, -2e4, 500.0])  # far from the origin, as on a real stage
  region = (REGION[0] + 1e4, REGION[1] - 2e4, REGION[2] + 1e4, REGION[3] - 2e4)
  grid = metrology.sample_region(mesh.vertices, mesh.faces, region, n=320)
  assert grid.tilt_deg == pytest.approx(10.0, abs=0.2)
  assert np.isfinite(grid.z).all()
  assert_close_to_analytic(metrology.areal_parameters(grid.z), rel=0.02)


def test_profile_follows_the_surface():
  mesh = sinusoid_mesh()
  s, xyz = metrology.profile(mesh.vertices, mesh.faces, (-30.0, 2.0), (30.0, 10.0), n=201)
  assert s[0] == 0 and s[-1] == pytest.approx(np.hypot(60.0, 8.0))
  # Piecewise-linear mesh of spacing h: |error| <= A (2 pi h / wavelength)^2 / 8.
  h = WAVELENGTH / 40
  np.testing.assert_allclose(xyz[:, 2], cosine(xyz[:, 0], xyz[:, 1]),
                             atol=A * (2 * np.pi * h / WAVELENGTH) ** 2 / 8 + 1e-4)
  _, off = metrology.profile(mesh.vertices, mesh.faces, (0.0, 0.0), (0.0, 105.0), n=8)
  assert np.isnan(off[:, 2]).tolist() == [False] * 3 + [True] * 5  # y > 40 um is beyond the mesh


def test_measure_cli(tmp_path, capsys):
  from ofjax import measure
  path = tmp_path / "wave.ply"
  sinusoid_mesh().export(path)
  region = ",".join(str(v) for v in REGION)
  assert measure.main(["roughness", "--mesh", str(path), f"--region={region}", "--grid", "128",
                       "--json"]) == 0
  out = json.loads(capsys.readouterr().out)
  assert set(metrology.PARAMETERS) <= set(out) and out["n_missing"] == 0
  assert out["Sq"] == pytest.approx(A / np.sqrt(2), rel=0.02)
  assert (tmp_path / "wave_roughness.png").stat().st_size > 0

  assert measure.main(["profile", "--mesh", str(path), "--from=-30,0", "--to", "30,0",
                       "--n", "61"]) == 0
  rows = np.loadtxt(tmp_path / "wave_profile.csv", delimiter=",", skiprows=1)
  assert rows.shape == (61, 4)
  np.testing.assert_allclose(rows[:, 3], cosine(rows[:, 1], rows[:, 2]), atol=0.02)
  assert (tmp_path / "wave_profile.png").stat().st_size > 0


@pytest.mark.parametrize("region", ["1,2,3", "5,0,1,10", "a,b,c,d", "1000,1000,2000,2000"])
def test_measure_cli_bad_region(tmp_path, capsys, region):
  from ofjax import measure
  path = tmp_path / "wave.ply"
  sinusoid_mesh().export(path)
  assert measure.main(["roughness", "--mesh", str(path), f"--region={region}"]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "--region" in err
  assert not (tmp_path / "wave_roughness.png").exists()


def test_flat_region_gives_null_skewness_in_json(tmp_path, capsys):
  from ofjax import measure
  path = tmp_path / "flat.ply"
  heightfield_mesh(np.linspace(0, 10, 11), np.linspace(0, 10, 11), lambda x, y: 0 * x).export(path)
  assert measure.main(["roughness", "--mesh", str(path), "--region", "2,2,8,8", "--json"]) == 0
  out = json.loads(capsys.readouterr().out)
  assert out["Sa"] == 0.0 and out["Ssk"] is None and out["Sku"] is None
