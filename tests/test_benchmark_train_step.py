"""benchmarks/train_step.py: each step's own peak memory, and a naive reference step that trains
the same model as the real one."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ofjax import config, fields, train
from ofjax import scene as scene_lib

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import train_step as bench  # noqa: E402

# The cpu preset's step on fewer rays and samples (64 x 24).
RAYS, SAMPLES = 64, (8, 8)
LARGE, SMALL = "cpu+hash.log2_table_size=14", "cpu+hash.log2_table_size=12"


def _param_bytes(spec: str) -> int:
  cfg = config.resolve_spec(spec)
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  return sum(int(np.asarray(p).nbytes) for p in jax.tree_util.tree_leaves(params))


def _data(cfg):
  scene = bench.benchmark_scene()
  return train.prepare_data(scene, scene_lib.compute_normalization(scene, cfg.train.box_margin))


@pytest.mark.slow
def test_peak_memory_is_each_steps_own_and_grows_with_the_table():
  large_cfg, small_cfg = (bench.make_config(s, RAYS, SAMPLES) for s in (LARGE, SMALL))
  data = _data(small_cfg)
  # The larger step first, the smaller twice: a process-wide peak (RSS) keeps what the first one
  # took, so it would not give the same step the same figure.
  peaks = [bench.time_step(cfg, data, fields.field_fns, 1)["peak_mem_mb"] * 2**20
           for cfg in (large_cfg, small_cfg, small_cfg)]
  assert peaks[1] == peaks[2]
  large, small = _param_bytes(LARGE), _param_bytes(SMALL)
  assert large > small
  for peak, n_bytes in zip(peaks, (large, small)):
    # Params, Adam's two moments and the moving average are all arguments of the step.
    assert peak >= 3 * n_bytes
  # The larger table costs at least its params and Adam's moments over again.
  assert peaks[0] - peaks[1] >= 3 * (large - small)


@pytest.mark.slow
def test_naive_step_computes_the_same_loss_as_the_real_one():
  """The reference the speed-up is measured against trains the same model: one step from the same
  params on the same batch gives the same losses (normals by nested autodiff vs the analytic
  Jacobian, float32 rounding apart)."""
  cfg = bench.make_config("cpu", RAYS, SAMPLES)
  data = _data(cfg)
  logs = {}
  for name, fns in (("real", fields.field_fns), ("naive", bench.naive_field_fns)):
    optimizer = train.make_optimizer(cfg)
    params = fields.init_params(jax.random.PRNGKey(cfg.train.seed), cfg)
    opt_state = optimizer.init(params)
    step = train.create_train_step(cfg, optimizer, field_fns=fns)
    _, _, out = step(params, opt_state, data, jnp.int32(0))
    logs[name] = {k: float(v) for k, v in out.items()}
  for key in ("loss/total", "loss/eikonal", "loss/wli", "loss/color"):
    np.testing.assert_allclose(logs["naive"][key], logs["real"][key], rtol=2e-3, atol=1e-6,
                               err_msg=key)
