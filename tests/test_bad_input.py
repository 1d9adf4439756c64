"""Bad input at scale: every case runs a CLI as a user would (a subprocess) and must exit with code
2 and one line `ofjax: error: ...` naming the file or option, with no traceback and nothing new
written. The cases run in parallel (each pays a Python + JAX import); each has its own folder.
"""

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))


def _cap(t, n_om=6, om_hw=(24, 32), poses=True, n_wli=5):
  """The analytic cap scene as a native bundle in t/s (with poses.json unless told)."""
  import analytic_scene
  from ofjax.scene import save_scene
  scene, _ = analytic_scene.make(wli_px=24, om_hw=om_hw, n_om=n_om)
  scene.wli = scene.wli[:n_wli]
  return save_scene(scene, t / "s", write_poses=poses)


def _cap_with(t, fn):
  d = _cap(t)
  fn(d)
  return d


def _edit_poses(d, fn):
  path = d / "poses.json"
  poses = json.loads(path.read_text())
  fn(poses)
  path.write_text(json.dumps(poses))
  return d


def _truncate(path):
  path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _set_depth(d, depth, name="0001", **more):
  np.savez(d / "wli" / f"{name}.npz", depth=depth, **more)
  return d


def _resize_photo(d, name="0003", hw=(20, 32)):
  Image.fromarray(np.zeros(hw + (3,), np.uint8)).save(d / "om" / f"{name}.png")
  return d


def _add_junk_scan(d):
  """A scan of random heights that overlaps nothing: association must refuse it."""
  meta = json.loads((d / "scene.json").read_text())
  rng = np.random.default_rng(0)
  np.savez(d / "wli" / "junk.npz", depth=rng.uniform(150, 250, (24, 24)).astype(np.float32))
  meta["wli"].append({**meta["wli"][0], "name": "junk", "file": "wli/junk.npz"})
  (d / "scene.json").write_text(json.dumps(meta))
  return d


def _of(t, breaker=None):
  from test_io_opticfusion import write_opticfusion
  write_opticfusion(t / "of")
  if breaker:
    breaker(t / "of")
  return t / "of"


def _of_npz(key, value):
  def brk(root):
    z = dict(np.load(root / "wl" / "0000.npz"))
    z[key] = value
    np.savez(root / "wl" / "0000.npz", **z)
  return brk


def _file(t, name="f.txt"):
  (t / name).write_text("x")
  return t / name


def _run_dir(t):
  (t / "run").mkdir()
  (t / "run" / "notes.txt").write_text("a previous result")
  return t / "run"


def train(data, *extra):
  return ["ofjax.train", "--data", data, "--out", "{t}/run", "--steps", "5", "--rays", "32",
          "--quiet", *extra]


def assoc(scene, *extra):
  return ["ofjax.associate", scene, *extra]


# name: (make(t) -> argv (module first, "{t}" = the case folder), expected part of the error line)
CASES = {
    # out-of-range options
    "steps 0": (lambda t: train(_cap(t), "--steps", "0"), "--steps 0: must be a positive"),
    "rays -1": (lambda t: train(_cap(t), "--rays", "-1"), "--rays -1: must be a positive"),
    "modalities foo": (lambda t: train(_cap(t), "--modalities", "foo"), "--modalities 'foo'"),
    "checkpoint-every 0": (lambda t: train(_cap(t), "--checkpoint-every", "0"),
                           "--checkpoint-every 0"),
    "keep-checkpoints -3": (lambda t: train(_cap(t), "--keep-checkpoints", "-3"),
                            "--keep-checkpoints -3"),
    "resume and overwrite": (lambda t: train(_cap(t), "--resume", "--overwrite"),
                             "--resume and --overwrite: choose one"),
    "zero factor": (lambda t: train(_of(t), "--um-per-unit", "0"), "--um-per-unit: 0.0 is not"),
    "negative factor": (lambda t: train(_of(t), "--um-per-unit", "-2"), "--um-per-unit: -2.0"),
    "factor on native": (lambda t: train(_cap(t), "--um-per-unit", "2"),
                         "--um-per-unit: the native layout is already in micrometres"),
    "max-features 0": (lambda t: assoc(_cap(t), "--max-features", "0"), "--max-features"),
    "export from a non-run dir": (lambda t: ["ofjax.export", _run_dir(t)],
                                  "config.json: not found; is"),
    # run directories
    "run dir not empty": (lambda t: train(_cap(t)) + ["--out", _run_dir(t)], "run: not empty"),
    "out is a file": (lambda t: train(_cap(t)) + ["--out", _file(t)], "f.txt: is a file"),
    "resume without run": (lambda t: train(_cap(t), "--resume"),
                           "config.json: not found, so there is no run to resume"),
    # scene folders and files
    "missing data": (lambda t: train(t / "nope"), "nope: not found"),
    "unknown layout": (lambda t: train((t / "empty").mkdir() or t / "empty"), "unknown layout"),
    "truncated npz": (lambda t: train(_cap_with(t, lambda d: _truncate(d / "wli" / "0001.npz"))),
                      "0001.npz: cannot read the WLI depth map"),
    "3-D depth": (lambda t: train(_set_depth(_cap(t), np.ones((4, 4, 2), np.float32))),
                  "0001.npz: depth must be a 2-D map"),
    "all-NaN depth": (lambda t: train(_set_depth(_cap(t), np.full((24, 24), np.nan, np.float32))),
                      "0001.npz: every pixel is a void"),
    "intensity of another shape": (lambda t: train(_set_depth(
        _cap(t), np.ones((24, 24), np.float32), intensity=np.ones((12, 24), np.float32))),
                                   "0001.npz: intensity image (12, 24) and depth map (24, 24)"),
    "truncated png": (lambda t: train(_cap_with(t, lambda d: _truncate(d / "om" / "0002.png"))),
                      "0002.png: cannot be read as an image"),
    "empty png": (lambda t: train(_cap_with(t, lambda d: (d / "om" / "0002.png").write_bytes(b""))),
                  "0002.png: cannot be read as an image"),
    "of: all-void depth": (lambda t: train(_of(t, _of_npz("depth_map", np.full((6, 8), np.nan))),
                                           "--um-per-unit", "1"), "0000.npz: every pixel is a void"),
    "of: string depth": (lambda t: train(_of(t, _of_npz("depth_map", np.array(["a", "b"]))),
                                         "--um-per-unit", "1"), "0000.npz"),
    "of: 2x2 extrinsic": (lambda t: train(_of(t, _of_npz("extrinsic_mat", np.eye(2))),
                                          "--um-per-unit", "1"), "0000.npz"),
    "of: no camera.xml": (lambda t: train(_of(t, lambda r: (r / "op" / "camera.xml").unlink()),
                                          "--um-per-unit", "1"), "camera.xml: not found"),
    # poses
    "NaN in poses": (lambda t: train(_edit_poses(_cap(t), lambda p: p["cameras"][0]["c2w"][0]
                                                 .__setitem__(1, float("nan")))),
                     "not a finite 4x4"),
    "inf in poses": (lambda t: train(_edit_poses(_cap(t), lambda p: p["cameras"][3]["c2w"][2]
                                                 .__setitem__(3, float("inf")))),
                     "not a finite 4x4"),
    "missing poses file": (lambda t: train(_cap(t), "--poses", t / "p.json"),
                           "p.json: poses file not found"),
    "corrupt poses file": (lambda t: train(_cap_with(t, lambda d: _truncate(d / "poses.json"))),
                           "poses.json: not a valid poses JSON"),
    "unposed scene": (lambda t: train(_cap(t, poses=False)), "has no pose; run `python -m ofjax.associate` first"),
    # association
    "too few OM photos": (lambda t: assoc(_cap(t, n_om=2, poses=False, n_wli=1)),
                          "2 OM photo(s); structure-from-motion needs at least 3"),
    "photo sizes differ": (lambda t: assoc(_resize_photo(_cap(t, poses=False, n_wli=1))),
                           "om: photos have different sizes"),
    "non-overlapping scan": (lambda t: assoc(_add_junk_scan(_cap(t, poses=False, n_wli=1))),
                             "scan(s) junk (best fitness"),
    "associate missing scene": (lambda t: assoc(t / "nope"), "scene.json: not found"),
}


def _listing(t):
  return sorted(str(p.relative_to(t)) for p in t.rglob("*"))


def _run_case(item, root):
  name, (make, expected) = item
  t = root / name.replace(" ", "_").replace(":", "")
  t.mkdir()
  argv = [str(a).replace("{t}", str(t)) for a in make(t)]
  before = _listing(t)
  res = subprocess.run([sys.executable, "-m", *argv], cwd=t, capture_output=True, text=True,
                       timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
  return name, res, expected, before, _listing(t)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
  root = tmp_path_factory.mktemp("bad")
  with ThreadPoolExecutor(max_workers=4) as pool:
    return {name: rest for name, *rest in pool.map(lambda it: _run_case(it, root), CASES.items())}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_exits_2_with_one_line(results, name):
  res, expected, before, after = results[name]
  err = [ln for ln in res.stderr.splitlines() if not ln.startswith("ofjax: warning:")]
  assert "Traceback" not in res.stderr, res.stderr
  assert res.returncode == 2, (res.returncode, res.stderr)
  assert len(err) == 1 and err[0].startswith("ofjax: error: "), res.stderr
  assert expected in err[0], err[0]
  assert after == before  # nothing written, not even a run directory


def test_at_least_twenty_cases():
  assert len(CASES) >= 20


def test_user_error_is_one_line_whatever_it_quotes():
  """A library's exception text can carry a file's own bytes (seen: a fuzzed .sur's unit field
  with a newline, quoted by surfalize's ValueError); the message stays one line."""
  from ofjax.errors import UserError
  e = UserError("f.sur: surfalize cannot read it (ValueError: Unit \n\r\tum does not exist.); fix")
  assert str(e) == "f.sur: surfalize cannot read it (ValueError: Unit um does not exist.); fix"
