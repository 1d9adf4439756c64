"""`python -m ofjax.inspect` as a user runs it: a report and contact sheet for good folders, one
line on stderr and exit code 2 (no traceback) for every kind of bad input."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from test_io_opticfusion import write_opticfusion

REPO = Path(__file__).resolve().parents[1]


def run_inspect(args, cwd):
  return subprocess.run([sys.executable, "-m", "ofjax.inspect", *map(str, args)], cwd=cwd,
                        capture_output=True, text=True, timeout=120,
                        env={**os.environ, "PYTHONPATH": str(REPO)})


def write_raw(root, sizes=((10, 12), (10, 12)), maps=None):
  """A raw folder: wli/*.npy height maps (um) and om/*.png photos."""
  (root / "wli").mkdir(parents=True)
  (root / "om").mkdir()
  rng = np.random.default_rng(5)
  for i, m in enumerate(maps if maps is not None else [rng.normal(size=(8, 9))] * 2):
    np.save(root / "wli" / f"s{i}.npy", m)
  for i, hw in enumerate(sizes):
    img = rng.integers(0, 256, hw + (3,), dtype=np.uint8)
    Image.fromarray(img).save(root / "om" / f"{i:04d}.png")
  return root


def test_opticfusion_report_and_contact_sheet(tmp_path):
  write_opticfusion(tmp_path / "of", n_om=4, unaligned=(2,))
  res = run_inspect([tmp_path / "of", "--um-per-unit", "50", "--out", tmp_path / "sheet.png"],
                    tmp_path)
  assert res.returncode == 0, res.stderr
  assert "layout opticfusion, units um, 2 WLI scans, 3 OM photos, posed" in res.stdout
  assert "wli 0000: 8x6 px, pixel 62.5 x 83.33 um, voids 6.2%" in res.stdout  # 3 of 48 void
  assert "om  0003: 12x10 px, f 20.0 px, posed" in res.stdout
  assert "ofjax: warning:" in res.stderr and "'0002' has no <transform>" in res.stderr
  with Image.open(tmp_path / "sheet.png") as im:
    assert im.format == "PNG" and im.size[0] > 200


def test_raw_report_without_factor_and_default_sheet_name(tmp_path):
  write_raw(tmp_path / "mysample")
  res = run_inspect([tmp_path / "mysample", "--pixel-size", "0.4"], tmp_path)
  assert res.returncode == 0, res.stderr
  assert "layout raw, units um, 2 WLI scans, 2 OM photos, not posed" in res.stdout
  assert "pixel 0.4 x 0.4 um, voids 0.0%" in res.stdout and "f unknown (SfM)" in res.stdout
  assert (tmp_path / "mysample_contact.png").is_file()


def _of(tmp, breaker=None):
  write_opticfusion(tmp / "s")
  if breaker:
    breaker(tmp / "s")
  return tmp / "s"


def _truncate(path):
  data = path.read_bytes()
  path.write_bytes(data[: len(data) // 2])


def _nan_extrinsic(root):
  z = dict(np.load(root / "wl" / "0000.npz"))
  z["extrinsic_mat"][0, 3] = np.inf
  np.savez(root / "wl" / "0000.npz", **z)


def _native(tmp, poses_nan=False):
  """A native bundle written by ofjax.scene from the OpticFusion fixture."""
  from ofjax.io import load
  from ofjax.scene import save_scene
  scene = load(_of(tmp), um_per_unit=1.0)
  save_scene(scene, tmp / "n", write_poses=True)
  if poses_nan:
    poses = json.loads((tmp / "n" / "poses.json").read_text())
    poses["cameras"][0]["c2w"][0][0] = float("nan")
    (tmp / "n" / "poses.json").write_text(json.dumps(poses))
  return tmp / "n"


CASES = {
    "missing path": (lambda t: [t / "nope"], "nope: not found"),
    "unknown layout": (lambda t: [t], "unknown layout"),
    "file not folder": (lambda t: [(t / "f.txt").write_text("x") and t / "f.txt"], "is a file"),
    "no camera.xml": (lambda t: [_of(t, lambda r: (r / "op" / "camera.xml").unlink()),
                                 "--um-per-unit", "1"], "camera.xml: not found"),
    "no align.aln": (lambda t: [_of(t, lambda r: (r / "op" / "align.aln").unlink()),
                                "--um-per-unit", "1"], "align.aln: not found"),
    "truncated npz": (lambda t: [_of(t, lambda r: _truncate(r / "wl" / "0001.npz")),
                                 "--um-per-unit", "1"], "0001.npz: cannot read the npz"),
    "all-void depth": (lambda t: [_of(t, lambda r: np.savez(
        r / "wl" / "0000.npz", depth_map=np.full((6, 8), np.nan), extrinsic_mat=np.eye(4)[:3])),
        "--um-per-unit", "1"], "0000.npz: every pixel is a void"),
    "non-finite extrinsic": (lambda t: [_of(t, _nan_extrinsic), "--um-per-unit", "1"],
                             "0000.npz: extrinsic_mat holds non-finite"),
    "zero factor": (lambda t: [_of(t), "--um-per-unit", "0"], "--um-per-unit: 0.0 is not"),
    "negative factor": (lambda t: [_of(t), "--um-per-unit", "-2"], "--um-per-unit: -2.0"),
    "nan factor": (lambda t: [_of(t), "--um-per-unit", "nan"], "--um-per-unit: nan"),
    "forced wrong layout": (lambda t: [write_raw(t / "r"), "--layout", "opticfusion"],
                            "wl: folder not found"),
    "factor on raw": (lambda t: [write_raw(t / "r"), "--um-per-unit", "2", "--pixel-size", "1"],
                      "--um-per-unit: the raw layout is already in micrometres"),
    "corrupt png": (lambda t: [write_raw(t / "r"), "--pixel-size", "1"], None),
    "photo sizes differ": (lambda t: [write_raw(t / "r", sizes=((10, 12), (12, 10))),
                                      "--pixel-size", "1"], "0001.png: photo is 10x12"),
    "no pixel size": (lambda t: [write_raw(t / "r")], "s0.npy: a plain npy height map does not"),
    "zero pixel size": (lambda t: [write_raw(t / "r"), "--pixel-size", "0"], "--pixel-size: 0.0"),
    "constant map": (lambda t: [write_raw(t / "r", maps=[np.full((5, 5), 3.0)]), "--pixel-size",
                                "1"], "s0.npy: every measured value is 3"),
    "3-D map": (lambda t: [write_raw(t / "r", maps=[np.ones((4, 4, 3))]), "--pixel-size", "1"],
                "s0.npy: the height map has shape (4, 4, 3)"),
    "stray file": (lambda t: [(write_raw(t / "r") / "wli" / "notes.txt").write_text("hi") and
                              t / "r", "--pixel-size", "1"], "notes.txt: unknown WLI file type"),
    "missing om folder": (lambda t: [(t / "r" / "wli").mkdir(parents=True) or t / "r"],
                          "om: folder not found"),
    "missing native file": (lambda t: [(_native(t) / "wli" / "0001.npz").unlink() or t / "n"],
                            "0001.npz: WLI file listed in scene.json is missing"),
    "non-finite poses": (lambda t: [_native(t, poses_nan=True)], "not a finite 4x4"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_exits_2_with_one_line(tmp_path, name):
  make, expected = CASES[name]
  args = make(tmp_path)
  if name == "corrupt png":
    _truncate(tmp_path / "r" / "om" / "0001.png")
    expected = "0001.png: cannot be read as an image"
  res = run_inspect(args, tmp_path)
  err_lines = [ln for ln in res.stderr.splitlines() if not ln.startswith("ofjax: warning:")]
  assert res.returncode == 2, (res.stdout, res.stderr)
  assert "Traceback" not in res.stderr
  assert len(err_lines) == 1 and err_lines[0].startswith("ofjax: error: "), res.stderr
  assert expected in err_lines[0], err_lines[0]
  assert not list(tmp_path.glob("*_contact.png"))  # nothing partial written
