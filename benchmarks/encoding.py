"""Throughput of the hash encoding: samples per second of each way to use it, as a table.

Rows (each jit-compiled, one call = `--points` samples, warm-up call excluded, median of repeats;
samples/s is from wall time, `cpu ms` is the process's CPU time per call, summed over threads):
  encode                 features only
  encode_with_jacobian   features and the analytic d feats / dx
  vg explicit jac        value_and_grad w.r.t. the tables of a loss using both feats and jac,
                         jac from `encode_with_jacobian` (what train_step should do)
  vg grad(encode)        the same loss with d sdf / dx from jax.grad of `encode` (its custom_jvp)
  vg naive autodiff      the same loss with d sdf / dx from jax.grad through the gather (no
                         custom_jvp): the nested-autodiff baseline
  table gather           the gather of the 8 corners of every level alone ([8, N, L, F])
  gather transpose       its reverse mode alone: the scatter-add of a [8, N, L, F] cotangent into
                         the table (what every table gradient ends in)
Each row runs for every --gather-groups value (HashConfig.gather_groups: the levels gathered and
scattered as that many independent ops).
The loss stands in for the SDF head (a per-point non-linearity, then a linear read-out):
sdf = tanh(feats) . a, loss = mean(sdf) + mean((|d sdf/dx| - 1)^2).

  python benchmarks/encoding.py [--points 65536] [--log2-table-sizes 16 19] [--gather-groups 1 4]
                                [--repeats 5] [--only ROW ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ofjax import encoding, machine
from ofjax.config import HashConfig
from ofjax.errors import UserError, cli


def _loss_from_grad(sdf: jax.Array, grad_sdf: jax.Array) -> jax.Array:
  """sdf: [N]; grad_sdf: [N, 3] -> a scalar like the SDF + eikonal terms of train_step."""
  return jnp.mean(sdf) + jnp.mean((jnp.linalg.norm(grad_sdf, axis=-1) - 1.0) ** 2)


def make_functions(cfg: HashConfig) -> dict[str, Callable]:
  """The benchmarked functions of (tables, x, a), each jit-compiled."""

  def explicit(tables, x, a):
    feats, jac = encoding.encode_with_jacobian(tables, x, cfg)
    h = jnp.tanh(feats)
    # Chain rule by hand: d sdf / dx = (a * tanh'(feats)) . d feats / dx.
    return _loss_from_grad(h @ a, jnp.einsum("nk,nkd->nd", a * (1.0 - h * h), jac))

  def through(encode_fn):
    def loss(tables, x, a):
      sdf = lambda p: jnp.tanh(encode_fn(tables, p, cfg)) @ a
      return _loss_from_grad(sdf(x), jax.vmap(jax.grad(sdf))(x))
    return loss

  gather = lambda t, x: encoding._gather(t, x, cfg)[0]  # noqa: E731
  cotangent = lambda t, x: [jnp.ones_like(v) for v in gather(t, x)]  # noqa: E731
  return {
      "encode": jax.jit(lambda t, x, a: encoding.encode(t, x, cfg)),
      "encode_with_jacobian": jax.jit(lambda t, x, a: encoding.encode_with_jacobian(t, x, cfg)),
      "vg explicit jac": jax.jit(jax.value_and_grad(explicit)),
      "vg grad(encode)": jax.jit(jax.value_and_grad(through(encoding.encode))),
      "vg naive autodiff": jax.jit(jax.value_and_grad(through(encoding._encode_plain))),
      "table gather": jax.jit(lambda t, x, a: gather(t, x)),
      "gather transpose": jax.jit(
          lambda t, x, a: jax.vjp(lambda u: gather(u, x), t)[1](cotangent(t, x))[0]),
  }


def time_call(fn, args, repeats: int) -> tuple[float, float]:
  """Median wall and CPU (all threads of this process) seconds per call, after a warm-up call.

  On a shared machine the CPU time is the steadier figure: it does not count time spent waiting
  for cores that other processes hold.
  """
  jax.block_until_ready(fn(*args))
  wall, cpu = [], []
  for _ in range(repeats):
    start, start_cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    wall.append(time.perf_counter() - start)
    cpu.append(time.process_time() - start_cpu)
  return float(np.median(wall)), float(np.median(cpu))


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--points", type=int, default=2 ** 16, help="samples per call")
  p.add_argument("--log2-table-sizes", type=int, nargs="+", default=[16, 19])
  p.add_argument("--gather-groups", type=int, nargs="+", default=[1],
                 help="HashConfig.gather_groups values to run every row with (must divide 16)")
  p.add_argument("--repeats", type=int, default=5, help="timed calls per row (median reported)")
  p.add_argument("--only", nargs="*", default=None, help="run only these rows")
  args = p.parse_args(argv)
  print(machine.line(machine.describe(devices=True)))
  print(f"{args.points} points per call, median of {args.repeats} calls, warm-up excluded")
  print(f"load average {os.getloadavg()[0]:.1f} at start")
  print(f"{'log2 T':>6} {'groups':>6}  {'function':<22} {'wall ms':>9} {'samples/s':>12} "
        f"{'cpu ms':>9}")
  rng = np.random.default_rng(0)
  x = jnp.asarray(rng.uniform(-1.0, 1.0, (args.points, 3)), jnp.float32)
  for log2_t in args.log2_table_sizes:
    for groups in args.gather_groups:
      try:
        cfg = HashConfig(log2_table_size=log2_t, gather_groups=groups)
      except ValueError as e:
        raise UserError(f"--gather-groups {groups}: {e}") from None
      tables = encoding.init_tables(jax.random.PRNGKey(0), cfg)
      a = jnp.asarray(rng.normal(size=cfg.n_levels * cfg.n_features), jnp.float32)
      for name, fn in make_functions(cfg).items():
        if args.only and name not in args.only:
          continue
        wall, cpu = time_call(fn, (tables, x, a), args.repeats)
        print(f"{log2_t:>6} {groups:>6}  {name:<22} {wall * 1e3:>9.1f} "
              f"{args.points / wall:>12,.0f} {cpu * 1e3:>9.1f}", flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())
