"""OM photo reading (ofjax.io.om) on files written by PIL, pypng and tifffile."""

import numpy as np
import png
import pytest
import tifffile
from PIL import Image

from ofjax.errors import UserError
from ofjax.io import om

RNG = np.random.default_rng(7)


def test_png_8bit_exact(tmp_path):
  a = RNG.integers(0, 256, (9, 13, 3), dtype=np.uint8)
  Image.fromarray(a).save(tmp_path / "a.png")
  out = om.read_image(tmp_path / "a.png")
  assert out.dtype == np.float32 and out.shape == (9, 13, 3)
  np.testing.assert_allclose(out, a.astype(np.float64) / 255, rtol=0, atol=1e-7)


def test_png_16bit_rgb_keeps_all_bits(tmp_path):
  # Pillow would truncate this file to 8 bits; the low byte must survive.
  a = RNG.integers(0, 65536, (7, 11, 3), dtype=np.uint16)
  png.from_array(a.reshape(7, -1), "RGB;16").save(tmp_path / "a.png")
  out = om.read_image(tmp_path / "a.png")
  np.testing.assert_allclose(out, a.astype(np.float64) / 65535, rtol=0, atol=1e-7)


def test_png_16bit_grey_becomes_grey_rgb(tmp_path):
  a = RNG.integers(0, 65536, (6, 5), dtype=np.uint16)
  Image.fromarray(a).save(tmp_path / "g.png")
  out = om.read_image(tmp_path / "g.png")
  ref = np.repeat((a.astype(np.float64) / 65535)[..., None], 3, -1)
  np.testing.assert_allclose(out, ref, rtol=0, atol=1e-7)


def test_tiff_16bit_rgb(tmp_path):
  a = RNG.integers(0, 65536, (5, 8, 3), dtype=np.uint16)
  tifffile.imwrite(tmp_path / "a.tif", a, photometric="rgb")
  np.testing.assert_allclose(om.read_image(tmp_path / "a.tif"), a / 65535.0, rtol=0, atol=1e-7)


def _blocky(h, w):
  """An upright test picture of flat colour blocks (JPEG keeps flat blocks nearly exact)."""
  up = np.zeros((h, w, 3), np.uint8)
  up[: h // 2, : w // 2] = (255, 0, 0)
  up[: h // 2, w // 2:] = (0, 255, 0)
  up[h // 2:, : w // 2] = (0, 0, 255)
  up[h // 2:, w // 2:] = (255, 255, 255)
  return up


@pytest.mark.parametrize("orientation, stored_from_upright", [
    (1, lambda a: a),
    (3, lambda a: a[::-1, ::-1]),
    (6, lambda a: np.rot90(a, 1)),  # 6: the viewer turns the stored picture 90 deg clockwise
    (8, lambda a: np.rot90(a, -1)),
])
def test_jpeg_exif_orientation_is_applied(tmp_path, orientation, stored_from_upright):
  up = _blocky(32, 48)
  exif = Image.Exif()
  exif[om.EXIF_ORIENTATION] = orientation
  Image.fromarray(np.ascontiguousarray(stored_from_upright(up))).save(
      tmp_path / "p.jpg", exif=exif, quality=95)
  out = om.read_image(tmp_path / "p.jpg")
  assert out.shape == up.shape
  # JPEG rings at block edges; a wrongly turned picture would be off by ~0.5 on average.
  assert np.abs(out - up / 255.0).mean() < 0.03


def test_png16_orientation_matches_pillow_transpose(tmp_path):
  a = RNG.integers(0, 65536, (4, 6, 3), dtype=np.uint16)
  for orientation in range(1, 9):
    # The same orientation on an 8-bit copy goes through PIL.ImageOps.exif_transpose.
    exif = Image.Exif()
    exif[om.EXIF_ORIENTATION] = orientation
    a8 = (a >> 8).astype(np.uint8)
    Image.fromarray(a8).save(tmp_path / "ref.png", exif=exif)
    ref = om.read_image(tmp_path / "ref.png")
    np.testing.assert_allclose(om._apply_orientation(a8, orientation) / 255.0, ref, atol=1e-7)


def test_exif_focal_plane_intrinsics(tmp_path):
  exif = Image.Exif()
  exif[om.EXIF_ORIENTATION] = 6
  sub = exif.get_ifd(om.EXIF_IFD)
  sub[om.EXIF_FOCAL_LENGTH] = 4.0  # mm
  sub[om.EXIF_FOCAL_PLANE_XRES] = 1000.0  # px per cm along the sensor's x
  sub[om.EXIF_FOCAL_PLANE_YRES] = 500.0
  sub[om.EXIF_FOCAL_PLANE_UNIT] = 3  # cm
  Image.fromarray(_blocky(10, 16)).save(tmp_path / "p.jpg", exif=exif)
  img = om.read_image(tmp_path / "p.jpg")
  k = om.exif_intrinsics(tmp_path / "p.jpg", img.shape[:2])
  # Sensor fx = 4 mm * 100 px/mm = 400 px, fy = 200 px; orientation 6 swaps the image axes.
  np.testing.assert_allclose(k, [[200, 0, 5], [0, 400, 8], [0, 0, 1]])


def test_exif_35mm_equivalent_intrinsics(tmp_path):
  exif = Image.Exif()
  exif.get_ifd(om.EXIF_IFD)[om.EXIF_FOCAL_35MM] = 50
  Image.fromarray(_blocky(30, 40)).save(tmp_path / "p.jpg", exif=exif)
  k = om.exif_intrinsics(tmp_path / "p.jpg", (30, 40))
  f_ref = 50 * 50.0 / np.sqrt(36.0**2 + 24.0**2)  # diagonal 50 px vs 43.27 mm
  np.testing.assert_allclose([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], [f_ref, f_ref, 20, 15])


def test_no_exif_leaves_intrinsics_to_sfm(tmp_path):
  Image.fromarray(_blocky(8, 8)).save(tmp_path / "p.png")
  assert om.exif_intrinsics(tmp_path / "p.png", (8, 8)) is None


def test_corrupt_png_is_a_user_error(tmp_path):
  Image.fromarray(_blocky(20, 20)).save(tmp_path / "p.png")
  data = (tmp_path / "p.png").read_bytes()
  (tmp_path / "p.png").write_bytes(data[: len(data) // 2])
  with pytest.raises(UserError, match="p.png"):
    om.read_image(tmp_path / "p.png")


def test_not_an_image_is_a_user_error(tmp_path):
  (tmp_path / "p.jpg").write_text("hello")
  with pytest.raises(UserError, match="p.jpg: cannot be read"):
    om.read_image(tmp_path / "p.jpg")


def test_mismatched_sizes_name_the_odd_photo(tmp_path):
  paths = [tmp_path / "a.png", tmp_path / "b.png"]
  with pytest.raises(UserError, match="b.png: photo is 5x4 but a.png is 6x4"):
    om.check_same_size(paths, [np.zeros((4, 6, 3)), np.zeros((4, 5, 3))])


def test_scene_bundle_png_16bit_round_trip(tmp_path):
  from ofjax import scene
  a = RNG.random((6, 9, 3)).astype(np.float32)
  scene.save_png(tmp_path / "b.png", a, bits=16)
  # Quantisation to 16 bits: at most half a step of 1/65535.
  np.testing.assert_allclose(scene.read_png(tmp_path / "b.png"), a, rtol=0, atol=0.5 / 65535 + 1e-7)
