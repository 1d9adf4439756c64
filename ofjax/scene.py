"""The Scene: ofjax's one in-memory form of a sample's data, and its native on-disk bundle.

Names used throughout ofjax:
  um        micrometres, the unit of every coordinate a user sees.
  c2w       [4, 4] camera-to-world matrix, OpenCV axes (x right, y down, z forward), in um.
  WLI scan  an orthographic camera: pixel (row r, col c) has origin
              c2w[:3, 3] + c2w[:3, :3] @ ((c + 0.5 - W / 2) * sx, (r + 0.5 - H / 2) * sy, 0)
            and direction c2w[:3, 2]; `depth` is the distance along that direction (um),
            NaN where the instrument measured nothing (a void).
  OM photo  a pinhole camera with intrinsics K (pixels); pixel (u, v) has its centre at
            (u + 0.5, v + 0.5), ray direction c2w[:3, :3] @ K^-1 (u + 0.5, v + 0.5, 1).
  normalisation  x_norm = (x_um - center) / scale maps the observed region into [-1, 1]^3.

On disk (format "ofjax-scene", version 1), a scene directory holds
  scene.json            what is in the bundle: units, source, per-scan pixel size and acquisition
                        prior, per-photo intrinsics and stage prior (both optional),
                        normalisation (optional)
  wli/<name>.npz        `depth`: [H, W] float32 um along the axis, NaN = void; optionally
                        `intensity`: [H, W] float32, the instrument's intensity image on the
                        same pixels (any linear unit, NaN = not recorded)
  om/<name>.png         RGB photo, 8 or 16 bit
  poses.json            (optional) camera-to-world of every camera; see `poses_to_json`
  ground_truth/         (synthetic scenes only) mesh.ply, surface_points.ply, poses.json
Every file is written atomically; scene.json is written last.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from ofjax import fileio
from ofjax.errors import UserError

FORMAT = "ofjax-scene"
VERSION = 1
POSES_FORMAT = "ofjax-poses"


@dataclasses.dataclass
class WLIScan:
  """One WLI measurement as an orthographic depth map."""
  name: str  # unique within the scene, e.g. "0000"
  depth: np.ndarray  # [H, W] float32, um along the viewing axis, NaN = void
  pixel_size: tuple[float, float]  # (sx, sy): um per pixel along columns and rows
  c2w: np.ndarray | None = None  # [4, 4] float64 camera-to-world in um, None until associated
  prior: dict[str, float] | None = None  # acquisition prior, e.g. {"tilt_deg": 30, "azimuth_deg": 90}
  # [H, W] float32 intensity image the instrument recorded with the heights, pixel for pixel (any
  # linear unit, NaN = not recorded), or None; ofjax.associate anchors the photos on its texture.
  intensity: np.ndarray | None = None

  @property
  def valid(self) -> np.ndarray:
    """[H, W] bool: where the WLI measured a depth."""
    return np.isfinite(self.depth)

  @property
  def shape(self) -> tuple[int, int]:
    return tuple(self.depth.shape)


@dataclasses.dataclass
class OMImage:
  """One optical-microscope photo as a pinhole camera."""
  name: str  # unique within the scene, e.g. "0000"
  image: np.ndarray  # [H, W, 3] float32 RGB in [0, 1]
  K: np.ndarray | None = None  # [3, 3] intrinsics in pixels, None until known (EXIF or SfM)
  c2w: np.ndarray | None = None  # [4, 4] float64 camera-to-world in um, None until associated
  # The stage's acquisition prior, as WLIScan.prior ({"tilt_deg", "azimuth_deg"} in the WLI
  # scans' sample frame); ofjax.associate uses it only to choose between turns that fit equally.
  prior: dict[str, float] | None = None

  @property
  def shape(self) -> tuple[int, int]:
    return tuple(self.image.shape[:2])


@dataclasses.dataclass(frozen=True)
class Normalization:
  """The similarity x_norm = (x_um - center) / scale into the training box [-1, 1]^3."""
  center: tuple[float, float, float]  # um
  scale: float  # um per normalised unit

  def to_norm(self, x: np.ndarray) -> np.ndarray:
    return (np.asarray(x) - np.asarray(self.center)) / self.scale

  def to_um(self, x: np.ndarray) -> np.ndarray:
    return np.asarray(x) * self.scale + np.asarray(self.center)


@dataclasses.dataclass
class Scene:
  """WLI scans + OM photos of one sample, in micrometres."""
  wli: list[WLIScan]
  om: list[OMImage]
  name: str = "scene"
  units: str = "um"  # "um", or the layout's own unit when no um-per-unit factor was given
  source: dict[str, Any] = dataclasses.field(default_factory=dict)  # where the data came from
  normalization: Normalization | None = None

  @property
  def posed(self) -> bool:
    return all(s.c2w is not None for s in self.wli) and all(
        o.c2w is not None and o.K is not None for o in self.om)

  def wli_points(self, stride: int = 1) -> np.ndarray:
    """[N, 3] float64: every valid WLI depth back-projected into the world (um)."""
    pts = []
    for s in self.wli:
      if s.c2w is None:
        raise UserError(f"WLI scan {s.name!r} has no pose; run `python -m ofjax.associate` first")
      pts.append(wli_points(s, stride))
    return np.concatenate(pts, axis=0) if pts else np.zeros((0, 3))


def wli_rays(scan: WLIScan, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
  """Origins and directions of a WLI scan's pixels.

  Returns:
    origins: [H', W', 3] float64 um.
    dirs: [H', W', 3] float64, unit.
  """
  h, w = scan.shape
  sx, sy = scan.pixel_size
  rows, cols = np.meshgrid(np.arange(0, h, stride), np.arange(0, w, stride), indexing="ij")
  local = np.stack([(cols + 0.5 - w / 2) * sx, (rows + 0.5 - h / 2) * sy, np.zeros_like(cols,
                                                                                   float)], -1)
  rot, t = scan.c2w[:3, :3], scan.c2w[:3, 3]
  origins = local @ rot.T + t
  dirs = np.broadcast_to(rot[:, 2] / np.linalg.norm(rot[:, 2]), origins.shape)
  return origins, dirs


def wli_points(scan: WLIScan, stride: int = 1) -> np.ndarray:
  """[N, 3] float64 um: the valid depths of one scan back-projected with its pose."""
  o, d = wli_rays(scan, stride)
  depth = scan.depth[::stride, ::stride].astype(np.float64)
  ok = np.isfinite(depth)
  return o[ok] + d[ok] * depth[ok][:, None]


def om_rays(image: OMImage, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
  """Origins [H', W', 3] and unit directions [H', W', 3] (float64, um) of a photo's pixels."""
  h, w = image.shape
  v, u = np.meshgrid(np.arange(0, h, stride), np.arange(0, w, stride), indexing="ij")
  pix = np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)], -1)
  cam = pix @ np.linalg.inv(image.K).T
  d = cam @ image.c2w[:3, :3].T
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  o = np.broadcast_to(image.c2w[:3, 3], d.shape)
  return o, d


def project_orthographic(points: np.ndarray, c2w: np.ndarray, pixel_size: tuple[float, float],
                         shape: tuple[int, int]
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """Where points land in an orthographic (WLI) scan: `wli_rays` inverted.

  Args:
    points: [N, 3] um.
    c2w: [4, 4] the scan's camera-to-world; pixel_size: (sx, sy) um; shape: (H, W).
  Returns:
    col, row: [N] continuous coordinates (pixel (c, r) spans [c, c + 1) x [r, r + 1)).
    z: [N] um along the scan's axis from its image plane (what `depth` measures).
    inside: [N] bool, inside the frame.
  """
  rot, t = c2w[:3, :3], c2w[:3, 3]
  local = (points - t) @ (rot / np.linalg.norm(rot, axis=0))  # camera axes; z along the view
  (h, w), (sx, sy) = shape, pixel_size
  col, row = local[:, 0] / sx + w / 2, local[:, 1] / sy + h / 2
  inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)  # NaN compares False
  return col, row, local[:, 2], inside


def project_pinhole(points: np.ndarray, K: np.ndarray, c2w: np.ndarray, shape: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Where points land in a pinhole (OM) photo.

  Args:
    points: [N, 3] um.
    K: [3, 3] intrinsics (pixel centres at +0.5, as `om_rays`).
    c2w: [4, 4] camera-to-world.
    shape: (H, W) of the photo.
  Returns:
    u, v: [N] column and row coordinates (pixel (c, r) spans [c, c + 1) x [r, r + 1)); NaN or inf
      for points in the camera's plane.
    inside: [N] bool, in front of the camera and inside the frame.
  """
  w2c = np.linalg.inv(c2w)
  cam = points @ w2c[:3, :3].T + w2c[:3, 3]
  uvw = cam @ K.T
  with np.errstate(divide="ignore", invalid="ignore"):
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
  h, w = shape
  inside = (cam[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)  # NaN compares False
  return u, v, inside


def compute_normalization(scene: Scene, margin: float = 0.05) -> Normalization:
  """The similarity that maps the posed WLI points' bounding box, grown by `margin`, into [-1, 1]^3."""
  pts = scene.wli_points(stride=4)
  if len(pts) == 0:
    raise UserError("the scene has no valid WLI depth: every scan is void; check the WLI files")
  lo, hi = pts.min(0), pts.max(0)
  center = (lo + hi) / 2
  scale = float(np.max(hi - lo) / 2 * (1 + margin))
  return Normalization(tuple(float(c) for c in center), scale)


# ----------------------------------------------------------------------------------------- poses


def intrinsics_to_json(cam: WLIScan | OMImage) -> dict[str, Any]:
  if isinstance(cam, WLIScan):
    return {"model": "orthographic", "pixel_size": [float(v) for v in cam.pixel_size]}
  k = cam.K
  return {"model": "pinhole", "fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]),
          "cy": float(k[1, 2])}


def K_from_json(d: dict[str, Any]) -> np.ndarray:
  fx, fy = numbers([d["fx"], d["fy"]], 2, "focal length", positive=True)
  cx, cy = numbers([d["cx"], d["cy"]], 2, "principal point")
  return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


# Mistakes in a JSON file's structure (a field missing, or of the wrong type or size).
MALFORMED = (KeyError, TypeError, ValueError, AttributeError, IndexError)


def numbers(value, n: int, what: str, positive: bool = False) -> tuple[float, ...]:
  """`value` as n finite floats (positive ones with `positive`), else a ValueError naming `what`."""
  if isinstance(value, (str, bytes, dict)) or np.shape(value) != (n,):
    raise ValueError(f"{what} is {value!r}, not {n} numbers")
  vals = tuple(float(v) for v in value)
  if not all(np.isfinite(vals)) or (positive and min(vals) <= 0):
    kind = "finite positive" if positive else "finite"
    raise ValueError(f"{what} is {value!r}, not {n} {kind} numbers")
  return vals


@contextlib.contextmanager
def json_fields(path, fix: str):
  """Turns a MALFORMED error while reading the fields of the JSON file `path` into a UserError."""
  try:
    yield
  except MALFORMED as e:
    detail = (str(e).splitlines() or [""])[0]
    raise UserError(f"{path}: a field is missing or malformed ({type(e).__name__}: {detail}); "
                    f"{fix}") from None


def camera_key(modality: str, name: str) -> str:
  return f"{modality}/{name}"


def poses_to_json(scene: Scene) -> dict[str, Any]:
  """The poses file: for every posed camera its name, modality, size, intrinsics and c2w (um)."""
  cams = []
  for modality, items in (("wli", scene.wli), ("om", scene.om)):
    for cam in items:
      if cam.c2w is None or (modality == "om" and cam.K is None):
        continue
      h, w = cam.shape
      cams.append({"name": camera_key(modality, cam.name), "modality": modality, "width": w,
                   "height": h, "intrinsics": intrinsics_to_json(cam),
                   "c2w": np.asarray(cam.c2w, np.float64).tolist()})
  return {"format": POSES_FORMAT, "version": VERSION, "units": scene.units, "cameras": cams}


def apply_poses(scene: Scene, poses: dict[str, Any], path: str | Path = "poses.json") -> None:
  """Sets every camera's c2w (and OM intrinsics) from a poses file's contents, validating them."""
  with json_fields(path, "fix or regenerate the poses file"):
    by_name = {c.get("name"): c for c in poses.get("cameras", [])}
    for modality, items in (("wli", scene.wli), ("om", scene.om)):
      for cam in items:
        entry = by_name.get(camera_key(modality, cam.name))
        if entry is None:
          raise UserError(f"{path}: no pose for camera {camera_key(modality, cam.name)!r}; "
                          "re-run `python -m ofjax.associate` on this scene")
        c2w = np.asarray(entry.get("c2w"), np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
          raise UserError(f"{path}: camera {entry['name']!r} has a c2w that is not a finite 4x4 "
                          "matrix; fix or regenerate the poses file")
        if abs(np.linalg.det(c2w[:3, :3])) < 1e-12:
          raise UserError(f"{path}: camera {entry['name']!r} has a singular rotation; fix or "
                          "regenerate the poses file")
        cam.c2w = c2w
        if modality == "om":
          cam.K = K_from_json(entry["intrinsics"])


def load_poses(path: str | Path) -> dict[str, Any]:
  path = Path(path)
  if not path.is_file():
    raise UserError(f"{path}: poses file not found; run `python -m ofjax.associate SCENE_DIR` or "
                    "pass --poses SCENE_DIR/ground_truth/poses.json")
  try:
    d = json.loads(path.read_text())
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise UserError(f"{path}: not a valid poses JSON file ({e.msg if hasattr(e, 'msg') else e}); "
                    "regenerate it with `python -m ofjax.associate`") from None
  if not isinstance(d, dict) or not isinstance(d.get("cameras"), list):
    raise UserError(f"{path}: has no 'cameras' list; regenerate it with `python -m ofjax.associate`")
  return d


# ---------------------------------------------------------------------------------------- bundle


def save_png(path: Path, image: np.ndarray, bits: int = 8) -> None:
  """Writes image: [H, W, 3] in [0, 1] as an 8- or 16-bit RGB PNG, atomically."""
  from PIL import Image
  img = np.clip(image, 0.0, 1.0)
  if bits == 16:
    import png  # Pillow cannot write 16-bit RGB: it would keep only the high byte
    arr = np.round(img * 65535).astype(np.uint16)
    with fileio.atomic_path(path) as tmp:
      png.from_array(arr.reshape(arr.shape[0], -1), "RGB;16").save(str(tmp))
    return
  pil = Image.fromarray(np.round(img * 255).astype(np.uint8), "RGB")
  with fileio.atomic_path(path) as tmp:
    pil.save(tmp, format="PNG")


def save_scene(scene: Scene, directory: str | Path, write_poses: bool = False) -> Path:
  """Writes `scene` as a native bundle; poses go to poses.json only with `write_poses`."""
  directory = Path(directory)
  (directory / "wli").mkdir(parents=True, exist_ok=True)
  (directory / "om").mkdir(parents=True, exist_ok=True)
  wli_meta, om_meta = [], []
  for s in scene.wli:
    f = f"wli/{s.name}.npz"
    arrays = {"depth": s.depth.astype(np.float32)}
    if s.intensity is not None:
      arrays["intensity"] = s.intensity.astype(np.float32)
    fileio.write_npz(directory / f, **arrays)
    wli_meta.append({"name": s.name, "file": f, "shape": list(s.shape),
                     "pixel_size": [float(v) for v in s.pixel_size], "prior": s.prior})
  for o in scene.om:
    f = f"om/{o.name}.png"
    save_png(directory / f, o.image)
    om_meta.append({"name": o.name, "file": f, "shape": list(o.shape),
                    "intrinsics": None if o.K is None else intrinsics_to_json(o), "prior": o.prior})
  if write_poses:
    fileio.write_json(directory / "poses.json", poses_to_json(scene))
  norm = scene.normalization
  meta = {"format": FORMAT, "version": VERSION, "units": scene.units, "name": scene.name,
          "source": scene.source, "wli": wli_meta, "om": om_meta,
          "normalization": None if norm is None else dataclasses.asdict(norm)}
  fileio.write_json(directory / "scene.json", meta)
  return directory


def _prior(entry: dict, kind: str) -> dict | None:
  """The optional "prior" object of a scene.json scan or photo entry."""
  prior = entry.get("prior")
  if prior is not None and not isinstance(prior, dict):
    raise ValueError(f"{kind} {entry['name']!r}: prior is {prior!r}, not an object")
  return prior


def read_png(path: Path) -> np.ndarray:
  """[H, W, 3] float32 in [0, 1] from an 8- or 16-bit photo (ofjax.io.om.read_image)."""
  from ofjax.io.om import read_image
  return read_image(path)


def load_scene(directory: str | Path, poses: str | Path | None | bool = None) -> Scene:
  """Reads a native bundle; applies `poses` (default: DIR/poses.json when it exists; False: none)."""
  directory = Path(directory)
  meta_path = directory / "scene.json"
  if not meta_path.is_file():
    raise UserError(f"{meta_path}: not found; is {directory} an ofjax scene (make one with "
                    "`python -m ofjax.synth`)?")
  try:
    meta = json.loads(meta_path.read_text())
  except (json.JSONDecodeError, UnicodeDecodeError):
    raise UserError(f"{meta_path}: not valid JSON; regenerate the scene bundle") from None
  meta = meta if isinstance(meta, dict) else {}
  if meta.get("format") != FORMAT or meta.get("version") != VERSION:
    raise UserError(f"{meta_path}: format {meta.get('format')!r} version {meta.get('version')!r}"
                    f" is not {FORMAT!r} version {VERSION}; regenerate the scene bundle")
  with json_fields(meta_path, "fix or regenerate the scene bundle"):
    wli = []
    for m in meta["wli"]:
      f = directory / m["file"]
      try:
        with np.load(f) as z:
          depth = np.asarray(z["depth"], np.float32)
          intensity = np.asarray(z["intensity"], np.float32) if "intensity" in z.files else None
      except FileNotFoundError:
        raise UserError(f"{f}: WLI file listed in scene.json is missing; restore it") from None
      except Exception as e:  # noqa: BLE001 - numpy raises many kinds on corrupt archives
        raise UserError(f"{f}: cannot read the WLI depth map ({type(e).__name__}); replace the "
                        "file") from None
      if depth.ndim != 2:
        raise UserError(f"{f}: depth must be a 2-D map, got shape {depth.shape}; replace the file")
      if not np.isfinite(depth).any():
        raise UserError(f"{f}: every pixel is a void; replace the file or drop the scan from "
                        "scene.json")
      if intensity is not None and intensity.shape != depth.shape:
        raise UserError(f"{f}: intensity image {intensity.shape} and depth map {depth.shape} "
                        "differ in shape; store both on the same pixels or drop the intensity")
      wli.append(WLIScan(m["name"], depth, numbers(m["pixel_size"], 2, "pixel_size", True),
                         prior=_prior(m, "scan"), intensity=intensity))
    om = []
    for m in meta["om"]:
      f = directory / m["file"]
      if not f.is_file():
        raise UserError(f"{f}: OM photo listed in scene.json is missing; restore it")
      intr = m.get("intrinsics")
      om.append(OMImage(m["name"], read_png(f), None if intr is None else K_from_json(intr),
                        prior=_prior(m, "photo")))
    norm = meta.get("normalization")
    scene = Scene(wli, om, name=meta.get("name", directory.name), units=meta.get("units", "um"),
                  source=meta.get("source", {}),
                  normalization=None if norm is None else Normalization(
                      numbers(norm["center"], 3, "normalization center"),
                      numbers([norm["scale"]], 1, "normalization scale", True)[0]))
  if poses is False:  # the raw data only (ofjax.associate makes the poses)
    return scene
  poses_path = Path(poses) if poses is not None else directory / "poses.json"
  if poses is not None or poses_path.is_file():
    apply_poses(scene, load_poses(poses_path), poses_path)
  return scene
