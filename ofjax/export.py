"""Mesh export: marching cubes of the SDF, vertex colours from the global colour network, in um.

`python -m ofjax.export RUN_DIR [--resolution N] [--refine-steps K] [--format ply|obj|glb] [--out FILE]
[--poses FILE | --keep-hidden]`

The SDF is evaluated in chunks on a grid over the observed region (the WLI points' box, stored in
the run's config.json) whose cells are half a WLI pixel (`grid_resolution`; or N cells along the
box's longest side, from --resolution or the run's train.mesh_resolution), the zero level set is
extracted with scikit-image, every vertex is moved along its grid edge from the linear
interpolation to the SDF's own zero (K bisection steps, default REFINE_STEPS; 0 keeps marching
cubes' interpolation), floating components smaller than `min_component` of the largest are
dropped, vertex colours come from G(x, n, f) only (paper Sec. 3.3.2: no view-dependent
highlights), and coordinates are mapped back to micrometres.
Last, the faces no camera of the run can see are dropped (`ofjax.visibility`: the pockets the SDF
leaves inside solid parts); the cameras are the run's poses.json (written by `ofjax.train`), or
--poses for a run trained before it; --keep-hidden keeps every face.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from skimage import measure

from ofjax import checkpoint, compile_cache, fields, visibility
from ofjax import scene as scene_lib
from ofjax.config import Config
from ofjax.errors import UserError, cli
from ofjax.meshfile import FORMATS, write_mesh

# Points per device call: bounded memory on a laptop. On the CPU 16,384 ran the demo's SDF at
# 0.68-0.87 us per point against 1.26-1.36 at 65,536 (the working set stays in cache).
CHUNK = 1 << 14
# Bisection steps per vertex: the zero is bracketed to 1/64 of a cell before the last linear
# interpolation. The fused SDF bends across a cpu-preset cell (~2.2 um): on `lenses` (4,800 steps)
# linear interpolation set its level faces 0.18 um low, 6 steps put them at +0.01 um, as a 1,024
# grid did (experiments/README.md); each step costs one SDF evaluation per vertex.
REFINE_STEPS = 6
# Below this share of the faces in some camera's sight, poses given for a run are not the run's
# (another frame, another scene): a trained surface lies in its cameras' view almost whole (>= 92%
# on the synthetic scenes, where the rest are pockets inside solid parts). Not applied to the
# poses a run was just trained with (train's own export): there a low share says the SDF made
# surface no camera measured, which the drop removes.
MIN_SEEN = 0.5
POSES = "poses.json"  # the cameras a run was trained with, in its directory
# The automatic grid's cell, in WLI pixels. The WLI samples the surface once per pixel, and a grid
# resolves detail down to about two of its cells, so half a pixel keeps what the scans measured.
# On `wing` (600 steps, fused, its ridges 1-2.5 um apart, pixel 1.41 um, box 443 um), Chamfer
# 0.179 / 0.159 / 0.145 / 0.142 um at 192 / 256 / 384 / 512 cells (1.64 / 1.23 / 0.82 / 0.61 px):
# the gain levels off before half a pixel (experiments/README.md).
AUTO_CELL_PX = 0.5
# The automatic grid's cap along the box's longest side: the SDF on a 1024 x 1024 grid over a flat
# sample ~150 cells deep is ~0.6 GB (float32); a finer grid takes an explicit --resolution.
MAX_AUTO_RESOLUTION = 1024


def evaluate_chunked(fn: Callable, x: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
  """Applies a jitted point function to x: [N, 3] in fixed-size chunks (one compilation)."""
  n = len(x)
  out = []
  for i in range(0, n, chunk):
    part = x[i:i + chunk]
    pad = chunk - len(part)
    res = np.asarray(fn(jnp.asarray(np.pad(part, ((0, pad), (0, 0))), jnp.float32)))
    out.append(res[:len(part)])
  return np.concatenate(out, 0) if out else np.zeros((0,))


def wli_pixel_um(poses: dict) -> float | None:
  """The median WLI pixel (mean of its two sides) of a poses file's cameras; None without WLI."""
  sizes = [float(np.mean(c["intrinsics"]["pixel_size"])) for c in poses.get("cameras", [])
           if c.get("modality") == "wli"]
  return float(np.median(sizes)) if sizes else None


def longest_side_um(box, norm: scene_lib.Normalization) -> float:
  """The longest side of a normalised (lo, hi) box, in the scene's units: what the grid divides."""
  return float(np.max(np.asarray(box[1]) - np.asarray(box[0]))) * norm.scale


def grid_resolution(mesh_resolution: int, box, norm: scene_lib.Normalization,
                    poses: dict | None) -> int:
  """Marching-cubes cells along the box's longest side: mesh_resolution when positive, else as many
  as make a cell AUTO_CELL_PX WLI pixels (poses: the run's cameras), at most MAX_AUTO_RESOLUTION.

  box: (lo, hi) normalised; norm maps it to um.
  """
  if mesh_resolution > 0:
    return mesh_resolution
  pixel = None if poses is None else wli_pixel_um(poses)
  if pixel is None:
    raise UserError("the mesh grid is set from the WLI pixel size, and no WLI camera is at hand; "
                    "pass --resolution N (cells along the longest side)")
  cells = np.ceil(longest_side_um(box, norm) / (AUTO_CELL_PX * pixel))
  return int(min(cells, MAX_AUTO_RESOLUTION))


def grid_shape(lo, hi, resolution: int) -> tuple[int, int, int]:
  """Cells per axis: `resolution` along the longest side, the same spacing on the others."""
  ext = np.asarray(hi) - np.asarray(lo)
  return tuple(max(int(np.ceil(resolution * e / ext.max())), 2) + 1 for e in ext)


def grid_layout(lo, hi, resolution: int) -> tuple[tuple[int, int, int], np.ndarray]:
  """The grid over [lo, hi]: nodes per axis (`grid_shape`) and [3] float64 node spacing."""
  lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
  shape = grid_shape(lo, hi, resolution)
  return shape, (hi - lo) / (np.asarray(shape) - 1)


def node_values(fn: Callable, lo: np.ndarray, spacing: np.ndarray, shape: tuple[int, int, int],
                flat: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
  """[N] float32 values of a point function at the grid nodes with these flat indices.

  The nodes' points are made one chunk at a time, so memory holds the values, not the points
  (a 1024-cell grid's points alone would be ~20x its float32 values).
  """
  out = np.empty(len(flat), np.float32)
  for i in range(0, len(flat), chunk):
    part = flat[i:i + chunk]
    out[i:i + len(part)] = evaluate_chunked(
        fn, lo + np.stack(np.unravel_index(part, shape), -1) * spacing, chunk)
  return out


# Narrow-band evaluation of the SDF grid. The grid is cut into blocks of BLOCK cells a side and
# the SDF evaluated at the block corners first; only blocks whose corners differ in sign or lie
# within BAND block diagonals of the zero level are evaluated at every node. Every point of a
# block is within half its diagonal of a corner (the centre is the farthest), and a trained SDF
# grows about as fast as the distance (the eikonal term), so a block holding surface has a corner
# within half a diagonal of the zero level; BAND = 1 allows the SDF to grow up to twice as fast.
# The other blocks hold no surface and take their nearest corner's value (the same sign: no
# vertex there).
BLOCK = 4
BAND = 1.0


def sdf_grid(sdf_fn: Callable, lo: np.ndarray, spacing: np.ndarray, shape: tuple[int, int, int],
             block: int = BLOCK, band: float = BAND) -> tuple[np.ndarray, float]:
  """[X, Y, Z] float32 SDF values at the nodes lo + index * spacing, exact near the zero level
  (see BLOCK), and the SDF evaluations made per node (block corners in the band count twice).
  block=1 evaluates every node once."""
  shape = tuple(int(n) for n in shape)
  # Block corners: every block-th node, and the last node of each axis.
  corners = [np.unique(np.r_[np.arange(0, n, block), n - 1]) for n in shape]
  cidx = np.stack(np.meshgrid(*corners, indexing="ij"), -1).reshape(-1, 3)
  coarse = node_values(sdf_fn, lo, spacing, shape,
                       np.ravel_multi_index(tuple(cidx.T), shape)).reshape(
                           tuple(len(c) for c in corners))
  if block == 1:
    return coarse, 1.0
  # Blocks (between consecutive corners along each axis) that may hold surface.
  c8 = np.stack([coarse[i:i + coarse.shape[0] - 1, j:j + coarse.shape[1] - 1,
                        k:k + coarse.shape[2] - 1]
                 for i in (0, 1) for j in (0, 1) for k in (0, 1)])
  reach = band * float(np.linalg.norm(spacing * block))
  active = (c8.min(0) < 0) & (c8.max(0) > 0) | (np.abs(c8).min(0) <= reach)
  mask = np.zeros(shape, bool)
  for a, b, c in np.argwhere(active):
    mask[corners[0][a]:corners[0][a + 1] + 1, corners[1][b]:corners[1][b + 1] + 1,
         corners[2][c]:corners[2][c + 1] + 1] = True
  # Every node first takes its nearest corner's value, then the band's nodes their own.
  nearest = [np.abs(np.arange(n)[:, None] - c[None]).argmin(1) for n, c in zip(shape, corners)]
  vol = coarse[np.ix_(*nearest)].astype(np.float32)
  flat = np.flatnonzero(mask)
  vol.reshape(-1)[flat] = node_values(sdf_fn, lo, spacing, shape, flat)
  return vol, (len(flat) + len(cidx)) / vol.size


def marching_cubes(sdf_fn: Callable, lo, hi, resolution: int, refine_steps: int = REFINE_STEPS,
                   min_component: float = 0.0) -> trimesh.Trimesh:
  """Zero level set of sdf_fn (positive outside) on a grid over [lo, hi]; faces point outside.

  refine_steps: bisection steps that move every vertex from the linear interpolation between its
    grid edge's two nodes to the SDF's own zero on that edge (`refine_on_edges`); 0 keeps the
    linear interpolation.
  min_component: components with fewer than this share of the largest one's faces are dropped
    (`drop_small_components`), before the refinement, which does not change the faces.
  Returns a mesh in the coordinates of sdf_fn (empty when the SDF has no sign change there).
  """
  lo = np.asarray(lo, np.float64)
  shape, spacing = grid_layout(lo, hi, resolution)
  vol, _ = sdf_grid(sdf_fn, lo, spacing, shape)
  if not (vol.min() < 0 < vol.max()):
    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
  verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=tuple(spacing))
  # scikit-image orients faces towards increasing values; the SDF grows outwards, so this is
  # already outward. (Checked by tests/test_export.py on a sphere.)
  mesh = drop_small_components(
      trimesh.Trimesh(np.asarray(verts, np.float64), faces, process=False), min_component)
  if refine_steps:
    mesh.vertices = refine_on_edges(sdf_fn, vol, np.asarray(mesh.vertices), spacing, lo,
                                    refine_steps)
  mesh.vertices = np.asarray(mesh.vertices) + lo
  return mesh


# A marching-cubes vertex sits on a grid edge: two of its grid coordinates are whole numbers (up to
# scikit-image's float32 arithmetic, ~1e-5 cells at these grid sizes). One closer than this to a
# node in all three coordinates is left where it is.
EDGE_TOL = 1e-3  # cells


def refine_on_edges(sdf_fn: Callable, vol: np.ndarray, verts: np.ndarray, spacing: np.ndarray,
                    lo: np.ndarray, steps: int) -> np.ndarray:
  """Marching-cubes vertices moved to the SDF's zero along their grid edges.

  Marching cubes places a vertex by linear interpolation between the two nodes of the edge whose
  signs differ. A trained SDF is not linear over a cell (near the surface its slope varies), so on
  coarse grids that places whole faces a fraction of a cell off the zero level set; bisection on
  the edge, bracketed by the two nodes, then a final linear interpolation inside the last bracket,
  finds the zero itself (to 2^-steps of a cell before that interpolation).

  Args:
    sdf_fn: [N, 3] -> [N], the function `vol` was sampled from.
    vol: [X, Y, Z] the SDF on the grid nodes lo + index * spacing.
    verts: [V, 3] vertices relative to lo (scikit-image's output with `spacing`).
    spacing: [3] node spacing; lo: [3] the grid's first node.
  Returns:
    [V, 3] refined vertices relative to lo; each stays on its edge.
  """
  g = verts / spacing  # grid coordinates
  frac = np.abs(g - np.round(g))
  axis = np.argmax(frac, 1)
  rows = np.flatnonzero(frac[np.arange(len(g)), axis] > EDGE_TOL)
  a = np.round(g[rows]).astype(np.int64)
  a[np.arange(len(rows)), axis[rows]] = np.floor(g[rows, axis[rows]]).astype(np.int64)
  b = a.copy()
  b[np.arange(len(rows)), axis[rows]] += 1
  f_lo, f_hi = vol[tuple(a.T)].astype(np.float64), vol[tuple(b.T)].astype(np.float64)
  bracketed = f_lo * f_hi < 0
  rows, a, f_lo, f_hi = rows[bracketed], a[bracketed], f_lo[bracketed], f_hi[bracketed]
  p0 = lo + a * spacing  # the edge's first node; the edge runs along `step`
  step = np.zeros_like(p0)
  step[np.arange(len(rows)), axis[rows]] = spacing[axis[rows]]
  t_lo, t_hi = np.zeros(len(rows)), np.ones(len(rows))
  for _ in range(steps):
    t = (t_lo + t_hi) / 2
    f = evaluate_chunked(sdf_fn, p0 + t[:, None] * step).astype(np.float64)
    low_side = np.sign(f) == np.sign(f_lo)
    t_lo, f_lo = np.where(low_side, t, t_lo), np.where(low_side, f, f_lo)
    t_hi, f_hi = np.where(low_side, t_hi, t), np.where(low_side, f_hi, f)
  # f_lo and f_hi still differ in sign (a zero f ends on the high side: f_hi = 0, t = t_hi).
  t = t_lo + (t_hi - t_lo) * f_lo / (f_lo - f_hi)
  out = verts.copy()
  out[rows] = p0 - lo + t[:, None] * step
  return out


def drop_small_components(mesh: trimesh.Trimesh, min_fraction: float) -> trimesh.Trimesh:
  """Removes connected components with fewer than min_fraction of the largest one's faces."""
  if len(mesh.faces) == 0 or min_fraction <= 0:
    return mesh
  labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, len(mesh.faces))
  counts = np.bincount(labels)
  keep = counts[labels] >= min_fraction * counts.max()
  out = mesh.copy()
  out.update_faces(keep)
  out.remove_unreferenced_vertices()
  return out


def surface_mesh(sdf_fn: Callable, color_fn: Callable, lo, hi, resolution: int,
                 norm: scene_lib.Normalization, min_component: float = 0.05,
                 refine_steps: int = REFINE_STEPS) -> trimesh.Trimesh:
  """Zero level set of sdf_fn over [lo, hi] (normalised), coloured by color_fn, mapped to um.

  sdf_fn: [N, 3] -> [N]; color_fn: [N, 3] -> [N, 3] in [0, 1]; both on normalised points.
  refine_steps: see `marching_cubes`.
  """
  mesh = marching_cubes(sdf_fn, lo, hi, resolution, refine_steps, min_component)
  if len(mesh.vertices):
    rgb = evaluate_chunked(color_fn, np.asarray(mesh.vertices))
    mesh.visual.vertex_colors = np.concatenate(
        [np.round(np.clip(rgb, 0, 1) * 255), np.full((len(rgb), 1), 255)], 1).astype(np.uint8)
  mesh.vertices = norm.to_um(np.asarray(mesh.vertices))
  return mesh


def field_function(fn: Callable, params, cfg: Config) -> Callable:
  """x [N, 3] -> fn(params, x, cfg), jitted. params are an argument of the jitted function, not a
  closed-over constant, so XLA neither embeds nor constant-folds the tables."""
  jitted = jax.jit(fn, static_argnums=2)
  return lambda x: jitted(params, x, cfg)


def extract_mesh(params, cfg: Config, norm: scene_lib.Normalization, box, resolution: int,
                 min_component: float = 0.05, refine_steps: int = REFINE_STEPS
                 ) -> trimesh.Trimesh:
  """The trained SDF's surface in um with vertex colours from the global colour network."""
  return surface_mesh(field_function(fields.sdf_value, params, cfg),
                      field_function(fields.global_color, params, cfg),
                      box[0], box[1], resolution, norm, min_component, refine_steps)


class Exported(NamedTuple):
  path: Path  # the mesh file written
  hidden: float  # share of the extracted faces dropped because no camera sees them (0 if kept)
  cell: float  # the marching-cubes grid's cell in `units`: finer detail is not in the mesh
  units: str  # the mesh's length unit

  def describe(self) -> str:
    """The path, the grid's cell, and the dropped share when faces were dropped (what a user sees
    as holes)."""
    dropped = f"; {self.hidden:.1%} of the faces, seen by no camera, dropped" if self.hidden else ""
    return f"{self.path} (grid cell {self.cell:.3g} {self.units}{dropped})"


def export_run(params, cfg: Config, norm, box, path: Path, resolution: int | None = None,
               units: str = "um", refine_steps: int = REFINE_STEPS,
               poses: dict | None = None, poses_path: str | Path = POSES,
               trained_in: Path | None = None) -> Exported:
  """Extracts and writes the mesh; refuses non-finite parameters (a diverged run).

  resolution: grid cells along the box's longest side; None: `grid_resolution` of
    cfg.train.mesh_resolution with `poses`.
  poses: the run's cameras (a poses file's contents, `poses_path` names it in messages): the
    faces none of them sees are dropped (`ofjax.visibility`); None keeps every face.
  trained_in: the run directory where `params` were just trained with `poses`, so a small share
    of faces in sight is the SDF's unmeasured surface, not foreign poses (no MIN_SEEN refusal);
    a surface none of them sees is refused naming the export of that run that keeps every face.
  """
  if resolution is None:
    resolution = grid_resolution(cfg.train.mesh_resolution, box, norm, poses)
  if not all(bool(jnp.all(jnp.isfinite(p))) for p in jax.tree_util.tree_leaves(params)):
    raise UserError(f"{path}: the parameters are not finite (the run diverged); no mesh written")
  mesh = extract_mesh(params, cfg, norm, box, resolution, refine_steps=refine_steps)
  if len(mesh.faces) == 0:
    raise UserError(f"{path}: the SDF has no zero crossing in the observed region; train longer "
                    "or check the data")
  seen = 1.0
  if poses is not None:
    mesh, seen = visibility.drop_hidden(mesh, poses)
    if trained_in is None and seen < MIN_SEEN:
      raise UserError(f"{poses_path}: only {seen:.0%} of the mesh's faces are in sight of its "
                      "cameras, so these are not the poses the run was trained with; pass those "
                      "(--poses), or --keep-hidden to keep every face; no mesh written")
    if len(mesh.faces) == 0:  # only with trained_in: given poses that see none are refused above
      raise UserError(f"{path}: none of the trained surface is in sight of the cameras it was "
                      f"trained with ({poses_path}); check the data, or export every face with "
                      f"`python -m ofjax.export {trained_in} --keep-hidden`; no mesh written")
  return Exported(write_mesh(mesh, path, units), 1.0 - seen,
                  longest_side_um(box, norm) / resolution, units)


class LoadedRun(NamedTuple):
  params: dict  # the newest checkpoint's, or their average when the run keeps one (ema_fraction)
  cfg: Config
  norm: scene_lib.Normalization
  box: tuple  # (lo, hi) of the observed region, normalised
  units: str
  poses_named: str | None  # the poses file the run was trained from (config.json "poses")


def load_run(run_dir: Path) -> LoadedRun:
  """A run directory's newest checkpoint and what its config.json says about it."""
  cfg_path = run_dir / "config.json"
  if not cfg_path.is_file():
    raise UserError(f"{cfg_path}: not found; is {run_dir} an ofjax run directory?")
  meta = json.loads(cfg_path.read_text())
  cfg = Config.from_dict(meta["config"])
  template = fields.init_params(jax.random.PRNGKey(0), cfg)
  if cfg.optim.ema_fraction > 0:  # the mesh comes from the parameters' average (ofjax.averaging)
    from ofjax import averaging, train
    state = checkpoint.restore(run_dir, template, train.make_optimizer(cfg).init(template))
    params = None if state is None else averaging.averaged(state[2])
  else:
    params = checkpoint.restore_params(run_dir, template)
  if params is None:
    raise UserError(f"{run_dir}: no checkpoint found; train first")
  norm = scene_lib.Normalization(tuple(meta["normalization"]["center"]),
                                 float(meta["normalization"]["scale"]))
  box = tuple(tuple(b) for b in meta["observed_box"])
  return LoadedRun(params, cfg, norm, box, meta.get("units", "um"), meta.get("poses"))


def run_poses(run_dir: Path, given: str | None, named: str | None, instead: str) -> Path:
  """The poses file of a run's cameras: `given`, else the run's own, else `named` (the one its
  config.json names: runs trained before the run directory kept its own).

  instead: the option that does without poses, for the message when none is found.
  """
  if given:
    return Path(given)
  if (run_dir / POSES).is_file():
    return run_dir / POSES
  if named and Path(named).is_file():
    return Path(named)
  raise UserError(f"{run_dir / POSES}: not found (the run predates it); pass the poses it was "
                  f"trained with (--poses FILE), or {instead}")


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m ofjax.export",
                              description="Export the mesh (um, vertex colours) of a training run.")
  p.add_argument("run_dir", help="run directory written by python -m ofjax.train")
  p.add_argument("--resolution", type=int,
                 help="grid cells along the box's longest side (default: the run's "
                      f"train.mesh_resolution; 0 there or here: cells of {AUTO_CELL_PX} WLI pixel)")
  p.add_argument("--refine-steps", type=int, default=REFINE_STEPS,
                 help="bisection steps that move each vertex to the SDF's zero along its grid edge "
                      f"(default {REFINE_STEPS}; 0: marching cubes' linear interpolation)")
  p.add_argument("--format", default="ply", choices=FORMATS)
  p.add_argument("--out", help="output file (default: RUN_DIR/mesh.<format>)")
  sight = p.add_mutually_exclusive_group()
  sight.add_argument("--poses", help=f"the cameras that decide which faces are seen (default: "
                     f"RUN_DIR/{POSES}, else the poses file named in its config.json)")
  sight.add_argument("--keep-hidden", action="store_true",
                     help="keep the faces no camera sees (pockets inside solid parts)")
  args = p.parse_args(argv)
  run_dir = Path(args.run_dir)
  compile_cache.enable()
  if args.resolution is not None and (args.resolution < 0 or 0 < args.resolution < 8):
    raise UserError(f"--resolution {args.resolution}: use at least 8 cells, or 0 for cells of "
                    f"{AUTO_CELL_PX} WLI pixel")
  if args.refine_steps < 0:
    raise UserError(f"--refine-steps {args.refine_steps}: use 0 or more")
  run = load_run(run_dir)
  setting = run.cfg.train.mesh_resolution if args.resolution is None else args.resolution
  # The cameras decide which faces are kept and, for the automatic grid, the WLI pixel.
  need_poses = not args.keep_hidden or setting == 0
  poses_path = run_poses(run_dir, args.poses, run.poses_named,
                         "--resolution N" if args.keep_hidden else "--keep-hidden to keep every "
                         "face") if need_poses else None
  poses = None if poses_path is None else scene_lib.load_poses(poses_path)
  res = grid_resolution(setting, run.box, run.norm, poses)
  out = Path(args.out) if args.out else run_dir / f"mesh.{args.format}"
  exported = export_run(run.params, run.cfg, run.norm, run.box, out, res, run.units,
                        args.refine_steps, None if args.keep_hidden else poses,
                        poses_path or POSES)
  print(f"ofjax: mesh written to {exported.describe()}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
