"""Step 1, WLI: register the WLI scans to one another and merge them into P_wli (um).

Frames and conventions:
  scan-local frame  the orthographic camera's own frame (OpenCV axes: x along columns, y along
                    rows, z along the viewing axis); a valid pixel (r, c) is the point
                    ((c + 0.5 - W/2) sx, (r + 0.5 - H/2) sy, depth) in um (ofjax.scene's rays
                    with c2w = identity).
  world frame       scan 0's frame, turned "sample up": world = W @ local_0 with W's rotation
                    `prior_rotation(scan0.prior)` (TOP_FROM_CAMERA when it has no prior) and its
                    origin at the median point of scan 0, so the first (top) scan defines the frame.
  poses             c2w_i = W @ pose_i where pose_i maps scan i's local frame into scan 0's
                    (open3d's pose-graph node pose with node 0 as reference).

Acquisition prior (turntable): WLIScan.prior = {"tilt_deg": t, "azimuth_deg": a} says the
instrument looked at the sample from polar angle t off the sample's +z axis, at azimuth a
(counter-clockwise from +x about +z), as if the stage had been tilted by t towards a:
  R(t, a) = Rot(axis (-sin a, cos a, 0), angle t) @ TOP_FROM_CAMERA,  TOP_FROM_CAMERA = diag(1, -1, -1),
i.e. the top view (t = 0) looks down -z with image x along +x and image y along -y, and a tilted
view is the top view turned by t about the horizontal axis perpendicular to the azimuth (the
convention of ofjax.synth.view_rotation). Its
viewing direction is -(sin t cos a, sin t sin a, cos t). The prior only seeds ICP; when it does
not lead to a good fit (a different turntable convention, a wrong entry), FPFH + RANSAC global
registration takes over, so a prior can never make the result worse than having none.
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from ofjax import scene as scene_lib
from ofjax.associate import register
from ofjax.errors import UserError

TOP_FROM_CAMERA = np.diag([1.0, -1.0, -1.0])  # top view: camera z (forward) = sample -z
TOWARDS_CAMERA = np.array([0.0, 0.0, -1.0])  # in the scan-local frame, normals face the camera
COARSE_VOXEL_PX = 6.0  # coarse ICP level, in WLI pixels (sub-sampled ~36x for speed)
FINE_VOXEL_PX = 1.0  # final ICP level: every valid pixel, normals from neighbours within 3 px
COARSE_DISTANCE_VOXELS = 4.0  # ICP correspondence gate at the coarse level, in coarse voxels
FINE_DISTANCE_VOXELS = 1.0  # fine ICP gate in fine voxels: wider gates pair points across steps
GLOBAL_VOXELS_ACROSS = 60  # FPFH + RANSAC works on clouds with about this many voxels across
MIN_SCAN_POINTS = 100  # fewer valid pixels than this cannot be registered


@dataclasses.dataclass
class PairResult:
  """ICP of scan `source` onto scan `target` (indices into the scan list)."""
  source: int
  target: int
  fitness: float  # fraction of source points with a target point within the fine gate
  rmse_um: float  # RMS distance of those correspondences
  transformation: np.ndarray  # [4, 4] target_local_from_source_local
  information: np.ndarray  # [6, 6] open3d information matrix of the pair
  init: str  # "prior" or "global": where the ICP started


@dataclasses.dataclass
class WLIRegistration:
  c2w: list[np.ndarray]  # per scan [4, 4] camera-to-world in um
  pairs: list[PairResult]  # every pair that was tried (edges are those with enough fitness)
  points: np.ndarray  # [N, 3] merged cloud P_wli in the world frame (um)
  normals: np.ndarray  # [N, 3] unit normals of P_wli, facing the cameras
  voxel_um: float  # spacing of P_wli


def prior_rotation(prior: dict[str, float] | None) -> np.ndarray:
  """[3, 3] camera-to-sample rotation of a turntable acquisition prior (see module docstring)."""
  if not prior:
    return TOP_FROM_CAMERA.copy()
  t = np.deg2rad(float(prior.get("tilt_deg", 0.0)))
  a = np.deg2rad(float(prior.get("azimuth_deg", 0.0)))
  axis = np.array([-np.sin(a), np.cos(a), 0.0])
  return Rotation.from_rotvec(axis * t).as_matrix() @ TOP_FROM_CAMERA


def scan_local_points(scan: scene_lib.WLIScan) -> np.ndarray:
  """[N, 3] float64: the scan's valid depths in its own (scan-local) frame, um."""
  return scene_lib.wli_points(dataclasses.replace(scan, c2w=np.eye(4)))


def _rigid(rot: np.ndarray, t: np.ndarray) -> np.ndarray:
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = rot, t
  return m


def _register_pair(src: tuple, tgt: tuple, init: np.ndarray, coarse_gate: float,
                   fine_gate: float) -> o3d.pipelines.registration.RegistrationResult:
  """Coarse-to-fine point-to-plane ICP, then generalized ICP at the fine level (register.gicp);
  src/tgt are (coarse cloud, fine cloud)."""
  coarse = register.icp(src[0], tgt[0], init, coarse_gate)
  mid = register.icp(src[0], tgt[0], coarse.transformation, coarse_gate / 3)
  # The fine level starts at twice its gate: straight from the coarse level, a one-voxel gate
  # can hold a shift of ~2 pixels on a periodic structure (sensor scene: 2.0 px -> 0.25 px).
  fine = register.icp(src[1], tgt[1], mid.transformation, 2 * fine_gate, max_iterations=100)
  fine = register.icp(src[1], tgt[1], fine.transformation, fine_gate, max_iterations=100)
  return register.gicp(src[1], tgt[1], fine.transformation, fine_gate)


def _spanning_tree(n: int, edges: list[PairResult]) -> dict[int, PairResult]:
  """For every scan reachable from scan 0, the edge that links it to the tree (best fitness first)."""
  adj: dict[int, list[PairResult]] = {i: [] for i in range(n)}
  for e in edges:
    adj[e.source].append(e)
    adj[e.target].append(e)
  parent: dict[int, PairResult] = {}
  seen, queue = {0}, deque([0])
  while queue:
    i = queue.popleft()
    for e in sorted(adj[i], key=lambda e: -e.fitness):
      j = e.target if e.source == i else e.source
      if j not in seen:
        seen.add(j)
        parent[j] = e
        queue.append(j)
  return parent


def register_scans(scans: list[scene_lib.WLIScan], min_overlap: float = 0.2,
                   scene_dir: str = "SCENE_DIR", seed: int = 0) -> WLIRegistration:
  """Registers all scans into one um frame (module docstring) with a pose graph over all pairs.

  `min_overlap` is the ICP fitness a pair needs to count as overlapping; a scan that overlaps no
  other scan, or a set of scans not connected to scan 0, is a UserError. seed: the global
  registration's RANSAC (`register.global_register`).
  """
  if not scans:
    raise UserError(f"{scene_dir}/scene.json: the scene has no WLI scans; add at least one")
  px = float(np.mean([np.mean(s.pixel_size) for s in scans]))
  local = []
  for s in scans:
    pts = scan_local_points(s)
    if len(pts) < MIN_SCAN_POINTS:
      raise UserError(f"{scene_dir}/wli/{s.name}.npz: only {len(pts)} valid pixels; a scan needs "
                      f"at least {MIN_SCAN_POINTS} to be registered - remove or re-measure it")
    local.append(pts)
  coarse_v, fine_v = COARSE_VOXEL_PX * px, FINE_VOXEL_PX * px
  clouds = []
  for pts in local:
    full = register.to_cloud(pts)
    clouds.append((register.downsample(full, coarse_v, TOWARDS_CAMERA),
                   register.downsample(full, fine_v, TOWARDS_CAMERA, keep_points=True)))
  extent = max(float(np.linalg.norm(np.ptp(p, axis=0))) for p in local)
  global_v = max(coarse_v, extent / GLOBAL_VOXELS_ACROSS)
  global_clouds: list = [None] * len(scans)
  coarse_gate, fine_gate = COARSE_DISTANCE_VOXELS * coarse_v, FINE_DISTANCE_VOXELS * fine_v
  # Prior guess of each scan's pose in scan 0's frame: prior rotations, centroids on top of each
  # other (the translation is unknown; the coarse ICP gate covers the centroid offset of views).
  have_prior = all(s.prior for s in scans)
  rot0 = prior_rotation(scans[0].prior)
  guess = []
  for s, pts in zip(scans, local):
    rot = rot0.T @ prior_rotation(s.prior)
    guess.append(_rigid(rot, local[0].mean(0) - rot @ pts.mean(0)))

  def global_cloud(i):
    if global_clouds[i] is None:
      global_clouds[i] = register.downsample(register.to_cloud(local[i]), global_v, TOWARDS_CAMERA)
    return global_clouds[i]

  pairs = []
  for i in range(len(scans)):
    for j in range(i + 1, len(scans)):
      best, how = None, ""
      if have_prior:
        best, how = _register_pair(clouds[i], clouds[j], np.linalg.inv(guess[j]) @ guess[i],
                                   coarse_gate, fine_gate), "prior"
      if best is None or best.fitness < min_overlap:
        g = register.global_register(global_cloud(i), global_cloud(j), global_v, seed)
        res = _register_pair(clouds[i], clouds[j], g.transformation, coarse_gate, fine_gate)
        if best is None or res.fitness > best.fitness:
          best, how = res, "global"
      info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
          clouds[i][1], clouds[j][1], fine_gate, best.transformation)
      pairs.append(PairResult(i, j, float(best.fitness), float(best.inlier_rmse),
                              np.asarray(best.transformation).copy(), np.asarray(info), how))
  edges = [p for p in pairs if p.fitness >= min_overlap]
  tree = _spanning_tree(len(scans), edges)
  lonely = [scans[i].name for i in range(1, len(scans)) if i not in tree]
  if lonely:
    best_fit = {scans[i].name: max((p.fitness for p in pairs if i in (p.source, p.target)),
                                   default=0.0) for i in range(len(scans))}
    detail = ", ".join(f"{n} (best fitness {best_fit[n]:.2f})" for n in lonely)
    raise UserError(f"{scene_dir}/wli: scan(s) {detail} do not overlap the others (ICP fitness "
                    f"< {min_overlap}); measure scans that share surface or remove them")
  # Node poses (scan 0 <- scan i) by chaining tree edges from scan 0.
  poses = {0: np.eye(4)}

  def pose_of(i):
    if i not in poses:
      e = tree[i]
      if e.source == i:  # T maps i into the parent's frame
        poses[i] = pose_of(e.target) @ e.transformation
      else:
        poses[i] = pose_of(e.source) @ np.linalg.inv(e.transformation)
    return poses[i]

  reg = o3d.pipelines.registration
  graph = reg.PoseGraph()
  for i in range(len(scans)):
    graph.nodes.append(reg.PoseGraphNode(pose_of(i)))
  tree_ids = {id(e) for e in tree.values()}
  for e in edges:
    graph.edges.append(reg.PoseGraphEdge(e.source, e.target, e.transformation, e.information,
                                         uncertain=id(e) not in tree_ids))
  if len(edges) > len(tree):  # loops exist: distribute the pairwise errors over the graph
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(),
                            reg.GlobalOptimizationOption(max_correspondence_distance=fine_gate,
                                                         edge_prune_threshold=0.25,
                                                         reference_node=0))
  node_poses = [np.asarray(graph.nodes[i].pose) for i in range(len(scans))]
  node_poses = [np.linalg.inv(node_poses[0]) @ p for p in node_poses]  # keep scan 0 the reference
  world = _rigid(rot0, -rot0 @ np.median(local[0], axis=0))
  c2w = [world @ p for p in node_poses]
  merged = o3d.geometry.PointCloud()
  for (_, fine), m in zip(clouds, c2w):
    merged += o3d.geometry.PointCloud(fine).transform(m)
  merged = merged.voxel_down_sample(fine_v)
  return WLIRegistration(c2w, pairs, np.asarray(merged.points), np.asarray(merged.normals), fine_v)
