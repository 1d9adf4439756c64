"""Checkpoints of the training state: atomic msgpack files (flax.serialization), the last K kept.

A checkpoint is RUN_DIR/checkpoints/step_<step:08d>.msgpack holding {"step", "params", "opt_state"};
it is written to a temporary name and renamed, so a kill mid-write leaves the previous ones intact.
The optimizer state includes the divergence guard's counters (ofjax.guard), so they resume too.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from flax import serialization

from ofjax import fileio
from ofjax.errors import UserError

_NAME = re.compile(r"^step_(\d{8})\.msgpack$")


def _dir(run_dir) -> Path:
  return Path(run_dir) / "checkpoints"


def list_steps(run_dir) -> list[int]:
  d = _dir(run_dir)
  if not d.is_dir():
    return []
  return sorted(int(m.group(1)) for p in d.iterdir() if (m := _NAME.match(p.name)))


def save(run_dir, step: int, params, opt_state, keep: int) -> Path:
  """Writes the state at `step` and deletes all but the newest `keep` checkpoints."""
  path = _dir(run_dir) / f"step_{step:08d}.msgpack"
  state = {"step": np.int64(step), "params": params, "opt_state": opt_state}
  fileio.write_bytes(path, serialization.to_bytes(state))
  for old in list_steps(run_dir)[:-keep]:
    (_dir(run_dir) / f"step_{old:08d}.msgpack").unlink(missing_ok=True)
  return path


def _read(run_dir, step: int | None, parse):
  """parse(bytes) of checkpoint `step` (default: the newest), or None when there is none."""
  steps = list_steps(run_dir)
  if not steps:
    return None
  step = steps[-1] if step is None else step
  path = _dir(run_dir) / f"step_{step:08d}.msgpack"
  try:
    return parse(path.read_bytes())
  except FileNotFoundError:
    raise UserError(f"{path}: checkpoint not found; pick one of steps {steps}") from None
  except Exception as e:  # noqa: BLE001 - msgpack and flax raise many kinds on a foreign file
    raise UserError(f"{path}: cannot restore this checkpoint ({type(e).__name__}); it belongs to "
                    "another ofjax version or config, or is damaged: delete it to use the one "
                    "before") from None


def restore(run_dir, params_template, opt_state_template, step: int | None = None):
  """Returns (step, params, opt_state) of checkpoint `step` (default: the newest), or None."""
  template = {"step": np.int64(0), "params": params_template, "opt_state": opt_state_template}
  state = _read(run_dir, step, lambda data: serialization.from_bytes(template, data))
  return None if state is None else (int(state["step"]), state["params"], state["opt_state"])


def restore_params(run_dir, params_template, step: int | None = None):
  """The params of checkpoint `step` (default: the newest), or None; the optimiser state is not
  read, so exporting works whatever optimiser wrote the checkpoint."""
  return _read(run_dir, step, lambda data: serialization.from_state_dict(
      params_template, serialization.msgpack_restore(data)["params"]))
