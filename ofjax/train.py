"""Training: data on the device, the single jitted train_step, the loop, and the CLI.

`python -m ofjax.train --data SCENE_DIR --out RUN_DIR [--preset cpu|paper] [--steps N] ...`

One batch holds WLI and OM rays with a per-ray modality mask (DESIGN.md: equivalent to the
reference's alternating batches): the first `n_wli` rays of every batch are WLI rays, the rest OM
rays, each drawn uniformly over the pixels of its modality. Sampling is keyed by the step
(jax.random.fold_in(seed, step)), never by a stateful generator, so a resumed run is exact.

Coordinates inside training are normalised (scene.Normalization): WLI depths and pixel sizes are
divided by the scale, camera centres shifted and scaled; rotations and OM intrinsics are unchanged.
The losses that have a length in them (WLI depth, sparsity) and NeuS's s are measured in the
reference code's unit instead (`reference_scale`: a tenth of the WLI field of view), so the
paper's weights keep the balance they had there whatever the box's size.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ofjax import __version__ as ofjax_version
from ofjax import (averaging, cameras, checkpoint, compile_cache, fields, fileio, guard, losses,
                   machine, parallel, prefit, render)
from ofjax import scene as scene_lib
from ofjax.config import KEEPING_FIELDS, PRESETS, Config, resolve_spec, with_steps
from ofjax.errors import UserError, cli

MODALITIES = ("wli", "om")


class TrainData(NamedTuple):
  """Everything the step samples from, on the device, in normalised coordinates."""
  wli_depth: jax.Array  # [Nw, H, W] float32 depth along the axis, 0 where void
  wli_valid: jax.Array  # [Nw, H, W] bool
  wli_c2w: jax.Array  # [Nw, 4, 4]
  wli_pixel: jax.Array  # [Nw, 2] pixel size (sx, sy)
  wli_hw: jax.Array  # [Nw, 2] image size (H, W)
  om_rgb: jax.Array  # [No, H, W, 3] uint8
  om_c2w: jax.Array  # [No, 4, 4]
  om_K: jax.Array  # [No, 3, 3]
  om_hw: jax.Array  # [No, 2]
  up: jax.Array  # [3] unit vector from the sample into the WLI objective (minus the top scan's axis)
  floor: jax.Array  # [] lowest WLI point along `up`: the substrate level
  level: jax.Array  # [] median WLI point along `up`: the height of the "plane" init


def _stack_padded(maps: list[np.ndarray], fill) -> np.ndarray:
  h = max(m.shape[0] for m in maps)
  w = max(m.shape[1] for m in maps)
  out = np.full((len(maps), h, w) + maps[0].shape[2:], fill, maps[0].dtype)
  for i, m in enumerate(maps):
    out[i, :m.shape[0], :m.shape[1]] = m
  return out


def _normalised_c2w(c2w: np.ndarray, norm: scene_lib.Normalization) -> np.ndarray:
  out = np.array(c2w, np.float64)
  out[:3, 3] = norm.to_norm(out[:3, 3])
  return out


def prepare_data(scene: scene_lib.Scene, norm: scene_lib.Normalization) -> TrainData:
  """Host side: validates the posed scene and moves it, normalised, to the device."""
  if not scene.wli:
    raise UserError("the scene has no WLI scans; ofjax needs at least one WLI height map")
  if not scene.om:
    raise UserError("the scene has no OM photos; ofjax needs the optical-microscope images")
  if not scene.posed:
    raise UserError("the scene has cameras without poses; run `python -m ofjax.associate "
                    "SCENE_DIR` or pass --poses")
  depth = [np.nan_to_num(s.depth / norm.scale, nan=0.0).astype(np.float32) for s in scene.wli]
  valid = [s.valid for s in scene.wli]
  rgb = [np.round(np.clip(o.image, 0, 1) * 255).astype(np.uint8) for o in scene.om]
  axes = np.stack([s.c2w[:3, 2] / np.linalg.norm(s.c2w[:3, 2]) for s in scene.wli])
  # The scan whose axis is closest to the mean axis is the top scan; "up" points against it.
  up = -axes[np.argmax(axes @ axes.mean(0))]
  heights = norm.to_norm(scene.wli_points(stride=2)) @ up  # [N] WLI points along up
  return TrainData(
      wli_depth=jnp.asarray(_stack_padded(depth, 0.0)),
      wli_valid=jnp.asarray(_stack_padded(valid, False)),
      wli_c2w=jnp.asarray(np.stack([_normalised_c2w(s.c2w, norm) for s in scene.wli]),
                          jnp.float32),
      wli_pixel=jnp.asarray([np.asarray(s.pixel_size) / norm.scale for s in scene.wli],
                            jnp.float32),
      wli_hw=jnp.asarray([s.shape for s in scene.wli], jnp.float32),
      om_rgb=jnp.asarray(_stack_padded(rgb, 0)),
      om_c2w=jnp.asarray(np.stack([_normalised_c2w(o.c2w, norm) for o in scene.om]), jnp.float32),
      om_K=jnp.asarray(np.stack([o.K for o in scene.om]), jnp.float32),
      om_hw=jnp.asarray([o.shape for o in scene.om], jnp.float32),
      up=jnp.asarray(up, jnp.float32),
      floor=jnp.asarray(float(np.min(heights)), jnp.float32),
      level=jnp.asarray(float(np.median(heights)), jnp.float32),
  )


def ray_split(cfg: Config) -> tuple[int, int]:
  """(n_wli, n_om) rays per batch: cfg.train.wli_share of them WLI when both modalities supervise."""
  n = cfg.train.n_rays
  mods = set(cfg.train.modalities)
  if mods == {"wli"}:
    return n, 0
  if mods == {"om"}:
    return 0, n
  n_wli = int(n * cfg.train.wli_share)  # floor: a share of 0.5 splits as n // 2 always did
  return n_wli, n - n_wli


def _pick(key, n: int, hw):
  """n uniform (camera, row, col) triples; hw: [C, 2] image sizes (all images sampled alike)."""
  k_c, k_r, k_x = jax.random.split(key, 3)
  cam = jax.random.randint(k_c, (n,), 0, hw.shape[0])
  rows = jnp.floor(jax.random.uniform(k_r, (n,)) * hw[cam, 0]).astype(jnp.int32)
  cols = jnp.floor(jax.random.uniform(k_x, (n,)) * hw[cam, 1]).astype(jnp.int32)
  return cam, rows, cols


# fold_in data of the key that draws train.wli_surface_points.
SURFACE_POINTS_STREAM = 1


def sample_batch(data: TrainData, key, cfg: Config) -> dict[str, jax.Array]:
  """One ray batch: WLI rays first, then OM rays (fixed shapes, keyed by `key`).

  Returns [R, ...] arrays: o, d, near, far, rgb (OM target), depth (WLI target), is_wli,
  wli_ok (WLI ray with a measured depth), om_ok (OM ray whose pixel the box can explain); with
  train.wli_surface_points = S > 0 (and WLI rays), also surface_x [S, 3] further measured WLI
  points and surface_ok [S] (their pixel is not a void), drawn uniformly over the WLI pixels.
  """
  n_wli, n_om = ray_split(cfg)
  k_w, k_o = jax.random.split(key)
  parts = []
  if n_wli:
    cam, r, c = _pick(k_w, n_wli, data.wli_hw)
    o, d = cameras.orthographic_rays(data.wli_c2w[cam], data.wli_pixel[cam], data.wli_hw[cam], r, c)
    parts.append(dict(o=o, d=d, rgb=jnp.zeros((n_wli, 3)), depth=data.wli_depth[cam, r, c],
                      valid=data.wli_valid[cam, r, c], is_wli=jnp.ones((n_wli,), bool)))
  if n_om:
    cam, r, c = _pick(k_o, n_om, data.om_hw)
    o, d = cameras.pinhole_rays(data.om_c2w[cam], data.om_K[cam], r, c)
    # An OM pixel is explained by the box only if its ray meets the substrate level inside it.
    t_floor = (data.floor - o @ data.up) / jnp.minimum(d @ data.up, -1e-6)
    p = o + d * t_floor[:, None]
    parts.append(dict(o=o, d=d, rgb=data.om_rgb[cam, r, c].astype(jnp.float32) / 255.0,
                      depth=jnp.zeros((n_om,)), valid=jnp.all(jnp.abs(p) <= 1.0, -1),
                      is_wli=jnp.zeros((n_om,), bool)))
  batch = {k: jnp.concatenate([p[k] for p in parts], 0) for k in parts[0]}
  near, far, hit = cameras.box_near_far(batch["o"], batch["d"])
  far = jnp.where(hit, far, near + 1e-3)
  valid = batch.pop("valid") & hit
  batch.update(near=near, far=far, hit=hit, wli_ok=valid & batch["is_wli"],
               om_ok=valid & ~batch["is_wli"])
  n_surf = cfg.train.wli_surface_points
  if n_surf and n_wli:
    # A key of its own (not a third split), so runs without these points draw as before.
    cam, r, c = _pick(jax.random.fold_in(key, SURFACE_POINTS_STREAM), n_surf, data.wli_hw)
    o, d = cameras.orthographic_rays(data.wli_c2w[cam], data.wli_pixel[cam], data.wli_hw[cam], r, c)
    batch.update(surface_x=o + d * data.wli_depth[cam, r, c][:, None],
                 surface_ok=data.wli_valid[cam, r, c])
  return batch


def lr_schedule(base: float, cfg: Config):
  """Linear warm-up from 1% (reference) then exponential decay to cfg.optim.decay_to x base."""
  oc, total = cfg.optim, cfg.train.steps

  def schedule(step):
    step = jnp.asarray(step, jnp.float32)
    warm = base * (0.01 + 0.99 * step / max(oc.warmup_steps, 1))
    frac = (step - oc.warmup_steps) / max(total - oc.warmup_steps, 1)
    decay = base * oc.decay_to ** jnp.clip(frac, 0.0, 1.0)
    return jnp.where(step < oc.warmup_steps, warm, decay)

  return schedule


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
  oc = cfg.optim
  adam = lambda lr: optax.adam(lr_schedule(lr, cfg), b1=oc.b1, b2=oc.b2, eps=oc.eps)
  labels = lambda params: {k: ("variance" if k == "variance" else "net") for k in params}
  opt = optax.multi_transform({"net": adam(oc.lr), "variance": adam(oc.lr_inv_s)}, labels)
  if oc.ema_fraction > 0:
    opt = averaging.with_param_ema(opt, averaging.decay_for(oc.ema_fraction, cfg.train.steps))
  # Divergence guard: a step with a non-finite gradient or update is skipped (ofjax.guard).
  return guard.skip_non_finite(opt)


def reference_scale(data: TrainData, cfg: Config):
  """[] reference units per normalised unit (TrainConfig.reference_unit; 1 when that is 0)."""
  if cfg.train.reference_unit <= 0:
    return jnp.float32(1.0)
  fov = jnp.median(data.wli_pixel[:, 0] * data.wli_hw[:, 1])  # scan width, normalised units
  return 1.0 / (fov * cfg.train.reference_unit)


def compute_losses(params, batch, key, step, cfg: Config, field_fns=fields.field_fns, unit=1.0):
  """Renders the batch and returns (total, {"loss/<name>": value, ...}).

  field_fns: (params, cfg) -> (geometry_fn, color_fn, sdf_fn) as fields.field_fns (benchmarks swap
  in a nested-autodiff reference). unit: [] reference units per normalised unit
  (reference_scale): the depth residual, the SDF in the sparsity term and NeuS's s are measured
  in it, as in the reference code. The batch's WLI rays (its first ray_split(cfg)[0]) are not
  coloured: only OM rays enter the colour losses.
  """
  n_wli = ray_split(cfg)[0]
  # sigmoid(s_ref * sdf_ref) with sdf_ref = unit * sdf: s per normalised unit is unit * s_ref.
  out = render.render_rays(*field_fns(params, cfg), batch["o"], batch["d"], batch["near"],
                           batch["far"], key, unit * fields.inv_s(params),
                           render.cos_anneal_ratio(step, cfg.render), cfg.render,
                           guide=batch["depth"], has_guide=batch["wli_ok"], n_uncolored=n_wli)
  lc = cfg.loss
  terms = {
      "color": losses.color(out["color"], batch["rgb"], batch["om_ok"]),
      "residual": losses.residual(out["color_res"], batch["om_ok"]),
      "wli": losses.wli(unit * out["depth"], unit * batch["depth"], batch["wli_ok"]),
      "eikonal": losses.eikonal(out["grad"], batch["hit"]),
      "sparsity": losses.sparsity(unit * out["sdf"], batch["hit"], lc.sparsity_scale),
  }
  if lc.lambda_wli_surface and n_wli:  # static: a run without the term compiles without it
    points = batch["o"][:n_wli] + batch["d"][:n_wli] * batch["depth"][:n_wli, None]
    measured = batch["wli_ok"][:n_wli]
    if "surface_x" in batch:  # train.wli_surface_points: more measured points, not rendered
      points = jnp.concatenate([points, batch["surface_x"]], 0)
      measured = jnp.concatenate([measured, batch["surface_ok"]], 0)
    # The SDF alone, differentiable in params: its spatial gradient is not needed here.
    terms["wli_surface"] = losses.wli_surface(unit * fields.sdf_value(params, points, cfg),
                                              measured)
  total = sum(getattr(lc, f"lambda_{k}") * v for k, v in terms.items())
  logs = {f"loss/{k}": v for k, v in terms.items()}
  logs["loss/total"] = total
  logs["inv_s"] = fields.inv_s(params)
  return total, logs


def create_train_step(cfg: Config, optimizer: optax.GradientTransformation,
                      field_fns=fields.field_fns, devices=None):
  """Returns the jitted step (params, opt_state, data, step) -> (params, opt_state, logs).

  params and opt_state are donated; the batch is drawn inside from fold_in(seed, step). The ray
  batch is split over `devices` (default: all of jax.devices()) by ofjax.parallel, everything else
  is replicated; on one device the program is the plain single-device one.
  """
  base_key = jax.random.PRNGKey(cfg.train.seed)
  mesh = parallel.batch_mesh(devices)
  parallel.check_divisible(cfg.train.n_rays, mesh)
  parallel.check_divisible(cfg.train.wli_surface_points, mesh, "train.wli_surface_points")

  def step_fn(params, opt_state, data: TrainData, step):
    key = jax.random.fold_in(base_key, step)
    k_batch, k_render = jax.random.split(key)
    batch = parallel.shard_rays(sample_batch(data, k_batch, cfg), mesh)
    chex.assert_shape(batch["o"], (cfg.train.n_rays, 3))
    (_, logs), grads = jax.value_and_grad(compute_losses, has_aux=True)(
        params, batch, k_render, step, cfg, field_fns, reference_scale(data, cfg))
    updates, opt_state = optimizer.update(grads, opt_state, params)
    params = optax.apply_updates(params, updates)
    return params, opt_state, logs

  if mesh.size == 1:
    return jax.jit(step_fn, donate_argnums=(0, 1))
  everywhere = parallel.replicated(mesh)
  return jax.jit(step_fn, donate_argnums=(0, 1), in_shardings=everywhere,
                 out_shardings=everywhere)


# --------------------------------------------------------------------------------------- the run

METRICS = "metrics.jsonl"


@dataclasses.dataclass
class RunResult:
  params: Any  # what the mesh is made from: the last step's, or their average (optim.ema_fraction)
  cfg: Config
  norm: scene_lib.Normalization
  box: tuple[tuple[float, ...], tuple[float, ...]]  # observed region in normalised coordinates
  seconds: float
  start: int = 0  # the step this call began at (> 0 when resumed)
  skipped: int = 0  # updates the divergence guard skipped in the whole run


def observed_box(scene: scene_lib.Scene, norm: scene_lib.Normalization, margin: float):
  """Bounding box of the WLI points in normalised coordinates, grown by `margin` of its size."""
  pts = norm.to_norm(scene.wli_points(stride=2))
  lo, hi = pts.min(0), pts.max(0)
  pad = margin * (hi - lo).max()
  return tuple(np.maximum(lo - pad, -1.0).tolist()), tuple(np.minimum(hi + pad, 1.0).tolist())


def _metrics_before(run_dir: Path, step: int) -> list[str]:
  """The metrics.jsonl lines of steps before `step`: a resumed run logs the later ones again."""
  path = run_dir / METRICS
  if not path.is_file():
    return []
  return [ln for ln in path.read_text().splitlines() if ln and json.loads(ln)["step"] < step]


def _diverged(run_dir: Path | None, cfg: Config, step: int) -> UserError:
  where = run_dir if run_dir is not None else "training"
  kept = checkpoint.list_steps(run_dir) if run_dir is not None else []
  last = f"the last good checkpoint is step {kept[-1]}" if kept else "no checkpoint was written"
  return UserError(f"{where}: diverged: {cfg.train.max_skipped_in_a_row} steps in a row had a "
                   f"non-finite gradient or update (stopped at step {step + 1}; {last}); lower the "
                   "learning rate or check the data")


def train(scene: scene_lib.Scene, cfg: Config, run_dir: Path | None = None, progress: bool = True,
          meta: dict | None = None, resume: bool = False) -> RunResult:
  """Trains on a posed scene; with run_dir, writes config.json, poses.json (the cameras),
  metrics.jsonl, checkpoints.

  resume: continue from run_dir's newest checkpoint (from scratch when it has none); the result
  is the same as that of an uninterrupted run, metrics.jsonl included. Non-finite steps are skipped
  (ofjax.guard); `max_skipped_in_a_row` of them in a row raise a UserError, leaving the
  checkpoints written so far.
  """
  from tqdm import tqdm

  tc = cfg.train
  if cfg.model.init_shape == "wli" and "wli" not in tc.modalities:
    raise UserError("model.init_shape 'wli' fits the SDF to the WLI points, which this run does "
                    "not train on (train.modalities); set it to 'plane' "
                    "(--set model.init_shape=plane)")
  norm = scene.normalization or scene_lib.compute_normalization(scene, tc.box_margin)
  box = observed_box(scene, norm, tc.box_margin)
  data = prepare_data(scene, norm)
  optimizer = make_optimizer(cfg)
  params = fields.init_params(jax.random.PRNGKey(tc.seed), cfg, substrate=(data.up, data.level))
  opt_state = optimizer.init(params)
  start = 0
  if resume and run_dir is not None:
    state = checkpoint.restore(run_dir, params, opt_state)
    if state is not None:
      start, params, opt_state = state[0], *jax.device_put(state[1:])
  prefit_logs, prefit_s = {}, 0.0
  if cfg.model.init_shape == "wli" and start == 0:
    fitted = prefit.fit(params, scene, norm, cfg, reference_scale(data, cfg), tc.seed, progress)
    params, prefit_s = fitted.params, fitted.seconds
    prefit_logs = {"prefit": {"seconds": fitted.seconds, **fitted.losses}}
  step_fn = create_train_step(cfg, optimizer)

  lines: list[str] = []
  if run_dir is not None:
    if resume:
      lines = _metrics_before(run_dir, start)
    else:
      # A fresh run replaces an earlier one's checkpoints and log; its mesh stays until the new
      # one is written over it (atomically).
      shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)
      (run_dir / METRICS).unlink(missing_ok=True)
      fileio.write_json(run_dir / "config.json", {
          "config": cfg.to_dict(), "units": scene.units,
          "normalization": dataclasses.asdict(norm), "observed_box": box,
          "jax": jax.__version__, "backend": jax.default_backend(),
          "ofjax": {"version": ofjax_version, **machine.git_state()},
          "machine": machine.describe(), **prefit_logs,
          **(meta or {})})
    # The cameras the run was trained with, beside its config: ofjax.export keeps what they see.
    from ofjax import export
    fileio.write_json(run_dir / export.POSES, scene_lib.poses_to_json(scene))
  # time_s continues across resumes: it is the training time (the WLI fit's included), not the
  # wall clock.
  t_before = json.loads(lines[-1])["time_s"] if lines else prefit_s

  t0 = time.time()
  bar = tqdm(total=tc.steps, initial=start, disable=not progress, unit="it", dynamic_ncols=True,
             desc="train")
  try:
    for step in range(start, tc.steps):
      params, opt_state, logs = step_fn(params, opt_state, data, jnp.int32(step))
      last = step == tc.steps - 1
      log = step % tc.log_every == 0 or last
      save = run_dir is not None and ((step + 1) % tc.checkpoint_every == 0 or last)
      # The guard's counters are read at every log, checkpoint and max_skipped_in_a_row steps:
      # a diverged run stops within that many steps, and no checkpoint follows a diverged step.
      if log or save or (step + 1) % tc.max_skipped_in_a_row == 0:
        counts = guard.stats(opt_state)
        if counts["worst"] >= tc.max_skipped_in_a_row:
          raise _diverged(run_dir, cfg, step)
      if log:
        logs = {k: float(v) for k, v in logs.items()}  # the only other host sync in the loop
        bar.set_postfix(loss=f"{logs['loss/total']:.4g}", wli=f"{logs['loss/wli']:.2e}",
                        color=f"{logs['loss/color']:.2e}", refresh=False)
        if run_dir is not None:
          lines.append(json.dumps({"step": step, "time_s": t_before + time.time() - t0, **logs,
                                   "skipped": counts["skipped"]}))
          fileio.write_text(run_dir / METRICS, "\n".join(lines) + "\n")
      if save:
        checkpoint.save(run_dir, step + 1, params, opt_state, tc.keep_checkpoints)
      bar.update(1)
  finally:
    bar.close()
  jax.block_until_ready(params)
  ema = averaging.averaged(opt_state)
  return RunResult(params if ema is None else ema, cfg, norm, box, time.time() - t0, start,
                   guard.stats(opt_state)["skipped"])


# ------------------------------------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(
      prog="python -m ofjax.train",
      description="Fuse WLI depth and OM colour into a neural SDF and export a coloured mesh (um).")
  p.add_argument("--data", required=True, help="scene directory (native bundle or OpticFusion layout)")
  p.add_argument("--out", required=True, help="run directory to create")
  p.add_argument("--preset", default="cpu", choices=sorted(PRESETS),
                 help="cpu: fast default for a laptop CPU; paper: the paper's numbers")
  p.add_argument("--steps", type=int, help="optimisation steps (default: the preset's)")
  p.add_argument("--rays", type=int, help="rays per batch (default: the preset's)")
  p.add_argument("--modalities", default="wli,om",
                 help="which data supervise: wli,om (fused) | wli | om (the paper's ablations)")
  p.add_argument("--no-residual", action="store_true", help="drop the residual colour branch")
  p.add_argument("--seed", type=int, default=0, help="seed of init and ray sampling")
  p.add_argument("--poses", help="poses file (default: SCENE_DIR/poses.json)")
  p.add_argument("--um-per-unit", type=float,
                 help="micrometres per unit of an OpticFusion-layout scene")
  p.add_argument("--layout", choices=["native", "opticfusion", "raw"], help="force the data layout")
  p.add_argument("--mesh-resolution", type=int,
                 help="marching-cubes cells along the longest side of mesh.ply's box (default: "
                      "cells of half a WLI pixel)")
  p.add_argument("--checkpoint-every", type=int,
                 help="write a checkpoint every N steps (default: the preset's)")
  p.add_argument("--keep-checkpoints", type=int, help="keep the newest K checkpoints (default: "
                 "the preset's)")
  p.add_argument("--log-every", type=int, help="a metrics.jsonl line every N steps (default: the "
                 "preset's)")
  p.add_argument("--max-skipped", type=int, help="stop after this many non-finite steps in a row "
                 "(default: the preset's)")
  p.add_argument("--resume", action="store_true",
                 help="continue the run in --out from its newest checkpoint")
  p.add_argument("--set", action="append", default=[], metavar="COMPONENT.FIELD=VALUE",
                 help="override any config field, e.g. --set model.init_shape=plane (repeatable; "
                 "the options above win over it)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
  p.add_argument("--quiet", action="store_true", help="no progress bar")
  return p


def config_from_args(args) -> Config:
  mods = tuple(m.strip() for m in args.modalities.split(",") if m.strip())
  if not mods or any(m not in MODALITIES for m in mods):
    raise UserError(f"--modalities {args.modalities!r}: use wli,om | wli | om")
  train_over: dict[str, Any] = {"modalities": mods, "seed": args.seed}
  for option, name in (("steps", "steps"), ("rays", "n_rays"),
                       ("mesh_resolution", "mesh_resolution"),
                       ("checkpoint_every", "checkpoint_every"),
                       ("keep_checkpoints", "keep_checkpoints"), ("log_every", "log_every"),
                       ("max_skipped", "max_skipped_in_a_row")):
    value = getattr(args, option)
    if value is not None:
      if value <= 0:
        raise UserError(f"--{option.replace('_', '-')} {value}: must be a positive integer")
      train_over[name] = value
  over: dict[str, dict[str, Any]] = {"train": train_over}
  if args.no_residual:
    over["model"] = {"residual": False}
  try:  # with no --set this is resolve(args.preset, **over)
    cfg = resolve_spec("+".join([args.preset, *args.set]), **over)
  except ValueError as e:
    raise UserError(f"--set: {e}") from None
  return cfg if args.steps is None else with_steps(cfg, args.steps)


def resume_config(run_dir: Path, cfg: Config) -> Config:
  """The config to resume run_dir with: the stored one, with cfg's KEEPING_FIELDS.

  Any other difference between cfg (from the command line) and the stored config would make the
  resumed run a different run, so it is a UserError naming the fields.
  """
  path = run_dir / "config.json"
  if not path.is_file():
    raise UserError(f"{path}: not found, so there is no run to resume; drop --resume")
  try:
    stored = Config.from_dict(json.loads(path.read_text())["config"])
  except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
    raise UserError(f"{path}: not an ofjax run config; start a new run with another --out or "
                    "--overwrite") from None
  new, old = cfg.to_dict(), stored.to_dict()
  differ = [f"{comp}.{k}" for comp, part in new.items() if isinstance(part, dict)
            for k, v in part.items() if old[comp].get(k) != v and k not in KEEPING_FIELDS]
  differ += ["preset"] if new["preset"] != old["preset"] else []
  if differ:
    raise UserError(f"--resume: {', '.join(differ)} differ from {path}; resume with the run's own "
                    "options, or start a new run with another --out")
  keep = {k: getattr(cfg.train, k) for k in KEEPING_FIELDS}
  return dataclasses.replace(stored, train=dataclasses.replace(stored.train, **keep))


def check_run_dir(run_dir: Path, resume: bool, overwrite: bool) -> None:
  """Refuses to clobber an existing run unless told (writes nothing)."""
  if resume and overwrite:
    raise UserError("--resume and --overwrite: choose one")
  if run_dir.exists() and not run_dir.is_dir():
    raise UserError(f"{run_dir}: is a file; give a directory as --out")
  if resume:
    return
  if run_dir.is_dir() and any(run_dir.iterdir()) and not overwrite:
    raise UserError(f"{run_dir}: not empty (a run already exists there); choose another --out, "
                    "or pass --resume to continue it or --overwrite to replace it")


def load_scene_for_training(args) -> scene_lib.Scene:
  """The scene in any layout ofjax reads (ofjax.io), with the poses the options name."""
  from ofjax import io as ofio
  return ofio.load(args.data, layout=args.layout, um_per_unit=args.um_per_unit, poses=args.poses)


@cli
def main(argv=None) -> int:
  args = build_parser().parse_args(argv)
  compile_cache.enable()
  cfg = config_from_args(args)
  run_dir = Path(args.out)
  check_run_dir(run_dir, args.resume, args.overwrite)
  if args.resume:
    cfg = resume_config(run_dir, cfg)
  scene = load_scene_for_training(args)
  slow_gpu = machine.scatter_regression_warning(jax.__version__, jax.default_backend())
  if slow_gpu:
    print(f"ofjax: warning: {slow_gpu}", file=sys.stderr)
  result = train(scene, cfg, run_dir, progress=not args.quiet,
                 meta={"data": str(Path(args.data).resolve()), "poses": args.poses},
                 resume=args.resume)
  from ofjax import export
  exported = export.export_run(result.params, cfg, result.norm, result.box, run_dir / "mesh.ply",
                               units=scene.units, poses=scene_lib.poses_to_json(scene),
                               trained_in=run_dir)
  resumed = f" (resumed at step {result.start})" if result.start else ""
  print(f"ofjax: trained {cfg.train.steps} steps{resumed} in {result.seconds:.1f} s, "
        f"{result.skipped} skipped; mesh: {exported.describe()}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
