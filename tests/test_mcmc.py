"""Posterior sampling (inversion._mcmc): coverage, diagnostics, outputs, configs, bad input.

Uses the analytic toy forward model of ``tests/test_refine.py`` (independent of the pulse
simulator). The likelihood is Gaussian with the noise model's variance, so data drawn from
exactly that Gaussian make the coverage check exact up to the sampler's Monte Carlo error.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_refine import TRUTH, TRUTH_INTERIOR, make_toy, perturbed

from inversion._mcmc import (
    ChainTooShortWarning,
    MCMCConfig,
    WalkersRaisedWarning,
    load_mcmc_config,
    make_log_prob,
    mcmc_config_from_dict,
    sample_posterior,
)
from inversion._params import Parametrisation
from inversion._refine import PoissonNoise, refine
from ppr._config import ConfigError

# The chains run thousands of log-probability evaluations: the module compiles with JAX's
# defaults (tests/compile_level.py; unoptimized, the coverage test alone took 74 s, not 14 s)
pytestmark = pytest.mark.optimized

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "inversion" / "default.toml"
NW = 32  # one walker count everywhere: the vmapped log-probability compiles once


def _fast_config(**sampler):
    base = {"n_walkers": NW, "n_steps": 800, "burn_in": 300, "init_scale": 0.5, "progress": False}
    base.update(sampler)
    return mcmc_config_from_dict({"sampler": base}, "test")


def _noisy(model, seed, noise, truth=TRUTH_INTERIOR):
    mu = np.asarray(model.expected(truth, model.prepare(truth)))
    sig = np.sqrt(np.asarray(noise.variance(jnp.asarray(mu))))
    return mu + sig * np.random.default_rng(seed).normal(size=mu.shape)


def test_default_config_loads_and_bad_configs_are_clear(tmp_path):
    cfg = load_mcmc_config(CONFIG)
    assert cfg.priors.m.kind == "loguniform" and cfg.sampler.n_walkers == 32
    bad = tmp_path / "bad.toml"
    # (file text, what the one-line error must say); a field its kind does not take is an
    # error, not dropped (low on a normal prior would have been an untruncated normal)
    cases = [
        (
            '[priors.m]\nkind = "uniform"\nlow = 10.0\nhigh = 1.0\n',
            r"bad.toml.*priors.m.*low < high",
        ),
        ("[sampler]\nn_walkerz = 3\n", r"sampler.n_walkerz.*unknown key"),
        (
            '[priors.gain]\nkind = "loguniform"\nlow = nan\nhigh = 1.0\n',
            r"priors.gain.low = nan: not finite",
        ),
        ("[sampler]\nn_steps = 100\nburn_in = 200\n", "burn_in"),
        (
            '[priors.range_offset]\nkind = "normal"\nmean = 0.0\nsigma = 1.0\nlow = -5.0\n',
            r"a normal prior takes mean and sigma, not low = -5.0",
        ),
        (
            '[priors.attitude]\nkind = "uniform"\nsigma_deg = 3.0\n',
            "attitude prior takes no sigma_deg",
        ),
    ]
    for text, needle in cases:
        bad.write_text(text)
        with pytest.raises(ConfigError, match=needle):
            load_mcmc_config(bad)


def test_log_prob_vectorised_equals_single_and_respects_support():
    model = make_toy()
    noise = PoissonNoise()
    data = _noisy(model, 0, noise)
    par = Parametrisation(TRUTH_INTERIOR)
    lp = make_log_prob(model, data, par, MCMCConfig().priors, noise=noise)
    rng = np.random.default_rng(0)
    th = np.asarray(par.from_physical(TRUTH_INTERIOR))[None] + 0.01 * rng.normal(
        size=(NW, par.size)
    )
    batch = lp(th)
    single = eqx.filter_jit(lp.single)
    singles = np.array([float(single(jnp.asarray(t))) for t in th[:4]])
    np.testing.assert_allclose(batch[:4], singles, rtol=1e-12)  # same float64 arithmetic
    assert batch.dtype == np.float64 and np.all(np.isfinite(batch))
    out = th.copy()
    out[0, 3] = np.log(2e6)  # m above the prior's upper bound 1e6
    out[1, 7] = -30.0  # n''[0] below the reparametrisation clamp: no mass there
    assert lp(out)[0] == -np.inf and lp(out)[1] == -np.inf and np.isfinite(lp(out)[2])


def test_prior_without_support_at_start_is_a_clear_error():
    model = make_toy()
    data = _noisy(model, 1, PoissonNoise())
    cfg = mcmc_config_from_dict({"priors": {"m": {"kind": "uniform", "low": 50.0, "high": 100.0}}})
    with pytest.raises(
        ValueError, match=r"no support.*m\[0\] = 6 outside the uniform prior's support \[50, 100\]"
    ):
        sample_posterior(model, data, TRUTH, config=cfg)


def test_bad_observation_is_a_clear_error():
    model = make_toy()
    data = _noisy(model, 1, PoissonNoise())
    with pytest.raises(ValueError, match="range bins"):
        sample_posterior(model, data[:, :-1], TRUTH, config=_fast_config())
    data[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        sample_posterior(model, data, TRUTH, config=_fast_config())


def test_short_chain_warns_and_outputs_are_written(tmp_path):
    model = make_toy()
    noise = PoissonNoise()
    data = _noisy(model, 2, noise)
    ref = refine(model, data, perturbed(TRUTH_INTERIOR, 1.0), noise=noise)
    assert ref.success, ref.summary()
    h5 = tmp_path / "chain.h5"
    with pytest.warns(ChainTooShortWarning, match="too short"):
        res = sample_posterior(
            model, data, ref, config=_fast_config(n_steps=60, burn_in=10), noise=noise, path=h5
        )
    assert not res.converged
    assert res.chain.shape == (60, NW, 11) and res.samples.shape == (50 * NW, 11)
    # the chain on disk is emcee's HDF5 format and equals the returned chain
    back = emcee.backends.HDFBackend(str(h5), read_only=True)
    np.testing.assert_array_equal(back.get_chain(), res.chain)
    assert 0.05 < np.mean(res.acceptance_fraction) < 0.9
    assert np.all(res.ess > 0) and np.all(np.isfinite(res.tau))
    iv = res.interval(0.95)
    assert iv.shape == (11, 2) and np.all(iv[:, 0] <= iv[:, 1])
    png = res.corner_plot(tmp_path / "corner.png", truth=TRUTH_INTERIOR)
    assert png.stat().st_size > 1000
    assert "acceptance" in res.summary()
    # too few walkers for the 11 sampled parameters: emcee's moves need 2 x 11; the run goes
    # on with 22 and says so, naming the setting (the refinement before it is not lost)
    with (
        pytest.warns(WalkersRaisedWarning, match="sampler.n_walkers = 8 is below twice the 11"),
        pytest.warns(ChainTooShortWarning),
    ):
        few = sample_posterior(
            model, data, ref, config=_fast_config(n_walkers=8, n_steps=20, burn_in=5), noise=noise
        )
    assert few.chain.shape == (20, 22, 11)


def test_posterior_coverage_small():
    """Truth inside the 99% (and 68%) intervals at the expected rate over seeded trials.

    The truth is interior (n'' > 0: an equal-tailed interval cannot contain a truth on the
    n'' = 0 boundary) and well constrained (gain 30). 6 trials x 11 parameters = 66 interval
    checks (not independent within a trial: the binomial bound is approximate). 99%: expected
    0.66 misses; P(misses >= 5) = 0.0006 under Binomial(66, 0.01) -> allow <= 4. 68%: expected
    44.9 hits, sd 3.8 -> allow 34..56 (~3 sd), which also fails if the intervals are far too
    wide (the 99% check alone would not).
    """
    model = make_toy()
    noise = PoissonNoise(floor=1.0)
    cfg = _fast_config()
    miss99 = hit68 = total = 0
    for seed in range(6):
        data = _noisy(model, 100 + seed, noise)
        ref = refine(model, data, perturbed(TRUTH_INTERIOR, 1.5, seed=seed), noise=noise)
        assert ref.success, ref.summary()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ChainTooShortWarning)  # judged by coverage here
            res = sample_posterior(model, data, ref, config=cfg, noise=noise)
        tv = res.truth_vector(TRUTH_INTERIOR)
        miss99 += int(np.sum(~res.contains(tv, 0.99)))
        hit68 += int(np.sum(res.contains(tv, 0.68)))
        total += tv.size
        assert np.min(res.ess) > 100, res.summary()
    assert total == 66
    assert miss99 <= 4, (miss99, hit68)
    assert 34 <= hit68 <= 56, (miss99, hit68)


def test_autocorr_of_a_parameter_that_never_moved():
    """A parameter whose series is constant in every walker (no accepted move changed it) has
    an undefined autocorrelation estimate: reported as tau = inf (ESS 0), not converged, with
    a warning naming it; the other parameters keep their estimates."""
    from inversion._mcmc import _autocorr

    rng = np.random.default_rng(0)
    kept = np.zeros((400, 8, 3))
    kept[..., 0] = rng.normal(size=(400, 8))  # white noise: tau ~ 1
    kept[..., 1] = 0.25  # never moved
    kept[..., 2] = np.cumsum(rng.normal(size=(400, 8)), axis=0) * 1e-3 + 1.0  # random walk
    with pytest.warns(ChainTooShortWarning, match=r"parameters \[1\]"):
        tau, converged = _autocorr(kept, 50.0)
    assert not converged
    assert np.isinf(tau[1]) and np.all(np.isfinite(tau[[0, 2]]))
    assert 0.5 < tau[0] < 2.0


def test_starting_ball_spreads_where_the_data_do_not_constrain():
    """The refined covariance is a pseudo-inverse: 0 in an exactly unconstrained direction.
    The starting ball keeps the data's covariance where they constrain (within the
    regularization's relative 4e-4 here) and gets the prior scale, not zero, in the null
    direction (a walker ensemble collapsed there mixes in it only by slow expansion)."""
    from inversion._mcmc import BALL_PRIOR_SCALE, _ball_root

    rot = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    cov = rot @ np.diag([1e-4, 0.0, 4e-6]) @ rot.T
    root = _ball_root(cov, 3)
    ball = root @ root.T
    null = rot[:, 1]
    assert np.isclose(null @ ball @ null, BALL_PRIOR_SCALE**2, rtol=1e-9)
    for i, var in ((0, 1e-4), (2, 4e-6)):
        d = rot[:, i]
        assert np.isclose(d @ ball @ d, var / (1 + var / BALL_PRIOR_SCALE**2), rtol=1e-9)
    assert np.allclose(_ball_root(None, 3), 1e-2 * np.eye(3))


def test_reflectance_shear_is_a_unit_jacobian_bijection():
    """The sampler's coordinates shift the log gain by a function of the index entries only:
    the map inverts exactly and its Jacobian determinant is 1 (finite differences), so the
    log-posterior needs no correction; the shift is the log normal-incidence reflectance."""
    from inversion._mcmc import _ReflectanceShear
    from inversion._params import Parametrisation

    param = Parametrisation(TRUTH_INTERIOR)
    assert _ReflectanceShear.applies(param)
    sh = _ReflectanceShear(param)
    rng = np.random.default_rng(0)
    theta = np.asarray(param.from_physical(TRUTH_INTERIOR)) + 0.3 * rng.normal(size=(5, param.size))
    np.testing.assert_allclose(sh.inverse(sh.forward(theta)), theta, rtol=0, atol=1e-14)
    h = 1e-6
    for t in theta:
        jac = np.stack(
            [(sh.forward(t + h * e) - sh.forward(t - h * e)) / (2 * h) for e in np.eye(t.size)], 1
        )
        assert abs(np.linalg.det(jac) - 1.0) < 1e-8
    n = np.asarray(param.to_physical(jnp.asarray(theta[0])).n)
    r0 = np.abs((n - 1) / (n + 1)) ** 2
    assert np.isclose(sh.shift(theta[0]), np.log(np.mean(r0) + 1e-4), rtol=1e-12)
    assert not _ReflectanceShear.applies(Parametrisation(TRUTH_INTERIOR, ("attitude", "gain")))


def test_roll_separated_coordinates_cover_so3_once_with_the_haar_volume():
    """The sampler's attitude coordinates ``(t_1, t_2, phi)``, ``exp(w) = exp(phi k) exp(t)``
    about an oblique line of sight ``k``: the map inverts exactly, ``phi`` is the roll about
    ``k`` (a pure roll maps to ``(0, 0, phi)``), and the Haar density ``4 sin^2(a/2) / a^2``
    of ``w`` times ``|det dw/d(t, phi)|`` integrates over the coordinates' box to the volume
    of SO(3) in rotation-vector coordinates, ``8 pi^2`` (Monte Carlo, 0.5 %): every rotation
    is counted once, so the corrected density is the posterior's."""
    from inversion._mcmc import _RollSeparation
    from inversion._params import Parametrisation

    param = Parametrisation(TRUTH_INTERIOR, ("attitude", "m", "gain"))
    k = np.array([0.3, 0.1, 0.95]) / np.linalg.norm([0.3, 0.1, 0.95])
    rs = _RollSeparation(param, k)
    rng = np.random.default_rng(0)
    theta = 0.8 * rng.normal(size=(200, param.size))
    theta = theta[np.linalg.norm(theta[:, :3], axis=1) < 3.0]
    np.testing.assert_allclose(rs.inverse(rs.forward(theta)), theta, rtol=0, atol=1e-12)
    roll = np.zeros((1, param.size))
    roll[0, :3] = 1.2 * k
    np.testing.assert_allclose(rs.forward(roll)[0, :3], [0.0, 0.0, 1.2], atol=1e-12)
    n = 200_000
    s = np.zeros((n, param.size))
    s[:, :3] = rng.uniform(-np.pi, np.pi, size=(n, 3))
    lj = rs.log_jacobian(s)
    a = np.linalg.norm(rs.inverse(s)[:, :3], axis=1)
    haar = 4.0 * np.sin(a / 2) ** 2 / np.maximum(a, 1e-12) ** 2
    vol = (2 * np.pi) ** 3 * np.mean(np.where(np.isfinite(lj), haar * np.exp(lj), 0.0))
    assert abs(vol / (8 * np.pi**2) - 1) < 5e-3, vol


@pytest.mark.parametrize("moves", ["stretch", "de_snooker"])
def test_gain_posterior_is_the_closed_form_gamma(moves):
    """Poisson counts k with expected ``g t`` and a log-uniform gain prior: the posterior of
    the gain is exactly Gamma(shape = sum k, rate = sum t) (background -> 0). Both emcee
    proposals (``sampler.moves``) reproduce its 5/50/95 % quantiles to 0.1 posterior sd
    (Monte Carlo error with >= 10^3 effective samples: ~0.04 sd)."""
    from scipy import stats
    from test_refine import TinyCounts, _sparse_counts

    from inversion._params import PhysicalParams
    from inversion._refine import PoissonCounts

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=0.02)
    data, _ = _sparse_counts(model, truth, seed=5)
    unit = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=1.0)
    t_sum = float(np.asarray(model.expected(unit, model.prepare(unit))).sum())
    post_ref = stats.gamma(a=data.sum(), scale=1.0 / t_sum)
    noise = PoissonCounts(background=1e-12)
    fit = refine(model, data, unit, noise=noise, free=("gain",))
    cfg = mcmc_config_from_dict(
        {
            "priors": {"gain": {"kind": "loguniform", "low": 1e-6, "high": 1e6}},
            # tau 21-27 steps across seeds and gain coordinates: 1700 kept > 50 tau
            "sampler": {"n_walkers": NW, "n_steps": 2000, "burn_in": 300, "moves": moves},
        }
    )
    res = sample_posterior(model, data, fit, config=cfg, noise=noise)
    g = res.samples[:, res.labels.index("gain")]
    q = np.quantile(g, [0.05, 0.5, 0.95])
    np.testing.assert_allclose(q, post_ref.ppf([0.05, 0.5, 0.95]), atol=0.1 * post_ref.std())
    assert res.converged and np.min(res.ess) > 1000, res.summary()


class ParityToy(eqx.Module):
    """Counts whose pulse sits at ``0.05 (log m)^2``: the likelihood is even in ``log m``, so
    the posterior has two mirror modes of equal mass (the parity of a mirror-symmetric body,
    in one dimension)."""

    bins: jax.Array

    def prepare(self, phys):
        return jnp.ones((), self.bins.dtype)

    def expected(self, phys, aux):
        x = jnp.log(phys.m[0])
        prof = jnp.exp(-0.5 * ((self.bins - 0.05 * x * x) / 0.03) ** 2)
        return aux * phys.gain * jnp.stack([prof, 0.5 * prof]) + 0.5


def test_two_mode_mixture_matches_quadrature():
    """A chain started in one mode of a two-mode posterior never visits the other (the gap
    is ~10^3 posterior sd wide); ``sample_modes`` samples each mode and weights them by
    ``exp(-cost/2)``: weights 1/2 each (exact parity), and its 5/25/75/95 % quantiles of
    ``log m`` match a 1-D quadrature of the exact posterior (flat prior in log m) to 0.1
    mode sd (the median of two equal modes is undefined: it falls in the gap)."""
    from test_refine import _sparse_counts

    from inversion._mcmc import sample_modes
    from inversion._params import PhysicalParams
    from inversion._refine import PoissonCounts

    model = ParityToy(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [np.e], [1.5 + 0j], gain=300.0)
    data, _ = _sparse_counts(model, truth, seed=2)
    noise = PoissonCounts(background=1e-12)
    fits = [
        refine(
            model,
            data,
            PhysicalParams([1.0, 0, 0, 0], [np.exp(s)], [1.5 + 0j], gain=300.0),
            noise=noise,
            free=("m",),
        )
        for s in (0.8, -0.8)
    ]
    xs = [float(np.log(f.params.m[0])) for f in fits]
    assert xs[0] > 0.5 and xs[1] < -0.5 and abs(xs[0] + xs[1]) < 1e-6
    cfg = mcmc_config_from_dict({"sampler": {"n_walkers": NW, "n_steps": 2000, "burn_in": 400}})
    mix = sample_modes(model, data, fits, config=cfg, noise=noise)
    np.testing.assert_allclose(mix.weights, [0.5, 0.5], atol=1e-6)
    for j, mode in enumerate(mix.modes):  # each chain stays in its own mode
        x = np.log(mode.samples[:, mode.labels.index("m[0]")])
        assert np.all(np.sign(x) == np.sign(xs[j]))
    # exact 1-D posterior in x = log m by quadrature (log-uniform prior: flat in x)
    grid = np.linspace(-1.3, 1.3, 200001)
    aux = model.prepare(truth)
    mu = jax.vmap(
        lambda g: model.expected(
            PhysicalParams([1.0, 0, 0, 0], jnp.exp(g)[None], [1.5 + 0j], gain=300.0), aux
        )
    )(jnp.asarray(grid))
    loglik = np.asarray(jnp.sum(data * jnp.log(mu) - mu, axis=(1, 2)))
    w = np.exp(loglik - loglik.max())
    cdf = np.cumsum(w) / np.sum(w)
    ref_q = np.interp([0.05, 0.25, 0.75, 0.95], cdf, grid)
    k, rows = mix.draw(40000, seed=1)
    i = mix.modes[0].labels.index("m[0]")
    x = np.log([mix.modes[j].samples[r, i] for j, r in zip(k, rows, strict=True)])
    sd = np.std(x[x > 0])
    np.testing.assert_allclose(np.quantile(x, [0.05, 0.25, 0.75, 0.95]), ref_q, atol=0.1 * sd)
    # mass of the positive mode: 1/2 by parity (quadrature), binomial sd of 40000 draws 0.0025
    assert abs(np.mean(x > 0) - 0.5) < 0.01 and abs(cdf[grid > 0][0] - 0.5) < 1e-3
    lo, hi = mix.interval("m[0]", 0.90)
    np.testing.assert_allclose(np.log([lo, hi]), ref_q[[0, 3]], atol=0.1 * sd)
    with pytest.raises(ValueError, match="fits is empty"):
        sample_modes(model, data, [], config=cfg, noise=noise)
    # a mode with weight but no samples is named, not indexed past its end
    import dataclasses

    starved = dataclasses.replace(mix.modes[1], samples=mix.modes[1].samples[:0])
    bad = dataclasses.replace(mix, modes=(mix.modes[0], starved))
    with pytest.raises(ValueError, match="mode 1 has weight .* but no samples"):
        bad.draw(10)


def test_library_index_posterior_is_the_closed_form_material_mixture():
    """The index sampled over a library of materials (``sampler.index = "library"``, with
    the material jumps and the total-signal gain coordinate): Poisson counts ``k`` with
    expected ``g t_k`` (``t_k`` the gain-1 profile of material ``k``) and a log-uniform gain
    prior give, exactly, ``p(k | d) propto prod t_k^d / T_k^D`` (``T_k = sum t_k``,
    ``D = sum d``) and ``g | k ~ Gamma(D, T_k)``. The chain's material frequencies match
    those probabilities to 0.03 and the gain's 5/50/95 % quantiles match the Gamma mixture's
    to 0.1 sd: the coordinate change, its prior correction and the moves are exact."""
    from scipy.special import xlogy
    from test_refine import TinyCounts, _sparse_counts

    from inversion._params import PhysicalParams
    from inversion._refine import PoissonCounts

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    lib = [1.3 + 0.4j, 1.6 + 0.1j, 1.2 + 1.0j]

    def phys(n, gain):
        return PhysicalParams([1.0, 0, 0, 0], [12.0], [n], range_offset=0.01, gain=gain)

    data, _ = _sparse_counts(model, phys(lib[0], 0.004), seed=7)
    t = [
        np.maximum(np.asarray(model.expected(phys(n, 1.0), model.prepare(phys(n, 1.0)))), 0.0)
        for n in lib
    ]
    d_sum = data.sum()
    logp = np.array([np.sum(xlogy(data, tk)) - d_sum * np.log(tk.sum()) for tk in t])
    p_ref = np.exp(logp - logp.max())
    p_ref /= p_ref.sum()
    assert 0.05 < p_ref.min() and p_ref.max() < 0.8, p_ref  # a real mixture
    noise = PoissonCounts(background=1e-12)
    fit = refine(model, data, phys(1.5 + 0.3j, 0.004), noise=noise, free=("n", "gain"))
    optima = [[phys(n, d_sum / tk.sum()) for n, tk in zip(lib, t, strict=True)]]
    cfg = mcmc_config_from_dict(
        {
            "priors": {"gain": {"kind": "loguniform", "low": 1e-8, "high": 1e4}},
            "sampler": {"n_walkers": NW, "n_steps": 1500, "burn_in": 300},
        }
    )
    res = sample_posterior(
        model, data, fit, config=cfg, noise=noise, materials=lib, material_fits=optima
    )
    n_re = res.samples[:, res.labels.index("n_re[0]")]
    freq = np.array([np.mean(np.isclose(n_re, n.real)) for n in lib])
    assert freq.sum() == 1.0
    np.testing.assert_allclose(freq, p_ref, atol=0.03)
    g = res.samples[:, res.labels.index("gain")]
    rng = np.random.default_rng(0)
    k = rng.choice(len(lib), size=200_000, p=p_ref)
    ref = rng.gamma(d_sum, 1.0 / np.array([tk.sum() for tk in t])[k])
    q = np.quantile(g, [0.05, 0.5, 0.95])
    np.testing.assert_allclose(q, np.quantile(ref, [0.05, 0.5, 0.95]), atol=0.1 * ref.std())


def test_roll_separated_sampler_draws_the_haar_measure():
    """Data that do not depend on the attitude (``ParityToy``) leave the attitude posterior
    equal to its uniform (Haar) prior, under which the rotation angle ``a`` about the start
    has the closed-form density ``(1 - cos a) / pi`` on ``[0, pi]``. Sampled in the
    roll-separated coordinates with the roll's independence moves (and the gain as the log
    total signal), the chain's angle quantiles match ``F(a) = (a - sin a) / pi`` to 0.05
    rad and the roll about the line of sight is uniform (mean cos/sin of twice the twist
    within 0.05 of 0): the coordinates' Jacobian and the moves leave the posterior exact."""
    from scipy.optimize import brentq
    from test_refine import _sparse_counts

    from inversion._mcmc import _RollSeparation
    from inversion._params import PhysicalParams
    from inversion._refine import PoissonCounts

    model = ParityToy(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [np.e], [1.5 + 0j], gain=300.0)
    data, _ = _sparse_counts(model, truth, seed=3)
    cfg = mcmc_config_from_dict(
        {"sampler": {"n_walkers": NW, "n_steps": 1000, "burn_in": 200, "init_scale": 1.0}}
    )
    with warnings.catch_warnings():  # tau of the flat attitude: ~50 steps
        warnings.simplefilter("ignore", ChainTooShortWarning)
        res = sample_posterior(
            model,
            data,
            truth,
            config=cfg,
            noise=PoissonCounts(background=1e-12),
            free=("attitude", "gain"),
        )
    kept = res.chain[res.burn_in :].reshape(-1, res.chain.shape[-1])
    a = np.linalg.norm(kept[:, :3], axis=1)
    levels = np.array([0.1, 0.25, 0.5, 0.75, 0.9])
    ref = [brentq(lambda x, p=p: (x - np.sin(x)) / np.pi - p, 0.0, np.pi) for p in levels]
    np.testing.assert_allclose(np.quantile(a, levels), ref, atol=0.05)
    rs = _RollSeparation(res.parametrisation)
    phi = rs.forward(kept)[:, 2]
    assert abs(np.mean(np.cos(phi))) < 0.05 and abs(np.mean(np.sin(phi))) < 0.05


def test_library_walkers_start_in_the_sampled_mode_when_the_optima_are_elsewhere():
    """The per-material optima handed to the sampler can sit in another mode than the one
    sampled (``inversion.invert`` runs its material stage at the first fit; a mirror image
    can be the best mode). The walkers must start in the sampled mode, moved only by the
    optima's differences: here the optima are displaced by 15 cm in range (far outside the
    posterior, whose range sd is ~1 mm), and every walker's first log-posterior is within 30
    of the best one (a displaced start: ~-1e4), its range offset within 1 cm of the fit's."""
    from test_refine import TinyCounts, _sparse_counts

    from inversion._params import PhysicalParams
    from inversion._refine import PoissonCounts

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    lib = [1.3 + 0.4j, 1.6 + 0.1j, 1.2 + 1.0j]

    def phys(n, gain, off=0.01):
        return PhysicalParams([1.0, 0, 0, 0], [12.0], [n], range_offset=off, gain=gain)

    data, _ = _sparse_counts(model, phys(lib[0], 0.004), seed=7)
    noise = PoissonCounts(background=1e-12)
    fit = refine(model, data, phys(lib[0], 0.004), noise=noise, free=("n", "gain", "range_offset"))
    elsewhere = [[phys(n, 0.004, off=0.16) for n in lib]]
    cfg = mcmc_config_from_dict(
        {
            "priors": {"gain": {"kind": "loguniform", "low": 1e-8, "high": 1e4}},
            "sampler": {"n_walkers": NW, "n_steps": 20, "burn_in": 5},
        }
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ChainTooShortWarning)
        res = sample_posterior(
            model, data, fit, config=cfg, noise=noise, materials=lib, material_fits=elsewhere
        )
    off0 = res.physical_chain[0, :, res.labels.index("range_offset [m]")]
    assert np.all(np.abs(off0 - float(fit.params.range_offset)) < 0.01), off0
    assert np.min(res.log_prob[0]) > np.max(res.log_prob) - 30, res.log_prob[0]


def test_independence_and_roll_moves_are_exact_with_a_misfitted_proposal():
    """The burn-in-fitted independence move (``_IndependenceMove``: Student-t per discrete key,
    the roll folded into its half-circle) and the half-circle roll move (``_RollMove``) leave
    the target invariant whatever the proposal was fitted to. The target: ``z`` uniform on
    [0, 2) (a library coordinate, key ``floor(z)``), and given the key a correlated Gaussian
    in ``(a0, a1, phi)`` whose mean moves with the key, ``phi`` a roll on ``[-pi, pi]``
    (12 % of its mass in the outer half ``|phi| >= pi/2``, where both moves propose the half
    turn's image of their draws). The independence move is fitted to samples with the wrong
    mean (+0.7 sd) and scales 0.6 sd (key 0) and 1.22 sd (key 1); it carries 30 % of the
    steps and its jumping variant, which also draws a new key and lands in that key's
    component, another 30 % (roll moves 10 %, jumps translated by the keys' means 10 %,
    the stretch move 20 %). The keys must be equally likely and the chain's 5/50/95 %
    quantiles of every coordinate per key must match the closed form to 0.1 sd: with a
    wrong Hastings factor (e.g. without the components' normalizations, which differ by
    the scales' determinants), confinement or half-circle rule the chain would lean toward
    the misfitted proposal. Fitted to the target itself, the continuous coordinates
    forget their state in a few steps (tau < 8)."""
    from inversion._mcmc import _IndependenceMove, _MaterialMove, _RollMove

    cov = np.array([[1.0, 0.5, 0.3], [0.5, 2.0, 0.0], [0.3, 0.0, 1.0]])
    prec = np.linalg.inv(cov)
    means = np.array([[0.0, 0.0, 0.0], [3.0, -1.0, 0.0]])

    def log_p(y):
        y = np.atleast_2d(y)
        z = y[:, 3]
        inside = (z >= 0) & (z < 2) & (np.abs(y[:, 2]) <= np.pi)
        k = np.clip(np.floor(z), 0, 1).astype(int)
        d = y[:, :3] - means[k]
        lp = -0.5 * np.einsum("ij,jk,ik->i", d, prec, d)
        return np.where(inside, lp, -np.inf)

    rng = np.random.default_rng(3)
    fake = []
    for k, c2 in ((0, 0.36), (1, 1.5)):
        g = rng.multivariate_normal(means[k] + 0.7 * np.sqrt(np.diag(cov)), c2 * cov, 400)
        fake.append(np.column_stack([g, k + rng.uniform(0, 1, 400)]))
    fake = np.concatenate(fake)[:, None, :]
    # the key jumps like a library material, translated between the keys' means
    shifts = np.zeros((1, 2, 4))
    shifts[0, :, :3] = means
    jump = _MaterialMove([3], 2, shifts)

    def run(samples, roll, steps):
        move = _IndependenceMove.fit(samples, fixed=[3], roll=roll)
        assert set(move.comps) == {(0,), (1,)}
        nw = 16
        p0 = np.column_stack([rng.normal(size=(nw, 3)), rng.uniform(0, 2, nw)])
        moves = [(jump, 0.2), (emcee.moves.StretchMove(), 0.2)]
        if roll is None:
            moves += [(move, 0.6)]
        else:
            moves = [(jump, 0.1), (emcee.moves.StretchMove(), 0.2), (_RollMove(roll), 0.1)]
            moves += [(move, 0.3), (move.jumping(2), 0.3)]
        sampler = emcee.EnsembleSampler(nw, 4, log_p, vectorize=True, moves=moves)
        sampler.random_state = np.random.RandomState(1).get_state()
        sampler.run_mcmc(p0, steps)
        tau = emcee.autocorr.integrated_time(sampler.get_chain(discard=200), quiet=True)
        return sampler.get_chain(discard=200, flat=True), tau

    # fitted to the target itself, no roll: every coordinate forgets its state in a few
    # steps (the stretch move with the same jumps instead: tau 26-94)
    exact = np.concatenate(
        [
            np.column_stack([rng.multivariate_normal(means[k], cov, 400), k + 0.5 + np.zeros(400)])
            for k in (0, 1)
        ]
    )
    _, tau = run(exact[:, None, :], None, 1200)
    assert np.max(tau[:3]) < 8, tau
    s, _ = run(fake, 2, 12000)
    key = np.floor(s[:, 3]).astype(int)
    assert abs(np.mean(key) - 0.5) < 0.05
    assert 0.06 < np.mean(np.abs(s[:, 2]) >= np.pi / 2) < 0.18
    outer = np.abs(s[:, 2]) >= np.pi / 2
    for k in (0, 1):
        exact = rng.multivariate_normal(means[k], cov, 1_000_000)
        exact = exact[np.abs(exact[:, 2]) <= np.pi]
        exact_outer = np.abs(exact[:, 2]) >= np.pi / 2
        sel = key == k
        assert abs(np.mean(outer[sel]) - np.mean(exact_outer)) < 0.03
        # per half-circle, the conditionals the two moves sample: the inner half to 0.1 sd;
        # the outer half (12 % of the samples, whose two sides exchange walkers only through
        # the moves' draws) to 0.25 sd, |phi| there to 0.1 rad
        for h, tol in ((False, 0.1), (True, 0.25)):
            rows, ref_rows = s[sel & (outer == h)], exact[exact_outer == h]
            cols = (0, 1, 2) if not h else (0, 1)
            for j in cols:
                q = np.quantile(rows[:, j], [0.05, 0.5, 0.95])
                ref = np.quantile(ref_rows[:, j], [0.05, 0.5, 0.95])
                np.testing.assert_allclose(
                    q, ref, atol=tol * np.sqrt(cov[j, j]), err_msg=f"key {k} outer {h} col {j}"
                )
            if h:
                assert abs(np.mean(np.abs(rows[:, 2])) - np.mean(np.abs(ref_rows[:, 2]))) < 0.1
