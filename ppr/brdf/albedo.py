r"""White-surface directional albedo ``E(m, cos theta)`` of the BRDF's explicit terms.

The multiple-scattering remainder (docs/physics/energy.md) needs, for an ideal white surface
(``F == 1``, :meth:`ppr.Material.ideal_white`), the directional albedo carried by the
*explicit* terms (single bounce now; single + double once the double-bounce term exists)

    E(m, mu) = integral over the outgoing hemisphere of f_explicit,00(k, k') (k'.n) d omega',
    mu = k.n,

and its cosine-weighted hemispherical average ``E_avg(m) = 2 int_0^1 E(m, mu) mu d mu``.

Tables
    One ``.npz`` table per set of explicit terms in ``ppr/data/albedo_<terms>.npz``
    (``albedo_single.npz``; a ``albedo_double_single.npz`` for single + double), written by
    ``scripts/make_albedo_tables.py`` and loaded once, lazily, as small NumPy constants.

    Grid: uniform in ``x = log(1 + m)`` (``0 <= m <= 1e6``) and in the warped cosine
    ``v = log(mu + MU0) + ALPHA mu`` (``0 <= mu <= 1``). The log part resolves the grazing band
    ``mu ~ 1/sqrt(m)`` at every roughness with the same number of nodes (E depends on
    ``mu sqrt(m)`` there); the linear part keeps nodes near normal incidence for small m.
    Interpolant: tensor-product Catmull-Rom (cubic convolution; C1, third-order) with ghost
    nodes from quadratic extrapolation, so ``E`` is smooth and differentiable in ``m`` and
    ``mu``. ``E_avg`` nodes are the exact (quadrature) integrals of the ``mu``-interpolant at
    each ``x`` node, so the 1-D Catmull-Rom interpolant of ``E_avg`` in ``x`` equals the
    integral of the 2-D interpolant (interpolation is linear in the node values): the
    multiple-scattering lobe built from the *interpolated* E conserves energy exactly up to
    that 1-D quadrature, independently of the table's own error.

Quadrature (:func:`directional_albedo`)
    In half-vector coordinates around the normal: with ``u = cos^(m+1) theta_h`` the lobe
    weight ``p(h) d omega_h = du d phi / (2 pi)`` is uniform, and with ``w = -log u`` the
    whole integrand (including ``p``) decays like ``e^-w`` for every m, with
    ``cos theta_h = exp(-w/(m+1))`` and ``1 - cos theta_h = -expm1(-w/(m+1))`` exact at
    m = 1e6. ``d omega_out = 4 (k.h) d omega_h`` and ``d omega_h = cos theta_h dw dphi/(m+1)``.
    The outgoing direction leaves the hemisphere at the closed-form
    ``theta_b(phi) = beta/2 + pi/4`` (``beta = atan2(sin theta cos phi, cos theta)``), and the
    joint-visibility ``min(P(k), P(k'))`` kinks where ``k'.n = k.n``, at ``theta_h = beta``:
    both are panel breakpoints. ``phi`` runs over ``[0, pi]`` (mirror symmetry) split at
    ``pi/2`` (where the kink curve meets ``theta_h = 0``), Gauss-Legendre in every panel.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._safe import float_dtype
from .._types import Array, ArrayLike

__all__ = [
    "AlbedoTable",
    "MU0",
    "ALPHA",
    "M_MAX",
    "albedo",
    "albedo_avg",
    "deficit",
    "deficit_avg",
    "build_table",
    "directional_albedo",
    "load_table",
    "table_path",
    "warp_mu",
]

DATA_DIR = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data")
MU0 = 1e-4
ALPHA = 3.0
M_MAX = 1e6
W_MAX = 40.0  # e^-40 = 4e-18: truncation of the w integral
# static panel breakpoints in w (geometric), completed by the kink and the horizon
_W_BREAKS = (0.5, 1.5, 3.5, 7.5, 15.5, 27.0)


def warp_mu(mu):
    """Grid coordinate of the cosine: ``log(mu + MU0) + ALPHA mu`` (works for numpy and jax)."""
    lib = jnp if isinstance(mu, jnp.ndarray) else np
    return lib.log(mu + MU0) + ALPHA * mu


def unwarp_v(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`warp_mu` on [0, 1] (NumPy, bisection; offline use)."""
    v = np.asarray(v, np.float64)
    lo = np.zeros_like(v)
    hi = np.ones_like(v)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        big = warp_mu(mid) > v
        hi = np.where(big, mid, hi)
        lo = np.where(big, lo, mid)
    return 0.5 * (lo + hi)


@dataclass(frozen=True, eq=False)
class AlbedoTable:
    """Albedo table of one set of explicit terms (NumPy constants, float64).

    It stores the *deficit* ``D = 1 - E`` (and ``D_avg = 1 - E_avg``), small numbers that keep
    their relative precision in float32 when ``E -> 1`` (large m away from grazing), so the
    remainder ``D(k) D(k') / (pi D_avg)`` never divides rounding noise.
    ``D_pad`` is ``(nx + 2, nv + 2)``: the ``nx x nv`` node values with one ghost node on each
    side; ``D_avg_pad`` is ``(nx + 2,)``. Node ``i`` sits at ``x = x_lo + i dx``.
    """

    terms: tuple[str, ...]
    x_lo: float
    dx: float
    nx: int
    v_lo: float
    dv: float
    nv: int
    D_pad: np.ndarray
    D_avg_pad: np.ndarray
    info: str = ""

    @property
    def D(self) -> np.ndarray:
        """Node values of the deficit ``1 - E``."""
        return self.D_pad[1:-1, 1:-1]

    @property
    def D_avg(self) -> np.ndarray:
        return self.D_avg_pad[1:-1]

    @property
    def x_nodes(self) -> np.ndarray:
        return self.x_lo + self.dx * np.arange(self.nx)

    @property
    def v_nodes(self) -> np.ndarray:
        return self.v_lo + self.dv * np.arange(self.nv)


def _pad_quadratic(a: np.ndarray, axis: int) -> np.ndarray:
    """Add one ghost node at each end along ``axis`` by quadratic extrapolation."""
    a = np.moveaxis(a, axis, 0)
    lo = 3 * a[0] - 3 * a[1] + a[2]
    hi = 3 * a[-1] - 3 * a[-2] + a[-3]
    out = np.concatenate([lo[None], a, hi[None]], axis=0)
    return np.moveaxis(out, 0, axis)


def grid_nodes(nx: int, nv: int):
    """Node coordinates ``(x_nodes, v_nodes)`` and the corresponding ``(m, mu)``."""
    x_hi = float(np.log1p(M_MAX))
    x = np.linspace(0.0, x_hi, nx)
    v = np.linspace(float(warp_mu(0.0)), float(warp_mu(1.0)), nv)
    m = np.expm1(x)
    mu = unwarp_v(v)
    mu[0], mu[-1] = 0.0, 1.0
    return x, v, m, mu


def _cr_weights(t, lib=jnp):
    t2 = t * t
    t3 = t2 * t
    return (
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    )


_CR_POLY = np.array(
    [[0.0, -0.5, 1.0, -0.5], [1.0, 0.0, -2.5, 1.5], [0.0, 0.5, 2.0, -1.5], [0.0, 0.0, -0.5, 0.5]]
)
"""``_cr_weights(t)[a] = sum_p _CR_POLY[a, p] t^p``."""


def _cr_cubics(rows: Array, n: int) -> tuple[Array, Array, Array, Array]:
    """Catmull-Rom through the padded ``rows`` (``(n + 2, ...)``, node ``j`` at row ``j + 1``)
    as the monomial coefficients ``(c0, c1, c2, c3)`` of each of the ``n - 1`` cells,
    each ``(n - 1, ...)``, stored once (:func:`ppr.optics._frames.store`) so that XLA CPU gathers
    them instead of re-computing them per query."""
    from ..optics._frames import store

    m = n - 1
    shifted = [rows[a : a + m] for a in range(4)]
    return tuple(
        store(sum(float(_CR_POLY[a, p]) * shifted[a] for a in range(4) if _CR_POLY[a, p]))
        for p in range(4)
    )


def _cr_eval(cubics, i: Array, t: Array) -> Array:
    """The cubics of :func:`_cr_cubics` at cell ``i`` (in ``[0, n - 2]``) and local ``t``:
    four column gathers and Horner (11 against 19 ns per 16-entry row, 250k float32: one
    gather of four rows of values ran slower)."""
    c0, c1, c2, c3 = (jnp.take(c, i, axis=0, mode="clip") for c in cubics)
    t = t.reshape(t.shape + (1,) * (c0.ndim - t.ndim))
    return ((c3 * t + c2) * t + c1) * t + c0


def _cell(coord, lo, step, n):
    """Cell index in [0, n-2] and local coordinate t in [0, 1] (clamped at the ends)."""
    s = jnp.clip((coord - lo) / step, 0.0, n - 1.0)
    i = jnp.clip(jnp.floor(s), 0, n - 2)
    return i.astype(jnp.int32), s - i


def _interp_1d_np_row(vals_pad: np.ndarray, v_lo: float, dv: float, nv: int, v: np.ndarray):
    """NumPy Catmull-Rom along the last axis of a padded row (offline E_avg quadrature)."""
    s = np.clip((v - v_lo) / dv, 0.0, nv - 1.0)
    i = np.clip(np.floor(s), 0, nv - 2).astype(int)
    t = s - i
    w = _cr_weights(t, np)
    return sum(w[a] * vals_pad[..., i + a] for a in range(4))


def build_table(terms, D_nodes: np.ndarray, info: str = "") -> AlbedoTable:
    """Table from deficit node values ``D_nodes = 1 - E`` of shape ``(nx, nv)`` on
    :func:`grid_nodes`.

    ``D_avg`` at each x node is the 1-D integral ``2 int_0^1 D(mu) mu dmu`` of the
    Catmull-Rom interpolant in ``v`` (8-point Gauss-Legendre per v cell, Jacobian
    ``dmu/dv`` from the exact inverse warp), so it matches the runtime interpolant.
    """
    D_nodes = np.asarray(D_nodes, np.float64)
    nx, nv = D_nodes.shape
    x, v, _, _ = grid_nodes(nx, nv)
    D_pad = _pad_quadratic(_pad_quadratic(D_nodes, 0), 1)
    # D_avg of each padded x row (ghost rows too: linear in the node values, so consistent)
    gx, gw = np.polynomial.legendre.leggauss(8)
    dv = v[1] - v[0]
    a = v[:-1, None] + 0.5 * dv * (gx[None, :] + 1.0)  # (nv-1, 8)
    wts = 0.5 * dv * gw[None, :] * np.ones_like(a)
    vq = a.ravel()
    wq = wts.ravel()
    muq = unwarp_v(vq)
    dmu_dv = 1.0 / (1.0 / (muq + MU0) + ALPHA)
    Dq = _interp_1d_np_row(D_pad, v[0], dv, nv, vq)  # (nx+2, nq)
    D_avg_pad = 2.0 * np.sum(Dq * (muq * dmu_dv * wq)[None, :], axis=-1)
    return AlbedoTable(
        terms=tuple(sorted(terms)),
        x_lo=float(x[0]),
        dx=float(x[1] - x[0]),
        nx=nx,
        v_lo=float(v[0]),
        dv=float(dv),
        nv=nv,
        D_pad=D_pad,
        D_avg_pad=D_avg_pad,
        info=info,
    )


def table_path(terms) -> str:
    return os.path.join(DATA_DIR, "albedo_" + "_".join(sorted(terms)) + ".npz")


def save_table(table: AlbedoTable, path: str | None = None) -> str:
    path = table_path(table.terms) if path is None else path
    os.makedirs(os.path.dirname(path), exist_ok=True)
    np.savez(
        path,
        terms=np.array(table.terms),
        grid=np.array([table.x_lo, table.dx, table.nx, table.v_lo, table.dv, table.nv, MU0, ALPHA]),
        D_pad=table.D_pad,
        D_avg_pad=table.D_avg_pad,
        info=np.array(table.info),
    )
    return path


@functools.cache
def load_table(terms: tuple[str, ...]) -> AlbedoTable:
    """The table for the explicit terms ``terms`` (loaded once; NumPy constants)."""
    path = table_path(terms)
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"no albedo table for explicit terms {tuple(sorted(terms))!r} at {path}; "
            f"run: python scripts/make_albedo_tables.py --terms {','.join(sorted(terms))}"
        )
    with np.load(path) as z:
        x_lo, dx, nx, v_lo, dv, nv, mu0, alpha = (float(g) for g in z["grid"])
        if mu0 != MU0 or alpha != ALPHA:
            raise ValueError(f"albedo table {path} was built with another warp; rebuild it")
        return AlbedoTable(
            terms=tuple(str(t) for t in z["terms"]),
            x_lo=x_lo,
            dx=dx,
            nx=int(nx),
            v_lo=v_lo,
            dv=dv,
            nv=int(nv),
            D_pad=np.array(z["D_pad"]),
            D_avg_pad=np.array(z["D_avg_pad"]),
            info=str(z["info"]),
        )


def deficit(table: AlbedoTable, m: ArrayLike, mu: ArrayLike) -> Array:
    """Interpolated deficit ``D(m, mu) = 1 - E(m, mu)`` (broadcasts; dtype of the inputs).

    Smooth (C1) and differentiable in ``m`` and ``mu``; ``m`` is clamped to [0, 1e6] and
    ``mu`` to [0, 1]. Not clamped to >= 0 (callers that need a non-negative lobe clamp).
    """
    dt = float_dtype(m, mu)
    m = jnp.asarray(m, dt)
    mu = jnp.asarray(mu, dt)
    m, mu = jnp.broadcast_arrays(m, mu)
    x = jnp.log1p(jnp.clip(m, 0.0, M_MAX))
    v = warp_mu(jnp.clip(mu, 0.0, 1.0))
    i, t = _cell(x, table.x_lo, table.dx, table.nx)
    j, s = _cell(v, table.v_lo, table.dv, table.nv)
    D = jnp.asarray(table.D_pad, dt)
    wx = _cr_weights(t)
    wv = _cr_weights(s)
    out = jnp.zeros(m.shape, dt)
    for a in range(4):
        row = jnp.zeros(m.shape, dt)
        for b in range(4):
            row = row + wv[b] * D[i + a, j + b]
        out = out + wx[a] * row
    return out


def deficit_one_material(table: AlbedoTable, m0: ArrayLike, mu: ArrayLike) -> Array:
    """:func:`deficit` for one ``m`` shared by the batch (scalar ``m0``): the Catmull-Rom step
    in ``m`` is done once on the table (a ``(nv + 3,)`` row, by a dot so that XLA CPU stores
    it rather than re-computing it per element), leaving a 4-point interpolation in ``mu``
    per element. Equal to :func:`deficit` up to rounding (same interpolant, summed in the
    other order; tests/test_furnace.py)."""
    dt = float_dtype(m0, mu)
    m0 = jnp.asarray(m0, dt)
    mu = jnp.asarray(mu, dt)
    x = jnp.log1p(jnp.clip(m0, 0.0, M_MAX))
    i, t = _cell(x, table.x_lo, table.dx, table.nx)
    D = jnp.asarray(table.D_pad, dt)
    rows = jax.lax.dynamic_slice_in_dim(D, i, 4, axis=0)  # (4, nv + 3)
    row = jnp.stack(_cr_weights(t)) @ rows  # (nv + 3,)
    v = warp_mu(jnp.clip(mu, 0.0, 1.0))
    j, s = _cell(v, table.v_lo, table.dv, table.nv)
    return _cr_eval(_cr_cubics(row, table.nv), j, s)


def deficit_avg(table: AlbedoTable, m: ArrayLike) -> Array:
    """Interpolated ``D_avg(m) = 1 - E_avg(m) = 2 int_0^1 D(m, mu) mu dmu`` (the exact
    integral of the 2-D interpolant, see the module docstring)."""
    m = jnp.asarray(m, float_dtype(m))
    x = jnp.log1p(jnp.clip(m, 0.0, M_MAX))
    i, t = _cell(x, table.x_lo, table.dx, table.nx)
    Da = jnp.asarray(table.D_avg_pad, m.dtype)
    w = _cr_weights(t)
    return sum(w[a] * Da[i + a] for a in range(4))


def albedo(table: AlbedoTable, m: ArrayLike, mu: ArrayLike) -> Array:
    """Interpolated white-surface directional albedo ``E(m, mu) = 1 - D(m, mu)``."""
    return 1.0 - deficit(table, m, mu)


def albedo_avg(table: AlbedoTable, m: ArrayLike) -> Array:
    """Interpolated ``E_avg(m) = 2 int_0^1 E(m, mu) mu dmu``."""
    return 1.0 - deficit_avg(table, m)


# ---------------------------------------------------------------------------------------
# quadrature of the directional albedo (offline tables, tests, benchmarks)


def _gl(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]


def albedo_nodes(m: ArrayLike, mu: ArrayLike, n_phi: int = 24, n_w: int = 12):
    """Quadrature nodes for ``E(m, mu)``: outgoing directions and weights.

    Returns ``(k_in, k_out, weights)`` with the normal ``+z``, ``k_in`` in the x-z plane,
    shapes ``(..., 3)``, ``(..., Q, 3)`` and ``(..., Q)`` where ``...`` is the broadcast shape
    of ``m`` and ``mu`` and ``Q = 2 n_phi * 8 n_w``. Then
    ``E ~= sum_q weights_q * f00(k_in, k_out_q)`` where ``weights`` include ``k'.n`` and the
    Jacobian ``d omega_out = 4 (k.h) cos theta_h dw dphi / (m + 1)``. Float64 NumPy.
    """
    m = np.asarray(m, np.float64)
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    m, mu = np.broadcast_arrays(m, mu)
    sin_k = np.sqrt((1.0 - mu) * (1.0 + mu))
    # phi panels [0, pi/2], [pi/2, pi]
    px, pw = _gl(n_phi)
    phi = np.concatenate([px * (np.pi / 2), np.pi / 2 + px * (np.pi / 2)])
    wphi = np.concatenate([pw, pw]) * (np.pi / 2) * 2.0  # x2: phi in [-pi, 0] by symmetry
    cphi, sphi = np.cos(phi), np.sin(phi)
    mm = m[..., None]
    A = mu[..., None] * np.ones_like(phi)
    B = sin_k[..., None] * cphi
    beta = np.arctan2(B, A)  # (..., P)
    theta_b = 0.5 * beta + 0.25 * np.pi
    # w = -(m+1) log cos theta ; cos(theta_b) can be 0 at grazing
    cb = np.cos(theta_b)
    with np.errstate(divide="ignore"):
        w_b = np.where(cb > 1e-300, -(mm + 1.0) * np.log(np.maximum(cb, 1e-300)), np.inf)
    W = np.minimum(w_b, W_MAX)
    w_k = np.where(beta > 0, -(mm + 1.0) * np.log(np.maximum(np.cos(beta), 1e-300)), 0.0)
    static = np.minimum(W[..., None], np.array(_W_BREAKS))
    dyn = np.stack([np.zeros_like(W), np.clip(w_k, 0.0, W), W], axis=-1)
    bk = np.sort(np.concatenate([dyn, static], axis=-1), axis=-1)  # (..., P, nb)
    lo, hi = bk[..., :-1], bk[..., 1:]  # (..., P, nb-1)
    gx, gw = _gl(n_w)
    w = lo[..., None] + (hi - lo)[..., None] * gx  # (..., P, nb-1, n_w)
    ww = (hi - lo)[..., None] * gw
    shp = w.shape
    w = w.reshape(shp[:-3] + (shp[-3], -1))  # (..., P, Qw)
    ww = ww.reshape(w.shape)
    cos_t = np.exp(-w / (mm[..., None] + 1.0))
    one_minus = -np.expm1(-w / (mm[..., None] + 1.0))
    sin_t = np.sqrt(one_minus * (1.0 + cos_t))
    h = np.stack(
        [sin_t * cphi[:, None], sin_t * sphi[:, None], cos_t], axis=-1
    )  # (..., P, Qw, 3)
    k_in = np.stack([sin_k, np.zeros_like(mu), mu], axis=-1)
    kh = np.sum(h * k_in[..., None, None, :], axis=-1)
    k_out = 2.0 * kh[..., None] * h - k_in[..., None, None, :]
    k_out = k_out / np.linalg.norm(k_out, axis=-1, keepdims=True)
    mu_out = np.clip(k_out[..., 2], 0.0, 1.0)
    # E = int f00 mu' d omega_out,  d omega_out = 4 (k.h) d omega_h,
    # d omega_h = cos theta_h dw dphi / (m + 1)  (phi over the full circle: wphi has the x2)
    wt = (wphi[:, None] * ww) * 4.0 * kh * cos_t / (mm[..., None] + 1.0) * mu_out
    Q = k_out.shape[-3] * k_out.shape[-2]
    k_out = k_out.reshape(k_out.shape[:-3] + (Q, 3))
    wt = wt.reshape(wt.shape[:-2] + (Q,))
    return k_in, k_out, wt


def directional_albedo(
    f00: Callable[[Array, Array, Array], Array],
    m: ArrayLike,
    mu: ArrayLike,
    n_phi: int = 24,
    n_w: int = 12,
) -> np.ndarray:
    """``E(m, mu) = int f00(k, k') (k'.n) d omega'`` by the half-vector quadrature above.

    ``f00(k_in, k_out, m)`` evaluates the scalar BRDF (e.g. the M00 of
    :func:`ppr.mueller_brdf` for :meth:`ppr.Material.ideal_white`) with broadcasting;
    ``m`` and ``mu`` broadcast against each other.
    """
    k_in, k_out, wt = albedo_nodes(m, mu, n_phi, n_w)
    m_b = np.broadcast_to(np.asarray(m, np.float64), k_in.shape[:-1])
    vals = f00(
        jnp.asarray(k_in[..., None, :]),
        jnp.asarray(k_out),
        jnp.asarray(m_b[..., None]),
    )
    return np.sum(np.asarray(vals) * wt, axis=-1)
