"""The conventional baseline (OpticFusion Sec. 3.3.1): screened Poisson on WLI + projected OM colour.

`python -m ofjax.conventional SCENE_DIR --out DIR [--poses FILE] [--depth 9]` writes DIR/mesh.ply
(um, vertex colours), DIR/mesh.png (top view: colour and height) and DIR/config.json
(parameters, counts, timings).

Steps (all in um, on a posed Scene):
  1. cloud     every valid WLI depth back-projected (`Scene.wli_points`), merged.
  2. normals   estimated by open3d from the `normal_knn` nearest neighbours of the merged cloud,
               then each flipped to face the WLI camera that measured its point (n . d < 0 for the
               scan's viewing direction d).
  3. Poisson   open3d's screened Poisson reconstruction at octree `depth`.
  4. trimming  vertices whose Poisson density (samples supporting them) is below the
               `trim_quantile` quantile are dropped (Poisson's closure far from data); then the
               mesh is cropped to the WLI points' bounding box grown by `crop_margin_px` WLI pixels
               (the observed region), and connected components holding less than
               `min_component` of the triangles are removed.
  5. colour    for every vertex, among the OM photos that see it - in front of the camera, inside
               the frame, facing it (cos > 0), and unoccluded: a ray from the camera centre
               reaches the vertex before hitting the mesh elsewhere, within `visibility_tol` x the
               median edge length - the most frontal one (largest cos between the vertex normal
               and the direction to the camera) gives the colour, sampled bilinearly at the
               vertex's projection. Vertices no photo sees take their nearest coloured vertex's
               colour (all grey when no photo sees any vertex).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from ofjax import fileio, meshfile, plots, visibility
from ofjax import scene as scn
from ofjax.errors import UserError, cli
from ofjax.meshquery import MeshQuery

MIN_POINTS = 100  # fewer WLI points cannot support a Poisson surface
UNSEEN_GREY = 0.5  # the colour of every vertex when no photo sees any (a scene without OM photos)


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
  depth: int = 9  # Poisson octree depth
  normal_knn: int = 30  # neighbours for normal estimation
  trim_quantile: float = 0.02  # vertices below this density quantile are dropped
  crop_margin_px: float = 2.0  # the observed box is grown by this many WLI pixels
  min_component: float = 0.01  # components below this share of the triangles are removed
  visibility_tol: float = 0.5  # occlusion slack, in median edge lengths
  stride: int = 1  # use every stride-th WLI pixel along rows and columns
  keep_hidden: bool = False  # keep the faces no camera sees (step 4; ofjax.visibility)


def wli_cloud(scene: scn.Scene, cfg: BaselineConfig) -> o3d.geometry.PointCloud:
  """Steps 1-2: the merged WLI points with normals facing their cameras."""
  points, dirs = [], []
  for s in scene.wli:
    p = scn.wli_points(s, cfg.stride)
    points.append(p)
    axis = s.c2w[:3, 2] / np.linalg.norm(s.c2w[:3, 2])  # the scan's viewing direction
    dirs.append(np.broadcast_to(axis, p.shape))
  points, dirs = np.concatenate(points), np.concatenate(dirs)
  if len(points) < MIN_POINTS:
    raise UserError(f"the scene's WLI scans hold only {len(points)} valid depths; Poisson needs "
                    f"at least {MIN_POINTS}: check the WLI files for voids")
  pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
  pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(cfg.normal_knn))
  n = np.asarray(pcd.normals)
  flip = np.sum(n * dirs, -1) > 0
  n[flip] *= -1
  pcd.normals = o3d.utility.Vector3dVector(n)
  return pcd


def poisson(pcd: o3d.geometry.PointCloud, cfg: BaselineConfig,
            pixel_size: float) -> o3d.geometry.TriangleMesh:
  """Steps 3-4: the trimmed, cropped Poisson surface."""
  # One thread: PoissonRecon's multithreaded build orders (and rounds) vertices differently run to
  # run; on one thread the same cloud gives the same bytes, at ~1.1x the time on 2 cores.
  mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
      pcd, depth=cfg.depth, n_threads=1)
  density = np.asarray(density)
  mesh.remove_vertices_by_mask(density < np.quantile(density, cfg.trim_quantile))
  box = pcd.get_axis_aligned_bounding_box()
  margin = cfg.crop_margin_px * pixel_size
  mesh = mesh.crop(o3d.geometry.AxisAlignedBoundingBox(box.min_bound - margin,
                                                      box.max_bound + margin))
  cluster, count, _ = mesh.cluster_connected_triangles()
  cluster, count = np.asarray(cluster), np.asarray(count)
  mesh.remove_triangles_by_mask(count[cluster] < cfg.min_component * len(cluster))
  mesh.remove_unreferenced_vertices()
  mesh.compute_vertex_normals()
  return mesh


def project_colours(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                    photos: list[scn.OMImage], cfg: BaselineConfig) -> tuple[np.ndarray, int]:
  """Step 5.

  Args:
    vertices: [V, 3] um; normals: [V, 3] unit, outward; faces: [F, 3].
  Returns:
    colours: [V, 3] RGB in [0, 1].
    n_unseen: how many vertices no photo sees (filled from their nearest coloured vertex).
  """
  query = MeshQuery(vertices, faces)
  edges = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=-1)
  tol = cfg.visibility_tol * float(np.median(edges))
  best = np.zeros(len(vertices))  # cos of the chosen view; 0 = none yet
  colours = np.full((len(vertices), 3), UNSEEN_GREY)
  for photo in photos:
    centre = photo.c2w[:3, 3]
    to_cam = centre - vertices
    cos = np.sum(normals * to_cam, -1) / np.linalg.norm(to_cam, axis=-1)
    u, v, inside = scn.project_pinhole(vertices, photo.K, photo.c2w, photo.shape)
    cand = np.flatnonzero((cos > best) & inside)
    if len(cand) == 0:
      continue
    cand = cand[query.clear(centre, vertices[cand], abs_slack=tol)]
    # Pixel (col c, row r) has its centre at (c + 0.5, r + 0.5): array index = coordinate - 0.5.
    coords = np.stack([v[cand] - 0.5, u[cand] - 0.5])
    colours[cand] = np.stack([ndimage.map_coordinates(photo.image[..., c], coords, order=1,
                                                      mode="nearest") for c in range(3)], -1)
    best[cand] = cos[cand]
  seen = best > 0
  if seen.any() and not seen.all():
    _, nearest = cKDTree(vertices[seen]).query(vertices[~seen])
    colours[~seen] = colours[seen][nearest]
  return colours, int((~seen).sum())


def reconstruct(scene: scn.Scene, cfg: BaselineConfig = BaselineConfig()
                ) -> tuple[trimesh.Trimesh, dict]:
  """The baseline mesh (um, vertex colours) of a posed scene, and what happened (counts, seconds)."""
  if not scene.posed:
    raise UserError(f"scene {scene.name!r} has cameras without poses; run `python -m "
                    "ofjax.associate` on it or pass --poses SCENE_DIR/ground_truth/poses.json")
  clock = time.perf_counter()
  timing = {}

  def lap(name):
    nonlocal clock
    now = time.perf_counter()
    timing[name] = round(now - clock, 3)
    clock = now

  pixel_size = float(np.mean([np.mean(s.pixel_size) for s in scene.wli]))
  pcd = wli_cloud(scene, cfg)
  lap("normals")
  mesh = poisson(pcd, cfg, pixel_size)
  lap("poisson")
  vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
  normals = np.asarray(mesh.vertex_normals)
  if len(faces) == 0:
    raise UserError("Poisson reconstruction left no surface after trimming; lower "
                    "--trim-quantile or check the WLI data")
  hidden = 0
  if not cfg.keep_hidden:
    seen = visibility.seen_faces(trimesh.Trimesh(vertices, faces, process=False),
                                 scn.poses_to_json(scene))
    hidden = int(np.sum(~seen))
    used = np.unique(faces[seen])
    remap = np.zeros(len(vertices), np.int64)
    remap[used] = np.arange(len(used))
    vertices, normals, faces = vertices[used], normals[used], remap[faces[seen]]
  lap("visibility")
  colours, unseen = project_colours(vertices, normals, faces, scene.om, cfg)
  lap("colour")
  out = trimesh.Trimesh(vertices, faces, vertex_colors=np.round(colours * 255).astype(np.uint8),
                        process=False)
  stats = {"wli_points": len(pcd.points), "vertices": len(vertices), "faces": len(faces),
           "hidden_faces_dropped": hidden, "unseen_vertices": unseen,
           "wli_pixel_size_um": pixel_size, "seconds": timing}
  return out, stats


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m ofjax.conventional", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  d = BaselineConfig()
  p.add_argument("scene", type=Path, help="scene directory (ofjax native bundle)")
  p.add_argument("--out", type=Path, required=True, help="output directory")
  p.add_argument("--poses", type=Path, help="poses file (default SCENE_DIR/poses.json; a "
                 "synthetic scene's truth is SCENE_DIR/ground_truth/poses.json)")
  p.add_argument("--depth", type=int, default=d.depth, help=f"Poisson octree depth ({d.depth})")
  p.add_argument("--trim-quantile", type=float, default=d.trim_quantile,
                 help=f"drop vertices below this Poisson-density quantile ({d.trim_quantile})")
  p.add_argument("--stride", type=int, default=d.stride,
                 help="use every n-th WLI pixel along rows and columns (1)")
  p.add_argument("--keep-hidden", action="store_true",
                 help="keep the faces no camera sees (pockets inside solid parts)")
  return p


@cli
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  if not 1 <= args.depth <= 14:
    raise UserError(f"--depth {args.depth}: choose an octree depth from 1 to 14 (9 is typical)")
  if not 0.0 <= args.trim_quantile < 1.0:
    raise UserError(f"--trim-quantile {args.trim_quantile}: must lie in [0, 1)")
  if args.stride < 1:
    raise UserError(f"--stride {args.stride}: must be a positive integer")
  if args.out.exists() and not args.out.is_dir():
    raise UserError(f"{args.out}: exists and is not a directory; choose another --out")
  cfg = BaselineConfig(depth=args.depth, trim_quantile=args.trim_quantile, stride=args.stride,
                       keep_hidden=args.keep_hidden)
  scene = scn.load_scene(args.scene, poses=args.poses)
  mesh, stats = reconstruct(scene, cfg)
  path = args.out / "mesh.ply"
  meshfile.write_mesh(mesh, path, scene.units)
  plots.mesh_preview(args.out / "mesh.png", mesh.vertices, mesh.faces,
                     np.asarray(mesh.visual.vertex_colors[:, :3]) / 255.0,
                     f"conventional baseline of {args.scene.name} (top view)")
  fileio.write_json(args.out / "config.json", {
      "method": "conventional: screened Poisson (open3d) on the merged WLI cloud + OM colour "
                "projection", "units": scene.units, "scene": str(args.scene),
      "poses": str(args.poses or args.scene / "poses.json"), **dataclasses.asdict(cfg), **stats})
  print(f"ofjax.conventional: {stats['vertices']} vertices, {stats['faces']} faces from "
        f"{stats['wli_points']} WLI points ({stats['unseen_vertices']} vertices seen by no photo); "
        f"{sum(stats['seconds'].values()):.1f} s; wrote {path} and {args.out / 'mesh.png'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
