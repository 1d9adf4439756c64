"""The train step: batches, schedule, shapes, loss decrease, and an end-to-end accuracy check."""

import dataclasses
import importlib.metadata
import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
import pytest
import trimesh

import analytic_scene
import ofjax
from ofjax import export, fields, machine, metrics, train
from ofjax import scene as scene_lib
from ofjax.config import resolve
from ofjax.errors import UserError

# A small engine for the tiny scene: the cpu preset's architecture with a smaller table and batch.
SMALL = dict(hash={"log2_table_size": 14}, train={"n_rays": 128, "steps": 60})


def small_with_surface_points(n: int) -> dict:
  """SMALL with train.wli_surface_points = n (0: the batch holds only its rays)."""
  return {**SMALL, "train": {**SMALL["train"], "wli_surface_points": n}}


@pytest.fixture(scope="module")
def cap():
  scene, mesh = analytic_scene.make()
  norm = scene_lib.compute_normalization(scene)
  return scene, mesh, norm


def test_batch_rays_reproduce_the_wli_surface(cap):
  """WLI rays of a batch, advanced by their target depth and mapped back to um, lie on the cap."""
  scene, mesh, norm = cap
  cfg = resolve("cpu", **SMALL)
  data = train.prepare_data(scene, norm)
  batch = train.sample_batch(data, jax.random.PRNGKey(0), cfg)
  n = cfg.train.n_rays
  chex.assert_shape([batch["o"], batch["d"], batch["rgb"]], [(n, 3)] * 3)
  chex.assert_shape([batch["near"], batch["far"], batch["depth"], batch["wli_ok"]], [(n,)] * 4)
  assert int(batch["is_wli"].sum()) == n // 2
  ok = np.asarray(batch["wli_ok"])
  assert ok.sum() > 0.8 * (n // 2)
  p = norm.to_um(np.asarray(batch["o"] + batch["d"] * batch["depth"][:, None])[ok])
  rc = o3d.t.geometry.RaycastingScene()
  rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
  dist = rc.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
  # float32 through normalisation: 1e-6 of the 120 um scene is ~1e-4 um; allow 1e-3 um.
  assert dist.max() < 1e-3, dist.max()
  # OM targets are the photos' pixels: colours in [0, 1], only OM rays flagged for colour.
  assert not np.any(np.asarray(batch["om_ok"] & batch["is_wli"]))
  assert float(batch["rgb"].max()) <= 1.0


def test_surface_points_lie_on_the_wli_surface_and_leave_the_rays_alone(cap):
  """train.wli_surface_points: S further measured WLI points on the cap (voids flagged), drawn
  from a key of their own, so the batch's rays are the ones drawn without them."""
  scene, mesh, norm = cap
  cfg = resolve("cpu", **small_with_surface_points(0))
  more = resolve("cpu", **small_with_surface_points(512))
  data = train.prepare_data(scene, norm)
  plain = train.sample_batch(data, jax.random.PRNGKey(0), cfg)
  batch = train.sample_batch(data, jax.random.PRNGKey(0), more)
  assert "surface_x" not in plain
  chex.assert_shape([batch["surface_x"], batch["surface_ok"]], [(512, 3), (512,)])
  chex.assert_trees_all_equal(plain, {k: batch[k] for k in plain})
  ok = np.asarray(batch["surface_ok"])
  assert 0.8 * 512 < ok.sum() < 512  # the scans' voids are flagged, the rest kept
  p = norm.to_um(np.asarray(batch["surface_x"], np.float64)[ok])
  rc = o3d.t.geometry.RaycastingScene()
  rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
  assert rc.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy().max() < 1e-3
  # The WLI points of 512 draws are not the batch's 64: a different pixel stream.
  assert not np.allclose(np.asarray(batch["surface_x"][:64]),
                         np.asarray(batch["o"][:64] + batch["d"][:64] * batch["depth"][:64, None]))


@pytest.mark.parametrize("modalities,share,expect", [
    (("wli", "om"), 0.5, (64, 64)), (("wli", "om"), 0.75, (96, 32)), (("wli",), 0.75, (128, 0)),
    (("om",), 0.5, (0, 128))])
def test_ray_split_follows_the_modalities(modalities, share, expect):
  cfg = resolve("cpu", train={"n_rays": 128, "modalities": modalities, "wli_share": share})
  assert train.ray_split(cfg) == expect


@pytest.mark.parametrize("n", [127, 128, 129, 130])
def test_even_share_splits_as_before(n):
  """share 0.5 keeps the fused split n // 2 WLI rays (odd n included): earlier runs reproduce."""
  assert train.ray_split(resolve("cpu", train={"n_rays": n})) == (n // 2, n - n // 2)


@pytest.mark.parametrize("share", [0.0, 1.0, 1.5])
def test_wli_share_outside_the_open_interval_is_refused(share):
  with pytest.raises(ValueError, match="wli_share"):
    resolve("cpu", train={"wli_share": share})


def test_lr_schedule_warms_up_then_decays_to_a_tenth():
  cfg = resolve("paper")
  s = train.lr_schedule(0.01, cfg)
  np.testing.assert_allclose(float(s(0)), 0.01 * 0.01, rtol=1e-5)
  np.testing.assert_allclose(float(s(250)), 0.01 * (0.01 + 0.99 * 0.5), rtol=1e-5)
  np.testing.assert_allclose(float(s(500)), 0.01, rtol=1e-5)
  np.testing.assert_allclose(float(s(20000)), 0.001, rtol=1e-5)
  mid = 500 + (20000 - 500) // 2
  np.testing.assert_allclose(float(s(mid)), 0.01 * 0.1**((mid - 500) / 19500), rtol=1e-4)


def test_reference_scale_is_ten_units_across_the_median_scan(cap):
  """The reference code's WLI image spans 10 of its units: float64 NumPy from the scene in um."""
  scene, _, norm = cap
  data = train.prepare_data(scene, norm)
  widths_um = np.array([s.shape[1] * s.pixel_size[0] for s in scene.wli], np.float64)
  expect = norm.scale / (np.median(widths_um) / 10.0)
  np.testing.assert_allclose(float(train.reference_scale(data, resolve("cpu"))), expect, rtol=1e-5)
  assert float(train.reference_scale(data, resolve("cpu", train={"reference_unit": 0.0}))) == 1.0


def test_losses_are_measured_in_the_reference_unit(cap):
  """unit u scales the depth residual and the SDF, and multiplies s: the same as unit 1 with
  the depth loss times u^2, the sparsity scale times u and the variance shifted by log(u) / 10."""
  scene, _, norm = cap
  cfg = resolve("cpu", **SMALL)
  data = train.prepare_data(scene, norm)
  batch = train.sample_batch(data, jax.random.PRNGKey(1), cfg)
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  u = 6.5
  _, scaled = train.compute_losses(params, batch, jax.random.PRNGKey(2), 300, cfg, unit=u)
  shifted = dict(params, variance=params["variance"] + np.log(u) / 10.0)
  plain_cfg = dataclasses.replace(
      cfg, loss=dataclasses.replace(cfg.loss, sparsity_scale=cfg.loss.sparsity_scale * u))
  _, plain = train.compute_losses(shifted, batch, jax.random.PRNGKey(2), 300, plain_cfg)
  np.testing.assert_allclose(float(scaled["loss/wli"]), u**2 * float(plain["loss/wli"]), rtol=1e-4)
  for k in ("loss/color", "loss/residual", "loss/eikonal", "loss/sparsity"):
    np.testing.assert_allclose(float(scaled[k]), float(plain[k]), rtol=1e-4, err_msg=k)
  assert float(scaled["loss/wli"]) > 0


@pytest.mark.parametrize("extra", [0, 256])
def test_wli_surface_term_is_the_sdf_squared_at_the_measured_points(cap, extra):
  """loss/wli_surface against a float64 NumPy mean over the batch's measured WLI points (in the
  reference unit) and, with train.wli_surface_points, the measured extra points too; absent when
  its weight is 0 (the step then computes what it did before)."""
  scene, _, norm = cap
  small = small_with_surface_points(extra)
  cfg = resolve("cpu", loss={"lambda_wli_surface": 10.0}, **small)
  data = train.prepare_data(scene, norm)
  batch = train.sample_batch(data, jax.random.PRNGKey(1), cfg)
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  u = 6.5
  total, logs = train.compute_losses(params, batch, jax.random.PRNGKey(2), 300, cfg, unit=u)
  n_wli = train.ray_split(cfg)[0]
  b = {k: np.asarray(v, np.float64) for k, v in batch.items()}
  points = [b["o"][:n_wli] + b["d"][:n_wli] * b["depth"][:n_wli, None]]
  ok = [b["wli_ok"][:n_wli].astype(bool)]
  assert 0 < ok[0].sum() < n_wli  # the synthetic scans have voids: the mask matters
  assert ("surface_x" in b) == (extra > 0)
  if extra:
    points.append(b["surface_x"])
    ok.append(b["surface_ok"].astype(bool))
  points, ok = np.concatenate(points), np.concatenate(ok)
  sdf = np.asarray(fields.sdf_value(params, jnp.asarray(points[ok], jnp.float32), cfg), np.float64)
  np.testing.assert_allclose(float(logs["loss/wli_surface"]), np.mean((u * sdf) ** 2), rtol=1e-4)
  _, without = train.compute_losses(params, batch, jax.random.PRNGKey(2), 300,
                                    resolve("cpu", loss={"lambda_wli_surface": 0.0}, **small),
                                    unit=u)
  assert "loss/wli_surface" not in without
  np.testing.assert_allclose(float(total), float(without["loss/total"])
                             + 10.0 * float(logs["loss/wli_surface"]), rtol=1e-5)


@pytest.mark.parametrize("color_features", ["shared", "own", "both"])
def test_step_shapes_and_loss_decrease(cap, color_features):
  scene, _, norm = cap
  cfg = resolve("cpu", **SMALL, model={"color_features": color_features})
  data = train.prepare_data(scene, norm)
  opt = train.make_optimizer(cfg)
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  shapes = jax.tree.map(lambda a: (a.shape, a.dtype), params)
  state = opt.init(params)
  step = train.create_train_step(cfg, opt)
  first, last = [], []
  for i in range(cfg.train.steps):
    params, state, logs = step(params, state, data, jnp.int32(i))
    (first if i < 5 else last if i >= cfg.train.steps - 5 else []).append(
        float(logs["loss/total"]))
  assert jax.tree.map(lambda a: (a.shape, a.dtype), params) == shapes
  assert set(logs) >= {"loss/color", "loss/residual", "loss/wli", "loss/eikonal", "loss/sparsity",
                       "loss/total"}
  assert np.isfinite(last).all()
  assert np.mean(last) < 0.7 * np.mean(first), (first, last)


@pytest.mark.slow
def test_end_to_end_chamfer_on_the_cap(cap, tmp_path):
  """A short run on the tiny scene reconstructs the cap to a fraction of a WLI pixel.

  Threshold: the WLI pixel here is 2.25 um and the scene 120 um wide. The untrained sphere-init SDF
  is tens of um off; a run that learned from the WLI depth is within about a pixel after a few
  hundred steps, so a Chamfer distance below one WLI pixel separates "learned the surface" from
  "did not" without asking a short CPU run for the full preset's sub-pixel accuracy.
  """
  scene, mesh, _ = cap
  cfg = resolve("cpu", hash={"log2_table_size": 14},
                train={"n_rays": 256, "steps": 400, "mesh_resolution": 96},
                render={"cos_anneal_steps": 400}, optim={"warmup_steps": 50})
  result = train.train(scene, cfg, tmp_path, progress=False)
  pred = export.extract_mesh(result.params, cfg, result.norm, result.box, 96)
  gt_mesh = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
  # GT points: the visible cap surface inside the region every WLI scan covers.
  pts, _ = trimesh.sample.sample_surface(gt_mesh, 20000, seed=0)
  pts = pts[np.all(np.abs(pts[:, :2]) < 45, axis=1)]
  ev = metrics.evaluate(pred, metrics.GroundTruth(gt_mesh, pts), n_samples=50000)
  pixel = scene.wli[0].pixel_size[0]
  assert ev.summary["chamfer_um"] < pixel, ev.summary
  assert (tmp_path / "metrics.jsonl").is_file()
  written = json.loads((tmp_path / "config.json").read_text())
  assert written["ofjax"]["version"] == ofjax.__version__
  assert written["ofjax"]["commit"] == machine.git_state()["commit"]
  # What a result depends on beyond the code: the compiler's and the numeric libraries' versions.
  assert written["machine"]["packages"]["jaxlib"] == importlib.metadata.version("jaxlib")
  assert written["machine"]["packages"]["numpy"] == np.__version__


def test_set_overrides_any_field_and_a_wli_init_needs_wli_rays(cap, tmp_path):
  """--set reaches every config field (unknown ones refused in one line); a run that asks for the
  "wli" init without WLI rays (it would hand an OM-only model the WLI's geometry) is refused
  before anything is written."""
  parse = lambda *extra: train.config_from_args(train.build_parser().parse_args(
      ["--data", "scene", "--out", "run", *extra]))
  assert parse().model.init_shape == "wli"
  assert parse("--set", "model.init_shape=plane").model.init_shape == "plane"
  set_two = parse("--set", "model.wli_fit_steps=50", "--set", "hash.log2_table_size=14")
  assert (set_two.model.wli_fit_steps, set_two.hash.log2_table_size) == (50, 14)
  for bad in ("model.no_such_field=1", "model.init_shape=cube", "init_shape"):
    with pytest.raises(UserError, match="--set"):
      parse("--set", bad)
  scene, _, _ = cap
  cfg = resolve("cpu", **{**SMALL, "model": {"init_shape": "wli"},
                          "train": {"n_rays": 128, "steps": 2, "modalities": ["om"]}})
  with pytest.raises(UserError, match="init_shape 'wli'"):
    train.train(scene, cfg, tmp_path / "run", progress=False)
  assert not (tmp_path / "run").exists()
