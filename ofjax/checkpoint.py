"""Checkpoints of the training state: atomic msgpack files (flax.serialization), the last K kept.

A checkpoint is RUN_DIR/checkpoints/step_<step:08d>.msgpack holding {"step", "params", "opt_state"};
it is written to a temporary name and renamed, so a kill mid-write leaves the previous ones intact.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from flax import serialization

from ofjax import fileio

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


def restore(run_dir, params_template, opt_state_template, step: int | None = None):
  """Returns (step, params, opt_state) of checkpoint `step` (default: the newest), or None."""
  steps = list_steps(run_dir)
  if not steps:
    return None
  step = steps[-1] if step is None else step
  data = (_dir(run_dir) / f"step_{step:08d}.msgpack").read_bytes()
  template = {"step": np.int64(0), "params": params_template, "opt_state": opt_state_template}
  state = serialization.from_bytes(template, data)
  return int(state["step"]), state["params"], state["opt_state"]
