"""Zygo .datx reading (ofjax.io.datx) on HDF5 files written by h5py in Mx's structure."""

import h5py
import numpy as np
import pytest

from ofjax.errors import UserError
from ofjax.io import wli

NO_DATA = np.finfo(np.float64).max  # what Mx writes for float surfaces
SURF_KEY = "{5A2C7D0E-0000-0000-0000-000000000001}"
DECOY_KEY = "{0000DECO-0000-0000-0000-000000000000}"  # sorts first: MetaData must be followed
CONVERTER = np.dtype([("Category", h5py.string_dtype()), ("BaseUnit", h5py.string_dtype()),
                      ("Parameters", h5py.vlen_dtype(np.float64))])
RNG = np.random.default_rng(11)


def _converter(base, step):
  c = np.zeros(1, CONVERTER)
  c[0] = ("LateralCat", base, np.array([0.0, step, 0.0, 0.0]))
  return c


def write_datx(path, values, unit=b"NanoMeters", steps=(0.8e-6, 0.9e-6), extra=None,
               lateral=None, metadata=True, intensity=None):
  """A .datx as Mx lays it out: MetaData links, Data/Surface/<guid> with its attributes, and
  optionally Data/Intensity/<guid> (its "No Data" the surface's)."""
  with h5py.File(path, "w") as f:
    if intensity is not None:
      f.create_dataset("Data/Intensity/{INT}", data=intensity).attrs["No Data"] = np.array(
          [NO_DATA])
    surf = f.create_group("Data/Surface")
    surf.create_dataset(DECOY_KEY, data=np.zeros_like(values))
    ds = surf.create_dataset(SURF_KEY, data=values)
    ds.attrs["No Data"] = np.array([NO_DATA])
    if unit is not None:
      ds.attrs["Unit"] = np.array([unit])
    if steps is not None:
      ds.attrs["X Converter"] = _converter("Meters", steps[0])
      ds.attrs["Y Converter"] = _converter("Meters", steps[1])
    for k, v in (extra or {}).items():
      ds.attrs[k] = np.array([v])
    if lateral is not None:
      g = f.create_group("Attributes/{ATTR-GUID}")
      g.attrs["Data Context.Lateral Resolution:Value"] = np.array([lateral])
      g.attrs["Data Context.Lateral Resolution:Unit"] = np.array([b"Meters"])
    if metadata:
      table = np.array([("Root", "Measurement", "{MEAS}"),
                        ("{MEAS}", "Surface", f"/Data/Surface/{SURF_KEY}")],
                       dtype=[("Source", h5py.string_dtype()), ("Link", h5py.string_dtype()),
                              ("Destination", h5py.string_dtype())])
      f.create_dataset("MetaData", data=table)


def _values(h=12, w=15):
  v = RNG.normal(0, 400, (h, w))
  v[3:5, 2:6] = NO_DATA
  return v


def test_nanometres_and_converter_steps(tmp_path):
  v = _values()
  write_datx(tmp_path / "m.datx", v)
  hm = wli.read_height_map(tmp_path / "m.datx")
  ref = np.where(v >= NO_DATA, np.nan, v / 1000.0)  # nm -> um
  np.testing.assert_allclose(hm.height, ref, rtol=1e-12, equal_nan=True)
  np.testing.assert_allclose(hm.pixel_size, (0.8, 0.9), rtol=1e-12)
  assert hm.source["surface"] == SURF_KEY and hm.source["reader"] == "h5py"


def test_intensity_on_the_same_pixels_is_read_and_other_shapes_left_out(tmp_path):
  v = _values()
  light = RNG.uniform(0, 4000, v.shape)
  light[0, 0] = NO_DATA
  write_datx(tmp_path / "m.datx", v, intensity=light)
  hm = wli.read_height_map(tmp_path / "m.datx")
  np.testing.assert_array_equal(hm.intensity, np.where(light >= NO_DATA, np.nan, light))
  scan = wli.to_scan("m", hm)
  assert scan.intensity.dtype == np.float32 and scan.intensity.shape == scan.depth.shape
  write_datx(tmp_path / "binned.datx", v, intensity=light[::2, ::2])
  assert wli.read_height_map(tmp_path / "binned.datx").intensity is None
  write_datx(tmp_path / "none.datx", v)
  assert wli.read_height_map(tmp_path / "none.datx").intensity is None


def test_fringes_use_wavelength_scale_and_obliquity(tmp_path):
  v = _values() / 1000.0
  extra = {"Wavelength": 0.57e-6, "Interferometric Scale Factor": 0.5, "Obliquity Factor": 1.04}
  write_datx(tmp_path / "m.datx", v, unit=b"Fringes", extra=extra)
  hm = wli.read_height_map(tmp_path / "m.datx")
  ref = np.where(v >= NO_DATA, np.nan, v * 0.5 * 1.04 * 0.57)  # fringes -> um
  np.testing.assert_allclose(hm.height, ref, rtol=1e-12, equal_nan=True)


def test_lateral_resolution_attribute_without_converters(tmp_path):
  write_datx(tmp_path / "m.datx", _values(), unit=b"MicroMeters", steps=None, lateral=1.25e-6,
             metadata=False)
  hm = wli.read_height_map(tmp_path / "m.datx")
  np.testing.assert_allclose(hm.pixel_size, (1.25, 1.25), rtol=1e-12)


def test_content_not_extension_picks_the_reader(tmp_path):
  write_datx(tmp_path / "m.h5", _values())  # HDF5 magic, unusual name
  assert wli.read_height_map(tmp_path / "m.h5").pixel_size == pytest.approx((0.8, 0.9))


@pytest.mark.parametrize("kwargs, match", [
    ({"unit": b"Furlongs"}, "unknown height unit 'Furlongs'"),
    ({"unit": None}, "no 'Unit' attribute"),
    ({"unit": b"Fringes"}, "attribute 'Wavelength' is missing"),
    ({"steps": None}, "no lateral resolution"),
])
def test_incomplete_attributes_are_user_errors(tmp_path, kwargs, match):
  write_datx(tmp_path / "m.datx", _values(), **kwargs)
  with pytest.raises(UserError, match=match):
    wli.read_height_map(tmp_path / "m.datx")


def test_all_void_and_truncated_files_are_user_errors(tmp_path):
  write_datx(tmp_path / "void.datx", np.full((5, 5), NO_DATA))
  with pytest.raises(UserError, match="void.datx: every pixel is a void"):
    wli.read_height_map(tmp_path / "void.datx")
  write_datx(tmp_path / "cut.datx", _values(64, 64))
  data = (tmp_path / "cut.datx").read_bytes()
  (tmp_path / "cut.datx").write_bytes(data[: len(data) // 3])
  with pytest.raises(UserError, match="cut.datx: cannot read the .datx file"):
    wli.read_height_map(tmp_path / "cut.datx")


def test_intensity_only_file_is_a_user_error(tmp_path):
  with h5py.File(tmp_path / "m.datx", "w") as f:
    f.create_dataset("Data/Intensity/{I}", data=np.ones((4, 4)))
  with pytest.raises(UserError, match="no /Data/Surface"):
    wli.read_height_map(tmp_path / "m.datx")


def test_a_file_that_crashes_hdf5_is_a_user_error():
  # tests/data/damaged_converter.datx is a valid .datx (write_datx) with one byte changed inside
  # a converter attribute's variable-length data: reading that attribute in-process segfaulted
  # (h5py 3.16, HDF5 2.0). read_datx reads in a child, so this process survives and says so.
  from pathlib import Path
  path = Path(__file__).parent / "data" / "damaged_converter.datx"
  with pytest.raises(UserError, match="damaged_converter.datx: cannot read the .datx") as e:
    wli.read_height_map(path)
  assert "\n" not in str(e.value)


def test_the_child_reports_user_errors_as_one_line(tmp_path):
  write_datx(tmp_path / "m.datx", _values(), unit=b"Furlongs")
  with pytest.raises(UserError) as e:
    wli.read_height_map(tmp_path / "m.datx")
  # The child's own message, not its "ofjax: error:" prefix nor a generic crash note.
  assert str(e.value).startswith(f"{tmp_path / 'm.datx'}: unknown height unit 'Furlongs'")
