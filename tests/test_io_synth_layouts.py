"""Done-when for issue 4: one synthetic scene written in the OpticFusion layout and as a native
bundle (+ its ground-truth poses) reads back as the same cameras, rays and WLI depths."""

import json

import numpy as np
import pytest

from ofjax import synth
from ofjax.io import detect_layout, load
from ofjax.scene import om_rays, wli_rays

# The two layouts store depth as float32 in different units (layout units vs um): two roundings
# of 2^-24 relative each on depths smaller than the scene, so 1e-6 of the scene size bounds them.
REL_TOL = 1e-6


@pytest.fixture(scope="module")
def both_layouts(tmp_path_factory):
  root = tmp_path_factory.mktemp("synth")
  for layout in ("opticfusion", "native"):
    assert synth.main(["--scene", "seed", "--out", str(root / layout), "--layout", layout,
                       "--resolution", "tiny"]) == 0
  meta = json.loads((root / "opticfusion" / "ground_truth" / "meta.json").read_text())
  assert detect_layout(root / "opticfusion") == "opticfusion"
  assert detect_layout(root / "native") == "native"
  of = load(root / "opticfusion", um_per_unit=meta["um_per_unit"])
  native = load(root / "native", poses=root / "native" / "ground_truth" / "poses.json")
  return of, native, meta["size_um"]


@pytest.mark.slow
def test_same_wli_rays_and_depths(both_layouts):
  of, native, size = both_layouts
  assert of.units == native.units == "um"
  assert [s.name for s in of.wli] == [s.name for s in native.wli]
  for a, b in zip(of.wli, native.wli):
    assert a.shape == b.shape
    np.testing.assert_allclose(a.pixel_size, b.pixel_size, rtol=1e-12)
    (oa, da), (ob, db) = wli_rays(a), wli_rays(b)
    np.testing.assert_allclose(oa, ob, rtol=0, atol=REL_TOL * size)
    np.testing.assert_allclose(da, db, rtol=0, atol=REL_TOL)
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_allclose(a.depth, b.depth, rtol=0, atol=REL_TOL * size, equal_nan=True)


@pytest.mark.slow
def test_same_om_rays_and_photos(both_layouts):
  of, native, size = both_layouts
  assert [o.name for o in of.om] == [o.name for o in native.om]
  for a, b in zip(of.om, native.om):
    np.testing.assert_allclose(a.K, b.K, rtol=1e-12)
    (oa, da), (ob, db) = om_rays(a), om_rays(b)
    np.testing.assert_allclose(oa, ob, rtol=0, atol=REL_TOL * size)
    np.testing.assert_allclose(da, db, rtol=0, atol=REL_TOL)
    np.testing.assert_array_equal(a.image, b.image)
