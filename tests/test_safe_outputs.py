"""Safe outputs: an interrupted or failed export, training or association keeps the previous result.

The interruptions are real SIGKILLs of real `python -m ofjax.<module>` subprocesses. To kill at the
moment that matters rather than at a guessed time, the subprocess installs a Python audit hook
(sys.addaudithook, the interpreter's own event mechanism; nothing of ofjax or a library is
replaced) that sends SIGKILL to its own process when the temporary file beside the result is
opened for writing ("written"), or when it is about to be renamed onto the result ("renamed"): the
write is then complete but not yet in place, the last moment an unsafe writer could have lost the
old file. A SIGKILL leaves no chance to clean up, so the hidden temporary `.<name>.*` may remain;
the result's own name must still hold the previous bytes.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
# One xdist worker runs the whole file (make test: --dist loadgroup), so `trained` trains once.
pytestmark = pytest.mark.xdist_group("safe_outputs")

TRAIN = ["--steps", "20", "--rays", "64", "--mesh-resolution", "24", "--quiet"]
EXPORT_RESOLUTION = "48"  # another resolution than the run's: the new mesh differs from the old

# Runs `python -m MODULE ARGS...` and SIGKILLs itself at MOMENT on the file named TARGET:
#   "written"  the temporary `.TARGET.*` exists and is being opened to write the content into it;
#   "renamed"  the temporary, complete, is about to be renamed onto TARGET.
KILLER = r"""
import os, runpy, signal, sys
moment, target, module, *args = sys.argv[1:]
def hook(event, a):
  if moment == "written" and event == "open" and isinstance(a[0], (str, bytes, os.PathLike)):
    path = os.fsdecode(a[0])  # open(path, mode, flags); an int is an already open descriptor
    hit = os.path.basename(path).startswith(f".{target}.") and os.path.exists(path)
  elif moment == "renamed" and event == "os.rename":  # os.replace(src, dst, ...) raises it too
    hit = os.path.basename(os.fsdecode(a[1])) == target
  else:
    hit = False
  if hit:
    os.kill(os.getpid(), signal.SIGKILL)
sys.addaudithook(hook)
sys.argv = [module, *args]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


def _env(cache):
  # One persistent compilation cache for the subprocesses: only the first one compiles the train
  # step and the export's SDF and colour functions (small ones too: no minimum compile time).
  return {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": str(cache),
          "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}


def _run(cache, module, *args, kill_at=None):
  """`python -m module args` (SIGKILLed at kill_at = (moment, file name), see KILLER)."""
  argv = ["-c", KILLER, *kill_at, module] if kill_at else ["-m", module]
  return subprocess.run([sys.executable, *argv, *map(str, args)], env=_env(cache),
                        capture_output=True, text=True, timeout=300)


def _listing(d):
  return sorted(str(p.relative_to(d)) for p in Path(d).rglob("*"))


def _left_over(d, before, name):
  """New entries of d since `before`: only hidden temporaries of `name` may be left by a kill."""
  new = sorted(set(_listing(d)) - set(before))
  assert all(Path(p).name.startswith(f".{name}.") for p in new), new
  return new


def _scene(d, **kw):
  import analytic_scene
  from ofjax.scene import save_scene
  scene, _ = analytic_scene.make(wli_px=24, om_hw=(24, 32), **kw)
  return scene, save_scene(scene, d, write_poses=True)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
  """(scene dir, run dir, JAX cache dir) of a tiny finished run with mesh.ply."""
  root = tmp_path_factory.mktemp("safe")
  _, scene_dir = _scene(root / "scene", n_om=6)
  run, cache = root / "run", root / "jax_cache"
  res = _run(cache, "ofjax.train", "--data", scene_dir, "--out", run, *TRAIN)
  assert res.returncode == 0 and (run / "mesh.ply").is_file(), res.stderr
  return scene_dir, run, cache


@pytest.fixture
def run_copy(trained, tmp_path):
  """A private copy of the trained run (tests kill processes in it) and its mesh bytes."""
  run = shutil.copytree(trained[1], tmp_path / "run")
  return run, (run / "mesh.ply").read_bytes()


@pytest.mark.slow  # the tiny training run of `trained` takes ~40 s on a busy 2-core CPU
@pytest.mark.parametrize("moment", ["written", "renamed"])
def test_export_killed_mid_write_keeps_the_previous_mesh(trained, run_copy, moment):
  run, old = run_copy
  before = _listing(run)
  res = _run(trained[2], "ofjax.export", run, "--resolution", EXPORT_RESOLUTION,
             kill_at=(moment, "mesh.ply"))
  assert res.returncode == -signal.SIGKILL, (res.returncode, res.stderr)
  assert (run / "mesh.ply").read_bytes() == old
  left = _left_over(run, before, "mesh.ply")
  # The kill came after the temporary file was made: the export was really writing.
  assert len(left) == 1, left


@pytest.mark.slow
def test_successful_export_replaces_the_mesh_by_rename(trained, run_copy):
  run, old = run_copy
  before, inode = _listing(run), (run / "mesh.ply").stat().st_ino
  res = _run(trained[2], "ofjax.export", run, "--resolution", EXPORT_RESOLUTION)
  assert res.returncode == 0, res.stderr
  new = (run / "mesh.ply").read_bytes()
  assert new != old and _listing(run) == before  # no temporary left beside it
  # A new file took the name (os.replace), rather than the old one being rewritten in place.
  assert (run / "mesh.ply").stat().st_ino != inode
  mesh = trimesh.load(run / "mesh.ply", process=False)
  assert len(mesh.faces) > 0 and np.all(np.isfinite(mesh.vertices))


@pytest.mark.slow
def test_export_refuses_non_finite_parameters(run_copy, capsys):
  import jax

  from ofjax import checkpoint, export, fields
  from ofjax import train as train_lib
  from ofjax.config import Config
  run, old = run_copy
  cfg = Config.from_dict(json.loads((run / "config.json").read_text())["config"])
  template = fields.init_params(jax.random.PRNGKey(0), cfg)
  step, params, opt_state = checkpoint.restore(run, template,
                                               train_lib.make_optimizer(cfg).init(template))
  def poisoned(tree):
    """One NaN weight in the first parameter array, and in every optimiser-state array of its
    shape (Adam's moments, the moving average export reads when the preset keeps one): a diverged
    run."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    shape = jax.tree_util.tree_leaves(params)[0].shape
    out = []
    for leaf in leaves:
      leaf = np.asarray(leaf)
      if leaf.shape == shape and np.issubdtype(leaf.dtype, np.floating):
        leaf = leaf.copy()
        leaf.flat[0] = np.nan
      out.append(leaf)
    return jax.tree_util.tree_unflatten(treedef, out)

  checkpoint.save(run, step, poisoned(params), poisoned(opt_state), keep=1)
  before = _listing(run)
  capsys.readouterr()
  # `python -m ofjax.export RUN` is this main (test_bad_input.py runs such CLIs as subprocesses).
  assert export.main([str(run)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("ofjax: error: "), err
  assert "not finite" in err[0] and "mesh.ply" in err[0]
  assert (run / "mesh.ply").read_bytes() == old and _listing(run) == before


@pytest.mark.slow
def test_overwrite_keeps_the_old_mesh_until_the_new_one_is_written(trained, run_copy):
  scene_dir, _, cache = trained
  run, old = run_copy
  # The same run again at another mesh resolution (the same train step: the compilation cache
  # serves it), so the new mesh differs from the old one.
  res = _run(cache, "ofjax.train", "--data", scene_dir, "--out", run, *TRAIN,
             "--mesh-resolution", "20", "--overwrite", kill_at=("renamed", "mesh.ply"))
  assert res.returncode == -signal.SIGKILL, (res.returncode, res.stderr)
  # The new run had finished training (its config and last checkpoint are there) ...
  assert json.loads((run / "config.json").read_text())["config"]["train"]["mesh_resolution"] == 20
  assert (run / "checkpoints" / "step_00000020.msgpack").is_file()
  # ... and its mesh was complete but not yet renamed: the old mesh is still the one in place.
  assert (run / "mesh.ply").read_bytes() == old
  (new,) = run.glob(".mesh.ply.*")
  assert new.read_bytes() != old and len(trimesh.load(new, process=False).faces) > 0


@pytest.mark.parametrize("case, expected", [
    ("too few photos", "structure-from-motion needs at least 3"),
    ("non-overlapping scan", "scan(s) junk (best fitness")])
def test_failed_association_keeps_the_existing_poses(tmp_path, case, expected):
  from test_bad_input import _add_junk_scan, _cap
  # Two photos fail before SfM (it needs three); a scan of random heights fails after the WLI
  # registration. Either way the previous poses.json must survive.
  if case == "too few photos":
    scene_dir = _cap(tmp_path, n_om=2, n_wli=1)
  else:
    scene_dir = _add_junk_scan(_cap(tmp_path, n_wli=1))
  poses = (scene_dir / "poses.json").read_bytes()
  before = _listing(scene_dir)
  res = _run(tmp_path / "jax_cache", "ofjax.associate", scene_dir)
  err = res.stderr.strip().splitlines()
  assert res.returncode == 2 and len(err) == 1 and err[0].startswith("ofjax: error: "), res.stderr
  assert expected in err[0], err[0]
  assert (scene_dir / "poses.json").read_bytes() == poses and _listing(scene_dir) == before


@pytest.mark.slow
def test_export_refuses_poses_the_run_was_not_trained_with(trained, run_copy, capsys):
  """The run keeps its cameras (poses.json, those of the scene); cameras moved 1 mm aside see
  none of the surface: one line naming the poses file, exit 2, the mesh untouched. --keep-hidden
  then exports without them."""
  from ofjax import export
  from ofjax import scene as scn
  run, old = run_copy
  poses = scn.load_poses(run / "poses.json")
  assert poses == scn.load_poses(Path(trained[0]) / "poses.json")
  for cam in poses["cameras"]:
    cam["c2w"][0][3] += 1000.0
  wrong = run.parent / "wrong_poses.json"
  wrong.write_text(json.dumps(poses))
  before = _listing(run)
  capsys.readouterr()
  assert export.main([str(run), "--poses", str(wrong)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith(f"ofjax: error: {wrong}: only 0% "), err
  assert (run / "mesh.ply").read_bytes() == old and _listing(run) == before
  out = run.parent / "kept.ply"
  assert export.main([str(run), "--keep-hidden", "--out", str(out)]) == 0
  assert len(trimesh.load(out, process=False).faces) > 0


@pytest.mark.slow
def test_export_grid_follows_the_wli_pixel(trained, run_copy, capsys):
  """`--resolution 0`: cells of half the run's WLI pixel along the box's longest side (config.json
  and poses.json give both), printed with the path. Without the run's poses and with
  --keep-hidden, the pixel is unknown: one line asking for --resolution N, exit 2."""
  from ofjax import export
  from ofjax import scene as scn
  run, old = run_copy
  meta = json.loads((run / "config.json").read_text())
  lo, hi = np.asarray(meta["observed_box"])
  longest_um = (hi - lo).max() * meta["normalization"]["scale"]
  pixels = [np.mean(c["intrinsics"]["pixel_size"])
            for c in scn.load_poses(run / "poses.json")["cameras"] if c["modality"] == "wli"]
  half_pixel = 0.5 * float(np.median(pixels))
  capsys.readouterr()
  out = run.parent / "auto.ply"
  assert export.main([str(run), "--resolution", "0", "--out", str(out)]) == 0
  printed = capsys.readouterr().out
  cell = float(printed.split("grid cell ")[1].split(" um")[0])
  cells = np.ceil(longest_um / half_pixel)
  # printed to 3 digits
  assert cell == pytest.approx(longest_um / cells, rel=5e-3) and cell <= half_pixel * 1.005
  assert len(trimesh.load(out, process=False).faces) > 0
  (run / "poses.json").unlink()
  assert export.main([str(run), "--keep-hidden", "--resolution", "0", "--out", str(out)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and str(run / "poses.json") in err[0] and "--resolution N" in err[0], err
  assert (run / "mesh.ply").read_bytes() == old
