"""ofjax.averaging: the parameters' moving average against a float64 NumPy recursion, through the
divergence guard, a checkpoint and the export's loader."""

import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ofjax import averaging, checkpoint, config, export, fields, guard, train

STEPS = 25
DECAY = 0.8


def reference(p0: np.ndarray, targets: np.ndarray, lr: float) -> tuple[np.ndarray, np.ndarray]:
  """Float64 gradient descent on 0.5 |p - target_k|^2 (target k at step k) and the EMA of its
  iterates, written out step by step."""
  p, ema = p0.astype(np.float64).copy(), p0.astype(np.float64).copy()
  for k in range(len(targets)):
    p = p - lr * (p - targets[k])
    ema = DECAY * ema + (1 - DECAY) * p
  return p, ema


class AveragingTest(chex.TestCase):

  @chex.variants(with_jit=True, without_jit=True)
  def test_ema_of_the_iterates_matches_the_recursion(self):
    rng = np.random.default_rng(0)
    p0 = {"w": rng.normal(size=(3, 4)).astype(np.float32), "b": rng.normal(size=(4,)).astype(np.float32)}
    targets = {k: rng.normal(size=(STEPS,) + v.shape).astype(np.float32) for k, v in p0.items()}
    opt = averaging.with_param_ema(optax.sgd(0.3), DECAY)
    params = jax.tree_util.tree_map(jnp.asarray, p0)
    state = opt.init(params)

    @self.variant
    def step(params, state, target):
      grads = jax.tree_util.tree_map(lambda p, t: p - t, params, target)
      updates, state = opt.update(grads, state, params)
      return optax.apply_updates(params, updates), state

    for k in range(STEPS):
      params, state = step(params, state, {n: t[k] for n, t in targets.items()})
    for name in p0:
      want_p, want_ema = reference(p0[name], targets[name], 0.3)
      np.testing.assert_allclose(params[name], want_p, rtol=1e-5, atol=1e-6)
      np.testing.assert_allclose(averaging.averaged(state)[name], want_ema, rtol=1e-5, atol=1e-6)
      chex.assert_type(averaging.averaged(state)[name], jnp.float32)
    # The average lags the iterates: it is not the last step's parameters.
    assert np.abs(np.asarray(averaging.averaged(state)["w"]) - np.asarray(params["w"])).max() > 1e-3


def test_decay_sets_the_time_constant_as_a_share_of_the_run():
  assert averaging.decay_for(0.2, 1000) == 1.0 - 1.0 / 200.0
  assert averaging.decay_for(0.001, 100) == 0.0  # never below one step
  assert averaging.decay_for(0.25, 600) == 1.0 - 1.0 / 150.0


def test_a_skipped_step_leaves_the_average_alone_and_the_guard_finds_it():
  opt = guard.skip_non_finite(averaging.with_param_ema(optax.sgd(0.5), DECAY))
  params = {"w": jnp.ones(3)}
  state = opt.init(params)
  _, state = opt.update({"w": jnp.full(3, 2.0)}, state, params)
  before = np.asarray(averaging.averaged(state)["w"])
  np.testing.assert_allclose(before, DECAY * 1.0 + (1 - DECAY) * (1.0 - 0.5 * 2.0))
  _, state = opt.update({"w": jnp.array([1.0, jnp.nan, 0.0])}, state, params)
  np.testing.assert_array_equal(averaging.averaged(state)["w"], before)
  assert guard.stats(state)["skipped"] == 1
  assert averaging.averaged(guard.skip_non_finite(optax.sgd(0.5)).init(params)) is None


def test_export_loads_the_average_a_checkpoint_keeps(tmp_path):
  """A run with optim.ema_fraction: load_run gives the checkpoint's average, not its parameters."""
  cfg = config.resolve("cpu", optim={"ema_fraction": 0.2}, train={"steps": 10})
  params = fields.init_params(jax.random.PRNGKey(0), cfg)
  opt = train.make_optimizer(cfg)
  state = opt.init(params)
  moved = jax.tree_util.tree_map(lambda p: p + 1.0, params)
  grads = jax.tree_util.tree_map(jnp.ones_like, params)
  _, state = opt.update(grads, state, moved)
  checkpoint.save(tmp_path, 1, moved, state, keep=1)
  (tmp_path / "config.json").write_text(json.dumps({
      "config": cfg.to_dict(), "normalization": {"center": [0.0, 0.0, 0.0], "scale": 1.0},
      "observed_box": [[-1, -1, -1], [1, 1, 1]]}))
  loaded, *_ = export.load_run(tmp_path)
  want = averaging.averaged(state)
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(want)):
    np.testing.assert_array_equal(a, b)
  ema_table = np.asarray(want["tables"])
  assert not np.array_equal(ema_table, np.asarray(moved["tables"]))
