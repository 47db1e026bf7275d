"""Pin the conventions of ppr/optics/conventions.py against first-principles field computations.

Each test builds the real 3D electric field from a Jones vector and a beam frame, so the
checks do not rely on the Stokes/Mueller code they are testing.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from ppr.optics._frames import (
    A_STOKES,
    facet_jones_in_beam_frames,
    facet_mueller_in_beam_frames,
    mueller_rotator,
    rotation_cos_sin_2a,
)

RNG = np.random.default_rng(20261122)


def stokes_from_jones(E):
    """S = A (E (x) E^*) with ppr's A."""
    return np.real(np.asarray(A_STOKES) @ np.kron(E, np.conj(E)))


def field_3d(E, x, d, omega_t):
    """Real field at z = 0 of a beam with Jones vector E in frame (x, y = d x x, d),
    time dependence exp(-i w t) (conventions: exp(i(kz - wt)))."""
    y = np.cross(d, x)
    ph = np.exp(-1j * omega_t)
    ex = np.real(E[0] * ph)
    ey = np.real(E[1] * ph)
    return ex[:, None] * x + ey[:, None] * y


def helicity(E, x, d):
    """Sign of (E x dE/dt) . d: > 0 when the field turns right-handed about d (from x to y),
    i.e. counterclockwise for a receiver looking back at the source."""
    t = np.array([0.0, 1e-4])
    f = field_3d(E, x, d, t)
    return np.dot(np.cross(f[0], (f[1] - f[0]) / 1e-4), d)


def random_frame(d):
    v = RNG.normal(size=3)
    x = np.cross(d, v)
    return x / np.linalg.norm(x)


def random_unit():
    v = RNG.normal(size=3)
    return v / np.linalg.norm(v)


def test_stokes_definitions_match_A():
    for _ in range(5):
        E = RNG.normal(size=2) + 1j * RNG.normal(size=2)
        S = stokes_from_jones(E)
        ref = [
            abs(E[0]) ** 2 + abs(E[1]) ** 2,
            abs(E[0]) ** 2 - abs(E[1]) ** 2,
            2 * np.real(E[0] * np.conj(E[1])),
            -2 * np.imag(E[0] * np.conj(E[1])),
        ]
        np.testing.assert_allclose(S, ref, atol=1e-12)  # exact algebra, rounding only


def test_S3_sign_is_right_handed_about_propagation():
    # (1, i)/sqrt 2 has S3 = +1 and its field turns from x toward y (right-handed about d)
    E = np.array([1.0, 1j]) / np.sqrt(2)
    assert stokes_from_jones(E)[3] == pytest.approx(1.0, abs=1e-12)
    d = random_unit()
    assert helicity(E, random_frame(d), d) > 0
    for _ in range(10):
        E = RNG.normal(size=2) + 1j * RNG.normal(size=2)
        d = random_unit()
        S3 = stokes_from_jones(E)[3]
        assert np.sign(S3) == np.sign(helicity(E, random_frame(d), d))


def test_frame_rotation_matrix_sign():
    # rotate the frame vector by a (right-handed about d); project the same physical field
    for a in (0.3, -1.1, 2.0):
        d = random_unit()
        x = random_frame(d)
        y = np.cross(d, x)
        x2 = np.cos(a) * x + np.sin(a) * y
        y2 = np.cross(d, x2)
        E = RNG.normal(size=2) + 1j * RNG.normal(size=2)
        vec = E[0] * x + E[1] * y  # complex 3D field amplitude
        E2 = np.array([np.dot(vec, x2), np.dot(vec, y2)])
        R = np.array(
            [[1, 0, 0, 0], [0, np.cos(2 * a), np.sin(2 * a), 0],
             [0, -np.sin(2 * a), np.cos(2 * a), 0], [0, 0, 0, 1]]
        )
        np.testing.assert_allclose(stokes_from_jones(E2), R @ stokes_from_jones(E), atol=1e-12)
        c2, s2 = rotation_cos_sin_2a(jnp.asarray(x), jnp.asarray(x2), jnp.asarray(d))
        np.testing.assert_allclose(np.asarray(mueller_rotator(c2, s2)), R, atol=1e-12)


def _perfect_conductor_reflect(vec, h):
    """Field reflected by a perfect conductor with normal h: tangential part reversed."""
    return -vec + 2 * np.dot(vec, h) * h


@pytest.mark.parametrize("incidence_deg", [0.0, 30.0, 75.0])
def test_facet_jones_matches_perfect_conductor(incidence_deg):
    # independent 3D reference: a perfect conductor keeps the normal E, reverses tangential E
    t = np.deg2rad(incidence_deg)
    h = random_unit()
    u = random_frame(h)
    k_in = np.cos(t) * h + np.sin(t) * u
    k_out = 2 * np.dot(k_in, h) * h - k_in
    x_in, x_out = random_frame(k_in), random_frame(k_out)
    J = np.asarray(
        facet_jones_in_beam_frames(0.0, 1e7, k_in, k_out, h, x_in, x_out)
    )
    y_in, y_out = np.cross(-k_in, x_in), np.cross(k_out, x_out)
    for E in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1j])):
        vec = E[0] * x_in + E[1] * y_in
        r = _perfect_conductor_reflect(vec, h)
        E_ref = np.array([np.dot(r, x_out), np.dot(r, y_out)])
        # |n| = 1e7: r_s, r_p differ from -1, +1 by ~2/|n|
        np.testing.assert_allclose(J @ E, E_ref, atol=1e-6)


def test_mirror_reverses_handedness_any_frame():
    # normal incidence on glass: M = R diag(1, 1, -1, -1) for any x (same lab vector both ways)
    n = 1.5
    R = ((n - 1) / (n + 1)) ** 2
    h = random_unit()
    for _ in range(4):
        x = random_frame(h)
        M = np.asarray(facet_mueller_in_beam_frames(n, 0.0, h, h, h, x, x))
        np.testing.assert_allclose(M, R * np.diag([1, 1, -1, -1]), atol=1e-14)
    # physical check of the handedness flip with the 3D field of a perfect conductor
    E = np.array([1.0, 1j]) / np.sqrt(2)
    x = random_frame(h)
    vec = E[0] * x + E[1] * np.cross(-h, x)
    r = _perfect_conductor_reflect(vec, h)
    E_out = np.array([np.dot(r, x), np.dot(r, np.cross(h, x))])
    assert helicity(E, x, -h) > 0 and helicity(E_out, x, h) < 0
    assert stokes_from_jones(E_out)[3] == pytest.approx(-1.0, abs=1e-12)


def test_fresnel_normal_incidence_sign():
    from ppr.optics._fresnel import fresnel_amplitudes

    rs, rp = fresnel_amplitudes(1.5, 1.0)
    assert complex(rs) == pytest.approx(-0.2, abs=1e-15)
    assert complex(rp) == pytest.approx(0.2, abs=1e-15)


def _jones_of_stokes(S):
    """A Jones vector whose Stokes vector (ppr's definitions, S0 = 1, fully polarized) is S,
    inverted by hand: E_x = sqrt((1 + S1) / 2) real, E_x E_y^* = (S2 - i S3) / 2."""
    ex = np.sqrt((1.0 + S[1]) / 2.0)
    return np.array([ex, (S[2] + 1j * S[3]) / (2.0 * ex)])


def _turns_seen_from_receiver(E, x, d, n_t=64):
    """Net turns of the real field ``Re[(E_x x + E_y y) exp(-i w t)]`` (``y = d x x``; the
    conventions' ``exp(i(kz - wt))`` at z = 0) over one period, as seen by an observer
    downstream looking back toward the source (along ``-d``), in the observer's own screen
    axes (``right`` any unit vector _|_ d, ``up`` with ``right x up`` pointing at the observer,
    i.e. ``+d``): +1 counterclockwise, -1 clockwise. Also returns the angular velocity
    ``(E x dE/dt) . d / |E|^2`` (analytic derivative) at every sample, in units of ``w``."""
    y = np.cross(d, x)
    amp = E[0] * x + E[1] * y  # complex 3-D amplitude
    wt = np.linspace(0.0, 2.0 * np.pi, n_t + 1)
    field = np.real(amp[None, :] * np.exp(-1j * wt)[:, None])
    dfield = np.real(-1j * amp[None, :] * np.exp(-1j * wt)[:, None])  # d/d(wt)
    right = random_frame(d)
    up = np.cross(d, right)
    ang = np.unwrap(np.arctan2(field @ up, field @ right))
    omega = np.cross(field, dfield) @ d / np.sum(field * field, axis=-1)
    return (ang[-1] - ang[0]) / (2.0 * np.pi), omega


def test_named_circular_states_rotation_sense():
    # "R" (right circular in Chipman's, Born & Wolf's and Hecht's naming): the field turns
    # clockwise for an observer looking toward the source, i.e. left-handed about the
    # propagation direction d: ppr's S3 = -1. "L" is the opposite (S3 = +1; IEEE's right-hand).
    from inversion._noise import STATES
    from ppr.pulse._pulse import STOKES_STATES

    assert STATES == STOKES_STATES  # one naming in ppr and inversion
    expect = {"R": -1, "L": +1}
    for name, sense in expect.items():
        S = np.asarray(STOKES_STATES[name], float)
        E = _jones_of_stokes(S)
        np.testing.assert_allclose(stokes_from_jones(E), S, atol=1e-15)  # inversion, rounding
        for _ in range(3):  # any propagation direction and frame vector
            d = random_unit()
            turns, omega = _turns_seen_from_receiver(E, random_frame(d), d)
            assert turns == pytest.approx(sense, abs=1e-12)  # one full turn per period
            # circular: constant angular velocity +-w about d (exact, rounding only)
            np.testing.assert_allclose(omega, sense, atol=1e-12)
    # (1, -i)/sqrt 2 with exp(-i w t) (the convention's time factor): clockwise seen from the
    # receiver, ppr's S3 = -1, "R"
    E_r = np.array([1.0, -1j]) / np.sqrt(2.0)
    np.testing.assert_allclose(stokes_from_jones(E_r), STOKES_STATES["R"], atol=1e-15)
    d = random_unit()
    assert _turns_seen_from_receiver(E_r, random_frame(d), d)[0] == pytest.approx(-1, abs=1e-12)
