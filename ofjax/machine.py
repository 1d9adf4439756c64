"""What a run ran on, for records and reports: host, CPU model, cores, platform, Python, JAX.

One description shared by the sweep records, the experiments' reports and the benchmarks, so a
table says the same machine the same way. `describe()` is a JSON-ready dict; `line(info)` its one
line for a report's header.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
from typing import Any


def cpu_model() -> str:
  """The CPU's model name ("AMD EPYC 9B14"); the architecture where the OS does not say."""
  try:
    with open("/proc/cpuinfo") as f:
      for entry in f:
        if entry.startswith("model name"):
          return entry.split(":", 1)[1].strip()
  except OSError:
    pass
  # macOS and Windows: platform.processor() names the CPU (family) or is empty.
  return platform.processor() or platform.machine()


def describe(devices: bool = False) -> dict[str, Any]:
  """The machine as a dict: host, platform, cpu, cpus, python, jax (version).

  devices: also JAX's backend and devices ("backend", "devices"). This initialises JAX's backend,
    so a process that runs no JAX (a sweep driver, a data job) leaves it False.
  """
  info: dict[str, Any] = {
      "host": platform.node(), "platform": platform.platform(), "cpu": cpu_model(),
      "cpus": os.cpu_count(), "python": platform.python_version(),
      "jax": importlib.metadata.version("jax")}
  if devices:
    import jax  # here, not at the top: describe() without devices must not initialise JAX

    info["backend"] = jax.default_backend()
    info["devices"] = [f"{d.platform}:{d.id} {d.device_kind}" for d in jax.devices()]
  return info


def line(info: dict[str, Any]) -> str:
  """One line for a report: "vm: AMD EPYC 9B14, 2 CPUs, Linux-..., Python 3.11.7, JAX 0.10.2".

  Records written before the CPU model and the JAX version were kept (key missing) read without
  them.
  """
  parts = [f"{info['host']}: {info['cpu']}" if info.get("cpu") else info["host"],
           f"{info['cpus']} CPUs", info["platform"], f"Python {info['python']}"]
  if info.get("jax"):
    parts.append(f"JAX {info['jax']}"
                 + (f" ({info['backend']}, {len(info['devices'])} device(s))" if "backend" in info else ""))
  return ", ".join(parts)
