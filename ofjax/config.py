"""Configuration: one frozen dataclass per component, paper values as defaults.

Two presets exist: `paper` (the numbers of OpticFusion and its reference code) and `cpu` (the
default: small enough to train the default synthetic scene on a 2-core laptop CPU in minutes).
`resolve(preset, **overrides)` returns a `Config`; `Config.to_dict()` is what a run writes to
`config.json`, and `Config.from_dict` reads it back.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any


@dataclasses.dataclass(frozen=True)
class HashConfig:
  """Multiresolution hash encoding (instant-ngp; OpticFusion supplementary A)."""
  n_levels: int = 16  # number of grid levels L
  n_features: int = 2  # features per level F
  log2_table_size: int = 19  # entries per level T = 2**log2_table_size
  base_resolution: int = 16  # resolution of the coarsest level N_min
  per_level_scale: float = 1.447269  # growth factor b between levels
  init_scale: float = 1e-4  # table entries start uniform in (-init_scale, init_scale)
  # Level groups gathered (and, in the gradient, scattered) as separate ops: independent ops that
  # XLA's CPU runtime may run on different cores. Must divide n_levels; the features are the same.
  gather_groups: int = 1

  def __post_init__(self):
    if self.gather_groups < 1 or self.n_levels % self.gather_groups:
      raise ValueError(f"hash.gather_groups {self.gather_groups} must divide hash.n_levels "
                       f"{self.n_levels}")


INIT_SHAPES = ("sphere", "plane", "wli")
COLOR_FEATURES = ("shared", "own", "both")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """SDF MLP, global colour MLP G and residual colour MLP R (DESIGN.md, supplementary A)."""
  sdf_hidden: int = 64  # width of the SDF MLP's hidden layers
  sdf_layers: int = 1  # number of hidden layers of the SDF MLP
  feature_dim: int = 13  # geometry feature f output beside the SDF value
  color_hidden: int = 64  # width of the colour MLPs' hidden layers
  color_layers: int = 2  # number of hidden layers of each colour MLP
  sh_degree: int = 4  # spherical-harmonics degree of the view direction fed to R (16 coefficients)
  # Geometric init of the SDF: "sphere" (SAL/NeuS and the reference: a sphere of
  # sphere_init_radius about the box centre), "plane" (the WLI's median height plane, positive on
  # the objective's side: a sample on a substrate seen from above) or "wli" (the plane, then fitted
  # to the oriented WLI points before rendering: ofjax.prefit; not in the paper).
  init_shape: str = "sphere"
  sphere_init_radius: float = 0.5  # radius of the "sphere" init (normalised units)
  wli_fit_steps: int = 300  # Adam steps of the "wli" init's fit
  wli_fit_points: int = 8192  # near-surface queries per fit step (a quarter more in the box)
  wli_fit_offset: float = 0.05  # std of the queries' offsets along the normal (reference units)
  wli_fit_lr: float = 0.01  # the fit's learning rate, cosine-decayed to a tenth
  # Weight of the fit's point-to-plane distance term (the others weigh 1). 30 puts the fitted
  # surface 2.3x closer to the WLI on `wing` but leaves a rougher field that trains to a worse
  # mesh (experiments/README.md), so the fit keeps 1.
  wli_fit_lambda_distance: float = 1.0
  residual: bool = True  # use the residual colour branch (False: the "fused w/o residual" ablation)
  # What the colour MLPs G and R see beside x, n (and v): "shared" is the SDF network's feature f,
  # as the paper and the reference, so the photos' gradient also reaches the SDF network and the
  # hash table through f; "own" is a hash encoding of their own (the same HashConfig, a separate
  # table) in place of f, so the photos move the geometry only through the normal and the
  # rendering weights (PermutoSDF's separate colour lattice; not in the paper); "both" is f and
  # that encoding side by side. The cpu preset uses "own" (its comment has the figures); at
  # colour weight 1 it lets `wing`'s SDF network die (experiments/README.md).
  color_features: str = "shared"

  def __post_init__(self):
    if self.init_shape not in INIT_SHAPES:
      raise ValueError(f"model.init_shape {self.init_shape!r}: use one of {', '.join(INIT_SHAPES)}")
    if self.color_features not in COLOR_FEATURES:
      raise ValueError(f"model.color_features {self.color_features!r}: use one of "
                       f"{', '.join(COLOR_FEATURES)}")


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """NeuS sampling and compositing."""
  n_samples: int = 64  # uniform samples per ray
  n_importance: int = 64  # hierarchically upsampled samples per ray (no gradient)
  n_importance_steps: int = 4  # rounds of importance upsampling (NeuS uses 4 x 16)
  # log of NeuS's learned inverse std s (per reference unit) starts at log(exp(10 * 0.3))
  init_inv_s: float = 0.3
  cos_anneal_steps: int = 20000  # NeuS cos-anneal ratio goes 0 -> 1 over these steps
  wli_guided_samples: int = 0  # extra samples per WLI ray placed around the measured depth
  wli_guided_width: float = 0.02  # half-width (normalised units) of that depth-guided band


@dataclasses.dataclass(frozen=True)
class LossConfig:
  """Loss weights (paper Sec. 3.4 and the reference code); each loss is summed as lambda * loss."""
  lambda_color: float = 1.0  # OM colour MSE
  lambda_residual: float = 0.001  # L2 of the composited residual colour (OM rays)
  lambda_wli: float = 1.0  # WLI depth MSE in reference units (TrainConfig.reference_unit; voids masked)
  # SDF^2 (reference units) at the measured WLI points, o + D d: the depth loss constrains only the
  # rendered expectation of a ray's weights, this term the surface itself (without it the
  # substrate's zero level sits ~0.8 um below the measured one). Not in the paper: 0 here; the
  # cpu preset uses 30 (see there).
  lambda_wli_surface: float = 0.0
  lambda_eikonal: float = 0.1  # (|grad sdf| - 1)^2 on all samples
  lambda_sparsity: float = 0.01  # exp(-scale * |sdf|) of the reference, on uniform samples
  sparsity_scale: float = 1.0  # sharpness of the sparsity term, per reference unit of SDF


@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """Adam with linear warm-up then exponential decay to `decay_to` x the base rate."""
  lr: float = 0.01  # base learning rate of the networks and hash tables
  lr_inv_s: float = 0.001  # learning rate of the NeuS variance parameter
  b1: float = 0.9
  b2: float = 0.99
  eps: float = 1e-15
  warmup_steps: int = 500  # linear warm-up length
  decay_to: float = 0.1  # the rate at the last step, as a fraction of `lr`
  # Time constant of an exponential moving average of the parameters, as a fraction of
  # train.steps; the run's mesh is made from that average (ofjax.averaging). 0: from the last
  # step's parameters, as the paper.
  ema_fraction: float = 0.0


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """The training loop."""
  steps: int = 20000  # optimisation steps
  n_rays: int = 256  # rays per batch (WLI and OM mixed, equal pixel probability)
  modalities: tuple[str, ...] = ("wli", "om")  # which data supervise: the paper's ablations
  wli_share: float = 0.5  # fraction of the rays that are WLI rays when both modalities supervise
  # Measured WLI points per step, beyond the batch's WLI rays, at which the SDF term at the WLI
  # points (loss.lambda_wli_surface) is also evaluated: SDF-only queries, no rendering.
  wli_surface_points: int = 0
  seed: int = 0  # seeds parameter init and ray sampling (sampling is keyed by step)
  log_every: int = 100  # host sync + metrics.jsonl line every k steps
  checkpoint_every: int = 5000  # checkpoint every k steps
  keep_checkpoints: int = 2  # how many checkpoints to keep
  max_skipped_in_a_row: int = 20  # divergence guard: this many non-finite steps in a row stop
  # Marching-cubes cells along the longest side of the observed box; 0: cells of half a WLI pixel
  # (ofjax.export.AUTO_CELL_PX, at most export.MAX_AUTO_RESOLUTION), so the mesh keeps the detail
  # the WLI measured at its own lateral sampling.
  mesh_resolution: int = 0
  box_margin: float = 0.05  # margin around the WLI points, fraction of the box, before normalising
  # The length unit of the WLI depth loss, NeuS's s and the sparsity term, as a fraction of the
  # WLI field of view (the median scan's width). 0.1 is the reference code's unit: its WLI image
  # spans depth_focal = 10 units, and the paper's weights and s were set in it. 0 measures them
  # in the normalised box instead (earlier ofjax: ~7x coarser on the synthetic scenes, so the
  # depth loss weighed ~45x less against the colour loss than in the reference).
  reference_unit: float = 0.1

  def __post_init__(self):
    if not 0.0 < self.wli_share < 1.0:
      raise ValueError(f"train.wli_share {self.wli_share}: use a fraction strictly between 0 and 1")
    if self.mesh_resolution < 0:
      raise ValueError(f"train.mesh_resolution {self.mesh_resolution}: use a cell count, or 0 for "
                       "cells of half a WLI pixel")


# TrainConfig fields that only say how a run is kept and meshed, not what it trains: --resume may
# change them, and Config.fingerprint leaves them out.
KEEPING_FIELDS = ("checkpoint_every", "keep_checkpoints", "max_skipped_in_a_row", "mesh_resolution")
# Fields added after runs were recorded (experiments/results), left out of the fingerprint while
# at their default, with which a run trains exactly as before they existed: the recorded runs'
# fingerprints stay valid and `make reproduce` does not retrain them.
ADDED_FIELDS = {"model": ("color_features",)}


def json_tuples(fields: dict[str, Any]) -> dict[str, Any]:
  """Field values with JSON lists (a spec's or a config.json's) as tuples: a Config is a hashable
  jit argument, and its tuple fields must compare equal to what was written."""
  return {k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}


@dataclasses.dataclass(frozen=True)
class Config:
  hash: HashConfig = HashConfig()
  model: ModelConfig = ModelConfig()
  render: RenderConfig = RenderConfig()
  loss: LossConfig = LossConfig()
  optim: OptimConfig = OptimConfig()
  train: TrainConfig = TrainConfig()
  preset: str = "paper"

  def to_dict(self) -> dict[str, Any]:
    return dataclasses.asdict(self)

  @staticmethod
  def from_dict(d: dict[str, Any]) -> "Config":
    parts = {}
    for name, cls in (("hash", HashConfig), ("model", ModelConfig), ("render", RenderConfig),
                      ("loss", LossConfig), ("optim", OptimConfig), ("train", TrainConfig)):
      parts[name] = cls(**json_tuples(d.get(name, {})))
    return Config(preset=d.get("preset", "custom"), **parts)

  def dumps(self) -> str:
    return json.dumps(self.to_dict(), indent=2, sort_keys=True)

  def fingerprint(self) -> str:
    """8 hex digits of the resolved values but KEEPING_FIELDS (and ADDED_FIELDS at their
    defaults): runs with equal fingerprints trained alike (how they were kept or meshed may
    differ)."""
    d = self.to_dict()
    d["train"] = {k: v for k, v in d["train"].items() if k not in KEEPING_FIELDS}
    for part, names in ADDED_FIELDS.items():
      default = getattr(Config(), part)
      d[part] = {k: v for k, v in d[part].items()
                 if not (k in names and v == getattr(default, k))}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:8]


PRESETS: dict[str, Config] = {
    "paper": Config(),
    # The cpu preset keeps the paper's architecture and, but for the colour's and the residual's
    # (and the added SDF term at the WLI points), its loss weights, and shrinks what sets the cost per step: a 2^16-entry table (CPU cache), fewer samples per
    # ray, fewer steps, and a schedule compressed to that step count. Its table gather runs as 4
    # level groups (the scatter-adds of the gradient then share the cores: 1.08x the step on 2
    # cores, measured in benchmarks/README.md). The variance keeps the paper's rate (lr_inv_s
    # 0.001); like the depth loss it is measured in the reference's unit
    # (TrainConfig.reference_unit), which took the default scene from 2.18 to 1.46 um at 1,200
    # steps (experiments/README.md, all five scenes).
    # The SDF starts fitted to the oriented WLI points ("wli", ofjax.prefit: 300 steps from the
    # WLI's median height plane) instead of the reference's sphere: from the sphere, without
    # depth (OM only), the field collapses into one solid everywhere and has no surface; from the
    # plane it forms one; from the fitted WLI shape the fused model reached 0.78x the plane's
    # Chamfer over the five scenes at 600 steps (experiments/README.md). OM-only runs have no WLI
    # to fit: they need `--set model.init_shape=plane` (train says so).
    # The residual colour's L2 weighs 10x the paper's: at 0.001 over this short schedule the
    # view-dependent branch kept part of the diffuse colour, which the mesh (coloured by G alone)
    # then lacks (circuit's albedo 12.7 dB against 21.5 without the branch). In the 600-step
    # ablation 0.01 raised the fused albedo by 1.3 to 8.3 dB on four scenes (sensor -0.3) at
    # 0.92-1.04x the Chamfer (experiments/README.md).
    # The SDF term at the measured WLI points at 30: the fused Chamfer fell to 0.66x over the five
    # scenes at 600 steps (true poses), the spread over three seeds of `seed` from +-0.08 to
    # +-0.04 um, at -0.4 dB of albedo on average; 10 left one seed's substrate 1.4 um low
    # (experiments/README.md).
    # The mesh from the parameters' moving average (time constant 5% of the run): over the five
    # scenes at 600 steps 0.96x the Chamfer and 3-7x less spread over seeds; `lenses`, still
    # converging there, 1.09x, level at 1,200 steps; `seed` at 2,400 steps 0.76x
    # (experiments/README.md).
    # 12 of the paper's 16 levels (finest grid 16 * 1.447^11 = 936 cells instead of 4,096, which
    # a 2^16-entry table cannot hold without collisions anyway) and the SDF term at the WLI
    # points also over 4,096 further measured points per step (SDF-only queries): together
    # 0.84x the fused Chamfer over the five scenes at 600 steps (true poses; 0.530 -> 0.447 um,
    # every scene lower), -0.2 dB of albedo on average, and 1.1-1.2x the steps per second of 16
    # levels without the points (experiments/README.md, benchmarks/README.md).
    # The OM colour MSE at 0.1 of the paper's weight: at 1 the photos pull the surface off the
    # measured heights (DESIGN.md: they must not), and the fused mesh ended above the WLI-only one
    # on every scene. At 0.1, 0.85x the fused Chamfer over the five scenes at 600 steps (true
    # poses; 0.472 -> 0.400 um, every scene but `seed` lower, that one level), confirmed on new
    # instances (synth seed 1) of circuit, wing, sensor, at -0.4 dB of albedo on average (-1.9 on
    # one); 0.03 gained nothing more (experiments/README.md). OM only keeps 1 (ablation.py).
    # The colour MLPs see a hash encoding of their own instead of the SDF network's feature
    # (model.color_features "own"): 0.75x / 0.94x the fused Chamfer on `lenses` / `wing` at 3,600
    # steps, 0.97x over the five scenes at 600 (true poses), the albedo higher on four scenes by
    # 0.6-2.4 dB, at 0.76-0.94x the samples per second (experiments/README.md).
    "cpu": Config(
        hash=HashConfig(n_levels=12, log2_table_size=16, gather_groups=4),
        model=ModelConfig(init_shape="wli", color_features="own"),
        loss=LossConfig(lambda_color=0.1, lambda_residual=0.01, lambda_wli_surface=30.0),
        render=RenderConfig(n_samples=32, n_importance=32, n_importance_steps=2,
                            cos_anneal_steps=1000, wli_guided_samples=8),
        optim=OptimConfig(warmup_steps=100, ema_fraction=0.05),
        train=TrainConfig(steps=1200, n_rays=512, log_every=50, checkpoint_every=400,
                          wli_surface_points=4096),
        preset="cpu",
    ),
}


def resolve(preset: str = "cpu", **overrides: dict[str, Any]) -> Config:
  """Returns the preset with `overrides` = {component: {field: value}} applied."""
  if preset not in PRESETS:
    raise KeyError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
  cfg = PRESETS[preset]
  for comp, fields in overrides.items():
    cfg = dataclasses.replace(cfg, **{comp: dataclasses.replace(getattr(cfg, comp),
                                                                **json_tuples(fields))})
  return cfg


def parse_spec(spec: str) -> tuple[str, dict[str, dict[str, Any]]]:
  """A preset variant 'cpu+hash.log2_table_size=19+optim.lr=0.005' -> (preset, overrides).

  Values are JSON where they parse (numbers, true/false, lists), else strings. Raises ValueError
  for an item that is not component.field=value.
  """
  name, *sets = spec.split("+")
  over: dict[str, dict[str, Any]] = {}
  for item in sets:
    key, sep, value = item.partition("=")
    comp, dot, field = key.partition(".")
    if not sep or not dot:
      raise ValueError(f"{spec!r}: write overrides as component.field=value")
    try:
      parsed = json.loads(value)
    except json.JSONDecodeError:
      parsed = value
    over.setdefault(comp, {})[field] = parsed
  return name, over


def resolve_spec(spec: str, **extra: dict[str, Any]) -> Config:
  """The Config of a preset variant (parse_spec), then `extra` overrides as resolve's.

  ValueError names what is unknown.
  """
  name, over = parse_spec(spec)
  for comp, fields in extra.items():
    over.setdefault(comp, {}).update(fields)
  try:
    return resolve(name, **over)
  except (KeyError, TypeError, AttributeError) as e:
    raise ValueError(f"{spec!r}: {e}; use a preset name and existing config fields") from None


def with_steps(cfg: Config, steps: int) -> Config:
  """cfg trained for `steps` steps with its schedule's shape: a shorter run ends cos-anneal with it
  at the latest and warms up for at most a tenth of it (the CLI's --steps; sweeps use the same)."""
  return dataclasses.replace(
      cfg, train=dataclasses.replace(cfg.train, steps=steps),
      render=dataclasses.replace(cfg.render,
                                 cos_anneal_steps=min(cfg.render.cos_anneal_steps, steps)),
      optim=dataclasses.replace(cfg.optim,
                                warmup_steps=min(cfg.optim.warmup_steps, max(steps // 10, 1))))
