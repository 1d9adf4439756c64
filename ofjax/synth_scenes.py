"""Procedural microstructures for `ofjax.synth`: geometry, materials and seeded albedo textures.

Conventions (all lengths in um):
  world     z up; the substrate is the plane z = 0; each sample sits near the origin, inside
            |x|, |y| <= `Sample.half_size` and 0 <= z <= `Sample.height`.
  heightfield  a 2.5-D part z = h(x, y) over the square |x|, |y| <= half_size, zero on its border,
            meshed on a grid of step `Sample.spacing`; steep walls are ramps a few um wide.
  solid     a closed triangle mesh (e.g. the seed) that may dip into the substrate.
  material  an albedo texture (a function of the 3-D surface point and of an integer part id,
            so textures have unlimited resolution and need no UV map) and a specular share
            beta = c_s / (c_d + c_s) in [0, 1] (OpticFusion supplementary; 0 diffuse, 1 mirror).
  part      an integer per face that varies the colour of repeated elements (wing scales).
Every random choice comes from `numpy.random.default_rng(seed)`, so a seed fixes the scene.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import trimesh
from scipy import ndimage

NOISE_LATTICE = 64  # cells per side of the periodic random lattice behind every texture
NOISE_CHANNELS = 64  # independent random offsets, so textures do not repeat each other


class Noise:
  """Seeded 3-D value noise: a periodic random lattice sampled trilinearly (scipy.ndimage)."""

  def __init__(self, seed: int):
    rng = np.random.default_rng([seed, 7])
    self.lattice = rng.random((NOISE_LATTICE,) * 3).astype(np.float32)
    self.offsets = rng.random((NOISE_CHANNELS, 3)) * NOISE_LATTICE

  def __call__(self, p: np.ndarray, period: float, octaves: int = 3, channel: int = 0,
               gain: float = 0.5) -> np.ndarray:
    """Fractal value noise in [0, 1].

    Args:
      p: [N, 3] points, um.
      period: lattice step of the coarsest octave, um.
    Returns:
      [N] float32.
    """
    total, norm = np.zeros(len(p), np.float32), 0.0
    for o in range(octaves):
      off = self.offsets[(channel * 8 + o) % NOISE_CHANNELS]
      coords = (np.asarray(p, np.float64) * (2.0**o / period) + off).T
      total += gain**o * ndimage.map_coordinates(self.lattice, coords, order=1, mode="grid-wrap")
      norm += gain**o
    # Trilinear value noise concentrates near 0.5; stretch it back to roughly [0, 1].
    return np.clip((total / norm - 0.5) * 2.2 + 0.5, 0.0, 1.0)


Albedo = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (points [N, 3] um, part [N]) -> [N, 3]


@dataclasses.dataclass(frozen=True)
class Material:
  name: str
  beta: float  # specular share c_s / (c_d + c_s)
  albedo: Albedo | None  # None: the solid's own vertex colours (a user's mesh)


def textured(noise: Noise, base, period: float, contrast: float, channel: int,
             speckle: float = 0.0, tint: float = 0.08) -> Albedo:
  """An albedo `base` modulated by fractal noise (brightness `contrast`, colour `tint`) and dark
  speckles (`speckle` = their darkness), all with feature sizes of about `period` um."""
  base = np.asarray(base, np.float32)

  def albedo(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    del part
    light = noise(p, period, 4, channel)
    hue = np.stack([noise(p, 2.5 * period, 2, channel + 1 + k) for k in range(3)], -1)
    rgb = base * (1.0 - contrast / 2 + contrast * light[:, None]) * (1 + tint * (hue - 0.5) * 2)
    if speckle:
      spots = noise(p, period / 2, 1, channel + 5)
      rgb *= 1.0 - speckle * np.clip((spots - 0.72) / 0.1, 0.0, 1.0)[:, None]
    return np.clip(rgb, 0.0, 1.0)

  return albedo


def by_part(noise: Noise, palette, period: float, contrast: float, channel: int,
            seed: int) -> Albedo:
  """Part k takes colour palette[k % len(palette)], its brightness jittered by a seeded hash of
  k, and fractal noise on top."""
  palette = np.asarray(palette, np.float32)
  jitter = np.random.default_rng([seed, 11]).uniform(0.8, 1.2, 4096).astype(np.float32)

  def albedo(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    part = np.asarray(part)
    base = palette[part % len(palette)] * jitter[part % len(jitter)][:, None]
    light = noise(p, period, 3, channel)
    return np.clip(base * (1.0 - contrast / 2 + contrast * light[:, None]), 0.0, 1.0)

  return albedo


@dataclasses.dataclass
class Solid:
  """A closed mesh part of a sample."""
  vertices: np.ndarray  # [V, 3] um
  faces: np.ndarray  # [F, 3] int
  material: int  # index into Sample.materials
  colors: np.ndarray | None = None  # [V, 3] albedo in [0, 1] for a material without one


HeightField = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
# (x [N] um, y [N] um) -> (z [N] um >= 0, material index [N], part id [N])


@dataclasses.dataclass
class Sample:
  """A procedural sample: what a scene builder returns; `ofjax.synth` meshes and sizes it."""
  name: str
  materials: list[Material]
  substrate: int  # material of the flat substrate around the sample
  half_size: float  # um: the sample lies within |x|, |y| <= half_size
  height: float  # um: its highest point
  spacing: float  # um: grid step of the heightfield region
  heightfield: HeightField | None = None  # None: a flat substrate
  solids: list[Solid] = dataclasses.field(default_factory=list)


def ramp(signed: np.ndarray, width: float) -> np.ndarray:
  """0 -> 1 as `signed` (um, positive inside a shape) crosses 0 over `width` um: a steep wall."""
  return np.clip(signed / width + 0.5, 0.0, 1.0)


def segment_distance(x: np.ndarray, y: np.ndarray, a, b) -> np.ndarray:
  """[N] distance (um) from points (x, y) to the segment a-b (2-vectors, um)."""
  a, b = np.asarray(a, float), np.asarray(b, float)
  d = b - a
  t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / max(d @ d, 1e-12), 0.0, 1.0)
  return np.hypot(x - a[0] - t * d[0], y - a[1] - t * d[1])


def box_signed(x: np.ndarray, y: np.ndarray, cx: float, cy: float, hx: float, hy: float):
  """[N] um: positive inside the axis-aligned rectangle, the distance to its nearest edge."""
  return np.minimum(hx - np.abs(x - cx), hy - np.abs(y - cy))


# ------------------------------------------------------------------------------------- scenes


def seed_scene(seed: int) -> Sample:
  """A rough, ridged, diffuse flower seed (~260 um long) lying on a polished specular substrate."""
  rng = np.random.default_rng([seed, 1])
  noise = Noise(seed)
  coat = Material("seed coat", 0.1, textured(noise, (0.50, 0.31, 0.16), 9.0, 0.75, 10,
                                             speckle=0.6, tint=0.12))
  wafer = Material("polished substrate", 0.85, textured(noise, (0.46, 0.47, 0.50), 8.0, 0.7, 20))
  a, b, c = 130.0, 80.0, 62.0  # semi-axes, um
  sphere = trimesh.creation.icosphere(subdivisions=6)
  u = np.asarray(sphere.vertices, np.float64)
  # Ridges run along the long axis (x): the radius swells with the angle around it; bumps on top.
  phi = np.arctan2(u[:, 2], u[:, 1])
  ridges = 0.035 * np.cos(14 * phi + 0.3 * np.sin(3 * np.pi * u[:, 0]))
  bumps = 0.05 * (noise(u * np.array([a, b, c]), 22.0, 3, 30) - 0.5)
  pits = -0.03 * np.clip((noise(u * np.array([a, b, c]), 11.0, 1, 31) - 0.75) / 0.15, 0, 1)
  r = 1.0 + ridges * (1 - u[:, 0]**4) + bumps + pits
  v = u * r[:, None] * np.array([a, b, c])
  yaw = rng.uniform(-0.6, 0.6)
  rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
  sink = 0.08 * c  # the seed rests slightly pressed into its bed, as on sticky tape
  v = v @ rot.T + np.array([0.0, 0.0, c - sink])
  solid = Solid(v, np.asarray(sphere.faces), material=0)
  half = float(np.abs(v[:, :2]).max())
  return Sample("seed", [coat, wafer], substrate=1, half_size=half, height=float(v[:, 2].max()),
                spacing=half / 24, solids=[solid])


def circuit_scene(seed: int) -> Sample:
  """Copper traces, pads and a black chip on a green board, all with steep side walls."""
  rng = np.random.default_rng([seed, 2])
  noise = Noise(seed)
  board = Material("FR4 board", 0.15, textured(noise, (0.20, 0.42, 0.22), 8.0, 0.7, 10,
                                               speckle=0.4))
  copper = Material("copper", 0.6, textured(noise, (0.78, 0.48, 0.24), 6.0, 0.55, 20,
                                            speckle=0.3))
  epoxy = Material("chip epoxy", 0.3, textured(noise, (0.16, 0.16, 0.17), 7.0, 0.9, 30,
                                               speckle=0.5, tint=0.2))
  half, t_cu, h_chip, wall = 200.0, 18.0, 70.0, 2.0
  chip = (rng.uniform(-15, 15), rng.uniform(-15, 15), 75.0, 52.0)  # cx, cy, hx, hy
  traces, pads = [], []
  for side in range(4):  # pins leave the chip on all four sides and bend by 45 degrees
    ang = side * np.pi / 2
    fwd, lat = np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
    reach = chip[2] if side % 2 == 0 else chip[3]
    n = 3 if side % 2 == 0 else 2
    for k in range(n):
      off = (k - (n - 1) / 2) * 2.1 * reach / n
      start = np.array(chip[:2]) + fwd * (reach - 10) + lat * off
      bend = start + fwd * rng.uniform(30, 45)
      end = bend + (fwd + lat * rng.choice([-1, 1])) / np.sqrt(2) * rng.uniform(35, 60)
      w = rng.uniform(12, 22)
      traces += [(start, bend, w), (bend, end, w)]
      pads.append((end, rng.uniform(14, 20)))

  def field(x, y):
    copper_in = np.full(x.shape, -np.inf)
    for a, b, w in traces:
      copper_in = np.maximum(copper_in, w / 2 - segment_distance(x, y, a, b))
    for (px, py), r in pads:
      copper_in = np.maximum(copper_in, box_signed(x, y, px, py, r, r))
    chip_in = box_signed(x, y, *chip)
    z_cu, z_chip = t_cu * ramp(copper_in, wall), h_chip * ramp(chip_in, wall)
    # a shallow dimple (pin-1 mark) and engraved lines on the chip top for texture and relief
    mark = 4.0 * ramp(8 - np.hypot(x - chip[0] + chip[2] * 0.6, y - chip[1] + chip[3] * 0.5), 2)
    z_chip = z_chip - mark * (chip_in > 10)
    z = np.maximum(z_cu, z_chip)
    mat = np.where(z_chip >= z_cu, np.where(chip_in > -wall, 2, 0), np.where(copper_in > -wall,
                                                                             1, 0))
    return z, mat, np.zeros(x.shape, np.int64)

  return Sample("circuit", [board, copper, epoxy], substrate=0, half_size=half, height=h_chip,
                spacing=1.25, heightfield=field)


def wing_scene(seed: int) -> Sample:
  """Overlapping butterfly-wing scales (roof tiles with fine ridges) crossed by veins."""
  rng = np.random.default_rng([seed, 3])
  noise = Noise(seed)
  stage = Material("stage", 0.5, textured(noise, (0.42, 0.42, 0.40), 12.0, 0.6, 10))
  membrane = Material("membrane", 0.3, textured(noise, (0.25, 0.20, 0.15), 8.0, 0.6, 20))
  palette = [(0.85, 0.45, 0.10), (0.12, 0.10, 0.09), (0.90, 0.85, 0.75), (0.25, 0.35, 0.65)]
  scales = Material("scales", 0.45, by_part(noise, palette, 6.0, 0.6, 30, seed))
  vein = Material("vein", 0.2, textured(noise, (0.20, 0.13, 0.08), 6.0, 0.6, 40, speckle=0.4))
  half, z_mem, length, width, pitch_x, pitch_y, lift = 170.0, 6.0, 62.0, 34.0, 42.0, 30.0, 7.0
  jitter = rng.uniform(-3, 3, (64, 64, 2))
  eye = rng.uniform(-40, 40, 2)  # an eyespot: rings of colour around this point
  stray = (rng.random((64, 64)) < 0.1).astype(int)  # a few scales break the pattern
  veins = [((-half, rng.uniform(-60, -30)), (half, rng.uniform(20, 50)), 14.0),
           ((rng.uniform(-40, 0), -half), (rng.uniform(40, 90), half), 11.0)]

  def field(x, y):
    inside = box_signed(x, y, 0.0, 0.0, half - 12, half - 12)
    z = z_mem * ramp(inside, 3.0)
    part = np.zeros(x.shape, np.int64)
    mat = np.where(inside > -1.5, 1, 0)
    for i in range(-6, 7):  # rows along x overlap like roof tiles; every other row shifts by half
      for j in range(-7, 8):
        jx, jy = jitter[i % 64, j % 64]
        x0, y0 = i * pitch_x + jx, (j + 0.5 * (i % 2)) * pitch_y + jy
        s = (x - x0) / length  # 0 at the scale's base, 1 at its tip
        # half width: narrow stalk at the base, widest at 60 %, a rounded tip
        hw = width / 2 * np.sqrt(np.clip(1 - ((s - 0.6) / np.where(s < 0.6, 0.75, 0.4))**2, 0, 1))
        shape = np.minimum(np.minimum(s, 1 - s) * length, hw - np.abs(y - y0))
        shape = np.minimum(shape, inside)
        zs = z_mem + 1.5 + lift * np.clip(s, 0, 1) + 0.5 * np.cos(2 * np.pi * (y - y0) / 4.0)
        zs = np.where(shape > 0, zs * ramp(shape, 1.5) + z * (1 - ramp(shape, 1.5)), -np.inf)
        win = zs > z
        z, mat = np.where(win, zs, z), np.where(win, 2, mat)
        ring = int(np.hypot(x0 + 0.6 * length - eye[0], y0 - eye[1]) // 38)
        colour = (ring + stray[i % 64, j % 64]) % len(palette)
        part = np.where(win, ((i + 7) * 16 + (j + 8)) * len(palette) + colour, part)
    for a, b, r in veins:
      d = segment_distance(x, y, a, b)
      zv = z_mem + np.sqrt(np.clip(r * r - d * d, 0, None)) * 1.1
      win = (zv > z) & (inside > 0)
      z, mat = np.where(win, zv, z), np.where(win, 3, mat)
    return z, mat, part

  return Sample("wing", [stage, membrane, scales, vein], substrate=0, half_size=half,
                height=z_mem + 1.5 + lift + 0.5 + 16.0, spacing=1.0, heightfield=field)


def sensor_scene(seed: int) -> Sample:
  """A MEMS accelerometer: a perforated, grooved proof mass, comb fingers, springs and anchors."""
  rng = np.random.default_rng([seed, 4])
  noise = Noise(seed)
  silicon = Material("silicon substrate", 0.7, textured(noise, (0.40, 0.42, 0.50), 10.0, 0.6, 10,
                                                        speckle=0.3))
  poly = Material("polysilicon", 0.5, textured(noise, (0.62, 0.56, 0.45), 5.0, 0.6, 20,
                                               speckle=0.4))
  gold = Material("gold pad", 0.75, textured(noise, (0.85, 0.68, 0.30), 7.0, 0.5, 30))
  half, t, wall = 170.0, 22.0, 1.0
  m = 62.0  # proof mass half width
  finger_w, finger_gap, finger_len = 4.0, 4.0, 34.0
  hole, hole_pitch, groove_w, groove_d, groove_pitch = 6.0, 20.0, 2.5, 2.0, 7.0
  skew = rng.uniform(-0.05, 0.05)

  def field(x, y):
    mass = box_signed(x, y, 0, 0, m, m)
    # release holes on a square lattice, and fine grooves (a diffraction grating) across the mass
    hx = (x + hole_pitch / 2) % hole_pitch - hole_pitch / 2
    hy = (y + hole_pitch / 2) % hole_pitch - hole_pitch / 2
    holes = np.minimum(hole / 2 - np.abs(hx), hole / 2 - np.abs(hy))
    mass = np.minimum(mass, -holes)
    gx = (x + skew * y) % groove_pitch
    grooves = groove_d * ramp(groove_w / 2 - np.abs(gx - groove_pitch / 2), 0.8)
    struct = mass
    # comb fingers: moving ones on the mass (left and right), fixed ones from electrode bars
    fpitch = 2 * (finger_w + finger_gap)
    for sgn in (-1, 1):
      fy = (y + fpitch / 2) % fpitch - fpitch / 2
      xin = sgn * x - m
      moving = np.minimum(np.minimum(xin, finger_len - xin), finger_w / 2 - np.abs(fy))
      fixed_y = y % fpitch - fpitch / 2  # fixed fingers sit half a pitch off the moving ones
      fixed = np.minimum(np.minimum(xin - 8, finger_len + 8 - xin), finger_w / 2 - np.abs(fixed_y))
      bar = box_signed(x, y, sgn * (m + finger_len + 16), 0, 8, m)
      band = m - np.abs(y)
      struct = np.maximum(struct, np.minimum(np.maximum(moving, fixed), band))
      struct = np.maximum(struct, bar)
    # serpentine springs from the mass corners to anchors above and below
    for sy in (-1, 1):
      for sx in (-1, 1):
        y0 = sy * m
        seg = np.full(x.shape, -np.inf)
        pts = [(sx * 30, y0), (sx * 30, y0 + sy * 12), (sx * 52, y0 + sy * 12),
               (sx * 52, y0 + sy * 24), (sx * 30, y0 + sy * 24), (sx * 30, y0 + sy * 36)]
        for a, b in zip(pts[:-1], pts[1:]):
          seg = np.maximum(seg, 2.0 - segment_distance(x, y, a, b))
        struct = np.maximum(struct, seg)
        struct = np.maximum(struct, box_signed(x, y, sx * 30, y0 + sy * 48, 14, 12))
    pads = np.full(x.shape, -np.inf)
    for px in (-120.0, -40.0, 40.0, 120.0):
      for py in (-140.0, 140.0):
        pads = np.maximum(pads, box_signed(x, y, px, py, 22, 16))
    z = t * ramp(struct, wall) - grooves * (mass > 1.0)
    zp = 3.0 * ramp(pads, wall)
    mat = np.where(struct > -wall, 1, np.where(pads > -wall, 2, 0))
    return np.maximum(z, zp), mat, np.zeros(x.shape, np.int64)

  return Sample("sensor", [silicon, poly, gold], substrate=0, half_size=half, height=t,
                spacing=1.0, heightfield=field)


def lenses_scene(seed: int) -> Sample:
  """Close-packed polished hemispherical microlenses on a rough, diffuse carrier."""
  rng = np.random.default_rng([seed, 5])
  noise = Noise(seed)
  carrier = Material("carrier", 0.1, textured(noise, (0.55, 0.50, 0.44), 7.0, 0.8, 10,
                                              speckle=0.5, tint=0.15))
  glass = Material("lens", 0.95, textured(noise, (0.62, 0.70, 0.78), 6.0, 0.55, 20, tint=0.15))
  radius, pitch, half = 28.0, 58.0, 165.0
  centres = []
  for j in range(-4, 5):  # hexagonal packing inside a disc
    for i in range(-4, 5):
      c = np.array([(i + 0.5 * (j % 2)) * pitch, j * pitch * np.sqrt(3) / 2])
      c += rng.uniform(-1.0, 1.0, 2)
      if np.hypot(*c) <= half - radius - 15:
        centres.append(c)
  centres = np.array(centres)

  def field(x, y):
    z = np.zeros(x.shape)
    part = np.zeros(x.shape, np.int64)
    for k, (cx, cy) in enumerate(centres):
      r2 = (x - cx)**2 + (y - cy)**2
      zk = np.sqrt(np.clip(radius * radius - r2, 0, None))
      win = zk > z
      z, part = np.where(win, zk, z), np.where(win, k + 1, part)
    return z, (z > 0).astype(np.int64), part

  return Sample("lenses", [carrier, glass], substrate=0, half_size=half, height=radius,
                spacing=1.0, heightfield=field)


SCENES: dict[str, Callable[[int], Sample]] = {
    "seed": seed_scene,
    "circuit": circuit_scene,
    "wing": wing_scene,
    "sensor": sensor_scene,
    "lenses": lenses_scene,
}
