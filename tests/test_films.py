"""Thin-film stacks on microfacets (ppr/optics/_films.py, docs/physics/thin_films.md).

References are independent of the library: a NumPy transfer matrix of the forward and backward
field amplitudes in every layer (continuity of the tangential fields, its own p convention
written with the magnetic field), brute-force lobe averages by quadrature over the exact
Blinn-Phong facet-tilt distribution, and closed forms.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppr
from ppr.brdf import _brdf
from ppr.optics import _films
from ppr.optics._films import Films, facet_components, facet_gram, facet_params, stack_amplitudes
from ppr.optics._fresnel import fresnel_amplitudes_re

LAM = 532e-9
ANGLES = np.radians(np.array([0.0, 10.0, 30.0, 45.0, 60.0, 75.0, 85.0, 89.0]))

STACKS = {
    # substrate, layers (outermost first)
    "single": (1.52 + 0j, [(1.38 + 0j, 97e-9)]),
    "double": (1.52 + 0j, [(1.38 + 0j, 97e-9), (2.3 + 0j, 60e-9)]),
    "absorbing": (0.94 + 6.42j, [(2.0 + 0.1j, 80e-9), (1.7 + 0.0015j, 2e-6)]),
    "ar_silicon": (4.1366 + 0.0338j, [(2.0559 + 0j, 75e-9)]),
    "metal_film": (1.46 + 0j, [(0.054 + 3.43j, 20e-9)]),
}


# --------------------------------------------------------------------------- NumPy reference


def _tmm(n_sub, layers, lam, theta, pol):
    """Reflection, transmission and the z-flux at each boundary (normalized to the incident
    flux) by forward/backward amplitudes in each medium; p written with ``H_y = n (a + b)``
    and ``E_x = (w/n)(a - b)`` (``a``, ``b`` electric amplitudes)."""
    s = math.sin(theta)
    ns = [1.0 + 0j] + [complex(n) for n, _ in layers] + [complex(n_sub)]
    ts = [0.0] + [t for _, t in layers] + [0.0]
    ws = []
    for n in ns:
        w = np.sqrt(n * n - s * s + 0j)
        ws.append(w if w.imag >= 0 else -w)
    k0 = 2 * math.pi / lam

    def fields(j, a, b):
        if pol == "s":
            return np.array([a + b, ws[j] * (a - b)])
        return np.array([ns[j] * (a + b), ws[j] / ns[j] * (a - b)])

    def amplitudes(j, f):
        if pol == "s":
            u, v = f[0], f[1] / ws[j]
        else:
            u, v = f[0] / ns[j], f[1] * ns[j] / ws[j]
        return (u + v) / 2, (u - v) / 2

    def flux(j, a, b):
        if pol == "s":
            return np.real((a + b) * np.conj(ws[j] * (a - b)))
        return np.real(ws[j] / ns[j] * (a - b) * np.conj(ns[j] * (a + b)))

    N = len(ns)
    f = fields(N - 1, 1.0 + 0j, 0j)
    inside = {}
    for j in range(N - 2, 0, -1):
        ab, bb = amplitudes(j, f)
        ph = np.exp(1j * k0 * ws[j] * ts[j])
        at, bt = ab / ph, bb * ph
        inside[j] = (flux(j, at, bt), flux(j, ab, bb))
        f = fields(j, at, bt)
    a0, b0 = amplitudes(0, f)
    inc = math.cos(theta) * abs(a0) ** 2
    absorbed = sum((top - bot) / inc for top, bot in inside.values())
    return b0 / a0, 1 / a0, absorbed


def _mk(layers, lam=LAM, m=300.0, mode="coherent", thick=-1, dt=jnp.float64):
    return Films(
        tuple(jnp.asarray(complex(n).real, dt) for n, _ in layers),
        tuple(jnp.asarray(complex(n).imag, dt) for n, _ in layers),
        tuple(jnp.asarray(2 * math.pi * t / lam, dt) for _, t in layers),
        jnp.asarray(m, dt),
        mode=mode,
        thick=thick,
    )


def _amps(n_sub, layers, cos_t, **kw):
    f = _mk(layers, **kw)
    n = complex(n_sub)
    rs_re, rs_im, rp_re, rp_im = stack_amplitudes(
        jnp.asarray(n.real), jnp.asarray(n.imag), f, jnp.asarray(cos_t)
    )
    return np.asarray(rs_re + 1j * rs_im), np.asarray(rp_re + 1j * rp_im)


# --------------------------------------------------------------------------- coherent stacks


@pytest.mark.parametrize("name", sorted(STACKS))
def test_stack_matches_numpy_transfer_matrix(name):
    # 0-89 deg, single, double, absorbing and metal-film stacks; float64 rounding level
    n_sub, layers = STACKS[name]
    rs, rp = _amps(n_sub, layers, np.cos(ANGLES))
    ref_s = np.array([_tmm(n_sub, layers, LAM, t, "s")[0] for t in ANGLES])
    ref_p = np.array([_tmm(n_sub, layers, LAM, t, "p")[0] for t in ANGLES])
    np.testing.assert_allclose(rs, ref_s, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rp, ref_p, rtol=0, atol=1e-13)


def test_closed_forms():
    c = np.cos(ANGLES)
    bare = [
        np.asarray(a)
        for a in fresnel_amplitudes_re(jnp.asarray(1.52), jnp.asarray(0.0), jnp.asarray(c))
    ]
    bare_s, bare_p = bare[0] + 1j * bare[1], bare[2] + 1j * bare[3]
    # quarter wave of index sqrt(n_0 n_s) on glass: no reflection at normal incidence
    n1 = math.sqrt(1.52)
    rs, rp = _amps(1.52, [(n1, LAM / (4 * n1))], 1.0)
    assert abs(rs) < 1e-15 and abs(rp) < 1e-15
    # half wave: the bare substrate at normal incidence (any layer index)
    for n_layer in (1.38, 2.3):
        rs, rp = _amps(1.52, [(n_layer, LAM / (2 * n_layer))], 1.0)
        assert rs == pytest.approx(bare_s[0], abs=1e-15)
        assert rp == pytest.approx(bare_p[0], abs=1e-15)
    # zero thickness, or a layer index-matched to the substrate: the bare substrate, 0-89 deg
    for layers in ([(2.3, 0.0)], [(0.054 + 3.43j, 0.0), (1.38, 0.0)], [(1.52, 3e-6)]):
        rs, rp = _amps(1.52, layers, c)
        np.testing.assert_allclose(rs, bare_s, rtol=0, atol=1e-15)
        np.testing.assert_allclose(rp, bare_p, rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", ["single", "double", "metal_film"])
def test_energy_balance(name):
    # R + T + A = 1: T from the same recursion (forward star product); lossless stacks have
    # A = 0, absorbing ones the absorbed power of the reference's Poynting flux per layer
    n_sub, layers = STACKS[name]
    f = _mk(layers)
    c = np.cos(ANGLES)
    r_s, r_p, t_s, t_p = _films.stack_transmission(
        jnp.asarray(n_sub.real), jnp.asarray(n_sub.imag), f, jnp.asarray(c)
    )
    w_sub = np.sqrt(n_sub**2 - np.sin(ANGLES) ** 2 + 0j).real
    lossless = all(complex(n).imag == 0 for n, _ in layers)
    for pol, r, t in (("s", r_s, t_s), ("p", r_p, t_p)):
        R = np.asarray(r[0] ** 2 + r[1] ** 2)
        T = w_sub / c * np.asarray(t[0] ** 2 + t[1] ** 2)
        A = np.array([_tmm(n_sub, layers, LAM, th, pol)[2] for th in ANGLES])
        if lossless:
            np.testing.assert_allclose(R + T, 1.0, rtol=0, atol=1e-13)
        else:
            assert np.all(A > 1e-4)  # 20 nm of silver absorbs 2.4 % at normal incidence
            np.testing.assert_allclose(1.0 - R - T, A, rtol=0, atol=1e-13)


# --------------------------------------------------------------------------- BRDF terms


def _mirror_geometry(theta):
    k = np.stack([np.sin(theta), 0 * theta, np.cos(theta)], -1)
    kp = np.stack([-np.sin(theta), 0 * theta, np.cos(theta)], -1)
    return k, kp, np.array([0.0, 0.0, 1.0])


def _mueller_of(rs, rp):
    a = 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)
    b = 0.5 * (abs(rs) ** 2 - abs(rp) ** 2)
    x = rs * np.conj(rp)
    M = np.zeros(np.shape(rs) + (4, 4))
    M[..., 0, 0] = M[..., 1, 1] = a
    M[..., 0, 1] = M[..., 1, 0] = b
    M[..., 2, 2] = M[..., 3, 3] = x.real
    M[..., 2, 3] = x.imag
    M[..., 3, 2] = -x.imag
    return M


def test_single_term_specular_is_coated_reflectance_times_bare_factor():
    # specular geometry (h = n): the facet is the macro-surface, the single term is the
    # Fresnel Mueller matrix of the facet times a material-independent scalar of the lobe and
    # shadowing; coating changes only the Mueller matrix (reference: NumPy transfer matrix)
    th = np.radians(np.array([5.0, 30.0, 55.0, 80.0]))
    k, kp, z = _mirror_geometry(th)
    n_sub, layers = STACKS["ar_silicon"]
    bare = ppr.Material(n_sub, 300.0)
    coated = ppr.Material(n_sub, 300.0, films=layers, wavelength=LAM)
    mb = np.asarray(ppr.mueller_brdf(k, kp, z, bare, terms=("single",), wavelength=LAM))
    mc = np.asarray(ppr.mueller_brdf(k, kp, z, coated, terms=("single",), wavelength=LAM))
    fb = _mueller_of(*_tmm_amps(n_sub, [], th))
    fc = _mueller_of(*_tmm_amps(n_sub, layers, th))
    scal = mb[:, 0, 0] / fb[:, 0, 0]
    np.testing.assert_allclose(mb, scal[:, None, None] * fb, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(mc, scal[:, None, None] * fc, rtol=1e-12, atol=1e-15)
    assert np.all(np.abs(mc - mb).max(axis=(1, 2)) > 1e-3 * mb[:, 0, 0])  # the coating shows


def _tmm_amps(n_sub, layers, th):
    rs = np.array([_tmm(n_sub, layers, LAM, t, "s")[0] for t in th])
    rp = np.array([_tmm(n_sub, layers, LAM, t, "p")[0] for t in th])
    return rs, rp


def test_bare_materials_take_the_existing_program(monkeypatch):
    # films=() never reaches the film code: tracing every BRDF term of a bare material with
    # the film kernels replaced by a failure succeeds (values then come from the same
    # Fresnel program as before the film stacks existed)
    def boom(*a, **k):
        raise AssertionError("film code traced for a bare material")

    for name in ("facet_gram", "facet_params", "facet_components", "facet_amplitudes"):
        monkeypatch.setattr(_films, name, boom)
    monkeypatch.setattr(_films, "stack_amplitudes", boom)
    monkeypatch.setattr(_brdf, "facet_params", boom)
    mat = ppr.Material(0.94 + 6.42j, 30.0)
    assert mat.films == () and mat.wavelength is None
    assert len(jax.tree.leaves(mat)) == 3  # n, m, corr_length: the pytree of before
    k = jnp.asarray([[0.3, 0.0, math.sqrt(1 - 0.09)]])
    kp = jnp.asarray([[-0.2, 0.1, math.sqrt(1 - 0.05)]])
    z = jnp.asarray([[0.0, 0.0, 1.0]])
    core = _brdf._brdf_core.__wrapped__
    for names, mono, ko in [
        (("single", "multiple", "double:quadrature"), False, kp),
        (("single", "multiple", "double"), True, k),
        (("double:backscatter",), False, k),
    ]:
        jax.make_jaxpr(
            lambda a, b, c, mt, names=names, mono=mono: core(
                a, b, c, mt, None, None, LAM, names=names, mono=mono
            )
        )(k, ko, z, mat)


def test_zero_thickness_and_stacked_parts_equal_bare():
    # a zero-thickness layer is no layer, in every term at exact backscatter (single,
    # multiple with its Fresnel average, the double term's table), to float64 rounding
    th = np.radians(np.array([3.0, 40.0, 70.0]))
    k = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    z = np.array([0.0, 0.0, 1.0])
    bare = ppr.Material(0.94 + 6.42j, 30.0)
    zero = ppr.Material(0.94 + 6.42j, 30.0, films=((1.7, 0.0), (2.0, 0.0)), wavelength=LAM)
    ref = np.asarray(ppr.mueller_brdf(k, k, z, bare, wavelength=LAM))
    got = np.asarray(ppr.mueller_brdf(k, k, z, zero, wavelength=LAM))
    assert np.abs(got - ref).max() / np.abs(ref[:, 0, 0]).min() < 1e-12
    # parts stacked into one batch (MLI: lobe, thick layer 0; AR cell: coherent; bare
    # aluminium) keep their facet reflection: padding layers are exact (vacuum on top, the
    # substrate's index at the bottom, a vacuum thick slot); bare parts to rounding
    c = jnp.asarray(np.cos(ANGLES))
    parts = [
        ppr.load_material(name, LAM, dtype=jnp.float64)
        for name in ("mli_kapton_aluminium", "solar_cell_si_ar", "aluminium")
    ]
    st = ppr.stack_materials(parts)
    assert (st.film_mode, st.thick_layer, len(st.films)) == ("lobe", 0, 2)
    fl = jax.tree.map(lambda a: a[:, None], _films_of(st))
    got = np.array(facet_params(jnp.real(st.n)[:, None], jnp.imag(st.n)[:, None], c[None], fl))
    for i, part in enumerate(parts):
        ref = np.array(facet_params(jnp.real(part.n), jnp.imag(part.n), c, _films_of(part)))
        tol = 0.0 if i == 0 else 1e-15  # MLI: bottom padding is exact; the others: rounding
        assert np.abs(got[:, i] - ref).max() <= tol, (i, np.abs(got[:, i] - ref).max())


# --------------------------------------------------------------------------- thick films


def _brute_lobe_gram(nf, t, n_sub, lam, m, c0, nu=1500, nphi=96):
    """The lobe average of ``r_x r_y^*`` for one film on a substrate: facet tilts with
    ``cos beta = u^(1/(m+1))`` (u uniform: the Blinn-Phong density exactly), uniform azimuth,
    back-facing tilts left out; the film's phase at the tilted facet, the interfaces at the
    nominal one (the lobe mode's model)."""
    kt = 2 * math.pi * t / lam
    u = (np.arange(nu) + 0.5) / nu
    cb = u ** (1.0 / (m + 1.0))
    sb = np.sqrt(1 - cb * cb)
    ph = (np.arange(nphi) + 0.5) / nphi * math.pi
    s0 = math.sqrt(1 - c0 * c0)
    cp = c0 * cb[:, None] + s0 * sb[:, None] * np.cos(ph)[None, :]
    wgt = (cp > 0).astype(float)
    cp = np.clip(cp, 1e-9, 1.0)

    def w_of(n, c):
        w = np.sqrt(n * n - 1 + c * c + 0j)
        return np.where(w.imag < 0, -w, w)

    w0, w1, w2 = c0 + 0j, w_of(nf, c0), w_of(n_sub, c0)
    e1, e2 = nf * nf, n_sub * n_sub
    r01 = ((w0 - w1) / (w0 + w1), (e1 * w0 - w1) / (e1 * w0 + w1))
    r12 = ((w1 - w2) / (w1 + w2), (e2 * w1 - e1 * w2) / (e2 * w1 + e1 * w2))
    zt = np.exp(2j * kt * w_of(nf, cp))
    rs, rp = ((a + b * zt) / (1 + a * b * zt) for a, b in zip(r01, r12, strict=True))
    W = wgt.sum()
    return np.array(
        [
            (abs(rs) ** 2 * wgt).sum() / W,
            (abs(rp) ** 2 * wgt).sum() / W,
            (rs * np.conj(rp) * wgt).sum() / W,
        ]
    )


@pytest.mark.parametrize("m", [300.0, 1e4])
def test_thick_film_lobe_average_against_brute_force(m):
    # 50.8 um Kapton over aluminium at 1064 nm (clear film, fringes in facet angle far narrower
    # than the lobe). Measured (bench/bench_films.py): lobe mode within 4e-4 of the brute-force
    # average at 0-70 deg for m = 300 and 1e4; the incoherent sum within 2e-5 where the phase
    # spread is large (m = 300, 20-70 deg); the coherent stack off by up to 1
    nf, t, n_sub, lam = 1.66, 50.8e-6, 1.38 + 10.25j, 1064e-9
    for deg in (0.0, 20.0, 45.0, 70.0):
        c0 = math.cos(math.radians(deg))
        ref = _brute_lobe_gram(nf, t, n_sub, lam, m, c0)
        got = {}
        for mode in ("coherent", "incoherent", "lobe"):
            f = _mk([(nf, t)], lam=lam, m=m, mode=mode, thick=-1 if mode == "coherent" else 0)
            g = facet_gram(jnp.asarray(n_sub.real), jnp.asarray(n_sub.imag), jnp.asarray(c0), f)
            got[mode] = np.array([g[0], g[1], g[2] + 1j * g[3]])
        assert np.abs(got["lobe"] - ref).max() < 1e-3, (deg, got["lobe"], ref)
        if m == 300.0 and deg >= 20.0:
            assert np.abs(got["incoherent"] - ref).max() < 1e-4
            assert np.abs(got["coherent"] - ref).max() > 1e-2


def test_thick_film_components_and_vacuum_slot():
    # the two Jones components reproduce the second moments; a zero-thickness vacuum layer in
    # the thick slot makes the averaged treatments the coherent stack exactly, single and
    # double term (the Jones-component chains of ppr.brdf.double)
    n_sub, layers = 4.1366 + 0.0338j, [(1.0, 0.0), (2.0559, 75e-9)]
    c = jnp.asarray(np.cos(ANGLES))
    nr, ni = jnp.asarray(n_sub.real), jnp.asarray(n_sub.imag)
    lobe = _mk(layers, mode="lobe", thick=0)
    coh = _mk(layers[1:])
    (x1, y1), (x2, y2) = facet_components(nr, ni, c, _mk([(1.7, 50e-6)], mode="lobe", thick=0))
    g = facet_gram(nr, ni, c, _mk([(1.7, 50e-6)], mode="lobe", thick=0))
    cx = lambda a: np.asarray(a[0]) + 1j * np.asarray(a[1])  # noqa: E731
    np.testing.assert_allclose(abs(cx(x1)) ** 2 + abs(cx(x2)) ** 2, g[0], rtol=1e-12)
    np.testing.assert_allclose(abs(cx(y1)) ** 2 + abs(cx(y2)) ** 2, g[1], rtol=1e-12)
    sp = cx(x1) * np.conj(cx(y1)) + cx(x2) * np.conj(cx(y2))
    np.testing.assert_allclose(sp, np.asarray(g[2]) + 1j * np.asarray(g[3]), rtol=1e-12, atol=1e-15)
    for mode in ("lobe", "incoherent"):
        f = _mk(layers, mode=mode, thick=0)
        np.testing.assert_allclose(
            np.array(facet_params(nr, ni, c, f)), np.array(facet_params(nr, ni, c, coh)), atol=1e-15
        )
    # the double bounce's Jones chains (ppr.brdf.double._path_jones) on random two-facet paths:
    # the four component chains of the vacuum-slot stack sum to the coherent chain's coherency
    from ppr.brdf.double import _coherency_sums, _path_jones

    rng = np.random.default_rng(3)

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    kk = unit(rng.normal(size=(6, 3)) + [0, 0, 2.0])
    kp = unit(rng.normal(size=(6, 3)) + [0, 0, 2.0])
    d1 = unit(rng.normal(size=(6, 3)))
    e = unit(np.cross(kk, kp))
    sp = lambda v: tuple(jnp.asarray(v[:, i]) for i in range(3))  # noqa: E731
    nr6, ni6 = jnp.full(6, n_sub.real), jnp.full(6, n_sub.imag)
    H = []
    for f in (_mk(layers, mode="lobe", thick=0), coh):
        f6 = jax.tree.map(lambda a: jnp.broadcast_to(a, (6,)), f)
        J = _path_jones(sp(kk), sp(kp), sp(d1), sp(e), nr6, ni6, False, 1e-300, films=f6)
        w = jnp.ones(J[0][0].shape)
        H.append(
            np.asarray(
                _coherency_sums(w[None], tuple((a[0][None], a[1][None]) for a in J), axes=-1)
            )
        )
    assert H[0].shape == H[1].shape == (1, 16)
    np.testing.assert_allclose(H[0], H[1], rtol=1e-12, atol=1e-16)
    del lobe


# --------------------------------------------------------------------------- numerics


@pytest.mark.parametrize("dt", [jnp.float64, jnp.float32])
def test_gradients_finite_on_the_stiff_grid(dt):
    # grazing (cos = 0, 1e-6), normal, TIR inside a layer (lossless n = 0.8 under glass:
    # evanescent beyond 53 deg), absorbing and metal layers, zero thickness; coherent and
    # lobe-averaged; derivatives in every index, thickness and m
    cos_t = jnp.asarray([0.0, 1e-6, 1e-3, 0.3, 0.6, 0.61, 0.9, 1.0], dt)
    cases = [
        (1.52 + 0j, [(0.8, 300e-9), (1.38, 100e-9)], "coherent", -1),
        (0.94 + 6.42j, [(2.0 + 0.1j, 80e-9), (1.7 + 0.0015j, 0.0)], "coherent", -1),
        (0.94 + 6.42j, [(1.7 + 0.0015j, 50e-6)], "lobe", 0),
        (0.054 + 3.43j, [(2.05, 60e-9), (1.46, 200e-6)], "lobe", 1),
        (1.38 + 10.25j, [(1.66, 50e-6)], "incoherent", 0),
        (1.52 + 0j, [(0.8, 0.0), (1.46, 20e-6)], "lobe", 1),
    ]
    xs = []
    for n_sub, layers, _, _ in cases:
        x0 = [complex(n_sub).real, complex(n_sub).imag, 300.0]
        for n, t in layers:
            x0 += [complex(n).real, complex(n).imag, t * 1e6]
        xs.append(jnp.asarray(x0, dt))

    def f(x, case):
        _, layers, mode, thick = case
        L = len(layers)
        fl = Films(
            tuple(x[3 + 3 * j] for j in range(L)),
            tuple(x[4 + 3 * j] for j in range(L)),
            tuple(2 * math.pi * x[5 + 3 * j] * 1e-6 / LAM for j in range(L)),
            x[2],
            mode=mode,
            thick=thick,
        )
        a, b, c, d = facet_params(x[0], x[1], cos_t, fl)
        return jnp.sum(a + 0.3 * b + 0.7 * c + 0.2 * d)

    # eagerly, case by case: the small programs of each operation are shared by the cases
    # (one jitted gradient of all cases compiled several times slower)
    keep = range(len(cases)) if dt == jnp.float64 else (0, 3, 5)
    for i in keep:
        val, g = jax.value_and_grad(f)(xs[i], cases[i])
        assert np.isfinite(float(val)) and np.all(np.isfinite(np.asarray(g))), (cases[i], g)


def test_float32_agreement_of_the_library_stacks():
    # float32 against float64 facet parameters (a, b, c, d), 0-89 deg: the thick layers'
    # round-trip phase (1e3-7e3 rad) carries float32 rounding of ~1e-4 rad; measured at 532 nm
    # max 1.5e-5 (MLI), 3.3e-5 (OSR), 1.9e-7 (AR cell); at 1064 nm 3.5e-5 and 1.7e-4
    c64 = jnp.asarray(np.cos(ANGLES))
    for name, tol in (
        ("mli_kapton_aluminium", 1e-4),
        ("osr_silica_silver", 5e-4),
        ("solar_cell_si_ar", 1e-5),
    ):
        out = []
        for dt in (jnp.float64, jnp.float32):
            mat = ppr.load_material(name, LAM, dtype=dt)
            p = facet_params(jnp.real(mat.n), jnp.imag(mat.n), c64.astype(dt), _films_of(mat))
            assert p[0].dtype == dt
            out.append(np.array(p, np.float64))
        assert np.abs(out[1] - out[0]).max() < tol, (name, np.abs(out[1] - out[0]).max())


def test_brdf_gradient_in_thickness_and_m():
    # the single term of MLI at 1064 nm: d/dt and d/dm (forward mode) finite
    # at normal incidence, oblique and 6e-5 deg from grazing; d/dt against a central
    # difference (the fringes' remainder after the lobe average: ~1/um)
    th = np.radians(np.array([0.0, 30.0, 60.0, 90.0 - 5.7e-5]))
    k = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    kp = np.stack([np.sin(th) * 0.9, 0.1 + 0 * th, np.cos(th)], -1)
    kp = kp / np.linalg.norm(kp, axis=-1, keepdims=True)
    z = np.array([0.0, 0.0, 1.0])
    mat = ppr.load_material("mli_kapton_aluminium", 1064e-9, "brushed", dtype=jnp.float64)

    def f(x):
        mt = ppr.Material(
            mat.n,
            x[1],
            films=((mat.films[0][0], x[0] * 1e-6),),
            wavelength=1064e-9,
            film_mode="lobe",
            thick_layer=0,
        )
        M = ppr.mueller_brdf(
            k, kp, z, mt, terms=("single",), wavelength=1064e-9, traced_checks=False
        )
        return M[:, 0, 0] + M[:, 1, 2] + M[:, 3, 3]

    # one forward-mode program along (dt [um], dm) = (1, 30): finite, and equal to a central
    # difference of the same program's values
    x0 = jnp.asarray([float(mat.films[0][1]) * 1e6, float(mat.m)])
    v = jnp.asarray([1.0, 30.0])
    fj = jax.jit(lambda x: jax.jvp(f, (x,), (v,)))
    val, tan = fj(x0)
    assert np.all(np.isfinite(np.asarray(tan))) and np.all(np.isfinite(np.asarray(val)))
    h = 1e-4
    fd = (fj(x0 + h * v)[0] - fj(x0 - h * v)[0]) / (2 * h)
    np.testing.assert_allclose(np.asarray(tan), np.asarray(fd), rtol=1e-4, atol=1e-9)


# --------------------------------------------------------------------------- materials


def test_library_coated_materials_and_modes():
    for wl in (532e-9, 1064e-9):
        mli = ppr.load_material("mli_kapton_aluminium", wl)
        osr = ppr.load_material("osr_silica_silver", wl)
        ar = ppr.load_material("solar_cell_si_ar", wl)
        assert (mli.film_mode, mli.thick_layer) == ("lobe", 0)
        assert (osr.film_mode, osr.thick_layer) == ("lobe", 0)
        assert (ar.film_mode, ar.thick_layer) == ("coherent", -1)
        for mat, sub in ((mli, "aluminium"), (osr, "silver"), (ar, "silicon")):
            assert complex(mat.n) == complex(ppr.load_material(sub, wl).n)
            assert float(mat.wavelength) == pytest.approx(wl)
        for name in ("mli_kapton_aluminium", "osr_silica_silver", "solar_cell_si_ar"):
            for _, idx, layer in ppr.materials.film_entries(name, wl):
                assert len(idx.source) > 10 and len(layer.source) > 10
    # AR coating: a quarter wave near 600 nm lowers the normal-incidence reflectance of
    # silicon at 532 nm from ~37 % to a few per cent
    ar = ppr.load_material("solar_cell_si_ar", 532e-9)
    a_bare = float(ppr.fresnel_mueller_params(4.1366, 0.0338, 1.0)[0])
    a_ar = float(facet_params(jnp.real(ar.n), jnp.imag(ar.n), 1.0, _films_of(ar))[0])
    assert a_bare > 0.35 and a_ar < 0.05


def _films_of(mat):
    return _films.films_of(mat, mat.dtype)


def test_bad_films_are_errors_naming_the_field():
    with pytest.raises(ValueError, match=r"films\[0\] thickness"):
        ppr.Material(1.5, 10.0, films=((1.38, -1e-9),), wavelength=LAM)
    with pytest.raises(ValueError, match=r"films\[1\] index"):
        ppr.Material(1.5, 10.0, films=((1.38, 1e-7), (1.4 - 0.1j, 1e-7)), wavelength=LAM)
    with pytest.raises(ValueError, match="wavelength"):
        ppr.Material(1.5, 10.0, films=((1.38, 1e-7),))
    with pytest.raises(ValueError, match="film_mode"):
        ppr.Material(1.5, 10.0, films=((1.38, 1e-7),), wavelength=LAM, film_mode="thick")
    with pytest.raises(ValueError, match="thick_layer"):
        ppr.Material(1.5, 10.0, films=((1.7, 50e-6), (1.46, 100e-6)), wavelength=LAM)
    with pytest.raises(ValueError, match="white"):
        ppr.Material(1.5, 10.0, white=True, films=((1.38, 1e-7),), wavelength=LAM)
    mat = ppr.Material(1.5, 10.0, films=((1.38, 1e-7),), wavelength=LAM)
    k = np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="material.wavelength"):
        ppr.mueller_brdf(k, k, k, mat, wavelength=1064e-9)
    two = ppr.Material(
        1.5, 10.0, films=((1.7, 50e-6), (1.46, 100e-6)), wavelength=LAM, thick_layer=1
    )
    assert (two.film_mode, two.thick_layer) == ("lobe", 1)


# --------------------------------------------------------------------------- inversion


@pytest.mark.slow
def test_thickness_is_fitted_with_its_cramer_rao_bound():
    # a cube coated with 120 nm of silicon nitride on silicon, seen by the simulator with the
    # polarizing stand-in BRDF (the stack's Fresnel matrix in the beam frames): the refiner
    # recovers the thickness from noise-free counts (from 105 nm: the normal-incidence
    # reflectance rises monotonically from the quarter wave at 65 nm to the half wave at
    # 129 nm), the Cramer-Rao bound of the thickness equals 1 / sqrt(Fisher) from central
    # differences of the expected counts, and the sampler's log posterior peaks at the truth
    from inversion._mcmc import PriorConfig, make_log_prob
    from inversion._noise import MeasurementModel
    from inversion._params import Parametrisation
    from inversion._refine import PoissonNoise, SimulatorModel, cramer_rao, refine
    from ppr.pulse import glossy_fresnel_mueller

    mat = ppr.Material(4.1366 + 0.0338j, 30.0, films=((2.0559, 120e-9),), wavelength=LAM)
    scene = ppr.Scene(
        ppr.shapes.cubesat(1),
        (mat,),
        ppr.Pose([1.0, 0.0, 0.0, 0.0]),
        ppr.Sensor.make(),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.01, 24),
    )
    chm = MeasurementModel.preset("stokes").channel_matrix()
    model = SimulatorModel(scene, chm, brdf=glossy_fresnel_mueller, dense=True)
    assert model.film_slots == (0,) and model.film_thickness[0] == pytest.approx(120e-9)
    q = np.asarray(quat := [0.9, 0.35, 0.25, 0.05]) / np.linalg.norm(quat)
    truth = model.physical_params(q, [30.0], [4.1366 + 0.0338j], gain=1e10)
    data = model.expected(truth, model.prepare(truth))
    # at exact backscatter the single-bounce facet is seen at normal incidence whatever its
    # tilt: a coating only scales (and for c, d: re-phases) that reflectance, so thickness and
    # gain are degenerate in this model; the bound says so, and the fit holds the gain
    assert cramer_rao(model, truth, free=("gain", "thickness")).condition > 1e12
    free = ("thickness",)
    start = eqx_replace(truth, thickness=jnp.asarray([105e-9]))
    res = refine(model, data, [start], noise=PoissonNoise(floor=1.0), free=free)
    assert res.success, res.summary()
    assert float(res.params.thickness[0]) == pytest.approx(120e-9, rel=1e-6)
    crb = cramer_rao(model, truth, free=("thickness",))
    assert crb.labels == ["thickness[0] [m]"]
    mu = lambda t: np.asarray(  # noqa: E731
        model.expected(eqx_replace(truth, thickness=jnp.asarray([t])), model.prepare(truth))
    )
    h = 1e-11
    d = (mu(120e-9 + h) - mu(120e-9 - h)) / (2 * h)
    m0 = mu(120e-9)
    on = m0 > 0  # empty bins carry no information (and d = 0 there)
    sigma_fd = 1.0 / math.sqrt(float(np.sum(d[on] ** 2 / m0[on])))
    assert crb.sigma[0] == pytest.approx(sigma_fd, rel=1e-4)
    assert 0 < crb.sigma[0] < 2e-8  # 7.4 nm from ~370 counts
    par = Parametrisation(truth, free=free)
    lp = make_log_prob(model, data, par, PriorConfig(), noise=PoissonNoise(floor=1.0))
    th0 = np.asarray(par.from_physical(truth))
    steps = np.array([0.0, 5.0, -5.0]) * crb.sigma[0] / 120e-9  # log-thickness offsets
    thetas = th0[None, :] + steps[:, None]
    vals = lp(thetas)
    assert np.all(np.isfinite(vals)) and vals[0] > vals[1] and vals[0] > vals[2]


def eqx_replace(phys, **kw):
    import equinox as eqx

    names = list(kw)
    return eqx.tree_at(lambda p: [getattr(p, k) for k in names], phys, [kw[k] for k in names])
