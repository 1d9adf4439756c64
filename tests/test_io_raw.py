"""The raw layout (ofjax.io.raw) on instrument files of mixed formats, through ofjax.io.load."""

import warnings

import numpy as np
import pytest
import surfalize
from PIL import Image

from ofjax import fileio
from ofjax.errors import UserError
from ofjax.io import detect_layout, load, om, wli
from ofjax.scene import poses_to_json

from test_io_datx import NO_DATA, write_datx


def _raw_folder(root):
  rng = np.random.default_rng(2)
  (root / "wli").mkdir(parents=True)
  (root / "om").mkdir()
  z = rng.normal(0, 2, (16, 20))
  z[0, 0] = np.nan
  surfalize.Surface(z, 0.6, 0.6).save(root / "wli" / "a.x3p")
  v = rng.normal(0, 500, (12, 14))
  v[1, 1] = NO_DATA
  write_datx(root / "wli" / "b.datx", v, steps=(0.3e-6, 0.3e-6))
  for i in range(2):
    exif = Image.Exif()
    exif.get_ifd(om.EXIF_IFD)[om.EXIF_FOCAL_35MM] = 100
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    Image.fromarray(img).save(root / "om" / f"p{i}.jpg", exif=exif, quality=95)
  return z, v


def test_mixed_formats_become_one_unposed_scene(tmp_path):
  z, v = _raw_folder(tmp_path / "r")
  assert detect_layout(tmp_path / "r") == "raw"
  scene = load(tmp_path / "r")
  assert scene.units == "um" and not scene.posed and scene.source["layout"] == "raw"
  a, b = scene.wli
  assert (a.name, a.pixel_size, b.name) == ("a", (0.6, 0.6), "b")
  np.testing.assert_allclose(b.pixel_size, (0.3, 0.3), rtol=1e-12)
  # depth = datum - height, datum = highest valid height (io.wli)
  np.testing.assert_allclose(a.depth, np.nanmax(z) - z, atol=1e-5, equal_nan=True)
  hb = np.where(v >= NO_DATA, np.nan, v / 1000.0)
  np.testing.assert_allclose(b.depth, np.nanmax(hb) - hb, atol=1e-6, equal_nan=True)
  assert b.prior[wli.DATUM_KEY] == pytest.approx(np.nanmax(hb))
  f_ref = 100 * np.hypot(32, 24) / np.hypot(36, 24)
  for o in scene.om:
    np.testing.assert_allclose(o.K, [[f_ref, 0, 16], [0, f_ref, 12], [0, 0, 1]])


def test_poses_file_is_applied(tmp_path):
  _raw_folder(tmp_path / "r")
  scene = load(tmp_path / "r")
  rng = np.random.default_rng(0)
  for cam in scene.wli + scene.om:
    cam.c2w = np.eye(4)
    cam.c2w[:3, 3] = rng.normal(size=3)
  fileio.write_json(tmp_path / "poses.json", poses_to_json(scene))
  posed = load(tmp_path / "r", poses=tmp_path / "poses.json")
  assert posed.posed
  for a, b in zip(posed.wli + posed.om, scene.wli + scene.om):
    np.testing.assert_array_equal(a.c2w, b.c2w)


def test_two_files_with_one_stem_are_a_user_error(tmp_path):
  _raw_folder(tmp_path / "r")
  Image.new("RGB", (32, 24)).save(tmp_path / "r" / "om" / "p0.png")
  with pytest.raises(UserError, match="p0.png: has the same name as p0.jpg"):
    load(tmp_path / "r")


@pytest.mark.parametrize("layout", ["native", "opticfusion", "bogus"])
def test_forcing_another_layout_names_what_is_missing(tmp_path, layout):
  _raw_folder(tmp_path / "r")
  with pytest.raises(UserError, match=r"scene.json: not found|wl: folder not found|'bogus'"), \
       warnings.catch_warnings():
    warnings.simplefilter("ignore")
    load(tmp_path / "r", layout=layout, um_per_unit=1.0 if layout == "opticfusion" else None)
