"""Checkpoints, the divergence guard, and exact resume after a real SIGKILL.

The resume check compares a run killed (SIGKILL, a real subprocess) after its first checkpoint and
then resumed with --resume against an uninterrupted run of the same seed: the final parameters
must be bitwise equal and metrics.jsonl equal line by line (all but the wall-clock time).
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import serialization

from ofjax import checkpoint, guard
from ofjax.errors import UserError

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))


# ------------------------------------------------------------------------------ checkpoint files


def _state(v):
  return {"w": np.full((3, 2), v, np.float32), "b": np.arange(4, dtype=np.int32) + int(v)}


def test_save_keeps_newest_k_and_restores_exactly(tmp_path):
  for step in (10, 20, 30, 40):
    checkpoint.save(tmp_path, step, _state(step), {"count": np.int32(step)}, keep=2)
  assert checkpoint.list_steps(tmp_path) == [30, 40]
  step, params, opt = checkpoint.restore(tmp_path, _state(0), {"count": np.int32(0)})
  assert step == 40 and int(opt["count"]) == 40
  np.testing.assert_array_equal(params["w"], _state(40)["w"])
  np.testing.assert_array_equal(params["b"], _state(40)["b"])
  assert checkpoint.restore(tmp_path, _state(0), {"count": np.int32(0)}, step=30)[0] == 30
  # No temporary files are left beside the checkpoints.
  assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [
      "step_00000030.msgpack", "step_00000040.msgpack"]


def test_restore_without_checkpoints_is_none(tmp_path):
  assert checkpoint.restore(tmp_path, _state(0), {}) is None


@pytest.mark.parametrize("damage", ["truncate", "foreign"])
def test_damaged_or_foreign_checkpoint_is_a_user_error(tmp_path, damage):
  path = checkpoint.save(tmp_path, 5, _state(1), {"count": np.int32(1)}, keep=1)
  if damage == "truncate":
    path.write_bytes(path.read_bytes()[:20])
    template = (_state(0), {"count": np.int32(0)})
  else:  # a checkpoint of another model: the template has other keys
    template = ({"other": np.zeros(2, np.float32)}, {"count": np.int32(0)})
  with pytest.raises(UserError, match="step_00000005.msgpack: cannot restore"):
    checkpoint.restore(tmp_path, *template)


# -------------------------------------------------------------------------------- the guard


def _run_guard(lr, grads_seq):
  opt = guard.skip_non_finite(optax.sgd(lr))
  params = {"x": jnp.array([1.0, 2.0])}
  state = opt.init(params)
  for g in grads_seq:
    updates, state = opt.update({"x": jnp.asarray(g, jnp.float32)}, state, params)
    params = optax.apply_updates(params, updates)
  return np.asarray(params["x"], np.float64), guard.stats(state)


def test_guard_skips_non_finite_gradients_and_counts_them():
  grads = [[1.0, 1.0], [np.nan, 0.0], [np.inf, 0.0], [0.5, -1.0], [np.nan, np.nan]]
  x, counts = _run_guard(0.1, grads)
  # float64 reference: plain SGD over the finite gradients only.
  ref = np.array([1.0, 2.0]) - 0.1 * (np.array([1.0, 1.0]) + np.array([0.5, -1.0]))
  np.testing.assert_allclose(x, ref, rtol=1e-6)
  assert counts == {"streak": 1, "worst": 2, "skipped": 3}


def test_guard_skips_finite_gradients_with_a_non_finite_result():
  x, counts = _run_guard(np.inf, [[1.0, 0.0], [1.0, 0.0]])
  np.testing.assert_array_equal(x, [1.0, 2.0])  # an infinite step is never taken
  assert counts == {"streak": 2, "worst": 2, "skipped": 2}


def test_guard_is_transparent_when_finite():
  x, counts = _run_guard(0.1, [[1.0, -2.0], [3.0, 0.5]])
  np.testing.assert_allclose(x, [1.0 - 0.4, 2.0 + 0.15], rtol=1e-6)
  assert counts == {"streak": 0, "worst": 0, "skipped": 0}


# ------------------------------------------------------------------- training: resume, divergence


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
  import analytic_scene
  from ofjax.scene import save_scene
  scene, _ = analytic_scene.make(wli_px=24, om_hw=(24, 32), n_om=6)
  return save_scene(scene, tmp_path_factory.mktemp("cap") / "scene", write_poses=True)


STEPS, EVERY = 30, 10
TRAIN_ARGS = ["--steps", str(STEPS), "--checkpoint-every", str(EVERY), "--log-every", "4",
              "--rays", "64", "--mesh-resolution", "16", "--quiet"]


def _train_cmd(scene_dir, out, *extra):
  return [sys.executable, "-m", "ofjax.train", "--data", str(scene_dir), "--out", str(out),
          *TRAIN_ARGS, *extra]


def _env(cache):
  # One persistent compilation cache for the three processes: only the first one compiles.
  return {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": str(cache)}


def _metrics(run):
  rows = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()]
  for r in rows:
    r.pop("time_s")
  return rows


def _final_state(run):
  return serialization.msgpack_restore(
      (run / "checkpoints" / f"step_{STEPS:08d}.msgpack").read_bytes())


@pytest.mark.slow
def test_sigkill_then_resume_equals_uninterrupted_run(scene_dir, tmp_path):
  env = _env(tmp_path / "jax_cache")
  ref, run = tmp_path / "ref", tmp_path / "run"
  done = subprocess.run(_train_cmd(scene_dir, ref), env=env, capture_output=True, text=True,
                        timeout=300)
  assert done.returncode == 0, done.stderr

  proc = subprocess.Popen(_train_cmd(scene_dir, run), env=env, stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
  first = run / "checkpoints" / f"step_{EVERY:08d}.msgpack"
  deadline = time.time() + 240
  while not first.exists() and proc.poll() is None and time.time() < deadline:
    time.sleep(0.01)
  proc.send_signal(signal.SIGKILL)
  assert proc.wait() == -signal.SIGKILL, "the run ended before it could be killed"
  killed_at = checkpoint.list_steps(run)
  assert killed_at and killed_at[-1] < STEPS and not (run / "mesh.ply").exists()

  resumed = subprocess.run(_train_cmd(scene_dir, run, "--resume"), env=env, capture_output=True,
                           text=True, timeout=300)
  assert resumed.returncode == 0, resumed.stderr
  assert f"resumed at step {killed_at[-1]}" in resumed.stdout

  a, b = _final_state(ref), _final_state(run)
  leaves_a, leaves_b = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
  assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
  diff = max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
             for x, y in zip(leaves_a, leaves_b) if np.size(x))
  print(f"resume check: killed after checkpoint {killed_at[-1]}, max |param diff| = {diff}")
  assert diff == 0.0
  assert _metrics(ref) == _metrics(run)
  assert [r["step"] for r in _metrics(run)] == [*range(0, STEPS, 4), STEPS - 1]


@pytest.mark.slow
def test_divergence_stops_and_keeps_the_last_good_checkpoint(scene_dir, tmp_path):
  import dataclasses

  from ofjax import train as train_lib
  from ofjax.config import resolve
  from ofjax.scene import load_scene

  scene = load_scene(scene_dir)
  cfg = resolve("cpu", train={"steps": 10, "n_rays": 32, "checkpoint_every": 5,
                              "max_skipped_in_a_row": 4, "log_every": 5})
  train_lib.train(scene, cfg, tmp_path, progress=False)
  good = (tmp_path / "checkpoints" / "step_00000010.msgpack").read_bytes()
  # The same run continued with an infinite learning rate: every update would be non-finite.
  bad = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, lr=float("inf")),
                            train=dataclasses.replace(cfg.train, steps=40))
  with pytest.raises(UserError, match=r"diverged: 4 steps in a row .* last good checkpoint is "
                                      r"step 10"):
    train_lib.train(scene, bad, tmp_path, progress=False, resume=True)
  assert checkpoint.list_steps(tmp_path) == [5, 10]
  assert (tmp_path / "checkpoints" / "step_00000010.msgpack").read_bytes() == good
  rows = [json.loads(ln) for ln in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  # The resumed part logged step 10 (its first update already skipped) before it stopped.
  assert [r["step"] for r in rows] == [0, 5, 9, 10] and rows[-1]["skipped"] == 1
