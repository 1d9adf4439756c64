"""The blocks test scene, built independently of the code under test.

A textured block sample (trimesh primitives) ray-cast with open3d, orthographically for the 5 WLI
scans (top + 30 deg tilt at 4 azimuths) and through pinholes for the 37 OM photos (top + rings at
15/30/45 deg every 30 deg), with poses from the acquisition geometry, in a frame of its own
(GAUGE). Used by tests/test_associate.py and tests/test_associate_anchor.py.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh
from scipy import ndimage

from ofjax import scene as scene_lib
from ofjax.associate import wli

PX = 1.0  # WLI pixel size, um
WLI_SHAPE = (200, 240)
OM_SHAPE = (240, 320)  # rows, cols
OM_FOCAL = 520.0  # px: the 240 um wide sample fills most of a photo from OM_DISTANCE
OM_DISTANCE = 420.0  # um from the scene centre
WLI_DISTANCE = 300.0  # um: any value works, depth is measured from the camera plane
LUMINANCE = np.array([0.299, 0.587, 0.114])  # Rec. 601 weights of a monochrome camera


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


GAUGE = trimesh.transformations.rotation_matrix(0.3, (1, 2, 3))
GAUGE[:3, 3] = (100.0, -50.0, 30.0)  # the truth's own frame: a rigid motion away from ours
WLI_VIEWS = [(0, 0)] + [(30, a) for a in (0, 90, 180, 270)]
OM_VIEWS = [(0, 0)] + [(t, a) for t in (15, 30, 45) for a in range(0, 360, 30)]


def wli_scans(mesh_gt: trimesh.Trimesh, prior: bool = True,
              intensity: bool = False) -> list[scene_lib.WLIScan]:
  """The 5 WLI scans of `mesh_gt` (truth frame), posed with the truth; with `intensity` each also
  carries an intensity image: the albedo's luminance (Rec. 601, a monochrome camera) under light
  along the scan axis."""
  inv = np.linalg.inv(GAUGE)
  scans = []
  for k, (tilt, az) in enumerate(WLI_VIEWS):
    scan = scene_lib.WLIScan(f"{k:04d}", np.zeros(WLI_SHAPE, np.float32), (PX, PX),
                             c2w=GAUGE @ look(tilt, az, WLI_DISTANCE),
                             prior={"tilt_deg": tilt, "azimuth_deg": az} if prior else None)
    o, d = scene_lib.wli_rays(scan)
    t, p, n = raycast(mesh_gt, o, d)
    scan.depth = t.astype(np.float32)
    if intensity:
      grey = albedo(p @ inv[:3, :3].T + inv[:3, 3]) @ LUMINANCE * np.abs(np.sum(n * d, -1))
      scan.intensity = np.where(np.isfinite(t), grey, 0.0).astype(np.float32)
    scans.append(scan)
  return scans


def om_images(mesh_gt: trimesh.Trimesh, views=tuple(OM_VIEWS)) -> list[scene_lib.OMImage]:
  """The OM photos of `mesh_gt` from `views` (tilt, azimuth; also their stage priors):
  Lambertian shading of a 3-D value-noise albedo."""
  K = np.array([[OM_FOCAL, 0, OM_SHAPE[1] / 2], [0, OM_FOCAL, OM_SHAPE[0] / 2], [0, 0, 1]])
  light = GAUGE[:3, :3] @ (np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]))
  inv = np.linalg.inv(GAUGE)
  om = []
  for k, (tilt, az) in enumerate(views):
    img = scene_lib.OMImage(f"{k:04d}", np.zeros(OM_SHAPE + (3,), np.float32), K,
                            GAUGE @ look(tilt, az, OM_DISTANCE),
                            prior={"tilt_deg": tilt, "azimuth_deg": az})
    t, p, n = raycast(mesh_gt, *scene_lib.om_rays(img))
    rgb = albedo(p @ inv[:3, :3].T + inv[:3, 3]) * (0.35 + 0.65 * np.abs(n @ light))[..., None]
    img.image = np.where(np.isfinite(t)[..., None], rgb, 0.05).astype(np.float32)
    om.append(img)
  return om


def unposed(scene: scene_lib.Scene) -> tuple[scene_lib.Scene, dict]:
  """(the scene without poses, its truth as poses file contents)."""
  gt = scene_lib.poses_to_json(scene)
  for cam in scene.wli + scene.om:
    cam.c2w = None
  return scene, gt


def scene_size(scans: list[scene_lib.WLIScan]) -> float:
  """Diagonal (um) of the bounding box of the truth-posed WLI points."""
  pts = np.concatenate([scene_lib.wli_points(s, 4) for s in scans])
  return float(np.linalg.norm(np.ptp(pts, axis=0)))


MESH_GT = block_mesh().apply_transform(GAUGE)


def assert_within_targets(summary: dict) -> None:
  """Issue 5's targets on an ofjax.associate.evaluate.pose_errors summary of this scene: WLI <=
  0.05 deg and 0.5 px; OM 37/37, <= 0.2 deg, centre <= 0.5% of the size, scale <= 0.5%."""
  w, o = summary["wli"], summary["om"]
  assert w["max_rot_deg"] <= 0.05 and w["max_trans_px"] <= 0.5, w
  assert o["registered"] == 37 and o["max_rot_deg"] <= 0.2, o
  assert o["max_centre_rel"] <= 0.005 and o["scale_error"] <= 0.005, o
