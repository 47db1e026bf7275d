"""Measurement model (PSG/PSA channels) and noise statistics against closed forms."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from inversion._noise import (
    ROUNDING_ULPS,
    STATES,
    MeasurementModel,
    NoiseModel,
    measure,
    measure_stokes,
    observe,
    shift_profile,
)
from inversion._refine import PoissonCounts


def test_full_preset_determines_mueller():
    mm = MeasurementModel.preset("full")
    p = mm.channel_matrix().reshape(16, 16)
    assert mm.n_channels == 16
    # the 16 x 16 system is invertible: full Mueller matrix recoverable (condition number of
    # the H,V,D,L PSG/PSA is modest; 1e-10 is float64 round-off times that)
    rng = np.random.default_rng(0)
    m = rng.normal(size=(4, 4, 3))
    chans = np.asarray(measure(mm, jnp.asarray(m)))
    rec = np.linalg.solve(p, chans).reshape(4, 4, 3)
    np.testing.assert_allclose(rec, m, atol=1e-10)


def test_channels_free_space_malus():
    # identity Mueller (no change of state): ideal analyzers follow Malus' law
    mm = MeasurementModel(("H",), ("H", "V", "D", "R"))
    ident = jnp.eye(4)[..., None]
    np.testing.assert_allclose(
        np.asarray(measure(mm, ident))[:, 0], [1.0, 0.0, 0.5, 0.5], atol=1e-15
    )
    # a mirror (diag(1, 1, -1, -1)) flips circular handedness: R in, L out
    mmr = MeasurementModel(("R",), ("R", "L"))
    mirror = jnp.diag(jnp.array([1.0, 1.0, -1.0, -1.0]))[..., None]
    np.testing.assert_allclose(np.asarray(measure(mmr, mirror))[:, 0], [0.0, 1.0], atol=1e-15)


def test_measure_stokes_matches_measure():
    mm = MeasurementModel.preset("stokes")
    rng = np.random.default_rng(1)
    m = rng.normal(size=(2, 4, 4, 5))
    s_in = np.asarray([STATES[g] for g in mm.generators])  # (G, 4)
    stokes = np.einsum("...ijb,gj->...gib", m, s_in)
    np.testing.assert_allclose(
        np.asarray(measure_stokes(mm, jnp.asarray(stokes))),
        np.asarray(measure(mm, jnp.asarray(m))),
        atol=1e-13,
    )
    with pytest.raises(ValueError, match="generators"):
        measure_stokes(mm, jnp.zeros((3, 4, 5)))


def test_bad_measurement_model():
    with pytest.raises(ValueError, match="unknown states"):
        MeasurementModel(("H", "X"), ("H",))
    with pytest.raises(ValueError, match="empty"):
        MeasurementModel((), ("H",))
    with pytest.raises(ValueError, match="preset"):
        MeasurementModel.preset("nope")


def test_shift_profile_integer_and_fractional():
    x = jnp.asarray(np.random.default_rng(2).random((3, 40)))
    x = x.at[:, :5].set(0.0).at[:, -5:].set(0.0)
    np.testing.assert_array_equal(np.asarray(shift_profile(x, 3.0)), np.roll(np.asarray(x), 3, -1))
    np.testing.assert_array_equal(
        np.asarray(shift_profile(x, -2.0)), np.roll(np.asarray(x), -2, -1)
    )
    y = np.asarray(shift_profile(x, 1.37))
    # flux-conserving rebinning: totals kept (1e-12: float64 round-off) and centroid moves by
    # exactly the shift (linear cumulative -> first moment shifts exactly)
    np.testing.assert_allclose(y.sum(-1), np.asarray(x).sum(-1), rtol=1e-12)
    b = np.arange(40)
    c0 = (np.asarray(x) * b).sum(-1) / np.asarray(x).sum(-1)
    c1 = (y * b).sum(-1) / y.sum(-1)
    np.testing.assert_allclose(c1 - c0, 1.37, atol=1e-10)


SHAPE = (16, 48)  # one shape for every observation here (and in test_classifier): one compile


def _samples(noise, lam_per_bin, n_seeds=26, shape=SHAPE):
    x = np.ones(shape)
    out = np.stack([np.asarray(observe(x, noise, seed=s).data) for s in range(n_seeds)])
    n_total = noise.snr**2
    assert math.isclose(n_total / x.size, lam_per_bin)
    return out.ravel()


@pytest.mark.parametrize("lam", [3.0, 20.0, 400.0])  # inversion branch, PTRS branch, large
def test_poisson_mean_variance(lam):
    noise = NoiseModel(snr=math.sqrt(lam * 768))
    c = _samples(noise, lam)
    n = c.size
    assert np.all(c == np.round(c))
    # mean: 5 standard errors sqrt(lam/n); variance: 5 standard errors of a Poisson sample
    # variance sqrt((2 lam^2 + lam)/n)
    assert abs(c.mean() - lam) < 5 * math.sqrt(lam / n)
    assert abs(c.var() - lam) < 5 * math.sqrt((2 * lam**2 + lam) / n)
    # the pmf at the mode matches Poisson (chi-square-free check of the shape, 5 sigma)
    mode = int(lam)
    p_mode = math.exp(-lam + mode * math.log(lam) - math.lgamma(mode + 1))
    assert abs(np.mean(c == mode) - p_mode) < 5 * math.sqrt(p_mode * (1 - p_mode) / n)


def test_speckle_negative_binomial_variance_and_contrast():
    lam, m = 20.0, 4.0
    noise = NoiseModel(snr=math.sqrt(lam * 768), speckle_cells=m)
    c = _samples(noise, lam)
    n = c.size
    var = lam + lam**2 / m  # Poisson on Gamma(M, 1/M)-modulated intensity
    assert abs(c.mean() - lam) < 5 * math.sqrt(var / n)
    # negative binomial (r = M): excess kurtosis 6/r + 1/(r p (1-p))-ish; 5% is > 3.5 sigma
    assert abs(c.var() / var - 1) < 0.05
    # speckle alone (no photon noise): contrast std/mean = 1/sqrt(M)
    noise = NoiseModel(speckle_cells=9.0)
    v = np.concatenate(
        [np.asarray(observe(np.ones(SHAPE), noise, seed=s).data).ravel() for s in range(13)]
    )
    # 1e4 samples of Gamma(9): relative SE of the std about 1/sqrt(2n) (0.7%), 5% bound
    assert abs(v.std() / v.mean() - 1 / 3) < 0.05 / 3
    assert abs(v.mean() - 1) < 5 * (1 / 3) / 100


def test_reproducible_and_nuisances():
    x = np.zeros(SHAPE)
    x[:, 10:40] = np.linspace(1, 2, 30)
    noise = NoiseModel(
        snr=50.0,
        speckle_cells=8.0,
        jitter_bins=0.5,
        max_offset_bins=5.0,
        gain_min=0.1,
        gain_max=10.0,
    )
    a, b, c = observe(x, noise, 7), observe(x, noise, 7), observe(x, noise, 8)
    np.testing.assert_array_equal(np.asarray(a.data), np.asarray(b.data))
    assert not np.array_equal(np.asarray(a.data), np.asarray(c.data))
    g = float(a.truth["gain"])
    assert 0.1 <= g <= 10.0 and abs(float(a.truth["offset_bins"])) <= 5.0
    counts = np.asarray(a.data) / g
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-9 * counts.max())
    assert np.ptp(np.asarray(a.truth["channel_offsets_bins"])) > 0
    assert a.seed == 7


def test_observe_bad_input():
    with pytest.raises(ValueError, match="no positive value"):
        observe(-np.ones((2, 4)), NoiseModel(), 0)
    with pytest.raises(ValueError, match="non-finite values .* channel 1, bin 2"):
        observe(np.array([[1.0, 1, 1, 1], [1, 1, np.nan, 1]]), NoiseModel(), 0)
    real_negative = np.array([[1.0, 1, 1, 1], [1, 1, -1e-4, 1]], np.float32)
    with pytest.raises(ValueError, match="negative values down to -0.0001 at channel 1, bin 2"):
        observe(real_negative, NoiseModel(), 0)
    with pytest.raises(ValueError, match="n_channels, n_bins"):
        observe(np.ones(4), NoiseModel(), 0)
    with pytest.raises((ValueError, TypeError)):  # beartype under pytest, ValueError otherwise
        observe(np.ones((2, 4)), NoiseModel(), 1.5)
    # a likelihood is not a noise recipe (it raised AttributeError 'snr'); seeds past int64
    with pytest.raises(TypeError):  # beartype under pytest, ours otherwise
        observe(np.ones((2, 4)), PoissonCounts(), 0)
    with pytest.raises(ValueError, match=r"seed must be in \[0, 2\^63\), got 118059"):
        observe(np.ones((2, 4)), NoiseModel(), 2**70)
    with pytest.raises(ValueError, match="snr"):
        NoiseModel(snr=0.0)
    with pytest.raises(ValueError, match="speckle_cells"):
        NoiseModel(speckle_cells=0.5)
    with pytest.raises(ValueError, match="gain"):
        NoiseModel(gain_min=2.0, gain_max=1.0)


def _polarizing_muellers(rng, n):
    """Mueller matrices (4, 4, n) of rank-one Jones matrices ``e a^T`` (any input, output
    state ``e`` cycling through H, V, D, A and both circular states): fully polarizing, so the
    analyzer orthogonal to ``e`` passes exactly 0."""
    from ppr.optics import jones_to_mueller

    states = [(1, 0), (0, 1), (1, 1), (1, -1), (1, 1j), (1, -1j)]
    J = np.zeros((n, 2, 2), complex)
    for i in range(n):
        e = np.asarray(states[i % 6], complex) / np.linalg.norm(states[i % 6])
        J[i] = np.outer(e, rng.normal(size=2) + 1j * rng.normal(size=2))
    return np.moveaxis(np.asarray(jones_to_mueller(J)), 0, -1)


def test_rounding_negatives_of_a_crossed_channel_are_zero():
    """A fully polarized return seen through crossed polarizers is exactly 0; computed as the
    16-term channel sum it comes out as +-rounding (how far depends on the compiler's order of
    the sum). Those values are taken as 0, so the noise-free observation is 0 there and the
    rest unchanged, bit for bit."""
    mm = MeasurementModel(("H", "V", "D", "L"), ("H", "V", "D", "A", "R", "L"))
    rng = np.random.default_rng(3)
    x = measure(mm, jnp.asarray(_polarizing_muellers(rng, 48), jnp.float32))
    xn = np.asarray(x)
    eps_peak = np.finfo(np.float32).eps * xn.max()
    assert xn.min() < 0 and xn.min() > -ROUNDING_ULPS * eps_peak  # rounding, inside the rule
    for given in (x, xn.astype(np.float64)):  # a float32 computation handed over as float64
        data = np.asarray(observe(given, NoiseModel(), 0).data)
        assert np.all(data >= 0)
        np.testing.assert_array_equal(data[xn > 0], xn[xn > 0])
        assert np.all(data[xn <= 0] == 0)
