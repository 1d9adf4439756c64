"""Which layout a data folder is in, and `load`, the one entry point that reads any of them.

Layouts, tried in this order:
  native       DIR/scene.json                  ofjax's own bundle (ofjax.scene.load_scene), um
  opticfusion  DIR/wl/ and DIR/op/             the OpticFusion WLI-OM dataset (io.opticfusion)
  raw          DIR/wli/ or DIR/om/             instrument files and photos (io.raw)
"""

from __future__ import annotations

from pathlib import Path

from ofjax.errors import UserError
from ofjax.scene import Scene, apply_poses, load_poses, load_scene

LAYOUTS = ("native", "opticfusion", "raw")


def detect_layout(path: str | Path) -> str:
  """The layout name of the folder `path`, or a UserError saying what a layout looks like."""
  path = Path(path)
  if not path.exists():
    raise UserError(f"{path}: not found; give a scene folder")
  if not path.is_dir():
    raise UserError(f"{path}: is a file; give the scene folder that holds it")
  if (path / "scene.json").is_file():
    return "native"
  if (path / "wl").is_dir() and (path / "op").is_dir():
    return "opticfusion"
  if (path / "wli").is_dir() or (path / "om").is_dir():
    return "raw"
  raise UserError(f"{path}: unknown layout (no scene.json, no wl/ + op/, no wli/ + om/); see "
                  "`python -m ofjax.inspect --help` for the layouts, or pass --layout")


def load(path: str | Path, layout: str | None = None, um_per_unit: float | None = None,
         poses: str | Path | None | bool = None, pixel_size=None) -> Scene:
  """The Scene in folder `path`.

  Args:
    layout: one of LAYOUTS; None detects it.
    um_per_unit: micrometres per layout unit (opticfusion only; without it the Scene keeps the
      layout's unit and says so in `scene.units`).
    poses: a poses.json (scene.poses_to_json schema) applied after reading; for the native layout
      DIR/poses.json is applied when present unless `poses` is False.
    pixel_size: um per pixel (a number or (sx, sy)) for plain .npy/.npz/.tif height maps.
  """
  path = Path(path)
  if layout is None:
    layout = detect_layout(path)
  elif layout not in LAYOUTS:
    raise UserError(f"--layout: {layout!r} is not one of {', '.join(LAYOUTS)}")
  elif not path.is_dir():
    raise UserError(f"{path}: folder not found; give a scene folder")
  if um_per_unit is not None and layout != "opticfusion":
    raise UserError(f"--um-per-unit: the {layout} layout is already in micrometres; drop the "
                    "option")
  if pixel_size is not None and layout != "raw":
    raise UserError(f"--pixel-size: the {layout} layout stores its pixel sizes; drop the option")
  if layout == "native":
    return load_scene(path, poses)
  if layout == "opticfusion":
    from ofjax.io.opticfusion import load_opticfusion
    scene = load_opticfusion(path, um_per_unit)
  else:
    from ofjax.io.raw import load_raw
    scene = load_raw(path, pixel_size)
  if poses is not None and poses is not False:
    apply_poses(scene, load_poses(poses), poses)
  return scene
