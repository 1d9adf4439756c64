"""Zygo Mx .datx height maps through h5py (surfalize does not read .datx).

The structure read (as Zygo Mx writes it):
  /MetaData                   (optional) table of (Source, Link, Destination) strings; the path
                              Root -> "Measurement" -> "Surface" names the measured surface
                              (without it: the first surface that has a "Unit").
  /Data/Surface/<key>         [H, W] heights (float or int); attributes:
      "No Data"               [1]: values >= it are voids,
      "Unit"                  [1] bytes: "NanoMeters", "MicroMeters", "MilliMeters", "Meters",
                              "Angstroms", "Inches", "Mils", "MicroInches", "Fringes" or "Waves",
      "Wavelength"            [1] metres, "Interferometric Scale Factor" [1],
      "Obliquity Factor"      [1]:
                              for "Fringes" h = v * scale * obliquity * wavelength, for "Waves"
                              h = v * wavelength,
      "X Converter", "Y Converter"
                              [1] compound (Category, BaseUnit, Parameters): Parameters[1] is the
                              lateral step in BaseUnit (normally "Meters").
  /Data/Intensity/<key>       (optional) [H, W] the instrument's intensity image, "No Data" as
                              above; kept when it has the heights' shape (ofjax.io.wli).
  /Attributes/<key>           attributes "...Lateral Resolution:Value" ([1], metres unless
                              "...Lateral Resolution:Unit" says otherwise): the step when the
                              surface has no X/Y converter.
Rows are kept in the file's order (row 0 first); heights and steps are returned in um.

The file is read in a child process (`python -m ofjax.io.datx FILE OUT.npz`, about 0.3 s each):
HDF5 dereferences the variable-length strings and arrays of the converter attributes and the
MetaData table through heap addresses stored in the file, and on a damaged file it can crash the
process (a segfault) instead of raising. In a child, a crash becomes a one-line UserError.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ofjax.errors import UserError
from ofjax.io.wli import HeightMap, check_pixel_size, same_pixels, validate_height

UM_PER_UNIT = {"meters": 1e6, "millimeters": 1e3, "micrometers": 1.0, "microns": 1.0,
               "nanometers": 1e-3, "angstroms": 1e-4, "inches": 25400.0, "mils": 25.4,
               "microinches": 0.0254, "feet": 304800.0}
LATERAL_KEY = "Lateral Resolution:Value"
# A child still reading after this long is stuck on a damaged file (a valid map reads in < 1 s).
READ_TIMEOUT_S = 300.0


def _text(v) -> str:
  v = np.asarray(v).reshape(-1)[0] if np.ndim(v) else v
  return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _scalar(v) -> float:
  return float(np.asarray(v, np.float64).reshape(-1)[0])


def _surface_key(f, path: Path) -> str:
  """The measured surface's key under /Data/Surface: via /MetaData, else the only (first) one."""
  if "Data" not in f or "Surface" not in f["Data"] or len(f["Data"]["Surface"]) == 0:
    raise UserError(f"{path}: has no /Data/Surface height data (an intensity-only .datx?); "
                    "export the measurement with its surface from Mx")
  keys = list(f["Data"]["Surface"].keys())
  if "MetaData" in f:
    try:
      rows = [tuple(_text(r[k]) for k in ("Source", "Link", "Destination"))
              for r in f["MetaData"][()]]
      meas = [d for s, link, d in rows if s == "Root" and link == "Measurement"]
      surf = [d for s, link, d in rows if meas and s == meas[0] and link == "Surface"]
      if surf and surf[0].split("/")[-1] in keys:
        return surf[0].split("/")[-1]
    except (KeyError, ValueError, TypeError, IndexError):
      pass  # an unusual MetaData table: fall back to the first surface that has a unit
  with_unit = [k for k in keys if "Unit" in f["Data"]["Surface"][k].attrs]
  return (with_unit or keys)[0]


def _height_scale(attrs, path: Path) -> float:
  """um per stored height value."""
  unit = _text(attrs["Unit"]) if "Unit" in attrs else None
  if unit is None and "Z Converter" in attrs:
    unit = _text(attrs["Z Converter"][0]["BaseUnit"])
  if unit is None:
    raise UserError(f"{path}: the surface has no 'Unit' attribute, so its heights have no unit; "
                    "re-export it from Mx")
  key = unit.strip().lower()
  if key in UM_PER_UNIT:
    return UM_PER_UNIT[key]
  if key in ("fringes", "waves"):
    needed = ["Wavelength"] + ([] if key == "waves" else ["Interferometric Scale Factor",
                                                          "Obliquity Factor"])
    missing = [k for k in needed if k not in attrs]
    if missing:
      raise UserError(f"{path}: heights are in {unit} but the attribute {missing[0]!r} is missing; "
                      "re-export the surface in a length unit")
    return 1e6 * float(np.prod([_scalar(attrs[k]) for k in needed]))
  raise UserError(f"{path}: unknown height unit {unit!r}; re-export the surface in nanometres or "
                  "micrometres")


def _lateral_step(f, attrs, path: Path) -> tuple[float, float]:
  """(sx, sy) um from the surface's X/Y converters, else the file's lateral resolution."""
  steps = []
  for axis in ("X Converter", "Y Converter"):
    if axis in attrs:
      conv = attrs[axis][0]
      base = _text(conv["BaseUnit"]).strip().lower()
      if base in UM_PER_UNIT:
        steps.append(float(np.asarray(conv["Parameters"], np.float64)[1]) * UM_PER_UNIT[base])
  if len(steps) == 2:
    return check_pixel_size(steps, f"{path}: X/Y Converter step")
  for group in (f["Attributes"].values() if "Attributes" in f else []):
    for key, val in group.attrs.items():
      if key.endswith(LATERAL_KEY):
        unit_key = key[:-len("Value")] + "Unit"
        unit = _text(group.attrs[unit_key]).lower() if unit_key in group.attrs else "meters"
        step = _scalar(val) * UM_PER_UNIT.get(unit, np.nan)
        return check_pixel_size(step, f"{path}: {key}")
  raise UserError(f"{path}: no lateral resolution (no X/Y Converter, no '{LATERAL_KEY}' "
                  "attribute); re-export the measurement from Mx")


def _intensity(f) -> np.ndarray | None:
  """The first /Data/Intensity image as float64 with NaN where it has no data, or None."""
  try:
    group = f["Data"].get("Intensity") if "Data" in f else None
    if group is None or not hasattr(group, "keys") or len(group) == 0:
      return None
    ds = group[next(iter(group.keys()))]
    arr = np.asarray(ds[()], np.float64)
    if "No Data" in ds.attrs:
      arr[arr >= _scalar(ds.attrs["No Data"])] = np.nan
    return arr
  except (KeyError, ValueError, TypeError, OSError):
    return None  # the intensity is optional: a damaged one leaves the heights as they are


def _read_here(path: Path) -> tuple[np.ndarray, tuple[float, float], str, str, np.ndarray | None]:
  """(heights in um with NaN voids, (sx, sy) um, height unit, surface key, intensity image or
  None), in this process."""
  import h5py
  try:
    with h5py.File(path, "r") as f:
      key = _surface_key(f, path)
      ds = f["Data"]["Surface"][key]
      attrs = ds.attrs
      raw = np.asarray(ds[()], np.float64)
      no_data = _scalar(attrs["No Data"]) if "No Data" in attrs else np.inf
      scale = _height_scale(attrs, path)
      unit = _text(attrs["Unit"]) if "Unit" in attrs else "?"
      step = _lateral_step(f, attrs, path)
      intensity = _intensity(f)
  except UserError:
    raise
  except Exception as e:  # noqa: BLE001 - h5py raises OSError/KeyError/... on damaged files
    raise UserError(f"{path}: cannot read the .datx file ({type(e).__name__}: {e}); check that "
                    "it is complete (re-copy or re-export it)") from None
  if raw.ndim != 2:
    raise UserError(f"{path}: surface {key!r} has shape {raw.shape}, not a 2-D map; export a "
                    "single height map")
  raw[raw >= no_data] = np.nan
  return raw * scale, step, unit, key, intensity


def _crash_reason(returncode: int, stderr: str) -> str:
  """Why the reading child failed without a UserError: the signal that killed it, else its exit
  code and last line of stderr (an exception h5py raised outside the reader's own handling)."""
  if returncode < 0:
    try:
      return f"the HDF5 library crashed on it: {signal.Signals(-returncode).name}"
    except ValueError:
      pass
  last = stderr.strip().splitlines()[-1:] or ["no message"]
  return f"the reader exited with code {returncode}: {last[0]}"


def read_datx(path: str | Path) -> HeightMap:
  """Heights (um, NaN voids) and lateral step (um) of a Zygo .datx file, read in a child."""
  path = Path(path)
  with tempfile.TemporaryDirectory(prefix="ofjax-datx-") as tmp:
    out = Path(tmp) / "map.npz"
    # The child imports this very ofjax, wherever the parent found it.
    paths = [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in paths if p))
    try:
      child = subprocess.run([sys.executable, "-m", "ofjax.io.datx", str(path), str(out)],
                             capture_output=True, text=True, timeout=READ_TIMEOUT_S, env=env)
    except subprocess.TimeoutExpired:
      raise UserError(f"{path}: reading the .datx file took over {READ_TIMEOUT_S:.0f} s (a "
                      "damaged file?); re-copy or re-export it") from None
    if child.returncode == 2 and child.stderr.strip():
      raise UserError(child.stderr.strip().splitlines()[-1].removeprefix("ofjax: error: "))
    if child.returncode != 0 or not out.exists():
      reason = _crash_reason(child.returncode, child.stderr)
      raise UserError(f"{path}: cannot read the .datx file ({reason}); check that it is complete "
                      "(re-copy or re-export it)")
    with np.load(out) as z:
      height, step = z["height"], tuple(float(v) for v in z["step"])
      meta = json.loads(str(z["meta"]))
      intensity = z["intensity"] if "intensity" in z.files else None
  height = validate_height(path, height)
  return HeightMap(height, step, {"file": str(path), "format": "datx", "reader": "h5py",
                                  "units": meta["unit"], "surface": meta["key"]},
                   same_pixels(intensity, height))


def _child_main(argv: list[str]) -> None:
  """`python -m ofjax.io.datx FILE OUT.npz`: the read that read_datx runs in a child."""
  path, out = Path(argv[0]), Path(argv[1])
  height, step, unit, key, intensity = _read_here(path)
  extra = {} if intensity is None else {"intensity": intensity}
  np.savez(out, height=height, step=np.asarray(step, np.float64),
           meta=np.asarray(json.dumps({"unit": unit, "key": key})), **extra)


if __name__ == "__main__":
  from ofjax.errors import cli
  sys.exit(cli(_child_main)(sys.argv[1:]))
