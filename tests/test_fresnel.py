"""Fresnel coefficients, Fresnel Mueller parameters, frame rotations and the facet helpers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr.optics._frames import (
    default_frame,
    facet_jones_in_beam_frames,
    facet_mueller_in_beam_frames,
    facet_mueller_rows,
    jones_rotator,
    jones_to_mueller,
    mueller_from_params,
    mueller_rotator,
    rotation_cos_sin,
    rotation_cos_sin_2a,
)
from ppr.optics._fresnel import fresnel_amplitudes, fresnel_amplitudes_re, fresnel_mueller_params
from ppr.optics._fresnel import fresnel_mueller_params as pol_params

RNG = np.random.default_rng(7)
METALS = [0.94 + 6.42j, 1.38 + 10.25j, 0.54 + 2.23j, 0.054 + 3.43j, 1 + 10j, 0.2 + 7j]


def ref_fresnel(n, c):
    """Independent NumPy complex-arithmetic reference (Hecht form, principal sqrt)."""
    n = np.asarray(n, complex)
    w = np.sqrt(n * n - (1 - c * c) + 0j)
    return (c - w) / (c + w), (n * n * c - w) / (n * n * c + w)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def perp(d):
    return unit(np.cross(d, RNG.normal(size=d.shape)))


# ---------------------------------------------------------------- known values


def test_normal_incidence_glass():
    rs, rp = fresnel_amplitudes(1.5, 1.0)
    R = 0.5 * (abs(complex(rs)) ** 2 + abs(complex(rp)) ** 2)
    assert R == pytest.approx(0.04, rel=1e-14)  # closed form ((n-1)/(n+1))^2, rounding only


def test_brewster_glass():
    tb = np.arctan(1.5)
    assert np.rad2deg(tb) == pytest.approx(56.31, abs=5e-3)  # quoted to 2 decimals
    rs, rp = fresnel_amplitudes(1.5, np.cos(tb))
    assert abs(complex(rp)) < 1e-15  # exact zero up to rounding
    assert abs(complex(rs)) > 0.3


@pytest.mark.parametrize("cos_t", [0.0, 1e-9, 0.3, 1.0])
def test_no_interface_no_reflection(cos_t):
    rs, rp = fresnel_amplitudes(1.0, cos_t)
    assert abs(complex(rs)) == 0.0 and abs(complex(rp)) == 0.0


def test_total_reflection_cases():
    cos_t = np.linspace(0.0, 1.0, 11)
    # purely imaginary n (lossless plasma / ideal metal): |r| = 1 at every angle
    for kappa in (0.3, 3.0, 50.0):
        rs, rp = fresnel_amplitudes(1j * kappa, cos_t)
        np.testing.assert_allclose(np.abs(rs), 1.0, rtol=1e-13)  # rounding
        np.testing.assert_allclose(np.abs(rp), 1.0, rtol=1e-13)
    # grazing: r_s = r_p = -1 for any n != 1
    for n in [1.5, 2.67, 0.5] + METALS:
        rs, rp = fresnel_amplitudes(n, 0.0)
        np.testing.assert_allclose([complex(rs), complex(rp)], [-1.0, -1.0], atol=1e-14)
    # real n < 1 beyond the critical angle (total internal reflection): |r| = 1
    n = 0.6
    c = np.linspace(0.0, np.sqrt(1 - n * n) * 0.999, 7)
    rs, rp = fresnel_amplitudes(n, c)
    np.testing.assert_allclose(np.abs(rs), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.abs(rp), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.array(rs), ref_fresnel(n, c)[0], atol=1e-12)


def test_against_complex_reference():
    ns = np.array(METALS + [1.5, 1.461, 2.67, 1.7 + 1e-3j, 0.6])
    c = np.concatenate([[0.0, 1e-6, 1.0], RNG.uniform(0, 1, 20)])
    N, C = np.meshgrid(ns, c, indexing="ij")
    rs, rp = fresnel_amplitudes(N, C)
    rs_ref, rp_ref = ref_fresnel(N, C)
    # both are ~1e-16 accurate; 1e-12 absolute allows the different sqrt/division orderings
    np.testing.assert_allclose(np.array(rs), rs_ref, atol=1e-12)
    np.testing.assert_allclose(np.array(rp), rp_ref, atol=1e-12)


def test_mueller_params_equal_jones_to_mueller():
    ns = np.array(METALS + [1.5, 0.6])
    c = RNG.uniform(0, 1, ns.shape)
    rs, rp = fresnel_amplitudes(ns, c)
    J = jnp.zeros(ns.shape + (2, 2), jnp.complex128).at[..., 0, 0].set(rs).at[..., 1, 1].set(rp)
    M_ref = jones_to_mueller(J)
    M = mueller_from_params(*fresnel_mueller_params(ns.real, ns.imag, c))
    np.testing.assert_allclose(np.array(M), np.array(M_ref), atol=1e-14)  # same algebra
    # unpolarized M00 is the scalar Fresnel reflectance
    rs_ref, rp_ref = ref_fresnel(ns, c)
    np.testing.assert_allclose(
        np.array(M[..., 0, 0]), 0.5 * (abs(rs_ref) ** 2 + abs(rp_ref) ** 2), rtol=1e-12
    )
    # the Fresnel Mueller matrix is non-depolarizing: a^2 = b^2 + c^2 + d^2
    a, b, cc, d = fresnel_mueller_params(ns.real, ns.imag, c)
    np.testing.assert_allclose(np.array(a**2), np.array(b**2 + cc**2 + d**2), atol=1e-14)


# ------------------------------------------------------------------- rotations


def test_malus_law():
    # polarizer along x, then a frame rotated by a: analyzer along the new x transmits cos^2 a
    P = 0.5 * np.array([[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    s_in = np.array([1.0, 0, 0, 0])
    for a in np.linspace(0, np.pi, 7):
        R = np.array(mueller_rotator(np.cos(2 * a), np.sin(2 * a)))
        out = P @ R @ P @ s_in
        assert out[0] == pytest.approx(0.5 * np.cos(a) ** 2, abs=1e-14)  # Malus, rounding


def test_rotation_composition_and_vectors():
    a, b = 0.4, -1.3
    R = lambda t: np.array(mueller_rotator(np.cos(2 * t), np.sin(2 * t)))
    np.testing.assert_allclose(R(a) @ R(b), R(a + b), atol=1e-14)
    Jr = lambda t: np.array(jones_rotator(np.cos(t), np.sin(t)))
    np.testing.assert_allclose(Jr(a) @ Jr(b), Jr(a + b), atol=1e-14)
    # rotation_cos_sin(_2a) from vectors: frame vector rotated right-handed about d
    d = unit(RNG.normal(size=3))
    x = perp(d)
    y = np.cross(d, x)
    for t in (0.0, 0.7, -2.5, np.pi):
        x2 = np.cos(t) * x + np.sin(t) * y
        c, s = rotation_cos_sin(x, x2, d)
        assert (float(c), float(s)) == pytest.approx((np.cos(t), np.sin(t)), abs=1e-14)
        c2, s2 = rotation_cos_sin_2a(x, x2, d)
        assert (float(c2), float(s2)) == pytest.approx((np.cos(2 * t), np.sin(2 * t)), abs=1e-14)
    # Jones rotator maps to the Mueller rotator
    np.testing.assert_allclose(
        np.array(jones_to_mueller(Jr(a).astype(complex))), R(a), atol=1e-14
    )


def test_default_frame():
    normal = np.array([0.0, 0.0, 1.0])
    d = unit(np.array([[0.3, -0.2, -0.9], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1e-20, 0, 1]]))
    x = np.array(default_frame(d, normal))
    np.testing.assert_allclose(np.linalg.norm(x, axis=-1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.sum(x * d, -1), 0.0, atol=1e-14)
    np.testing.assert_allclose(x[0], unit(np.cross(normal, d[0])), atol=1e-14)
    g = jax.jit(jax.grad(lambda v: jnp.sum(default_frame(v, normal) * jnp.arange(3.0))))(
        jnp.array([0.0, 0.0, -1.0])
    )
    assert np.all(np.isfinite(g))


# --------------------------------------------------------------- facet helper


def _geometry(nb, backscatter=False):
    h = unit(RNG.normal(size=(nb, 3)))
    u = perp(h)
    t = RNG.uniform(0, 1.4, (nb, 1))
    k_in = np.cos(t) * h + np.sin(t) * u
    k_out = k_in.copy() if backscatter else 2 * np.sum(k_in * h, -1, keepdims=True) * h - k_in
    return k_in, k_out, h, perp(k_in), perp(k_out)


def test_facet_mueller_equals_rotated_jones():
    k_in, k_out, h, x_in, x_out = _geometry(16)
    n = np.array(METALS * 3)[:16]
    M = facet_mueller_in_beam_frames(n.real, n.imag, k_in, k_out, h, x_in, x_out)
    J = facet_jones_in_beam_frames(n.real, n.imag, k_in, k_out, h, x_in, x_out)
    np.testing.assert_allclose(np.array(M), np.array(jones_to_mueller(J)), atol=1e-13)
    # independent NumPy reference: R(b) F R(a) with angles from the shared s axis
    s = unit(np.cross(k_in, k_out))

    def rot(x_from, x_to, d):
        a = np.arctan2(np.sum(d * np.cross(x_from, x_to), -1), np.sum(x_from * x_to, -1))
        R = np.zeros(a.shape + (4, 4))
        R[:, 0, 0] = R[:, 3, 3] = 1
        R[:, 1, 1] = R[:, 2, 2] = np.cos(2 * a)
        R[:, 1, 2], R[:, 2, 1] = np.sin(2 * a), -np.sin(2 * a)
        return R

    rs, rp = ref_fresnel(n, np.sum(k_in * h, -1))
    F = np.zeros((16, 4, 4))
    F[:, 0, 0] = F[:, 1, 1] = (abs(rs) ** 2 + abs(rp) ** 2) / 2
    F[:, 0, 1] = F[:, 1, 0] = (abs(rs) ** 2 - abs(rp) ** 2) / 2
    F[:, 2, 2] = F[:, 3, 3] = np.real(rs * np.conj(rp))
    F[:, 2, 3] = np.imag(rs * np.conj(rp))
    F[:, 3, 2] = -F[:, 2, 3]
    M_ref = rot(s, x_out, k_out) @ F @ rot(x_in, s, -k_in)
    np.testing.assert_allclose(np.array(M), M_ref, atol=1e-13)
    # structure-of-arrays entry point with 3-tuples of components gives the same matrix
    comps = [tuple(v[:, i] for i in range(3)) for v in (k_in, k_out, h, x_in, x_out)]
    rows = jax.jit(facet_mueller_rows)(n.real, n.imag, *comps)
    np.testing.assert_allclose(np.array(rows).transpose(2, 0, 1), np.array(M), atol=1e-15)
    # realizable (Jones-derived): Cloude coherency has one eigenvalue M00, the rest ~0
    from ppr.optics.polarimetry import _COHERENCY_BASIS

    H = 0.25 * np.einsum("nij,ijab->nab", np.array(M), _COHERENCY_BASIS)
    w = np.linalg.eigvalsh(H)
    np.testing.assert_allclose(w[:, :3], 0.0, atol=1e-13)
    np.testing.assert_allclose(w[:, 3], np.array(M)[:, 0, 0], rtol=1e-12)


def test_facet_reciprocity():
    # swapping source and receiver: M(k_out, k_in) = Q M(k_in, k_out)^T Q, Q = diag(1,1,-1,1),
    # with the frames carried over (x_in <-> x_out); standard Mueller reciprocity
    k_in, k_out, h, x_in, x_out = _geometry(16)  # same shape as above: one compile
    n = 0.94 + 6.42j
    M = np.array(facet_mueller_in_beam_frames(n.real, n.imag, k_in, k_out, h, x_in, x_out))
    Mr = np.array(facet_mueller_in_beam_frames(n.real, n.imag, k_out, k_in, h, x_out, x_in))
    Q = np.diag([1.0, 1.0, -1.0, 1.0])
    np.testing.assert_allclose(Mr, Q @ np.swapaxes(M, -1, -2) @ Q, atol=1e-13)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gradients_finite_stiff_cases(dtype):
    """Gradients of the Fresnel params and of the facet Mueller matrix in n and directions are
    finite at grazing, normal incidence, n = 1, n < 1 critical angle, metals, backscatter."""
    pts = [(1.0, 0.0, 0.0), (1.0, 0.0, 1.0), (1.5, 0.0, 0.0), (1.5, 0.0, 1.0), (0.94, 6.42, 0.0),
           (1.0, 10.0, 1.0), (0.2, 7.0, 1e-6), (0.6, 0.0, 0.8), (0.054, 3.43, 0.5)]
    pts = jnp.asarray(np.array(pts, dtype))

    def f(p):
        a, b, c, d = pol_params(p[..., 0], p[..., 1], p[..., 2])
        return jnp.sum(a + 0.3 * b + 0.7 * c + 1.1 * d)

    k_in, k_out, h, x_in, x_out = (np.asarray(v, dtype) for v in _geometry(6))
    kb, _, _, xb, _ = (np.asarray(v, dtype) for v in _geometry(3, backscatter=True))
    zero = np.array([0.0, 0.0, 1.0], dtype)
    k_in = np.concatenate([k_in, kb, zero[None]])
    k_out = np.concatenate([k_out, kb, zero[None]])
    h = np.concatenate([h, kb, zero[None]])
    x_in = np.concatenate([x_in, xb, np.array([[1.0, 0, 0]], dtype)])
    x_out = np.concatenate([x_out, xb, np.array([[0.0, 1, 0]], dtype)])

    def g2(nr, ni, ki, ko, hh):
        M = facet_mueller_rows(nr, ni, ki, ko, hh, x_in, x_out)
        return sum(jnp.sum(e * (0.1 + 0.05 * i)) for i, e in enumerate(x for r in M for x in r))

    @jax.jit
    def all_grads(pts, nr, ni, ki, ko, hh):
        return (jax.vmap(jax.grad(f))(pts),) + jax.grad(g2, argnums=(0, 1, 2, 3, 4))(
            nr, ni, ki, ko, hh
        )

    for n in [(1.5, 0.0), (1.0, 0.0), (0.94, 6.42)]:
        grads = all_grads(pts, dtype(n[0]), dtype(n[1]), k_in, k_out, h)
        assert grads[0].dtype == dtype
        for gg in grads:
            assert np.all(np.isfinite(np.array(gg)))


def test_float32_matches_float64():
    ns = np.array(METALS + [1.5, 1.0, 0.6])
    c = np.linspace(0, 1, 9)
    N, C = np.meshgrid(ns, c, indexing="ij")
    p64 = fresnel_mueller_params(N.real, N.imag, C)
    p32 = fresnel_mueller_params(N.real.astype(np.float32), N.imag.astype(np.float32),
                                 C.astype(np.float32))
    for a, b in zip(p32, p64, strict=True):
        assert a.dtype == np.float32
        # a few float32 ulps amplified by |n|^2 ~ 100 in the p-wave division
        np.testing.assert_allclose(np.array(a), np.array(b), atol=2e-5)


def test_jvp_matches_finite_differences():
    f = lambda p: jnp.stack(pol_params(p[0], p[1], p[2]))
    e = 1e-6

    @jax.jit
    def both(p, v):
        _, jv = jax.jvp(f, (p,), (v,))
        return jv, (f(p + e * v) - f(p - e * v)) / (2 * e)

    for p in ([0.94, 6.42, 0.37], [1.5, 0.0, 0.2], [0.6, 0.0, 0.9], [1.2, 0.01, 0.05]):
        jv, fd = both(jnp.asarray(p), jnp.asarray(RNG.normal(size=3)))
        # central differences: O(e^2 f''') + rounding/e ~ 1e-10
        np.testing.assert_allclose(np.array(jv), np.array(fd), atol=1e-8)


def test_real_and_complex_entry_points_agree():
    n = 1.38 + 10.25j
    rs, rp = fresnel_amplitudes(n, 0.42)
    r = fresnel_amplitudes_re(n.real, n.imag, 0.42)
    # jitted vs op-by-op evaluation may differ in the last bit
    assert complex(rs) == pytest.approx(complex(r[0], r[1]), rel=1e-15)
    assert complex(rp) == pytest.approx(complex(r[2], r[3]), rel=1e-15)


def _rotation_case(seed: int, n: int = 64):
    """Random (non-physical) Mueller matrices, rotation cos/sin pairs and the explicit
    product ``R(b) M R(a)`` of mueller_rotator matrices for any ``M`` of the batch."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, 4, 4))
    a, b = rng.uniform(-np.pi, np.pi, (2, n))
    cs = [jnp.asarray(f(2 * t)) for t in (a, b) for f in (np.cos, np.sin)]

    def ref(m):
        return np.asarray(mueller_rotator(cs[2], cs[3])) @ m @ np.asarray(
            mueller_rotator(cs[0], cs[1])
        )

    return rng, M, cs, ref


def test_rotate_mueller_flat_and_materialize():
    """The (16, 36) monomial map of ppr.optics._frames.rotate_mueller_flat equals the explicit
    product R(b) M R(a) of mueller_rotator matrices (any M, including non-physical), and
    materialize (identity dot) returns its inputs bit for bit."""
    from ppr.optics._frames import materialize, rotate_mueller_flat

    rng, M, cs, ref = _rotation_case(11)
    n = M.shape[0]
    flat = jax.jit(rotate_mueller_flat)(jnp.asarray(M.reshape(n, 16).T), *cs)
    np.testing.assert_allclose(np.asarray(flat).T.reshape(n, 4, 4), ref(M), rtol=0, atol=1e-14)
    xs = [jnp.asarray(rng.normal(size=(3, 5)) * 10.0 ** rng.integers(-30, 30, (3, 5)))
          for _ in range(4)]
    for dt in (jnp.float32, jnp.float64):
        xd = [x.astype(dt) for x in xs]
        for got, want in zip(jax.jit(materialize)(*xd), xd, strict=True):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_rotate_mueller_44_and_store():
    """ppr.optics._frames.rotate_mueller_44 (column and row reversals against constant patterns)
    equals the explicit product R(b) M R(a) of mueller_rotator matrices for any M, batched and
    broadcast; store (identity dot on rows of gcd(size, 8)) returns its input bit for bit,
    sizes without a factor 2 included, and keeps gradients."""
    from ppr.optics._frames import rotate_mueller_44, store

    rng, M, cs, ref = _rotation_case(12)
    got = jax.jit(rotate_mueller_44)(jnp.asarray(M), *cs)
    np.testing.assert_allclose(np.asarray(got), ref(M), rtol=0, atol=1e-14)
    # one M for the batch, angles batched
    got1 = rotate_mueller_44(jnp.asarray(M[0]), *cs)
    np.testing.assert_allclose(np.asarray(got1), ref(M[0]), rtol=0, atol=1e-14)
    for shape in [(5, 3), (8,), (250, 4, 4), (7,)]:
        x = rng.normal(size=shape) * 10.0 ** rng.integers(-30, 30, shape)
        for dt in (jnp.float32, jnp.float64):
            xd = jnp.asarray(x, dt)
            np.testing.assert_array_equal(np.asarray(jax.jit(store)(xd)), np.asarray(xd))
    g = jax.grad(lambda x: jnp.sum(jnp.sin(store(x))))(jnp.arange(16.0))
    np.testing.assert_allclose(np.asarray(g), np.cos(np.arange(16.0)), rtol=1e-14)
