"""The OpticFusion WLI-OM dataset layout (zju3dv/OpticFusion), read as it is.

  <scene>/wl/NNNN.npz     `depth_map` [H, W] float, NaN = void; `extrinsic_mat` [3, 4] world->camera
  <scene>/op/NNNN.png     RGB photos (any format io.om reads)
  <scene>/op/camera.xml   Agisoft Metashape cameras export
  <scene>/op/align.aln    MeshLab alignment; its lines 4-7 hold a 4x4 matrix A

WLI cameras (the reference's orthographic model): c2w = inverse(extrinsic_mat as 4x4); pixel
(row r, col c) has origin c2w[:3, 3] + c2w[:3, :3] @ ((c / W - 0.5) K, (r / H - 0.5) K, 0) with
K = `IMAGE_WIDTH_UNITS` = 10 layout units across the image, direction c2w[:3, :3] @ (0, 0, 1), and
depth_map is the distance along it. There is NO half-pixel offset, so in ofjax's pixel-centre
model (scene.py: (c + 0.5 - W / 2) sx) the pixel size is sx = K / W, sy = K / H and the translation
moves by -R @ (sx / 2, sy / 2, 0). (The reference swaps H and W in its ray grid; the two agree on
its square 1024 x 1024 maps, and ofjax follows c / W, r / H.)

OM cameras: each `<camera>`'s `<transform>` is a row-major 4x4 camera-to-chunk matrix (OpenCV
axes); its `<component>`'s `<transform>` (rotation 9, translation 3, scale 1) is chunk-to-world
M = [s R | t]; c2w = A @ M @ T. Focal f from the camera's sensor `<calibration><f>` in pixels
(rescaled if the photo's size differs from the calibration's resolution), principal point
(W // 2, H // 2) with pixel centres at +0.5, no distortion (the reference ignores cx, cy and the
distortion terms). A camera without `<transform>` was not aligned: it is skipped with a warning.
Photos are matched to cameras by label (file stem), else by their index among the cameras.

Units and rigidity: every c2w ofjax keeps is rigid. A uniform scale s in a camera's 3x3 part
(the chunk scale, a scaled alignment) goes into the positions and is removed from the rotation;
for a WLI scan it also multiplies the pixel size and the depths. `um_per_unit` then multiplies all
positions, pixel sizes and depths; without it ofjax warns once and the Scene's units are
`LAYOUT_UNIT` ("unit").
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ofjax.errors import UserError
from ofjax.io import om
from ofjax.scene import OMImage, Scene, WLIScan

IMAGE_WIDTH_UNITS = 10.0  # the reference's `depth_focal`: layout units across a WLI image
LAYOUT_UNIT = "unit"
RIGID_TOL = 1e-4  # max deviation of R^T R / s^2 from the identity accepted as "rigid up to scale"


def check_um_per_unit(value, what: str = "--um-per-unit") -> float:
  try:
    f = float(value)
  except (TypeError, ValueError):
    f = float("nan")
  if not np.isfinite(f) or f <= 0:
    raise UserError(f"{what}: {value!r} is not a positive finite number; give the micrometres per "
                    "layout unit, e.g. --um-per-unit 100")
  return f


def _finite_matrix(values, shape, path: Path, what: str) -> np.ndarray:
  try:
    m = np.asarray(values, np.float64)
  except (TypeError, ValueError):
    raise UserError(f"{path}: {what} is not numeric; fix or re-export the file") from None
  if m.size != int(np.prod(shape)):
    raise UserError(f"{path}: {what} has {m.size} values, expected {int(np.prod(shape))} "
                    f"({shape[0]}x{shape[1]}); fix or re-export the file")
  m = m.reshape(shape)
  if not np.all(np.isfinite(m)):
    raise UserError(f"{path}: {what} holds non-finite values (NaN/inf); fix or re-export the file")
  return m


def rigidify(m: np.ndarray, path: Path, what: str) -> tuple[np.ndarray, float]:
  """(rigid [4, 4] c2w, uniform scale s) of a similarity [4, 4]; rotation = nearest rotation to M/s.

  The translation is kept as is; a reflection or a non-uniform scale is a UserError.
  """
  a = m[:3, :3]
  det = np.linalg.det(a)
  if not det > 0:
    raise UserError(f"{path}: {what} is singular or mirrored (det {det:.3g}); fix or re-export it")
  s = float(np.cbrt(det))
  if np.abs(a.T @ a / s**2 - np.eye(3)).max() > RIGID_TOL:
    raise UserError(f"{path}: {what} is not a rotation with a uniform scale; fix or re-export it")
  u, _, vt = np.linalg.svd(a / s)
  out = np.eye(4)
  out[:3, :3] = u @ vt
  out[:3, 3] = m[:3, 3]
  return out, s


def _read_wli(path: Path, name: str, um_per_unit: float) -> WLIScan:
  try:
    with np.load(path, allow_pickle=False) as z:
      missing = [k for k in ("depth_map", "extrinsic_mat") if k not in z.files]
      if missing:
        raise UserError(f"{path}: has no {' / '.join(missing)} (holds {z.files}); an OpticFusion "
                        "scan needs depth_map and extrinsic_mat")
      depth = np.asarray(z["depth_map"])
      ext = np.asarray(z["extrinsic_mat"])
  except UserError:
    raise
  except Exception as e:  # noqa: BLE001 - numpy raises many kinds on truncated archives
    raise UserError(f"{path}: cannot read the npz ({type(e).__name__}); the file is damaged, "
                    "re-copy it") from None
  from ofjax.io.wli import validate_height
  depth = validate_height(path, depth, "depth_map")
  if ext.shape not in ((3, 4), (4, 4)):
    raise UserError(f"{path}: extrinsic_mat has shape {ext.shape}, not 3x4; fix the file")
  w2c = np.eye(4)
  w2c[:ext.shape[0]] = _finite_matrix(ext, ext.shape, path, "extrinsic_mat")
  c2w, s = rigidify(np.linalg.inv(w2c), path, "the inverse of extrinsic_mat")
  h, w = depth.shape
  sx, sy = s * IMAGE_WIDTH_UNITS / w, s * IMAGE_WIDTH_UNITS / h
  c2w[:3, 3] -= c2w[:3, :3] @ np.array([sx / 2, sy / 2, 0.0])  # reference has no +0.5 offset
  c2w[:3, 3] *= um_per_unit
  return WLIScan(name, (depth * s * um_per_unit).astype(np.float32),
                 (sx * um_per_unit, sy * um_per_unit), c2w)


def read_aln(path: Path) -> np.ndarray:
  """[4, 4] the matrix on lines 4-7 of a MeshLab .aln file."""
  if not path.is_file():
    raise UserError(f"{path}: not found; the OpticFusion layout needs op/align.aln (MeshLab "
                    "alignment of the OM reconstruction to the WLI)")
  lines = path.read_text(errors="replace").splitlines()
  try:
    rows = [[float(v) for v in line.split()] for line in lines[3:7]]
  except ValueError:
    raise UserError(f"{path}: lines 4-7 are not a 4x4 matrix of numbers; re-export the alignment "
                    "from MeshLab") from None
  if len(rows) != 4 or any(len(r) != 4 for r in rows):
    raise UserError(f"{path}: lines 4-7 are not a 4x4 matrix; re-export the alignment from MeshLab")
  return _finite_matrix(rows, (4, 4), path, "the alignment matrix")


def _floats(el, tag: str, n: int, path: Path, what: str) -> np.ndarray:
  node = el.find(tag)
  if node is None or not (node.text or "").strip():
    raise UserError(f"{path}: {what} has no <{tag}>; re-export the cameras from Metashape")
  try:
    vals = [float(v) for v in node.text.split()]
  except ValueError:
    raise UserError(f"{path}: <{tag}> of {what} is not numeric; re-export the cameras") from None
  return _finite_matrix(vals, (n, 1), path, f"<{tag}> of {what}").reshape(-1)


def read_metashape(path: Path) -> tuple[list[dict], dict[str, dict], dict[str, np.ndarray]]:
  """Cameras, sensors and components of a Metashape cameras XML.

  Returns:
    cameras: [{"label", "index", "sensor", "component", "T" ([4, 4] or None)}] in file order.
    sensors: id -> {"f": pixels, "resolution": (W, H) or None}.
    components: id -> [4, 4] chunk-to-world M = [s R | t] (identity when the file has none).
  """
  if not path.is_file():
    raise UserError(f"{path}: not found; the OpticFusion layout needs op/camera.xml (Metashape "
                    "cameras export)")
  try:
    root = ET.parse(path).getroot()
  except ET.ParseError as e:
    raise UserError(f"{path}: not valid XML ({e}); re-export the cameras from Metashape") from None
  sensors = {}
  for sensor in root.iter("sensor"):
    calibs = sensor.findall("calibration")
    calib = next((c for c in calibs if c.get("class") == "adjusted"), calibs[0] if calibs else None)
    if calib is None or calib.find("f") is None:
      continue
    f = float(_floats(calib, "f", 1, path, f"sensor {sensor.get('id')} calibration")[0])
    res = calib.find("resolution")
    if res is None:
      res = sensor.find("resolution")
    try:
      wh = None if res is None else (int(res.get("width", 0)), int(res.get("height", 0)))
    except ValueError:
      raise UserError(f"{path}: <resolution> of sensor {sensor.get('id')} is not a pair of whole "
                      "numbers; re-export the cameras from Metashape") from None
    sensors[sensor.get("id", "0")] = {"f": f, "resolution": wh}
  if not sensors:
    raise UserError(f"{path}: no sensor with a <calibration><f>; re-export the cameras from "
                    "Metashape after alignment")
  components = {}
  for comp in root.iter("component"):
    tr = comp.find("transform")
    m = np.eye(4)
    if tr is not None:
      what = f"component {comp.get('id')} transform"
      rot = _floats(tr, "rotation", 9, path, what).reshape(3, 3)
      trans = _floats(tr, "translation", 3, path, what)
      scale = float(_floats(tr, "scale", 1, path, what)[0]) if tr.find("scale") is not None else 1.0
      m[:3, :3], m[:3, 3] = scale * rot, trans
    components[comp.get("id", "0")] = m
  cameras = []
  for i, cam in enumerate(root.iter("camera")):
    node = cam.find("transform")
    t = None
    if node is not None and (node.text or "").strip():
      t = _finite_matrix(node.text.split(), (4, 4), path,
                         f"camera {cam.get('label', i)!r} transform")
    cameras.append({"label": cam.get("label", ""), "index": i, "T": t,
                    "sensor": cam.get("sensor_id", next(iter(sensors))),
                    "component": cam.get("component_id")})
  if not cameras:
    raise UserError(f"{path}: holds no <camera>; re-export the cameras from Metashape")
  return cameras, sensors, components


def _photo_for(camera: dict, photos: list[Path], path: Path) -> Path:
  stem = Path(camera["label"]).stem
  by_stem = {p.stem: p for p in photos}
  if stem in by_stem:
    return by_stem[stem]
  if camera["index"] < len(photos):
    return photos[camera["index"]]
  raise UserError(f"{path}: camera {camera['label']!r} has no photo in {path.parent} (no file "
                  f"named {stem}.* and fewer photos than cameras); add the photo")


def _read_om(op: Path, um_per_unit: float) -> list[OMImage]:
  xml = op / "camera.xml"
  cameras, sensors, components = read_metashape(xml)
  a = read_aln(op / "align.aln")
  photos = om.list_photos(op)
  if not photos:
    raise UserError(f"{op}: no photos (.png/.jpg/.tif); the OpticFusion layout keeps the OM "
                    "photos in op/")
  images, paths = [], []
  for cam in cameras:
    if cam["T"] is None:
      warnings.warn(f"{xml}: camera {cam['label']!r} has no <transform> (not aligned in Metashape);"
                    " skipping it", stacklevel=3)
      continue
    comp = components.get(cam["component"]) if cam["component"] is not None else None
    m = comp if comp is not None else next(iter(components.values()), np.eye(4))
    what = f"camera {cam['label']!r} (align.aln @ component @ transform)"
    c2w, _ = rigidify(a @ m @ cam["T"], xml, what)
    c2w[:3, 3] *= um_per_unit
    photo = _photo_for(cam, photos, xml)
    image = om.read_image(photo)
    h, w = image.shape[:2]
    sensor = sensors.get(cam["sensor"]) or next(iter(sensors.values()))
    f = sensor["f"]
    if sensor["resolution"] and sensor["resolution"][0] > 0 and sensor["resolution"][0] != w:
      f *= w / sensor["resolution"][0]  # the photo was resized after calibration
    k = np.array([[f, 0, w // 2], [0, f, h // 2], [0, 0, 1]], np.float64)
    images.append(OMImage(photo.stem, image, k, c2w))
    paths.append(photo)
  om.check_same_size(paths, [o.image for o in images])
  return images


def load_opticfusion(directory: str | Path, um_per_unit: float | None = None) -> Scene:
  """The Scene of an OpticFusion WLI-OM scene folder, posed, in um when `um_per_unit` is given."""
  directory = Path(directory)
  wl, op = directory / "wl", directory / "op"
  for d in (wl, op):
    if not d.is_dir():
      raise UserError(f"{d}: folder not found; an OpticFusion scene has wl/ (WLI .npz) and op/ "
                      "(photos, camera.xml, align.aln)")
  if um_per_unit is None:
    warnings.warn(f"{directory}: no --um-per-unit given; the scene stays in the layout's own "
                  f"unit ({LAYOUT_UNIT!r}) and so will every output", stacklevel=2)
    factor, units = 1.0, LAYOUT_UNIT
  else:
    factor, units = check_um_per_unit(um_per_unit), "um"
  scans = sorted(p for p in wl.iterdir()
                 if p.suffix.lower() == ".npz" and not p.name.startswith("."))
  if not scans:
    raise UserError(f"{wl}: no .npz scans; the OpticFusion layout keeps the WLI scans as "
                    "wl/0000.npz ...")
  wli = [_read_wli(p, p.stem, factor) for p in scans]
  return Scene(wli, _read_om(op, factor), name=directory.name, units=units,
               source={"layout": "opticfusion", "path": str(directory.resolve()),
                       "um_per_unit": None if um_per_unit is None else factor})
