"""Tests of the two-step data association (ofjax.associate) against known poses.

The test scene is built here, independently of the code under test: a textured block sample
(trimesh primitives) ray-cast with open3d, orthographically for the 5 WLI scans (top + 30 deg tilt
at 4 azimuths) and through pinholes for the 37 OM photos (top + rings at 15/30/45 deg every 30 deg),
with poses from the acquisition geometry. Thresholds are the issue's done-when targets.
"""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy import ndimage

from ofjax import scene as scene_lib
from ofjax.associate import __main__ as cli
from ofjax.associate import evaluate, wli
from ofjax.errors import UserError

PX = 1.0  # WLI pixel size, um
WLI_SHAPE = (200, 240)
OM_SHAPE = (240, 320)  # rows, cols
OM_FOCAL = 520.0  # px: the 240 um wide sample fills most of a photo from OM_DISTANCE
OM_DISTANCE = 420.0  # um from the scene centre
WLI_DISTANCE = 300.0  # um: any value works, depth is measured from the camera plane


def block_mesh() -> trimesh.Trimesh:
  parts = [trimesh.creation.box((200, 160, 20)).apply_translation((0, 0, -10)),
           trimesh.creation.icosphere(4, 35).apply_translation((-40, 20, 0)),
           trimesh.creation.cylinder(20, 50, 64).apply_translation((45, -30, 25)),
           trimesh.creation.box((40, 30, 30)).apply_transform(
               trimesh.transformations.rotation_matrix(0.5, (0, 0, 1))).apply_translation(
                   (30, 45, 15)),
           trimesh.creation.cone(25, 40, 64).apply_translation((-50, -40, 0))]
  return trimesh.util.concatenate(parts)


def raycast(mesh: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray):
  """Hit distance [...] (NaN on a miss), hit point [..., 3] and unit normal [..., 3]."""
  rc = o3d.t.geometry.RaycastingScene()
  rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                   o3d.core.Tensor(mesh.faces.astype(np.uint32)))
  rays = np.concatenate([origins, dirs], -1).reshape(-1, 6).astype(np.float32)
  hit = rc.cast_rays(o3d.core.Tensor(rays))
  t = hit["t_hit"].numpy().astype(np.float64).reshape(origins.shape[:-1])
  t[~np.isfinite(t)] = np.nan
  normals = hit["primitive_normals"].numpy().reshape(origins.shape)
  return t, origins + dirs * np.nan_to_num(t)[..., None], normals


def albedo(p: np.ndarray) -> np.ndarray:
  """[..., 3] in [0.1, 0.9]: value noise of the 3-D point at 8 and 3 um periods (SIFT texture)."""
  lattice = np.random.default_rng(1).random((3, 32, 32, 32))
  out = 0
  for period, w in ((8.0, 0.6), (3.0, 0.4)):
    c = (p.reshape(-1, 3) / period).T
    out = out + w * np.stack([ndimage.map_coordinates(lattice[k], c, order=1, mode="grid-wrap")
                              for k in range(3)], -1)
  return (0.1 + 0.8 * out).reshape(p.shape)


def look(tilt: float, azimuth: float, distance: float, target=(0.0, 0.0, 10.0)) -> np.ndarray:
  """[4, 4] c2w looking at `target` from (tilt, azimuth), in the prior's convention."""
  rot = wli.prior_rotation({"tilt_deg": tilt, "azimuth_deg": azimuth})
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = rot, np.asarray(target) - distance * rot[:, 2]
  return m


def make_scene() -> tuple[scene_lib.Scene, dict]:
  """The test scene (raw data, no poses) and its ground-truth poses file contents.

  The truth lives in its own frame: every pose is moved by a fixed rigid motion, so the
  estimated frame (scan 0, sample up) differs from it by a gauge the evaluation must remove.
  """
  mesh = block_mesh()
  gauge = np.eye(4)
  gauge[:3, :3] = trimesh.transformations.rotation_matrix(0.3, (1, 2, 3))[:3, :3]
  gauge[:3, 3] = (100.0, -50.0, 30.0)
  mesh_gt = mesh.copy().apply_transform(gauge)
  wli_scans = []
  priors = [(0, 0)] + [(30, a) for a in (0, 90, 180, 270)]
  for k, (tilt, az) in enumerate(priors):
    c2w = gauge @ look(tilt, az, WLI_DISTANCE)
    scan = scene_lib.WLIScan(f"{k:04d}", np.zeros(WLI_SHAPE, np.float32), (PX, PX), c2w=c2w,
                             prior={"tilt_deg": tilt, "azimuth_deg": az})
    o, d = scene_lib.wli_rays(scan)
    scan.depth = raycast(mesh_gt, o, d)[0].astype(np.float32)
    wli_scans.append(scan)
  K = np.array([[OM_FOCAL, 0, OM_SHAPE[1] / 2], [0, OM_FOCAL, OM_SHAPE[0] / 2], [0, 0, 1]])
  om = []
  views = [(0, 0)] + [(t, a) for t in (15, 30, 45) for a in range(0, 360, 30)]
  light = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
  for k, (tilt, az) in enumerate(views):
    img = scene_lib.OMImage(f"{k:04d}", np.zeros(OM_SHAPE + (3,), np.float32), K,
                            gauge @ look(tilt, az, OM_DISTANCE))
    o, d = scene_lib.om_rays(img)
    t, p, n = raycast(mesh_gt, o, d)
    shade = 0.35 + 0.65 * np.abs(n @ (gauge[:3, :3] @ light))
    rgb = albedo(p @ gauge[:3, :3] + (-gauge[:3, 3] @ gauge[:3, :3])) * shade[..., None]
    img.image = np.where(np.isfinite(t)[..., None], rgb, 0.05).astype(np.float32)
    om.append(img)
  posed = scene_lib.Scene(wli_scans, om, name="blocks")
  gt = scene_lib.poses_to_json(posed)
  for s in wli_scans:
    s.c2w = None
  for o in om:
    o.c2w = None
  return posed, gt


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
  scene, gt = make_scene()
  d = tmp_path_factory.mktemp("blocks")
  scene_lib.save_scene(scene, d)
  (d / "truth.json").write_text(json.dumps(gt))
  return d


def scene_size(scene: scene_lib.Scene, gt: dict) -> float:
  for s in scene.wli:
    s.c2w = np.asarray(next(c for c in gt["cameras"] if c["name"] == f"wli/{s.name}")["c2w"])
  pts = scene.wli_points(stride=4)
  return float(np.linalg.norm(np.ptp(pts, axis=0)))
