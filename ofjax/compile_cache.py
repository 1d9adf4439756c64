"""A disk cache of XLA's compiled programs for the command-line tools, one per machine.

Every training compiles the same train step (17 s on a 2-core CPU), its WLI fit and the export's
field functions; a second `make demo`, each run of a sweep or of the ablation, and each resumed
run compile them again. JAX keeps compiled programs on disk when given a directory
(`jax_compilation_cache_dir`); a program found there loads in a fraction of its compile time. A
loaded program is the executable a fresh compile of the same program gives, so results do not
change (tests/test_compile_cache.py).

XLA:CPU compiles for the host's instruction set, and runs an entry built on another CPU (a home
directory shared by a cluster's nodes) after only logging a warning, so the cache is split by the
host's CPU: `<root>/<host_key()>`. The directory is bounded (MAX_BYTES, least recently used
entries go first), which also makes JAX lock it, so processes side by side (a sweep's workers)
read no half-written entry.

OFJAX_COMPILATION_CACHE: `off` turns the cache off; a directory puts the root there instead of
`$XDG_CACHE_HOME/ofjax/xla` (`~/.cache/ofjax/xla`). A directory set with JAX's own
JAX_COMPILATION_CACHE_DIR is left to JAX as it is.
"""

from __future__ import annotations

import hashlib
import os
import platform
from pathlib import Path

import jax

from ofjax import machine

ENV = "OFJAX_COMPILATION_CACHE"
OFF = ("off", "0", "false", "no")  # values of ENV that turn the cache off
# Programs that compile faster than this are not kept (JAX's default). The train step and the WLI
# fit are kept; the ~250 small programs of a training (the fit's set-up, the export's functions)
# are not: kept too, they took a 50-step training of `wing` (cpu preset, 2-core Zen 1 VM) from 68
# to 60 s (83 s cold), but the bounded cache scans every entry on each write, and with the
# thousands a test suite makes that cost more than it saved (CI 28.5 min against 21.7).
MIN_COMPILE_S = 1.0
# Bound on the cache's size per machine. One train step's entry is ~0.6 MB, all of a training's
# programs a few MB, so this holds every preset and variant a user trains many times over.
MAX_BYTES = 1 << 30


def host_key() -> str:
  """12 hex digits naming this host's CPU: architecture, model, generation and its full feature
  flags (what XLA:CPU compiles for)."""
  text = "|".join((platform.machine(), machine.cpu_model(), machine.cpu_id() or "",
                   " ".join(machine.cpu_flags())))
  return hashlib.sha256(text.encode()).hexdigest()[:12]


def cache_dir(env: dict[str, str] | None = None) -> Path | None:
  """Where this machine's cache lies, from ENV and XDG_CACHE_HOME; None when ENV turns it off."""
  env = os.environ if env is None else env
  setting = env.get(ENV, "").strip()
  if setting.lower() in OFF:
    return None
  if setting:
    root = Path(setting).expanduser()
  else:
    xdg = env.get("XDG_CACHE_HOME", "").strip()
    root = (Path(xdg) if xdg else Path.home() / ".cache") / "ofjax" / "xla"
  return root / host_key()


def enable() -> Path | None:
  """Turns the cache on for this process (before its first compilation); returns its directory,
  None when it stays off: turned off, set by JAX_COMPILATION_CACHE_DIR (JAX's, returned as is),
  or a directory that cannot be made (a read-only home: the tools then compile as without it)."""
  if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
  path = cache_dir()
  if path is None:
    return None
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError:
    return None
  jax.config.update("jax_compilation_cache_dir", str(path))
  jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
  jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
  return path
