"""The neural fields: SDF MLP (+ geometry feature), global colour G and residual colour R.

Names: `x` [..., 3] points in the normalised box [-1, 1]^3; `sdf` signed distance (positive
outside); `grad` d sdf / d x (its normalisation is the surface normal `n`); `f` the 13-d geometry
feature; `v` unit view direction; `c_global` = G(x, n, f) in (0, 1), `c_res` = R(x, n, f, v) in
(-1, 1); the rendered colour is c = c_global + c_res (paper Eqs. 1-2). With
`model.color_features = "own"`, G and R see a hash encoding of x with its own table
(`params["color_tables"]`) in place of f; with "both", beside f.

The SDF network sees [x, hash(x)]; its spatial gradient is computed with the hash encoding's
analytic Jacobian (encoding.encode_with_jacobian) chained with the MLP's input gradient, so the
normal needs no autodiff through the table gather.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from ofjax import encoding
from ofjax.config import Config


def _sdf_first_layer_init(n_xyz: int):
  """Geometric init of the first layer: xyz weights ~ N(0, sqrt(2)/sqrt(out)), encoding weights 0.

  With the hash features switched off at init the network is the SAL/NeuS sphere MLP in xyz alone.
  """

  def init(key, shape, dtype=jnp.float32):
    std = math.sqrt(2.0) / math.sqrt(shape[1])
    w = jax.random.normal(key, shape, dtype) * std
    return w.at[n_xyz:].set(0.0)

  return init


class SDFNet(nn.Module):
  """MLP [x, hash(x)] -> [sdf, f] with geometric (sphere) initialisation (init_params may replace
  it by the plane, ModelConfig.init_shape)."""
  hidden: int
  layers: int
  feature_dim: int
  radius: float

  @nn.compact
  def __call__(self, inp):
    h = inp
    for i in range(self.layers):
      init = (_sdf_first_layer_init(3) if i == 0 else
              nn.initializers.normal(math.sqrt(2.0) / math.sqrt(self.hidden)))
      h = nn.relu(nn.Dense(self.hidden, kernel_init=init, bias_init=nn.initializers.zeros)(h))
    out_init = lambda k, s, d=jnp.float32: (math.sqrt(math.pi) / math.sqrt(s[0]) +
                                            1e-4 * jax.random.normal(k, s, d))
    return nn.Dense(1 + self.feature_dim, kernel_init=out_init,
                    bias_init=nn.initializers.constant(-self.radius))(h)


class ColorNet(nn.Module):
  """MLP -> 3 channels (pre-activation); `layers` hidden ReLU layers of width `hidden`."""
  hidden: int
  layers: int

  @nn.compact
  def __call__(self, inp):
    h = inp
    for _ in range(self.layers):
      h = nn.relu(nn.Dense(self.hidden)(h))
    return nn.Dense(3)(h)


# Real spherical harmonics up to degree 3 (16 coefficients, "degree 4" in tiny-cuda-nn's count),
# the standard constants of the real SH basis.
_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
          0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_encode(v, degree: int = 4):
  """Real spherical harmonics of unit directions.

  Args:
    v: [..., 3] unit vectors.
    degree: number of bands (1..4), giving degree**2 coefficients.

  Returns:
    [..., degree**2].
  """
  x, y, z = v[..., 0], v[..., 1], v[..., 2]
  out = [jnp.full_like(x, _SH_C0)]
  if degree > 1:
    out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
  if degree > 2:
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out += [_SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * xz,
            _SH_C2[4] * (xx - yy)]
  if degree > 3:
    out += [_SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * xy * z, _SH_C3[2] * y * (4 * zz - xx - yy),
            _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
            _SH_C3[5] * z * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy)]
  return jnp.stack(out, -1)


def _nets(cfg: Config):
  m = cfg.model
  return (SDFNet(m.sdf_hidden, m.sdf_layers, m.feature_dim, m.sphere_init_radius),
          ColorNet(m.color_hidden, m.color_layers), ColorNet(m.color_hidden, m.color_layers))


def _plane_init(sdf_params: dict, up, level, layers: int) -> dict:
  """The SDF network as the plane sdf(x) = up . x - level, exactly, with the shapes unchanged.

  Two hidden units carry relu(up . x - level) and relu(level - up . x) through every hidden layer
  and the output subtracts them; every other unit's SDF output weight starts at zero (the feature
  outputs keep their random init, and the zero weights get gradients from the first step).
  """
  p = jax.tree.map(jnp.asarray, sdf_params)
  up = jnp.asarray(up, jnp.float32)
  k0 = p["Dense_0"]["kernel"].at[:, :2].set(0.0)
  p["Dense_0"]["kernel"] = k0.at[:3, 0].set(up).at[:3, 1].set(-up)
  p["Dense_0"]["bias"] = p["Dense_0"]["bias"].at[0].set(-level).at[1].set(level)
  for i in range(1, layers):  # deeper hidden layers pass the two units on unchanged
    k = p[f"Dense_{i}"]["kernel"].at[:, :2].set(0.0)
    p[f"Dense_{i}"]["kernel"] = k.at[0, 0].set(1.0).at[1, 1].set(1.0)
    p[f"Dense_{i}"]["bias"] = p[f"Dense_{i}"]["bias"].at[:2].set(0.0)
  out = p[f"Dense_{layers}"]
  out["kernel"] = out["kernel"].at[:, 0].set(0.0).at[0, 0].set(1.0).at[1, 0].set(-1.0)
  out["bias"] = out["bias"].at[0].set(0.0)
  return p


def init_params(key, cfg: Config, substrate=None) -> dict:
  """All trainable parameters: hash tables, the three MLPs and NeuS's variance.

  substrate: (up [3] unit vector, level []) of the plane the "plane" init starts from
  (ModelConfig.init_shape), in normalised units; None is the box's mid-plane z = 0 (enough for a
  template whose values a checkpoint replaces).
  """
  k_tab, k_sdf, k_g, k_r = jax.random.split(key, 4)
  sdf_net, g_net, r_net = _nets(cfg)
  n_enc = cfg.hash.n_levels * cfg.hash.n_features
  mode = cfg.model.color_features
  geo_in = 3 + 3 + (mode != "own") * cfg.model.feature_dim + (mode != "shared") * n_enc
  sdf = sdf_net.init(k_sdf, jnp.zeros((1, 3 + n_enc)))["params"]
  if cfg.model.init_shape in ("plane", "wli"):  # "wli" fits the plane to the WLI (ofjax.prefit)
    up, level = substrate if substrate is not None else ((0.0, 0.0, 1.0), 0.0)
    sdf = _plane_init(sdf, up, level, cfg.model.sdf_layers)
  params = {
      "tables": encoding.init_tables(k_tab, cfg.hash),
      "sdf": sdf,
      "color": g_net.init(k_g, jnp.zeros((1, geo_in)))["params"],
      "residual": r_net.init(k_r, jnp.zeros((1, geo_in + cfg.model.sh_degree**2)))["params"],
      # NeuS: inverse std s = exp(10 * variance).
      "variance": jnp.asarray(cfg.render.init_inv_s, jnp.float32),
  }
  if mode != "shared":  # a key apart from the four above: "shared" runs draw what they always drew
    params["color_tables"] = encoding.init_tables(jax.random.fold_in(key, 1), cfg.hash)
  return params


def inv_s(params):
  return jnp.exp(10.0 * params["variance"])


def sdf_and_feature(params, x, cfg: Config, encode=encoding.encode):
  """[..., 1 + feature_dim] SDF network output (SDF, then f) at points x: [..., 3].

  encode: (tables, x, hash cfg) -> features; benchmarks pass the plain gather to differentiate
  through it.
  """
  feats = encode(params["tables"], x, cfg.hash)
  return _nets(cfg)[0].apply({"params": params["sdf"]}, jnp.concatenate([x, feats], -1))


def sdf_value(params, x, cfg: Config):
  """[...] SDF at points x: [..., 3] without its spatial gradient (sampling, export and the WLI
  surface loss; differentiable in params)."""
  return sdf_and_feature(params, x, cfg)[..., 0]


def geometry(params, x, cfg: Config):
  """SDF, its spatial gradient and the geometry feature at points x.

  Args:
    x: [..., 3] points in the normalised box.

  Returns:
    sdf: [...]; grad: [..., 3] = d sdf / d x; f: [..., feature_dim].
  """
  feats, jac = encoding.encode_with_jacobian(params["tables"], x, cfg.hash)
  inp = jnp.concatenate([x, feats], -1)
  sdf_net = _nets(cfg)[0]
  out, vjp = jax.vjp(lambda i: sdf_net.apply({"params": params["sdf"]}, i), inp)
  # d sdf / d inp through the small MLP only (points are independent, so pulling back a one-hot
  # cotangent on the SDF channel gives every point's gradient); the chain to x uses the analytic
  # encoding Jacobian.
  (g_inp,) = vjp(jnp.zeros_like(out).at[..., 0].set(1.0))
  grad = g_inp[..., :3] + jnp.einsum("...k,...kj->...j", g_inp[..., 3:], jac)
  return out[..., 0], grad, out[..., 1:]


def colors(params, x, n, f, v, cfg: Config):
  """Global colour G(x, n, f) in (0, 1) and residual R(x, n, f, v) in (-1, 1) (paper Eqs. 1-2).

  Args:
    x: [..., 3] points; n: [..., 3] unit normals; f: [..., feature_dim]; v: [..., 3] unit view dirs.

  Returns:
    c_global: [..., 3]; c_res: [..., 3] (zeros when the residual branch is off).
  """
  _, _, r_net = _nets(cfg)
  geo = _color_input(params, x, n, f, cfg)
  c_global = _global(params, geo, cfg)
  if not cfg.model.residual:
    return c_global, jnp.zeros_like(c_global)
  r_in = jnp.concatenate([geo, sh_encode(v, cfg.model.sh_degree)], -1)
  c_res = (jax.nn.sigmoid(r_net.apply({"params": params["residual"]}, r_in)) - 0.5) * 2.0
  return c_global, c_res


def _color_input(params, x, n, f, cfg: Config):
  """[..., 6 + k] what G and R see of a point: [x, n, f] ("shared"), [x, n, own hash(x)] ("own":
  f unused) or [x, n, f, own hash(x)] ("both"), by model.color_features."""
  mode = cfg.model.color_features
  parts = [x, n] + [f] * (mode != "own")
  if mode != "shared":
    parts.append(encoding.encode(params["color_tables"], x, cfg.hash))
  return jnp.concatenate(parts, -1)


def _global(params, geo, cfg: Config):
  """G on its input (_color_input): [..., 3] in (0, 1)."""
  return jax.nn.sigmoid(_nets(cfg)[1].apply({"params": params["color"]}, geo))


# The SDF gradient vanishes exactly where every hidden ReLU is off; there |v| must stay
# differentiable (the gradient of sqrt at 0 is infinite), so norms are smoothed by this epsilon.
NORM_EPS = 1e-6


def safe_norm(v):
  """[...] Euclidean norm of v: [..., k], with a finite gradient at v = 0."""
  return jnp.sqrt(jnp.sum(v * v, -1) + NORM_EPS**2)


def unit(v):
  return v / safe_norm(v)[..., None]


def field_fns(params, cfg: Config):
  """The three point functions the renderer needs: (geometry_fn, color_fn, sdf_fn).

  geometry_fn(x) -> (sdf, grad, f) and color_fn(x, n, f, v) -> (c_global, c_res) are
  differentiable; sdf_fn(x) -> sdf has no gradient (sample placement).
  """
  frozen = jax.lax.stop_gradient(params)
  return (lambda x: geometry(params, x, cfg), lambda x, n, f, v: colors(params, x, n, f, v, cfg),
          lambda x: sdf_value(frozen, x, cfg))


def global_color(params, x, cfg: Config):
  """Vertex colour for export: G(x, n, f) with n and f from the SDF network (paper Sec. 3.3.2)."""
  _, grad, f = geometry(params, x, cfg)
  return _global(params, _color_input(params, x, unit(grad), f, cfg), cfg)
