r"""Double-bounce term near exact backscatter from material-independent tables.

PPR sensors are monostatic up to the velocity aberration (tens of microradians), and every
facet of a mesh is then seen at exact backscatter ``k' = k``. There the double term of
:mod:`ppr.brdf.double` has a structure that removes its quadrature from the per-evaluation cost:

1. Every double path is coplanar (``h1 . h2 = 0``, paper eq. 14) and ``k = cos t1 h1 +
   cos t2 h2``, so ``t2 = pi/2 - t1``: the path's Jones matrix, in its own s/p frame, is
   ``diag(a, b)`` with ``a = r_s(t1) r_s(pi/2 - t1)``, ``b = r_p(t1) r_p(pi/2 - t1)``; the
   material enters only through the angle ``t1`` of the first facet.
2. In the shared beam frame ``e``, ``J = a J_s + b J_p`` with real 2x2 matrices ``J_s``,
   ``J_p`` fixed by the geometry (obtained from :func:`ppr.brdf.double._path_jones` with the
   probes ``(r_s, r_p) = (1, 0), (0, 1)``), so the path's coherency is
   ``|a|^2 U_ss + |b|^2 U_pp + Re(a b*) U_re + Im(a b*) U_im`` with geometric ``U``.
3. The four products ``g(t) = (|a|^2, |b|^2, Re a b*, Im a b*)`` are smooth in ``t`` on
   ``[0, pi/2]``; with the Lagrange basis ``l_j`` of ``K`` Chebyshev-Lobatto nodes ``t_j``,
   ``g(t) ~= sum_j g(t_j) l_j(t)``. Hence

       M_inc(c, m; n) = sum_{q, j} g_q(t_j; n) Z_{q j}(c, m),
       Z_{q j} = <prefactor> sum_paths w l_j(t1) (G_inc U_q)       (4x4 each),

   ``Z`` independent of the material. Stacked over grid points and nodes, its rows (4
   products ``q`` x 16 Mueller elements) have a small numerical rank ``R`` (singular values
   above ``RANK_TOL`` of the largest, measured at build time): ``R = 6`` in the shipped
   table, three dominant singular values and three at 4e-6 to 9e-5 of the largest (the
   table's ``info`` lists them). So ``Z_{q j} = sum_r T_{j r}(c, m) V_{r q}`` with constant
   ``V`` (``R`` sets of four 4x4 matrices): the table stores ``T`` (``K x R`` per grid
   point).
4. At exact backscatter the reversed path's Jones matrix equals the forward one, so the
   coherent part is exactly ``2 M_inc`` (tested) and ``M = (1 + gamma(psi)) M_inc``.

Error of the Fresnel interpolation (``K = K_NODES = 16``; max over t of ``|g - interp|``,
``|g| <= 1``; tests/test_double_table.py::test_fresnel_node_interpolation): 1.9e-3 for
aluminium at 532 nm (``n = 0.94 + 6.42i``, the hardest library material: its
pseudo-Brewster dip is narrow), 1.2e-5 for gold, 7e-6 for TiO2, 4e-8 for silica; after the
average over paths it is below the grid's interpolation error (K = 20 gave the same table
error, K = 12 1.7x larger).

Grid: ``x = asinh(TAU tan theta)`` (``TAU = 2``; ``x ~ 2 theta`` at normal incidence, where
the term has a cusp ``|theta|``: the shadow boundary separates from the hemisphere's edge;
at m = 0.03 the converged M00 drops linearly, 3.7e-3 relative per 2 deg; and ``x ~ log(4 /
c)`` near grazing, where the term is a power of ``c``) on ``[0, X_MAX]`` (84 nodes), and
``u = sqrt(m + 1) - 1`` (analytic at ``m = 0``; ``log E ~ -kappa m`` is quadratic in ``u``,
reproduced exactly by cubic convolution) on ``[0, U_MAX]`` (100 nodes). Stored: ``log E``
(``E`` the white M00 of the double term, a positive envelope spanning 300 decades over the
grid) and ``T / E``, interpolated by tensor-product Catmull-Rom (:mod:`ppr.brdf.albedo`'s
kernel). Beyond ``X_MAX`` (``c < C_MIN = 1e-3``) ``log E`` continues linearly in ``x`` (a
power law in ``c``) and ``T / E`` is held. Above ``M_MAX = 200`` the term is 0: at ``m =
M_MAX`` the double term at backscatter is below 1e-30 of the rest of the BRDF at incidence
0-85 deg (tests/test_double_table.py::test_cut_above_m_max_is_negligible).

Accuracy against the quadrature at order (32, 128), as ``|M - M_ref| / M00(single +
double)`` on random geometries (incidence 0-88 deg, m 0.02-150, aluminium, gold, TiO2,
silica) at exact backscatter and up to ``psi = PSI_MAX``, next to the default quadrature's:
measured by bench/bench_double_table.py, table in bench/results/double_table.md; the bounds
asserted are in tests/test_double_table.py.

The table is built by ``scripts/double_backscatter_table.py`` from the quadrature of
:mod:`ppr.brdf.double` at a high order (``BUILD_ORDER``); its error against that quadrature at a
still higher order, off the grid nodes, is measured in tests/test_double_table.py and
bench/bench_double.py.
"""

from __future__ import annotations

import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from .._safe import tiny
from .._types import Array, ArrayLike, Float
from ..optics._frames import (
    _cross3,
    _default_frame3,
    _dot3,
    _neg3,
    _perp3_any,
    _split,
    rotate_mueller_44,
    store,
)
from ..optics._fresnel import fresnel_amplitudes_re
from ..optics.conventions import DEFAULT_WAVELENGTH_M
from . import double as D
from ._microfacet import mean_cosine_plus
from .albedo import _cell, _cr_cubics, _cr_eval, _cr_weights, _pad_quadratic

__all__ = [
    "K_NODES",
    "M_MAX",
    "PSI_MAX",
    "backscatter_moments",
    "build_table",
    "double_backscatter_term",
    "double_bounce_term_auto",
    "double_term_dispatch",
    "load_table",
    "near_backscatter",
]

K_NODES: int = 16
"""Chebyshev-Lobatto nodes in the first facet's angle ``t1`` (module docstring, step 3)."""

TAU: float = 2.0
"""Scale of the incidence variable ``x = asinh(TAU tan theta)``."""

C_MIN: float = 1e-3
"""Grid end in ``c``: incidence 89.94 deg; beyond, ``log E`` continues linearly in ``x``."""

X_MAX: float = math.asinh(TAU * math.sqrt(1.0 - C_MIN**2) / C_MIN)

M_MAX: float = 200.0
"""Largest tabulated Blinn-Phong exponent; above it the backscatter double term is 0."""

M_SHIFT: float = 1.0
"""Roughness variable ``u = sqrt(m + M_SHIFT) - sqrt(M_SHIFT)``."""

U_MAX: float = math.sqrt(M_MAX + M_SHIFT) - math.sqrt(M_SHIFT)

BUILD_ORDER: tuple[int, int] = (24, 96)
"""Quadrature order ``(n_u, n_phi)`` of :mod:`ppr.brdf.double` used to build the table."""

LOG_FLOOR: float = -700.0
"""``log E`` is clipped below at this value (``exp`` of it is 0 in float32 and subnormal in
float64); ``T / E`` is 0 where ``E`` underflowed."""

RANK_TOL: float = 1e-9
"""Singular values of the stacked ``Z`` below ``RANK_TOL`` times the largest are dropped."""

ONE_MATERIAL_MIN_BATCH: int = 96
"""Smallest batch for which one shared material takes the contracted-rows path
(:func:`_interp_one_material`, a fixed cost of contracting all the table's rows); smaller
batches gather their own rows. Measured crossover between 64 and 128 elements under ``vmap``
over 12 materials (an MCMC half-ensemble; bench/results/double_table.md, "small
batches"), where the contraction made the log-probability 2x slower."""

PSI_MAX: float = 1e-3
"""Largest bistatic angle (rad) at which ``mueller_brdf`` uses the table for the double
term (its dependence on ``psi`` through ``gamma(psi)`` is kept; the rest is taken at
``psi = 0``, which adds 2.5e-4 of M00 at ``psi = PSI_MAX``, measured:
tests/test_double_table.py::test_table_matches_quadrature_near_backscatter)."""

_DATA = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data")
TABLE_FILE = os.path.join(_DATA, "double_backscatter.npz")


# --------------------------------------------------------------------------------------------
# the Lagrange basis in t1 and the material's node values


@functools.cache
def lobatto(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chebyshev-Lobatto nodes ``x_j`` on [-1, 1], angles ``t_j = (x_j + 1) pi/4`` in
    [0, pi/2] and the barycentric weights."""
    x = np.cos(np.pi * np.arange(k) / (k - 1))
    t = (x + 1.0) * np.pi / 4.0
    w = np.ones(k)
    w[0] = w[-1] = 0.5
    w *= (-1.0) ** np.arange(k)
    return x, t, w


def angle_basis(t: Array, k: int) -> Array:
    """Lagrange basis ``l_j(t)``, ``(..., k)``, of the nodes :func:`lobatto` (barycentric
    form, exact 0/1 at the nodes)."""
    x, _, w = lobatto(k)
    dt = t.dtype
    xx = 4.0 * t / math.pi - 1.0
    d = xx[..., None] - jnp.asarray(x, dt)
    at = jnp.abs(d) < 1e-12
    lam = jnp.asarray(w, dt) / jnp.where(at, 1.0, d)
    lam = lam / jnp.sum(lam, axis=-1, keepdims=True)
    return jnp.where(jnp.any(at, axis=-1, keepdims=True), at.astype(dt), lam)


def node_products(
    n_re: Array, n_im: Array, k: int, *, white: bool = False, films=None
) -> Array:
    """``g_q(t_j)`` for ``q`` in (``|a|^2``, ``|b|^2``, ``Re a b*``, ``Im a b*``): ``(..., 4,
    k)``. ``white``: the ideal white facet (``r_s = -1``, ``r_p = 1``: ``a = b = 1``).
    ``films`` (:class:`ppr.optics._films.Films` broadcast like ``n_re``): coated facets, whose
    products are those of the facets' second moments (independent facets:
    ``<|a|^2> = G_ss(t) G_ss(pi/2 - t)``, ``<a b*> = G_sp(t) G_sp(pi/2 - t)``), exact for the
    coherent and the averaged thick-film facets alike."""
    dt = n_re.dtype
    if white:
        g = np.zeros((4, k))
        g[:3] = 1.0
        return jnp.broadcast_to(jnp.asarray(g, dt), n_re.shape + (4, k))
    _, t, _ = lobatto(k)
    c = jnp.asarray(np.cos(t), dt)
    ex = lambda a: a[..., None]  # noqa: E731
    if films is not None:
        from ..optics._films import facet_gram  # noqa: PLC0415

        leaves = jax.tree.leaves(films)
        shape = jnp.broadcast_shapes(n_re.shape, *(jnp.shape(a) for a in leaves))
        fx = jax.tree.map(lambda a: ex(jnp.broadcast_to(a, shape)), films)
        nb = [ex(jnp.broadcast_to(a, shape)) for a in (n_re, n_im)]
        gss, gpp, gr, gi = facet_gram(nb[0], nb[1], c, fx)
        rev = lambda a: a[..., ::-1]  # noqa: E731
        sp_re = gr * rev(gr) - gi * rev(gi)
        sp_im = gr * rev(gi) + gi * rev(gr)
        return jnp.stack([gss * rev(gss), gpp * rev(gpp), sp_re, sp_im], axis=-2)
    rs_r, rs_i, rp_r, rp_i = fresnel_amplitudes_re(ex(n_re), ex(n_im), c)
    # the complementary angle pi/2 - t_j is the node k-1-j (symmetric nodes)
    rev = lambda a: a[..., ::-1]  # noqa: E731
    a_r = rs_r * rev(rs_r) - rs_i * rev(rs_i)
    a_i = rs_r * rev(rs_i) + rs_i * rev(rs_r)
    b_r = rp_r * rev(rp_r) - rp_i * rev(rp_i)
    b_i = rp_r * rev(rp_i) + rp_i * rev(rp_r)
    return jnp.stack(
        [
            a_r * a_r + a_i * a_i,
            b_r * b_r + b_i * b_i,
            a_r * b_r + a_i * b_i,
            a_i * b_r - a_r * b_i,
        ],
        axis=-2,
    )


# --------------------------------------------------------------------------------------------
# building the table (float64)


def _pack(s: list, p: list) -> list[Array]:
    """16 coherency reals (``ppr.brdf.double`` layout) of ``U_ss, U_pp, U_re, U_im``."""
    z = jnp.zeros_like(s[0])
    pairs = D._PAIRS
    u_ss = [s[a] * s[a] for a in range(4)] + [s[a] * s[b] for a, b in pairs] + [z] * 6
    u_pp = [p[a] * p[a] for a in range(4)] + [p[a] * p[b] for a, b in pairs] + [z] * 6
    u_re = [2.0 * s[a] * p[a] for a in range(4)]
    u_re += [s[a] * p[b] + p[a] * s[b] for a, b in pairs] + [z] * 6
    u_im = [z] * 10 + [s[a] * p[b] - p[a] * s[b] for a, b in pairs]
    return [jnp.stack(u, axis=-1) for u in (u_ss, u_pp, u_re, u_im)]


@functools.partial(jax.jit, static_argnames=("order", "k"))
def backscatter_moments(
    c: Float[Array, " G"], m: Float[Array, " G"], *, order: tuple[int, int], k: int
) -> Float[Array, "G 4 k 16"]:
    """``Z_{q j}(c, m)`` (module docstring, step 3): row-major e-frame Mueller matrices of the
    incoherent double term at exact backscatter, per Fresnel product ``q`` and node ``j``,
    with the prefactor ``<h.n> / <h.k>+^2``. ``k = (sin, 0, cos)``, ``n = z``,
    ``e = normalize(n x k)`` (:func:`ppr.brdf.double._common_frame`)."""
    s = jnp.sqrt(jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0))
    z = jnp.zeros_like(c)
    kv = jnp.stack([s, z, c], axis=-1)
    nv = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], c.dtype), kv.shape)
    e = D._common_frame(kv, kv, nv, c.dtype)
    coef = D._mcp_interpolant(m, D.INNER_ORDER)
    g_inc = jnp.asarray(D._linear_maps()[0], c.dtype)
    out = 0.0
    for reverse in (False, True):
        kw = dict(reverse=reverse, order=order, coef=coef, white=False)
        w, js, c1 = D._half_paths(kv, kv, nv, e, m, z, z, probe="s", **kw)
        _, jp, _ = D._half_paths(kv, kv, nv, e, m, z, z, probe="p", **kw)
        t1 = jnp.arccos(jnp.clip(c1, 0.0, 1.0))
        wl = w[..., None] * angle_basis(t1, k)  # (G, N, k)
        us = _pack([js[a][0] for a in range(4)], [jp[a][0] for a in range(4)])
        out = out + jnp.stack([jnp.einsum("gnk,gnq->gkq", wl, u) for u in us], axis=1)
    hn = (m + 1.0) / (m + 2.0)
    pref = hn / mean_cosine_plus(m, c, order=128) ** 2
    return pref[:, None, None, None] * (out @ g_inc.T)


def grid(nx: int, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """Node coordinates ``x`` (``nx``) and ``u`` (``nu``)."""
    return np.linspace(0.0, X_MAX, nx), np.linspace(0.0, U_MAX, nu)


def build_table(
    nx: int = 84,
    nu: int = 100,
    *,
    order: tuple[int, int] = BUILD_ORDER,
    k: int = K_NODES,
    chunk: int = 32,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Compute the table (float64; minutes at the defaults on 2 cores). Returns the arrays
    that :func:`save_table` writes."""
    from tqdm.auto import tqdm  # noqa: PLC0415

    jax.config.update("jax_enable_x64", True)
    xs, us = grid(nx, nu)
    X, U = np.meshgrid(xs, us, indexing="ij")
    c = 1.0 / np.sqrt(1.0 + (np.sinh(X.ravel()) / TAU) ** 2)
    m = (U.ravel() + math.sqrt(M_SHIFT)) ** 2 - M_SHIFT
    m[U.ravel() == 0.0] = 0.0
    n = c.size
    pad = (-n) % chunk
    cp = np.concatenate([c, np.full(pad, c[-1])])
    mp = np.concatenate([m, np.full(pad, m[-1])])
    zs = []
    for a in tqdm(range(0, n + pad, chunk), desc="double backscatter table", disable=not progress):
        zs.append(
            np.asarray(
                backscatter_moments(
                    jnp.asarray(cp[a : a + chunk]),
                    jnp.asarray(mp[a : a + chunk]),
                    order=order,
                    k=k,
                )
            )
        )
    Z = np.concatenate(zs)[:n]  # (G, 4, k, 16)
    # rank reduction: rows (G, j), columns (q, Mueller element)
    rows = np.transpose(Z, (0, 2, 1, 3)).reshape(n * k, 64)
    scale = np.abs(rows).max(axis=1, keepdims=True)
    rows_n = rows / np.where(scale > 0, scale, 1.0)
    _, sv, vt = np.linalg.svd(rows_n, full_matrices=False)
    r = int(np.sum(sv > RANK_TOL * sv[0]))
    V = vt[:r]  # (r, 64), orthonormal rows
    T = rows @ V.T  # (G k, r)
    resid = np.abs(rows - T @ V).max() / np.abs(rows).max()
    T = T.reshape(n, k, r)
    white = node_products(jnp.zeros(()), jnp.zeros(()), k, white=True)
    E = np.einsum("qj,gjqe->ge", np.asarray(white), Z.transpose(0, 2, 1, 3))[:, 0]
    logE = np.where(E > 0, np.log(np.where(E > 0, E, 1.0)), LOG_FLOOR)
    logE = np.maximum(logE, LOG_FLOOR)
    Tn = np.where(E[:, None, None] > 0, T / np.where(E > 0, E, 1.0)[:, None, None], 0.0)
    info = (
        f"order={order} K={k} nx={nx} nu={nu} rank={r} singular values={sv[: r + 2].tolist()} "
        f"rank-{r} max residual {resid:.2e}"
    )
    return dict(
        logE=logE.reshape(nx, nu),
        Tn=Tn.reshape(nx, nu, k * r),
        V=V.reshape(r, 4, 16),
        x=xs,
        u=us,
        info=np.asarray(info),
    )


def save_table(tab: dict[str, np.ndarray], path: str = TABLE_FILE) -> str:
    np.savez_compressed(
        path,
        logE=tab["logE"].astype(np.float32),
        Tn=tab["Tn"].astype(np.float32),
        V=tab["V"],
        x=tab["x"],
        u=tab["u"],
        info=tab["info"],
    )
    load_table.cache_clear()
    return path


class _Table:
    """The padded interpolation arrays (NumPy, float64)."""

    def __init__(self, f):
        x, u = np.asarray(f["x"], float), np.asarray(f["u"], float)
        self.nx, self.nu = len(x), len(u)
        # Python floats: NumPy float64 scalars are not weakly typed in JAX, and would promote
        # float32 lookups to float64 when x64 is enabled
        self.dx, self.du = float(x[1] - x[0]), float(u[1] - u[0])
        self.V = np.asarray(f["V"], float)  # (r, 4, 16)
        self.rank = self.V.shape[0]
        logE = np.asarray(f["logE"], float)
        self.slope_end = (logE[-1] - logE[-2]) / self.dx  # (nu,) d log E / dx at X_MAX
        vals = np.concatenate([logE[..., None], np.asarray(f["Tn"], float)], axis=-1)
        self.k = (vals.shape[-1] - 1) // self.rank
        self.vals = _pad_quadratic(_pad_quadratic(vals, 0), 1)  # (nx+2, nu+2, 1 + k r)
        # u-major copy for the one-material path: its 4 rows in u are one contiguous block
        self.vals_u = np.ascontiguousarray(self.vals.transpose(1, 0, 2))  # (nu+2, nx+2, .)
        self.slope_pad = _pad_quadratic(self.slope_end, 0)
        self.info = str(f["info"])


@functools.cache
def load_table(path: str = TABLE_FILE) -> _Table:
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"double-bounce backscatter table {path} is missing; build it with "
            "`python scripts/double_backscatter_table.py`"
        )
    with np.load(path) as f:
        return _Table(f)


def _interp(tab: _Table, x: Array, u: Array, dt) -> tuple[Array, Array, Array]:
    """Catmull-Rom values ``(log E, T / E, d log E / dx at X_MAX)`` at ``(x, u)`` (clamped to
    the grid)."""
    i, tx = _cell(x, 0.0, tab.dx, tab.nx)
    j, tu = _cell(u, 0.0, tab.du, tab.nu)
    # rows of flat (nodes, values) arrays by jnp.take: on XLA CPU 7x faster than indexing the
    # 3-D array with two index arrays, and log E comes from its own array (slicing it off a
    # joint result made XLA recompute the gathers per output: 9x slower; both measured,
    # 2.5e5 points, float32)
    nv = tab.vals.shape[-1]
    flat_e = jnp.asarray(tab.vals[..., 0].reshape(-1), dt)
    flat_t = jnp.asarray(tab.vals[..., 1:].reshape(-1, nv - 1), dt)
    nu2 = tab.vals.shape[1]
    wx = _cr_weights(tx)
    wu = _cr_weights(tu)
    out_e = 0.0
    out_t = 0.0
    for a in range(4):
        row_e = 0.0
        row_t = 0.0
        for b in range(4):
            idx = (i + a) * nu2 + (j + b)
            row_e = row_e + wu[b] * jnp.take(flat_e, idx, axis=0)
            row_t = row_t + wu[b][..., None] * jnp.take(flat_t, idx, axis=0)
        out_e = out_e + wx[a] * row_e
        out_t = out_t + wx[a][..., None] * row_t
    sl = jnp.asarray(tab.slope_pad, dt)
    slope = sum(wu[b] * sl[j + b] for b in range(4))
    return out_e, out_t, slope


def _interp_one_material(
    tab: _Table, x: Array, u: Array, W: Array, dt
) -> tuple[Array, Array, Array]:
    """Fast path of :func:`_interp` followed by the contraction with ``W`` (``(k r, 16)``) for
    one material (scalar ``u``): the Catmull-Rom step in ``u`` and the contraction are done
    once on the table's rows (both linear, so they commute with the interpolation in ``x``),
    leaving a 4-point interpolation in ``x`` of 17 values per element, instead of 16
    gathered 97-vectors (measured ~10x faster, bench/bench_double_table.py).

    Returns ``(log E, slope)`` as ``(...,)`` arrays and ``T/E @ W`` as ``(..., 16)``."""
    j, tu = _cell(u, 0.0, tab.du, tab.nu)
    wu = _cr_weights(tu)
    vals = jnp.asarray(tab.vals_u, dt)  # (nu + 3, nx + 3, 1 + k r), u-major
    # one contiguous (4, nx + 3, 1 + k r) block: under vmap over materials (MCMC walkers) a
    # slice along the table's second axis became a strided gather and copy
    cols = jax.lax.dynamic_slice_in_dim(vals, j, 4, axis=0)
    row = jnp.einsum("b,bxv->xv", jnp.stack(wu), cols)  # (nx + 3, 1 + k r)
    rows_e = row[:, 0]  # log E
    rows_m = row[:, 1:] @ W  # (nx + 3, 16): the contracted T/E
    sl = jnp.asarray(tab.slope_pad, dt)
    slope = sum(wu[b] * jax.lax.dynamic_index_in_dim(sl, j + b, keepdims=False) for b in range(4))
    i, tx = _cell(x, 0.0, tab.dx, tab.nx)
    # log E and the 16 entries gathered separately (contiguous 16-value rows): slicing one
    # joint (17, ...) result made XLA CPU re-run the gathers per slice (7x slower)
    log_e = _cr_eval(_cr_cubics(rows_e, tab.nx), i, tx)
    out = _cr_eval(_cr_cubics(rows_m, tab.nx), i, tx)
    return log_e, jnp.broadcast_to(slope, x.shape), out


# --------------------------------------------------------------------------------------------
# evaluation


def near_backscatter(
    k_in: Float[ArrayLike, "... 3"], k_out: Float[ArrayLike, "... 3"], psi_max: float = PSI_MAX
) -> Array:
    """``psi <= psi_max`` per element (``|k' - k| = 2 sin(psi / 2)``)."""
    dk = jnp.asarray(k_out) - jnp.asarray(k_in)
    # component arithmetic (a trailing-axis reduction ran ~5x slower on XLA CPU)
    q2 = dk[..., 0] * dk[..., 0] + dk[..., 1] * dk[..., 1] + dk[..., 2] * dk[..., 2]
    return q2 <= (2.0 * math.sin(0.5 * psi_max)) ** 2


def _rot2a3(x_from, x_to, d):
    """SoA :func:`ppr.optics.rotation_cos_sin_2a`: ``(cos 2a, sin 2a)`` of the rotation about
    ``d`` taking frame vector ``x_from`` to ``x_to`` (identity where undefined)."""
    c = _dot3(x_from, x_to)
    s = _dot3(d, _cross3(x_from, x_to))
    r2 = c * c + s * s
    ok = r2 > tiny(r2.dtype)
    inv = 1.0 / jnp.where(ok, r2, 1.0)
    return jnp.where(ok, (c * c - s * s) * inv, 1.0), jnp.where(ok, 2.0 * c * s * inv, 0.0)


def incidence_variable(c: Array) -> Array:
    """The table's incidence variable ``x = asinh(TAU tan theta)`` of ``c = cos theta`` in
    ``(0, 1]`` (``c`` above the grazing cut), with finite derivatives everywhere.

    ``s = sin theta`` by the double where (the term has a cusp ``|theta|`` at normal
    incidence: zero gradient there instead of ``0 * inf``). Near grazing (``z = TAU s / c >
    1e4``) as ``log(TAU s + sqrt((TAU s)^2 + c^2)) - log c``, which is ``asinh z`` exactly:
    there asinh's own derivative ``1 / sqrt(1 + z^2)`` underflows to 0 while ``dz/dc = -z /
    c`` overflows (float32 below ``c ~ 1e-19``, float64 below ``1e-160``): a NaN gradient."""
    dt = c.dtype
    s2 = jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0)
    s_ok = s2 > tiny(dt) * 1e8
    sn = jnp.where(s_ok, jnp.sqrt(jnp.where(s_ok, s2, 1.0)), 0.0)
    ts = TAU * sn
    z_ok = ts < 1e4 * c
    x_mid = jnp.arcsinh(jnp.where(z_ok, ts, 0.0) / jnp.where(z_ok, c, 1.0))
    ts_b, c_b = jnp.where(z_ok, 1.0, ts), jnp.where(z_ok, 1.0, c)
    x_big = jnp.log(ts_b + jnp.sqrt(ts_b * ts_b + c_b * c_b)) - jnp.log(c_b)
    return jnp.where(z_ok, x_mid, x_big)


def backscatter_local(k3, n3, material, m, dt, batch, scale) -> tuple[Array, Array]:
    """The table's double term at exact backscatter in the shared frames ``e = normalize(n x
    k)`` (input beam along ``-k`` and output beam along ``+k``, both with x axis ``e``):
    ``(M, valid)``, ``M`` the row-major ``(..., 16)`` entries times ``scale`` (the coherent
    enhancement ``1 + gamma``), 0 where ``valid`` is false (grazing, or ``m > M_MAX``).
    ``k3``, ``n3``: SoA unit vectors of shape ``batch``; ``m`` the exponent broadcast to it."""
    tab = load_table()
    g_min = tiny(dt) * 1e8
    c = _dot3(k3, n3)
    valid = (c > g_min) & (m <= M_MAX)
    c_safe = jnp.where(valid, jnp.clip(c, 0.0, 1.0), 1.0)
    x = incidence_variable(c_safe)
    m_safe = jnp.where(valid, m, 0.0)
    u = jnp.sqrt(m_safe + M_SHIFT) - math.sqrt(M_SHIFT)
    white = bool(getattr(material, "white", False))
    n_re0 = jnp.real(jnp.asarray(material.n)).astype(dt)
    n_im0 = jnp.imag(jnp.asarray(material.n)).astype(dt)
    from ..optics._films import films_of  # noqa: PLC0415

    films = films_of(material, dt)
    if films is not None:
        leaves = jax.tree.leaves(films)
        fshape = jnp.broadcast_shapes(n_re0.shape, *(jnp.shape(a) for a in leaves))
        n_re0, n_im0 = (jnp.broadcast_to(a, fshape) for a in (n_re0, n_im0))
    # (..., 4, k), material's own shape
    g = node_products(n_re0, n_im0, tab.k, white=white, films=films)
    V = jnp.asarray(tab.V, dt)  # (r, 4, 16)
    if g.ndim == 2 and jnp.ndim(material.m) == 0 and math.prod(batch) >= ONE_MATERIAL_MIN_BATCH:
        # one material for the whole batch: fold it into the (k r, 16) map and interpolate
        # the contracted rows
        W = jnp.einsum("qj,rqe->jre", g, V).reshape(tab.k * tab.rank, 16)
        u0 = jnp.sqrt(jnp.asarray(material.m, dt) + M_SHIFT) - math.sqrt(M_SHIFT)
        log_e, slope, M16 = _interp_one_material(tab, x, u0, W, dt)
        log_e = log_e + slope * jnp.maximum(x - X_MAX, 0.0)
        env = jnp.where(valid, jnp.exp(jnp.minimum(log_e, 50.0)), 0.0)
        M16 = M16 * (env * scale)[..., None]
    else:
        log_e, tn, slope = _interp(tab, x, u, dt)
        log_e = log_e + slope * jnp.maximum(x - X_MAX, 0.0)
        env = jnp.where(valid, jnp.exp(jnp.minimum(log_e, 50.0)), 0.0)
        # the envelope and the coherent enhancement scale whole rows, before the contraction
        tn = tn * (env * scale)[..., None]
        if g.ndim == 2:
            W = jnp.einsum("qj,rqe->jre", g, V).reshape(tab.k * tab.rank, 16)
            M16 = tn @ W
        else:
            # per-element material (e.g. a mesh's facets): 3.7e5 evals/s float32 against
            # 1.6e6 for one material (measured)
            T = tn.reshape(batch + (tab.k, tab.rank))
            gb = jnp.broadcast_to(g, batch + (4, tab.k))
            # beta_rq = sum_j T_jr g_qj, one reduction per q (measured 1.9x faster than one
            # 4-D broadcast product and sum)
            beta = jnp.stack([jnp.sum(T * gb[..., q, :, None], axis=-2) for q in range(4)], -1)
            M16 = beta.reshape(batch + (4 * tab.rank,)) @ V.reshape(4 * tab.rank, 16)
    return M16, valid


def double_backscatter_44(
    k_in,
    k_out,
    normal,
    material,
    frame_in,
    frame_out,
    *,
    wavelength=DEFAULT_WAVELENGTH_M,
    coherent=True,
) -> Array:
    """:func:`double_backscatter_term` (``frame_in``/``frame_out`` may be SoA tuples of three
    arrays). The entries stay on a trailing axis throughout, and the frame rotations are
    :func:`ppr.optics._frames.rotate_mueller_44`: built ``(16, ...)`` and transposed at the end, the
    term ran 1.8x slower (bench/profile_brdf.py)."""
    f_in3, f_out3 = _split(frame_in), _split(frame_out)
    k, kp, nrm, _, _, m, n_re, n_im, dt, batch = D._broadcast_inputs(
        k_in, k_out, normal, material, k_in, k_out
    )
    k3, kp3, n3 = _split(k), _split(kp), _split(nrm)
    f_in3 = tuple(jnp.broadcast_to(jnp.asarray(a, dt), batch) for a in f_in3)
    f_out3 = tuple(jnp.broadcast_to(jnp.asarray(a, dt), batch) for a in f_out3)
    if coherent:
        gamma = D.coherence_factor(k, kp, wavelength, material.corr_length).astype(dt)
        gamma = jnp.broadcast_to(gamma, batch)
    else:
        gamma = jnp.zeros(batch, dt)
    M16, valid = backscatter_local(k3, n3, material, m, dt, batch, 1.0 + gamma)
    valid = valid & (_dot3(kp3, n3) > tiny(dt) * 1e8)
    # frames: e = normalize(n x k) (as in the table; ppr.brdf.double._common_frame at k' = k),
    # its projection _|_ k' for the output; component arithmetic throughout
    e = _default_frame3(k3, n3)
    ek = _dot3(e, kp3)
    e_out = tuple(a - ek * b for a, b in zip(e, kp3, strict=True))
    sq = _dot3(e_out, e_out)
    ok = sq > 0.25
    inv = 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0))
    fb = _perp3_any(kp3)
    e_out = tuple(jnp.where(ok, a * inv, f) for a, f in zip(e_out, fb, strict=True))
    return rotate_local(M16, valid, e, e_out, k3, kp3, f_in3, f_out3)


def rotate_local(M16, valid, e_in, e_out, k3, kp3, f_in3, f_out3) -> Array:
    """``(..., 4, 4)``: the local ``(..., 16)`` entries ``M16`` (input frame x axis ``e_in``
    about ``-k``, output ``e_out`` about ``+k'``) rotated into the frames ``f_in3``, ``f_out3``
    (SoA), 0 where not ``valid``."""
    batch = M16.shape[:-1]
    c_in, s_in = _rot2a3(f_in3, e_in, _neg3(k3))
    c_out, s_out = _rot2a3(e_out, f_out3, kp3)
    # M and the angles stored first: XLA CPU otherwise re-computes the gathers, the envelope
    # and the frame arithmetic inside the rotation, once per entry (full BRDF at backscatter
    # 2.6 -> 4.5-4.9 M evals/s float32 with the store in mueller_brdf, bench/profile_brdf.py)
    M16 = store(M16)
    c_in, s_in, c_out, s_out = (store(x) for x in (c_in, s_in, c_out, s_out))
    out = rotate_mueller_44(M16.reshape(batch + (4, 4)), c_in, s_in, c_out, s_out)
    return jnp.where(valid[..., None, None], out, 0.0)


def double_backscatter_term(
    k_in: Float[ArrayLike, "*#batch 3"],
    k_out: Float[ArrayLike, "*#batch 3"],
    normal: Float[ArrayLike, "*#batch 3"],
    material,
    frame_in: Float[ArrayLike, "*#batch 3"],
    frame_out: Float[ArrayLike, "*#batch 3"],
    *,
    wavelength: float | Float[ArrayLike, "..."] = DEFAULT_WAVELENGTH_M,
    coherent: bool = True,
) -> Float[Array, "*batch 4 4"]:
    """Double-bounce Mueller BRDF (1/sr) at exact backscatter from the table, with the
    coherent enhancement ``(1 + gamma(psi))`` (module docstring). Valid where
    ``psi <= PSI_MAX`` (the incoherent part is taken at ``psi = 0``); same signature as
    :func:`ppr.brdf.double.double_bounce_term`. Differentiable in the directions, ``m`` and
    ``n``; exactly grazing rows give 0."""
    dt = D.float_dtype(k_in, k_out, normal, frame_in, frame_out, material.m, material.n)
    fi = jnp.broadcast_to(jnp.asarray(frame_in, dt), jnp.broadcast_shapes(
        jnp.shape(k_in), jnp.shape(frame_in)))
    fo = jnp.broadcast_to(jnp.asarray(frame_out, dt), jnp.broadcast_shapes(
        jnp.shape(k_out), jnp.shape(frame_out)))
    return double_backscatter_44(
        k_in, k_out, normal, material, fi, fo, wavelength=wavelength, coherent=coherent
    )


def double_term_dispatch(
    k_in: Float[ArrayLike, "*#batch 3"],
    k_out: Float[ArrayLike, "*#batch 3"],
    normal: Float[ArrayLike, "*#batch 3"],
    material,
    frame_in: Float[ArrayLike, "*#batch 3"] | tuple[Array, Array, Array],
    frame_out: Float[ArrayLike, "*#batch 3"] | tuple[Array, Array, Array],
    *,
    wavelength: float | Float[ArrayLike, "..."] = DEFAULT_WAVELENGTH_M,
    branch: str | None = None,
) -> Float[Array, "*batch 4 4"]:
    """The double term: the backscatter table where *every* element of the batch is within
    ``PSI_MAX`` of exact backscatter, else the quadrature of :mod:`ppr.brdf.double`.

    One ``lax.cond`` on the whole batch (under ``vmap`` with a batched predicate it becomes a
    select that evaluates both; ``ppr.render`` therefore decides once per sensor, see
    ``ppr.pulse._pulse.facet_weights``). A compiled ``lax.cond`` holds both branches, so a caller
    that knows the answer on the host passes ``branch`` (static: ``"table"`` or
    ``"quadrature"``) and the program holds that branch only (``mueller_brdf`` does for
    concrete inputs). The frames may be SoA tuples of three arrays (as ``mueller_brdf``
    passes them: stacking them into ``(..., 3)`` arrays runs as a scalar concatenate loop on
    XLA CPU, so only the quadrature branch does it)."""
    n = jnp.asarray(material.n)
    dt = D.float_dtype(k_in, k_out, normal, material.m, n)

    def arr(f):
        if isinstance(f, tuple | list):
            return jnp.stack(jnp.broadcast_arrays(*f), axis=-1)
        return f

    def table(_):
        return double_backscatter_44(
            k_in, k_out, normal, material, frame_in, frame_out, wavelength=wavelength
        ).astype(dt)

    def quadrature(_):
        args = (k_in, k_out, normal, material, arr(frame_in), arr(frame_out))
        return D.double_bounce_term(*args, wavelength=wavelength).astype(dt)

    if branch == "table":
        return table(None)
    if branch == "quadrature":
        return quadrature(None)
    if branch is not None:
        raise ValueError(f"branch={branch!r}: expected None, 'table' or 'quadrature'")
    near = jnp.all(near_backscatter(k_in, k_out))
    return jax.lax.cond(near, table, quadrature, None)


def double_bounce_term_auto(
    k_in: Float[Array, "*batch 3"],
    k_out: Float[Array, "*batch 3"],
    normal: Float[Array, "*batch 3"],
    material,
    frame_in: Float[Array, "*batch 3"],
    frame_out: Float[Array, "*batch 3"],
    *,
    wavelength: float | Float[ArrayLike, "..."] = DEFAULT_WAVELENGTH_M,
) -> Float[Array, "*batch 4 4"]:
    """The double term (:func:`double_term_dispatch`: the backscatter table
    or the quadrature) where :func:`ppr.brdf.double.double_needed`, else 0.

    One ``lax.cond`` on the whole batch: the quadrature runs only if *some* element needs it
    (jit-compatible; under ``vmap`` a cond becomes a select and saves nothing, so batch by
    broadcasting, as ``mueller_brdf`` does). Elements of a mixed batch that do not need the
    term get it anyway (exact, just not cheaper); zeroing them would add nothing but error.
    """
    n = jnp.asarray(material.n)
    dt = D.float_dtype(k_in, k_out, normal, material.m, n)
    batch = jnp.broadcast_shapes(
        jnp.shape(k_in)[:-1],
        jnp.shape(k_out)[:-1],
        jnp.shape(normal)[:-1],
        jnp.shape(material.m),
        n.shape,
    )
    need = jnp.any(D.double_needed(material.m, k_in, k_out))

    def yes(_):
        return double_term_dispatch(
            k_in, k_out, normal, material, frame_in, frame_out, wavelength=wavelength
        ).astype(dt)

    def no(_):
        return jnp.zeros(batch + (4, 4), dt)

    return jax.lax.cond(need, yes, no, None)
