"""WLI height maps (ofjax.io.wli) on files written by surfalize, numpy and tifffile."""

import numpy as np
import pytest
import surfalize
import tifffile

from ofjax.errors import UserError
from ofjax.io import wli
from ofjax.scene import wli_points

RNG = np.random.default_rng(3)
SX, SY = 0.5, 0.7  # um, deliberately different so that x and y cannot be swapped unnoticed


def _heights(h=24, w=32):
  y, x = np.mgrid[:h, :w]
  z = 3.0 * np.sin(x / 4.0) + 0.2 * y + RNG.normal(0, 0.05, (h, w))  # um
  z[2:5, 3:7] = np.nan  # a void
  return z


# Tolerance per writer: x3p/sdf store float64; .sur/.al3d quantise heights to integers with a
# float32 z-spacing and offset, .tmd stores float32: all far below a WLI's ~1e-4 um z-resolution.
@pytest.mark.parametrize("ext, atol", [("x3p", 1e-12), ("sdf", 1e-12), ("sur", 1e-5),
                                       ("al3d", 1e-5), ("tmd", 1e-5)])
def test_surfalize_writers_round_trip(tmp_path, ext, atol):
  z = _heights()
  with pytest.warns(UserWarning, match="different pixel size"):
    surf = surfalize.Surface(z, SX, SY)
  surf.save(tmp_path / f"m.{ext}")
  with pytest.warns(UserWarning, match="different pixel size"):
    hm = wli.read_height_map(tmp_path / f"m.{ext}")
  assert hm.height.shape == z.shape
  np.testing.assert_array_equal(np.isnan(hm.height), np.isnan(z))
  np.testing.assert_allclose(hm.height, z, rtol=0, atol=atol, equal_nan=True)
  np.testing.assert_allclose(hm.pixel_size, (SX, SY), rtol=1e-6)
  assert hm.source["reader"] == "surfalize"


@pytest.mark.parametrize("kind", ["npy", "npz", "tif"])
def test_plain_arrays_need_and_use_a_pixel_size(tmp_path, kind):
  z = _heights()
  path = tmp_path / f"m.{kind}"
  if kind == "npy":
    np.save(path, z)
  elif kind == "npz":
    np.savez(path, height=z, intensity=np.ones_like(z))
  else:
    tifffile.imwrite(path, z.astype(np.float32))
  with pytest.raises(UserError, match=r"--pixel-size"):
    wli.read_height_map(path)
  hm = wli.read_height_map(path, pixel_size=0.8)
  atol = 1e-5 if kind == "tif" else 0  # float32 TIFF
  np.testing.assert_allclose(hm.height, z, rtol=0, atol=atol, equal_nan=True)
  assert hm.pixel_size == (0.8, 0.8)


def test_npz_intensity_on_the_same_pixels_becomes_the_scans(tmp_path):
  z = _heights()
  light = np.linspace(0.0, 1.0, z.size).reshape(z.shape)
  np.savez(tmp_path / "m.npz", height=z, intensity=light)
  hm = wli.read_height_map(tmp_path / "m.npz", pixel_size=0.8)
  np.testing.assert_array_equal(hm.intensity, light)
  np.testing.assert_array_equal(wli.to_scan("m", hm).intensity, light.astype(np.float32))
  np.savez(tmp_path / "other.npz", height=z, intensity=light[:, :-1])
  assert wli.read_height_map(tmp_path / "other.npz", pixel_size=0.8).intensity is None


def test_npz_without_a_height_key_is_a_user_error(tmp_path):
  np.savez(tmp_path / "m.npz", a=_heights(), b=_heights())
  with pytest.raises(UserError, match="none named height"):
    wli.read_height_map(tmp_path / "m.npz", pixel_size=1.0)


def test_depth_convention_puts_the_height_on_world_z(tmp_path):
  z = _heights(10, 14)
  hm = wli.HeightMap(z, (SX, SY), {})
  scan = wli.to_scan("s", hm)
  assert np.nanmin(scan.depth) == 0  # the image plane touches the highest point
  scan.c2w = wli.height_c2w(scan)
  pts = wli_points(scan)
  # Independent reference: column c -> x = (c + 0.5 - W/2) sx, row r -> y = -(r + 0.5 - H/2) sy.
  h, w = z.shape
  r, c = np.nonzero(np.isfinite(z))
  ref = np.stack([(c + 0.5 - w / 2) * SX, -(r + 0.5 - h / 2) * SY, z[r, c]], -1)
  np.testing.assert_allclose(pts, ref, rtol=0, atol=1e-5)  # depth is float32 (~1e-6 um here)


@pytest.mark.parametrize("make, match", [
    (lambda: np.full((6, 6), np.nan), "every pixel is a void"),
    (lambda: np.where(np.eye(6) > 0, np.nan, 2.5), "constant height map"),
    (lambda: np.zeros(12), "not a 2-D map"),
    (lambda: np.ones((1, 9)), "not a 2-D map"),
    (lambda: np.ones((4, 4), bool), "not numbers"),
])
def test_bad_maps_are_user_errors(tmp_path, make, match):
  np.save(tmp_path / "m.npy", make())
  with pytest.raises(UserError, match=match):
    wli.read_height_map(tmp_path / "m.npy", pixel_size=1.0)


def test_truncated_x3p_is_a_user_error(tmp_path):
  surfalize.Surface(_heights(), SX, SX).save(tmp_path / "m.x3p")
  data = (tmp_path / "m.x3p").read_bytes()
  (tmp_path / "m.x3p").write_bytes(data[: len(data) // 2])
  with pytest.raises(UserError, match="m.x3p: surfalize cannot read it"):
    wli.read_height_map(tmp_path / "m.x3p")


def test_unknown_or_mislabelled_files_are_user_errors(tmp_path):
  (tmp_path / "m.txt").write_text("1 2 3")
  with pytest.raises(UserError, match="unknown WLI file type '.txt'"):
    wli.read_height_map(tmp_path / "m.txt")
  (tmp_path / "m.datx").write_bytes(b"not hdf5 at all")
  with pytest.raises(UserError, match="m.datx: is not an HDF5 file"):
    wli.read_height_map(tmp_path / "m.datx")


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "abc", (1, 2, 3)])
def test_pixel_size_must_be_positive_and_finite(bad):
  with pytest.raises(UserError, match="--pixel-size"):
    wli.check_pixel_size(bad)
