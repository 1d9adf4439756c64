"""Property-based tests: random and mutated files fed to the readers raise only UserError.

Each reader gets a valid seed file, then hypothesis truncates it, flips bytes in it, or replaces it
with random bytes; the reader must either return or raise ofjax.errors.UserError (the documented
error), never anything else.
"""

import io
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from ofjax import scene as scene_lib
from ofjax.errors import UserError
from ofjax.io import om, opticfusion, wli

FUZZ = settings(max_examples=200, deadline=None, database=None,
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


READERS = {
    "npy": (".npy", _npy, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "npz": (".npz", _npz, lambda p: wli.read_height_map(p, pixel_size=1.0)),
    "png": (".png", _png, om.read_image),
    "aln": (".aln", _aln, opticfusion.read_aln),
    "camera.xml": (".xml", _xml, opticfusion.read_metashape),
    "poses.json": (".json", _poses, scene_lib.load_poses),
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


@pytest.mark.parametrize("name", list(READERS))
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
