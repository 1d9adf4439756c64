"""WLI height maps from instrument files, and their conversion to ofjax's orthographic depth.

Readers, picked by the file's content first (magic bytes) and its extension second:
  HDF5 (.datx)          Zygo Mx .datx through h5py (ofjax.io.datx).
  surfalize formats     .x3p .sur .sdf .plu .plux .opd .vk3/.vk4/.vk6/.vk7 .gwy .al3d .os3d .zmg
                        .nms .tmd .xyz .zon .lext .oir/.poir .hdat .sflz .fits and Zygo MetroPro
                        .dat, through `surfalize.Surface.load`: heights and steps in um, voids NaN.
  .npy / .npz / .tif(f) plain arrays of heights in um (npz: the array `height`, `z` or `data`, or
                        its only array); the pixel size is not in the file and must be given
                        (`pixel_size=`, CLI `--pixel-size UM`).

A height map is `HeightMap.height`: [H, W] float64 um, NaN = void; row r, column c is the sample
at x = c * sx, y = r * sy in the instrument's frame as the file stores it (row 0 first). Where the
file also holds the instrument's intensity image on the same pixels (.datx /Data/Intensity, an
.npz array `intensity`), it is `HeightMap.intensity` ([H, W] float64, NaN = not recorded) and
becomes the scan's `intensity` (ofjax.associate anchors the photos on it); one of another shape
is left out.

Height -> depth (`to_scan`): the WLI looks straight down at the sample. ofjax's orthographic camera
(scene.py) measures `depth` along its viewing axis from its image plane, so the scan becomes
    depth = datum - height,        datum = the highest valid height of the map,
stored with the prior {"height_datum_um": datum}. The plane then touches the highest point and
every depth is >= 0. With the camera-to-world `height_c2w(scan)` = [[1, 0, 0, 0], [0, -1, 0, 0],
[0, 0, -1, datum], [0, 0, 0, 1]] (diag(1, -1, -1, 1) lifted to the datum) a pixel's world point
has z = the instrument's height exactly, x growing with the column and y shrinking with the row
(row 0 at the top, as the instrument displays it). With diag(1, -1, -1, 1) itself world z is
height - datum.
"""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ofjax.errors import UserError
from ofjax.scene import WLIScan

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK\x03\x04"
TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
PLAIN_EXTENSIONS = (".npy", ".npz", ".tif", ".tiff")
NPZ_HEIGHT_KEYS = ("height", "z", "data")
MIN_SIZE = 2  # a map needs at least 2 x 2 pixels to have a lateral extent
DATUM_KEY = "height_datum_um"
FORMATS_HINT = (".datx, a surfalize format (.x3p .sur .plu .opd .dat .vk4 .gwy ...) or a plain "
                ".npy/.npz/.tif height map")


@dataclasses.dataclass
class HeightMap:
  """One WLI measurement as the instrument gives it."""
  height: np.ndarray  # [H, W] float64 um, NaN = void
  pixel_size: tuple[float, float]  # (sx, sy) um per pixel along columns and rows
  source: dict[str, Any]  # file, format, units seen in the file
  intensity: np.ndarray | None = None  # [H, W] float64 intensity image on the same pixels, or None


def same_pixels(intensity, height: np.ndarray) -> np.ndarray | None:
  """The intensity image as [H, W] float64 (non-finite -> NaN) if it is numeric, on the height
  map's pixels and not empty; else None (the heights are read either way)."""
  if intensity is None:
    return None
  arr = np.asarray(intensity)
  if arr.shape != height.shape or not (np.issubdtype(arr.dtype, np.floating)
                                       or np.issubdtype(arr.dtype, np.integer)):
    return None
  arr = arr.astype(np.float64)
  arr[~np.isfinite(arr)] = np.nan
  return arr if np.isfinite(arr).any() else None


def surfalize_extensions() -> tuple[str, ...]:
  import surfalize.file
  return tuple(sorted(surfalize.file.supported_formats_read))


def _magic(path: Path) -> bytes:
  with open(path, "rb") as fh:
    return fh.read(8)


def check_pixel_size(pixel_size, what: str = "--pixel-size") -> tuple[float, float]:
  """(sx, sy) um from a number or a pair; positive and finite, or a UserError naming `what`."""
  vals = np.atleast_1d(np.asarray(pixel_size, dtype=object))
  try:
    vals = np.asarray(vals, np.float64)
  except (TypeError, ValueError):
    raise UserError(f"{what}: {pixel_size!r} is not a number; give the pixel size in um") from None
  if vals.shape not in ((1,), (2,)) or not np.all(np.isfinite(vals)) or np.any(vals <= 0):
    raise UserError(f"{what}: {pixel_size!r} is not a positive finite pixel size; give the "
                    "pixel size in um, e.g. --pixel-size 0.8")
  return (float(vals[0]), float(vals[-1]))


def validate_height(path: Path, height: np.ndarray, what: str = "height map") -> np.ndarray:
  """[H, W] float64 with voids as NaN, or a UserError naming `path` and what is wrong."""
  height = np.asarray(height)
  if height.ndim != 2 or min(height.shape) < MIN_SIZE:
    raise UserError(f"{path}: the {what} has shape {height.shape}, not a 2-D map of at least "
                    f"{MIN_SIZE}x{MIN_SIZE} pixels; export the measurement as one map")
  if height.dtype == bool or not (np.issubdtype(height.dtype, np.floating)
                                  or np.issubdtype(height.dtype, np.integer)):
    raise UserError(f"{path}: the {what} has type {height.dtype}, not numbers; export it as "
                    "floating-point values")
  height = height.astype(np.float64)
  height[~np.isfinite(height)] = np.nan
  valid = np.isfinite(height)
  if not valid.any():
    raise UserError(f"{path}: every pixel is a void (nothing was measured); re-measure or remove "
                    "the file")
  if np.ptp(height[valid]) == 0:
    raise UserError(f"{path}: every measured value is {height[valid][0]:g}, a constant {what} "
                    "(a failed export?); re-export the measurement or remove the file")
  return height


def _read_surfalize(path: Path) -> HeightMap:
  import surfalize
  try:
    surf = surfalize.Surface.load(path)
  except Exception as e:  # noqa: BLE001 - surfalize raises many kinds on corrupt files
    raise UserError(f"{path}: surfalize cannot read it ({type(e).__name__}: {e}); check that "
                    "the file is complete and in the format its extension says") from None
  sx, sy = check_pixel_size((surf.step_x, surf.step_y), f"{path}: lateral step")
  height = validate_height(path, np.array(surf.data, np.float64))
  return HeightMap(height, (sx, sy), {"file": str(path), "format": path.suffix.lower().lstrip("."),
                                      "reader": "surfalize", "units": "um"})


def _read_plain(path: Path, kind: str, pixel_size) -> HeightMap:
  if pixel_size is None:
    raise UserError(f"{path}: a plain {kind} height map does not say its pixel size; pass "
                    "--pixel-size UM (pixel_size= in Python)")
  sx, sy = check_pixel_size(pixel_size)
  try:
    if kind == "tif":
      import tifffile
      arr = tifffile.imread(path)
    elif kind == "npy":
      arr = np.load(path, allow_pickle=False)
    else:
      with np.load(path, allow_pickle=False) as z:
        keys = list(z.keys())
        key = next((k for k in NPZ_HEIGHT_KEYS if k in keys), keys[0] if len(keys) == 1 else None)
        if key is None:
          raise UserError(f"{path}: holds arrays {keys} but none named "
                          f"{' / '.join(NPZ_HEIGHT_KEYS)}; save the heights as `height`")
        arr = z[key]
        intensity = z["intensity"] if "intensity" in keys and key != "intensity" else None
  except UserError:
    raise
  except Exception as e:  # noqa: BLE001 - numpy / tifffile raise many kinds on corrupt files
    raise UserError(f"{path}: cannot read the {kind} height map ({type(e).__name__}); check that "
                    "the file is complete") from None
  height = validate_height(path, arr)
  return HeightMap(height, (sx, sy), {"file": str(path), "format": kind, "reader": "numpy",
                                      "units": "um (assumed)"},
                   same_pixels(intensity if kind == "npz" else None, height))


def read_height_map(path: str | Path, pixel_size=None) -> HeightMap:
  """Reads one WLI file of any supported format (see the module docstring)."""
  path = Path(path)
  if not path.is_file():
    raise UserError(f"{path}: WLI file not found; check the path")
  ext = path.suffix.lower()
  try:
    magic = _magic(path)
  except OSError as e:
    raise UserError(f"{path}: cannot open the WLI file ({e.strerror}); check its "
                    "permissions") from None
  if magic.startswith(HDF5_MAGIC):
    from ofjax.io import datx
    return datx.read_datx(path)
  if ext == ".datx":
    raise UserError(f"{path}: is not an HDF5 file, so not a Zygo .datx (truncated or "
                    "mislabelled?); re-export it from Mx")
  if magic.startswith(NPY_MAGIC) or ext == ".npy":
    return _read_plain(path, "npy", pixel_size)
  if ext == ".npz" or (magic.startswith(ZIP_MAGIC) and not ext and zipfile.is_zipfile(path)):
    return _read_plain(path, "npz", pixel_size)
  if any(magic.startswith(m) for m in TIFF_MAGICS) or ext in (".tif", ".tiff"):
    return _read_plain(path, "tif", pixel_size)
  if ext in surfalize_extensions():
    return _read_surfalize(path)
  raise UserError(f"{path}: unknown WLI file type {ext or '(no extension)'!r}; export the "
                  f"measurement as {FORMATS_HINT}")


def to_scan(name: str, hm: HeightMap) -> WLIScan:
  """The height map as an unposed orthographic WLI scan: depth = datum - height (module doc)."""
  datum = float(np.nanmax(hm.height))
  depth = (datum - hm.height).astype(np.float32)
  intensity = None if hm.intensity is None else hm.intensity.astype(np.float32)
  return WLIScan(name, depth, hm.pixel_size, prior={DATUM_KEY: datum}, intensity=intensity)


def height_c2w(scan: WLIScan) -> np.ndarray:
  """[4, 4] float64 camera-to-world (um) under which the scan's world z is the instrument height."""
  datum = (scan.prior or {}).get(DATUM_KEY, 0.0)
  return np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, datum], [0, 0, 0, 1]], np.float64)
