"""The "raw" layout: a folder of files straight from the instruments.

  <dir>/wli/<name>.<ext>   WLI measurements, one per file, any format io.wli reads (.datx, .x3p,
                           .sur, .plu, .opd, .dat, .vk4, .gwy, ... and plain .npy/.npz/.tif height
                           maps in um, which need `pixel_size`); every visible file there must be
                           one (a stray file is a UserError naming it)
  <dir>/om/<name>.<ext>    OM photos (.png .jpg .jpeg .tif .tiff), all of one size
  <dir>/poses.json         (optional) camera poses in ofjax's poses schema (scene.poses_to_json)

Files are taken in name order; a camera's name is its file stem (so two files may not share a
stem). Heights become depths as io.wli documents (depth = datum - height, unposed); photo
intrinsics come from EXIF when it has a focal length, else stay None for SfM. Everything is in um.
"""

from __future__ import annotations

from pathlib import Path

from ofjax.errors import UserError
from ofjax.io import om, wli
from ofjax.scene import OMImage, Scene

WLI_DIR = "wli"
OM_DIR = "om"


def _unique_stems(paths: list[Path]) -> None:
  seen = {}
  for p in paths:
    if p.stem in seen:
      raise UserError(f"{p}: has the same name as {seen[p.stem].name}; camera names come from file "
                      "stems, rename one of them")
    seen[p.stem] = p


def list_wli_files(directory: Path) -> list[Path]:
  """Every visible file in `directory`: each must be a WLI file (io.wli says which it is not)."""
  return sorted(p for p in directory.iterdir() if p.is_file() and not p.name.startswith("."))


def load_raw(directory: str | Path, pixel_size=None) -> Scene:
  """The unposed Scene of a raw instrument folder (module docstring)."""
  directory = Path(directory)
  for sub, what in ((WLI_DIR, "WLI measurements"), (OM_DIR, "OM photos")):
    if not (directory / sub).is_dir():
      raise UserError(f"{directory / sub}: folder not found; a raw scene keeps its {what} in "
                      f"{directory}/{sub}/")
  wli_files = list_wli_files(directory / WLI_DIR)
  if not wli_files:
    raise UserError(f"{directory / WLI_DIR}: no WLI files; put the measurements there as "
                    f"{wli.FORMATS_HINT}")
  photos = om.list_photos(directory / OM_DIR)
  if not photos:
    raise UserError(f"{directory / OM_DIR}: no photos; put the OM photos there as "
                    f"{' / '.join(om.IMAGE_EXTENSIONS)}")
  _unique_stems(wli_files)
  _unique_stems(photos)
  maps = [wli.read_height_map(p, pixel_size) for p in wli_files]
  scans = [wli.to_scan(p.stem, m) for p, m in zip(wli_files, maps)]
  images = [om.read_image(p) for p in photos]
  om.check_same_size(photos, images)
  oms = [OMImage(p.stem, im, om.exif_intrinsics(p, im.shape[:2])) for p, im in zip(photos, images)]
  return Scene(scans, oms, name=directory.name, units="um",
               source={"layout": "raw", "path": str(directory.resolve()),
                       "wli": [m.source for m in maps]})
