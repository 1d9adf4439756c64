"""Divergence guard: an optax wrapper that skips updates with a non-finite gradient or result.

`skip_non_finite(inner)` behaves like `inner`, except that when a gradient, or a parameter after
the update, is not finite (NaN or inf) the update is zero and the inner state is left unchanged:
that step is skipped. A non-finite loss reaches the guard through its gradients (the chain rule
carries a NaN or inf loss into them). Checking the updated parameters as well catches what
finite gradients can still produce, e.g. an infinite learning rate.

The counters live in the optimizer state, so they are checkpointed with it and a resumed run
continues them: `streak` (skipped steps in a row now), `worst` (the longest such run so far) and
`skipped` (all skipped steps). The training loop reads them with `stats` at its host syncs.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax


class GuardState(NamedTuple):
  inner: Any  # the wrapped optimizer's state
  streak: jax.Array  # [] int32, skipped steps in a row ending at the last step
  worst: jax.Array  # [] int32, the longest streak so far
  skipped: jax.Array  # [] int32, skipped steps in all


def all_finite(tree) -> jax.Array:
  """[] bool: every leaf of `tree` is finite."""
  leaves = jax.tree_util.tree_leaves(tree)
  return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.True_


def skip_non_finite(inner: optax.GradientTransformation) -> optax.GradientTransformation:
  """`inner`, with non-finite steps skipped and counted (see the module docstring)."""

  def init(params):
    # Three distinct buffers: the train step donates its state, and XLA refuses one buffer twice.
    zero = lambda: jnp.zeros((), jnp.int32)
    return GuardState(inner.init(params), zero(), zero(), zero())

  def update(grads, state: GuardState, params=None):
    updates, new_inner = inner.update(grads, state.inner, params)
    ok = all_finite(grads) & all_finite(updates)
    if params is not None:
      ok &= all_finite(optax.apply_updates(params, updates))
    updates = jax.tree_util.tree_map(lambda u: jnp.where(ok, u, jnp.zeros_like(u)), updates)
    new_inner = jax.tree_util.tree_map(lambda n, o: jnp.where(ok, n, o), new_inner, state.inner)
    streak = jnp.where(ok, 0, state.streak + 1).astype(jnp.int32)
    return updates, GuardState(new_inner, streak, jnp.maximum(state.worst, streak),
                               state.skipped + (~ok).astype(jnp.int32))

  return optax.GradientTransformation(init, update)


def stats(opt_state: GuardState) -> dict[str, int]:
  """Host copies of the counters (one device sync)."""
  streak, worst, skipped = jax.device_get((opt_state.streak, opt_state.worst, opt_state.skipped))
  return {"streak": int(streak), "worst": int(worst), "skipped": int(skipped)}
