"""The demo's roughness of the true surface: the truth moved into the poses' frame, then sampled."""

import json

import numpy as np
import pytest

from ofjax import demo, metrology, synth
from ofjax.meshquery import load_mesh


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
  out = tmp_path_factory.mktemp("demo") / "scene"
  assert synth.main(["--scene", "seed", "--resolution", "tiny", "--out", str(out)]) == 0
  return out


def test_truth_roughness_reads_the_true_surface_in_the_poses_frame(scene_dir, tmp_path):
  """Poses shifted by d (as an association's frame differs from the truth's by a rigid motion):
  the region shifted by d reads what the unshifted region reads on the true surface itself."""
  d = np.array([37.0, -21.0, 5.0])
  poses = json.loads((scene_dir / "ground_truth" / "poses.json").read_text())
  for cam in poses["cameras"]:
    for i in range(3):
      cam["c2w"][i][3] += d[i]
  shifted = tmp_path / "poses.json"
  shifted.write_text(json.dumps(poses))
  truth = load_mesh(scene_dir / "ground_truth" / "mesh.ply")
  v = np.asarray(truth.vertices)
  c, half = (v.min(0) + v.max(0)) / 2, 0.1 * np.ptp(v[:, :2], 0).min()
  region = (c[0] - half, c[1] - half, c[0] + half, c[1] + half)
  expected = metrology.areal_parameters(
      metrology.sample_region(v, np.asarray(truth.faces), region, n=64).z)
  moved = (region[0] + d[0], region[1] + d[1], region[2] + d[0], region[3] + d[1])
  got = demo.truth_roughness(scene_dir, shifted, moved, 64)
  assert expected["Sq"] > 0.01  # the region is not flat: the comparison means something
  for k in ("Sa", "Sq", "Sp", "Sv", "Sz"):
    assert got[k] == pytest.approx(expected[k], rel=1e-3, abs=1e-4), k
  # Unshifted, the region lands elsewhere on the sample and reads otherwise.
  assert demo.truth_roughness(scene_dir, shifted, region, 64)["Sq"] != pytest.approx(
      expected["Sq"], rel=1e-2)
