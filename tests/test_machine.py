"""ofjax.machine: the description every record and report shares."""

import json
import os
import platform
import subprocess
from pathlib import Path

from ofjax import machine


def test_describe_is_json_and_names_the_cpu():
  info = machine.describe()
  assert json.loads(json.dumps(info)) == info
  assert info["cpus"] == os.cpu_count() and info["python"] == platform.python_version()
  assert "backend" not in info  # JAX's backend is initialised only when asked for
  if os.path.exists("/proc/cpuinfo"):
    with open("/proc/cpuinfo") as f:
      names = {ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")}
    if names:
      assert info["cpu"] in names
  assert info["cpu"]


def test_describe_names_the_cpu_generation_its_vector_extensions_and_the_libraries():
  """Against /proc/cpuinfo read here (first processor) and the modules' own versions."""
  import jaxlib
  import numpy
  import scipy

  info = machine.describe()
  assert json.loads(json.dumps(info)) == info
  assert info["packages"]["jaxlib"] == jaxlib.__version__
  assert info["packages"]["numpy"] == numpy.__version__
  assert info["packages"]["scipy"] == scipy.__version__
  assert set(info["packages"]) <= set(machine.PACKAGES)
  if not os.path.exists("/proc/cpuinfo"):
    assert info["cpu_id"] is None and info["simd"] == []
    return
  first = Path("/proc/cpuinfo").read_text().split("\n\n")[0].splitlines()
  fields = {k.strip(): v.strip() for k, _, v in (ln.partition(":") for ln in first)}
  if "cpu family" in fields:
    assert info["cpu_id"] == f"family {fields['cpu family']} model {fields['model']}"
    assert info["cpu_id"] in machine.line(info)
  flags = (fields.get("flags") or fields.get("Features") or "").split()
  assert info["simd"] == [f for f in machine.SIMD_FLAGS if f in flags]


def test_describe_devices_lists_jax_backend():
  import jax

  info = machine.describe(devices=True)
  assert info["backend"] == jax.default_backend()
  assert info["jax"] == jax.__version__
  assert len(info["devices"]) == jax.device_count()


def test_line_reads_new_and_old_records():
  info = machine.describe(devices=True)
  text = machine.line(info)
  assert info["cpu"] in text and f"{info['cpus']} CPUs" in text and f"JAX {info['jax']}" in text
  assert info["backend"] in text
  # A record from before the CPU model and JAX version were kept (experiments/results/*_init/).
  old = {"host": "vm", "platform": "Linux-6.1", "processor": "x86_64", "cpus": 2, "python": "3.11.7"}
  assert machine.line(old) == "vm, 2 CPUs, Linux-6.1, Python 3.11.7"


def test_release_reads_plain_and_suffixed_versions():
  assert machine.release("0.10.2") == (0, 10, 2)
  assert machine.release("0.11.0rc1") == (0, 11, 0)
  assert machine.release("0.11.1.dev20261201") == (0, 11, 1)
  assert machine.release("1.0") == (1, 0)


def test_scatter_warning_names_only_gpu_runs_on_the_regressed_releases():
  for version in ("0.10.2", "0.10.5", "0.11.0", "0.11.0rc1"):
    message = machine.scatter_regression_warning(version, "gpu")
    assert message is not None and version in message and ".[gpu]" in message
  for version in ("0.10.1", "0.9.2", "0.11.1", "1.0.0"):
    assert machine.scatter_regression_warning(version, "gpu") is None
  assert machine.scatter_regression_warning("0.10.2", "cpu") is None
  assert machine.scatter_regression_warning("0.10.2", "tpu") is None


def test_git_state_names_this_checkouts_commit():
  root = Path(machine.__file__).resolve().parents[1]
  head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True)
  state = machine.git_state()
  if head.returncode != 0:  # an installed copy, not a checkout
    assert state == {"commit": None, "uncommitted_code": []}
  else:
    assert state["commit"] == head.stdout.strip()
    changed = subprocess.run(["git", "status", "--porcelain", "--", "ofjax"], cwd=root,
                             capture_output=True, text=True).stdout.splitlines()
    assert state["uncommitted_code"] == changed
