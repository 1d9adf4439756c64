"""PNG pictures of results, shared by the CLIs: height maps, top-view scatter maps, line plots,
top-view previews of coloured meshes.

Figures are built with matplotlib's object API (`matplotlib.figure.Figure`, rendered by Agg), so
drawing never opens a window nor changes the caller's pyplot backend. Lengths on the axes are in um.
Every PNG is written atomically (ofjax.fileio).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.axes_grid1 import make_axes_locatable

from ofjax import fileio
from ofjax.meshquery import RAY_CLEARANCE, MeshQuery

DPI = 120


def save(fig: Figure, path: str | Path) -> Path:
  """Writes `fig` as a PNG at `path` (atomically) and returns the path."""
  path = Path(path)
  with fileio.atomic_path(path) as tmp:
    fig.savefig(tmp, format="png", dpi=DPI, bbox_inches="tight")
  return path


def colorbar(fig: Figure, ax, mappable, label: str) -> None:
  """A colour bar exactly as tall as `ax` (equal-aspect axes are often much flatter than the figure)."""
  cax = make_axes_locatable(ax).append_axes("right", size="3%", pad=0.1)
  fig.colorbar(mappable, cax=cax, label=label)


def height_map(path: str | Path, z: np.ndarray, extent: tuple[float, float, float, float],
               title: str, label: str = "height (um)", axis_names: tuple[str, str] = ("x", "y"),
               cmap: str = "viridis") -> Path:
  """An image of a height grid.

  Args:
    z: [ny, nx] heights, row 0 at the low end of the second axis; NaN is drawn blank.
    extent: (x0, x1, y0, y1) of the grid in um.
  """
  fig = Figure(figsize=(6.4, 5.2))
  ax = fig.add_subplot()
  im = ax.imshow(z, origin="lower", extent=extent, cmap=cmap, interpolation="nearest")
  ax.set(title=title, xlabel=f"{axis_names[0]} (um)", ylabel=f"{axis_names[1]} (um)",
         aspect="equal")
  colorbar(fig, ax, im, label)
  return save(fig, path)


def scatter_map(path: str | Path, xy: np.ndarray, values: np.ndarray, title: str, label: str,
                vmax: float | None = None, cmap: str = "magma") -> Path:
  """A top view of points coloured by a value (e.g. an error on the surface).

  Args:
    xy: [N, 2] point positions in um.
    values: [N] the value drawn at each point; the colour scale runs from 0 to `vmax`
      (default: the 99th percentile, so a few outliers do not wash the map out).
  """
  values = np.asarray(values, np.float64)
  if vmax is None:
    vmax = float(np.percentile(values, 99)) if len(values) else 1.0
  fig = Figure(figsize=(6.4, 5.2))
  ax = fig.add_subplot()
  order = np.argsort(values)  # draw large errors last so they are not hidden under small ones
  vmax = max(vmax, np.finfo(np.float64).tiny)  # all-zero errors still need a colour range
  sc = ax.scatter(xy[order, 0], xy[order, 1], c=values[order], s=2, cmap=cmap, vmin=0.0,
                  vmax=vmax, linewidths=0)
  ax.set(title=title, xlabel="x (um)", ylabel="y (um)", aspect="equal")
  colorbar(fig, ax, sc, label)
  return save(fig, path)


def line_plot(path: str | Path, x: np.ndarray, ys: dict[str, np.ndarray], title: str,
              xlabel: str, ylabel: str, equal_aspect: bool = False) -> Path:
  """Curves sharing one x axis; `ys` maps a legend label to [N] values (NaN breaks the line)."""
  fig = Figure(figsize=(7.0, 3.6))
  ax = fig.add_subplot()
  for name, y in ys.items():
    ax.plot(x, y, label=name, linewidth=1.2)
  ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
  if equal_aspect:
    ax.set_aspect("equal", adjustable="datalim")
  if len(ys) > 1:
    ax.legend()
  ax.grid(True, alpha=0.3)
  return save(fig, path)


def mesh_preview(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
                 colours: np.ndarray | None, title: str, size: int = 512) -> Path:
  """A top view of a mesh, rendered orthographically by ray casting: colour beside height.

  Args:
    vertices: [V, 3] um; faces: [F, 3].
    colours: [V, 3] RGB in [0, 1] (interpolated across faces), or None for height only.
    size: pixels along the longer side of the mesh's XY extent.
  """
  vertices = np.asarray(vertices, np.float64)
  lo, hi = vertices.min(0), vertices.max(0)
  step = max(hi[0] - lo[0], hi[1] - lo[1]) / size
  xs = lo[0] + (np.arange(max(1, round((hi[0] - lo[0]) / step))) + 0.5) * step
  ys = lo[1] + (np.arange(max(1, round((hi[1] - lo[1]) / step))) + 0.5) * step
  gx, gy = np.meshgrid(xs, ys)
  top = hi[2] + RAY_CLEARANCE
  query = MeshQuery(vertices, faces)
  origins = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, top)], -1)
  t, face, bary = query.cast(origins, np.broadcast_to([0.0, 0.0, -1.0], origins.shape))
  hit = face >= 0
  z = np.where(hit, top - t, np.nan).reshape(gx.shape)
  extent = (lo[0], hi[0], lo[1], hi[1])
  panels = 1 if colours is None else 2
  fig = Figure(figsize=(6.0 * panels, 5.2))
  if colours is not None:
    rgb = np.ones((gx.size, 3))  # white background where no surface is
    rgb[hit] = np.clip(query.interpolate(colours, face[hit], bary[hit]), 0.0, 1.0)
    ax = fig.add_subplot(1, 2, 1)
    ax.imshow(rgb.reshape(*gx.shape, 3), origin="lower", extent=extent, interpolation="nearest")
    ax.set(title="colour", xlabel="x (um)", ylabel="y (um)")
  ax = fig.add_subplot(1, panels, panels)
  im = ax.imshow(z, origin="lower", extent=extent, cmap="viridis", interpolation="nearest")
  ax.set(title="height", xlabel="x (um)", ylabel="y (um)")
  colorbar(fig, ax, im, "z (um)")
  fig.suptitle(title)
  return save(fig, path)

