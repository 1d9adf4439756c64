"""Throughput of the jitted train step per preset, against a naive nested-autodiff reference step.

For each preset (or preset variant) the benchmark builds the real step (ofjax.train.create_train_step:
normals from the hash encoding's analytic Jacobian) and, in the same run and on the same data, the
NAIVE step: the same model, params, optimiser and losses, but geometry_fn gets d sdf / dx by
jax.grad through the plain hash gather (nested autodiff: the loss's gradient differentiates that
gradient again). Each step is compiled ahead of time (compile_s), run once to warm up, then
`--steps` times with one host sync at the end.

Columns: samples/step = rays x (n_samples + wli_guided_samples + n_importance), the points the
differentiable fields are evaluated at (the upsampling rounds' SDF-only queries come on top, as
in NeuS); samples/s and it/s from wall time; peak_mem_mb is what the compiled real step holds
while it runs, from XLA's buffer assignment (see `peak_mem_mb()`), the same on CPU and GPU. A
process-wide peak (RSS, or a device's peak_bytes_in_use) never falls, so it would give every
preset after the largest one 0.

A variant is `preset+component.field=value+...`, e.g. `cpu+hash.log2_table_size=19`: levers are
measured against their preset in one run, e.g.
  python benchmarks/train_step.py --presets cpu,cpu+render.wli_guided_samples=0 --no-naive

  python benchmarks/train_step.py [--json] [--presets cpu,paper] [--rays N] [--samples U,I]
                                  [--steps K] [--no-naive] [--bound]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from ofjax import config, encoding, fields, machine, synth, train
from ofjax import scene as scene_lib
from ofjax.config import Config
from ofjax.errors import UserError, cli

# Timed steps per preset when --steps is not given: the paper step is several times the cpu one.
DEFAULT_STEPS = {"cpu": 10, "paper": 4}


def naive_field_fns(params, cfg: Config):
  """fields.field_fns with d sdf / dx by jax.grad through the plain hash gather (nested autodiff)."""
  def sdf_and_feature(p, x):
    return fields.sdf_and_feature(p, x, cfg, encode=encoding._encode_plain)

  def geometry_fn(x):
    out = sdf_and_feature(params, x)
    # Points are independent, so the gradient of the sum is the per-point gradient.
    grad = jax.grad(lambda y: sdf_and_feature(params, y)[..., 0].sum())(x)
    return out[..., 0], grad, out[..., 1:]

  frozen = jax.lax.stop_gradient(params)
  return (geometry_fn, lambda x, n, f, v: fields.colors(params, x, n, f, v, cfg),
          lambda x: sdf_and_feature(frozen, x)[..., 0])


def no_normal_field_fns(params, cfg: Config):
  """The step's upper bound (--bound): the same fields with the normal branch removed.

  d sdf / dx is replaced by zeros (no Jacobian, no nested derivative), so the step pays only for
  the SDF values, colours, losses and Adam: what any way of computing normals adds comes on top.
  The losses it trains are wrong (the eikonal term is constant); it is timed, never trained.
  """
  _, color_fn, sdf_fn = fields.field_fns(params, cfg)

  def geometry_without_normal(x):
    out = fields.sdf_and_feature(params, x, cfg)
    return out[..., 0], jnp.zeros_like(x), out[..., 1:]

  return geometry_without_normal, color_fn, sdf_fn


def make_config(spec: str, rays: int | None, samples: tuple[int, int] | None) -> Config:
  extra: dict[str, dict] = {}
  if rays:
    extra["train"] = {"n_rays": rays}
  if samples:
    extra["render"] = {"n_samples": samples[0], "n_importance": samples[1]}
  try:
    return config.resolve_spec(spec, **extra)
  except ValueError as e:
    raise UserError(f"--presets {e}") from None


def samples_per_ray(cfg: Config) -> int:
  rc = cfg.render
  return rc.n_samples + rc.wli_guided_samples + rc.n_importance


def peak_mem_mb(compiled) -> float:
  """The memory the compiled step holds while it runs, from XLA's buffer assignment, in MiB: its
  arguments (params, Adam state, data) and outputs, the donated ones counted once, and its block of
  temporaries. (`peak_memory_in_bytes` leaves the temporaries out on the CPU: 36 of 170 MiB for the
  cpu preset's step.)"""
  m = compiled.memory_analysis()
  return (m.argument_size_in_bytes + m.output_size_in_bytes - m.alias_size_in_bytes
          + m.temp_size_in_bytes) / 2**20


def time_step(cfg: Config, data: train.TrainData, field_fns, steps: int) -> dict:
  """Compiles the step ahead of time, warms it up, times `steps` steps (one sync at the end)."""
  optimizer = train.make_optimizer(cfg)
  params = fields.init_params(jax.random.PRNGKey(cfg.train.seed), cfg)
  # optax may hand out one zero buffer for several state leaves; the compiled executable (unlike
  # jit's dispatch) refuses to donate a buffer twice, so every leaf gets its own.
  opt_state = jax.tree_util.tree_map(jnp.copy, optimizer.init(params))
  step_fn = train.create_train_step(cfg, optimizer, field_fns=field_fns)
  t0 = time.perf_counter()
  compiled = step_fn.lower(params, opt_state, data, jnp.int32(0)).compile()
  compile_s = time.perf_counter() - t0
  params, opt_state, logs = compiled(params, opt_state, data, jnp.int32(0))
  jax.block_until_ready(params)
  t0 = time.perf_counter()
  for step in range(1, steps + 1):
    params, opt_state, logs = compiled(params, opt_state, data, jnp.int32(step))
  jax.block_until_ready((params, logs))
  seconds = time.perf_counter() - t0
  loss = float(logs["loss/total"])
  if not np.isfinite(loss):
    raise RuntimeError(f"{cfg.preset}: the loss is {loss} after {steps + 1} steps")
  per_step = cfg.train.n_rays * samples_per_ray(cfg)
  return {"it_per_s": steps / seconds, "samples_per_s": steps * per_step / seconds,
          "compile_s": compile_s, "peak_mem_mb": peak_mem_mb(compiled)}


def benchmark_scene() -> scene_lib.Scene:
  """The default synthetic scene (seed, quick) with its true poses."""
  scene, gt = synth.make_scene("seed", resolution="quick")
  scene_lib.apply_poses(scene, gt.poses)
  return scene


def run(specs: list[str], rays, samples, steps, naive: bool, bound: bool = False) -> dict:
  scene = benchmark_scene()
  results = {}
  for spec in specs:
    cfg = make_config(spec, rays, samples)
    data = train.prepare_data(scene, scene_lib.compute_normalization(scene, cfg.train.box_margin))
    n = steps or DEFAULT_STEPS.get(config.parse_spec(spec)[0], 4)
    fast = time_step(cfg, data, fields.field_fns, n)
    row = {"rays": cfg.train.n_rays, "samples_per_ray": samples_per_ray(cfg),
           "log2_table_size": cfg.hash.log2_table_size, **fast}
    if naive:
      ref = time_step(cfg, data, naive_field_fns, n)
      row.update(naive_samples_per_s=ref["samples_per_s"], naive_compile_s=ref["compile_s"],
                 speedup=fast["samples_per_s"] / ref["samples_per_s"])
    if bound:
      top = time_step(cfg, data, no_normal_field_fns, n)
      row.update(bound_samples_per_s=top["samples_per_s"],
                 fraction_of_bound=fast["samples_per_s"] / top["samples_per_s"])
    results[spec] = row
    print(f"# {spec}: {json.dumps(row)}", file=sys.stderr, flush=True)
  return results


def table(results: dict, info: dict) -> str:
  slow_gpu = machine.scatter_regression_warning(info["jax"], info["backend"])
  lines = [f"machine: {machine.line(info)}", *([f"warning: {slow_gpu}"] if slow_gpu else []),
           f"{'preset':<34} {'rays':>5} {'smp/ray':>7} {'it/s':>7} {'samples/s':>10} "
           f"{'naive smp/s':>11} {'speedup':>7} {'bound smp/s':>11} {'of bound':>8} "
           f"{'compile s':>9} {'peak MB':>8}"]
  fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
  for spec, r in results.items():
    lines.append(
        f"{spec:<34} {r['rays']:>5} {r['samples_per_ray']:>7} {r['it_per_s']:>7.2f} "
        f"{r['samples_per_s']:>10.0f} {fmt(r.get('naive_samples_per_s'), '.0f'):>11} "
        f"{fmt(r.get('speedup'), '.2f'):>7} {fmt(r.get('bound_samples_per_s'), '.0f'):>11} "
        f"{fmt(r.get('fraction_of_bound'), '.2f'):>8} {r['compile_s']:>9.1f} "
        f"{r['peak_mem_mb']:>8.0f}")
  return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="python benchmarks/train_step.py", description=__doc__.split(
      "\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
  p.add_argument("--presets", default="cpu,paper",
                 help="comma-separated presets or variants (preset+component.field=value)")
  p.add_argument("--rays", type=int, help="rays per batch (default: each preset's)")
  p.add_argument("--samples", help="U,I: uniform and importance samples per ray (default: preset's)")
  p.add_argument("--steps", type=int, help="timed steps per preset (default: cpu 10, paper 4)")
  p.add_argument("--no-naive", action="store_true", help="skip the nested-autodiff reference step")
  p.add_argument("--bound", action="store_true",
                 help="also time the step with the normal branch removed (the upper bound)")
  return p


@cli
def main(argv=None) -> int:
  args = build_parser().parse_args(argv)
  samples = None
  if args.samples:
    try:
      samples = tuple(int(v) for v in args.samples.split(","))
    except ValueError:
      samples = ()
    if len(samples) != 2 or min(samples) < 1:
      raise UserError(f"--samples {args.samples!r}: write U,I, two positive integers")
  for name, value in (("rays", args.rays), ("steps", args.steps)):
    if value is not None and value < 1:
      raise UserError(f"--{name} {value}: must be positive")
  specs = [s.strip() for s in args.presets.split(",") if s.strip()]
  info = machine.describe(devices=True)
  results = run(specs, args.rays, samples, args.steps, not args.no_naive, args.bound)
  if args.json:
    print(json.dumps({"machine": info, **results}, indent=2))
  else:
    print(table(results, info))
  return 0


if __name__ == "__main__":
  sys.exit(main())
