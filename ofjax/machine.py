"""What a run ran on, for records and reports: host, CPU model, cores, platform, Python, JAX, and
the ofjax commit; for telling why two machines give different numbers, the CPU's generation, its
vector extensions and the numeric libraries' versions.

One description shared by the sweep records, the experiments' reports and the benchmarks, so a
table says the same machine the same way. `describe()` is a JSON-ready dict; `line(info)` its one
line for a report's header.
"""

from __future__ import annotations

import functools
import importlib.metadata
import os
import platform
import re
import subprocess
from pathlib import Path
from typing import Any


# The vector extensions XLA's CPU code generation chooses among: two machines that differ here may
# compile the same step to different float arithmetic (a run repeats byte for byte only on one).
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile",
              "asimd", "sve")
# The distributions whose versions can change a result: the JAX compiler, the numeric libraries
# training, export and evaluation use, and the association's.
PACKAGES = ("jaxlib", "numpy", "scipy", "optax", "flax", "open3d", "open3d-cpu", "trimesh",
            "scikit-image", "pycolmap")


@functools.lru_cache(maxsize=1)
def _cpuinfo() -> dict[str, str]:
  """The first processor's entries of /proc/cpuinfo (empty where there is none); read once per
  process, as describe() asks it three times. Callers must not change the dict."""
  entries: dict[str, str] = {}
  try:
    with open("/proc/cpuinfo") as f:
      for entry in f:
        if not entry.strip():
          break
        key, _, value = entry.partition(":")
        entries[key.strip()] = value.strip()
  except OSError:
    pass
  return entries


def cpu_model() -> str:
  """The CPU's model name ("AMD EPYC 9B14"); the architecture where the OS does not say."""
  # macOS and Windows: platform.processor() names the CPU (family) or is empty.
  return _cpuinfo().get("model name") or platform.processor() or platform.machine()


def cpu_id() -> str | None:
  """"family 25 model 17" on x86 Linux (the generation, which a generic model name such as "AMD
  EPYC" hides), "implementer 0x41 part 0xd40" on ARM Linux, None elsewhere."""
  info = _cpuinfo()
  if "cpu family" in info and "model" in info:
    return f"family {info['cpu family']} model {info['model']}"
  if "CPU implementer" in info and "CPU part" in info:
    return f"implementer {info['CPU implementer']} part {info['CPU part']}"
  return None


def cpu_flags() -> list[str]:
  """Every feature flag of the CPU, sorted (Linux; empty elsewhere)."""
  info = _cpuinfo()
  return sorted(set((info.get("flags") or info.get("Features") or "").split()))


def simd() -> list[str]:
  """Which of SIMD_FLAGS the CPU has (Linux; empty elsewhere)."""
  flags = set(cpu_flags())
  return [f for f in SIMD_FLAGS if f in flags]


def packages() -> dict[str, str]:
  """{distribution: version} of the installed PACKAGES."""
  found = {}
  for name in PACKAGES:
    try:
      found[name] = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
      pass
  return found


def git_state(paths: tuple[str, ...] = ("ofjax",)) -> dict[str, Any]:
  """The ofjax checkout this code runs from: {"commit": HEAD or None, "uncommitted_code": [...]}.

  paths: what counts as code (relative to the checkout's root); `uncommitted_code` lists the ones
    with changes `git status --porcelain` shows. An installed ofjax (no checkout, or no git) gives
    {"commit": None, "uncommitted_code": []}.
  """
  root = Path(__file__).resolve().parents[1]

  def git(*args: str) -> str | None:
    try:
      done = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
    except OSError:  # no git on this machine
      return None
    return done.stdout if done.returncode == 0 else None

  head = git("rev-parse", "HEAD") if (root / ".git").exists() else None
  # Not stripped: a porcelain line starts with a space when only the work tree changed.
  changes = git("status", "--porcelain", "--", *paths) if head else None
  return {"commit": head.strip() if head else None,
          "uncommitted_code": changes.splitlines() if changes else []}


def describe(devices: bool = False) -> dict[str, Any]:
  """The machine as a dict: host, platform, cpu, cpus, python, jax (version), cpu_id, simd,
  packages (module functions of those names).

  devices: also JAX's backend and devices ("backend", "devices"). This initialises JAX's backend,
    so a process that runs no JAX (a sweep driver, a data job) leaves it False.
  """
  info: dict[str, Any] = {
      "host": platform.node(), "platform": platform.platform(), "cpu": cpu_model(),
      "cpus": os.cpu_count(), "python": platform.python_version(),
      "jax": importlib.metadata.version("jax"), "cpu_id": cpu_id(), "simd": simd(),
      "packages": packages()}
  if devices:
    import jax  # here, not at the top: describe() without devices must not initialise JAX

    info["backend"] = jax.default_backend()
    info["devices"] = [f"{d.platform}:{d.id} {d.device_kind}" for d in jax.devices()]
  return info


# JAX releases whose float32 scatter-add on GPU regressed (first, last). The hash table's gradient
# is one scatter-add per step, so training and the benchmarks there run slow; CPU is unaffected.
GPU_SCATTER_REGRESSION = ((0, 10, 2), (0, 11, 0))


def release(version: str) -> tuple[int, ...]:
  """(0, 10, 2) from "0.10.2" (a suffix such as ".dev20260101" or "rc1" is dropped)."""
  parts = []
  for piece in version.split(".")[:3]:
    digits = re.match(r"\d+", piece)
    if digits is None:
      break
    parts.append(int(digits.group()))
  return tuple(parts)


def scatter_regression_warning(jax_version: str, backend: str) -> str | None:
  """The warning for a GPU run on a JAX release with the slow scatter-add; None when not one."""
  first, last = GPU_SCATTER_REGRESSION
  if backend not in ("gpu", "cuda", "rocm") or not first <= release(jax_version) <= last:
    return None
  return (f"JAX {jax_version} on GPU has a slow float32 scatter-add (releases "
          f"{'.'.join(map(str, first))}-{'.'.join(map(str, last))}), which the hash table's "
          "gradient uses every step: install another release, e.g. pip install -e '.[gpu]'")


def line(info: dict[str, Any]) -> str:
  """One line for a report: "vm: AMD EPYC (family 25 model 17), 2 CPUs, Linux-..., Python 3.11.7,
  JAX 0.10.2".

  Records written before the CPU model, its generation and the JAX version were kept (key
  missing) read without them.
  """
  cpu = f"{info['cpu']} ({info['cpu_id']})" if info.get("cpu_id") else info.get("cpu")
  parts = [f"{info['host']}: {cpu}" if cpu else info["host"],
           f"{info['cpus']} CPUs", info["platform"], f"Python {info['python']}"]
  if info.get("jax"):
    parts.append(f"JAX {info['jax']}"
                 + (f" ({info['backend']}, {len(info['devices'])} device(s))" if "backend" in info else ""))
  return ", ".join(parts)
