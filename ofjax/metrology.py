"""Surface metrology on meshes in um: levelling, ISO 25178-2 height parameters, cross-sections.

Conventions:
  region    (x0, y0, x1, y1) um: a rectangle in the mesh's XY plane.
  levelling a least-squares plane z = a x + b y + c is fitted to the heights and subtracted
            (ISO 25178's F-operation by a plane).
  heights   are taken from the first hit of rays cast from above, i.e. the topmost surface, as an
            areal instrument (or a WLI) sees it.
  roughness sampling (see `sample_region`): heights are first cast straight down (-z) on a regular
            XY grid over the region to fit the plane; then a regular grid of the same size and
            spacing is laid in the fitted plane (axes: u = x projected onto the plane, v = n x u,
            centred above the region's centre) and cast along -n, so the heights are measured
            perpendicular to the mean surface; these are levelled once more and evaluated.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ofjax.meshquery import RAY_CLEARANCE, MeshQuery

PARAMETERS = ("Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku")
MIN_SAMPLES = 3  # a plane has 3 unknowns; fewer finite heights cannot be levelled


def areal_parameters(z: np.ndarray) -> dict[str, float]:
  """ISO 25178-2 height parameters of a (levelled) height grid.

  Args:
    z: [...] heights in um on a regular grid; NaN marks points not measured and is left out.
  Returns:
    {"Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku"}: heights in um about the mean; Ssk and Sku are
    dimensionless and NaN for a perfectly flat grid (Sq = 0).
  """
  v = np.asarray(z, np.float64)
  v = v[np.isfinite(v)]
  if v.size < 1:
    raise ValueError("no finite heights")
  d = v - v.mean()
  sq = float(np.sqrt(np.mean(d ** 2)))
  sp, sv = float(d.max()), float(-d.min())
  with np.errstate(divide="ignore", invalid="ignore"):
    ssk = float(np.mean(d ** 3) / sq ** 3) if sq > 0 else float("nan")
    sku = float(np.mean(d ** 4) / sq ** 4) if sq > 0 else float("nan")
  return {"Sa": float(np.mean(np.abs(d))), "Sq": sq, "Sp": sp, "Sv": sv, "Sz": sp + sv,
          "Ssk": ssk, "Sku": sku}


def fit_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
  """[3] float64 (a, b, c) of the least-squares plane z = a x + b y + c through the finite z.

  x, y, z: [...] matching arrays (um).
  """
  x, y, z = (np.asarray(a, np.float64).ravel() for a in np.broadcast_arrays(x, y, z))
  ok = np.isfinite(z)
  if ok.sum() < MIN_SAMPLES:
    raise ValueError(f"need at least {MIN_SAMPLES} finite heights to fit a plane")
  # Centre the coordinates so the normal equations stay well conditioned far from the origin.
  xm, ym = x[ok].mean(), y[ok].mean()
  A = np.stack([x[ok] - xm, y[ok] - ym, np.ones(ok.sum())], -1)
  (a, b, c), *_ = np.linalg.lstsq(A, z[ok], rcond=None)
  return np.array([a, b, c - a * xm - b * ym])


def level(z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
  """z minus its least-squares plane (NaN stays NaN). z, x, y: [...] matching arrays (um)."""
  a, b, c = fit_plane(x, y, z)
  return np.asarray(z, np.float64) - (a * np.asarray(x) + b * np.asarray(y) + c)


def region_grid(region: tuple[float, float, float, float], n: int) -> tuple[float, int, int]:
  """(step um, nx, ny) of a grid of square cells with `n` cells along the region's longer side."""
  x0, y0, x1, y1 = region
  step = max(x1 - x0, y1 - y0) / n
  return step, max(1, int(round((x1 - x0) / step))), max(1, int(round((y1 - y0) / step)))


def cast_down(query: MeshQuery, top: float, xy: np.ndarray) -> np.ndarray:
  """[N] z (um) of the topmost surface above each xy [N, 2] (NaN where there is none).

  top: a height above the whole mesh (um).
  """
  origins = np.concatenate([xy, np.full((len(xy), 1), top)], -1)
  dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
  t, _, _ = query.cast(origins, dirs)
  return np.where(np.isfinite(t), top - t, np.nan)


@dataclasses.dataclass
class HeightGrid:
  """Levelled heights sampled over a region, perpendicular to the mesh's mean plane there."""
  z: np.ndarray  # [ny, nx] um above the least-squares plane, NaN where no surface was hit
  step: float  # um between samples along u and v
  center: np.ndarray  # [3] um: the plane point above the region's centre, where u = v = 0
  axes: np.ndarray  # [3, 3] rows u, v, n: the plane's in-plane axes and its upward unit normal

  @property
  def extent(self) -> tuple[float, float, float, float]:
    """(u0, u1, v0, v1) um of the grid's cells."""
    ny, nx = self.z.shape
    return (-nx * self.step / 2, nx * self.step / 2, -ny * self.step / 2, ny * self.step / 2)

  @property
  def tilt_deg(self) -> float:
    """Angle between the fitted plane's normal and +z."""
    return float(np.degrees(np.arccos(np.clip(self.axes[2, 2], -1.0, 1.0))))


def sample_region(vertices: np.ndarray, faces: np.ndarray,
                  region: tuple[float, float, float, float], n: int = 256,
                  query: MeshQuery | None = None) -> HeightGrid:
  """Levelled heights of a mesh region on a regular grid (see the module docstring).

  Args:
    vertices: [V, 3] um; faces: [F, 3].
    region: (x0, y0, x1, y1) um with x1 > x0, y1 > y0.
    n: samples along the region's longer side.
  Raises:
    ValueError when fewer than MIN_SAMPLES rays hit the mesh.
  """
  query = query or MeshQuery(vertices, faces)
  vertices = np.asarray(vertices, np.float64)
  x0, y0, x1, y1 = region
  step, nx, ny = region_grid(region, n)
  cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
  iu = (np.arange(nx) + 0.5 - nx / 2) * step
  iv = (np.arange(ny) + 0.5 - ny / 2) * step
  gu, gv = np.meshgrid(iu, iv)  # [ny, nx]
  top = vertices[:, 2].max() + RAY_CLEARANCE
  z0 = cast_down(query, top, np.stack([cx + gu.ravel(), cy + gv.ravel()], -1)).reshape(gu.shape)
  a, b, c = fit_plane(gu, gv, z0)  # c: the plane's height above the region's centre
  normal = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1.0)
  u = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
  u /= np.linalg.norm(u)
  axes = np.stack([u, np.cross(normal, u), normal])
  center = np.array([cx, cy, c])
  points = center + gu[..., None] * axes[0] + gv[..., None] * axes[1]  # [ny, nx, 3] in the plane
  above = float(((vertices - center) @ normal).max()) + RAY_CLEARANCE
  t, _, _ = query.cast((points + above * normal).reshape(-1, 3),
                    np.broadcast_to(-normal, (points.size // 3, 3)))
  h = np.where(np.isfinite(t), above - t, np.nan).reshape(gu.shape)
  return HeightGrid(level(h, gu, gv), step, center, axes)


def profile(vertices: np.ndarray, faces: np.ndarray, start: tuple[float, float],
            end: tuple[float, float], n: int = 512,
            query: MeshQuery | None = None) -> tuple[np.ndarray, np.ndarray]:
  """The topmost surface's height along a straight XY line (not levelled).

  Args:
    vertices: [V, 3] um; faces: [F, 3].
    start, end: (x, y) um, the line's ends (both sampled).
    n: number of samples.
  Returns:
    s: [n] um, distance from `start` along the line.
    xyz: [n, 3] um, the surface points; z is NaN where the line leaves the mesh.
  """
  start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
  f = np.linspace(0.0, 1.0, n)
  xy = start + f[:, None] * (end - start)
  query = query or MeshQuery(vertices, faces)
  z = cast_down(query, float(np.max(np.asarray(vertices)[:, 2])) + RAY_CLEARANCE, xy)
  return f * np.linalg.norm(end - start), np.concatenate([xy, z[:, None]], -1)
