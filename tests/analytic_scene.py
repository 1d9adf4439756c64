"""A tiny analytic scene for engine tests: a spherical cap on a plane, seen by WLI and OM cameras.

Independent of ofjax.synth on purpose: the engine's tests must not share a bug with the generator.
Surface (um): z = max(0, sqrt(R^2 - x^2 - y^2) - (R - CAP_HEIGHT)) over [-HALF, HALF]^2.
Albedo: a smooth two-tone pattern of (x, y). Rays are cast with open3d's RaycastingScene.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ofjax import scene as scene_lib

HALF = 60.0  # half-width of the plane, um
R = 40.0  # radius of the sphere the cap is cut from, um
CAP_HEIGHT = 20.0  # height of the cap above the plane, um


def height(x, y):
  return np.maximum(0.0, np.sqrt(np.maximum(R**2 - x**2 - y**2, 0.0)) - (R - CAP_HEIGHT))


def albedo(p):
  """[N, 3] colour of surface points p: [N, 3]."""
  s = 0.5 + 0.5 * np.sin(p[:, 0] / 6.0) * np.cos(p[:, 1] / 7.0)
  return np.stack([0.2 + 0.6 * s, 0.3 + 0.3 * (1 - s), 0.5 - 0.3 * s], -1)


def mesh(n: int = 241) -> o3d.geometry.TriangleMesh:
  xs = np.linspace(-HALF, HALF, n)
  xx, yy = np.meshgrid(xs, xs, indexing="xy")
  verts = np.stack([xx, yy, height(xx, yy)], -1).reshape(-1, 3)
  idx = np.arange(n * n).reshape(n, n)
  a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
  faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                          np.stack([a, d, c], -1).reshape(-1, 3)])
  return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                   o3d.utility.Vector3iVector(faces))


def look_at(center, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
  """c2w (OpenCV axes: z forward, y down) of a camera at `center` looking at `target`."""
  z = np.asarray(target, float) - np.asarray(center, float)
  z /= np.linalg.norm(z)
  x = np.cross(z, up)
  if np.linalg.norm(x) < 1e-6:
    x = np.cross(z, (1.0, 0.0, 0.0))
  x /= np.linalg.norm(x)
  y = np.cross(z, x)
  c2w = np.eye(4)
  c2w[:3, :3] = np.stack([x, y, z], 1)
  c2w[:3, 3] = center
  return c2w


def _cast(rc, o, d):
  rays = np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32)
  t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(o.shape[:-1])
  return t


def make(wli_px: int = 48, om_hw: tuple[int, int] = (48, 64), n_om: int = 12) -> tuple[
    scene_lib.Scene, o3d.geometry.TriangleMesh]:
  """The scene with true poses (c2w set), and its mesh (um)."""
  m = mesh()
  rc = o3d.t.geometry.RaycastingScene()
  rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
  wli = []
  pixel = 2 * HALF / wli_px
  for i, (tilt, az) in enumerate([(0, 0), (30, 0), (30, 90), (30, 180), (30, 270)]):
    th, ph = np.radians(tilt), np.radians(az)
    direction = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    c2w = look_at(direction * 200.0, np.zeros(3))
    scan = scene_lib.WLIScan(f"{i:04d}", np.zeros((wli_px, wli_px), np.float32),
                             (pixel * 0.9, pixel * 0.9), c2w, {"tilt_deg": tilt, "azimuth_deg": az})
    o, d = scene_lib.wli_rays(scan)
    t = _cast(rc, o, d)
    scan.depth = np.where(np.isfinite(t), t, np.nan).astype(np.float32)
    wli.append(scan)
  om = []
  h, w = om_hw
  f = 2.2 * w
  K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
  for i in range(n_om):
    elev = np.radians([0, 20, 40][i % 3])
    az = 2 * np.pi * i / n_om
    direction = np.array([np.sin(elev) * np.cos(az), np.sin(elev) * np.sin(az), np.cos(elev)])
    c2w = look_at(direction * 250.0, np.zeros(3))
    img = scene_lib.OMImage(f"{i:04d}", np.zeros((h, w, 3), np.float32), K, c2w)
    o, d = scene_lib.om_rays(img)
    t = _cast(rc, o, d)
    p = (o + d * np.nan_to_num(t, posinf=0.0)[..., None]).reshape(-1, 3)
    col = albedo(p).reshape(h, w, 3)
    img.image = np.where(np.isfinite(t)[..., None], col, 0.0).astype(np.float32)
    om.append(img)
  return scene_lib.Scene(wli, om, name="cap"), m
