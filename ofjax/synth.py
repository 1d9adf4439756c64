"""Synthetic WLI + OM scenes with ground truth: `python -m ofjax.synth --scene seed --out DIR`.

A procedural sample (ofjax.synth_scenes) or a user's mesh is placed on a substrate and imaged the
way OpticFusion's data were taken, by casting rays with open3d's RaycastingScene (CPU):
  WLI  5 orthographic scans: top, and tilted by 30 deg at azimuths 0, 90, 180, 270 deg; depth is
       exact, and each pixel is dropped (NaN) with the paper's void model: it survives with
       probability f(alpha, beta) (`valid_probability`), alpha the angle between the surface
       normal and the WLI axis, beta the material's specular share, NA = 0.13. Each scan also
       carries the instrument's intensity image: the albedo's luminance times the light the
       surface returns into the objective (`wli_reflectance`).
  OM   37 pinhole photos: top, and rings at 15, 30, 45 deg from the vertical every 30 deg of
       azimuth; narrow field of view; Lambert shading of the albedo under a light beside the
       objective plus a Blinn-Phong highlight whose strength is beta (for the residual branch).
Cameras follow ofjax.scene exactly (OpenCV axes, camera z from the instrument towards the sample,
WLI pixel centres at +0.5, OM principal point at (W/2, H/2)). World: um, z up, substrate z = 0.

Outputs (`write`): the native bundle (`ofjax.scene.save_scene`, no poses.json) or the public
OpticFusion layout (wl/*.npz, op/*.png, op/camera.xml, op/align.aln in layout units of
`um_per_unit` um), and in both cases DIR/ground_truth/ with mesh.ply (um, vertex colours =
albedo), surface_points.ply (the visible surface, true albedo and normals), poses.json (true
c2w, um), meta.json, timing.json (wall-clock seconds: the one file that differs between runs)
and overview.png. The same seed gives the same bytes in every other file.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial.transform import Rotation

from ofjax import fileio
from ofjax import scene as scn
from ofjax.errors import UserError, cli
from ofjax.meshquery import MeshQuery
from ofjax.synth_scenes import SCENES, Material, Sample, Solid

NA = 0.13  # numerical aperture of the WLI objective in the paper's experiments
WLI_TILT_DEG = 30.0
WLI_AZIMUTHS_DEG = (0.0, 90.0, 180.0, 270.0)
OM_ELEVATIONS_DEG = (15.0, 30.0, 45.0)  # rings, measured from the vertical
OM_AZIMUTH_STEP_DEG = 30.0
OM_FOV_DEG = 24.0  # horizontal field of view: a zoom microscope, far from a wide-angle lens
OM_FRAME_FILL = 1.15  # the frame's half height is this many sample half-sizes at the target
OM_LIGHT_OFFSET_DEG = 8.0  # the light sits beside the objective, this far off its axis
AMBIENT, DIFFUSE, SPECULAR = 0.45, 0.55, 0.55  # shading weights (a ring light is mostly diffuse)
WLI_FIELD_MARGIN = 1.06  # the WLI field is this much wider than the sample's widest projection
SUBSTRATE_MARGIN = 1.1  # the substrate reaches this far beyond the farthest pixel on it
GRID_GROWTH = 1.3  # outside the sample the substrate grid coarsens by this factor per cell
VISIBLE_EPS = 1e-5  # relative depth slack when testing a ground-truth point for occlusion
LAYOUT_WIDTH = 10.0  # OpticFusion's `depth_focal`: layout units across a WLI image
BACKGROUND = 0.0  # OM pixels that see nothing (cannot happen with the substrate sized as here)
LUMINANCE = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601 weights: a monochrome camera


@dataclasses.dataclass(frozen=True)
class Resolution:
  wli: int  # WLI scans are wli x wli pixels
  om: tuple[int, int]  # OM photos are (width, height), both even
  points: int  # ground-truth surface samples drawn (before the visibility test)


RESOLUTIONS = {
    "tiny": Resolution(96, (160, 120), 30_000),
    "quick": Resolution(256, (320, 240), 200_000),
    "full": Resolution(1024, (1296, 972), 250_000),
}


def valid_probability(alpha_deg, beta, na: float = NA) -> np.ndarray:
  """The paper's p = f(alpha, beta) that a WLI pixel holds a measurement (supplementary, eq. 1-2).

  Args:
    alpha_deg: [...] angle between the surface normal and the WLI axis, degrees.
    beta: [...] specular share c_s / (c_d + c_s) of the surface, in [0, 1].
  Returns:
    [...] float64 probability in [0, 1].
  """
  alpha = np.asarray(alpha_deg, np.float64)
  theta = np.degrees(np.arcsin(na))
  x = np.clip((alpha - theta) / (90.0 - theta), 0.0, 1.0)
  t = 2.0 * np.asarray(beta, np.float64) - 1.0
  # Both branches are evaluated; the exponent of the unused one is clipped so it cannot overflow.
  g_diffuse = 1.0 - np.exp(np.minimum(10.0 * (1.0 - x) * t, 0.0)) * x
  g_specular = np.exp(-10.0 * x * np.maximum(t, 0.0)) * (1.0 - x)
  return np.where(alpha < theta, 1.0, np.where(t < 0, g_diffuse, g_specular))


def wli_reflectance(alpha_deg, beta, na: float = NA) -> np.ndarray:
  """[...] light a surface returns into the WLI objective, relative to a level white diffuse one.

  The objective illuminates along its axis and collects within its aperture: the diffuse share
  (1 - beta) returns as cos(alpha) (Lambert), the specular share beta only while its mirror
  direction, 2 alpha off the axis, stays inside the aperture's half-angle asin(NA) (a Gaussian
  fall-off of that width).

  Args:
    alpha_deg: [...] angle between the surface normal and the WLI axis, degrees.
    beta: [...] specular share of the surface, in [0, 1].
  """
  alpha = np.radians(np.asarray(alpha_deg, np.float64))
  beta = np.asarray(beta, np.float64)
  return (1.0 - beta) * np.cos(alpha) + beta * np.exp(-(2.0 * alpha / np.arcsin(na)) ** 2)


def void_probability(alpha_deg, beta, na: float = NA) -> np.ndarray:
  """[...] probability that a WLI pixel is a void: 1 - `valid_probability` (the paper's 1 - f)."""
  return 1.0 - valid_probability(alpha_deg, beta, na)


# ------------------------------------------------------------------------------------ the mesh


@dataclasses.dataclass
class SynthMesh:
  """The imaged surface: a triangle mesh (um) with a material and a part id per face."""
  vertices: np.ndarray  # [V, 3] float64 um
  faces: np.ndarray  # [F, 3] int64
  face_material: np.ndarray  # [F] int, index into materials
  face_part: np.ndarray  # [F] int
  materials: list[Material]
  vertex_colors: np.ndarray  # [V, 3] albedo for materials whose albedo is None (user meshes)

  def __post_init__(self):
    tm = trimesh.Trimesh(self.vertices, self.faces, process=False)
    self.vertex_normals = np.asarray(tm.vertex_normals, np.float64)
    self.betas = np.array([m.beta for m in self.materials])

  def interpolate(self, values: np.ndarray, face_ids: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """[N, C]: per-vertex `values` [V, C] at barycentric (u, v) [N, 2] of faces `face_ids` [N]."""
    tri = self.faces[face_ids]
    u, v = uvs[:, :1], uvs[:, 1:2]
    return values[tri[:, 0]] * (1 - u - v) + values[tri[:, 1]] * u + values[tri[:, 2]] * v

  def normals(self, face_ids: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """[N, 3] unit shading normals (interpolated vertex normals)."""
    n = self.interpolate(self.vertex_normals, face_ids, uvs)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)

  def albedo(self, points: np.ndarray, face_ids: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """[N, 3] true albedo in [0, 1] at surface `points` [N, 3] um on faces `face_ids`."""
    out = np.zeros((len(points), 3), np.float32)
    mats = self.face_material[face_ids]
    for k, m in enumerate(self.materials):
      sel = mats == k
      if not sel.any():
        continue
      if m.albedo is None:
        out[sel] = self.interpolate(self.vertex_colors, face_ids[sel], uvs[sel])
      else:
        out[sel] = m.albedo(points[sel], self.face_part[face_ids[sel]])
    return out

  def vertex_albedo(self) -> np.ndarray:
    """[V, 3] albedo at every vertex (the material of the last face that uses it)."""
    vface = np.zeros(len(self.vertices), np.int64)
    vuv = np.zeros((len(self.vertices), 2))
    f = np.arange(len(self.faces))
    for corner, uv in enumerate(((0.0, 0.0), (1.0, 0.0), (0.0, 1.0))):
      vface[self.faces[:, corner]] = f
      vuv[self.faces[:, corner]] = uv
    return self.albedo(self.vertices, vface, vuv)

  def query(self) -> MeshQuery:
    """Ray casts on this mesh, unshifted: the samples are built around the world origin already
    (float32 resolves ~1e-4 um at their ~1,000 um extent), and the scenes stay as rendered
    before `MeshQuery` took over the casts."""
    return MeshQuery(self.vertices, self.faces, shift=np.zeros(3))


def graded_axis(half: float, spacing: float, outer: float) -> tuple[np.ndarray, int]:
  """Grid coordinates (um) from -outer to outer: step `spacing` inside |s| <= half, then growing.

  Returns the coordinates and the index of -half in them.
  """
  n = int(np.ceil(2 * half / spacing))
  fine = np.linspace(-half, half, n + 1)
  steps, s, step = [], half, spacing
  while s < outer:
    step *= GRID_GROWTH
    s = min(s + step, outer) if outer - (s + step) > step else outer
    steps.append(s)
  coarse = np.array(steps)
  return np.concatenate([-coarse[::-1], fine, coarse]), len(coarse)


def build_mesh(sample: Sample, substrate_half: float) -> SynthMesh:
  """Meshes `sample` on a square substrate of half-size `substrate_half` um."""
  axis, lo = graded_axis(sample.half_size, sample.spacing, substrate_half)
  n = len(axis)
  x, y = np.meshgrid(axis, axis, indexing="ij")
  z = np.zeros_like(x)
  vmat = np.full(x.shape, sample.substrate, np.int64)
  vpart = np.zeros(x.shape, np.int64)
  if sample.heightfield is not None:
    inner = (slice(lo, n - lo), slice(lo, n - lo))
    zi, mi, pi = sample.heightfield(x[inner].ravel(), y[inner].ravel())
    zi = zi.reshape(x[inner].shape)
    border = np.concatenate([zi[0], zi[-1], zi[:, 0], zi[:, -1]])
    if np.abs(border).max() > 1e-9:
      raise ValueError(f"scene {sample.name!r}: its heightfield is not zero on its border")
    z[inner], vmat[inner], vpart[inner] = zi, mi.reshape(zi.shape), pi.reshape(zi.shape)
  idx = np.arange(n * n).reshape(n, n)
  a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
  faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                          np.stack([a, c, d], -1).reshape(-1, 3)])
  verts = np.stack([x, y, z], -1).reshape(-1, 3)
  # a face takes the material of its highest corner, so walls belong to the part they bound
  top = np.argmax(verts[faces, 2], axis=1)
  corner = faces[np.arange(len(faces)), top]
  fmat, fpart = vmat.ravel()[corner], vpart.ravel()[corner]
  colors = np.zeros_like(verts)
  for s in sample.solids:
    faces = np.concatenate([faces, s.faces + len(verts)])
    fmat = np.concatenate([fmat, np.full(len(s.faces), s.material)])
    fpart = np.concatenate([fpart, np.zeros(len(s.faces), np.int64)])
    colors = np.concatenate([colors, np.zeros_like(s.vertices) if s.colors is None else s.colors])
    verts = np.concatenate([verts, s.vertices])
  return SynthMesh(verts, faces.astype(np.int64), fmat, fpart, sample.materials, colors)


# ----------------------------------------------------------------------------------- the rig


def view_rotation(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
  """[3, 3] c2w rotation of a camera looking down, tilted towards `azimuth_deg` (from +x).

  The top view has x_cam = +x, y_cam = -y, z_cam = -z; a tilted view is that frame rotated by
  the tilt about the horizontal axis perpendicular to the azimuth (like tilting the stage).
  """
  az = np.radians(azimuth_deg)
  axis = np.array([-np.sin(az), np.cos(az), 0.0])
  return Rotation.from_rotvec(axis * np.radians(tilt_deg)).as_matrix() @ np.diag([1.0, -1.0, -1.0])


def pose(rot: np.ndarray, target: np.ndarray, distance: float) -> np.ndarray:
  """[4, 4] c2w of a camera with rotation `rot` whose axis meets `target` at `distance` um."""
  c2w = np.eye(4)
  c2w[:3, :3] = rot
  c2w[:3, 3] = target - distance * rot[:, 2]
  return c2w


def make_rig(sample: Sample, res: Resolution) -> tuple[list[scn.WLIScan], list[scn.OMImage], float]:
  """Posed WLI scans and OM photos (placeholder data) around `sample`, and the substrate half-size
  (um) that fills every camera's view."""
  half, height = sample.half_size, sample.height
  target = np.array([0.0, 0.0, height / 3])
  corners = np.array([[sx * half, sy * half, z] for sx in (-1, 1) for sy in (-1, 1)
                      for z in (0.0, height)]) - target
  wli_views = [(0.0, 0.0)] + [(WLI_TILT_DEG, az) for az in WLI_AZIMUTHS_DEG]
  rots = [view_rotation(t, az) for t, az in wli_views]
  field = 2 * WLI_FIELD_MARGIN * max(np.abs(corners @ r[:, :2]).max() for r in rots)
  px = field / res.wli
  standoff = 3.0 * (half + height)  # the orthographic image plane lies well above the sample
  wli = []
  for k, ((tilt, az), rot) in enumerate(zip(wli_views, rots)):
    wli.append(scn.WLIScan(f"{k:04d}", np.zeros((res.wli, res.wli), np.float32), (px, px),
                           c2w=pose(rot, target, standoff),
                           prior={"tilt_deg": tilt, "azimuth_deg": az}))
  w, h = res.om
  f = (w / 2) / np.tan(np.radians(OM_FOV_DEG) / 2)
  K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
  distance = f * OM_FRAME_FILL * half / (h / 2)
  om_views = [(0.0, 0.0)] + [(e, a) for e in OM_ELEVATIONS_DEG
                             for a in np.arange(0.0, 360.0, OM_AZIMUTH_STEP_DEG)]
  om = [scn.OMImage(f"{k:04d}", np.zeros((h, w, 3), np.float32), K.copy(),
                    c2w=pose(view_rotation(e, a), target, distance),
                    prior={"tilt_deg": e, "azimuth_deg": float(a)})
        for k, (e, a) in enumerate(om_views)]
  # The substrate must reach beyond every pixel's ray hit on the plane z = 0.
  reach = 0.0
  for cam in wli + om:
    if isinstance(cam, scn.WLIScan):
      o, d = scn.wli_rays(cam, stride=cam.shape[0] - 1)
    else:
      o, d = scn.om_rays(cam, stride=2)
    t = -o[..., 2] / d[..., 2]
    reach = max(reach, np.abs((o + t[..., None] * d)[..., :2]).max())
  return wli, om, SUBSTRATE_MARGIN * reach + px


# --------------------------------------------------------------------------------- rendering


def cast(query: MeshQuery, o: np.ndarray, d: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """First hits of rays (origins, unit directions [..., 3], um).

  Returns t [...] um, face ids [...] (any face where the ray misses), uvs [..., 2] (the weights of
  the face's second and third vertices, as `SynthMesh.interpolate`) and hit [...] bool.
  """
  shape = d.shape[:-1]
  t, ids, bary = query.cast(np.broadcast_to(o, d.shape).reshape(-1, 3), d.reshape(-1, 3))
  return t.reshape(shape), ids.reshape(shape), bary[:, 1:].reshape(shape + (2,)), np.isfinite(
      t).reshape(shape)


def _wli_hits(mesh: SynthMesh, query: MeshQuery, scan: scn.WLIScan):
  """What each pixel of `scan` sees: its rays' hits (`cast`'s t, face ids, uvs, hit [H, W]),
  the angle alpha [H, W] (degrees) between the surface normal and the WLI axis, and the ray
  origins and directions [H, W, 3]."""
  o, d = scn.wli_rays(scan)
  t, ids, uvs, ok = cast(query, o, d)
  n = mesh.normals(ids.ravel(), uvs.reshape(-1, 2)).reshape(d.shape)
  # |cos|: the instrument sees a surface from either side (user meshes may have flipped faces)
  alpha = np.degrees(np.arccos(np.clip(np.abs((n * d).sum(-1)), 0.0, 1.0)))
  return t, ids, uvs, ok, alpha, o, d


def render_wli(mesh: SynthMesh, query: MeshQuery, scan: scn.WLIScan, rng: np.random.Generator,
               na: float = NA) -> np.ndarray:
  """[H, W] float32 depth (um) of `scan` with voids drawn from the paper's model."""
  t, ids, _, ok, alpha, _, _ = _wli_hits(mesh, query, scan)
  p = valid_probability(alpha, mesh.betas[mesh.face_material[ids]], na)
  keep = ok & (rng.random(t.shape) < p)
  return np.where(keep, t, np.nan).astype(np.float32)


def render_wli_intensity(mesh: SynthMesh, query: MeshQuery, scan: scn.WLIScan,
                         na: float = NA) -> np.ndarray:
  """[H, W] float32 intensity image of `scan` in [0, 1]: the albedo's luminance (Rec. 601) times
  `wli_reflectance`; recorded at every pixel, voids included (the camera sees them, dimly)."""
  t, ids, uvs, ok, alpha, o, d = _wli_hits(mesh, query, scan)
  p = (o + np.where(ok, t, 0.0)[..., None] * d).reshape(-1, 3)
  luminance = mesh.albedo(p, ids.ravel(), uvs.reshape(-1, 2)) @ LUMINANCE
  out = luminance.reshape(t.shape) * wli_reflectance(alpha, mesh.betas[mesh.face_material[ids]],
                                                     na)
  return np.where(ok, np.clip(out, 0.0, 1.0), BACKGROUND).astype(np.float32)


def render_om(mesh: SynthMesh, query: MeshQuery, photo: scn.OMImage) -> np.ndarray:
  """[H, W, 3] float32 RGB in [0, 1]: albedo under a light beside the objective + highlights."""
  o, d = scn.om_rays(photo)
  t, ids, uvs, ok = cast(query, o, d)
  o, d, t, ids, uvs = o[ok], d[ok], t[ok], ids[ok], uvs[ok]
  p = o + t[:, None] * d
  n = mesh.normals(ids, uvs)
  n = np.where(((n * d).sum(-1) > 0)[:, None], -n, n)  # seen from behind: shade the side seen
  # the light sits above the objective (image up = -y_cam), OM_LIGHT_OFFSET_DEG off its axis as
  # seen from the sample near the world origin
  rot, centre = photo.c2w[:3, :3], photo.c2w[:3, 3]
  light = centre - rot[:, 1] * np.linalg.norm(centre) * np.tan(np.radians(OM_LIGHT_OFFSET_DEG))
  l = light - p
  l /= np.linalg.norm(l, axis=-1, keepdims=True)
  hvec = l - d
  hvec /= np.linalg.norm(hvec, axis=-1, keepdims=True)
  beta = mesh.betas[mesh.face_material[ids]]
  shininess = 10.0 + 120.0 * beta  # polished surfaces have tight highlights
  spec = beta * SPECULAR * np.clip((n * hvec).sum(-1), 0, 1)**shininess
  diffuse = AMBIENT + DIFFUSE * np.clip((n * l).sum(-1), 0, 1)
  rgb = mesh.albedo(p, ids, uvs) * diffuse[:, None] + spec[:, None]
  img = np.full(photo.image.shape, BACKGROUND, np.float32)
  img[ok] = np.clip(rgb, 0.0, 1.0)
  return img


def visible_points(query: MeshQuery, points: np.ndarray, photos: list[scn.OMImage]) -> np.ndarray:
  """[N] bool: the point (um, on the surface) is inside some photo and not occluded there."""
  seen = np.zeros(len(points), bool)
  for photo in photos:
    todo = np.flatnonzero(~seen)
    if len(todo) == 0:
      break
    todo = todo[scn.project_pinhole(points[todo], photo.K, photo.c2w, photo.shape)[2]]
    seen[todo[query.clear(photo.c2w[:3, 3], points[todo], rel_slack=VISIBLE_EPS)]] = True
  return seen


@dataclasses.dataclass
class GroundTruth:
  """What the synthetic scene really is (um)."""
  mesh: trimesh.Trimesh  # the imaged surface, vertex colours = albedo
  points: np.ndarray  # [N, 3] float64 samples of the visible surface near the sample
  albedo: np.ndarray  # [N, 3] float32 true albedo at `points`, in [0, 1]
  normals: np.ndarray  # [N, 3] float64 unit surface normals at `points`
  poses: dict[str, Any]  # true c2w of every camera, as `ofjax.scene.poses_to_json`
  meta: dict[str, Any]  # scene name, seed, sizes, materials, void fractions, um_per_unit
  timing: dict[str, float]  # wall-clock seconds per stage
  synth_mesh: SynthMesh  # materials and per-face data, for tests and further renders


def om_size_checked(om_size) -> tuple[int, int]:
  """(width, height) of the OM photos, both positive and even (the principal point is the
  centre), or a UserError naming --om-size."""
  w, h = om_size
  if min(w, h) < 2 or w % 2 or h % 2:
    raise UserError(f"--om-size {w},{h}: width and height must be even and at least 2 pixels")
  return int(w), int(h)


def simulate(sample: Sample, seed: int = 0, resolution: str = "quick",
             source: dict[str, Any] | None = None,
             om_size: tuple[int, int] | None = None) -> tuple[scn.Scene, GroundTruth]:
  """Images `sample` with the WLI and the OM; see `make_scene`."""
  if resolution not in RESOLUTIONS:
    raise UserError(f"--resolution {resolution!r}: unknown; choose one of {sorted(RESOLUTIONS)}")
  res = RESOLUTIONS[resolution]
  if om_size is not None:
    # Same field of view and distance: only the photos' sampling of the sample changes.
    res = dataclasses.replace(res, om=om_size_checked(om_size))
    source = {**(source or {}), "om_size": list(res.om)}
  clock, timing = time.perf_counter(), {}

  def lap(name):
    nonlocal clock
    now = time.perf_counter()
    timing[name] = round(now - clock, 3)
    clock = now

  wli, om, substrate_half = make_rig(sample, res)
  mesh = build_mesh(sample, substrate_half)
  query = mesh.query()
  lap("mesh")
  for k, scan in enumerate(wli):
    scan.depth = render_wli(mesh, query, scan, np.random.default_rng([seed, 100, k]))
    scan.intensity = render_wli_intensity(mesh, query, scan)
  lap("wli")
  for photo in om:
    photo.image = render_om(mesh, query, photo)
  lap("om")
  # Ground-truth points: the surface over the WLI field, where some photo sees it.
  region = wli[0].pixel_size[0] * wli[0].shape[1] / 2
  tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
  centre = tm.triangles_center
  weight = tm.area_faces * (np.abs(centre[:, :2]).max(1) <= region)
  pts, fids = trimesh.sample.sample_surface(tm, res.points, face_weight=weight, seed=seed)
  bary = trimesh.triangles.points_to_barycentric(tm.triangles[fids], pts)
  uvs = bary[:, 1:]
  keep = visible_points(query, pts, om)
  pts, fids, uvs = pts[keep], fids[keep], uvs[keep]
  albedo = mesh.albedo(pts, fids, uvs)
  normals = mesh.normals(fids, uvs)
  tm.visual.vertex_colors = np.round(mesh.vertex_albedo() * 255).astype(np.uint8)
  lap("ground_truth")
  posed = scn.Scene(wli, om, name=sample.name, units="um")
  poses = scn.poses_to_json(posed)
  for cam in wli + om:
    cam.c2w = None  # the scene on disk carries no poses: association recovers them
  px = wli[0].pixel_size[0]
  lo = pts.min(0) if len(pts) else np.zeros(3)
  hi = pts.max(0) if len(pts) else np.zeros(3)
  meta = {
      "format": "ofjax-synth", "version": 1, "units": "um", "scene": sample.name, "seed": seed,
      "resolution": resolution, "sample_half_size_um": sample.half_size,
      "sample_height_um": sample.height, "bbox_um": [lo.tolist(), hi.tolist()],
      "size_um": float(np.max(hi - lo)), "substrate_half_size_um": float(substrate_half),
      "wli_pixel_size_um": px, "na": NA,
      "um_per_unit": px * res.wli / LAYOUT_WIDTH,
      "om_focal_px": float(om[0].K[0, 0]), "om_size_px": list(res.om),
      "materials": [{"name": m.name, "beta": m.beta} for m in mesh.materials],
      "void_fraction": {s.name: float(np.mean(~s.valid)) for s in wli},
      "triangles": int(len(mesh.faces)), "surface_points": int(len(pts)),
  }
  scene = scn.Scene(wli, om, name=sample.name, units="um",
                    source={"generator": "ofjax.synth", **(source or {}), "seed": seed,
                            "resolution": resolution})
  gt = GroundTruth(tm, pts, albedo, normals, poses, meta, timing, mesh)
  return scene, gt


def make_scene(name: str = "seed", seed: int = 0, resolution: str = "quick",
               om_size: tuple[int, int] | None = None) -> tuple[scn.Scene, GroundTruth]:
  """A procedural scene (see `SCENES`) imaged as in the paper.

  The returned Scene mirrors what `write` puts on disk: WLI depths with pixel sizes and
  acquisition priors, OM photos with intrinsics K, and no poses (c2w None): the true poses are
  `gt.poses`; `ofjax.scene.apply_poses(scene, gt.poses)` sets them. `om_size` (width, height)
  replaces the resolution's photo size; the WLI scans and the truth do not change with it.
  """
  if name not in SCENES:
    raise UserError(f"--scene {name!r}: unknown; choose one of {', '.join(SCENES)} "
                    "(`python -m ofjax.synth --list`)")
  return simulate(SCENES[name](seed), seed, resolution, {"scene": name}, om_size)


def make_scene_from_mesh(path: str | Path, seed: int = 0, resolution: str = "quick",
                         beta: float = 0.2, om_size: tuple[int, int] | None = None
                         ) -> tuple[scn.Scene, GroundTruth]:
  """A user's mesh (um; vertex colours = albedo, grey without) on a diffuse textured substrate.

  The mesh is moved so that its footprint is centred at the origin and its lowest point touches
  the substrate; `beta` is its specular share.
  """
  from ofjax.synth_scenes import Noise, textured
  path = Path(path)
  if not path.is_file():
    raise UserError(f"{path}: mesh file not found; pass a .ply/.obj/.stl/.glb file with --mesh")
  if not 0.0 <= beta <= 1.0:
    raise UserError(f"--beta {beta}: must lie in [0, 1] (0 diffuse, 1 mirror)")
  try:
    tm = trimesh.load(path, force="mesh", process=False)
  except Exception as e:  # noqa: BLE001 - trimesh raises many kinds on bad files
    raise UserError(f"{path}: cannot read the mesh ({type(e).__name__}: {e}); export it as PLY "
                    "or OBJ") from None
  if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
    raise UserError(f"{path}: holds no triangles; export the surface as a triangle mesh")
  v = np.asarray(tm.vertices, np.float64)
  if not np.all(np.isfinite(v)) or np.ptp(v, axis=0).max() <= 0:
    raise UserError(f"{path}: vertices are not finite or the mesh has no extent; fix the mesh")
  lo, hi = v.min(0), v.max(0)
  v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
  colors = np.full((len(v), 3), 0.6)
  vc = getattr(tm.visual, "vertex_colors", None)
  if tm.visual.kind == "vertex" and vc is not None and len(vc) == len(v):
    colors = np.asarray(vc, np.float64)[:, :3] / 255.0
  half = float(np.abs(v[:, :2]).max())
  noise = Noise(seed)
  mats = [Material(path.stem, beta, None),
          Material("substrate", 0.2, textured(noise, (0.45, 0.45, 0.42), half / 15, 0.7, 10,
                                              speckle=0.4))]
  sample = Sample(path.stem, mats, substrate=1, half_size=half, height=float(v[:, 2].max()),
                  spacing=half / 24, solids=[Solid(v, np.asarray(tm.faces), 0, colors)])
  return simulate(sample, seed, resolution, {"mesh": str(path)}, om_size)


# ----------------------------------------------------------------------------------- writers


def write_ground_truth(scene: scn.Scene, gt: GroundTruth, directory: Path) -> None:
  """DIR/ground_truth/: mesh.ply, surface_points.ply, poses.json, meta.json, timing.json and
  overview.png (see the module docstring)."""
  directory.mkdir(parents=True, exist_ok=True)
  with fileio.atomic_path(directory / "mesh.ply") as tmp:
    gt.mesh.export(tmp, file_type="ply")
  pc = o3d.t.geometry.PointCloud()
  pc.point.positions = o3d.core.Tensor(gt.points.astype(np.float32))
  pc.point.normals = o3d.core.Tensor(gt.normals.astype(np.float32))
  pc.point.colors = o3d.core.Tensor(np.round(gt.albedo * 255).astype(np.uint8))
  with fileio.atomic_path(directory / "surface_points.ply") as tmp:
    o3d.t.io.write_point_cloud(str(tmp), pc)
  fileio.write_json(directory / "poses.json", gt.poses)
  fileio.write_json(directory / "meta.json", gt.meta)
  fileio.write_json(directory / "timing.json", {"seconds": gt.timing})
  write_overview(scene, gt, directory / "overview.png")


def write_overview(scene: scn.Scene, gt: GroundTruth, path: Path) -> None:
  """A contact sheet: the 5 WLI depth maps (voids grey) above 5 of the OM photos."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  picks = [0, 1, 4, 16, 28]  # top, and one photo of each ring
  fig, axes = plt.subplots(2, 5, figsize=(15, 6.4))
  for ax, s in zip(axes[0], scene.wli):
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.6")
    im = ax.imshow(s.depth, cmap=cmap)
    ax.set_title(f"WLI {s.name}: tilt {s.prior['tilt_deg']:.0f}, az {s.prior['azimuth_deg']:.0f}"
                 f"\nvoids {gt.meta['void_fraction'][s.name]:.0%}", fontsize=9)
    fig.colorbar(im, ax=ax, fraction=0.046, label="depth (um)")
  for ax, k in zip(axes[1], picks):
    ax.imshow(scene.om[k].image)
    ax.set_title(f"OM {scene.om[k].name}", fontsize=9)
  for ax in axes.ravel():
    ax.set_xticks([])
    ax.set_yticks([])
  fig.suptitle(f"ofjax.synth scene {gt.meta['scene']!r}, seed {gt.meta['seed']}, "
               f"WLI pixel {gt.meta['wli_pixel_size_um']:.3f} um")
  fig.tight_layout()
  with fileio.atomic_path(path) as tmp:
    fig.savefig(tmp, dpi=80, metadata={"Software": None})
  plt.close(fig)


# The OpticFusion layout stores OM poses through a Metashape chunk similarity M and a MeshLab
# alignment A (c2w = A @ M @ T_camera). Real exports have arbitrary ones; these fixed, non-trivial
# values make a reader that drops or transposes either of them fail.
CHUNK_ROTATION = Rotation.from_euler("zyx", [37.0, -21.0, 64.0], degrees=True).as_matrix()
CHUNK_TRANSLATION = np.array([2.15, -0.73, 1.42])
CHUNK_SCALE = 0.418
ALIGN_ROTATION = Rotation.from_rotvec(np.radians(17.0) * np.array([1.0, 2.0, 0.5]) /
                                      np.sqrt(5.25)).as_matrix()
ALIGN_TRANSLATION = np.array([0.81, -1.27, 0.46])


def similarity(rot: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
  """[4, 4] the map x -> s rot x + t."""
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = s * rot, t
  return m


def layout_transforms() -> tuple[np.ndarray, np.ndarray]:
  """The chunk-to-world similarity M and the alignment A of the written OpticFusion layout."""
  return (similarity(CHUNK_ROTATION, CHUNK_TRANSLATION, CHUNK_SCALE),
          similarity(ALIGN_ROTATION, ALIGN_TRANSLATION))


def fmt(values) -> str:
  return " ".join(repr(float(v)) for v in np.ravel(values))


def write_opticfusion(scene: scn.Scene, gt: GroundTruth, directory: Path) -> float:
  """The public OpticFusion WLI-OM layout (DESIGN.md); returns its um per layout unit."""
  poses = {c["name"]: np.asarray(c["c2w"]) for c in gt.poses["cameras"]}
  first = scene.wli[0]
  unit = first.pixel_size[0] * first.shape[1] / LAYOUT_WIDTH
  for s in scene.wli:
    h, w = s.shape
    sx, sy = s.pixel_size
    if h * sy != w * sx:
      raise ValueError("the OpticFusion layout needs WLI images as tall as wide, in um")
    c2w = poses[scn.camera_key("wli", s.name)].copy()
    # layout pixel (r, c) sits at (c/W - 0.5) K: half a pixel off ofjax's centres; fold it in
    c2w[:3, 3] = (c2w[:3, 3] + c2w[:3, :3] @ np.array([0.5 * sx, 0.5 * sy, 0.0])) / unit
    fileio.write_npz(directory / "wl" / f"{s.name}.npz", depth_map=s.depth / np.float32(unit),
                     extrinsic_mat=np.linalg.inv(c2w)[:3])
  chunk, align = layout_transforms()
  am = align @ chunk
  scale = np.cbrt(np.linalg.det(am[:3, :3]))
  q = am[:3, :3] / scale
  root = ET.Element("document", version="1.4.0")
  ch = ET.SubElement(root, "chunk", label="Chunk 1", enabled="true")
  sensors = ET.SubElement(ch, "sensors", next_id="1")
  h, w = scene.om[0].shape
  sensor = ET.SubElement(sensors, "sensor", id="0", label="microscope", type="frame")
  ET.SubElement(sensor, "resolution", width=str(w), height=str(h))
  calib = ET.SubElement(sensor, "calibration", type="frame", **{"class": "adjusted"})
  ET.SubElement(calib, "resolution", width=str(w), height=str(h))
  ET.SubElement(calib, "f").text = repr(float(scene.om[0].K[0, 0]))
  ET.SubElement(calib, "cx").text = "0"
  ET.SubElement(calib, "cy").text = "0"
  comps = ET.SubElement(ch, "components", next_id="1", active_id="0")
  comp = ET.SubElement(comps, "component", id="0", label="Component 1")
  tr = ET.SubElement(comp, "transform")
  ET.SubElement(tr, "rotation", locked="false").text = fmt(CHUNK_ROTATION)
  ET.SubElement(tr, "translation", locked="false").text = fmt(CHUNK_TRANSLATION)
  ET.SubElement(tr, "scale", locked="false").text = fmt([CHUNK_SCALE])
  cams = ET.SubElement(ch, "cameras", next_id=str(len(scene.om)), next_group_id="0")
  for k, o in enumerate(scene.om):
    if not np.allclose(o.K, scene.om[0].K) or o.shape != (h, w):
      raise ValueError("the OpticFusion layout holds one OM sensor: all photos share K and size")
    c2w = poses[scn.camera_key("om", o.name)].copy()
    c2w[:3, 3] /= unit
    t_cam = np.eye(4)  # rigid camera-to-chunk: A M T_cam = [scale q R | t] = scaled true pose
    t_cam[:3, :3] = q.T @ c2w[:3, :3]
    t_cam[:3, 3] = q.T @ (c2w[:3, 3] - am[:3, 3]) / scale
    cam = ET.SubElement(cams, "camera", id=str(k), sensor_id="0", component_id="0", label=o.name)
    ET.SubElement(cam, "transform").text = fmt(t_cam)
    scn.save_png(directory / "op" / f"{o.name}.png", o.image)
  ET.SubElement(ch, "reference").text = ('LOCAL_CS["Local Coordinates (m)",LOCAL_DATUM["Local '
                                         'Datum",0],UNIT["metre",1]]')
  ET.indent(root)
  xml = '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
  fileio.write_text(directory / "op" / "camera.xml", xml)
  rows = "\n".join(fmt(row) for row in align)
  fileio.write_text(directory / "op" / "align.aln", f"1\nsparse_point_cloud.ply\n#\n{rows}\n0\n")
  return unit


LAYOUTS = ("native", "opticfusion")


def write(scene: scn.Scene, gt: GroundTruth, out: str | Path, layout: str = "native") -> Path:
  """Writes `scene` in `layout` ("native" or "opticfusion") and its ground truth under `out`."""
  if layout not in LAYOUTS:
    raise UserError(f"--layout {layout!r}: unknown; choose one of {', '.join(LAYOUTS)}")
  out = Path(out)
  if out.exists() and not out.is_dir():
    raise UserError(f"{out}: exists and is not a directory; choose another --out")
  if layout == "native":
    scn.save_scene(scene, out)
  else:
    write_opticfusion(scene, gt, out)
  write_ground_truth(scene, gt, out / "ground_truth")
  return out


# ------------------------------------------------------------------------------------------ CLI


def parse_om_size(text: str) -> tuple[int, int]:
  try:
    w, h = (int(v) for v in text.split(","))
  except ValueError:
    raise argparse.ArgumentTypeError(f"{text!r}: expected W,H in pixels, e.g. 640,480") from None
  return w, h


def parse_args(argv):
  p = argparse.ArgumentParser(
      prog="python -m ofjax.synth", description="Render a synthetic WLI + OM scene (um) with "
      "ground truth: 5 WLI scans with voids, 37 OM photos, the true mesh, points and poses.")
  p.add_argument("--scene", default="seed", help="procedural scene (default: seed; see --list)")
  p.add_argument("--mesh", type=Path, help="simulate this mesh instead (um; vertex colours = "
                 "albedo)")
  p.add_argument("--beta", type=float, default=0.2,
                 help="specular share of the --mesh surface, 0 diffuse .. 1 mirror (default 0.2)")
  p.add_argument("--out", type=Path, help="output directory")
  p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
  p.add_argument("--resolution", default="quick", choices=sorted(RESOLUTIONS),
                 help="tiny (tests), quick (CPU work, default) or full (the paper's sizes)")
  p.add_argument("--om-size", metavar="W,H", type=parse_om_size,
                 help="OM photo size in pixels (both even), in place of the resolution's; the "
                 "field of view stays, so the photos sample the sample more or less finely")
  p.add_argument("--layout", default="native", choices=LAYOUTS,
                 help="native ofjax bundle (default) or the public OpticFusion layout")
  p.add_argument("--list", action="store_true", help="list the procedural scenes and exit")
  return p.parse_args(argv)


@cli
def main(argv=None) -> int:
  args = parse_args(argv)
  if args.list:
    for name, builder in SCENES.items():
      print(f"{name:8s} {builder.__doc__.splitlines()[0]}")
    return 0
  if args.out is None:
    raise UserError("--out: missing; pass the directory to write the scene to")
  if args.mesh is not None:
    scene, gt = make_scene_from_mesh(args.mesh, args.seed, args.resolution, args.beta,
                                     args.om_size)
  else:
    scene, gt = make_scene(args.scene, args.seed, args.resolution, args.om_size)
  t0 = time.perf_counter()
  write(scene, gt, args.out, args.layout)
  gt.timing["write"] = round(time.perf_counter() - t0, 3)
  fileio.write_json(args.out / "ground_truth" / "timing.json", {"seconds": gt.timing})
  voids = np.mean(list(gt.meta["void_fraction"].values()))
  size = f", photos {args.om_size[0]}x{args.om_size[1]}" if args.om_size else ""
  print(f"ofjax.synth: wrote {gt.meta['scene']!r} ({args.layout} layout, {args.resolution}{size})"
        f" to {args.out}: {len(scene.wli)} WLI scans (mean void fraction {voids:.1%}), "
        f"{len(scene.om)} OM photos, {len(gt.points)} ground-truth points; "
        f"{sum(gt.timing.values()):.1f} s")
  return 0


if __name__ == "__main__":
  sys.exit(main())
