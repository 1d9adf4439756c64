"""The OpticFusion WLI-OM layout (ofjax.io.opticfusion) against a float64 reference of its model.

The fixture writes a scene folder the way the dataset is laid out (numpy npz, PIL png,
ElementTree Metashape XML, a MeshLab .aln); the reference rays are computed here straight from
DESIGN.md's description of the reference implementation, independently of ofjax's conversion.
"""

import warnings
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from PIL import Image

from ofjax.errors import UserError
from ofjax.io import load, opticfusion
from ofjax.scene import om_rays, wli_rays

K_UNITS = 10.0  # layout units across a WLI image (the reference's depth_focal)
WLI_HW = (6, 8)  # non-square, so that rows and columns cannot be confused
OM_HW = (10, 12)
FOCAL = 20.0
CHUNK_SCALE = 2.5
ALN_SCALE = 1.3


def _rot(rng):
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  return q if np.linalg.det(q) > 0 else -q


def _similarity(rng, scale):
  m = np.eye(4)
  m[:3, :3], m[:3, 3] = scale * _rot(rng), rng.normal(size=3)
  return m


def write_opticfusion(root, seed=0, n_wli=2, n_om=3, unaligned=()):
  """Writes an OpticFusion scene folder; returns the ground truth used to write it."""
  rng = np.random.default_rng(seed)
  (root / "wl").mkdir(parents=True)
  (root / "op").mkdir()
  gt = {"w2c": [], "depth": [], "T": [], "photos": []}
  for i in range(n_wli):
    depth = rng.uniform(2, 4, WLI_HW)
    depth[0, :3] = np.nan
    w2c = np.linalg.inv(_similarity(rng, 1.0))[:3]
    np.savez(root / "wl" / f"{i:04d}.npz", depth_map=depth, extrinsic_mat=w2c)
    gt["w2c"].append(w2c)
    gt["depth"].append(depth)
  m = _similarity(rng, CHUNK_SCALE)
  a = _similarity(rng, ALN_SCALE)
  doc = ET.Element("document", version="1.5.0")
  chunk = ET.SubElement(doc, "chunk")
  sensor = ET.SubElement(ET.SubElement(chunk, "sensors"), "sensor", id="0", label="cam",
                         type="frame")
  ET.SubElement(sensor, "resolution", width=str(OM_HW[1]), height=str(OM_HW[0]))
  calib = ET.SubElement(sensor, "calibration", type="frame", **{"class": "adjusted"})
  ET.SubElement(calib, "resolution", width=str(OM_HW[1]), height=str(OM_HW[0]))
  ET.SubElement(calib, "f").text = repr(FOCAL)
  ET.SubElement(calib, "cx").text = "0.7"  # ignored, as in the reference
  comp = ET.SubElement(ET.SubElement(chunk, "components"), "component", id="0", label="C1")
  tr = ET.SubElement(comp, "transform")
  r = m[:3, :3] / CHUNK_SCALE
  ET.SubElement(tr, "rotation").text = " ".join(f"{v:.17g}" for v in r.ravel())
  ET.SubElement(tr, "translation").text = " ".join(f"{v:.17g}" for v in m[:3, 3])
  ET.SubElement(tr, "scale").text = repr(CHUNK_SCALE)
  cams = ET.SubElement(chunk, "cameras")
  for i in range(n_om):
    cam = ET.SubElement(cams, "camera", id=str(i), sensor_id="0", component_id="0",
                        label=f"{i:04d}")
    t = _similarity(rng, 1.0)
    if i not in unaligned:
      ET.SubElement(cam, "transform").text = " ".join(f"{v:.17g}" for v in t.ravel())
      gt["T"].append(t)
    img = rng.integers(0, 256, OM_HW + (3,), dtype=np.uint8)
    Image.fromarray(img).save(root / "op" / f"{i:04d}.png")
    if i not in unaligned:
      gt["photos"].append(img)
  ET.ElementTree(doc).write(root / "op" / "camera.xml")
  rows = "\n".join(" ".join(f"{v:.17g}" for v in row) for row in a)
  (root / "op" / "align.aln").write_text(f"1\nop.ply\n#\n{rows}\n0\n")
  gt.update(M=m, A=a)
  return gt


def reference_wli(w2c, depth, um):
  """Origins, unit directions and points of the reference's orthographic model, in um."""
  c2w = np.linalg.inv(np.vstack([w2c, [0, 0, 0, 1]]))
  h, w = depth.shape
  r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
  local = np.stack([(c / w - 0.5) * K_UNITS, (r / h - 0.5) * K_UNITS, np.zeros_like(c, float)], -1)
  o = (c2w[:3, 3] + local @ c2w[:3, :3].T) * um
  d = c2w[:3, :3] @ np.array([0, 0, 1.0])
  return o, np.broadcast_to(d / np.linalg.norm(d), o.shape), o + d * depth[..., None] * um


def reference_om(c2w_scaled, h, w, um):
  v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
  cam = np.stack([(u + 0.5 - w // 2) / FOCAL, (v + 0.5 - h // 2) / FOCAL, np.ones((h, w))], -1)
  d = cam @ c2w_scaled[:3, :3].T
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  return np.broadcast_to(c2w_scaled[:3, 3] * um, d.shape), d


@pytest.mark.parametrize("um", [1.0, 37.5])
def test_rays_match_the_reference_model(tmp_path, um):
  gt = write_opticfusion(tmp_path / "s")
  scene = load(tmp_path / "s", um_per_unit=um)
  assert scene.units == "um" and scene.posed and scene.source["layout"] == "opticfusion"
  tol = 1e-9 * um * K_UNITS
  for scan, w2c, depth in zip(scene.wli, gt["w2c"], gt["depth"]):
    o_ref, d_ref, p_ref = reference_wli(w2c, depth, um)
    o, d = wli_rays(scan)
    np.testing.assert_allclose(o, o_ref, rtol=0, atol=tol)
    np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-12)
    pts = o + d * scan.depth[..., None].astype(np.float64)
    ok = np.isfinite(depth)
    # depth is stored as float32: 4 units * 6e-8 relative
    np.testing.assert_allclose(pts[ok], p_ref[ok], rtol=0, atol=1e-6 * um * K_UNITS)
    assert np.array_equal(scan.valid, ok)
    np.testing.assert_allclose(np.linalg.det(scan.c2w[:3, :3]), 1.0, atol=1e-12)
  for image, t, photo in zip(scene.om, gt["T"], gt["photos"]):
    c2w_scaled = gt["A"] @ gt["M"] @ t
    o_ref, d_ref = reference_om(c2w_scaled, *OM_HW, um)
    o, d = om_rays(image)
    np.testing.assert_allclose(o, o_ref, rtol=0, atol=tol * CHUNK_SCALE * ALN_SCALE)
    np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(image.image, photo / 255.0, atol=1e-7)
    np.testing.assert_allclose(image.c2w[:3, :3].T @ image.c2w[:3, :3], np.eye(3), atol=1e-12)


def test_without_factor_warns_and_keeps_layout_units(tmp_path):
  write_opticfusion(tmp_path / "s")
  with pytest.warns(UserWarning, match="no --um-per-unit"):
    scene = load(tmp_path / "s")
  assert scene.units == opticfusion.LAYOUT_UNIT
  assert scene.source["um_per_unit"] is None


def test_unaligned_camera_is_skipped_with_a_warning(tmp_path):
  gt = write_opticfusion(tmp_path / "s", n_om=4, unaligned=(1,))
  with pytest.warns(UserWarning, match="camera '0001' has no <transform>"):
    scene = load(tmp_path / "s", um_per_unit=2.0)
  assert [o.name for o in scene.om] == ["0000", "0002", "0003"]
  np.testing.assert_allclose(scene.om[1].image, gt["photos"][1] / 255.0, atol=1e-7)


@pytest.mark.parametrize("bad", [0, -3.0, float("nan"), float("inf")])
def test_bad_unit_factor_is_a_user_error(tmp_path, bad):
  write_opticfusion(tmp_path / "s")
  with pytest.raises(UserError, match="--um-per-unit"):
    load(tmp_path / "s", um_per_unit=bad)


def _break_extrinsic(root):
  z = dict(np.load(root / "wl" / "0001.npz"))
  z["extrinsic_mat"][1, 2] = np.nan
  np.savez(root / "wl" / "0001.npz", **z)


def _truncate(path):
  data = path.read_bytes()
  path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("breaker, match", [
    (lambda r: (r / "op" / "camera.xml").unlink(), r"camera.xml: not found"),
    (lambda r: (r / "op" / "align.aln").write_text("1\nx\n#\n1 2 3\n"), r"align.aln: lines 4-7"),
    (lambda r: (r / "op" / "camera.xml").write_text("<document><chunk>"),
     r"camera.xml: not valid XML"),
    (_break_extrinsic, r"0001.npz: extrinsic_mat holds non-finite"),
    (lambda r: _truncate(r / "wl" / "0000.npz"), r"0000.npz: cannot read the npz"),
    (lambda r: np.savez(r / "wl" / "0000.npz", depth_map=np.full((4, 4), np.nan),
                        extrinsic_mat=np.eye(4)[:3]), r"0000.npz: every pixel is a void"),
    (lambda r: np.savez(r / "wl" / "0000.npz", depth=np.ones((4, 4))), r"has no depth_map"),
    (lambda r: np.savez(r / "wl" / "0000.npz", depth_map=np.ones((4, 4, 2)),
                        extrinsic_mat=np.eye(4)[:3]), r"not a 2-D map"),
    (lambda r: Image.fromarray(np.zeros((5, 5, 3), np.uint8)).save(r / "op" / "0002.png"),
     r"0002.png: photo is 5x5 but 0000.png is 12x10"),
])
def test_broken_layouts_are_user_errors(tmp_path, breaker, match):
  write_opticfusion(tmp_path / "s")
  breaker(tmp_path / "s")
  with pytest.raises(UserError, match=match), warnings.catch_warnings():
    warnings.simplefilter("ignore")
    load(tmp_path / "s", um_per_unit=1.0)


def test_mirrored_alignment_is_a_user_error(tmp_path):
  write_opticfusion(tmp_path / "s")
  (tmp_path / "s" / "op" / "align.aln").write_text(
      "1\nop.ply\n#\n-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n0\n")
  with pytest.raises(UserError, match="mirrored"):
    load(tmp_path / "s", um_per_unit=1.0)
