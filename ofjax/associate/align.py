"""Step 2: the similarity that maps the SfM frame (P_om, OM cameras) into the WLI um frame (P_wli).

Conventions: `S` is a [4, 4] similarity [s R | t] with x_um = s R x_sfm + t (s = um per SfM unit).
"Up" is the WLI frame's sample normal (world +z in ofjax.associate's frame); the height map of
P_wli holds the range of its heights over the plane normal to up, in cells of a given size.

Why not one-sided ICP fitness: the OM photos usually cover more than the WLI footprint, and P_wli
has voids (steep sides). Scaled ICP scored by the share of SfM points near P_wli therefore shrinks
P_om (more points land inside the footprint, fewer in voids), and on a mostly flat part (a
circuit board) a shrunk, turned copy fits as well as the truth. The criterion here compares
heights instead: an SfM point inside the WLI footprint costs min(r / gate, 1)^2, with r how far
its height lies outside the range of the WLI heights in its cell (a point over a WLI void costs
VOID_COST, points outside the footprint nothing), so a board point moved onto a component top
pays in full. A candidate must also cover the footprint: the share of footprint cells with an SfM
point nearby must be close to the best candidate's, which rules out solutions that slide most of
P_om off the footprint to hide it.

Search: the OM cameras look down on the sample, so their mean viewing direction fixes up in the
SfM frame; the turn about up (every 15 degrees) and the scale (a log grid around the ratio of the
clouds' robust spreads, which underestimates when the photos see more than the WLI) are swept,
plus FPFH + RANSAC global registration on scale-normalised clouds as one more turn. Each
candidate gets a rigid ICP at its scale on coarse clouds and is scored on a coarse height map;
the best few distinct ones get a 1-D search over the scale (rigid refit at every scale, fine
height map); the best is polished by robust point-to-plane least squares with scaling (`_polish`),
which sets the final scale, tilt and offset more finely than the height cost's cells. A sample
that is symmetric to the data (a MEMS die turned by 180 degrees) leaves finalists turned from
one another that fit about equally well. When the photos carry stage priors (tilt and azimuth,
as the WLI scans'), `stage_turn` estimates the similarity's rotation from them, the finalists
are polished and compared by the polish's objective, and where turns within TURN_WARN_MARGIN of
the best remain, the priors choose the turn (the one nearest their estimate) and the data the
fit within it (`_choose_turn`). The priors decide nothing else: a clear winner stands even where
they disagree (the CLI warns). The result
is rejected (UserError) when too few SfM points meet the WLI surface, or when the polish's
objective has no clear minimum at the found scale (scale_is_determined: the scale is then not
determined by the data, and wrong poses must not be written).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ofjax.associate import register
from ofjax.errors import UserError

GLOBAL_VOXELS_ACROSS = 40  # coarse resolution: clouds ~40 voxels across their robust spread
YAW_STEPS = 24  # the turn about up is swept every 15 degrees
SCALE_RANGE = (0.5, 2.2)  # swept scales relative to the spread-ratio estimate ...
SCALE_STEP = 1.1  # ... in steps of this factor
SEED_GATES_SPREADS = (0.3, 0.1)  # rigid ICP gates of the coarse search, in robust spreads ...
SEED_GATE_VOXELS = 2.0  # ... then in coarse voxels (also the coarse height gate)
FINE_CELL_VOXELS = 2.0  # fine height map cells, in P_wli voxels ...
FINE_GATE_VOXELS = 3.0  # ... and the fine height gate (SfM points scatter ~1 voxel)
VOID_COST = 0.5  # cost of an SfM point over a WLI void: unknown, half an outlier
COVERAGE_SHARE = 0.7  # candidates must cover this share of the best candidate's footprint coverage
FOOTPRINT_CLOSING = 2  # cells: closes the gaps between WLI samples before filling voids
FINALISTS = 6  # the best distinct candidates searched over the scale
DISTINCT_DEG = 10.0  # candidates whose turns differ by less than this ...
DISTINCT_LOG_SCALE = 0.15  # ... and whose scales differ by less than this (log) are one solution
SCALE_SEARCH = 0.12  # the 1-D scale search spans +-this (log) around a finalist ...
SCALE_GRID = 7  # ... on a grid of this many scales (4% apart), which the polish then refines
POLISH_GATES_VOXELS = (3.0, 2.0, 1.5)  # the scaled point-to-plane polish's pairing gates (P_wli
# voxels); the last is also the final fitness gate (wider gates let SfM points where the WLI has
# voids pull on the fit)
POLISH_ITERATIONS = 30  # Gauss-Newton steps per gate at most ...
POLISH_TOL = 1e-7  # ... ending early when a step's norm (radians, um, log scale) is below this
POLISH_MIN_PAIRS = 20  # fewer weighted pairs than this leave the similarity as it is
DAMPING = 1e-6  # Tikhonov share of the normal equations' mean diagonal: bounds the step
# along a direction the data do not fix (the scale over a flat board)
SCALE_PROBE = 0.05  # the found scale is probed this far either side (relative) ...
SCALE_PEAK_MARGIN = 0.05  # ... where the polish's objective must be higher, by this much (relative)
# on average over the two sides (scale_is_determined)
TURN_WARN_MARGIN = 0.1  # a turned solution within this relative cost of the best is warned about
COST_FLOOR = 1e-12  # keeps the relative turn margin finite when the best cost is 0 (exact data)
PRIOR_CONTENDERS = 3.0  # with stage priors, finalists within this factor of the best cost are
# polished and compared (_choose_turn)


@dataclasses.dataclass
class Alignment:
  S: np.ndarray  # [4, 4] um_from_sfm similarity
  scale: float  # s: um per SfM unit
  fitness: float  # share of P_om points within the final gate of P_wli
  rmse_um: float  # RMS distance of those points
  residuals_um: np.ndarray  # [N] distance of every aligned P_om point to its nearest P_wli point
  seed: str  # "fpfh" or "cameras": where the winning turn came from
  initial_scale: float  # the spread-ratio estimate of s
  height_cost: float  # the fine height cost of S (module docstring), 0 = every point on H
  coverage: float  # share of the WLI footprint with an aligned SfM point nearby
  # relative cost gap to the best solution turned > DISTINCT_DEG away: the height cost's, or the
  # polish objective's where the stage priors decided (negative when they chose the costlier turn)
  turn_margin: float
  turn_runner_up_deg: float  # that solution's turn from the winner (NaN if there is none)
  turn_source: str = "data"  # "priors" when the photos' stage priors chose among near-equal turns
  prior_deg: float = float("nan")  # rotation angle from the priors' estimate (NaN without priors)


class HeightMap:
  """Height range of a z-up cloud on a grid of `cell`-sized squares, and the costs of the module
  docstring. points: [M, 3] with z up."""

  def __init__(self, points: np.ndarray, cell: float):
    self.cell = cell
    self.lo = points[:, :2].min(0) - 2 * cell
    ij = self._cells(points)
    self.shape = tuple(ij.max(0) + 3)
    top, bottom = np.full(self.shape, -np.inf), np.full(self.shape, np.inf)
    np.maximum.at(top, (ij[:, 0], ij[:, 1]), points[:, 2])
    np.minimum.at(bottom, (ij[:, 0], ij[:, 1]), points[:, 2])
    # [X, Y] height range of the WLI points in a cell, NaN = void: a point anywhere in it is on
    # the surface (a slope or a wall spans a range within one cell)
    self.top = np.where(np.isfinite(top), top, np.nan)
    self.bottom = np.where(np.isfinite(bottom), bottom, np.nan)
    measured = ndimage.binary_closing(np.isfinite(self.top), iterations=FOOTPRINT_CLOSING)
    self.footprint = ndimage.binary_fill_holes(measured)  # [X, Y] inside the WLI's area

  def _cells(self, points: np.ndarray) -> np.ndarray:
    return np.floor((points[:, :2] - self.lo) / self.cell).astype(np.int64)

  def _lookup(self, points: np.ndarray):
    ij = self._cells(points)
    ok = np.all((ij >= 0) & (ij < self.shape), axis=1)
    inside = np.zeros(len(points), bool)
    inside[ok] = self.footprint[ij[ok, 0], ij[ok, 1]]
    return ij, inside

  def cost(self, points: np.ndarray, gate: float) -> float:
    """Mean height cost of `points` [N, 3] inside the footprint (1.0 when fewer than 10 are)."""
    ij, inside = self._lookup(points)
    if inside.sum() < 10:
      return 1.0
    z, k = points[inside, 2], (ij[inside, 0], ij[inside, 1])
    r = np.maximum(np.maximum(self.bottom[k] - z, z - self.top[k]), 0.0)
    return float(np.mean(np.where(np.isfinite(r), np.minimum(r / gate, 1.0) ** 2, VOID_COST)))

  def coverage(self, points: np.ndarray) -> float:
    """Share of footprint cells within one cell of one of `points` [N, 3]."""
    ij, inside = self._lookup(points)
    hit = np.zeros(self.shape, bool)
    hit[ij[inside, 0], ij[inside, 1]] = True
    return float((ndimage.binary_dilation(hit) & self.footprint).sum() / self.footprint.sum())


def robust_frame(points: np.ndarray) -> tuple[np.ndarray, float]:
  """points: [N, 3] -> (median point [3], median distance to it): outlier-proof centre and size."""
  c = np.median(points, axis=0)
  return c, float(np.median(np.linalg.norm(points - c, axis=1)))


def _similarity(s: float, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = s * rot, t
  return m


def _apply(S: np.ndarray, points: np.ndarray) -> np.ndarray:
  return points @ S[:3, :3].T + S[:3, 3]


def _scale_of(S: np.ndarray) -> float:
  return float(np.cbrt(np.linalg.det(S[:3, :3])))


def _rescaled(S: np.ndarray, factor: float, centre: np.ndarray) -> np.ndarray:
  """S with its scale times `factor`, about the um-frame point `centre` [3]."""
  out = S.copy()
  out[:3, :3] *= factor
  out[:3, 3] = factor * S[:3, 3] + (1 - factor) * centre
  return out


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


def _rigid_refit(points: np.ndarray, S: np.ndarray, tgt, gates) -> np.ndarray:
  """S followed by rigid point-to-plane ICP of `points` [N, 3] (SfM frame) onto `tgt`, one round
  per gate of `gates` (um) -> [4, 4]."""
  moved = register.to_cloud(_apply(S, points))
  T = np.eye(4)
  for gate in gates:
    T = np.asarray(register.icp(moved, tgt, T, gate).transformation)
  return T @ S


def _plane_pairs(x: np.ndarray, p_wli: np.ndarray, wli_normals: np.ndarray, tree: cKDTree,
                 hm: HeightMap, cut: float):
  """Pairs of moved SfM points x [N, 3] inside the WLI footprint with their nearest P_wli point
  within `cut` -> (inside [N] bool, paired [N] bool, normals [K, 3], signed point-to-plane
  residuals [K]) for the K paired points."""
  _, inside = hm._lookup(x)
  d, j = tree.query(x, distance_upper_bound=cut)
  paired = inside & np.isfinite(d)
  n = wli_normals[j[paired]]
  return inside, paired, n, np.einsum("ij,ij->i", n, x[paired] - p_wli[j[paired]])


def _polish(p_om: np.ndarray, S: np.ndarray, p_wli: np.ndarray, wli_normals: np.ndarray,
            tree: cKDTree, hm: HeightMap, voxel: float, free_scale: bool = True) -> np.ndarray:
  """Robust point-to-plane alignment with scaling: the similarity S' = D S minimising
  sum_i rho(n_i . (S' p_i - q_i)) over SfM points p_i inside the WLI footprint (hm) paired with
  their nearest P_wli point q_i (normal n_i) within each gate of POLISH_GATES_VOXELS; rho is
  Tukey's biweight with its cut at the gate. Gauss-Newton over D = (rotation vector w,
  translation t, log scale u) linearised about the moved points' median c:
  d r_i = ((x_i - c) x n_i) . w + n_i . t + (n_i . (x_i - c)) u; `free_scale=False` holds u = 0.
  (open3d's point-to-plane estimation has no scale, and point-to-point pairs a sparse SfM point
  with the nearest WLI sample rather than the surface, which biases scale and tilt.)

  p_om: [N, 3] SfM frame; S: [4, 4] start; p_wli, wli_normals: [M, 3] z-up frame; -> [4, 4].
  """
  c = np.median(_apply(S, p_om), axis=0)
  dof = 7 if free_scale else 6
  for gate in POLISH_GATES_VOXELS:
    cut = gate * voxel
    for _ in range(POLISH_ITERATIONS):
      x = _apply(S, p_om)
      _, paired, n, r = _plane_pairs(x, p_wli, wli_normals, tree, hm, cut)
      xc = x[paired] - c
      w = np.where(np.abs(r) < cut, (1 - (r / cut) ** 2) ** 2, 0.0)
      if np.count_nonzero(w) < POLISH_MIN_PAIRS:
        return S
      J = np.column_stack([np.cross(xc, n), n, np.einsum("ij,ij->i", n, xc)])[:, :dof]
      H = J.T @ (J * w[:, None])
      step = np.zeros(7)
      step[:dof] = np.linalg.solve(H + DAMPING * np.trace(H) / dof * np.eye(dof), -J.T @ (w * r))
      D = _similarity(float(np.exp(step[6])), Rotation.from_rotvec(step[:3]).as_matrix(),
                      np.zeros(3))
      D[:3, 3] = c + step[3:6] - D[:3, :3] @ c
      S = D @ S
      if np.linalg.norm(step) < POLISH_TOL:
        break
  return S


def _fit_cost(p_om: np.ndarray, S: np.ndarray, p_wli: np.ndarray, wli_normals: np.ndarray,
              tree: cKDTree, hm: HeightMap, cut: float) -> float:
  """The polish's objective as a mean over the SfM points inside the footprint: Tukey's loss
  normalised to [0, 1] (1 - (1 - (r/cut)^2)^3 within the cut), 1 for a point with no WLI point
  within `cut` (1.0 when fewer than POLISH_MIN_PAIRS are inside)."""
  inside, _, _, r = _plane_pairs(_apply(S, p_om), p_wli, wli_normals, tree, hm, cut)
  if inside.sum() < POLISH_MIN_PAIRS:
    return 1.0
  loss = np.where(np.abs(r) < cut, 1 - (1 - (r / cut) ** 2) ** 3, 1.0)
  return float((loss.sum() + inside.sum() - len(r)) / inside.sum())


def scale_is_determined(cost: float, probes: list[float]) -> bool:
  """Whether the polish's objective has a clear minimum at the found scale: it costs `cost` there
  and `probes` at SCALE_PROBE either side (the other six parameters re-polished). Both sides must
  cost more, and by SCALE_PEAK_MARGIN on average: the objective's curvature over the probes. Not
  each side by the margin: Tukey's loss saturates, so the two sides rise unequally where the
  relief that fixes the scale is sparse (a flat board with a few chips: -5% costs 4.4% more and
  +5% 11.8% on `circuit`, whose scale is then right to 0.3%), while a free scale (a plane) leaves
  both sides at the found cost."""
  return min(probes) > cost and float(np.mean(probes)) >= (1 + SCALE_PEAK_MARGIN) * cost


def _distinct(cands: list, limit: int) -> list:
  """The first `limit` of `cands` [(cost, scale, S, seed, coverage)], best first, that differ in
  turn or scale from every earlier one kept."""
  kept = []
  for c in cands:
    r = c[2][:3, :3] / c[1]
    if all(_angle_deg(r, k[2][:3, :3] / k[1]) > DISTINCT_DEG
           or abs(np.log(c[1] / k[1])) > DISTINCT_LOG_SCALE for k in kept):
      kept.append(c)
    if len(kept) == limit:
      break
  return kept


def _scale_search(p_om: np.ndarray, S: np.ndarray, tgt, hm: HeightMap, gates, gate: float,
                  centre: np.ndarray):
  """1-D search of the log scale of S on a grid of SCALE_GRID scales, each with a rigid refit ->
  (height cost, S) of the best (the polish refines it: the height cost's cells are too coarse to
  fix the scale to better than a few tenths of a percent)."""
  tried = []
  for u in np.linspace(-SCALE_SEARCH, SCALE_SEARCH, SCALE_GRID):
    Su = _rigid_refit(p_om, _rescaled(S, float(np.exp(u)), centre), tgt, gates)
    tried.append((hm.cost(_apply(Su, p_om), gate), Su))
  return min(tried, key=lambda c: c[0])


def stage_turn(sfm_rotations: list[np.ndarray], stage_rotations: list[np.ndarray]) -> np.ndarray:
  """[3, 3] the rotation R of S that best maps the photos' SfM camera rotations onto their stage
  priors' (R @ R_sfm_i ~ R_stage_i): the chordal L2 mean of R_stage_i @ R_sfm_i^T, projected
  onto SO(3) by SVD. sfm_rotations, stage_rotations: [3, 3] each, in the same order."""
  m = sum(r_stage @ r_sfm.T for r_sfm, r_stage in zip(sfm_rotations, stage_rotations))
  u, _, vt = np.linalg.svd(m)
  return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _rotation(S: np.ndarray) -> np.ndarray:
  return S[:3, :3] / _scale_of(S)


def _choose_turn(contenders: list, hint: np.ndarray) -> int | None:
  """The stage priors' choice among `contenders` [(cost, S, seed)], sorted by cost: None when
  those within TURN_WARN_MARGIN of the best share its turn (the data decide); otherwise the
  priors choose the turn, that of the near-equal contender closest to the rotation `hint`
  [3, 3], and the data the contender within it: the index of that turn's cheapest."""
  rot = lambda k: _rotation(contenders[k][1])
  best = contenders[0][0]
  ties = [k for k in range(len(contenders))
          if (contenders[k][0] - best) / max(best, COST_FLOOR) < TURN_WARN_MARGIN]
  if all(_angle_deg(rot(0), rot(k)) <= DISTINCT_DEG for k in ties):
    return None
  pick = min(ties, key=lambda k: _angle_deg(rot(k), hint))
  return next(k for k in range(len(contenders)) if _angle_deg(rot(k), rot(pick)) <= DISTINCT_DEG)


def align_om_to_wli(p_om: np.ndarray, p_wli: np.ndarray, wli_normals: np.ndarray,
                    wli_voxel_um: float, om_forward: np.ndarray, min_fitness: float = 0.3,
                    scene_dir: str = "SCENE_DIR", wli_up=(0.0, 0.0, 1.0),
                    turn_hint: np.ndarray | None = None, seed: int = 0) -> Alignment:
  """Similarity alignment of P_om onto P_wli (module docstring).

  p_om: [N, 3] SfM frame; p_wli: [M, 3] um; wli_normals: [M, 3] unit normals of P_wli;
  om_forward: [K, 3] the OM cameras' viewing directions in the SfM frame; wli_voxel_um: spacing of
  P_wli; wli_up: [3] the sample's up direction in P_wli's frame; turn_hint: [3, 3] the stage
  priors' estimate of S's rotation in P_wli's frame (`stage_turn`), or None; seed: the global
  registration's RANSAC. A final fitness below `min_fitness` (share of SfM points within
  POLISH_GATES_VOXELS[-1] of P_wli) is a UserError.
  """
  if len(p_om) < 10:
    raise UserError(f"{scene_dir}/om: structure-from-motion left only {len(p_om)} reliable points; "
                    "take sharper photos of a textured surface")
  # Work in a z-up copy of the WLI frame (`level`), map the result back at the end.
  level = np.eye(4)
  level[:3, :3] = _rot_to_z(np.asarray(wli_up, np.float64))
  p_wli = _apply(level, p_wli)
  wli_normals = wli_normals @ level[:3, :3].T
  c_om, r_om = robust_frame(p_om)
  c_wli, r_wli = robust_frame(p_wli)
  s0 = r_wli / r_om
  tgt = register.to_cloud(p_wli, wli_normals)
  gv = r_wli * 2 / GLOBAL_VOXELS_ACROSS
  tgt_coarse = tgt.voxel_down_sample(gv)
  src_coarse = np.asarray(register.to_cloud(p_om).voxel_down_sample(gv / s0).points)
  hm_coarse = HeightMap(p_wli, gv)
  hm_cover = HeightMap(p_wli, 2 * gv)  # coverage cells of ~2 SfM point spacings
  hm_fine = HeightMap(p_wli, FINE_CELL_VOXELS * wli_voxel_um)
  fine_gate = FINE_GATE_VOXELS * wli_voxel_um
  # Turns: about up from the cameras, and the FPFH one (x_um = g (s0 (x - c_om)) + c_wli).
  src_n = register.downsample(register.to_cloud((p_om - c_om) * s0), gv)
  tgt_n = register.downsample(register.to_cloud(p_wli - c_wli), gv)
  fpfh = register.global_register(src_n, tgt_n, gv, seed)
  turns = [("fpfh", np.asarray(fpfh.transformation)[:3, :3])]
  up = _rot_to_z(-np.mean(om_forward, axis=0))
  turns += [("cameras", _rz(2 * np.pi * k / YAW_STEPS) @ up) for k in range(YAW_STEPS)]
  coarse_gates = [f * r_wli for f in SEED_GATES_SPREADS] + [SEED_GATE_VOXELS * gv]
  cands = []  # (coarse cost, scale, S, seed, coverage)
  for f in np.exp(np.arange(np.log(SCALE_RANGE[0]), np.log(SCALE_RANGE[1]), np.log(SCALE_STEP))):
    s = s0 * f
    for name, rot in turns:
      S = _rigid_refit(src_coarse, _similarity(s, rot, c_wli - s * rot @ c_om), tgt_coarse,
                       coarse_gates)
      moved = _apply(S, src_coarse)
      cands.append((hm_coarse.cost(moved, SEED_GATE_VOXELS * gv), _scale_of(S), S, name,
                    hm_cover.coverage(moved)))
  best_cover = max(c[4] for c in cands)
  cands = sorted((c for c in cands if c[4] >= COVERAGE_SHARE * best_cover), key=lambda c: c[0])
  fine_gates = [4 * gv, 2 * gv, 8 * wli_voxel_um, fine_gate]
  finals = []
  for _, _, S0, name, _ in _distinct(cands, FINALISTS):
    cost, S = _scale_search(p_om, S0, tgt, hm_fine, fine_gates, fine_gate, c_wli)
    if hm_cover.coverage(_apply(S, p_om)) < COVERAGE_SHARE * best_cover:
      continue
    finals.append((cost, S, name))
  if not finals:
    raise UserError(f"{scene_dir}: OM-to-WLI alignment failed: no placement of the SfM points "
                    "covers the WLI scans; check that the photos and scans show the same sample")
  finals.sort(key=lambda c: c[0])
  tree = cKDTree(p_wli)
  final_gate = POLISH_GATES_VOXELS[-1] * wli_voxel_um
  fit_args = (p_wli, wli_normals, tree, hm_fine)
  polish = lambda S: _polish(p_om, S, *fit_args, wli_voxel_um)
  _, S, seed = finals[0]
  ranked, chosen, turn_source = finals, 0, "data"
  hint = None if turn_hint is None else level[:3, :3] @ turn_hint
  if hint is not None:
    # The height cost bins heights in cells that a half turn does not map onto cells, so it
    # tells the turns of a symmetric sample apart by its walls' binning (0.019 vs 0.028 on the
    # test's board that a half turn maps onto itself, polished). The priors therefore compare
    # the contenders polished, by the polish's own, unbinned objective.
    contenders = sorted(((_fit_cost(p_om, P, *fit_args, final_gate), P, name)
                         for P, name in ((polish(S), name) for c, S, name in finals
                                         if c <= PRIOR_CONTENDERS * finals[0][0])),
                        key=lambda c: c[0])
    k = _choose_turn(contenders, hint)
    if k is not None:
      ranked, chosen, turn_source = contenders, k, "priors"
      if _angle_deg(_rotation(contenders[k][1]), _rotation(S)) > DISTINCT_DEG:
        _, S, seed = contenders[k]  # the priors turn the data's choice
  # A (nearly) symmetric sample fits a turned copy almost as well; the margin says how clearly
  # the data chose the turn (the CLI warns when it is small).
  turned = [(c - ranked[chosen][0], _angle_deg(_rotation(ranked[chosen][1]), _rotation(T)))
            for k, (c, T, _) in enumerate(ranked) if k != chosen]
  turned = [t for t in turned if t[1] > DISTINCT_DEG]
  margin, runner_up_deg = (turned[0][0] / max(ranked[chosen][0], COST_FLOOR), turned[0][1]) \
      if turned else (float("inf"), float("nan"))
  S = polish(S)
  moved = _apply(S, p_om)
  cost = hm_fine.cost(moved, fine_gate)
  src = register.to_cloud(p_om)
  res = o3d.pipelines.registration.evaluate_registration(src, tgt, final_gate, S)
  if res.fitness < min_fitness:
    raise UserError(f"{scene_dir}: OM-to-WLI alignment failed: only {res.fitness:.0%} of the SfM "
                    f"points lie within {final_gate:.3g} um of the WLI surface (need "
                    f"{min_fitness:.0%}); check that the photos and scans show the same sample")
  # A determined scale is a clear minimum of the polish's objective: scales SCALE_PROBE either
  # side, each with the other six parameters re-polished, must cost clearly more (a flat part
  # leaves the scale free).
  cost_fit = _fit_cost(p_om, S, *fit_args, final_gate)
  probes = [_fit_cost(p_om, _polish(p_om, _rescaled(S, 1 + d, c_wli), *fit_args, wli_voxel_um,
                                    free_scale=False), *fit_args, final_gate)
            for d in (-SCALE_PROBE, SCALE_PROBE)]
  if not scale_is_determined(cost_fit, probes):
    raise UserError(f"{scene_dir}: OM-to-WLI alignment is ambiguous: scaling the SfM points by "
                    f"{1 - SCALE_PROBE:g} or {1 + SCALE_PROBE:g} fits the WLI surface about as "
                    f"well (cost {probes[0]:.3f} / {probes[1]:.3f} vs {cost_fit:.3f}), so the "
                    "scale is not determined; scan a larger area with relief (WLI) or take photos "
                    "with more overlap so that both clouds share distinct 3D structure")
  coverage = hm_cover.coverage(moved)
  prior_deg = float("nan") if hint is None else _angle_deg(_rotation(S), hint)
  # Distances do not change when the level turn is undone, so they are taken in its frame.
  residuals = np.asarray(register.to_cloud(moved).compute_point_cloud_distance(tgt))
  S = np.linalg.inv(level) @ S
  return Alignment(S, _scale_of(S), float(res.fitness), float(res.inlier_rmse), residuals, seed,
                   s0, cost, coverage, float(margin), float(runner_up_deg), turn_source, prior_deg)


def om_c2w_um(c2w_sfm: np.ndarray, S: np.ndarray) -> np.ndarray:
  """[4, 4] rigid camera-to-world in um from an SfM-frame c2w and the similarity S."""
  s = np.cbrt(np.linalg.det(S[:3, :3]))
  out = np.eye(4)
  out[:3, :3] = S[:3, :3] / s @ c2w_sfm[:3, :3]
  out[:3, 3] = S[:3, :3] @ c2w_sfm[:3, 3] + S[:3, 3]
  return out
