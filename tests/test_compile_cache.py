"""ofjax.compile_cache: where the cache lies, when it stays off, and that a program loaded from it
computes what the freshly compiled one did."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ofjax import compile_cache

# A child process that turns the cache on, compiles the cpu preset's SDF with its gradient, and
# prints the values' bytes, the cache's entries, and JAX's count of cache hits and misses.
CHILD = r"""
import json, sys
import jax, jax.numpy as jnp, numpy as np
from ofjax import compile_cache, config, fields
path = compile_cache.enable()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # keep these small programs
events = {"hits": 0, "misses": 0}
def count(name, **kwargs):
  for kind in events:
    if name == f"/jax/compilation_cache/cache_{kind}":
      events[kind] += 1
jax.monitoring.register_event_listener(count)
cfg = config.resolve("cpu")
params = fields.init_params(jax.random.PRNGKey(0), cfg)
x = jax.random.uniform(jax.random.PRNGKey(1), (4096, 3), minval=-1.0, maxval=1.0)
value_and_grad = jax.jit(jax.vmap(jax.value_and_grad(
    lambda p: fields.sdf_value(params, p[None], cfg)[0])))
sdf, grad = value_and_grad(x)
print(json.dumps({"path": str(path), "sdf": np.asarray(sdf).tobytes().hex(),
                  "grad": np.asarray(grad).tobytes().hex(), **events,
                  "entries": sorted(p.name for p in path.glob("*-cache")) if path else []}))
"""


def _child(env: dict) -> dict:
  proc = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                        env={**os.environ, **env}, cwd=Path(__file__).resolve().parents[1])
  assert proc.returncode == 0, proc.stderr[-2000:]
  return json.loads(proc.stdout.strip().splitlines()[-1])


def test_cache_dir_follows_the_setting_and_splits_by_host(tmp_path):
  key = compile_cache.host_key()
  assert len(key) == 12 and int(key, 16) >= 0
  assert compile_cache.host_key() == key
  assert compile_cache.cache_dir({compile_cache.ENV: str(tmp_path)}) == tmp_path / key
  assert compile_cache.cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == \
      tmp_path / "ofjax" / "xla" / key
  assert compile_cache.cache_dir({}) == Path.home() / ".cache" / "ofjax" / "xla" / key
  for off in ("off", "OFF", "0", "false", "no"):
    assert compile_cache.cache_dir({compile_cache.ENV: off}) is None


def test_stays_off_when_turned_off_or_unwritable(tmp_path, monkeypatch):
  monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
  monkeypatch.setenv(compile_cache.ENV, "off")
  assert compile_cache.enable() is None
  blocker = tmp_path / "a_file"
  blocker.write_text("")
  monkeypatch.setenv(compile_cache.ENV, str(blocker / "cache"))
  assert compile_cache.enable() is None
  # JAX's own setting is JAX's: returned, not replaced.
  monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jax"))
  assert compile_cache.enable() == tmp_path / "jax"


@pytest.mark.slow
def test_a_loaded_program_computes_what_the_compiled_one_did(tmp_path):
  env = {compile_cache.ENV: str(tmp_path), "JAX_COMPILATION_CACHE_DIR": ""}
  first = _child(env)
  assert first["path"] == str(tmp_path / compile_cache.host_key())
  assert first["entries"], "the first process wrote nothing into the cache"
  assert first["misses"] > 0
  second = _child(env)
  # Every program found, none compiled anew.
  assert second["misses"] == 0 and second["hits"] == first["hits"] + first["misses"]
  assert second["entries"] == first["entries"]
  assert second["sdf"] == first["sdf"] and second["grad"] == first["grad"]
  # And what a process without the cache computes.
  cold = _child({compile_cache.ENV: "off", "JAX_COMPILATION_CACHE_DIR": ""})
  assert cold["path"] == "None" and cold["entries"] == [] and cold["hits"] == 0
  assert cold["sdf"] == first["sdf"] and cold["grad"] == first["grad"]
