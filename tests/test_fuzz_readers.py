"""Property-based tests: random and mutated files fed to the readers raise only UserError.

Each reader gets a valid seed file, then hypothesis truncates it, flips bytes in it, or replaces it
with random bytes; the reader must either return or raise ofjax.errors.UserError (the documented
error), never anything else. The native bundle (scene.load_scene) has each of its files mutated in
turn, its JSON files also as documents.
"""

import io
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from ofjax import scene as scene_lib
from ofjax.errors import UserError
from ofjax.io import om, opticfusion, wli

sys.path.insert(0, str(Path(__file__).parent))

# OFJAX_FUZZ_EXAMPLES=N runs N examples per reader instead of 200 (a deeper search by hand);
# OFJAX_FUZZ_RANDOM=1 draws new examples each run. By default the examples are the same in every
# run (derandomize), so that a failure found in CI is found again by the next run.
FUZZ = settings(max_examples=int(os.environ.get("OFJAX_FUZZ_EXAMPLES", 200)), deadline=None,
                database=None, derandomize=not os.environ.get("OFJAX_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _npy():
  buf = io.BytesIO()
  np.save(buf, np.random.default_rng(0).normal(size=(6, 7)))
  return buf.getvalue()


def _npz():
  buf = io.BytesIO()
  np.savez(buf, height=np.random.default_rng(1).normal(size=(5, 4)))
  return buf.getvalue()


def _png():
  buf = io.BytesIO()
  Image.fromarray(np.random.default_rng(2).integers(0, 256, (6, 5, 3), dtype=np.uint8)).save(
      buf, format="PNG")
  return buf.getvalue()


def _aln():
  m = "\n".join(" ".join(str(v) for v in row) for row in np.eye(4))
  return f"1\nscan.ply\n#\n{m}\n0\n".encode()


def _poses():
  return json.dumps({"cameras": [{"modality": "wli", "name": "0000", "c2w": np.eye(4).tolist()}]
                     }).encode()


def _xml():
  return (b'<?xml version="1.0"?><document><chunk><sensors><sensor id="0"><resolution width="5" '
          b'height="6"/><calibration><f>20</f></calibration></sensor></sensors><cameras>'
          b'<camera id="0" sensor_id="0" label="0000"><transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1'
          b'</transform></camera></cameras></chunk></document>')


# Instrument formats whose writers want a path: surfalize (.x3p, .sur), tifffile, h5py (.datx).


def _written(name, write):
  """The bytes of a small valid file that `write(path)` makes (writers that want a path)."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / name
    write(path)
    return path.read_bytes()


def _heights(seed):
  return np.random.default_rng(seed).normal(size=(6, 7))


def _surfalize(ext):
  import surfalize
  return lambda: _written(f"m.{ext}", lambda p: surfalize.Surface(_heights(3), 0.5, 0.5).save(p))


def _tif():
  import tifffile
  return _written("m.tif", lambda p: tifffile.imwrite(p, _heights(4).astype(np.float32)))


def _datx():
  from test_io_datx import write_datx
  return _written("m.datx", lambda p: write_datx(p, _heights(5) * 100.0))


def _read_datx(path):
  from ofjax.io import datx
  return datx.read_datx(path)


READERS = {
    "npy": (".npy", _npy, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "npz": (".npz", _npz, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "png": (".png", _png, om.read_image),
    "aln": (".aln", _aln, opticfusion.read_aln),
    "camera.xml": (".xml", _xml, opticfusion.read_metashape),
    "poses.json": (".json", _poses, scene_lib.load_poses),
    "x3p": (".x3p", _surfalize("x3p"), wli.read_height_map),
    "sur": (".sur", _surfalize("sur"), wli.read_height_map),
    "tif": (".tif", _tif, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "tiff": (".tiff", _tif, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "datx": (".datx", _datx, _read_datx),
}


@st.composite
def mutated(draw, seed: bytes):
  kind = draw(st.sampled_from(["truncate", "flip", "random"]))
  if kind == "truncate":
    return seed[:draw(st.integers(0, max(len(seed) - 1, 0)))]
  if kind == "random":
    return draw(st.binary(max_size=2 * len(seed)))
  data = bytearray(seed)
  for _ in range(draw(st.integers(1, 8))):
    i = draw(st.integers(0, len(data) - 1))
    data[i] = draw(st.integers(0, 255))
  return bytes(data)


@pytest.mark.parametrize("name", READERS)
def test_reader_raises_only_user_errors(tmp_path, name):
  suffix, make, read = READERS[name]
  seed = make()
  read_path = tmp_path / f"f{suffix}"
  read_path.write_bytes(seed)
  read(read_path)  # the seed itself is valid

  @FUZZ
  @given(data=mutated(seed))
  def check(data):
    read_path.write_bytes(data)
    try:
      read(read_path)
    except UserError as e:
      assert "\n" not in str(e) and str(read_path.name) in str(e)

  check()


# The native bundle: every file of a tiny scene is mutated as bytes, and its JSON files also as
# documents (a value replaced by another JSON value, or a key dropped), which reaches the
# structure checks that byte mutations mostly stop short of (invalid JSON).
json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-3, 10**6) | st.floats() | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=3), max_leaves=8)


def _nodes(doc, at=()):
  """Paths (key tuples) of every node of a JSON document below the root."""
  items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
  for k, v in items:
    yield at + (k,)
    yield from _nodes(v, at + (k,))


@st.composite
def mutated_json(draw, seed: bytes):
  doc = json.loads(seed)
  at = draw(st.sampled_from(list(_nodes(doc))))
  parent = doc
  for k in at[:-1]:
    parent = parent[k]
  if isinstance(parent, dict) and draw(st.booleans()):
    del parent[at[-1]]
  else:
    parent[at[-1]] = draw(json_values)
  return json.dumps(doc).encode()


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
  import analytic_scene
  scene, _ = analytic_scene.make(wli_px=6, om_hw=(4, 5), n_om=1)
  scene.wli = scene.wli[:1]
  scene.normalization = scene_lib.compute_normalization(scene)
  return scene, scene_lib.save_scene(scene, tmp_path_factory.mktemp("bundle") / "s",
                                     write_poses=True)


BUNDLE_FILES = ("scene.json", "poses.json", "wli/0000.npz", "om/0000.png")


def test_load_scene_raises_only_user_errors(bundle):
  scene, bundle = bundle
  seeds = {name: (bundle / name).read_bytes() for name in BUNDLE_FILES}
  # The seed bundle is valid and reads back as written (the checks must not change a field).
  for poses in (None, False):
    back = scene_lib.load_scene(bundle, poses=poses)
    assert back.normalization == scene.normalization
    for a, b in zip(back.wli + back.om, scene.wli + scene.om):
      assert a.name == b.name and (a.c2w is None if poses is False else
                                   np.array_equal(a.c2w, b.c2w))
    assert [(s.pixel_size, s.prior) for s in back.wli] == [(s.pixel_size, s.prior)
                                                          for s in scene.wli]
    np.testing.assert_array_equal(back.om[0].K, scene.om[0].K)

  @FUZZ
  @given(data=st.data())
  def check(data):
    name = data.draw(st.sampled_from(BUNDLE_FILES))
    seed = seeds[name]
    structural = name.endswith(".json") and data.draw(st.booleans())
    (bundle / name).write_bytes(data.draw(mutated_json(seed) if structural else mutated(seed)))
    try:
      scene_lib.load_scene(bundle)
    except UserError as e:
      assert "\n" not in str(e) and str(bundle) in str(e), str(e)
    finally:
      (bundle / name).write_bytes(seed)

  check()
