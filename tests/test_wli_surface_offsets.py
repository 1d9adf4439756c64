"""experiments/wli_surface_offsets.py: the zero crossing, NeuS's dense expectation and the slopes
against closed forms for piecewise-linear SDFs along a ray."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import wli_surface_offsets as wso  # noqa: E402

T = np.linspace(-wso.WINDOW_UM, wso.WINDOW_UM, wso.WINDOW_POINTS)
S = 5.0  # NeuS s per um: weights ~0.2 um wide, well inside the +-4 um window


def _sdf(c, above, below):
  """[R, n] f(t) = slope * (c - t), `above` before the surface at t = c, `below` after it."""
  c = np.asarray(c, np.float64)[:, None]
  return np.where(T[None] < c, above * (c - T[None]), below * (c - T[None]))


def test_a_unit_slope_surface_is_found_exactly_and_rendered_unbiased():
  c = np.array([0.37, -1.204, 2.5])
  r = wso.crossing_offsets(T, _sdf(c, 1.0, 1.0), S)
  assert r["has"].all()
  np.testing.assert_allclose(r["crossing"], c, atol=1e-9)
  np.testing.assert_allclose(r["slope_above"], 1.0, atol=1e-9)
  np.testing.assert_allclose(r["slope_below"], 1.0, atol=1e-9)
  np.testing.assert_allclose(r["acc"], 1.0, atol=1e-3)  # c = 2.5: Phi(-7.5) stays past the window
  np.testing.assert_allclose(r["expected"], c, atol=2e-3)
  np.testing.assert_allclose(r["before"], 0.5, atol=0.03)


def test_steeper_below_pulls_the_expectation_before_the_crossing_by_the_closed_form():
  """T(t) = Phi(s f(t)): half the weight on each side, each a half-logistic of scale 1/(s g), so
  E[t] - c = ln 2 (1 / (s g_below) - 1 / (s g_above))."""
  c, g_above, g_below = np.array([0.1, -0.6]), 1.0, 3.0
  r = wso.crossing_offsets(T, _sdf(c, g_above, g_below), S)
  closed = np.log(2.0) * (1.0 / (S * g_below) - 1.0 / (S * g_above))
  np.testing.assert_allclose(r["expected"] - r["crossing"], closed, atol=3e-3)
  np.testing.assert_allclose(r["slope_above"], g_above, atol=1e-9)
  np.testing.assert_allclose(r["slope_below"], g_below, atol=1e-9)


def test_a_ray_without_a_crossing_is_flagged():
  f = np.ones((1, len(T)))
  assert not wso.crossing_offsets(T, f, S)["has"][0]
