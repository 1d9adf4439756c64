"""Chamfer / F-score / normal / albedo metrics on meshes whose true errors are known exactly."""

import json

import numpy as np
import open3d as o3d
import pytest
import trimesh

from ofjax import eval as evaluation
from ofjax import metrics
from plates import grid_plate

SIZE = 100.0  # um, side of the test plates
N = 20_000  # pred samples: enough for means within ~1% (the errors here are exact, not sampled)


def plate(z: float, size: float = SIZE, cells: int = 20) -> trimesh.Trimesh:
  """A flat square plate at height z, subdivided into cells^2 quads, with colours linear in x, y."""
  mesh = grid_plate(0.0, size, z, cells)
  mesh.visual.vertex_colors = np.round(albedo(mesh.vertices) * 255).astype(np.uint8)
  return mesh


def albedo(p: np.ndarray) -> np.ndarray:
  """Colours linear in x and y, so barycentric interpolation reproduces them exactly."""
  return np.stack([0.2 + 0.6 * p[:, 0] / SIZE, 0.8 - 0.5 * p[:, 1] / SIZE,
                   np.full(len(p), 0.4)], -1)


def visible_points(rng, n=4000, inset=10.0) -> np.ndarray:
  """GT points on the plate z = 0, away from its border (the 'visible' part)."""
  xy = rng.uniform(inset, SIZE - inset, size=(n, 2))
  return np.concatenate([xy, np.zeros((n, 1))], -1)


def test_mesh_against_itself_is_zero():
  rng = np.random.default_rng(0)
  mesh = plate(0.0)
  pts = visible_points(rng)
  s = metrics.evaluate(mesh, metrics.GroundTruth(mesh, pts, albedo(pts)), n_samples=N).summary
  assert s["chamfer_um"] < 1e-5 * SIZE  # float32 ray casting
  assert all(f["fscore"] == 1.0 for f in s["fscore"])
  assert s["normal_consistency"] == pytest.approx(1.0, abs=1e-6)
  # Vertex colours are 8-bit: interpolated they differ from the albedo by at most 0.5/255.
  assert s["albedo_mae"] < 0.5 / 255 and s["albedo_psnr"] > 20 * np.log10(2 * 255)


def test_plane_shifted_along_its_normal_by_d():
  rng = np.random.default_rng(1)
  gt = metrics.GroundTruth(plate(0.0), visible_points(rng))
  d = 0.007 * gt.diagonal  # between the two default F-score thresholds (0.5% and 1%)
  ev = metrics.evaluate(plate(d), gt, n_samples=N)
  s = ev.summary
  # Every evaluated pred sample and every GT point is exactly d from the other plate's interior.
  assert s["accuracy_um"] == pytest.approx(d, rel=1e-4)
  assert s["completeness_um"] == pytest.approx(d, rel=1e-4)
  assert s["chamfer_um"] == pytest.approx(d, rel=1e-4)
  assert s["chamfer_rel"] == pytest.approx(0.007, rel=1e-4)
  assert [f["fscore"] for f in s["fscore"]] == [0.0, 1.0]
  # Only pred samples over the GT points' XY box (inset 10 of 100 um per side) are evaluated.
  assert s["n_pred_evaluated"] / N == pytest.approx(ev_box_share(gt.points), abs=0.02)


def ev_box_share(points: np.ndarray) -> float:
  lo, hi = points.min(0), points.max(0)
  return float(np.prod(hi[:2] - lo[:2]) / SIZE ** 2)


def segment_distance(p, a, b):
  """|p - nearest point of segment ab|; p: [P, 1, 3], a, b: [F, 3] -> [P, F]."""
  ab = b - a
  t = np.clip(np.sum((p - a) * ab, -1) / np.sum(ab * ab, -1), 0.0, 1.0)
  return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def surface_distance(points: np.ndarray, mesh: trimesh.Trimesh, chunk: int = 100) -> np.ndarray:
  """Float64 brute force: [P] distance of points [P, 3] to the nearest of all the mesh's faces."""
  tri = mesh.vertices[mesh.faces]
  a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
  n = np.cross(b - a, c - a)
  n /= np.linalg.norm(n, axis=-1, keepdims=True)
  out = []
  for i in range(0, len(points), chunk):
    p = points[i:i + chunk, None]
    h = np.sum((p - a) * n, -1)
    q = p - h[..., None] * n  # projection onto each face's plane
    inside = np.ones(h.shape, bool)
    for u, v in ((a, b), (b, c), (c, a)):
      inside &= np.sum(np.cross(v - u, q - u) * n, -1) >= 0
    edges = np.minimum(np.minimum(segment_distance(p, a, b), segment_distance(p, b, c)),
                       segment_distance(p, c, a))
    out.append(np.where(inside, np.abs(h), edges).min(1))
  return np.concatenate(out)


def test_distances_match_float64_reference():
  rng = np.random.default_rng(2)
  bumpy = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
  bumpy.vertices *= 1 + 0.05 * rng.standard_normal((len(bumpy.vertices), 1))
  truth = trimesh.creation.icosphere(subdivisions=3, radius=31.0)
  up = truth.vertices[truth.vertices[:, 2] > 5.0]  # visible cap only
  gt = metrics.GroundTruth(truth, up)
  ev = metrics.evaluate(bumpy, gt, n_samples=1500)
  acc = surface_distance(ev.pred_points, truth)
  comp = surface_distance(up, bumpy)
  np.testing.assert_allclose(ev.accuracy, acc, atol=1e-4)
  np.testing.assert_allclose(ev.completeness, comp, atol=1e-4)
  samples, _ = metrics.sample_surface(bumpy, 1500)
  keep = metrics.evaluated_region(samples, up, metrics.CROP_MARGIN * gt.diagonal)
  np.testing.assert_array_equal(ev.pred_points, samples[keep])
  assert 0 < keep.sum() < len(samples)  # the closed underside of the sphere is cropped away
  assert ev.summary["chamfer_um"] == pytest.approx((acc.mean() + comp.mean()) / 2, abs=1e-4)


def test_floaters_count_and_the_unseen_underside_does_not():
  rng = np.random.default_rng(3)
  gt = metrics.GroundTruth(plate(0.0), visible_points(rng))
  below = plate(-0.5 * SIZE)  # a closed bottom far under the visible surface: not evaluated
  floater = plate(20.0, size=20.0)  # a 20 x 20 um sheet 20 um above: counts
  floater.apply_translation([40.0, 40.0, 0.0])
  pred = trimesh.util.concatenate([plate(0.0), below, floater])
  ev = metrics.evaluate(pred, gt, n_samples=5 * N)
  s = ev.summary
  assert np.all(ev.pred_points[:, 2] >= 0.0)
  # The evaluated box is the GT points' XY box; the floater lies inside it. Expected accuracy:
  # floater area share of the evaluated area x 20 um; ~2000 floater samples -> ~2% noise.
  box = ev_box_share(gt.points) * SIZE ** 2
  assert s["accuracy_um"] == pytest.approx(20.0 * 400.0 / (box + 400.0), rel=0.1)
  assert s["completeness_um"] < 1e-4


def test_albedo_error_and_gain_alignment():
  rng = np.random.default_rng(4)
  pts = visible_points(rng)
  truth = albedo(pts)
  gt = metrics.GroundTruth(plate(0.0), pts, truth)
  pred = plate(0.0)
  dark = np.asarray(pred.visual.vertex_colors, np.float64)
  dark[:, :3] = np.round(albedo(pred.vertices) * 0.8 * 255)
  pred.visual.vertex_colors = dark.astype(np.uint8)
  s = metrics.evaluate(pred, gt, n_samples=2000).summary
  want_mse = np.mean((0.2 * truth) ** 2)  # pred = 0.8 albedo, up to 8-bit rounding
  assert s["albedo_psnr"] == pytest.approx(-10 * np.log10(want_mse), abs=0.1)
  assert s["albedo_mae"] == pytest.approx(np.mean(0.2 * truth), abs=1e-3)
  assert s["albedo_gain"] == pytest.approx([1.25] * 3, abs=0.01)
  assert s["albedo_psnr_gain"] > 45.0  # only the 8-bit rounding (<= 0.5/255) is left


def write_ground_truth(directory, rng, pixel_size=2.0):
  """A scene directory's ground_truth/ as ofjax.synth lays it out: the plate z = 0."""
  gt_dir = directory / "ground_truth"
  gt_dir.mkdir(parents=True)
  plate(0.0).export(gt_dir / "mesh.ply")
  pts = visible_points(rng)
  pc = o3d.t.geometry.PointCloud()
  pc.point.positions = o3d.core.Tensor(pts.astype(np.float32))
  pc.point.normals = o3d.core.Tensor(np.tile(np.float32([0, 0, 1]), (len(pts), 1)))
  pc.point.colors = o3d.core.Tensor(np.round(albedo(pts) * 255).astype(np.uint8))
  o3d.t.io.write_point_cloud(str(gt_dir / "surface_points.ply"), pc)
  (gt_dir / "meta.json").write_text(json.dumps({"wli_pixel_size_um": pixel_size}))


def test_eval_cli(tmp_path, capsys):
  write_ground_truth(tmp_path / "scene", np.random.default_rng(5))
  d = 1.5
  plate(d).export(tmp_path / "pred.ply")
  assert evaluation.main(["--pred", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "scene"),
                          "--json", "--samples", "5000"]) == 0
  out = json.loads(capsys.readouterr().out)
  assert out["chamfer_um"] == pytest.approx(d, rel=1e-4)
  assert out["chamfer_px"] == pytest.approx(d / 2.0, rel=1e-4)
  assert out["albedo_psnr"] > 40.0 and out["normal_consistency"] == pytest.approx(1.0, abs=1e-6)
  for key in ("completeness_png", "accuracy_png"):
    assert (tmp_path / out[key]).stat().st_size > 0
  assert json.loads((tmp_path / "pred_eval.json").read_text()) == out
  assert "wli_blind_share" not in out  # no scene bundle beside ground_truth/: coverage unknown

  assert evaluation.main(["--pred", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "scene"),
                          "--samples", "2000", "--out", str(tmp_path / "o")]) == 0
  table = capsys.readouterr().out
  assert "chamfer" in table and "F-score @0.5%" in table
  assert (tmp_path / "o" / "pred_completeness.png").is_file()


def _rigid(deg: float, axis, t) -> np.ndarray:
  """[4, 4] rotation by deg about the unit axis, then translation t (Rodrigues)."""
  k = np.asarray(axis, float) / np.linalg.norm(axis)
  kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  a = np.radians(deg)
  m = np.eye(4)
  m[:3, :3] = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
  m[:3, 3] = t
  return m


def test_eval_cli_moves_a_mesh_from_the_poses_frame_into_the_truths(tmp_path, capsys):
  """A perfect reconstruction made in another frame (poses and mesh both moved by one rigid
  motion, as ofjax.associate's scan-0 frame is) scores zero with --poses and not without."""
  scene = tmp_path / "scene"
  write_ground_truth(scene, np.random.default_rng(7))
  meta = json.loads((scene / "ground_truth" / "meta.json").read_text())
  (scene / "ground_truth" / "meta.json").write_text(json.dumps({**meta, "size_um": SIZE}))
  rng = np.random.default_rng(8)
  true_c2w = [_rigid(30.0, rng.normal(size=3), rng.uniform(-50, 50, 3)) for _ in range(3)]
  cams = lambda c2ws: {"cameras": [{"name": f"wli_{i}", "modality": "wli", "c2w": m.tolist(),
                                     "intrinsics": {"pixel_size": [2.0, 2.0]}}
                                    for i, m in enumerate(c2ws)]}
  (scene / "ground_truth" / "poses.json").write_text(json.dumps(cams(true_c2w)))
  frame = _rigid(7.0, [0.2, -0.4, 1.0], [3.0, -2.0, 11.0])  # truth -> the estimate's frame
  (tmp_path / "est.json").write_text(json.dumps(cams([frame @ m for m in true_c2w])))
  moved = plate(0.0)
  moved.apply_transform(frame)
  moved.export(tmp_path / "pred.ply")
  common = ["--pred", str(tmp_path / "pred.ply"), "--gt", str(scene), "--json", "--samples", "4000"]
  assert evaluation.main(common) == 0
  assert json.loads(capsys.readouterr().out)["chamfer_um"] > 1.0
  assert evaluation.main(common + ["--poses", str(tmp_path / "est.json")]) == 0
  out = json.loads(capsys.readouterr().out)
  assert out["chamfer_um"] < 1e-4 * SIZE
  np.testing.assert_allclose(out["to_truth_frame"], np.linalg.inv(frame), atol=1e-6)
  assert evaluation.main(common + ["--poses", str(tmp_path / "missing.json")]) == 2
  (tmp_path / "om_only.json").write_text(json.dumps({"cameras": [
      {"name": "om_0", "modality": "om", "c2w": np.eye(4).tolist()}]}))
  capsys.readouterr()
  assert evaluation.main(common + ["--poses", str(tmp_path / "om_only.json")]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "shares no WLI camera" in err


@pytest.mark.parametrize("args", [["--gt", "nowhere"], ["--thresholds", "2"],
                                  ["--pred", "missing.ply"]])
def test_eval_cli_user_errors(tmp_path, capsys, args):
  write_ground_truth(tmp_path / "scene", np.random.default_rng(6))
  plate(0.0).export(tmp_path / "pred.ply")
  base = {"--pred": str(tmp_path / "pred.ply"), "--gt": str(tmp_path / "scene")}
  base.update({args[0]: str(tmp_path / args[1]) if args[0] != "--thresholds" else args[1]})
  argv = [x for kv in base.items() for x in kv]
  assert evaluation.main(argv) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and err.startswith("ofjax: error:")
  assert not (tmp_path / "pred_eval.json").exists()


def test_measured_counts_match_brute_force():
  rng = np.random.default_rng(11)
  points = rng.uniform(0, 10, (500, 3))
  clouds = [rng.uniform(0, 10, (k, 3)) for k in (300, 50, 0, 800)]
  radius = 0.9
  want = np.zeros(len(points), int)
  for cloud in clouds:
    if len(cloud):
      dist = np.sqrt(((points[:, None, :] - cloud[None, :, :]) ** 2).sum(-1))  # float64 [N, M]
      want += dist.min(1) < radius
  got = metrics.measured_counts(points, clouds, radius)
  assert got.dtype.kind == "i" and got.shape == (len(points),)
  np.testing.assert_array_equal(got, want)
  assert 0 < (want == 0).sum() < len(points) and want.max() >= 2  # every case occurs


def test_completeness_split_into_wli_blind_and_measured_points():
  """GT points on z = 0; the right half (x > SIZE/2) unmeasured. The prediction is exact on the
  left half and lifted by d on the right, so blind points are min(d, x - SIZE/2) away."""
  d = 3.0
  pts = visible_points(np.random.default_rng(12))
  half = SIZE / 2
  left, right = plate(0.0), plate(d)
  keep = lambda m, side: m.submesh([np.flatnonzero(side(m.triangles_center[:, 0]))], append=True)
  pred = trimesh.util.concatenate([keep(left, lambda x: x < half), keep(right, lambda x: x > half)])
  blind = pts[:, 0] > half
  gt = metrics.GroundTruth(plate(0.0), pts, wli_scans=np.where(blind, 0, 3))
  s = metrics.evaluate(pred, gt, n_samples=N).summary
  assert s["wli_blind_share"] == pytest.approx(blind.mean())
  want = np.minimum(d, pts[blind, 0] - half).mean()
  assert s["completeness_blind_um"] == pytest.approx(want, rel=1e-4)
  assert s["completeness_measured_um"] == pytest.approx(0.0, abs=1e-4)
  assert "wli_blind_share" not in metrics.evaluate(pred, metrics.GroundTruth(plate(0.0), pts),
                                                   n_samples=100).summary


@pytest.fixture(scope="module")
def lenses_tiny(tmp_path_factory):
  """The `lenses` scene (steep polished flanks: WLI voids) written as a native bundle."""
  from ofjax import synth
  out = tmp_path_factory.mktemp("lenses")
  scene, gt = synth.make_scene("lenses", seed=0, resolution="tiny")
  synth.write(scene, gt, out, "native")
  return out, gt


def test_wli_coverage_of_a_synthetic_scene(lenses_tiny, capsys):
  """Counts against a reference that back-projects every valid pixel from the poses file's c2w
  and the depth files directly, then the eval CLI's blind-region numbers for the true mesh."""
  scene_dir, gt = lenses_tiny
  poses = json.loads((scene_dir / "ground_truth" / "poses.json").read_text())
  meta = json.loads((scene_dir / "scene.json").read_text())
  rng = np.random.default_rng(13)
  pts = gt.points[rng.choice(len(gt.points), 400, replace=False)]
  want = np.zeros(len(pts), int)
  for m in meta["wli"]:
    c2w = np.asarray(next(c["c2w"] for c in poses["cameras"] if c["name"] == f"wli/{m['name']}"))
    depth = np.load(scene_dir / m["file"])["depth"].astype(np.float64)
    sx, sy = m["pixel_size"]
    h, w = depth.shape
    r, c = np.nonzero(np.isfinite(depth))
    local = np.stack([(c + 0.5 - w / 2) * sx, (r + 0.5 - h / 2) * sy, depth[r, c]], -1)
    world = local @ c2w[:3, :3].T + c2w[:3, 3]
    dist = np.sqrt(((pts[:, None, :] - world[None]) ** 2).sum(-1)).min(1)
    want += dist < max(sx, sy)
  np.testing.assert_array_equal(evaluation.wli_coverage(scene_dir, pts), want)
  assert 0 < (want == 0).mean() < 1

  gt.mesh.export(scene_dir / "truth.ply")
  assert evaluation.main(["--pred", str(scene_dir / "truth.ply"), "--gt", str(scene_dir), "--json",
                          "--samples", "20000", "--out", str(scene_dir / "ev")]) == 0
  out = json.loads(capsys.readouterr().out)
  assert 0.05 < out["wli_blind_share"] < 0.95
  assert out["completeness_blind_um"] < 1e-3 and out["completeness_measured_um"] < 1e-3
  assert evaluation.main(["--pred", str(scene_dir / "truth.ply"), "--gt", str(scene_dir),
                          "--samples", "2000", "--out", str(scene_dir / "ev")]) == 0
  assert "WLI-blind truth" in capsys.readouterr().out
