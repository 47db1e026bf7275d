"""Lu-Chipman decomposition, depolarization index, DOP, Cloude realizability."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr.optics import polarimetry as pol
from ppr.optics._frames import jones_to_mueller
from ppr.optics.polarimetry import coherency_matrix

# jit once per shape: the unrolled polar iteration is slow op-by-op
lu_chipman = jax.jit(pol.lu_chipman)
cloude_eigenvalues = jax.jit(pol.cloude_eigenvalues)
degree_of_polarization = jax.jit(pol.degree_of_polarization)
depolarization_index = jax.jit(pol.depolarization_index)
diattenuation = jax.jit(pol.diattenuation)
is_realizable = jax.jit(pol.is_realizable)
polarizance = jax.jit(pol.polarizance)
retardance = jax.jit(pol.retardance)

RNG = np.random.default_rng(11)


def rot3(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def diattenuator(Dv, T=1.0):
    Dv = np.asarray(Dv, float)
    D = np.linalg.norm(Dv)
    a = np.sqrt(1 - D * D)
    mD = a * np.eye(3) + np.outer(Dv, Dv) / (1 + a)
    M = np.eye(4)
    M[0, 1:] = Dv
    M[1:, 0] = Dv
    M[1:, 1:] = mD
    return T * M


def retarder(axis, R):
    M = np.eye(4)
    M[1:, 1:] = rot3(axis, R)
    return M


def depolarizer(eigs, P_delta, rot=None):
    Q = np.eye(3) if rot is None else rot
    M = np.eye(4)
    M[1:, 1:] = Q @ np.diag(eigs) @ Q.T
    M[1:, 0] = P_delta
    return M


def random_jones():
    return RNG.normal(size=(2, 2)) + 1j * RNG.normal(size=(2, 2))


def test_recovers_synthetic_product():
    Dv = np.array([0.2, -0.3, 0.1])
    axis, R = np.array([0.3, 1.0, -0.5]), 1.1
    eigs = np.array([0.7, 0.5, 0.3])
    Q = rot3([1.0, 2.0, 0.5], 0.8)
    Md, Mr, Mz = diattenuator(Dv, 0.6), retarder(axis, R), depolarizer(eigs, [0.05, 0.0, -0.1], Q)
    M = Mz @ Mr @ Md
    r = lu_chipman(M)
    # exact algebra up to Newton-iteration convergence (quadratic; converged to rounding)
    tol = 1e-12
    assert float(r.m00) == pytest.approx(0.6, abs=tol)
    assert float(r.diattenuation) == pytest.approx(np.linalg.norm(Dv), abs=tol)
    np.testing.assert_allclose(np.array(r.diattenuation_vector), Dv, atol=tol)
    assert float(r.retardance) == pytest.approx(R, abs=1e-10)
    assert float(jnp.linalg.norm(r.retardance_vector)) == pytest.approx(R, abs=1e-10)
    assert float(r.depolarization_power) == pytest.approx(1 - eigs.sum() / 3, abs=tol)
    np.testing.assert_allclose(np.array(r.M_D), Md, atol=tol)
    np.testing.assert_allclose(np.array(r.M_R), Mr, atol=1e-10)
    np.testing.assert_allclose(np.array(r.M_Delta), Mz, atol=1e-10)
    np.testing.assert_allclose(np.array(r.M_Delta @ r.M_R @ r.M_D), M, atol=1e-12)
    assert not bool(r.singular) and bool(r.valid)


def test_ideal_depolarizer():
    M = np.diag([0.3, 0.0, 0.0, 0.0])
    r = lu_chipman(M)
    assert float(r.depolarization_power) == 1.0
    assert float(r.diattenuation) == 0.0 and float(r.polarizance) == 0.0
    assert bool(r.singular)
    assert float(depolarization_index(M)) == 0.0
    assert float(degree_of_polarization(M, np.array([1.0, 1.0, 0.0, 0.0]))) == 0.0
    assert bool(is_realizable(M))
    np.testing.assert_allclose(np.array(cloude_eigenvalues(M)), [0.075] * 4, atol=1e-15)


def test_partial_depolarizer_index():
    for a in (0.0, 0.25, 0.9, 1.0):
        M = np.diag([2.0, 2 * a, 2 * a, 2 * a])
        assert float(depolarization_index(M)) == pytest.approx(a, abs=1e-15)


def test_pure_retarders():
    # quarter-wave linear retarder at 30 deg: Jones in conventions' frame
    t, d = np.deg2rad(30), np.pi / 2
    c, s = np.cos(t), np.sin(t)
    Rot = np.array([[c, -s], [s, c]])
    J = Rot @ np.diag([np.exp(-1j * d / 2), np.exp(1j * d / 2)]) @ Rot.T
    M = np.array(jones_to_mueller(J))
    r = lu_chipman(M)
    assert float(r.retardance) == pytest.approx(d, abs=1e-12)
    assert float(r.linear_retardance) == pytest.approx(d, abs=1e-7)  # sqrt at q ~ 1: ~sqrt(eps)
    assert float(r.optical_rotation) == pytest.approx(0.0, abs=1e-12)
    assert float(r.diattenuation) == pytest.approx(0.0, abs=1e-15)
    assert float(r.depolarization_power) == pytest.approx(0.0, abs=1e-12)
    assert float(depolarization_index(M)) == pytest.approx(1.0, abs=1e-14)
    # circular retarder (optical rotator by psi): total retardance 2 psi
    psi = 0.35
    J = np.array([[np.cos(psi), np.sin(psi)], [-np.sin(psi), np.cos(psi)]])
    r = lu_chipman(jones_to_mueller(J.astype(complex)))
    assert float(r.retardance) == pytest.approx(2 * psi, abs=1e-12)
    assert abs(float(r.optical_rotation)) == pytest.approx(psi, abs=1e-12)
    assert float(r.linear_retardance) == pytest.approx(0.0, abs=1e-7)  # same sqrt(eps) reason


def test_pure_diattenuator():
    J = np.diag([1.0, 0.5]).astype(complex)
    M = np.array(jones_to_mueller(J))
    r = lu_chipman(M)
    assert float(r.diattenuation) == pytest.approx(0.6, abs=1e-15)  # (1 - .25)/(1 + .25)
    assert float(r.polarizance) == pytest.approx(0.6, abs=1e-15)
    assert float(diattenuation(M)) == pytest.approx(0.6, abs=1e-15)
    assert float(polarizance(M)) == pytest.approx(0.6, abs=1e-15)
    assert float(retardance(M)) == pytest.approx(0.0, abs=1e-7)
    assert float(r.depolarization_power) == pytest.approx(0.0, abs=1e-12)
    # ideal polarizer: unpolarized in -> fully polarized out, D = 1, no NaN
    Mp = np.array(jones_to_mueller(np.diag([1.0, 0.0]).astype(complex)))
    assert float(degree_of_polarization(Mp, np.array([1.0, 0, 0, 0]))) == pytest.approx(1.0)
    rp = lu_chipman(Mp)
    assert float(rp.diattenuation) == pytest.approx(1.0)
    assert bool(rp.singular)  # M_D singular at D = 1: flagged, not NaN
    assert all(np.all(np.isfinite(np.asarray(x))) for x in rp)


def test_cloude_eigenvalues_and_realizability():
    J1, J2 = random_jones(), random_jones()
    M1, M2 = np.array(jones_to_mueller(J1)), np.array(jones_to_mueller(J2))
    w = np.array(cloude_eigenvalues(M1))
    # one non-zero eigenvalue equal to M00 (rank-one coherency), rest rounding
    assert w[0] == pytest.approx(M1[0, 0], rel=1e-13)
    np.testing.assert_allclose(w[1:], 0.0, atol=1e-13 * M1[0, 0])
    H = np.array(coherency_matrix(M1))
    assert np.trace(H).real == pytest.approx(M1[0, 0], rel=1e-14)
    w2 = np.array(cloude_eigenvalues(M1 + 0.4 * M2))
    assert np.all(w2 >= -1e-13 * w2[0]) and w2[1] > 1e-6
    assert bool(is_realizable(M1 + 0.4 * M2))
    # non-physical: diattenuation > 1, and the "time-reversal" diag(1, 1, 1, -1)
    bad1 = np.eye(4)
    bad1[0, 1] = bad1[1, 0] = 1.2
    for bad in (bad1, np.diag([1.0, 1.0, 1.0, -1.0])):
        assert not bool(is_realizable(bad))
        assert float(cloude_eigenvalues(bad)[-1]) < -0.05


def test_no_light_and_batching():
    Ms = np.stack([np.zeros((4, 4)), np.diag([1.0, 0.2, 0.2, 0.2]),
                   np.array(jones_to_mueller(random_jones()))])
    Ms = np.broadcast_to(Ms, (2, 3, 4, 4))
    r = jax.jit(lu_chipman)(Ms)
    assert r.diattenuation.shape == (2, 3) and r.M_R.shape == (2, 3, 4, 4)
    assert not bool(r.valid[0, 0]) and bool(r.valid[0, 1])
    for x in r:
        assert np.all(np.isfinite(np.asarray(x)))
    assert float(r.diattenuation[0, 0]) == 0.0 and float(r.retardance[0, 0]) == 0.0
    assert float(depolarization_index(np.zeros((4, 4)))) == 0.0
    assert float(degree_of_polarization(np.zeros((4, 4)), np.array([1.0, 0, 0, 0]))) == 0.0
    # batched equals looped
    one = lu_chipman(Ms[1, 2])
    np.testing.assert_allclose(np.array(r.retardance[1, 2]), np.array(one.retardance), atol=1e-14)


def test_gradients_finite():
    """float64 (the inversion precision); float32 forward values are checked below."""

    def scalar(M):
        r = pol.lu_chipman(M)
        return jnp.sum(r.diattenuation + r.polarizance + r.retardance + r.depolarization_power
                       + pol.depolarization_index(M)
                       + pol.degree_of_polarization(M, jnp.array([1.0, 0.3, 0.0, 0.2], M.dtype)))

    synth = depolarizer([0.7, 0.5, 0.3], [0.05, 0, -0.1]) @ retarder([0.3, 1, -0.5], 1.1) @ \
        diattenuator([0.2, -0.3, 0.1])
    Ms = np.stack([
        synth,
        retarder([0, 0, 1.0], 0.7),  # degenerate singular values of m' (all 1)
        np.eye(4),
        np.zeros((4, 4)),  # no light
        np.diag([1.0, 0.0, 0.0, 0.0]),  # ideal depolarizer
        np.diag([1.0, 0.5, 0.5, 0.5]),
    ])
    V = RNG.normal(size=Ms.shape)
    e = 1e-6

    @jax.jit
    def run(Ms, V):
        g = jax.vmap(jax.grad(scalar))(Ms)
        fd = jax.vmap(lambda m, t: (scalar(m + e * t) - scalar(m - e * t)) / (2 * e))(Ms, V)
        return g, fd

    g, fd = run(Ms, V)
    assert np.all(np.isfinite(np.array(g)))
    # directional derivative g.v vs central FD at the generic point: O(e^2) + rounding/e
    assert float(np.sum(g[0] * V[0])) == pytest.approx(float(fd[0]), abs=1e-7)


def test_float32_agrees():
    f32 = jax.jit(pol.lu_chipman)
    for _ in range(4):
        M = np.array(jones_to_mueller(random_jones()))
        M = M / M[0, 0] * 0.5 + np.diag([0.1, 0, 0, 0])  # mix in some depolarization
        r64 = lu_chipman(M)
        r32 = f32(M.astype(np.float32))
        assert all(np.all(np.isfinite(np.asarray(x))) for x in r32)
        for name in ("diattenuation", "polarizance", "retardance", "depolarization_power"):
            a, b = getattr(r32, name), getattr(r64, name)
            assert a.dtype == np.float32
            # a few hundred float32 ulps through the 3x3 polar iteration
            np.testing.assert_allclose(np.array(a), np.array(b), atol=1e-4)
