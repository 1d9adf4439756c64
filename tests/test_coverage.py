"""ofjax.coverage: which points a WLI scan measured, against a float64 NumPy loop over the scans
(scene.project_orthographic, written for the host) and against the ground truth's coverage."""

import chex
import jax.numpy as jnp
import numpy as np

import analytic_scene
from ofjax import coverage, metrics, synth, train
from ofjax import scene as scene_lib
from ofjax.config import resolve

# Points closer than this (in pixels, or in tolerances) to a pixel edge or to the tolerance's
# bound are left out of the exact comparison: float32 against float64 may fall either side.
EDGE = 1e-3


def reference(points_um, scans, tolerance_px):
  """[N] bool and [N] bool (whether the answer sits on an edge), float64, one scan at a time."""
  measured = np.zeros(len(points_um), bool)
  edge = np.zeros(len(points_um), bool)
  for s in scans:
    col, row, z, inside = scene_lib.project_orthographic(points_um, s.c2w, s.pixel_size, s.shape)
    r = np.clip(np.floor(row), 0, s.shape[0] - 1).astype(int)
    c = np.clip(np.floor(col), 0, s.shape[1] - 1).astype(int)
    depth = s.depth[r, c].astype(np.float64)
    off = np.abs(depth - z) / (tolerance_px * s.pixel_size[0])
    hit = inside & np.isfinite(depth) & (off <= 1.0)
    measured |= hit
    frac = lambda v: np.abs(v - np.round(v))  # noqa: E731 distance to the nearest pixel edge
    edge |= (frac(col) < EDGE) | (frac(row) < EDGE) | (np.isfinite(depth) & (np.abs(off - 1) < EDGE))
  return measured, edge


class MeasuredTest(chex.TestCase):

  @chex.variants(with_jit=True, without_jit=True)
  def test_matches_a_float64_loop_over_the_scans(self):
    scene, _ = analytic_scene.make()
    # Scans of different sizes: the device arrays are padded to the largest, each keeps its own.
    scene.wli[1].depth = scene.wli[1].depth[:-8, :-6]  # even: pixel centres stay on the grid
    norm = scene_lib.compute_normalization(scene)
    data = train.prepare_data(scene, norm)
    tol = 2.0
    rng = np.random.default_rng(0)
    on = [scene_lib.wli_points(s, 3) for s in scene.wli]
    axes = np.concatenate([np.broadcast_to(s.c2w[:3, 2], p.shape) for s, p in zip(scene.wli, on)])
    on = np.concatenate(on)
    lo, hi = on.min(0) - 5.0, on.max(0) + 5.0
    points = np.concatenate([
        on,  # the measured points themselves
        on + axes * rng.uniform(-3, 3, (len(on), 1)) * tol * scene.wli[0].pixel_size[0],  # moved
        rng.uniform(lo, hi, (3000, 3)),  # anywhere in the box
    ])
    expect, edge = reference(points, scene.wli, tol)
    measured = self.variant(coverage.wli_measured, static_argnums=(6,))
    got = np.asarray(measured(jnp.asarray(norm.to_norm(points), jnp.float32), data.wli_depth,
                              data.wli_valid, data.wli_c2w, data.wli_pixel, data.wli_hw, tol))
    chex.assert_shape(got, (len(points),))
    assert got.dtype == bool
    np.testing.assert_array_equal(got[~edge], expect[~edge])
    assert edge.mean() < 0.05  # one scan's grid of points can fall on another's pixel edges
    assert 0.2 < expect.mean() < 0.8  # both answers are well represented
    assert expect[:len(on)].all()  # every measured point is measured


def test_lenses_blind_truth_as_the_eval_finds_it():
  """On `lenses` (voids on its polished flanks), at the true surface the depth test answers as
  the evaluation's 3-D test (metrics.measured_counts: a measured point within one WLI pixel) for
  most points, and finds a blind share of the same size."""
  scene, gt = synth.make_scene("lenses", seed=0, resolution="tiny")
  scene_lib.apply_poses(scene, gt.poses)
  norm = scene_lib.compute_normalization(scene)
  data = train.prepare_data(scene, norm)
  got = np.asarray(train.wli_measured(data, resolve("cpu"))(
      jnp.asarray(norm.to_norm(gt.points), jnp.float32)))
  radius = max(max(s.pixel_size) for s in scene.wli)
  want = metrics.measured_counts(gt.points, [scene_lib.wli_points(s) for s in scene.wli],
                                 radius) > 0
  blind, blind_eval = 1 - got.mean(), 1 - want.mean()
  assert 0.1 < blind_eval < 0.6, blind_eval
  assert abs(blind - blind_eval) < 0.1, (blind, blind_eval)
  assert (got == want).mean() > 0.85
