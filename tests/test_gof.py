"""Goodness of fit (inversion._gof): exact null moments of the deviance, fitted degrees of
freedom and p-value calibration, all against brute-force simulation in NumPy.

The toy fits are NumPy models fitted by Fisher scoring over all replicates at once: a
log-linear Poisson model (the canonical link, where the deviance of sparse counts is most
degenerate) and an identity-link model with counting noise (Pearson chi-square).
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
from scipy import stats

from inversion._gof import (
    _lower_tail,
    _poisson_exact,
    _poisson_fields,
    detection_power,
    detection_power_bound,
    deviance_moments,
    goodness_of_fit,
    poisson_deviance_moments,
)
from inversion._params import PhysicalParams
from inversion._refine import GaussianNoise, PoissonCounts, PoissonNoise


def _mp_moments(lam):
    """Mean, variance, third cumulant of the Poisson unit deviance by 40-digit sums."""
    with mpmath.workdps(40):
        lam = mpmath.mpf(lam)
        top = int(float(lam) + 20 * math.sqrt(float(lam)) + 60)
        ps, ds = [], []
        for y in range(top):
            p = mpmath.exp(y * mpmath.log(lam) - lam - mpmath.loggamma(y + 1))
            d = 2 * ((y * mpmath.log(y / lam) if y else 0) - (y - lam))
            ps.append(p)
            ds.append(d)
        mean = mpmath.fsum(p * d for p, d in zip(ps, ds, strict=True))
        var = mpmath.fsum(p * (d - mean) ** 2 for p, d in zip(ps, ds, strict=True))
        k3 = mpmath.fsum(p * (d - mean) ** 3 for p, d in zip(ps, ds, strict=True))
        return float(mean), float(var), float(k3)


def test_poisson_moments_against_mpmath_and_series():
    lams = np.array([1e-6, 0.03, 0.7, 4.0, 40.0])
    mean, var, k3 = poisson_deviance_moments(lams)
    for i, lam in enumerate(lams):
        ref = _mp_moments(lam)
        # float64 sums of ~100 positive terms: 1e-12
        np.testing.assert_allclose([mean[i], var[i], k3[i]], ref, rtol=1e-12)
    # sparse limit: E d = 2 lam log(1/lam) + O(lam^2 log lam) (the rule of thumb "1 per bin"
    # is 4e4x off)
    assert mean[0] == pytest.approx(2e-6 * math.log(1e6), rel=1e-4)
    # the derivatives of the mean in lam (used for the fitted moments) against mpmath's
    for lam in (0.05, 3.0):
        f = lambda t: _mp_moments(float(t))[0]  # noqa: E731
        with mpmath.workdps(40):
            d1 = float(mpmath.diff(f, lam, 1, h=mpmath.mpf("1e-6")))
        ex = _poisson_exact(np.array([lam]), np.zeros(1))
        assert ex["d1"][0] == pytest.approx(d1, rel=1e-6)  # finite difference step 1e-6
    # the 1/lam series above the switch against the sums, every field, a != 0 (the estimation
    # term): truncated after lam^-5, so the error falls like lam^-6
    lam = np.array([100.0, 150.0, 400.0])
    a = np.array([2e-3, -1e-3, 5e-4])
    exact = _poisson_exact(lam, a)
    for i, lb in enumerate(lam):
        fields = _poisson_fields(np.array([lb + 1e-9]), a[i : i + 1])  # lb + eps: series side
        for k in ("mean", "var", "k3", "c2"):
            assert fields[k][0] == pytest.approx(exact[k][i], rel=3e-9), (k, lb)
        for k in ("d1", "d2"):
            assert fields[k][0] == pytest.approx(exact[k][i], rel=1e-6, abs=1e-14), (k, lb)


def _sim_counting(rng, mu, noise: PoissonNoise, gain, r):
    g = gain if noise.counts_per_photon == "gain" else 1.0
    lam = np.broadcast_to(mu / g, (r, mu.size))
    if noise.speckle_cells is not None:
        m = noise.speckle_cells
        lam = lam * rng.gamma(m, 1.0 / m, size=lam.shape)
    return g * rng.poisson(lam) + math.sqrt(noise.floor) * rng.normal(size=lam.shape)


@pytest.mark.parametrize(
    "case", ["poisson_sparse", "poisson_mixed", "counting_sparse", "counting_speckle", "gauss"]
)
def test_null_moments_and_calibration_against_simulation(case):
    """No fitted parameters: the deviance's mean, variance and third cumulant equal their
    simulated values, and the p-value's rejection rates are nominal down to 1e-3 (Pearson III),
    where the normal reference is off by 2x or more on sparse counts."""
    rng = np.random.default_rng(7)
    r = 20000
    phys = None
    if case == "poisson_sparse":
        mu = np.exp(rng.uniform(np.log(1e-3), np.log(0.3), 250))
        noise = PoissonCounts(background=1e-3)
        y = rng.poisson(mu + 1e-3, size=(r, mu.size)).astype(float)
    elif case == "poisson_mixed":  # a return of 50 counts at its peak on a sparse background
        mu = 50.0 * np.exp(-0.5 * ((np.arange(256) - 128) / 6.0) ** 2)
        noise = PoissonCounts(background=1e-3)
        y = rng.poisson(mu + 1e-3, size=(r, mu.size)).astype(float)
    elif case == "counting_sparse":  # Gaussian model with a small floor on sparse counts
        mu = np.exp(rng.uniform(np.log(0.02), np.log(1.0), 200))
        noise = PoissonNoise(floor=0.01)
        y = _sim_counting(rng, mu, noise, 1.0, r)
    elif case == "counting_speckle":  # speckle and a gain of 2.5 data units per photon
        mu = rng.uniform(0.5, 40.0, 100)
        noise = PoissonNoise(floor=0.5, speckle_cells=3.0, counts_per_photon="gain")
        phys = PhysicalParams([1.0, 0, 0, 0], [1.0], [1.5], gain=2.5)
        y = _sim_counting(rng, mu, noise, 2.5, r)
    else:
        mu = rng.uniform(-5, 5, 150)
        sig = rng.uniform(0.5, 2.0, 150)
        noise = GaussianNoise(sig)
        y = mu + sig * rng.normal(size=(r, mu.size))
    e, v, k3 = deviance_moments(mu, noise, phys)
    g = goodness_of_fit(y[0], mu, noise, phys=phys)
    if case.startswith("poisson"):
        lam = mu + 1e-3
        pos = y > 0
        dev = 2 * (np.where(pos, y * np.log(np.where(pos, y, 1) / lam), 0) - (y - lam)).sum(1)
    else:
        g_ = 2.5 if case == "counting_speckle" else 1.0
        var = {
            "gauss": lambda: sig**2,
            "counting_sparse": lambda: mu + 0.01,
            "counting_speckle": lambda: g_ * mu + mu**2 / 3.0 + 0.5,
        }[case]()
        dev = ((y - mu) ** 2 / var).sum(1)
    assert g.deviance == pytest.approx(dev[0], rel=1e-12)
    m, s2 = dev.mean(), dev.var()
    c4 = np.mean((dev - m) ** 4)
    assert abs(m - e.sum()) < 5 * math.sqrt(s2 / r), (m, e.sum())  # 5 standard errors
    assert abs(s2 - v.sum()) < 5 * math.sqrt((c4 - s2 * s2) / r), (s2, v.sum())
    # third cumulant: sampling error of a heavy-tailed k3 with 2e4 draws, ~5%
    assert stats.moment(dev, 3) == pytest.approx(k3.sum(), rel=0.2)
    p = g.tail(dev)
    z = (dev - g.expected) / g.std
    for alpha in (0.1, 0.01, 1e-3):
        band = 4.5 * math.sqrt(alpha * (1 - alpha) / r)  # binomial, 4.5 sigma
        assert abs(np.mean(p < alpha) - alpha) < band + 0.1 * alpha, (alpha, np.mean(p < alpha))
    if case in ("poisson_sparse", "poisson_mixed", "counting_sparse"):
        # the normal reference rejects at least twice too often at 1e-3 here
        assert np.mean(stats.norm.sf(z) < 1e-3) > 2e-3
    # the lower tail (data scattering less than the noise model allows): nominal rates, and
    # the underdispersion verdict (lower tail < 1e-3 and z < -3) no more often than 1e-3
    lo = _lower_tail(dev, g.expected, g.std**2, g.skewness * g.std**3)
    for alpha in (0.1, 0.01):
        band = 4.5 * math.sqrt(alpha * (1 - alpha) / r)
        assert abs(np.mean(lo < alpha) - alpha) < band + 0.1 * alpha, (alpha, np.mean(lo < alpha))
    assert np.mean((lo < 1e-3) & (z < -3.0)) <= 1e-3 + 4.5 * math.sqrt(1e-3 / r)
    assert not g.underdispersed or lo[0] < 1e-3


def _glm_fit(y, X, beta0, iters=30):
    """Poisson maximum likelihood for log mu = X beta, every replicate at once."""
    b = np.tile(beta0, (y.shape[0], 1))
    for _ in range(iters):
        mu = np.exp(b @ X.T)
        h = np.einsum("ri,ij,ik->rjk", mu, X, X)
        b = b + np.linalg.solve(h, ((y - mu) @ X)[..., None])[..., 0]
    return np.exp(b @ X.T)


def _design(n):
    x = np.linspace(-1, 1, n)
    return np.stack([np.ones(n), x, x * x], 1)


@pytest.mark.parametrize("n, beta", [(300, (-1.0, 0.5, -3.0)), (40, (4.0, 0.3, -1.0))])
def test_fitted_poisson_deviance_brute_force(n, beta):
    """Three fitted parameters of a log-linear Poisson model, sparse (56 counts in 300 bins)
    and dense (1600 in 40): the deviance at the maximum-likelihood fit matches the predicted null
    mean and variance, and the p-values are uniform. Without the Jacobian (plug-in moments
    minus p) the sparse case is badly off: the fitted expectation follows the counts, so the
    deviance and its plug-in mean move together."""
    rng = np.random.default_rng(n)
    X = _design(n)
    mu = np.exp(X @ np.asarray(beta))
    r = 300
    y = rng.poisson(mu, size=(r, n)).astype(float)
    fit = _glm_fit(y, X, np.asarray(beta))
    noise = PoissonCounts(background=1e-12)
    res = [goodness_of_fit(y[i], fit[i], noise, jacobian=fit[i][:, None] * X) for i in range(r)]
    assert all(g.n_params == 3 for g in res)
    z = np.array([g.z for g in res])
    p = np.array([g.p_value for g in res])
    assert abs(z.mean()) < 4 / math.sqrt(r)  # 4 standard errors of a unit-variance mean
    # predicted variance within sampling error (16 % at 300 draws) plus the expansion's
    # second-order error on the sparse case (measured: 11 % conservative)
    assert 0.65 < z.var() < 1.3, z.var()
    assert stats.kstest(p, "uniform").pvalue > 1e-3 or z.var() < 1  # uniform, or conservative
    assert abs(np.mean(p < 0.1) - 0.1) < 4.5 * math.sqrt(0.09 / r)
    if n == 300:  # sparse: the plug-in moments overstate the spread 2.3x
        naive = [goodness_of_fit(y[i], fit[i], noise, n_params=3) for i in range(100)]
        assert np.var([g.z for g in naive]) < 0.4


def test_fitted_counting_noise_brute_force():
    """Identity-link model mu = X beta with the PoissonNoise variance mu + floor, data photo-
    counts plus Gaussian read noise, fitted by iteratively re-weighted least squares with the
    weights at the fit (as the refiner). The counting noise's kurtosis makes the statistic at
    the truth 1.7x more variable than chi-square; at the fit, weights that follow the counts
    take that back. The predicted mean and spread match the simulated ones; the plug-in
    moments without the Jacobian overstate the spread by 30 %."""
    rng = np.random.default_rng(3)
    n, r = 120, 2000
    X = _design(n)
    beta = np.array([0.6, 0.3, 0.5])
    mu = X @ beta
    noise = PoissonNoise(floor=0.02)
    y = _sim_counting(rng, mu, noise, 1.0, r)
    b = np.tile(beta, (r, 1))
    for _ in range(8):
        w = 1.0 / (np.maximum(b @ X.T, 0.0) + noise.floor)
        h = np.einsum("ri,ij,ik->rjk", w, X, X)
        b = np.linalg.solve(h, np.einsum("ri,ij,ri->rj", w, X, y)[..., None])[..., 0]
    fit = b @ X.T
    dev = ((y - fit) ** 2 / (fit + noise.floor)).sum(1)
    res = [goodness_of_fit(y[i], fit[i], noise, jacobian=X) for i in range(100)]
    mean = np.mean([g.expected for g in res])
    sd = np.mean([g.std for g in res])
    assert abs(dev.mean() - mean) < 4 * dev.std() / math.sqrt(r)  # 4 standard errors
    # spread to 6 % (sampling error of a standard deviation from 2000 draws: 2 %)
    assert dev.std() == pytest.approx(sd, rel=0.06)
    naive = goodness_of_fit(y[0], fit[0], noise, n_params=3)
    assert naive.std > 1.2 * dev.std()


def test_mismatch_is_flagged_and_reported():
    """Counts from two peaks fitted with one: model_mismatch, in the summary; the right model
    is accepted. Bad input names the problem."""
    rng = np.random.default_rng(11)
    n = 80
    X = _design(n)
    x = X[:, 1]
    truth = 20.0 * np.exp(-0.5 * ((x - 0.4) / 0.15) ** 2) + 12.0 * np.exp(
        -0.5 * ((x + 0.4) / 0.15) ** 2
    )
    y = rng.poisson(truth + 0.05).astype(float)[None]
    fit = _glm_fit(y, X, np.array([0.0, 0.0, -1.0]))[0]
    bad = goodness_of_fit(y[0], fit, PoissonCounts(1e-12), jacobian=fit[:, None] * X)
    assert bad.model_mismatch and bad.p_value < 1e-3 and bad.z > 3
    assert "MODEL MISMATCH" in bad.summary()
    good = goodness_of_fit(y[0], truth, PoissonCounts(0.05))
    assert not good.model_mismatch and "acceptable" in good.summary()
    d = good.to_dict()
    assert d["model_mismatch"] is False and isinstance(d["p_value"], float)
    assert not good.underdispersed and d["underdispersed"] is False
    # an allowance for model error raises the null's mean: an exact fit is still not "too
    # little scatter" (the lower tail is taken under the exact model)
    allowed = goodness_of_fit(y[0], truth, PoissonCounts(0.05), allowance=500.0)
    assert allowed.z < -3 and not allowed.underdispersed
    # counts averaged over 16 shots (scatter 1/4 of Poisson's) fitted as photo-counts with
    # the Gaussian mu + 1 variance: the data scatter far less than the noise model says;
    # that is said, not called an acceptable fit
    avg = rng.poisson(truth + 0.05, size=(16, n)).mean(0)
    under = goodness_of_fit(avg, truth + 0.05, PoissonNoise(floor=1.0))
    assert under.underdispersed and under.z < -3 and under.lower_p_value < 1e-3
    assert not under.model_mismatch and "SCATTER BELOW THE NOISE MODEL" in under.summary()
    with pytest.raises(ValueError, match="shape"):
        goodness_of_fit(y[0, :-1], truth, PoissonCounts())
    with pytest.raises(ValueError, match="negative"):
        goodness_of_fit(-y[0], truth, PoissonCounts())
    with pytest.raises(ValueError, match="not both"):
        goodness_of_fit(y[0], truth, PoissonCounts(), jacobian=X, n_params=3)
    with pytest.raises(ValueError, match="threshold"):
        goodness_of_fit(y[0], truth, PoissonCounts(), threshold=0.0)
    with pytest.raises(ValueError, match="degrees of freedom"):
        goodness_of_fit(y[0, :2], truth[:2], PoissonCounts(), n_params=5)


def _two_peaks(n, scale):
    x = _design(n)[:, 1]
    return scale * (
        np.exp(-0.5 * ((x - 0.4) / 0.15) ** 2) + 0.6 * np.exp(-0.5 * ((x + 0.4) / 0.15) ** 2)
    )


def test_detection_power_of_a_linear_gaussian_fit_is_the_noncentral_chi_square():
    """Gaussian data (sigma = 1) whose mean lies ``lambda = 25`` (squared distance) from a
    3-parameter linear model: the residual sum of squares at the least-squares fit is the
    non-central chi-square with 57 degrees of freedom, so the rejection rate of 20,000
    simulated fits matches ``detection_power`` (also through the GoodnessOfFit null of the
    noise-free fit), and the likelihood-ratio test against the closest model reaches the
    Neyman-Pearson bound, above the goodness-of-fit test."""
    rng = np.random.default_rng(7)
    n, r, alpha = 60, 20000, 0.01
    X = _design(n)
    proj = X @ np.linalg.pinv(X)
    e = _two_peaks(n, 1.0) - proj @ _two_peaks(n, 1.0)  # the misfit direction
    e *= math.sqrt(25.0) / np.linalg.norm(e)
    mu1 = X @ np.array([1.0, -0.5, 0.3]) + e
    mu0 = proj @ mu1  # the closest model expectation
    lam = float(np.sum((mu1 - mu0) ** 2))
    y = mu1 + rng.normal(size=(r, n))
    res = y - y @ proj.T
    rss = np.sum(res * res, axis=1)
    sim = np.mean(rss > stats.chi2.isf(alpha, n - 3))
    pred = detection_power(lam, n - 3, alpha)
    band = 4.0 * math.sqrt(pred * (1 - pred) / r)
    assert abs(sim - pred) < band, (sim, pred)
    assert 0.2 < pred < 0.8  # a sensitive point of the power curve
    g0 = goodness_of_fit(mu1, mu0, GaussianNoise(1.0), jacobian=X)
    assert g0.deviance == pytest.approx(lam, rel=1e-9)
    assert detection_power(lam, g0, alpha) == pytest.approx(pred, abs=0.01)
    # Neyman-Pearson: T = (mu1 - mu0) . (y - mu0) is N(0, lam) under mu0, N(lam, lam) under mu1
    t1 = (y - mu0) @ (mu1 - mu0)
    crit = math.sqrt(lam) * stats.norm.isf(alpha)
    bound = detection_power_bound(lam, alpha)
    assert abs(np.mean(t1 > crit) - bound) < 4.0 * math.sqrt(bound * (1 - bound) / r)
    assert bound > pred + 0.2
    assert detection_power(0.0, n - 3, alpha) == pytest.approx(alpha)
    assert detection_power_bound(0.0, alpha) == pytest.approx(alpha)
    # Neyman-Pearson: the omnibus test never beats the bound, at any dof and noncentrality
    grid = np.linspace(0.0, 400.0, 401)
    for dof in (1, 2, 10, 100, 1000):
        assert np.all(detection_power(grid, dof, 1e-3) <= detection_power_bound(grid, 1e-3) + 1e-12)


def test_detection_power_of_a_fitted_poisson_model_against_simulation():
    """Poisson counts from two peaks (about 6 counts per bin at the top, 40 bins) fitted with
    a log-quadratic model (one peak): ``lambda`` is the deviance of the noise-free counts at
    their maximum-likelihood fit. The goodness-of-fit test's rejection rate over 600 simulated
    fits matches ``detection_power(lambda, gof of the noise-free fit)``, below the bound.
    The simulated Poisson likelihood-ratio test of two simple hypotheses (the fit against a
    source half way to the truth, 40,000 draws each) matches ``detection_power_bound``:
    the normal limit holds at these counts."""
    rng = np.random.default_rng(5)
    n, alpha = 40, 0.01
    X = _design(n)
    mu1 = _two_peaks(n, 5.0) + 1.0
    mu0 = _glm_fit(mu1[None], X, np.array([1.0, 0.0, -1.0]))[0]
    noise = PoissonCounts(background=1e-12)
    g0 = goodness_of_fit(mu1, mu0, noise, jacobian=mu0[:, None] * X)
    lam = g0.deviance
    pred = detection_power(lam, g0, alpha)
    assert 0.2 < pred < 0.8, pred
    r = 600
    y = rng.poisson(mu1, size=(r, n)).astype(float)
    fit = _glm_fit(y, X, np.array([1.0, 0.0, -1.0]))
    rej = [
        goodness_of_fit(
            y[i], fit[i], noise, jacobian=fit[i][:, None] * X, threshold=alpha
        ).model_mismatch
        for i in range(r)
    ]
    sim = float(np.mean(rej))
    assert abs(sim - pred) < 4.0 * math.sqrt(pred * (1 - pred) / r) + 0.02, (sim, pred)
    assert pred < detection_power_bound(lam, alpha) - 0.3
    # the most powerful test of mu0 against mu_h: log-likelihood ratio, critical value from
    # draws under mu0
    mu_h = mu0 + 0.5 * (mu1 - mu0)
    lam_h = float(np.sum(goodness_of_fit(mu_h, mu0, noise).deviance))
    w = np.log(mu_h / mu0)
    t0 = rng.poisson(mu0, size=(40000, n)) @ w
    t1 = rng.poisson(mu_h, size=(40000, n)) @ w
    lr = float(np.mean(t1 > np.quantile(t0, 1 - alpha)))
    bound = detection_power_bound(lam_h, alpha)
    assert 0.2 < bound < 0.8, bound
    assert lr == pytest.approx(bound, abs=0.04), (lr, bound)


def test_detection_power_rejects_bad_input():
    with pytest.raises(ValueError, match="noncentrality.*-1"):
        detection_power(-1.0, 10)
    with pytest.raises(ValueError, match="alpha.*1.5"):
        detection_power_bound(1.0, 1.5)
    with pytest.raises(ValueError, match="dof.*0"):
        detection_power(1.0, 0)


# --------------------------------------------------------------------------- marginal tests
_PATTERN = np.array([1.0, 0.6, 0.3, 0.8])  # the channels' fixed responses (C = 4)
_TILT = np.array([-1.0, -1.0 / 3.0, 1.0 / 3.0, 1.0])  # one fitted channel-dependent slope


def _channel_design(B, pattern=_PATTERN, tilt=_TILT):
    """(C * B, 4) design of ``log mu_cb = log s_c + b0 + b1 x + b2 x^2 + b3 t_c x``: a range
    profile seen through C channels with fixed responses ``s_c``, one parameter moving
    the channels apart (as a material moves the polarization channels)."""
    x = np.linspace(-1.0, 1.0, B)
    one = np.ones((pattern.size, B))
    X = np.stack([one, one * x, one * x * x, tilt[:, None] * x], -1).reshape(-1, 4)
    off = np.repeat(np.log(pattern), B)
    return X, off


def _offset_glm_fit(y, X, off, beta0, iters=30):
    b = np.tile(beta0, (y.shape[0], 1))
    for _ in range(iters):
        mu = np.exp(b @ X.T + off)
        h = np.einsum("ri,ij,ik->rjk", mu, X, X)
        b = b + np.linalg.solve(h, ((y - mu) @ X)[..., None])[..., 0]
    return np.exp(b @ X.T + off)


@pytest.mark.parametrize("b0", [0.0, 3.0])
def test_marginal_statistics_null_law_brute_force(b0):
    """The range profile (channels summed) and channel totals (bins summed) of fitted
    Poisson counts, sparse (~0.7 counts per value at the top, ~60 in all) and dense (~20): the
    statistics of 600 maximum-likelihood fits have the predicted means and spreads (the fit
    removes part of a degree of freedom from each: ``tr G``, not ``p``), the p-values are
    uniform, and the Bonferroni combination's false-alarm rate stays below its level."""
    rng = np.random.default_rng(int(10 * b0) + 50)
    B, r = 40, 600
    X, off = _channel_design(B)
    beta = np.array([b0, 0.3, -2.0, 0.4])
    mu = np.exp(X @ beta + off)
    y = rng.poisson(mu, size=(r, mu.size)).astype(float)
    fit = _offset_glm_fit(y, X, off, beta)
    noise = PoissonCounts(background=1e-12)
    res = [
        goodness_of_fit(
            y[i].reshape(4, B), fit[i].reshape(4, B), noise, jacobian=fit[i][:, None] * X
        )
        for i in range(r)
    ]
    names = [c.name for c in res[0].components]
    assert names == ["all values", "range profile", "channel totals"]
    for j, name in enumerate(names):
        # z against each fit's own null law (it moves with the fit): mean 0, variance 1
        # (sampling error of the variance of 600 z's: 0.06, 0.1 for the skewed 3-dof totals)
        z = np.array([g.components[j].z for g in res])
        assert abs(z.mean()) < 4 / math.sqrt(r), (name, z.mean())
        assert 0.65 < z.var() < 1.45, (name, z.var())
        p = np.array([g.components[j].p_value for g in res])
        assert abs(np.mean(p < 0.1) - 0.1) < 4.5 * math.sqrt(0.09 / r), (name, np.mean(p < 0.1))
    # the channel totals keep 4 - tr G degrees of freedom: the fit's offset and tilt move them
    dof_tot = np.mean([g.components[2].expected for g in res])
    assert 1.0 < dof_tot < 3.5
    pc = np.array([g.p_value for g in res])
    assert np.mean(pc < 0.1) < 0.1 + 4.5 * math.sqrt(0.09 / r)
    assert all(g.p_value == min(1.0, 3 * min(c.p_value for c in g.components)) for g in res)


def test_marginal_tests_find_a_profile_error_the_deviance_misses():
    """A feature of the target missing from the model (a bump in the range profile) shows
    in all 16 channels alike: the deviance over all 512 values spreads its power over every
    direction and rarely flags it at 1e-3, the range profile (32 sums) almost always does.
    Without a Jacobian, or with ``marginals=False``, only the deviance is tested."""
    rng = np.random.default_rng(8)
    C, B, r = 16, 32, 200
    X, off = _channel_design(B, np.linspace(0.3, 1.0, C), np.linspace(-1.0, 1.0, C))
    beta = np.array([3.0, 0.3, -2.0, 0.4])
    x = np.linspace(-1.0, 1.0, B)
    bump = 1.0 + 0.55 * np.exp(-0.5 * ((x - 0.45) / 0.08) ** 2)
    truth = np.exp(X @ beta + off) * np.tile(bump, C)
    y = rng.poisson(truth, size=(r, truth.size)).astype(float)
    fit = _offset_glm_fit(y, X, off, beta)
    noise = PoissonCounts(background=1e-12)
    res = [
        goodness_of_fit(
            y[i].reshape(C, B), fit[i].reshape(C, B), noise, jacobian=fit[i][:, None] * X
        )
        for i in range(r)
    ]
    full = np.mean([g.components[0].p_value < 1e-3 for g in res])
    prof = np.mean([g.components[1].p_value < 1e-3 for g in res])
    comb = np.mean([g.model_mismatch for g in res])
    assert full < 0.3 and prof > 0.9 and comb > 0.9, (full, prof, comb)  # 0.11, 0.98, 0.965
    assert all(g.strongest.name == "range profile" for g in res if g.model_mismatch)
    assert "range profile" in res[0].summary()
    d = res[0].to_dict()
    assert [c["name"] for c in d["components"]] == ["all values", "range profile", "channel totals"]
    g = goodness_of_fit(y[0].reshape(C, B), fit[0].reshape(C, B), noise, n_params=4)
    assert len(g.components) == 1 and g.p_value == g.components[0].p_value
    g = goodness_of_fit(
        y[0].reshape(C, B),
        fit[0].reshape(C, B),
        noise,
        jacobian=fit[0][:, None] * X,
        marginals=False,
    )
    assert len(g.components) == 1 and g.p_value == g.tail(g.deviance)


def test_marginal_statistics_gaussian_linear_fit_brute_force_and_exact_law():
    """Known Gaussian noise (sigma varying over the values) and a weighted least-squares fit
    of the linear model ``mu_cb = s_c (b0 + b1 x + b2 x^2) + b3 t_c x``: each summed
    statistic is exactly ``e^T (I - P) U U^T (I - P) e``, so 4000 fits match its predicted
    mean and spread (sampling error 2-4 %); the null law does not depend on the fit."""
    rng = np.random.default_rng(21)
    C, B, r = 4, 24, 4000
    x = np.linspace(-1.0, 1.0, B)
    s = np.repeat(_PATTERN, B)
    xx = np.tile(x, C)
    X = np.stack([s, s * xx, s * xx * xx, np.repeat(_TILT, B) * xx], 1)
    sigma = 0.5 + rng.uniform(size=C * B)
    mu = X @ np.array([2.0, 0.5, -1.0, 0.3])
    y = mu + sigma * rng.normal(size=(r, mu.size))
    w = 1.0 / sigma**2
    beta = np.linalg.solve(X.T @ (w[:, None] * X), ((y * w) @ X).T).T
    res = (y - beta @ X.T).reshape(r, C, B)
    var = (sigma**2).reshape(C, B)
    sims = [
        np.sum(res**2 / var, axis=(1, 2)),
        np.sum(res.sum(1) ** 2 / var.sum(0), axis=1),
        np.sum(res.sum(2) ** 2 / var.sum(1), axis=1),
    ]
    noise = GaussianNoise(sigma.reshape(C, B))
    g = goodness_of_fit(y[0].reshape(C, B), (beta[0] @ X.T).reshape(C, B), noise, jacobian=X)
    assert [c.name for c in g.components] == ["all values", "range profile", "channel totals"]
    for c, sim in zip(g.components, sims, strict=True):
        assert abs(sim.mean() - c.expected) < 4 * c.std / math.sqrt(r), (c.name, sim.mean())
        assert sim.std() == pytest.approx(c.std, rel=0.06), (c.name, sim.std(), c.std)
    assert g.components[0].expected == pytest.approx(C * B - 4)
    # the channel totals: 4 sums, of which the fit takes tr G (between 0 and 4)
    assert 0.5 < g.components[2].expected < 3.5
    # exactly: with Gaussian data the summed statistic is e^T (I - P) U U^T (I - P) e, a
    # weighted sum of chi-square(1) with weights the eigenvalues of I - G, G = U^T P U (not a
    # chi-square unless G is a projector): cumulants tr(I - G)^j, built here independently
    Q, _ = np.linalg.qr(X / sigma[:, None])
    P = Q @ Q.T
    for c, ax, k in zip(g.components[1:], (0, 1), (B, C), strict=True):
        grp = np.tile(np.arange(B), C) if ax == 0 else np.repeat(np.arange(C), B)
        V = np.bincount(grp, sigma**2, k)
        U = np.zeros((C * B, k))
        U[np.arange(C * B), grp] = sigma / np.sqrt(V[grp])
        IG = np.eye(k) - U.T @ P @ U
        assert not np.allclose(IG @ IG, IG, atol=1e-3)  # G is no projector here
        # sigma^2 is evaluated in float32 by the noise model: rel 1e-6
        assert c.expected == pytest.approx(np.trace(IG), rel=1e-6)
        assert c.std**2 == pytest.approx(2 * np.trace(IG @ IG), rel=1e-6)
        assert c.skewness * c.std**3 == pytest.approx(8 * np.trace(IG @ IG @ IG), rel=1e-6)


@pytest.mark.parametrize("b0", [-2.0, 0.0, 3.0])
def test_marginal_moments_reduce_to_the_validated_own_fit_formula(b0):
    """Two exact identities tie the marginal moments to the deviance's (checked by brute force
    above), sparse to dense: (1) for ``mu_cb = s_c I_b(theta)`` the range profile is
    sufficient, so its component equals the goodness of fit of the 1-D sums fitted with the
    summed Jacobian (every plug-in, curvature and kurtosis term included); (2) with nothing
    summed (``U = I``) the marginal moments are the own-fit moments. And they do not depend
    on the parameters' units (a column in units 1e5 times larger, nearly collinear with
    another)."""
    from inversion._gof import _fitted_moments, _marginal

    C, B = 4, 40
    x = np.linspace(-1.0, 1.0, B)
    Xb = np.stack([np.ones(B), x, x * x], 1)
    mu = _PATTERN[:, None] * np.exp(Xb @ np.array([b0, 0.3, -2.0]))[None, :]
    J = (mu[..., None] * Xb[None]).reshape(C * B, 3)
    noise = PoissonCounts(background=1e-12)
    y = np.random.default_rng(3).poisson(mu).astype(float)
    prof = goodness_of_fit(y, mu, noise, jacobian=J).components[1]
    Y, M = y.sum(0), mu.sum(0)
    g1 = goodness_of_fit(Y, M, noise, jacobian=M[:, None] * Xb)
    assert prof.name == "range profile"
    for a, b in [(prof.expected, g1.expected), (prof.std, g1.std), (prof.deviance, g1.deviance)]:
        assert a == pytest.approx(b, rel=1e-9, abs=1e-9)
    assert prof.skewness == pytest.approx(g1.skewness, rel=1e-8, abs=1e-9)
    # (2) U = I, with a background and a channel-dependent parameter
    X, off = _channel_design(B)
    noise = PoissonCounts(background=0.05)
    mu = np.exp(X @ np.array([b0, 0.3, -2.0, 0.4]) + off)
    Jf = mu[:, None] * X
    y = np.random.default_rng(2).poisson(mu + 0.05).astype(float)
    c = _marginal("U = I", 1, y[:, None], mu[:, None], noise, None, Jf, None, 0.0)
    mean, var, third, _ = _fitted_moments(noise, mu, None, Jf, None)
    assert (c.expected, c.std**2, c.skewness * c.std**3) == pytest.approx(
        (mean, var, third), rel=1e-9
    )
    # units: one column x 1e5 and a fifth nearly collinear with x change no component
    X5 = np.c_[X, np.tile(x + 1e-3 * x**3, 4)]
    ref = goodness_of_fit(y.reshape(4, B), mu.reshape(4, B), noise, jacobian=mu[:, None] * X5)
    sc = np.array([1.0, 1.0, 1.0, 1e5, 1.0])
    alt = goodness_of_fit(y.reshape(4, B), mu.reshape(4, B), noise, jacobian=mu[:, None] * X5 * sc)
    for c0, c1 in zip(ref.components, alt.components, strict=True):
        assert c1.expected == pytest.approx(c0.expected, rel=1e-7)
        assert c1.std == pytest.approx(c0.std, rel=1e-7)
