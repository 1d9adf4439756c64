"""The SDF fitted to the merged WLI cloud before rendering (ModelConfig.init_shape "wli").

Not in the paper: its SDF starts as a sphere and meets the WLI surface only through the rendered
depth (Eq. 5), over 20,000 steps. Here it first regresses the measured points directly, as IGR
(Gropp et al. 2020) fits an SDF to an oriented point cloud, and NeuS then starts from a surface
that is already where the WLI measured it; the rendering losses refine it and fill in what the
WLI did not see. The fit starts from the "plane" init, so the field is positive on the objective's
side from the first step.

Names (normalised box coordinates):
  p      [M, 3] the WLI points of every scan; n [M, 3] their unit normals, toward the objective.
  delta  [B] offsets along n, normal with std `wli_fit_offset` reference units: q = p + delta n
         is a near-surface query whose signed distance is delta to first order (point-to-plane).
  r      [K, 3] uniform points of the box, drawn once; s [K] their signed distance to the cloud:
         the distance to the nearest WLI point, signed by what the scans saw there (free_space):
         positive where a scan's ray passed the point before it met the surface, negative where
         scans met the surface before the point and none passed it, NaN (no term) where no scan
         measured its pixel (the voids). Away from the surface it keeps the field free of stray
         zero crossings, in the air and, where no ray ever looks, inside the sample; it is compared
         truncated at `BOX_TRUNCATION`, beyond which only its sign is asked. (The nearest point's
         normal is no sign there: across a void it belongs to another face, and it left closed
         bubbles inside the sample on two of three seeds of the default scene.)
Loss per step (B near-surface queries and B / 4 box points):
  lambda u^2 mean (sdf(q) - delta)^2 + mean |grad sdf(q) - n|^2
  + mean (clip(u sdf(r)) - clip(u s))^2 + mean (|grad sdf(r)| - 1)^2,
with u the reference units per normalised unit (train.reference_scale), as the WLI depth loss, and
lambda = ModelConfig.wli_fit_lambda_distance.
"""

from __future__ import annotations

import dataclasses
import time

import chex
import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
import optax
from tqdm import tqdm

from ofjax import fields
from ofjax import scene as scene_lib
from ofjax.config import Config
from ofjax.errors import UserError

# Neighbours of a WLI point in its own scan that define its tangent plane (open3d's PCA normal).
NORMAL_NEIGHBOURS = 16
# Box points drawn once for the far-field term: ~64^3, a few per coarse hash cell.
BOX_POINTS = 2**18
# The fit's progress bar shows the loss every this many steps (a host sync).
LOG_EVERY = 50
# A box point within this many WLI pixels of a scan's measured depth is neither in front of it nor
# behind it for that scan.
SIDE_MARGIN_PX = 2.0
# Far-field distances are compared up to this many reference units (a tenth of the field of view
# each): beyond it only the sign is asked, as the nearest-point distance is no SDF in the voids.
BOX_TRUNCATION = 1.0


@dataclasses.dataclass(frozen=True)
class FitResult:
  params: dict  # all parameters, tables and SDF net fitted
  losses: dict  # loss/<name> of the last step (floats)
  seconds: float


def oriented_cloud(scene: scene_lib.Scene, norm: scene_lib.Normalization
                   ) -> tuple[np.ndarray, np.ndarray]:
  """Host side: points [M, 3] and unit normals [M, 3] (float32, normalised) of every WLI scan.

  Normals come from each scan's own points (its neighbours are on one height map, so a step in
  another scan cannot tilt them) and face that scan's objective: a point is seen from there.
  """
  pts, nrm = [], []
  for scan in scene.wli:
    p = norm.to_norm(scene_lib.wli_points(scan))
    if len(p) < NORMAL_NEIGHBOURS:
      continue
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
    axis = scan.c2w[:3, 2] / np.linalg.norm(scan.c2w[:3, 2])
    cloud.orient_normals_to_align_with_direction(-axis)
    pts.append(p)
    nrm.append(np.asarray(cloud.normals))
  if not pts:
    raise UserError(f"every WLI scan has fewer than {NORMAL_NEIGHBOURS} valid depths: too few to "
                    "fit the SDF to; check the WLI files, or train with model.init_shape 'plane'")
  return (np.concatenate(pts).astype(np.float32), np.concatenate(nrm).astype(np.float32))


def free_space(r_um: np.ndarray, scans) -> np.ndarray:
  """[K] sign of each point r_um [K, 3] (um) as the WLI scans saw it: +1 where some scan's ray
  passed it before meeting the surface (free space), else -1 where some scan met the surface
  before it, else 0 (no scan measured its pixel, or only within SIDE_MARGIN_PX of the point)."""
  front = np.zeros(len(r_um), bool)
  behind = np.zeros(len(r_um), bool)
  for scan in scans:
    col, row, z, seen = scene_lib.project_orthographic(r_um, scan.c2w, scan.pixel_size, scan.shape)
    # The pixel whose ray passes nearest: the one the point projects into.
    depth = np.full(len(r_um), np.nan)
    depth[seen] = scan.depth[np.floor(row[seen]).astype(np.int64),
                             np.floor(col[seen]).astype(np.int64)]
    margin = SIDE_MARGIN_PX * max(scan.pixel_size)
    with np.errstate(invalid="ignore"):  # NaN depths (voids) compare False: no evidence
      front |= z < depth - margin
      behind |= z > depth + margin
  return np.where(front, 1.0, np.where(behind, -1.0, 0.0))


def box_targets(points: np.ndarray, scene: scene_lib.Scene, norm: scene_lib.Normalization,
                seed: int, count: int = BOX_POINTS) -> tuple[np.ndarray, np.ndarray]:
  """Host side: `count` uniform points r [K, 3] of [-1, 1]^3 and their signed distance s [K] to
  the WLI points [M, 3] (normalised; the nearest one's distance, signed by free_space; NaN where
  the scans say nothing), float32."""
  r = np.random.default_rng(seed).uniform(-1.0, 1.0, (count, 3)).astype(np.float32)
  nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(points))
  nns.knn_index()
  dist2 = nns.knn_search(o3d.core.Tensor(r), 1)[1].numpy()[:, 0]
  side = free_space(norm.to_um(r.astype(np.float64)), scene.wli)
  return r, np.where(side == 0, np.nan, side * np.sqrt(dist2)).astype(np.float32)


def fit_losses(geo, params, cloud, key, cfg: Config, unit):
  """(total, {"loss/<name>": value}) of one fit batch; geo = {"tables", "sdf"} is what is fitted.

  cloud: (p, n, r, s) as the module docstring; unit: [] reference units per normalised unit.
  """
  p, n, r, s = cloud
  mc = cfg.model
  b = mc.wli_fit_points
  k_i, k_d, k_r = jax.random.split(key, 3)
  idx = jax.random.randint(k_i, (b,), 0, p.shape[0])
  delta = jax.random.normal(k_d, (b,)) * (mc.wli_fit_offset / unit)
  q = p[idx] + delta[:, None] * n[idx]
  far = jax.random.randint(k_r, (b // 4,), 0, r.shape[0])
  sdf, grad, _ = fields.geometry({**params, **geo}, jnp.concatenate([q, r[far]]), cfg)
  chex.assert_shape([sdf, grad], [(b + b // 4,), (b + b // 4, 3)])
  clip = lambda v: jnp.clip(unit * v, -BOX_TRUNCATION, BOX_TRUNCATION)
  known = jnp.isfinite(s[far])
  far_err = jnp.where(known, clip(sdf[b:]) - clip(jnp.where(known, s[far], 0.0)), 0.0)
  terms = {
      "distance": jnp.mean((unit * (sdf[:b] - delta)) ** 2),
      "normal": jnp.mean(jnp.sum((grad[:b] - n[idx]) ** 2, -1)),
      "far": jnp.sum(far_err**2) / jnp.maximum(jnp.sum(known), 1),
      "eikonal": jnp.mean((fields.safe_norm(grad[b:]) - 1.0) ** 2),
  }
  weights = {"distance": mc.wli_fit_lambda_distance}
  total = sum(weights.get(k, 1.0) * v for k, v in terms.items())
  return total, {f"loss/{k}": v for k, v in terms.items()}


def fit(params, scene: scene_lib.Scene, norm: scene_lib.Normalization, cfg: Config, unit,
        seed: int, progress: bool = True) -> FitResult:
  """Fits params' tables and SDF net to the scene's WLI for cfg.model.wli_fit_steps steps.

  The oriented cloud and box targets are made here (host); unit: [] reference units per
  normalised unit; seed draws the box points and the batches.
  Adam at wli_fit_lr, cosine-decayed to a tenth; the colour nets and NeuS's variance are kept.
  """
  t0 = time.time()
  mc = cfg.model
  key = jax.random.PRNGKey(seed)
  schedule = optax.cosine_decay_schedule(mc.wli_fit_lr, max(mc.wli_fit_steps, 1), alpha=0.1)
  opt = optax.adam(schedule, b1=cfg.optim.b1, b2=cfg.optim.b2, eps=cfg.optim.eps)
  geo = {k: params[k] for k in ("tables", "sdf")}
  rest = {k: v for k, v in params.items() if k not in geo}
  points, normals = oriented_cloud(scene, norm)
  cloud = tuple(map(jnp.asarray, (points, normals, *box_targets(points, scene, norm, seed))))

  @jax.jit
  def step(geo, state, rest, cloud, unit, i):
    (_, logs), g = jax.value_and_grad(fit_losses, has_aux=True)(
        geo, rest, cloud, jax.random.fold_in(key, i), cfg, unit)
    updates, state = opt.update(g, state, geo)
    return optax.apply_updates(geo, updates), state, logs

  state = opt.init(geo)
  logs = {}
  bar = tqdm(range(mc.wli_fit_steps), disable=not progress, unit="it", dynamic_ncols=True,
             desc="fit WLI")
  for i in bar:
    geo, state, logs = step(geo, state, rest, cloud, unit, jnp.int32(i))
    if progress and i % LOG_EVERY == 0:
      bar.set_postfix(distance=f"{float(logs['loss/distance']):.2e}",
                      normal=f"{float(logs['loss/normal']):.2e}", refresh=False)
  logs = {k: float(v) for k, v in logs.items()}
  return FitResult({**rest, **geo}, logs, time.time() - t0)
