"""Data parallelism of the train step: the ray batch is split over local devices with jax.sharding.

Conventions: one 1-D `Mesh` over the devices with the axis name `BATCH_AXIS`; every [R, ...] batch
array is sharded along its first (ray) axis, everything else (params, optimiser state, the scene
data, the step) is replicated. XLA's SPMD partitioner then computes each device's rays locally and
all-reduces the gradients (the table gradient is a scatter-add per device, then a sum). On one
device no constraint is emitted at all, so the single-device program is unchanged.

Multi-host: after `jax.distributed.initialize()` `jax.devices()` lists the devices of all hosts
and the same mesh spans them (benchmarks/README.md).
"""

from __future__ import annotations

from typing import Sequence

import jax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ofjax.errors import UserError

BATCH_AXIS = "batch"


def batch_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A 1-D mesh over `devices` (default: all devices, local and remote) named BATCH_AXIS."""
  devices = list(jax.devices() if devices is None else devices)
  return Mesh(devices, (BATCH_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  """The sharding of params, optimiser state and scene data: a full copy on every device."""
  return NamedSharding(mesh, PartitionSpec())


def check_divisible(n_rays: int, mesh: Mesh, what: str = "--rays") -> None:
  """Raises UserError unless a batch of n_rays rows (named `what` in the message) splits evenly
  over the mesh (fixed shapes per device)."""
  if n_rays % mesh.size:
    raise UserError(f"{what} {n_rays}: must be a multiple of the {mesh.size} devices the ray batch "
                    "is split over; choose a multiple")


def shard_rays(batch: dict[str, jax.Array], mesh: Mesh) -> dict[str, jax.Array]:
  """Inside jit: constrains every [R, ...] array of `batch` to be split along R over the mesh."""
  if mesh.size == 1:
    return batch
  rays = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
  return {k: jax.lax.with_sharding_constraint(v, rays) for k, v in batch.items()}
