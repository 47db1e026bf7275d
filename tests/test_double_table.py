"""The double-bounce term near exact backscatter from tables (ppr/brdf/double_table.py).

References: the quadrature of ppr/brdf/double.py at order (16, 64) (6144 paths; itself checked
against an independent NumPy brute force over the whole sphere in tests/test_double.py, and
within 5e-4 of M00(single + double) of order (24, 96)), and independent NumPy Fresnel for
the node interpolation. The table is built from order (24, 96); what is tested is what a
user gets: interpolation in incidence and roughness, the Fresnel node basis, the envelope,
the frames, the coherent factor and psi > 0 up to PSI_MAX.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr import Material, mueller_brdf
from ppr.brdf import double as D
from ppr.brdf import double_table as T
from ppr.brdf._sampling import bistatic_geometry
from ppr.optics.polarimetry import cloude_eigenvalues
from ppr.pulse._pulse import backscatter_terms

AL = 0.94 + 6.42j  # aluminium 532 nm
AU = 0.47 + 2.4j  # gold 532 nm
TIO2 = 2.67 + 0j
SILICA = 1.461 + 0j
REF_ORDER = (16, 64)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_geometry(rng, n, psi):
    """Random normals, incidences (half of them beyond 60 deg), receivers at bistatic angle
    psi in a random azimuth (kept above the horizon), random beam frames."""
    th = np.where(np.arange(n) % 2 == 0, rng.uniform(0, 60, n), rng.uniform(60, 88, n))
    return bistatic_geometry(rng, th, psi)


# one compiled program per shape (eager op-by-op dispatch of the table term is slow)
_table = jax.jit(T.double_backscatter_term, static_argnames=("coherent",))


@functools.cache
def _quadrature(order, coherent):
    return jax.jit(
        lambda k, kp, n, mat, fi, fo: D.double_bounce_term(
            k, kp, n, mat, fi, fo, order=order, coherent=coherent
        )
    )


@pytest.mark.optimized  # runs large batches (tests/compile_level.py)
def test_table_matches_quadrature_near_backscatter():
    """Error of the table vs the (16, 64) quadrature, as a fraction of M00(single + double):
    <= 1e-3 (measured 3.3e-4 at psi <= 1e-4, 5.8e-4 at psi = PSI_MAX = 1e-3, aluminium)."""
    rng = np.random.default_rng(7)
    rows = []
    for psi in (0.0, 3e-4, T.PSI_MAX):
        for n in (AL, AU, TIO2, SILICA):
            nrm, k, kp, fi, fo = random_geometry(rng, 12, psi)
            m = np.exp(rng.uniform(np.log(0.02), np.log(150.0), 12))
            rows.append((nrm, k, kp, fi, fo, np.full(12, n), m))
    nrm, k, kp, fi, fo, n, m = (np.concatenate(a) for a in zip(*rows, strict=True))
    mat = Material(n=jnp.asarray(n), m=jnp.asarray(m))
    ref = np.asarray(_quadrature(REF_ORDER, True)(k, kp, nrm, mat, fi, fo))
    got = np.asarray(_table(k, kp, nrm, mat, fi, fo))
    single = np.asarray(mueller_brdf(k, kp, nrm, mat, terms=("single",), frame_in=fi, frame_out=fo))
    err = np.abs(got - ref).max(axis=(1, 2)) / (single[:, 0, 0] + ref[:, 0, 0])
    assert err.max() < 1e-3, (err.max(), np.argmax(err))
    # where the double term is a visible part of the return, also relative to itself
    big = ref[:, 0, 0] > 0.05 * (single[:, 0, 0] + ref[:, 0, 0])
    assert big.sum() > 20
    rel = np.abs(got[big] - ref[big]).max(axis=(1, 2)) / ref[big, 0, 0]
    assert np.median(rel) < 2e-3, np.median(rel)


def test_coherent_part_is_twice_the_incoherent_at_backscatter():
    """Step 4 of the module docstring, on the quadrature itself: at psi = 0 the reversed
    path's Jones matrix equals the forward one, so M(gamma = 1) = 2 M(gamma = 0) in every
    element (co- and cross-polarized, linear and circular)."""
    rng = np.random.default_rng(3)
    nrm, k, _, fi, _ = random_geometry(rng, 6, 0.0)
    mat = Material(n=jnp.asarray(np.array([AL, TIO2] * 3)), m=jnp.asarray([0.5, 2.0, 8.0] * 2))
    both = jax.jit(
        lambda *a: [D.double_bounce_term(*a, order=(2, 8), coherent=c) for c in (False, True)]
    )
    inc, coh = (np.asarray(x) for x in both(k, k, nrm, mat, fi, fi))
    np.testing.assert_allclose(coh, 2.0 * inc, rtol=1e-9, atol=1e-12 * np.abs(inc).max())


def np_fresnel(n, c):
    w = np.sqrt(n * n - (1.0 - c * c) + 0j)
    return (c - w) / (c + w), (n * n * c - w) / (n * n * c + w)


@pytest.mark.parametrize("n,tol", [(AL, 2e-3), (AU, 2e-5), (TIO2, 2e-5), (SILICA, 1e-6)])
def test_fresnel_node_interpolation(n, tol):
    """The four products g(t) = |a|^2, |b|^2, Re a b*, Im a b* (a = r_s(t) r_s(pi/2 - t),
    b likewise for p) against their Lagrange interpolant on the K Chebyshev-Lobatto nodes,
    independent complex NumPy Fresnel; |g| <= 1."""
    t = np.linspace(0.0, np.pi / 2, 3001)
    rs1, rp1 = np_fresnel(n, np.cos(t))
    rs2, rp2 = np_fresnel(n, np.sin(t))
    a, b = rs1 * rs2, rp1 * rp2
    ab = a * np.conj(b)
    exact = np.stack([np.abs(a) ** 2, np.abs(b) ** 2, ab.real, ab.imag])
    g = np.asarray(T.node_products(jnp.asarray(n.real), jnp.asarray(n.imag), T.K_NODES))
    L = np.asarray(T.angle_basis(jnp.asarray(t), T.K_NODES))
    assert np.abs(g @ L.T - exact).max() < tol


def _stiff():
    th = np.radians([0.0, 1e-4, 30.0, 60.0, 89.0, 89.99, 89.9999, 90.0])
    k = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    k[-1] = [1.0, 0.0, 0.0]  # exactly grazing (cos(pi/2) rounds to 6e-17)
    ms = np.array([0.0, 1e-6, 1.0, 10.0, 199.0, 200.0, 1e3, 1e6])
    i, j = np.meshgrid(np.arange(len(th)), np.arange(len(ms)), indexing="ij")
    return k[i.ravel()], ms[j.ravel()], th[i.ravel()]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_stiff_cases_finite_values_and_gradients(dtype):
    """The stiff set (docs/physics/numerics.md), table path: normal incidence (a cusp |theta|: zero
    gradient there), grazing to 1e-4 deg and exactly 90 deg (0), m = 0, 1e-6, the table's end
    M_MAX and beyond (0), in float32 and float64; values and gradients in the directions,
    m and both parts of n finite."""
    k, ms, th = _stiff()
    cdt = jnp.complex64 if dtype == jnp.float32 else jnp.complex128
    z = jnp.asarray([0.0, 0.0, 1.0], dtype)
    e = jnp.asarray([0.0, 1.0, 0.0], dtype)

    @jax.jit
    def f(k, m, nr, ni):
        mat = Material(n=(nr + 1j * ni).astype(cdt), m=m)
        return T.double_backscatter_term(k, k, z, mat, e, e)

    args = (jnp.asarray(k, dtype), jnp.asarray(ms, dtype), dtype(0.94), dtype(6.42))
    val = np.asarray(f(*args))
    assert np.all(np.isfinite(val))
    assert np.all(val[th >= np.pi / 2] == 0.0)
    assert np.all(val[ms > T.M_MAX] == 0.0)
    assert np.all(val[(th < np.radians(89.0)) & (ms <= 10.0), 0, 0] > 0.0)
    grads = jax.jit(jax.grad(lambda *a: jnp.sum(f(*a) ** 2), argnums=(0, 1, 2, 3)))(*args)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_incidence_variable_is_asinh_with_finite_derivatives(dtype):
    """``x = asinh(2 tan theta)`` against mpmath over cos theta from 1 down to the grazing
    cut (both sides of the near-grazing form's switch at 2 tan theta = 1e4): relative error
    <= 4 eps of the dtype; its derivative equals the closed form
    ``-2 / (s c sqrt(c^2 + 4 s^2))`` to 1e-5 relative (float64: 1e-12) and is finite, 0 at
    normal incidence (asinh's own derivative times dz/dc was 0 * inf = NaN below c ~ 1e-19
    in float32 and 1e-160 in float64)."""
    import mpmath

    lo = -37 if dtype == jnp.float32 else -299
    c = np.concatenate(
        [
            [1.0, 1.0 - 1e-6],
            1.0 - np.logspace(-3, -0.5, 9),
            np.logspace(-1, lo, 60),
            2.0 / np.sqrt(4.0 + 1e8) * np.array([0.999, 1.0, 1.001]),
        ]
    )
    c = np.asarray(c, dtype)
    x = np.asarray(T.incidence_variable(jnp.asarray(c)), np.float64)
    mpmath.mp.dps = 40
    ref = []
    for ci in np.asarray(c, np.float64):
        cm = mpmath.mpf(float(ci))
        ref.append(float(mpmath.asinh(2 * mpmath.sqrt((1 - cm) * (1 + cm)) / cm)))
    ref = np.array(ref)
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(x, ref, rtol=4 * eps, atol=4 * eps)
    d = np.asarray(jax.vmap(jax.grad(T.incidence_variable))(jnp.asarray(c)), np.float64)
    assert np.all(np.isfinite(d)) and d[0] == 0.0
    c64 = np.asarray(c, np.float64)[1:]
    s = np.sqrt((1 - c64) * (1 + c64))
    want = -2.0 / (s * c64 * np.sqrt(c64**2 + 4 * s**2))
    keep = np.isfinite(want) & (np.abs(want) < float(jnp.finfo(dtype).max) / 10)
    rtol = 1e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_allclose(d[1:][keep], want[keep], rtol=rtol)


def test_float32_matches_float64():
    rng = np.random.default_rng(11)
    nrm, k, kp, fi, fo = random_geometry(rng, 64, 2e-4)
    m = np.exp(rng.uniform(np.log(0.05), np.log(100.0), 64))
    out = {}
    for dt, cdt in ((np.float64, np.complex128), (np.float32, np.complex64)):
        mat = Material(n=jnp.asarray(np.full(64, AL), cdt), m=jnp.asarray(m, dt))
        a = [jnp.asarray(x, dt) for x in (k, kp, nrm, fi, fo)]
        out[dt] = np.asarray(_table(a[0], a[1], a[2], mat, a[3], a[4]))
    scale = np.abs(out[np.float64][:, 0, 0])[:, None, None]
    # rows whose double term is below float32's range (grazing at large m: 4e-85 here) are 0
    # in float32; the others agree to 1e-4 of their M00
    ok = scale > 1e-30
    err = np.abs(out[np.float32] - out[np.float64]) / scale
    assert np.max(np.where(ok, err, 0.0)) < 1e-4
    assert np.all(np.abs(np.where(ok, 0.0, out[np.float32])) <= 1e-30)


def test_reciprocity_and_realizability():
    """Exact backscatter: reciprocity M(frames fo, fi) = Q M(fi, fo)^T Q (Q = diag(1, 1, -1,
    1), tests/test_brdf.py) holds through the table's frame handling, and the interpolated
    matrices stay physically realizable (Cloude coherency eigenvalues >= -1e-6 M00)."""
    rng = np.random.default_rng(5)
    nrm, k, _, fi, fo = random_geometry(rng, 24, 0.0)
    fo = unit(np.cross(k, rng.normal(size=k.shape)))
    mat = Material(
        n=jnp.asarray(np.array([AL, TIO2, AU] * 8)), m=jnp.asarray(np.geomspace(0.02, 80, 24))
    )
    M = np.asarray(_table(k, k, nrm, mat, fi, fo))
    Mr = np.asarray(_table(k, k, nrm, mat, fo, fi))
    Q = np.diag([1.0, 1.0, -1.0, 1.0])
    scale = np.abs(M[:, 0, 0])[:, None, None]
    assert np.max(np.abs(Mr - Q @ np.swapaxes(M, -1, -2) @ Q) / scale) < 1e-9
    eig = np.asarray(cloude_eigenvalues(M))  # tested against its definition in test_polarimetry
    assert np.all(eig[:, -1] > -1e-6 * M[:, 0, 0]), (eig[:, -1] / M[:, 0, 0]).min()


def test_quadrature_term_is_the_double_term_without_the_table_branch():
    """``"double:quadrature"`` is what ``"double"`` runs on a batch that is not all within
    PSI_MAX of backscatter (equal to rounding, eager and traced), and a traced call of it holds
    no dispatching ``lax.cond`` (the table branch is neither compiled nor differentiated;
    tests/test_grazing.py differentiates the quadrature on the stiff set). A concrete
    bistatic sensor gets it from ``sensor_terms`` (a monostatic one the table); naming two
    double terms is an error."""
    import ppr
    from ppr.pulse._pulse import sensor_terms

    rng = np.random.default_rng(5)
    nrm, k, kp, fi, fo = random_geometry(rng, 8, 0.3)
    mat = Material(n=AL, m=3.0)

    def call(names):
        def f(a, b, m):
            return mueller_brdf(
                a, b, nrm, Material(n=AL, m=m), terms=names, frame_in=fi, frame_out=fo
            )

        return f

    quad = np.asarray(call(("double:quadrature",))(k, kp, 3.0))
    tol = dict(rtol=1e-9, atol=1e-12 * np.abs(quad[:, 0, 0]).max())  # program rounding
    np.testing.assert_allclose(quad, np.asarray(call(("double",))(k, kp, 3.0)), **tol)
    conds = {
        names: str(jax.make_jaxpr(call(names))(k, kp, 3.0)).count("cond[")
        for names in (("double",), ("double:quadrature",), ("double:backscatter",))
    }
    # the traced checks' conds are common to all three; "double" adds its dispatch
    assert conds[("double:quadrature",)] == conds[("double:backscatter",)], conds
    assert conds[("double",)] == conds[("double:quadrature",)] + 1, conds
    traced = jax.jit(call(("double:quadrature",)))(k, kp, 3.0)
    np.testing.assert_allclose(np.asarray(traced), quad, **tol)

    bi = ppr.Sensor.make((0.0, 0.0, -1.0), bistatic_angle=0.05)
    mono = ppr.Sensor.make((0.0, 0.0, -1.0))
    assert sensor_terms(mueller_brdf, None, bi) == ("single", "double:quadrature", "multiple")
    assert sensor_terms(mueller_brdf, None, mono) == ("single", "double:backscatter", "multiple")
    assert sensor_terms(mueller_brdf, "auto", bi) == "auto"  # its run-time skip is kept
    with pytest.raises(ValueError, match="same term"):
        mueller_brdf(k, kp, nrm, mat, terms=("double", "double:quadrature"))


def test_brdf_routing_and_errors():
    """mueller_brdf's "double" uses the table when the whole batch is within PSI_MAX of
    backscatter; "double:backscatter" refuses larger bistatic angles naming the argument;
    render's choice of terms for ppr.mueller_brdf."""
    rng = np.random.default_rng(2)
    nrm, k, _, fi, _ = random_geometry(rng, 8, 0.0)
    mat = Material(n=AL, m=3.0)
    via_brdf = np.asarray(
        mueller_brdf(k, k, nrm, mat, terms=("double",), frame_in=fi, frame_out=fi)
    )
    table = np.asarray(_table(k, k, nrm, mat, fi, fi))
    np.testing.assert_allclose(via_brdf, table, rtol=1e-9, atol=0)
    ax = unit(np.cross(k, rng.normal(size=k.shape)))
    # k_out a different array within PSI_MAX (the general kernel; the branch is picked on the
    # host for concrete inputs): the table, not the quadrature (which differs by ~1e-4 here)
    kn = unit(np.cos(0.5 * T.PSI_MAX) * k + np.sin(0.5 * T.PSI_MAX) * ax)
    fo = unit(np.cross(kn, np.cross(fi, kn)))
    via_brdf = mueller_brdf(k, kn, nrm, mat, terms=("double",), frame_in=fi, frame_out=fo)
    table = np.asarray(_table(k, kn, nrm, mat, fi, fo))
    np.testing.assert_allclose(np.asarray(via_brdf), table, rtol=1e-9, atol=0)
    psi = 3.0 * T.PSI_MAX
    kp = unit(np.cos(psi) * k + np.sin(psi) * ax)
    kp = np.where(
        np.sum(kp * nrm, -1, keepdims=True) > 0, kp, unit(np.cos(psi) * k - np.sin(psi) * ax)
    )
    with pytest.raises(ValueError, match="k_out.*PSI_MAX"):
        mueller_brdf(k, kp, nrm, mat, terms=("double:backscatter",))
    with pytest.raises(ValueError, match="same term"):
        mueller_brdf(k, k, nrm, mat, terms=("double", "double:backscatter"))
    assert backscatter_terms(mueller_brdf, None) == ("single", "double:backscatter", "multiple")
    assert backscatter_terms(mueller_brdf, "auto") == ("single", "double:backscatter", "multiple")
    assert backscatter_terms(mueller_brdf, ("single",)) is None
    assert backscatter_terms(lambda *a, **kw: None, None) is None


def test_cut_above_m_max_is_negligible():
    """Above M_MAX the table returns 0. At m = M_MAX the quadrature's double term is below
    1e-30 of the rest of the BRDF (single + multiple; at large incidence the single bounce
    is as small as the double, the depolarizing remainder is not) at exact backscatter for
    incidence 0-85 deg."""
    th = np.radians(np.linspace(0.0, 85.0, 12))
    k = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    z = np.broadcast_to([0.0, 0.0, 1.0], k.shape)
    e = np.broadcast_to([0.0, 1.0, 0.0], k.shape)
    mat = Material(n=AL, m=T.M_MAX)
    dbl = np.asarray(_quadrature(REF_ORDER, True)(k, k, z, mat, e, e))[:, 0, 0]
    rest = np.asarray(mueller_brdf(k, k, z, mat, terms=("single", "multiple")))[:, 0, 0]
    assert np.all(dbl <= 1e-30 * rest), (dbl / rest).max()


def test_one_material_paths_agree():
    """One material for the whole batch has two evaluation orders of the same linear
    interpolation: from ``ONE_MATERIAL_MIN_BATCH`` elements up, the table's rows are
    contracted with the material once and interpolated in incidence only
    (``_interp_one_material``); smaller batches (a few facets per MCMC walker) gather their own
    rows. Both must equal the per-element-material evaluation to rounding (float64), in
    values and in the gradient with respect to m and n (which flow through the contraction
    in the first order and through the per-element rows in the others)."""
    rng = np.random.default_rng(11)
    n_rows = 2 * T.ONE_MATERIAL_MIN_BATCH
    nrm, k, _, fi, _ = random_geometry(rng, n_rows, 0.0)
    small = T.ONE_MATERIAL_MIN_BATCH // 4

    def total(mv, nv, sl):
        mat = Material(n=nv, m=mv)
        return _table(k[sl], k[sl], nrm[sl], mat, fi[sl], fi[sl])

    def summed(mv, nv, kk, nn, ff):
        out = T.double_backscatter_term(kk, kk, nn, Material(n=nv, m=mv), ff, ff)
        return jnp.sum(out[..., :2, :])

    grad = jax.jit(jax.grad(summed, argnums=(0, 1)))
    for n_idx, m in ((AL, 0.7), (TIO2, 12.0)):
        one = (jnp.asarray(m), jnp.asarray(n_idx, jnp.complex128))
        per = (jnp.full(n_rows, m), jnp.full(n_rows, n_idx, jnp.complex128))
        whole = np.asarray(total(*one, slice(None)))
        ref = np.asarray(total(*per, slice(None)))
        chunks = np.concatenate(
            [np.asarray(total(*one, slice(a, a + small))) for a in range(0, n_rows, small)]
        )
        scale = np.abs(ref[:, :1, :1]).max()
        assert scale > 0
        np.testing.assert_allclose(whole / scale, ref / scale, rtol=0, atol=1e-12)
        np.testing.assert_allclose(chunks / scale, ref / scale, rtol=0, atol=1e-12)
        g_whole = grad(*one, k, nrm, fi)
        g_small = [grad(*one, k[a:a + small], nrm[a:a + small], fi[a:a + small])
                   for a in range(0, n_rows, small)]
        for i in range(2):
            got = complex(g_whole[i])
            want = complex(sum(complex(g[i]) for g in g_small))
            assert abs(got - want) <= 1e-10 * abs(want), (i, got, want)
