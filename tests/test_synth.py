"""Tests of ofjax.synth: the WLI void model, camera conventions against the true mesh, the two
layout writers, determinism, the CLI. Scenes render at the `tiny` resolution."""

import json
import math
import time
import xml.etree.ElementTree as ET

import numpy as np
import open3d as o3d
import pytest
import trimesh

from ofjax import scene as scn
from ofjax import synth
from ofjax.associate.wli import prior_rotation
from ofjax.synth_scenes import SCENES, Material

ON_MESH_TOL = 1e-4  # fraction of the scene size: the bound for back-projected WLI depths


def paper_p_valid(alpha_deg: float, beta: float, na: float = 0.13) -> float:
  """OpticFusion supplementary eq. (1)-(2), written out scalar by scalar."""
  theta = math.degrees(math.asin(na))
  if alpha_deg < theta:
    return 1.0
  x = (alpha_deg - theta) / (90.0 - theta)
  t = 2.0 * beta - 1.0
  if t < 0:
    return 1.0 - math.exp(10.0 * (1.0 - x) * t) * x
  return math.exp(-10.0 * x * t) * (1.0 - x)


def raycaster(mesh: trimesh.Trimesh) -> o3d.t.geometry.RaycastingScene:
  rc = o3d.t.geometry.RaycastingScene()
  rc.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                   o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
  return rc


@pytest.fixture(scope="module")
def seed_tiny():
  scene, gt = synth.make_scene("seed", seed=0, resolution="tiny")
  assert all(c.c2w is None for c in scene.wli + scene.om)  # as on disk: no poses
  scn.apply_poses(scene, gt.poses)  # poses are not written by `synth.write`
  return scene, gt


def test_probability_matches_the_paper_formula():
  alphas = np.linspace(0.0, 90.0, 37)
  betas = np.linspace(0.0, 1.0, 11)
  a, b = np.meshgrid(alphas, betas, indexing="ij")
  want = np.array([[paper_p_valid(x, y) for y in betas] for x in alphas])
  np.testing.assert_allclose(synth.valid_probability(a, b), want, rtol=0, atol=1e-12)
  np.testing.assert_allclose(synth.void_probability(a, b), 1.0 - want, rtol=0, atol=1e-12)
  # at the NA cone the diffuse and specular limits meet p = 1; at 90 degrees nothing is measured
  assert synth.valid_probability(90.0, 0.0) == pytest.approx(0.0)
  assert synth.valid_probability(7.0, 1.0) == 1.0


@pytest.mark.parametrize("beta", [0.1, 0.5, 0.9])
def test_tilted_plane_valid_fraction_follows_the_void_model(beta):
  """A plane tilted by alpha, seen by a top WLI scan: the valid fraction is p(alpha, beta)."""
  n = 96  # pixels per side: the valid fraction's standard error is <= 0.5 / 96 = 0.0052
  tol = 0.026  # five standard errors
  scan = scn.WLIScan("top", np.zeros((n, n), np.float32), (1.0, 1.0),
                     c2w=synth.pose(synth.view_rotation(0.0, 0.0), np.zeros(3), 500.0))
  mat = Material("plane", beta, lambda p, part: np.full((len(p), 3), 0.5, np.float32))
  for k, alpha in enumerate([0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 75.0]):
    rot = trimesh.transformations.rotation_matrix(np.radians(alpha), [1, 0, 0])[:3, :3]
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * 400 @ rot.T
    mesh = synth.SynthMesh(quad, np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int),
                           np.zeros(2, int), [mat], np.zeros((4, 3)))
    depth = synth.render_wli(mesh, mesh.query(), scan, np.random.default_rng([7, k]))
    assert np.mean(np.isfinite(depth)) == pytest.approx(paper_p_valid(alpha, beta), abs=tol), alpha


@pytest.mark.parametrize("beta", [0.2, 0.9])
def test_wli_intensity_of_a_tilted_plane_follows_the_aperture(beta):
  """A grey plane tilted by alpha under a top scan: luminance 0.5 times the diffuse share's
  cos(alpha) plus the specular share while its mirror direction (2 alpha) is in the aperture."""
  scan = scn.WLIScan("top", np.zeros((16, 16), np.float32), (1.0, 1.0),
                     c2w=synth.pose(synth.view_rotation(0.0, 0.0), np.zeros(3), 500.0))
  mat = Material("plane", beta, lambda p, part: np.full((len(p), 3), 0.5, np.float32))
  aperture = np.arcsin(synth.NA)  # half-angle, radians
  for alpha in (0.0, 3.0, 10.0, 40.0):
    rot = trimesh.transformations.rotation_matrix(np.radians(alpha), [0, 1, 0])[:3, :3]
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * 400 @ rot.T
    mesh = synth.SynthMesh(quad, np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int),
                           np.zeros(2, int), [mat], np.zeros((4, 3)))
    img = synth.render_wli_intensity(mesh, mesh.query(), scan)
    a = np.radians(alpha)
    want = 0.5 * ((1 - beta) * np.cos(a) + beta * np.exp(-(2 * a / aperture) ** 2))
    assert img.dtype == np.float32 and img.shape == scan.shape
    np.testing.assert_allclose(img, want, rtol=1e-5)


def test_wli_depths_lie_on_the_true_mesh(seed_tiny):
  scene, gt = seed_tiny
  size = gt.meta["size_um"]
  rc = raycaster(gt.mesh)
  for s in scene.wli:
    pts = scn.wli_points(s)
    assert len(pts) > 0.3 * s.depth.size
    dist = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert dist.max() < ON_MESH_TOL * size, s.name
  # the top scan holds the whole sample: its border sees only the flat substrate (z = 0)
  top = scene.wli[0]
  o, d = scn.wli_rays(top)
  z = (o + d * top.depth[..., None].astype(np.float64))[..., 2]
  border = np.concatenate([z[0], z[-1], z[:, 0], z[:, -1]])
  assert np.nanmax(np.abs(border)) < ON_MESH_TOL * size


def test_ground_truth_points_are_seen_by_the_om(seed_tiny):
  """Every ground-truth point projects (own float64 pinhole model) into some photo, unoccluded."""
  scene, gt = seed_tiny
  rng = np.random.default_rng(0)
  pts = gt.points[rng.choice(len(gt.points), 3000, replace=False)]
  rc = raycaster(gt.mesh)
  seen = np.zeros(len(pts), bool)
  for photo in scene.om:
    h, w = photo.shape
    assert photo.K[0, 2] == w / 2 and photo.K[1, 2] == h / 2 and photo.K[0, 0] == photo.K[1, 1]
    rot, centre = photo.c2w[:3, :3], photo.c2w[:3, 3]
    cam = (pts - centre) @ rot  # world -> camera (OpenCV: z forward)
    u = photo.K[0, 0] * cam[:, 0] / cam[:, 2] + photo.K[0, 2]
    v = photo.K[1, 1] * cam[:, 1] / cam[:, 2] + photo.K[1, 2]
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ray = pts - centre
    dist = np.linalg.norm(ray, axis=1)
    rays = np.concatenate([np.broadcast_to(centre, ray.shape), ray / dist[:, None]], 1)
    t = rc.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    seen |= inside & (np.abs(t - dist) < ON_MESH_TOL * gt.meta["size_um"])
    # foreground: the photo shows the surface (substrate or sample) at every pixel
    assert photo.image.max(-1).min() > 0.0
  assert seen.all()
  # the points carry their surface's albedo: the seed coat is brown, the substrate grey
  on_seed = pts[:, 2] > 5.0
  assert on_seed.any() and (~on_seed).any()


def test_same_seed_same_bytes(tmp_path, seed_tiny):
  for k in range(2):
    scene, gt = seed_tiny if k == 0 else synth.make_scene("seed", seed=0, resolution="tiny")
    for layout in synth.LAYOUTS:
      synth.write(scene, gt, tmp_path / f"{layout}{k}", layout)
  for layout in synth.LAYOUTS:
    a, b = tmp_path / f"{layout}0", tmp_path / f"{layout}1"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) > 40
    for f in files:
      if f.name != "timing.json":
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
  assert not np.array_equal(SCENES["seed"](0).solids[0].vertices,
                            SCENES["seed"](1).solids[0].vertices)


def test_native_layout_round_trips(tmp_path, seed_tiny):
  scene, gt = seed_tiny
  synth.write(scene, gt, tmp_path, "native")
  assert not (tmp_path / "poses.json").exists()
  back = scn.load_scene(tmp_path, poses=tmp_path / "ground_truth" / "poses.json")
  for a, b in zip(back.wli, scene.wli):
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    np.testing.assert_array_equal(a.c2w, b.c2w)
    assert a.prior == b.prior and a.pixel_size == b.pixel_size
  for a, b in zip(back.om, scene.om):
    np.testing.assert_allclose(a.image, b.image, atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(a.K, b.K)
    assert a.prior == b.prior
    # The stage prior is the photo's true orientation in the WLI priors' convention.
    np.testing.assert_allclose(prior_rotation(a.prior), a.c2w[:3, :3], atol=1e-9)
  mesh = trimesh.load(tmp_path / "ground_truth" / "mesh.ply", process=False)
  np.testing.assert_allclose(mesh.vertices, gt.mesh.vertices, atol=1e-3)
  pc = o3d.io.read_point_cloud(str(tmp_path / "ground_truth" / "surface_points.ply"))
  assert len(pc.points) == len(gt.points) and pc.has_normals() and pc.has_colors()


def test_opticfusion_layout_encodes_the_true_poses(tmp_path, seed_tiny):
  """Parse camera.xml / align.aln / wl/*.npz back (DESIGN.md's conventions) and recover poses."""
  scene, gt = seed_tiny
  synth.write(scene, gt, tmp_path, "opticfusion")
  unit = gt.meta["um_per_unit"]
  lines = (tmp_path / "op" / "align.aln").read_text().splitlines()
  align = np.array([[float(v) for v in line.split()] for line in lines[3:7]])
  chunk = ET.parse(tmp_path / "op" / "camera.xml").getroot().find("chunk")
  tr = chunk.find("components/component/transform")
  rot = np.array(tr.find("rotation").text.split(), float).reshape(3, 3)
  m = np.eye(4)
  m[:3, :3] = float(tr.find("scale").text) * rot
  m[:3, 3] = np.array(tr.find("translation").text.split(), float)
  assert not np.allclose(m, np.eye(4)) and not np.allclose(align, np.eye(4))
  assert abs(float(tr.find("scale").text) - 1.0) > 0.1
  calib = chunk.find("sensors/sensor/calibration")
  res = calib.find("resolution")
  photos = {p.name: p for p in scene.om}
  cams = chunk.findall("cameras/camera")
  assert len(cams) == 37
  for cam in cams:
    photo = photos[cam.get("label")]
    assert (int(res.get("width")), int(res.get("height"))) == photo.shape[::-1]
    assert float(calib.find("f").text) == pytest.approx(photo.K[0, 0], rel=1e-12)
    t_cam = np.array(cam.find("transform").text.split(), float).reshape(4, 4)
    c2w = align @ m @ t_cam
    s = np.cbrt(np.linalg.det(c2w[:3, :3]))
    got = np.eye(4)
    got[:3, :3], got[:3, 3] = c2w[:3, :3] / s, c2w[:3, 3] * unit
    np.testing.assert_allclose(got, photo.c2w, atol=1e-9 * gt.meta["size_um"])
    png = scn.read_png(tmp_path / "op" / f"{photo.name}.png")
    np.testing.assert_allclose(png, photo.image, atol=0.5 / 255 + 1e-6)
  for s in scene.wli:
    with np.load(tmp_path / "wl" / f"{s.name}.npz") as z:
      depth, ext = z["depth_map"], z["extrinsic_mat"]
    c2w = np.linalg.inv(np.vstack([ext, [0, 0, 0, 1]]))
    h, w = depth.shape
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    local = np.stack([(c / w - 0.5) * 10.0, (r / h - 0.5) * 10.0, np.zeros_like(r, float)], -1)
    origin = (local @ c2w[:3, :3].T + c2w[:3, 3]) * unit
    pts = origin + c2w[:3, 2] * depth[..., None] * unit
    o, d = scn.wli_rays(s)
    want = o + d * s.depth[..., None].astype(np.float64)
    np.testing.assert_array_equal(np.isfinite(depth), s.valid)
    np.testing.assert_allclose(pts[s.valid], want[s.valid], atol=1e-5 * gt.meta["size_um"])


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in SCENES if n != "seed"])
def test_every_scene_renders(name):
  scene, gt = synth.make_scene(name, seed=3, resolution="tiny")
  assert len(scene.wli) == 5 and len(scene.om) == 37
  voids = np.array(list(gt.meta["void_fraction"].values()))
  assert np.all((voids > 0.0) & (voids < 0.95)), voids
  assert all(p.image.max(-1).min() > 0.0 for p in scene.om)
  assert gt.meta["size_um"] > 200.0 and len(gt.points) > 10_000


def test_cli(tmp_path, capsys):
  assert synth.main(["--list"]) == 0
  assert set(SCENES) <= set(capsys.readouterr().out.split())
  assert synth.main(["--scene", "nope", "--out", str(tmp_path / "x")]) == 2
  assert synth.main(["--mesh", str(tmp_path / "missing.ply"), "--out", str(tmp_path)]) == 2
  assert "missing.ply" in capsys.readouterr().err
  box = trimesh.creation.box((120.0, 80.0, 40.0))
  box.visual.vertex_colors = np.tile([200, 40, 40, 255], (len(box.vertices), 1))
  box.export(tmp_path / "box.ply")
  out = tmp_path / "user"
  assert synth.main(["--mesh", str(tmp_path / "box.ply"), "--out", str(out), "--resolution",
                     "tiny", "--layout", "opticfusion"]) == 0
  assert len(list((out / "wl").glob("*.npz"))) == 5 and len(list((out / "op").glob("*.png"))) == 37
  pc = o3d.io.read_point_cloud(str(out / "ground_truth" / "surface_points.ply"))
  top = np.asarray(pc.points)[:, 2] > 39.0  # the box's top face keeps the mesh's red
  red = np.asarray(pc.colors)[top]
  assert len(red) > 100
  np.testing.assert_allclose(red, np.broadcast_to([200 / 255, 40 / 255, 40 / 255], red.shape),
                             atol=1e-3)


def test_om_size_changes_only_the_photos(tmp_path, seed_tiny, capsys):
  """Photos at half the tiny size: same field of view (the focal length halves with the width),
  the WLI scans and the truth unchanged; a bad size is one line and exit code 2."""
  scene, gt = seed_tiny
  small, small_gt = synth.make_scene("seed", seed=0, resolution="tiny", om_size=(80, 60))
  for a, b in zip(small.om, scene.om):
    assert a.image.shape == (60, 80, 3)
    np.testing.assert_allclose(a.K[:2], b.K[:2] / 2)
  for a, b in zip(small.wli, scene.wli):
    np.testing.assert_array_equal(a.depth, b.depth)
  np.testing.assert_array_equal(small_gt.points, gt.points)
  assert small_gt.meta["om_size_px"] == [80, 60] and small.source["om_size"] == [80, 60]
  # The top photo of the smaller size is the larger one sampled at every other pixel's corner:
  # their mean colours agree to a few percent (the same scene at half the sampling).
  assert abs(small.om[0].image.mean() - scene.om[0].image.mean()) < 0.03
  out = tmp_path / "s"
  assert synth.main(["--scene", "seed", "--resolution", "tiny", "--om-size", "80,60", "--out",
                     str(out)]) == 0
  assert "photos 80x60" in capsys.readouterr().out
  assert json.loads((out / "ground_truth" / "meta.json").read_text())["om_size_px"] == [80, 60]
  assert synth.main(["--scene", "seed", "--om-size", "81,60", "--out", str(tmp_path / "b")]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "--om-size 81,60" in err and not (tmp_path / "b").exists()


@pytest.mark.slow
def test_quick_default_scene_time():
  t0 = time.perf_counter()
  scene, gt = synth.make_scene(resolution="quick")
  seconds = time.perf_counter() - t0
  print(f"quick seed scene: {seconds:.1f} s {gt.timing}")
  assert seconds < 120.0 and scene.wli[0].shape == (256, 256)
