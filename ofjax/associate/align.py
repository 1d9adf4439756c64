"""Step 2: the similarity that maps the SfM frame (P_om, OM cameras) into the WLI um frame (P_wli).

Conventions: `S` is a [4, 4] similarity [s R | t] with x_um = s R x_sfm + t (s = um per SfM unit).
Seeds, each refined by scaled point-to-point ICP (open3d, with_scaling=True), best fitness wins:
  - FPFH + RANSAC on scale-normalised clouds: P_om scaled by the ratio of the clouds' robust
    spreads (median distance to the median point), both centred;
  - the acquisition geometry: OM photos are taken from above the sample, so the mean viewing
    direction of the cameras points down (world -z); the remaining turn about z is swept.
The second seed needs no features, so sparse, noisy SfM points (whose FPFH descriptors differ
from those of the dense WLI cloud) still align. Seeds are scored coarsely; the best few distinct
ones are refined to the end and the best final fitness wins (a nearly symmetric sample fits its
turned copy almost as well at a coarse gate). The result is rejected (UserError) unless its
fitness is a clear peak over the scale: on a mostly flat sample scaled ICP drifts to a smaller
scale (and an arbitrary turn) that fits as well, and wrong poses must not be written.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d

from ofjax.associate import register
from ofjax.errors import UserError

GLOBAL_VOXELS_ACROSS = 40  # global registration resolution: clouds ~40 voxels across their spread
YAW_STEPS = 24  # the camera-geometry seed tries the turn about z every 15 degrees
SEED_GATE_SPREADS = 0.3  # coarse ICP gate of the seeds, in robust spreads
FINAL_GATE_VOXELS = 1.5  # last ICP gate in P_wli voxels: wider gates let SfM points where
# the WLI has voids (steep sides) pull on the scale (seed scene: 1.2% scale error at 3 voxels)
GATE_SHRINK = 0.5  # the gate halves between ICP rounds ...
SCORE_GATE_VOXELS = 6.0  # ... seeds are scored by the share of P_om within this many voxels
SCORE_GATE_COARSE_VOXELS = 2.0  # ... or of global-resolution voxels, whichever is wider
FINALISTS = 4  # the best-scored distinct seeds refined to the end
DISTINCT_DEG = 10.0  # seeds whose rotations differ by less than this are the same solution
SCALE_PROBE = 0.05  # the found scale is probed this far either side (relative) ...
SCALE_PEAK_RATIO = 0.9  # ... where the fitness must drop below this share of the found one


@dataclasses.dataclass
class Alignment:
  S: np.ndarray  # [4, 4] um_from_sfm similarity
  scale: float  # s: um per SfM unit
  fitness: float  # share of P_om points within the final gate of P_wli
  rmse_um: float  # RMS distance of those points
  residuals_um: np.ndarray  # [N] distance of every aligned P_om point to its nearest P_wli point
  seed: str  # "fpfh" or "cameras": which seed won
  initial_scale: float  # the spread-ratio estimate of s


def robust_frame(points: np.ndarray) -> tuple[np.ndarray, float]:
  """points: [N, 3] -> (median point [3], median distance to it): outlier-proof centre and size."""
  c = np.median(points, axis=0)
  return c, float(np.median(np.linalg.norm(points - c, axis=1)))


def _similarity(s: float, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = s * rot, t
  return m


def _rot_to_z(v: np.ndarray) -> np.ndarray:
  """[3, 3] rotation taking unit vector v onto +z (Rodrigues; v = -z handled by a half turn)."""
  v = v / np.linalg.norm(v)
  z = np.array([0.0, 0.0, 1.0])
  c = float(v @ z)
  if c < -1 + 1e-12:
    return np.diag([1.0, -1.0, -1.0])
  k = np.cross(v, z)
  kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  return np.eye(3) + kx + kx @ kx / (1 + c)


def _rz(a: float) -> np.ndarray:
  return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _angle_deg(r0: np.ndarray, r1: np.ndarray) -> float:
  return float(np.degrees(np.arccos(np.clip((np.trace(r0.T @ r1) - 1) / 2, -1.0, 1.0))))


def _refine(src, tgt, S: np.ndarray, seed_gate: float, final_gate: float):
  """Scaled point-to-point ICP with a halving gate down to `final_gate`, then a rigid
  point-to-plane ICP at the found scale -> (S [4, 4], open3d result of the last ICP)."""
  gate = seed_gate * GATE_SHRINK
  while True:
    gate = max(gate * GATE_SHRINK, final_gate)
    res = register.icp(src, tgt, S, gate, point_to_plane=False, with_scaling=True,
                       max_iterations=100)
    S = np.asarray(res.transformation)
    if gate <= final_gate:
      break
  # Point-to-point pairs a sparse SfM point with the nearest WLI sample, not the surface, which
  # tilts the fit by a few tenths of a degree; a last rigid point-to-plane ICP at the found
  # scale removes that (open3d has no point-to-plane estimation with scaling).
  scaled = o3d.geometry.PointCloud(src).transform(S)
  res = register.icp(scaled, tgt, np.eye(4), final_gate, max_iterations=100)
  return np.asarray(res.transformation) @ S, res


def _fitness_at_scale(src, tgt, S: np.ndarray, factor: float, centre: np.ndarray,
                      first_gate: float, final_gate: float) -> float:
  """Fitness of the similarity S with its scale times `factor` (about `centre`, [3]) after a
  rigid point-to-plane refit whose gate halves from `first_gate` down to `final_gate`."""
  Sf = S.copy()
  Sf[:3, :3] *= factor
  Sf[:3, 3] = factor * S[:3, 3] + (1 - factor) * centre
  scaled = o3d.geometry.PointCloud(src).transform(Sf)
  T, gate = np.eye(4), first_gate
  while True:
    res = register.icp(scaled, tgt, T, max(gate, final_gate), max_iterations=50)
    T = np.asarray(res.transformation)
    if gate <= final_gate:
      return float(res.fitness)
    gate *= GATE_SHRINK


def align_om_to_wli(p_om: np.ndarray, p_wli: np.ndarray, wli_normals: np.ndarray,
                    wli_voxel_um: float, om_forward: np.ndarray, min_fitness: float = 0.3,
                    scene_dir: str = "SCENE_DIR") -> Alignment:
  """Similarity alignment of P_om onto P_wli (module docstring).

  p_om: [N, 3] SfM frame; p_wli: [M, 3] um, world z up; wli_normals: [M, 3] unit normals of
  P_wli; om_forward: [K, 3] the OM cameras' viewing directions in the SfM frame; wli_voxel_um:
  spacing of P_wli. A final fitness below `min_fitness` is a UserError.
  """
  if len(p_om) < 10:
    raise UserError(f"{scene_dir}/om: structure-from-motion left only {len(p_om)} reliable points; "
                    "take sharper photos of a textured surface")
  c_om, r_om = robust_frame(p_om)
  c_wli, r_wli = robust_frame(p_wli)
  s0 = r_wli / r_om
  src = register.to_cloud(p_om)
  tgt = register.to_cloud(p_wli, wli_normals)
  # Seeds as similarities um_from_sfm.
  seeds = []
  gv = r_wli * 2 / GLOBAL_VOXELS_ACROSS
  src_n = register.downsample(register.to_cloud((p_om - c_om) * s0), gv)
  tgt_n = register.downsample(register.to_cloud(p_wli - c_wli), gv)
  g = np.asarray(register.global_register(src_n, tgt_n, gv).transformation)
  # x_um = g (s0 (x - c_om)) + c_wli
  seeds.append(("fpfh", _similarity(s0, g[:3, :3], g[:3, :3] @ (-s0 * c_om) + g[:3, 3] + c_wli)))
  up = _rot_to_z(-np.mean(om_forward, axis=0))
  for k in range(YAW_STEPS):
    rot = _rz(2 * np.pi * k / YAW_STEPS) @ up
    seeds.append(("cameras", _similarity(s0, rot, c_wli - s0 * rot @ c_om)))
  seed_gate = SEED_GATE_SPREADS * r_wli
  # Seeds are refined and scored on P_wli at the global resolution: wide gates on the full cloud
  # would cost seconds per ICP.
  tgt_coarse = tgt.voxel_down_sample(gv)
  score_gate = max(SCORE_GATE_VOXELS * wli_voxel_um, SCORE_GATE_COARSE_VOXELS * gv)
  scored = []
  for name, init in seeds:
    res = register.icp(src, tgt_coarse, init, seed_gate, point_to_plane=False, with_scaling=True)
    res = register.icp(src, tgt_coarse, res.transformation, seed_gate * GATE_SHRINK,
                       point_to_plane=False, with_scaling=True)
    score = o3d.pipelines.registration.evaluate_registration(src, tgt_coarse, score_gate,
                                                             res.transformation)
    scored.append((score.fitness, name, np.asarray(res.transformation)))
  # A coarse score cannot tell a nearly symmetric sample from its turned copy; the best few
  # seeds are therefore refined to the end and judged at the final gate.
  scored.sort(key=lambda c: -c[0])
  distinct = []  # seeds that converged to the same turn count once
  for _, name, S0 in scored:
    r0 = S0[:3, :3] / np.cbrt(np.linalg.det(S0[:3, :3]))
    if all(_angle_deg(r0, r1) > DISTINCT_DEG for _, r1, _ in distinct):
      distinct.append((name, r0, S0))
  final = [_refine(src, tgt, S0, seed_gate, FINAL_GATE_VOXELS * wli_voxel_um) + (name,)
           for name, _, S0 in distinct[:FINALISTS]]
  S, res, seed = max(final, key=lambda c: (c[1].fitness, -c[1].inlier_rmse))
  final_gate = FINAL_GATE_VOXELS * wli_voxel_um
  scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
  aligned = o3d.geometry.PointCloud(src).transform(S)
  residuals = np.asarray(aligned.compute_point_cloud_distance(tgt))
  if res.fitness < min_fitness:
    raise UserError(f"{scene_dir}: OM-to-WLI alignment failed: only {res.fitness:.0%} of the SfM "
                    f"points lie within {final_gate:.3g} um of the WLI surface (need "
                    f"{min_fitness:.0%}); check that the photos and scans show the same sample")
  # Scaled ICP on a mostly flat sample (a circuit board) is free to shrink P_om: fewer points then
  # fall into WLI voids or beyond its footprint, so the fitness keeps rising as the scale drops
  # and the converged scale (and with it the turn) is arbitrary. A determined scale is a peak of
  # the fitness: scales SCALE_PROBE either side must fit clearly worse.
  probes = [_fitness_at_scale(src, tgt, S, 1 + d, c_wli, 2 * SCALE_PROBE * r_wli, final_gate)
            for d in (-SCALE_PROBE, SCALE_PROBE)]
  if max(probes) > SCALE_PEAK_RATIO * res.fitness:
    raise UserError(f"{scene_dir}: OM-to-WLI alignment is ambiguous: scaling the SfM points by "
                    f"{1 - SCALE_PROBE:g} or {1 + SCALE_PROBE:g} fits the WLI surface about as well "
                    f"({max(probes):.0%} vs {res.fitness:.0%} within {final_gate:.3g} um), so the "
                    "scale is not determined; scan a larger area with relief (WLI) or take photos "
                    "with more overlap so that both clouds share distinct 3D structure")
  return Alignment(S, scale, float(res.fitness), float(res.inlier_rmse), residuals, seed, s0)


def om_c2w_um(c2w_sfm: np.ndarray, S: np.ndarray) -> np.ndarray:
  """[4, 4] rigid camera-to-world in um from an SfM-frame c2w and the similarity S."""
  s = np.cbrt(np.linalg.det(S[:3, :3]))
  out = np.eye(4)
  out[:3, :3] = S[:3, :3] / s @ c2w_sfm[:3, :3]
  out[:3, 3] = S[:3, :3] @ c2w_sfm[:3, 3] + S[:3, 3]
  return out
