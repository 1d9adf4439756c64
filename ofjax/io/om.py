"""Optical-microscope photos: PNG / JPEG / TIFF, 8 or 16 bit, -> RGB float32 in [0, 1].

Conventions:
  image     [H, W, 3] float32 RGB in [0, 1], rows top to bottom as the photo is meant to be seen:
            the EXIF orientation tag is applied (PIL.ImageOps.exif_transpose), so a camera that
            stored a portrait photo sideways gives an upright array.
  K         [3, 3] pinhole intrinsics in pixels with ofjax's pixel-centre model (scene.py): pixel
            (u, v) has its centre at (u + 0.5, v + 0.5); the principal point is the image centre
            (W / 2, H / 2) when only EXIF is known.
  16 bit    PNG files of 16 bits per channel are read with pypng (Pillow truncates 16-bit RGB PNG
            to 8 bits); 16-bit TIFF with tifffile; 16-bit greyscale becomes grey RGB.

Intrinsics come from, in this order: the Scene (bundle / poses), the photo's EXIF focal length
(FocalLength in mm with FocalPlaneXResolution / FocalPlaneYResolution, else FocalLengthIn35mmFilm),
or stay None so that structure-from-motion estimates them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ofjax.errors import UserError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
EXIF_ORIENTATION = 0x0112
EXIF_IFD = 0x8769
EXIF_FOCAL_LENGTH = 0x920A
EXIF_FOCAL_35MM = 0xA405
EXIF_FOCAL_PLANE_XRES = 0xA20E
EXIF_FOCAL_PLANE_YRES = 0xA20F
EXIF_FOCAL_PLANE_UNIT = 0xA210
MM_PER_FOCAL_PLANE_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # EXIF: 2 inch, 3 cm, (4 mm, 5 um)
FILM_35MM_DIAGONAL_MM = float(np.hypot(36.0, 24.0))  # CIPA DC-004: equivalence by the diagonal
TRANSPOSING_ORIENTATIONS = (5, 6, 7, 8)  # EXIF orientations that swap width and height


def _fail(path: Path, what: str) -> UserError:
  return UserError(f"{path}: {what}; replace the photo or remove it from the folder")


def _scale_to_unit(arr: np.ndarray, path: Path) -> np.ndarray:
  """[H, W, 3] float32 in [0, 1] from an integer or float array of 1, 3 or 4 channels."""
  if arr.ndim == 2:
    arr = arr[..., None]
  if arr.ndim != 3 or arr.shape[-1] not in (1, 2, 3, 4):
    raise _fail(path, f"has shape {arr.shape}, not a greyscale or RGB image")
  if arr.shape[-1] in (2, 4):  # drop alpha: the photo's colour is what the loss sees
    arr = arr[..., :-1]
  if arr.shape[-1] == 1:
    arr = np.repeat(arr, 3, axis=-1)
  if np.issubdtype(arr.dtype, np.integer):
    return (arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max))
  if np.issubdtype(arr.dtype, np.floating):
    out = arr.astype(np.float32)
    if not np.all(np.isfinite(out)) or out.min() < 0 or out.max() > 1:
      raise _fail(path, "is a floating-point image with values outside [0, 1]")
    return out
  raise _fail(path, f"has pixel type {arr.dtype}, not 8/16-bit integer or float")


def _read_png16(path: Path) -> np.ndarray | None:
  """The pixels of a 16-bit PNG through pypng, or None when the PNG has 8 bits or fewer."""
  import png
  with open(path, "rb") as fh:
    reader = png.Reader(file=fh)
    reader.preamble()
    if reader.bitdepth != 16:
      return None
    width, height, rows, info = reader.asDirect()
    arr = np.vstack([np.asarray(r, np.uint16) for r in rows])
  return arr.reshape(height, width, info["planes"])


def _orientation(im) -> int:
  try:
    return int(im.getexif().get(EXIF_ORIENTATION, 1))
  except Exception:  # noqa: BLE001 - a malformed EXIF block must not make the photo unreadable
    return 1


def _apply_orientation(arr: np.ndarray, orientation: int) -> np.ndarray:
  """The array turned as EXIF orientation 1..8 asks (the same as PIL.ImageOps.exif_transpose)."""
  ops = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
         5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
         7: lambda a: np.swapaxes(a, 0, 1)[::-1, ::-1], 8: lambda a: np.rot90(a, 1)}
  return np.ascontiguousarray(ops[orientation](arr)) if orientation in ops else arr


def read_image(path: str | Path) -> np.ndarray:
  """[H, W, 3] float32 RGB in [0, 1] from a PNG, JPEG or TIFF photo, EXIF orientation applied."""
  from PIL import Image, ImageOps
  path = Path(path)
  if not path.is_file():
    raise UserError(f"{path}: photo not found; check the path")
  try:
    with Image.open(path) as im:
      fmt, orientation = im.format, _orientation(im)
      if fmt == "PNG":
        arr = _read_png16(path)
        if arr is not None:
          return _scale_to_unit(_apply_orientation(arr, orientation), path)
      if fmt == "TIFF":
        import tifffile
        arr = tifffile.imread(path)
        return _scale_to_unit(_apply_orientation(arr, orientation), path)
      im = ImageOps.exif_transpose(im)
      im.load()
      if im.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        arr = np.asarray(im)
        if im.mode == "I":  # PIL widens 16-bit greyscale to 32-bit "I"; its range is 16 bits
          arr = arr.astype(np.uint16)
        return _scale_to_unit(arr, path)
      return _scale_to_unit(np.asarray(im.convert("RGB")), path)
  except UserError:
    raise
  except Exception as e:  # noqa: BLE001 - PIL / pypng / tifffile raise many kinds on corrupt files
    raise _fail(path, f"cannot be read as an image ({type(e).__name__}: {e})") from None


def _rational(v) -> float | None:
  try:
    f = float(v)
  except (TypeError, ValueError, ZeroDivisionError):
    return None
  return f if np.isfinite(f) and f > 0 else None


def exif_intrinsics(path: str | Path, shape: tuple[int, int]) -> np.ndarray | None:
  """[3, 3] K in pixels from the photo's EXIF focal length, or None when EXIF does not say.

  Args:
    path: the photo.
    shape: (H, W) of the photo as read by `read_image` (orientation already applied).
  """
  from PIL import Image
  h, w = shape
  try:
    with Image.open(path) as im:
      exif = im.getexif()
      sub = exif.get_ifd(EXIF_IFD)
  except Exception:  # noqa: BLE001 - no or broken EXIF: intrinsics are then left to SfM
    return None
  tags = {**dict(exif), **dict(sub)}
  swap = int(tags.get(EXIF_ORIENTATION, 1)) in TRANSPOSING_ORIENTATIONS
  f_mm = _rational(tags.get(EXIF_FOCAL_LENGTH))
  xres = _rational(tags.get(EXIF_FOCAL_PLANE_XRES))
  unit_mm = MM_PER_FOCAL_PLANE_UNIT.get(int(tags.get(EXIF_FOCAL_PLANE_UNIT, 2) or 2))
  fx = fy = None
  if f_mm is not None and xres is not None and unit_mm is not None:
    yres = _rational(tags.get(EXIF_FOCAL_PLANE_YRES)) or xres
    # The focal-plane resolutions are along the sensor's axes; a transposing orientation swaps them.
    fx, fy = f_mm * xres / unit_mm, f_mm * yres / unit_mm
    if swap:
      fx, fy = fy, fx
  else:
    f35 = _rational(tags.get(EXIF_FOCAL_35MM))
    if f35 is None:
      return None
    fx = fy = f35 * float(np.hypot(w, h)) / FILM_35MM_DIAGONAL_MM
  return np.array([[fx, 0, w / 2], [0, fy, h / 2], [0, 0, 1]], np.float64)


def check_same_size(paths: list[Path], images: list[np.ndarray]) -> None:
  """Raises a UserError naming the first photo whose size differs from the first one's."""
  for p, im in zip(paths[1:], images[1:]):
    if im.shape[:2] != images[0].shape[:2]:
      raise UserError(f"{p}: photo is {im.shape[1]}x{im.shape[0]} but {paths[0].name} is "
                      f"{images[0].shape[1]}x{images[0].shape[0]}; all photos of a scene must "
                      "have one size (resize or remove the odd one)")


def list_photos(directory: Path) -> list[Path]:
  """The photos in `directory`, sorted by name (hidden files skipped)."""
  return sorted(p for p in directory.iterdir() if p.is_file()
                and p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith("."))
