"""An exponential moving average (EMA) of the parameters, kept in the optimizer state.

The fused model's noisy colour gradients keep moving whole surfaces after they have converged in
the mean: on the default scene (true poses, 2,400 steps, checkpoints every 100 steps) the SDF at
the true substrate swings by +-0.3 um from one checkpoint to the next, up to 1 um; the mesh of the
last step is one draw of that swing. The mean of the last checkpoints' parameters is not
(experiments/README.md measures both). The average is what the run's mesh is made from;
training itself steps with the raw parameters, as without it.

With decay d, after every update ema <- ema + (1 - d) (params_new - ema), starting from the
initial parameters; its time constant is 1 / (1 - d) steps. `OptimConfig.ema_fraction` sets that
time constant as a share of the run, so a shorter or longer run averages over the same share.

The EMA sits inside the divergence guard (ofjax.guard): a skipped step changes neither the
parameters nor their average. It is saved and resumed with the optimizer state.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import optax


class EMAState(NamedTuple):
  inner: Any  # the wrapped optimizer's state
  ema: Any  # the moving average, a tree like the parameters


def decay_for(fraction: float, steps: int) -> float:
  """The decay whose time constant is `fraction` of `steps` (at least one step)."""
  return 1.0 - 1.0 / max(fraction * steps, 1.0)


def with_param_ema(inner: optax.GradientTransformation, decay: float
                   ) -> optax.GradientTransformation:
  """`inner`, with the EMA of the parameters it produces kept beside its state.

  update() needs `params` (the train step passes them).
  """

  def init(params):
    # A copy, not the same buffers: the train step donates both params and the optimizer state.
    return EMAState(inner.init(params), jax.tree_util.tree_map(lambda p: p.copy(), params))

  def update(grads, state: EMAState, params=None):
    if params is None:
      raise ValueError("with_param_ema needs the parameters in update()")
    updates, new_inner = inner.update(grads, state.inner, params)
    new_params = optax.apply_updates(params, updates)
    ema = jax.tree_util.tree_map(lambda e, p: e + (1.0 - decay) * (p - e), state.ema, new_params)
    return updates, EMAState(new_inner, ema)

  return optax.GradientTransformation(init, update)


def averaged(opt_state) -> Any | None:
  """The EMA of the parameters held in an optimizer state, or None when it keeps none."""
  if isinstance(opt_state, EMAState):
    return opt_state.ema
  inner = getattr(opt_state, "inner", None)
  return None if inner is None else averaged(inner)
