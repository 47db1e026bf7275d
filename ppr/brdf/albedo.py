r"""White-surface energy deficit ``D(m, cos theta)`` of the BRDF's explicit terms: tables.

The multiple-scattering remainder (:func:`ppr.brdf._brdf.multiple_scattering_term`,
docs/physics/multiple_scattering.md) needs, for the ideal white surface (``F == 1``,
:meth:`ppr.Material.ideal_white`), the fraction of the incident flux that the *explicit* terms
(single + double) do not return,

    D(m, mu) = 1 - E(m, mu),   mu = k.n,
    E = integral over the outgoing hemisphere of f_explicit,00 (k'.n) d omega',

and its cosine-weighted hemispherical average ``D_avg(m) = 2 int_0^1 D(m, mu) mu d mu``.

Tables
    One ``.npz`` table per set of explicit terms in ``ppr/data/albedo_<terms>.npz``
    (``albedo_single.npz``, ``albedo_double_single.npz``), written by
    ``scripts/make_albedo_tables.py`` and loaded once, lazily, as small NumPy constants. The
    node values are computed as a *positive* integral (the probability that light is still
    inside the surface after one or two facets, scripts/deficit_reference.py), never as
    ``1 - E``: ``D`` spans 300 decades (1e-3 at grazing incidence on a glossy surface, 1e-18 at
    60 deg for m = 1000, below 1e-300 at normal incidence for m = 1e4), and a difference of two
    numbers near 1 would leave only rounding and quadrature noise in its tail.

    Stored: ``L = log D`` (floored at ``LOG_FLOOR``, D = 1e-300) on a grid uniform in
    ``x = log(1 + m)`` (``0 <= m <= 1e6``) and in the warped cosine
    ``v = log(mu + MU0) + ALPHA mu`` (``0 <= mu <= 1``). The log part of ``v`` resolves the
    grazing band ``mu ~ 1/sqrt(m)`` at every roughness with the same nodes (``D`` depends on
    ``mu sqrt(m)`` there); the linear part keeps nodes near normal incidence for small m.
    Interpolant: tensor-product Catmull-Rom (cubic convolution; C1, third order) of ``L`` with
    ghost nodes from quadratic extrapolation, then ``D = exp(L)``: positive by construction,
    smooth and differentiable in ``m`` and ``mu``, with the relative precision of ``L`` (an
    interpolant of ``D`` itself rings around its steep rise toward grazing and went negative,
    which the remainder clamped to exact zeros). ``log D_avg`` is tabulated on an x grid
    ``AVG_REFINE`` times finer, each node the integral of the 2-D interpolant at that ``m``
    (8-point Gauss-Legendre per v cell), and interpolated by Catmull-Rom: the remainder built
    from the *interpolated* ``D`` conserves energy up to that 1-D interpolation
    (tests/test_furnace.py), independently of the table's own error.

Quadrature of the BRDF (:func:`directional_albedo`, tests and benchmarks)
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
    "deficit_one_material",
    "log_deficit",
    "log_deficit_avg",
    "log_deficit_one_material",
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
LOG_FLOOR = float(np.log(1e-300))
"""Floor of the stored ``log D`` (D = 1e-300: the remainder is exactly 0 in either dtype)."""
AVG_REFINE = 8
"""The ``log D_avg`` grid is this many times finer in x than the deficit grid."""
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
    """Deficit table of one set of explicit terms (NumPy constants, float64).

    ``L_pad`` is ``(nx + 2, nv + 2)``: ``log D`` at the ``nx x nv`` nodes with one ghost node on
    each side (node ``i`` at ``x = x_lo + i dx``, ``j`` at ``v = v_lo + j dv``). ``La_pad`` is
    ``(nxa + 2,)``: ``log D_avg`` on the finer grid ``x = x_lo + i dxa`` with its ghosts.
    """

    terms: tuple[str, ...]
    x_lo: float
    dx: float
    nx: int
    v_lo: float
    dv: float
    nv: int
    L_pad: np.ndarray
    dxa: float
    nxa: int
    La_pad: np.ndarray
    info: str = ""
    Lm_pad: np.ndarray | None = None
    """``log`` of the model's deficit (before the closure of scripts/make_albedo_tables.py),
    padded like ``L_pad``; for tests and documentation, not used by the BRDF."""

    @property
    def L(self) -> np.ndarray:
        """Node values of ``log D``."""
        return self.L_pad[1:-1, 1:-1]

    @property
    def D(self) -> np.ndarray:
        """Node values of the deficit ``D = 1 - E``."""
        return np.exp(self.L)

    @property
    def D_avg(self) -> np.ndarray:
        """``D_avg`` at the nodes of the fine x grid (:attr:`xa_nodes`)."""
        return np.exp(self.La_pad[1:-1])

    @property
    def x_nodes(self) -> np.ndarray:
        return self.x_lo + self.dx * np.arange(self.nx)

    @property
    def xa_nodes(self) -> np.ndarray:
        return self.x_lo + self.dxa * np.arange(self.nxa)

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


def clamp_in(v, lo, hi):
    """``v`` clamped to ``[lo, hi]`` with derivative 1 on the closed interval: at a bound
    (``m = 0``, the first node of a table) the one-sided derivative into the domain.
    ``jnp.clip`` splits a tie's gradient in half (``d max(v, lo) / dv = 1/2`` at ``v = lo``),
    which halved ``d/dm`` of every tabulated term at ``m = 0``."""
    return jnp.where(v < lo, lo, jnp.where(v > hi, hi, v))


def _cell(coord, lo, step, n):
    """Cell index in [0, n-2] and local coordinate t in [0, 1] (clamped at the ends)."""
    s = clamp_in((coord - lo) / step, 0.0, n - 1.0)
    i = jnp.clip(jnp.floor(s), 0, n - 2)
    return i.astype(jnp.int32), s - i


def _interp_1d_np_row(vals_pad: np.ndarray, v_lo: float, dv: float, nv: int, v: np.ndarray):
    """NumPy Catmull-Rom along the last axis of a padded row (offline E_avg quadrature)."""
    s = np.clip((v - v_lo) / dv, 0.0, nv - 1.0)
    i = np.clip(np.floor(s), 0, nv - 2).astype(int)
    t = s - i
    w = _cr_weights(t, np)
    return sum(w[a] * vals_pad[..., i + a] for a in range(4))


def _log_avg_at_x(L_pad, x_lo, dx, nx, v, xq):
    """``log D_avg`` of the 2-D interpolant at the x values ``xq`` (NumPy, float64): the
    Catmull-Rom row in x, then ``2 int_0^1 exp(L(v)) mu dmu`` by 8-point Gauss-Legendre per
    v cell (``dmu/dv`` from the exact inverse warp)."""
    nv = len(v)
    dv = v[1] - v[0]
    s = np.clip((np.asarray(xq) - x_lo) / dx, 0.0, nx - 1.0)
    i = np.clip(np.floor(s), 0, nx - 2).astype(int)
    w = _cr_weights(s - i, np)
    rows = sum(w[a][:, None] * L_pad[i + a] for a in range(4))  # (nq, nv + 2)
    gx, gw = np.polynomial.legendre.leggauss(8)
    vq = (v[:-1, None] + 0.5 * dv * (gx[None, :] + 1.0)).ravel()
    wq = np.broadcast_to(0.5 * dv * gw[None, :], (nv - 1, 8)).ravel()
    muq = unwarp_v(vq)
    dmu_dv = 1.0 / (1.0 / (muq + MU0) + ALPHA)
    Lq = _interp_1d_np_row(rows, v[0], dv, nv, vq)  # (nq, nvq)
    wmu = 2.0 * muq * dmu_dv * wq
    top = np.max(Lq, axis=-1, keepdims=True)
    return top[:, 0] + np.log(np.sum(np.exp(Lq - top) * wmu[None, :], axis=-1))


def _log_pad(D_nodes) -> np.ndarray:
    with np.errstate(divide="ignore"):
        L = np.maximum(np.log(np.maximum(np.asarray(D_nodes, np.float64), 0.0)), LOG_FLOOR)
    return _pad_quadratic(_pad_quadratic(L, 0), 1)


def build_table(
    terms, D_nodes: np.ndarray, info: str = "", D_model: np.ndarray | None = None
) -> AlbedoTable:
    """Table from deficit node values ``D_nodes`` (positive; floored at ``exp(LOG_FLOOR)``)
    of shape ``(nx, nv)`` on :func:`grid_nodes`: ``log D`` with quadratic ghosts, and
    ``log D_avg`` of the 2-D interpolant on the x grid refined ``AVG_REFINE`` times.
    ``D_model``: the model's deficit, kept for reference (:attr:`AlbedoTable.Lm_pad`)."""
    D_nodes = np.asarray(D_nodes, np.float64)
    nx, nv = D_nodes.shape
    x, v, _, _ = grid_nodes(nx, nv)
    L_pad = _log_pad(D_nodes)
    nxa = AVG_REFINE * (nx - 1) + 1
    dxa = (x[-1] - x[0]) / (nxa - 1)
    xa = x[0] + dxa * np.arange(nxa)
    La = _log_avg_at_x(L_pad, x[0], x[1] - x[0], nx, v, xa)
    return AlbedoTable(
        terms=tuple(sorted(terms)),
        x_lo=float(x[0]),
        dx=float(x[1] - x[0]),
        nx=nx,
        v_lo=float(v[0]),
        dv=float(v[1] - v[0]),
        nv=nv,
        L_pad=L_pad,
        dxa=float(dxa),
        nxa=nxa,
        La_pad=_pad_quadratic(La, 0),
        info=info,
        Lm_pad=None if D_model is None else _log_pad(D_model),
    )


def table_path(terms) -> str:
    return os.path.join(DATA_DIR, "albedo_" + "_".join(sorted(terms)) + ".npz")


_FORMAT = "log-deficit-1"


def save_table(table: AlbedoTable, path: str | None = None) -> str:
    path = table_path(table.terms) if path is None else path
    os.makedirs(os.path.dirname(path), exist_ok=True)
    np.savez(
        path,
        format=np.array(_FORMAT),
        terms=np.array(table.terms),
        grid=np.array(
            [
                table.x_lo,
                table.dx,
                table.nx,
                table.v_lo,
                table.dv,
                table.nv,
                MU0,
                ALPHA,
                table.dxa,
                table.nxa,
            ]
        ),
        L_pad=table.L_pad,
        La_pad=table.La_pad,
        Lm_pad=table.L_pad if table.Lm_pad is None else table.Lm_pad,
        info=np.array(table.info),
    )
    load_table.cache_clear()
    return path


@functools.cache
def load_table(terms: tuple[str, ...]) -> AlbedoTable:
    """The table for the explicit terms ``terms`` (loaded once; NumPy constants)."""
    path = table_path(terms)
    rebuild = "run: python scripts/make_albedo_tables.py (builds both tables)"
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"no albedo table for explicit terms {tuple(sorted(terms))!r} at {path}; {rebuild}"
        )
    with np.load(path) as z:
        fmt = str(z["format"]) if "format" in z.files else "deficit-0"
        if fmt != _FORMAT:
            raise ValueError(f"albedo table {path} has format {fmt!r}, not {_FORMAT!r}; {rebuild}")
        x_lo, dx, nx, v_lo, dv, nv, mu0, alpha, dxa, nxa = (float(g) for g in z["grid"])
        if mu0 != MU0 or alpha != ALPHA:
            raise ValueError(f"albedo table {path} was built with another warp; {rebuild}")
        return AlbedoTable(
            terms=tuple(str(t) for t in z["terms"]),
            x_lo=x_lo,
            dx=dx,
            nx=int(nx),
            v_lo=v_lo,
            dv=dv,
            nv=int(nv),
            L_pad=np.array(z["L_pad"]),
            dxa=dxa,
            nxa=int(nxa),
            La_pad=np.array(z["La_pad"]),
            info=str(z["info"]),
            Lm_pad=np.array(z["Lm_pad"]),
        )


def log_deficit(table: AlbedoTable, m: ArrayLike, mu: ArrayLike) -> Array:
    """Interpolated ``log D(m, mu)`` (broadcasts; dtype of the inputs; ``m`` clamped to
    [0, 1e6], ``mu`` to [0, 1]). Smooth (C1) and differentiable in ``m`` and ``mu``."""
    dt = float_dtype(m, mu)
    m = jnp.asarray(m, dt)
    mu = jnp.asarray(mu, dt)
    m, mu = jnp.broadcast_arrays(m, mu)
    return interpolate_nodes(table, table.L_pad, m, mu)


def interpolate_nodes(table: AlbedoTable, nodes_pad: ArrayLike, m: Array, mu: Array) -> Array:
    """Catmull-Rom interpolation of padded node values ``nodes_pad`` (the shape of
    ``table.L_pad``) on ``table``'s (log1p m, warped mu) grid at broadcast ``m``, ``mu``."""
    dt = mu.dtype
    x = jnp.log1p(clamp_in(m, 0.0, M_MAX))
    v = warp_mu(jnp.clip(mu, 0.0, 1.0))
    i, t = _cell(x, table.x_lo, table.dx, table.nx)
    j, s = _cell(v, table.v_lo, table.dv, table.nv)
    P = jnp.asarray(nodes_pad, dt)
    wx = _cr_weights(t)
    wv = _cr_weights(s)
    out = jnp.zeros(mu.shape, dt)
    for a in range(4):
        row = jnp.zeros(mu.shape, dt)
        for b in range(4):
            row = row + wv[b] * P[i + a, j + b]
        out = out + wx[a] * row
    return out


def deficit(table: AlbedoTable, m: ArrayLike, mu: ArrayLike) -> Array:
    """Interpolated deficit ``D(m, mu) = 1 - E(m, mu) = exp(log_deficit)``: positive,
    smooth and differentiable in ``m`` and ``mu``."""
    return jnp.exp(log_deficit(table, m, mu))


def log_deficit_one_material(table: AlbedoTable, m0: ArrayLike, mu: ArrayLike) -> Array:
    """:func:`log_deficit` for one ``m`` shared by the batch (scalar ``m0``): the Catmull-Rom
    step in ``m`` is done once on the table (a ``(nv + 3,)`` row, by a dot so that XLA CPU
    stores it rather than re-computing it per element), leaving a 4-point interpolation in
    ``mu`` per element. Equal to :func:`log_deficit` up to rounding (same interpolant, summed
    in the other order; tests/test_furnace.py)."""
    dt = float_dtype(m0, mu)
    m0 = jnp.asarray(m0, dt)
    mu = jnp.asarray(mu, dt)
    x = jnp.log1p(clamp_in(m0, 0.0, M_MAX))
    i, t = _cell(x, table.x_lo, table.dx, table.nx)
    L = jnp.asarray(table.L_pad, dt)
    rows = jax.lax.dynamic_slice_in_dim(L, i, 4, axis=0)  # (4, nv + 3)
    row = jnp.stack(_cr_weights(t)) @ rows  # (nv + 3,)
    v = warp_mu(jnp.clip(mu, 0.0, 1.0))
    j, s = _cell(v, table.v_lo, table.dv, table.nv)
    return _cr_eval(_cr_cubics(row, table.nv), j, s)


def deficit_one_material(table: AlbedoTable, m0: ArrayLike, mu: ArrayLike) -> Array:
    """``exp`` of :func:`log_deficit_one_material`."""
    return jnp.exp(log_deficit_one_material(table, m0, mu))


def log_deficit_avg(table: AlbedoTable, m: ArrayLike) -> Array:
    """Interpolated ``log D_avg(m)``, ``D_avg = 2 int_0^1 D(m, mu) mu dmu`` of the 2-D
    interpolant (exact at the fine x nodes, Catmull-Rom between them)."""
    m = jnp.asarray(m, float_dtype(m))
    x = jnp.log1p(clamp_in(m, 0.0, M_MAX))
    i, t = _cell(x, table.x_lo, table.dxa, table.nxa)
    La = jnp.asarray(table.La_pad, m.dtype)
    w = _cr_weights(t)
    return sum(w[a] * La[i + a] for a in range(4))


def deficit_avg(table: AlbedoTable, m: ArrayLike) -> Array:
    """Interpolated ``D_avg(m) = 1 - E_avg(m)``."""
    return jnp.exp(log_deficit_avg(table, m))


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
    h = np.stack([sin_t * cphi[:, None], sin_t * sphi[:, None], cos_t], axis=-1)  # (..., P, Qw, 3)
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
