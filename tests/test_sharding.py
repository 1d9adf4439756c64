"""Data parallelism: the train step sharded over 2 forced CPU devices equals the single-device step.

The comparison runs in a subprocess because the device count is fixed when JAX starts
(XLA_FLAGS=--xla_force_host_platform_device_count=2). Both runs start from the same params and draw
the same rays (sampling is keyed by the step), so after a few steps they may differ only by the
order of float32 reductions (the all-reduce of the gradients over the two halves of the batch).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STEPS = 3
# float32 sums of ~10^3-10^4 terms reordered: relative error ~1e-6 per step; Adam divides by the
# running RMS of the gradient, so a parameter's update may change by ~1e-4 of the learning rate
# (1e-2) in a few steps; 1e-5 absolute on params of magnitude <~1 is far below any real bug (a
# dropped half of the batch or a missing all-reduce changes updates by ~lr).
ATOL = 1e-5
RTOL = 1e-4


def _child() -> None:
  import chex
  import jax
  import jax.numpy as jnp

  sys.path.insert(0, str(ROOT / "tests"))
  import analytic_scene
  from ofjax import fields, train
  from ofjax import scene as scene_lib
  from ofjax.config import resolve
  from ofjax.errors import UserError

  assert jax.device_count() == 2, jax.devices()
  scene, _ = analytic_scene.make()
  cfg = resolve("cpu", hash={"log2_table_size": 12},
                render={"n_samples": 16, "n_importance": 16, "n_importance_steps": 1,
                        "wli_guided_samples": 4},
                train={"n_rays": 64},
                # Adam's eps of 1e-15 turns a table entry's gradient of rounding noise (~1e-12,
                # its sign set by the reduction order) into a full +-lr step; 1e-8 keeps the
                # update continuous in the gradient, so float tolerance is a fair test.
                optim={"eps": 1e-8})
  data = train.prepare_data(scene, scene_lib.compute_normalization(scene, cfg.train.box_margin))
  optimizer = train.make_optimizer(cfg)

  def run(devices):
    params = fields.init_params(jax.random.PRNGKey(0), cfg)
    opt_state = optimizer.init(params)
    step_fn = train.create_train_step(cfg, optimizer, devices=devices)
    for step in range(STEPS):
      params, opt_state, logs = step_fn(params, opt_state, data, jnp.int32(step))
    return jax.device_get(params), jax.device_get(logs), step_fn

  single, single_logs, _ = run(jax.devices()[:1])
  sharded, sharded_logs, step_fn = run(jax.devices())
  # The sharded program really splits the rays: its HLO all-reduces across the two devices.
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  hlo = step_fn.lower(params, optimizer.init(params), data, jnp.int32(0)).compile().as_text()
  assert "all-reduce" in hlo, "the sharded step has no all-reduce: the batch was not split"
  chex.assert_trees_all_close(sharded_logs, single_logs, atol=ATOL, rtol=RTOL)
  chex.assert_trees_all_close(sharded, single, atol=ATOL, rtol=RTOL)
  moved = jax.tree_util.tree_map(lambda a, b: float(abs(a - b).max()), sharded,
                                 fields.init_params(jax.random.PRNGKey(0), cfg))
  assert max(jax.tree_util.tree_leaves(moved)) > 10 * ATOL, "the steps did not change the params"
  # A batch that does not split over the devices is a user error naming the option.
  odd = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, n_rays=63))
  try:
    train.create_train_step(odd, optimizer)
  except UserError as e:
    assert "--rays 63" in str(e), e
  else:
    raise AssertionError("63 rays over 2 devices was accepted")
  print("sharded == single", flush=True)


@pytest.mark.slow
def test_sharded_step_equals_single_device_step():
  env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
             JAX_PLATFORMS="cpu")
  proc = subprocess.run([sys.executable, __file__], cwd=ROOT, env=env, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
  assert "sharded == single" in proc.stdout


if __name__ == "__main__":
  _child()
