"""White furnace and energy bounds of the full BRDF (single + double + multiple), the albedo
tables and the Kulla-Conty Fresnel average.

Each term is integrated over the outgoing hemisphere with a rule suited to its lobe:

* single + double (the explicit terms): the half-vector rule of
  :func:`ppr.brdf.albedo.albedo_nodes` (uniform in the lobe weight, panel ends at the horizon and
  at the joint-visibility kink). At large m the double lobe sits next to the mirror
  direction (two small facet tilts), inside the half-vector cone; at small m the rule covers
  the whole hemisphere. It is the rule the tables were built with, but at another order.
* multiple (a broad lobe ``D(k) D(k') / (pi D_avg)`` that depends on ``k'.n`` only):
  Gauss-Legendre in ``v = log(mu' + 1e-4) + 3 mu'`` (resolves the grazing band
  ``mu' ~ 1/sqrt(m)`` where the deficit ``D(mu')`` lives at large m) times three azimuths.
  The half-vector rule would miss it at large m (it only covers ``theta_h < ~0.09`` rad
  around the mirror direction at m = 1e4).

The BRDF is evaluated through ``ppr.mueller_brdf`` (default terms, coherent backscatter
included), so the test checks the assembled model, not the tables. All (m, incidence, node)
triples go through one jitted kernel of fixed chunk shape (one compilation per material kind).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from ppr.brdf import albedo as _albedo
from ppr.brdf._brdf import explicit_terms, fresnel_average, implemented_terms, mueller_brdf
from ppr.materials._material import Material
from ppr.optics._fresnel import fresnel_mueller_params

Z = jnp.asarray([0.0, 0.0, 1.0])
M_LIST = [0.0, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e6]
THETA_DEG = [0.0, 30.0, 60.0, 75.0, 85.0, 88.0, 89.0]
HV_ORDER = (12, 6)  # (n_phi, n_w) of albedo_nodes: 1152 nodes per (m, mu)
N_V, PHI_MS = 96, (0.3, 1.4, 2.7)  # multiple-scattering rule
CHUNK = 4096


def _explicit_and_rest():
    terms = implemented_terms()
    expl = tuple(t for t in terms if t != "multiple")
    return expl, ("multiple",) if "multiple" in terms else ()


@functools.cache
def _kernel(white: bool, terms: tuple[str, ...]):
    @jax.jit
    def f(k_in, k_out, m, n_re, n_im):
        mat = Material.ideal_white(m) if white else Material(n=n_re + 1j * n_im, m=m)
        z = jnp.broadcast_to(Z, k_in.shape)
        return mueller_brdf(k_in, k_out, z, mat, terms=terms)[..., 0, 0]

    return f


def _padded(a, *, s, e, pad):
    return jnp.asarray(np.concatenate([a[s:e], np.repeat(a[:1], pad, 0)]))


def _eval(white, terms, k_in, k_out, m, n_re, n_im):
    """M00 for flat rows, in fixed-size chunks (one compilation)."""
    f = _kernel(white, terms)
    n = len(m)
    out = np.empty(n)
    for s in range(0, n, CHUNK):
        e = min(s + CHUNK, n)
        pad = CHUNK - (e - s)
        p = functools.partial(_padded, s=s, e=e, pad=pad)
        out[s:e] = np.asarray(f(p(k_in), p(k_out), p(m), p(n_re), p(n_im)))[: e - s]
    return out


def _ms_nodes():
    """k' rule for the multiple-scattering lobe: GL in the warped cosine, 3 azimuths."""
    x, w = np.polynomial.legendre.leggauss(N_V)
    v0, v1 = float(_albedo.warp_mu(0.0)), float(_albedo.warp_mu(1.0))
    v = v0 + 0.5 * (v1 - v0) * (x + 1.0)
    wv = 0.5 * (v1 - v0) * w
    mu = _albedo.unwarp_v(v)
    dmu = 1.0 / (1.0 / (mu + _albedo.MU0) + _albedo.ALPHA)
    ph = np.asarray(PHI_MS)
    s = np.sqrt(1.0 - mu**2)
    kp = np.stack(
        [s[:, None] * np.cos(ph), s[:, None] * np.sin(ph), np.broadcast_to(mu[:, None], (N_V, 3))],
        -1,
    ).reshape(-1, 3)
    # int d omega' = int dmu' dphi' ; the three azimuths share 2 pi
    wt = np.repeat(wv * dmu * mu * 2.0 * np.pi / len(ph), len(ph))
    return kp, wt


def directional_albedo(m_list, theta, n=1.0 + 0j, white=True, hv_order=HV_ORDER):
    """``E(m, theta)`` of the default-terms BRDF on the (m, theta) grid: explicit terms by
    the half-vector rule, the multiple-scattering remainder by the warped-cosine rule.
    Returns (E_explicit, E_multiple), each of shape (len(m_list), len(theta))."""
    expl, rest = _explicit_and_rest()
    mm, tt = np.meshgrid(np.asarray(m_list, float), np.asarray(theta, float), indexing="ij")
    mu = np.maximum(np.cos(tt), 0.0)
    k_in, k_out, wt = _albedo.albedo_nodes(mm, mu, *hv_order)
    Q = k_out.shape[-2]
    ki = np.broadcast_to(k_in[..., None, :], k_out.shape).reshape(-1, 3)
    mq = np.broadcast_to(mm[..., None], wt.shape).reshape(-1)
    nre = np.full(mq.shape, float(np.real(n)))
    nim = np.full(mq.shape, float(np.imag(n)))
    f = _eval(white, expl, ki, k_out.reshape(-1, 3), mq, nre, nim).reshape(wt.shape)
    e_expl = np.sum(f * wt, -1)
    if not rest:
        return e_expl, np.zeros_like(e_expl)
    kp, wq = _ms_nodes()
    Qm = len(kp)
    ki = np.broadcast_to(k_in[..., None, :], mm.shape + (Qm, 3)).reshape(-1, 3)
    ko = np.broadcast_to(kp, mm.shape + (Qm, 3)).reshape(-1, 3)
    mq = np.broadcast_to(mm[..., None], mm.shape + (Qm,)).reshape(-1)
    nre = np.full(mq.shape, float(np.real(n)))
    nim = np.full(mq.shape, float(np.imag(n)))
    g = _eval(white, rest, ki, ko, mq, nre, nim).reshape(mm.shape + (Qm,))
    del Q
    return e_expl, np.sum(g * wq, -1)


@functools.cache
def _white_grid():
    return directional_albedo(M_LIST, np.deg2rad(THETA_DEG))


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
def test_white_furnace_all_terms():
    """Ideal white (F = 1), default terms: directional albedo 1 within 1e-3 at every m in
    [0, 1e6] and incidence 0..89 deg."""
    e1, e3 = _white_grid()
    err = np.abs(e1 + e3 - 1.0)
    i, j = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() < 1e-3, (err.max(), M_LIST[i], THETA_DEG[j], e1[i, j], e3[i, j])


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
def test_explicit_terms_never_exceed_one():
    """single + double <= 1 (the flux entering bounce 2 is exactly 1 - E_single,
    docs/physics/double_bounce.md / ppr/brdf/double.py): the runtime quadrature must not
    overshoot (quadrature slack 2e-4)."""
    e1, _ = _white_grid()
    assert e1.max() <= 1.0 + 2e-4, (e1.max(), np.unravel_index(np.argmax(e1), e1.shape))


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
def test_white_furnace_independent_plain_quadrature():
    """Broad lobes (m <= 10): plain Gauss-Legendre in (cos theta_out, phi_out), 64 x 64
    nodes, for every term together, independent of the half-vector mapping. Kinks of the
    integrand (joint visibility min, forward azimuth, horizon of the double paths) limit it
    to a few 1e-4."""
    gx, gw = np.polynomial.legendre.leggauss(64)
    mu_o = 0.5 * (gx + 1.0)
    phi = np.pi * (gx + 1.0)
    MU, PHI = np.meshgrid(mu_o, phi, indexing="ij")
    s = np.sqrt(1 - MU**2)
    k_out = np.stack([s * np.cos(PHI), s * np.sin(PHI), MU], -1).reshape(-1, 3)
    W = (0.5 * gw[:, None] * np.pi * gw[None, :] * MU).ravel()
    rows = [(m, th) for m in (0.0, 1.0, 10.0) for th in (0.0, 40.0, 75.0)]
    Q = len(W)
    ki = np.concatenate(
        [np.repeat([[np.sin(np.deg2rad(t)), 0.0, np.cos(np.deg2rad(t))]], Q, 0) for _, t in rows]
    )
    ko = np.tile(k_out, (len(rows), 1))
    mq = np.repeat([m for m, _ in rows], Q)
    one = np.ones_like(mq)
    E = 0.0
    for terms in _explicit_and_rest():  # same kernels as the other tests (no recompilation)
        if terms:
            E = E + _eval(True, terms, ki, ko, mq, one, 0 * one).reshape(len(rows), Q) @ W
    np.testing.assert_allclose(E, 1.0, atol=1e-3, err_msg=str(list(zip(rows, E, strict=True))))


N_REAL = [0.94 + 6.42j, 0.54 + 2.23j, 0.054 + 3.43j, 1.461 + 0j, 2.668 + 0j, 1.0 + 10j, 1.0 + 0j]


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
@pytest.mark.parametrize("n_index", N_REAL)
def test_albedo_at_most_one_for_real_materials(n_index):
    theta = np.deg2rad([0.0, 60.0, 85.0, 89.0])
    e1, e3 = directional_albedo(
        [0.0, 1.0, 100.0, 1e4, 1e6], theta, n=n_index, white=False, hv_order=(8, 4)
    )
    E = e1 + e3
    # quadrature error of the low-order rule is the only slack
    assert np.all(E <= 1.0 + 5e-4), E.max()
    assert np.all(E >= 0.0)
    if n_index == 1.0:
        np.testing.assert_allclose(E, 0.0, atol=1e-12)  # no index contrast, no reflection


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
@pytest.mark.xfail(
    strict=True,
    reason="known, open: 40 x 48 Catmull-Rom table of single + double vs direct quadrature "
    "(half-vector rule (12, 6)) at 24 random off-node (m, mu): measured max |D_tab - D_ref| "
    "= 8.7e-4 against the 5e-4 target (the white furnace itself still closes within 1e-3)",
)
def test_table_interpolation_error_off_nodes():
    """Interpolated deficit of the explicit terms vs direct quadrature at random off-node
    (m, mu): the furnace tolerance 1e-3 needs < ~5e-4."""
    rng = np.random.default_rng(0)
    table = _albedo.load_table(explicit_terms())
    m = np.expm1(rng.uniform(0, np.log1p(1e6), 24))
    mu = rng.uniform(0, 1, 24) ** 2
    expl, _ = _explicit_and_rest()
    k_in, k_out, wt = _albedo.albedo_nodes(m, mu, *HV_ORDER)
    ki = np.broadcast_to(k_in[:, None, :], k_out.shape).reshape(-1, 3)
    mq = np.repeat(m, wt.shape[-1])
    one = np.ones_like(mq)
    f = _eval(True, expl, ki, k_out.reshape(-1, 3), mq, one, 0 * one).reshape(wt.shape)
    D_ref = 1.0 - np.sum(f * wt, axis=-1)
    D_tab = np.asarray(_albedo.deficit(table, m, mu))
    assert np.max(np.abs(D_tab - D_ref)) < 5e-4, np.max(np.abs(D_tab - D_ref))


def test_deficit_avg_is_integral_of_interpolant():
    """``D_avg(m)`` is the integral of the 2-D interpolant ``exp(L(m, mu))``: to rounding at the
    nodes of its fine x grid, and within its own Catmull-Rom interpolation between them
    (8 times finer than the deficit grid; the closure of the double term's quadrature error
    makes ``log D_avg(m)`` less smooth: measured 9.4e-5 relative at worst over 95 values of m,
    i.e. below 3e-5 of the incident flux)."""
    table = _albedo.load_table(explicit_terms())
    gx, gw = np.polynomial.legendre.leggauss(64)
    # integrate in v (warped), where the interpolant of log D is piecewise cubic
    v_lo, v_hi = table.v_lo, table.v_lo + table.dv * (table.nv - 1)
    edges = np.linspace(v_lo, v_hi, table.nv)
    a, b = edges[:-1, None], edges[1:, None]
    v = (0.5 * (b - a) * gx[None, :] + 0.5 * (a + b)).ravel()
    w = (0.5 * (b - a) * gw[None, :]).ravel()
    mu = _albedo.unwarp_v(v)
    dmu = 1.0 / (1.0 / (mu + _albedo.MU0) + _albedo.ALPHA)
    xa = table.xa_nodes
    on_nodes = [float(np.expm1(xa[i])) for i in (0, 3, 101, 200, len(xa) - 1)]
    off_nodes = [0.37, 7.3, 512.0, 3.3e4, 7e5]
    for ms, rtol in ((on_nodes, 1e-9), (off_nodes, 2e-4)):
        for m in ms:
            D = np.asarray(_albedo.deficit(table, np.full_like(mu, m), mu))
            integral = 2.0 * np.sum(D * mu * dmu * w)
            np.testing.assert_allclose(
                float(_albedo.deficit_avg(table, m)), integral, rtol=rtol, err_msg=f"m={m}"
            )


def test_deficit_smooth_and_differentiable():
    table = _albedo.load_table(explicit_terms())
    g = jax.grad(lambda m, mu: _albedo.deficit(table, m, mu), argnums=(0, 1))
    for m, mu in [(0.0, 0.0), (0.0, 1.0), (1e6, 0.0), (1e6, 1.0), (3.0, 0.3)]:
        dm, dmu = g(m, mu)
        assert np.isfinite(float(dm)) and np.isfinite(float(dmu))
    # C1: left and right derivatives agree at a node in x
    x0 = table.x_lo + 17 * table.dx
    m0 = np.expm1(x0)
    h = 1e-7 * (1 + m0)
    d = lambda m: float(_albedo.deficit(table, m, 0.01))  # noqa: E731
    left = (d(m0) - d(m0 - h)) / h
    right = (d(m0 + h) - d(m0)) / h
    assert abs(left - right) <= 1e-4 * (abs(left) + abs(right)) + 1e-12


@pytest.mark.parametrize("n_index", [1.5, 0.94 + 6.42j, 0.2 + 7j, 1.0])
def test_fresnel_average_against_scipy(n_index):
    def F(mu):
        a, _, _, _ = fresnel_mueller_params(np.real(n_index), np.imag(n_index), mu)
        return float(a)

    ref, _ = integrate.quad(lambda mu: 2 * F(mu) * mu, 0, 1, epsabs=1e-13, limit=200)
    got = float(fresnel_average(Material(n=n_index, m=1.0)))
    # 32-point Gauss-Legendre on a smooth integrand
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-14)
