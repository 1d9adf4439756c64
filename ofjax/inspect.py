"""`python -m ofjax.inspect SCENE_OR_DIR`: what a data folder holds, and a contact sheet of it.

Prints the layout, units, every WLI scan (size, pixel size, void fraction, depth range, pose) and
every OM photo (size, focal length, pose), then writes a contact-sheet PNG: the WLI depth maps
(voids in magenta) followed by the OM photos as thumbnails. Layouts are those of ofjax.io.detect:
native (scene.json), opticfusion (wl/ + op/), raw (wli/ + om/).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from ofjax import fileio
from ofjax.errors import cli
from ofjax.io import LAYOUTS, load
from ofjax.scene import Scene

THUMB_PX = 256  # longest side of a contact-sheet tile, in pixels of the source
SHEET_COLS = 6
VOID_RGB = (1.0, 0.0, 1.0)  # magenta: no real depth or photo is drawn in it


def _thumb(arr: np.ndarray) -> np.ndarray:
  stride = max(1, int(np.ceil(max(arr.shape[:2]) / THUMB_PX)))
  return arr[::stride, ::stride]


def describe(scene: Scene) -> list[str]:
  """Human-readable lines about the scene's contents."""
  u = scene.units
  lines = [f"scene {scene.name!r}: layout {scene.source.get('layout', 'native')}, units {u}, "
           f"{len(scene.wli)} WLI scans, {len(scene.om)} OM photos, "
           f"{'posed' if scene.posed else 'not posed (run `python -m ofjax.associate`)'}"]
  for s in scene.wli:
    h, w = s.shape
    valid = s.valid
    rng = (f"depth {np.nanmin(s.depth):.4g}..{np.nanmax(s.depth):.4g} {u}" if valid.any()
           else "no valid depth")
    lines.append(f"  wli {s.name}: {w}x{h} px, pixel {s.pixel_size[0]:.4g} x {s.pixel_size[1]:.4g}"
                 f" {u}, voids {100 * (1 - valid.mean()):.1f}%, {rng}, "
                 f"{'posed' if s.c2w is not None else 'no pose'}")
  for o in scene.om:
    h, w = o.shape
    k = "f unknown (SfM)" if o.K is None else f"f {o.K[0, 0]:.1f} px"
    lines.append(f"  om  {o.name}: {w}x{h} px, {k}, {'posed' if o.c2w is not None else 'no pose'}")
  return lines


def contact_sheet(scene: Scene, out: Path) -> None:
  """Writes a PNG grid of the WLI depth maps (voids magenta) and OM thumbnails to `out`."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  tiles = [(f"WLI {s.name}", _thumb(s.depth), True) for s in scene.wli]
  tiles += [(f"OM {o.name}", _thumb(o.image), False) for o in scene.om]
  cols = max(1, min(SHEET_COLS, len(tiles)))
  rows = max(1, int(np.ceil(len(tiles) / cols)))
  fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.6 * rows + 0.4), squeeze=False,
                           layout="constrained")
  cmap = plt.get_cmap("viridis").with_extremes(bad=VOID_RGB)
  for ax in axes.ravel():
    ax.axis("off")
  for ax, (title, arr, is_depth) in zip(axes.ravel(), tiles):
    if is_depth:
      ax.imshow(np.ma.masked_invalid(arr), cmap=cmap, interpolation="nearest")
      title += f" ({100 * np.mean(~np.isfinite(arr)):.0f}% void)"
    else:
      ax.imshow(arr, interpolation="nearest")
    ax.set_title(title, fontsize=8)
  fig.suptitle(f"{scene.name}: WLI depth ({scene.units}, magenta = void) and OM photos", fontsize=9)
  with fileio.atomic_path(out) as tmp:
    fig.savefig(tmp, dpi=100, format="png")
  plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python -m ofjax.inspect", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("path", metavar="SCENE_OR_DIR", help="scene folder in any layout")
  p.add_argument("--layout", choices=LAYOUTS, help="force a layout instead of detecting it")
  p.add_argument("--um-per-unit", type=float, metavar="F",
                 help="micrometres per layout unit (OpticFusion layout)")
  p.add_argument("--pixel-size", type=float, metavar="UM",
                 help="pixel size in um of plain .npy/.npz/.tif height maps (raw layout)")
  p.add_argument("--poses", metavar="JSON", help="poses.json to apply to the cameras")
  p.add_argument("--out", metavar="PNG", help="contact sheet path (default: ./<scene>_contact.png)")
  return p


@cli
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    scene = load(args.path, layout=args.layout, um_per_unit=args.um_per_unit, poses=args.poses,
                 pixel_size=args.pixel_size)
  for w in caught:
    if issubclass(w.category, UserWarning):
      print(f"ofjax: warning: {w.message}", file=sys.stderr)
  print("\n".join(describe(scene)))
  out = Path(args.out) if args.out else Path(f"{scene.name}_contact.png")
  contact_sheet(scene, out)
  print(f"contact sheet: {out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
