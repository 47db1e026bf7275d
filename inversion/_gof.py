r"""Calibrated goodness of fit: the deviance at a fit against its exact null distribution.

**Statistic.** The deviance the refiner minimises (:attr:`RefineResult.cost`):

- :class:`~inversion.PoissonCounts`: the Poisson deviance ``D = sum_i d(y_i; lam_i)``,
  ``d(y; lam) = 2 [y log(y / lam) - (y - lam)]`` (``d(0; lam) = 2 lam``) with
  ``lam = expected + background``;
- :class:`~inversion.PoissonNoise`, :class:`~inversion.GaussianNoise` (and any noise model
  that only defines ``variance``): the Pearson chi-square ``X = sum_i (y_i - mu_i)^2 / v_i``
  with the model's variance ``v_i = variance(mu_i)``.

**Null moments, per bin, at the fitted expectation.** The chi-squared rule of thumb
(``E = n - p``, ``Var = 2 (n - p)``) is wrong for sparse counts: a bin with ``lam = 0.01``
contributes ``E d = 0.092`` (``~ 2 lam log(1/lam)``), not 1, and most bins of a
photon-starved return are like that.
Here every bin's mean, variance and third cumulant are exact:

- Poisson, ``lam <= 100``: sums over the probability mass function,
  ``E d = sum_y p(y; lam) d(y; lam)`` and likewise for the central moments, truncated at
  ``y <= lam + 12 sqrt(lam) + 30`` (the tail beyond holds less than ``1e-30`` of the mass);
- Poisson, ``lam > 100``: the asymptotic series in ``1/lam``, derived from the Poisson central
  moments (expanding ``d = 2 lam [(1 + e) log(1 + e) - e]`` in ``e = (y - lam)/lam``)::

      E d   = 1 + 1/(6 lam) + 1/(6 lam^2) + 19/(60 lam^3) + 9/(10 lam^4) + 863/(252 lam^5)
      Var d = 2 + 2/(3 lam) + 4/(3 lam^2) + 701/(180 lam^3) + 449/(30 lam^4)
              + 90329/(1260 lam^5)
      k3 d  = 8 + 4/lam + 12/lam^2 + 283/(6 lam^3) + 1144/(5 lam^4) + 1430593/(1080 lam^5)

  At ``lam = 100`` the series and the sums agree to 2e-11 (mean) and 4e-10 (variance)
  (``tests/test_gof.py``);
- Gaussian models: ``X_i = Z_i^2`` with ``Z_i = (y_i - mu_i) / sqrt(v_i)``. For
  :class:`~inversion.GaussianNoise` ``Z`` is normal: ``(1, 2, 8)`` per bin. For
  :class:`~inversion.PoissonNoise` the data are the counting process the variance describes:
  photo-counts (negative binomial with ``M`` speckle cells, Poisson without speckle) times
  ``g`` (the gain for ``counts_per_photon = "gain"``, else 1), plus Gaussian noise of variance
  ``floor``. Its cumulants ``kappa_n = g^n M sum_j S(n, j) (j - 1)! (lam / M)^j``
  (``lam = mu / g`` photons; ``S`` Stirling numbers of the second kind; ``kappa_n = g^n lam``
  for Poisson) give ``E X_i = 1``, ``Var X_i = 2 + kappa_4 / v^2`` and the third cumulant from
  the sixth moment: the variance depends on ``mu``, and so does the kurtosis it implies. The
  ``floor`` is taken as real noise in the data: on pure Poisson data the statistic is then
  smaller than expected (a conservative test).

**Fitted parameters.** A fit of ``p`` parameters absorbs part of the noise: to leading
order ``E[D_fit] = sum_i E d_i - p``, ``Var = sum_i Var d_i - 2 p``, ``k3 = sum k3_i - 8 p``
(the likelihood-ratio statistic of ``p`` locally identifiable parameters is chi-square with
``p`` degrees of freedom, asymptotically in the total information, not per bin), with the
moments evaluated at the fitted expectation. That plug-in is not enough for sparse counts:
there ``E d ~ 2 mu log(1/mu)`` moves with the fitted ``mu``, which follows the counts, so the
deviance and its plug-in mean fluctuate together (brute force on a 3-parameter Poisson fit of
56 counts in 300 bins: the plug-in's z-score has variance 0.2, not 1). Given the fit's
Jacobian (:func:`goodness_of_fit` ``jacobian=``, :func:`fit_goodness_of_fit`), the first-
and second-order estimation terms are included (:func:`_fitted_moments`): z-score variance
0.93, rejection rates nominal (``bench/results/gof_calibration.md``). ``p`` is then the
number of *observable* directions of the fit (:func:`inversion.observability`): an
unconstrained direction (a roll about the line of sight) removes nothing.

**Reference distribution.** The deviance of sparse counts is skewed (a sum of mostly small
values and a few large ones), so a normal reference gives too many small p-values (measured:
5e-3 at a nominal 1e-3 on a mixed profile). The p-value is the upper tail of a Pearson
type III (shifted gamma) law matched to the first three cumulants, measured within 15 % of
nominal at levels down to 1e-3 on sparse, mixed and dense profiles and counting noise (2e5
simulated deviances each); a two-moment gamma was off by up to 2x, the normal by 5x.

**Marginal tests.** The deviance over all ``n`` values is an omnibus test: its null law
has as many effective degrees of freedom as values carrying counts (~340 of 1024 in the
benches), so a misfit of size ``lambda`` must reach ``~ 3 sqrt(2 dof)`` to show. A wrong
shape does not spread its misfit that way: it puts light at the wrong ranges in every
polarization channel alike (the channels see one Mueller response per range bin, near-equal
over a single-material target), so the misfit lies almost entirely in the *range profile*,
the data summed over channels; a wrong material or index moves the *channel totals*, the
data summed over range bins. Each sum is itself Poisson (or Gaussian) data, and its
deviance is tested against its null moments after the fit: the sums' exact cumulants with
the fit's second-order corrections (:func:`_marginal`: the fit, made on all values, removes
``tr G <= p`` degrees of freedom from a sum, ``G`` the overlap of the fitted directions with
the summed ones). For a ``(C, B)`` observation fitted
with its Jacobian the family is {all values, range profile, channel totals} and the
reported p-value is their Bonferroni combination ``min(1, K min_k p_k)``: its false-alarm
rate is at most the level whatever the correlation between the three. On the out-of-bank
bench's misses of the deviance alone the range profile's 64 sums held 95-100 % of the
misfit at ~25 effective degrees of freedom (``bench/results/inversion_oob.md``: physically
detectable mismatches at SNR >= 100 detected 62 of 64 times, 56 by the deviance alone);
``tests/test_gof.py`` checks the null moments of both sums by brute force (600 fits, sparse
and dense) and the power gain on a profile error (0.11 -> 0.98 at 1e-3).

**Allowance.** ``allowance = lambda`` tests "the model misses by at most ``lambda``" instead
of "the model is exact" (used by the classifier for the template grid's resolution): a
model error of Pearson size ``lambda`` adds ``lambda`` to the mean, ``4 lambda`` to the
variance and ``24 lambda`` to the third cumulant (the non-central chi-square's cumulants);
each marginal statistic gets the same allowance (a conservative choice: a sum's share of the
model error is at most all of it).

**Detectability.** A model error is only detectable if the data carry it. Fit the model to
the *expected* data of the true source (noise-free; the deviance accepts non-integer
counts): the minimum deviance ``lambda = D(mu_true, mu_0)`` is the noncentrality, ``mu_0``
the closest model expectation found (any model expectation gives a valid, looser bound).
By Neyman-Pearson no level-``alpha`` test of "the model holds" has more power at ``mu_true``
than the likelihood-ratio test of the simple hypotheses ``mu_0`` against ``mu_true``, whose
statistic is normal with mean difference ``lambda`` and variance ``lambda`` for large
counts: power ``<= Phi(sqrt(lambda) - z_alpha)`` (:func:`detection_power_bound`). This
goodness-of-fit test, which does not know the alternative, spreads its power over every
direction of misfit: its statistic is the non-central chi-square with the fitted degrees
of freedom and noncentrality ``lambda`` (:func:`detection_power`): for a power of 0.95 at
``alpha = 1e-3`` it needs ``lambda = 40 / 86 / 232`` at 10 / 100 / 1000 degrees of freedom,
where the bound needs ``lambda = 22.4`` (docs/physics/model_evidence.md).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from scipy import special, stats

__all__ = [
    "GoodnessOfFit",
    "GofComponent",
    "DEFAULT_MISMATCH_P",
    "goodness_of_fit",
    "fit_goodness_of_fit",
    "deviance_terms",
    "deviance_moments",
    "poisson_deviance_moments",
    "detection_power",
    "detection_power_bound",
]

DEFAULT_MISMATCH_P = 1e-3

# asymptotic series in 1/lam of the Poisson unit deviance d(Y; lam): mean, variance, third
# cumulant, Cov(d, (Y - lam)^2) - 2 lam and E[(d - E d)^2 (Y - lam)] (derived from the Poisson
# central moments with a computer algebra system; tests/test_gof.py checks them against the
# sums)
_E_SERIES = (1.0, 1 / 6, 1 / 6, 19 / 60, 9 / 10, 863 / 252)
_V_SERIES = (2.0, 2 / 3, 4 / 3, 701 / 180, 449 / 30, 90329 / 1260)
_K3_SERIES = (8.0, 4.0, 12.0, 283 / 6, 1144 / 5, 1430593 / 1080)
_C2_SERIES = (0.0, 1 / 6, 2 / 3, 57 / 20, 72 / 5, 6425 / 63)
# E[(d - E d)^2 (Y - lam)]
_M21_SERIES = (0.0, -4 / 3, -4.0, -929 / 60, -1114 / 15, -35863 / 84)
SERIES_FROM = 100.0  # lam above: the series (error < 1e-9 of the sums); at or below: exact sums
_CHUNK = 128  # values of lam per pmf table: sorted, so the sparse bins get short tables


def _series(coef, lam, deriv=0):
    """``sum_k c_k lam^-k`` or its first or second derivative in ``lam``."""
    x = 1.0 / lam
    out = np.zeros_like(lam)
    for k in range(len(coef) - 1, -1, -1):
        c = coef[k] * (1.0 if deriv == 0 else -k if deriv == 1 else k * (k + 1))
        out = out * x + c
    return out * x**deriv if deriv else out


def _unit_poisson_deviance(y, lam):
    """``2 [y log(y/lam) - (y - lam)]`` with ``0 log 0 = 0`` (``y >= 0``, ``lam > 0``)."""
    pos = y > 0
    ys = np.where(pos, y, 1.0)
    return 2.0 * (np.where(pos, y * np.log(ys / lam), 0.0) - (y - lam))


# per-bin quantities of the null distribution (arrays over bins):
# mean, d mean / d mu, d2 mean / d mu2, and of t = stat - a Y: variance, third cumulant,
# Cov(t, (Y - mu)^2) / var(Y); plus var(Y) and kappa_4(Y) / var(Y)^2
_FIELDS = ("mean", "d1", "d2", "var", "k3", "c2", "var_y", "k4n")


def _poisson_exact(lam: np.ndarray, a: np.ndarray) -> dict:
    """The :data:`_FIELDS` of the Poisson deviance by summing the pmf (``lam`` sorted
    ascending so each chunk's table is as short as it can be)."""
    out = {k: np.empty(lam.size) for k in _FIELDS}
    for lo in range(0, lam.size, _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        mu, aa = lam[sl][:, None], a[sl][:, None]
        top = float(mu.max())
        y = np.arange(int(math.ceil(top + 12.0 * math.sqrt(top) + 30.0)) + 1, dtype=np.float64)
        p = np.exp(y * np.log(mu) - mu - special.gammaln(y + 1.0))
        d = _unit_poisson_deviance(y, mu)
        mean = np.sum(p * d, axis=1)
        # derivatives in lam: dp = p (y/lam - 1), dd = 2 (1 - y/lam), d2d = 2 y / lam^2
        r = y / mu
        dp = p * (r - 1.0)
        dd = 2.0 * (1.0 - r)
        d2p = p * ((r - 1.0) ** 2 - y / mu**2)
        out["d1"][sl] = np.sum(dp * d + p * dd, axis=1)
        out["d2"][sl] = np.sum(d2p * d + 2.0 * dp * dd + p * 2.0 * y / mu**2, axis=1)
        t = d - aa * y
        c = t - np.sum(p * t, axis=1)[:, None]
        out["mean"][sl] = mean
        out["var"][sl] = np.sum(p * c * c, axis=1)
        out["k3"][sl] = np.sum(p * c * c * c, axis=1)
        out["c2"][sl] = np.sum(p * c * (y - mu) ** 2, axis=1) / mu[:, 0]
    out["var_y"] = lam.copy()
    out["k4n"] = 1.0 / lam
    return out


def _poisson_fields(lam: np.ndarray, a: np.ndarray | None = None) -> dict:
    """:data:`_FIELDS` of the Poisson unit deviance at each ``lam`` (exact sums up to
    :data:`SERIES_FROM`, series above)."""
    flat = lam.ravel()
    a = np.zeros_like(flat) if a is None else np.asarray(a, np.float64).ravel()
    out = {k: np.empty(flat.size) for k in _FIELDS}
    small = flat <= SERIES_FROM
    if small.any():
        idx = np.flatnonzero(small)
        order = idx[np.argsort(flat[idx], kind="stable")]
        part = _poisson_exact(flat[order], a[order])
        for k in _FIELDS:
            out[k][order] = part[k]
    big = ~small
    if big.any():
        lb, ab = flat[big], a[big]
        d1 = _series(_E_SERIES, lb, 1)
        out["mean"][big] = _series(_E_SERIES, lb)
        out["d1"][big] = d1
        out["d2"][big] = _series(_E_SERIES, lb, 2)
        # Cov(d, Y) = lam d mean / d lam (differentiate the pmf sum)
        out["var"][big] = _series(_V_SERIES, lb) - 2.0 * ab * lb * d1 + ab * ab * lb
        cov2 = 2.0 * lb + _series(_C2_SERIES, lb)  # Cov(d, (Y - lam)^2)
        # k3(d - a Y) = k3(d) - 3 a E[(d - Ed)^2 (Y - lam)] + 3 a^2 Cov(d, (Y - lam)^2)
        #               - a^3 k3(Y), with k3(Y) = lam
        out["k3"][big] = (
            _series(_K3_SERIES, lb) - 3.0 * ab * _series(_M21_SERIES, lb) + 3.0 * ab * ab * cov2
        ) - ab**3 * lb
        out["c2"][big] = cov2 / lb - ab
        out["var_y"][big] = lb
        out["k4n"][big] = 1.0 / lb
    return {k: v.reshape(lam.shape) for k, v in out.items()}


def poisson_deviance_moments(lam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, variance and third cumulant of the Poisson unit deviance ``d(Y; lam)``,
    ``Y ~ Poisson(lam)``, elementwise (``lam > 0``; exact sums up to ``lam = 100``, the
    asymptotic series above; module docstring)."""
    lam = np.asarray(lam, np.float64)
    if not np.all(np.isfinite(lam)) or np.any(lam <= 0):
        bad = lam[~(np.isfinite(lam) & (lam > 0))].ravel()
        raise ValueError(
            f"poisson_deviance_moments: expectations must be finite and > 0, got {bad[:3]!r}"
        )
    f = _poisson_fields(lam)
    return f["mean"], f["var"], f["k3"]


# --------------------------------------------------------------------------- noise models
def _kind(noise) -> str:
    from ._refine import GaussianNoise, PoissonCounts, PoissonNoise

    if isinstance(noise, PoissonCounts):
        return "poisson"
    if isinstance(noise, PoissonNoise):
        return "counting"
    if isinstance(noise, GaussianNoise) or (
        hasattr(noise, "variance") and getattr(noise, "residuals", None) is None
    ):
        return "gaussian"
    raise ValueError(
        f"goodness_of_fit: noise model {type(noise).__name__} defines its own residuals; the "
        "null moments are known for PoissonCounts (Poisson deviance) and for models that only "
        "define variance() (Pearson chi-square: PoissonNoise, GaussianNoise)"
    )


def _stirling2(n: int) -> list[int]:
    """Stirling numbers of the second kind ``S(n, j)``, ``j = 0..n``."""
    row = [1]
    for i in range(1, n + 1):
        new = [0] * (i + 1)
        for j in range(1, i + 1):
            new[j] = j * (row[j] if j < len(row) else 0) + row[j - 1]
        row = new
    return row


def _counting_cumulants(mu, g, cells):
    """Cumulants 3 to 6 of ``g N`` with ``N`` negative binomial (mean ``mu / g``, ``cells``
    speckle cells; Poisson for ``cells = None``), in data units."""
    lam = mu / g
    out = {}
    for n in (3, 4, 5, 6):
        if cells is None:
            k = lam
        else:
            s = _stirling2(n)
            p = lam / cells
            k = cells * sum(s[j] * math.factorial(j - 1) * p**j for j in range(1, n + 1))
        out[n] = g**n * k
    return out


def _variance_call(noise, mu, phys):
    return noise.variance(mu, phys)


_variance_jit = None


def _variance(noise, mu, phys):
    global _variance_jit
    import equinox as eqx
    import jax.numpy as jnp

    if _variance_jit is None:  # one small program per noise model and shape (eager: ~1 ms)
        _variance_jit = eqx.filter_jit(_variance_call)
    v = np.asarray(_variance_jit(noise, jnp.asarray(mu), phys), np.float64)
    v = np.broadcast_to(v, mu.shape)
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ValueError(
            f"goodness_of_fit: {type(noise).__name__}.variance must be finite and > 0 at the "
            f"fitted expectation (min {np.min(v)!r})"
        )
    return v


def _variance_derivatives(noise, mu, phys):
    """``v'(mu)`` and ``v''(mu)`` of an elementwise variance function (closed forms for the
    library's models, forward-mode autodiff for others)."""
    import jax
    import jax.numpy as jnp

    from ._refine import GaussianNoise

    if isinstance(noise, GaussianNoise):
        return np.zeros_like(mu), np.zeros_like(mu)
    if _kind(noise) == "counting":  # v = g max(mu, 0) + max(mu, 0)^2 / M + floor
        g = 1.0
        if noise.counts_per_photon == "gain" and phys is not None:
            g = float(np.asarray(phys.gain))
        inv_m = 0.0 if noise.speckle_cells is None else 1.0 / float(noise.speckle_cells)
        pos = mu > 0
        return np.where(pos, g + 2.0 * mu * inv_m, 0.0), np.where(pos, 2.0 * inv_m, 0.0)
    x = jnp.asarray(mu)
    ones = jnp.ones_like(x)

    def first(m):
        return jax.jvp(lambda t: noise.variance(t, phys), (m,), (ones,))[1]

    v1, v2 = jax.jvp(first, (x,), (ones,))
    return np.asarray(v1, np.float64), np.asarray(v2, np.float64)


def _pearson_fields(noise, mu, phys, a=None) -> dict:
    """:data:`_FIELDS` of ``X = (y - mu)^2 / v`` (module docstring) and of ``X - a y``."""
    v = np.array(_variance(noise, mu, phys))
    a = np.zeros_like(mu) if a is None else np.asarray(a, np.float64)
    zero = np.zeros_like(mu)
    if _kind(noise) == "counting":
        g = 1.0
        if noise.counts_per_photon == "gain" and phys is not None:
            g = float(np.asarray(phys.gain))
        k = _counting_cumulants(np.maximum(mu, 0.0), g, noise.speckle_cells)
    else:  # Gaussian data: no cumulants beyond the variance
        k = dict.fromkeys((3, 4, 5, 6), zero)
    # central moments of y (the floor is Gaussian: it enters v only)
    m4 = k[4] + 3.0 * v * v
    m5 = k[5] + 10.0 * k[3] * v
    m6 = k[6] + 15.0 * k[4] * v + 10.0 * k[3] ** 2 + 15.0 * v**3
    var_x = (m4 - v * v) / (v * v)
    k3_x = (m6 - 3.0 * v * m4 + 2.0 * v**3) / v**3
    v1, v2 = _variance_derivatives(noise, mu, phys)
    # moments of X - a y: Cov(X, y) = k3 / v; E[(X - 1)^2 (y - mu)] = (m5 - 2 v k3) / v^2;
    # E[(X - 1)(y - mu)^2] = (m4 - v^2) / v
    return {
        "mean": np.ones_like(mu),
        "d1": zero,
        "d2": zero,
        "var": var_x - 2.0 * a * k[3] / v + a * a * v,
        "k3": k3_x
        - 3.0 * a * (m5 - 2.0 * v * k[3]) / (v * v)
        + 3.0 * a * a * (m4 - v * v) / v
        - a**3 * k[3],
        "c2": var_x - a * k[3] / v,
        "var_y": v,
        "k4n": k[4] / (v * v),
        # d/d mu of E[X] at fixed data is -v'/v: the fitted weights move the statistic
        "b": v1 / v,
        "xm": v1 * v1 / v - 0.5 * v2 - k[3] * v1 / (v * v),
    }


def _check_pair(data, expected):
    y = np.asarray(data, np.float64)
    mu = np.asarray(expected, np.float64)
    if y.shape != mu.shape:
        raise ValueError(f"goodness_of_fit: data shape {y.shape} != expected shape {mu.shape}")
    if not np.all(np.isfinite(y)) or not np.all(np.isfinite(mu)):
        raise ValueError("goodness_of_fit: data and expected must be finite")
    return y, mu


def deviance_terms(data, expected, noise, phys=None) -> np.ndarray:
    """Per-bin contributions to the deviance (module docstring): Poisson unit deviances for
    :class:`~inversion.PoissonCounts` (against ``expected + background``), squared Pearson
    residuals ``(y - mu)^2 / v`` otherwise. Their sum is the refiner's cost at ``expected``."""
    y, mu = _check_pair(data, expected)
    if _kind(noise) == "poisson":
        noise.check_data(y)
        return _unit_poisson_deviance(y, _poisson_lam(noise, mu))
    return (y - mu) ** 2 / _variance(noise, mu, phys)


def deviance_function(noise, phys=None):
    """``f(data, expected) -> float``: the summed :func:`deviance_terms` without the input
    checks (for host-side fits that evaluate it many times on checked data)."""
    if _kind(noise) == "poisson":
        return functools.partial(_poisson_deviance_sum, b=float(noise.background))
    return functools.partial(_pearson_sum, noise=noise, phys=phys)


def _poisson_deviance_sum(y, mu, b):
    lam = mu + b
    return float(np.sum(_unit_poisson_deviance(y, np.where(lam > 0.5 * b, lam, b))))


def _pearson_sum(y, mu, noise, phys):
    return float(np.sum((y - mu) ** 2 / _variance(noise, mu, phys)))


def _poisson_lam(noise, mu):
    b = float(noise.background)
    lam = mu + b
    # as PoissonCounts._lam: a model dipping below 0 by more than round-off counts as 0
    return np.where(lam > 0.5 * b, lam, b)


def _fields(noise, mu, phys, a=None) -> dict:
    if _kind(noise) == "poisson":
        f = _poisson_fields(_poisson_lam(noise, mu), a)
        f["b"] = f["d1"]  # the plug-in mean moves with the fit; the deviance's slope is 0
        f["xm"] = np.zeros_like(f["d1"])
        return f
    return _pearson_fields(noise, mu, phys, a)


def deviance_moments(expected, noise, phys=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin mean, variance and third cumulant of :func:`deviance_terms` when the data are
    drawn from the noise model at ``expected`` (module docstring)."""
    f = _fields(noise, np.asarray(expected, np.float64), phys)
    return f["mean"], f["var"], f["k3"]


def _fitted_moments(noise, mu, phys, jacobian, rtol):
    """Null (mean, variance, third cumulant) of the deviance after a fit whose expectation has
    the Jacobian ``jacobian`` (``(n, P)``) at ``mu``, and the number of observable directions.

    Write the statistic as ``S = sum_i s(y_i, mu_i)`` and compare it with its plug-in mean
    ``sum_i E_i(mu_hat)``. To first order the fit moves ``mu`` by ``delta = H W (y - mu)``,
    ``H = J I^+ J^T``, ``W = diag(1 / var(y))``, ``I = J^T W J`` (``I^+``: its
    observable-subspace inverse, rank ``p``; ``h_i = H_ii W_ii``, ``sum h_i = p``). Expanding
    ``T = S(y, mu_hat) - sum E_i(mu_hat)`` about ``mu``:

    - first order: ``sum_i (E[ds_i/dmu] - E'_i) delta_i = -a^T (y - mu)``, ``a = W H b``,
      ``b = E' - E[ds/dmu]``. For the Poisson deviance ``E[dd/dmu] = 0`` and ``b = E'``,
      large for sparse counts where ``E ~ 2 mu log(1 / mu)``: the plug-in mean follows the
      counts. For the Pearson statistic ``E' = 0`` but ``E[ds/dmu] = -v'/v``: weights taken
      at the fitted ``mu`` follow the counts when the variance depends on ``mu``;
    - second order: the likelihood-ratio drop ``Q = (y - mu)^T W H W (y - mu)`` (mean ``p``,
      variance ``2 p + sum_i h_i^2 kappa_4 / var^2``), the curvature ``-1/2 sum E''_i H_ii``
      of the plug-in mean, and for a variance depending on ``mu`` the mean
      ``sum_i h_i (v'^2 / v - v''/2 - kappa_3 v' / v^2)`` (curvature of ``1/v`` and the
      covariance of ``(y - mu)^2`` with ``delta``).

    So, with ``t_i = s_i - a_i y_i``:

        E[T]   = sum_i E_i - p - 1/2 sum_i E''_i H_ii + sum_i h_i xm_i
        Var[T] = sum_i Var t_i + Var Q - 2 sum_i h_i Cov(t_i, (y_i - mu_i)^2) / var_i
        k3[T]  = sum_i k3 t_i - 8 p

    For Gaussian data with a constant variance this is ``n - p``, ``2 (n - p)``,
    ``8 (n - p)``: the chi-square law. ``tests/test_gof.py`` checks it by brute force.
    """
    from ._observability import observable_inverse

    f0 = _fields(noise, mu, phys)
    n = mu.size
    J = np.asarray(jacobian, np.float64).reshape(n, -1)
    if not np.all(np.isfinite(J)):
        raise ValueError("goodness_of_fit: the Jacobian has non-finite entries")
    w = 1.0 / f0["var_y"].ravel()
    inv, p = observable_inverse(J.T @ (w[:, None] * J), rtol)
    JI = J @ inv
    H_diag = np.sum(JI * J, axis=1)
    a = w * (JI @ (J.T @ f0["b"].ravel()))
    f = _fields(noise, mu, phys, a.reshape(mu.shape)) if np.any(a) else f0
    h = H_diag * w
    mean = (
        float(np.sum(f["mean"]))
        - p
        - 0.5 * float(np.sum(f["d2"].ravel() * H_diag))
        + float(np.sum(h * f["xm"].ravel()))
    )
    var_q = 2.0 * p + float(np.sum(h * h * f["k4n"].ravel()))
    var = float(np.sum(f["var"])) + var_q - 2.0 * float(np.sum(h * f["c2"].ravel()))
    third = float(np.sum(f["k3"])) - 8.0 * p
    return mean, var, third, p


# --------------------------------------------------------------------------- marginals
# the summed statistics of "Marginal tests" (module docstring): name and the data axis summed
MARGINALS = (("range profile", 0), ("channel totals", 1))


def _gaussian_sum_fields(var: np.ndarray, a: np.ndarray) -> dict:
    """:data:`_FIELDS` of ``X = (Y - M)^2 / V`` and of ``X - a Y`` for Gaussian ``Y``."""
    zero = np.zeros_like(var)
    return {
        "mean": np.ones_like(var),
        "d1": zero,
        "d2": zero,
        "var": 2.0 + a * a * var,
        "k3": 8.0 + 6.0 * a * a * var,
        "c2": np.full_like(var, 2.0),
        "var_y": var,
        "k4n": zero,
        "b": zero,
    }


def _marginal(name, axis, y, mu, noise, phys, jac, rtol, allowance):
    """The :class:`GofComponent` of the deviance of the data summed over ``axis`` of
    ``(C, B)`` (module docstring, "Marginal tests"), or ``None`` when the fit leaves it less
    than one degree of freedom.

    In whitened coordinates ``e = W^(1/2) (y - mu)`` the fit removes ``P e`` (``P`` the
    projector on the whitened Jacobian's observable columns) and the summed residual is
    ``z = U^T e`` (``U`` orthonormal, one column per summed value ``t``:
    ``sqrt(var_i / V_t)`` on its members). With ``G = U^T P U`` the statistic loses
    ``tr G`` degrees of freedom (``p`` when the sums keep every fitted direction, 0 when
    none): to second order ``T = e^T (I - P) U U^T (I - P) e``. The moments are those of
    :func:`_fitted_moments` with ``p -> tr G``, the hat diagonal ``-> diag(2 G - G^2)`` and the
    likelihood-ratio drop's variance ``2 p -> 2 (2 tr G - tr G^2)`` plus its kurtosis term
    ``sum_i K_ii^2 kappa_4,i / var_i^2`` (``K = P U U^T + U U^T P - P U U^T P``); the first-order
    plug-in term ``a = W H A^T b`` acts on the sums through
    ``a_bar_t = sum_(i in t) a_i var_i / V_t`` (given the sums, the rest of ``a^T y`` has mean
    zero: uncorrelated with any function of them; it adds its variance). For ``U = I`` these
    are :func:`_fitted_moments`' moments. The per-sum cumulants are exact; the fit's
    corrections are second order, with three small cross terms of the third cumulants taken
    at the level of the sums (below 0.5 % of the spread on the tests' designs, up to 6 % with
    20 fitted directions and ~13 counts in all; very sparse sums are conservative, as for the
    deviance)."""
    from ._observability import observable_inverse

    kind = _kind(noise)
    lam = _poisson_lam(noise, mu) if kind == "poisson" else mu
    var_y = lam if kind == "poisson" else _variance(noise, mu, phys)
    C, B = mu.shape
    k = B if axis == 0 else C
    groups = (np.tile(np.arange(B), C) if axis == 0 else np.repeat(np.arange(C), B)).ravel()
    Yt, Mt, Vt = y.sum(axis), lam.sum(axis), var_y.sum(axis)
    J = np.asarray(jac, np.float64).reshape(mu.size, -1)
    w = 1.0 / var_y.ravel()
    fisher = J.T @ (w[:, None] * J)
    inv, p = observable_inverse(fisher, rtol)
    # P = Jw inv Jw^T = Lw Lw^T, factored in the correlation scaling (eigenvalues of the
    # scaled inverse lie in [1, 1/rtol] whatever the parameters' units): the p largest
    d = np.sqrt(np.where(np.diag(fisher) > 0, np.diag(fisher), 1.0))
    s, E = np.linalg.eigh(0.5 * (inv + inv.T) * d[:, None] * d[None, :])
    top = np.argsort(s)[::-1][:p]
    Lw = (J * np.sqrt(w)[:, None]) @ ((E[:, top] / d[:, None]) * np.sqrt(np.maximum(s[top], 0)))
    su = np.sqrt(var_y.ravel() / Vt[groups])  # U's entries
    X = np.zeros((k, p))
    np.add.at(X, groups, su[:, None] * Lw)  # U^T Lw
    G = X @ X.T
    G2 = G @ G
    trG = float(np.trace(G))
    if k - trG < 1.0:
        return None
    # diagonal of K = P U U^T + U U^T P - P U U^T P (the fit's drop of the summed statistic,
    # per value): the kurtosis term of its variance is sum_i K_ii^2 kappa_4,i / var_i^2
    PU = Lw @ X.T  # (n, k)
    K_ii = 2.0 * PU[np.arange(mu.size), groups] * su - np.sum(PU * PU, axis=1)
    k4n_i = 1.0 / var_y.ravel() if kind == "poisson" else np.zeros(mu.size)
    if kind == "poisson":
        f = _poisson_fields(Mt)
        b = f["d1"]
    else:
        f = _gaussian_sum_fields(Vt, np.zeros(k))
        b = f["b"]
    extra = 0.0
    if np.any(b):  # the plug-in mean follows the fit: its first-order term on the data
        a = np.sqrt(w) * (Lw @ (Lw.T @ (su * (np.sqrt(Vt) * b)[groups])))
        abar = np.bincount(groups, a * var_y.ravel(), k) / Vt
        extra = float(np.sum(a * a * var_y.ravel()) - np.sum(abar * abar * Vt))
        f = _poisson_fields(Mt, abar) if kind == "poisson" else _gaussian_sum_fields(Vt, abar)
    g = np.diag(2.0 * G - G2)
    mean = float(np.sum(f["mean"]) - trG - 0.5 * np.sum(f["d2"] * Vt * np.diag(G)))
    var = float(
        np.sum(f["var"])
        + extra
        + 2.0 * (2.0 * trG - np.trace(G2))
        + np.sum(K_ii * K_ii * k4n_i)
        - 2.0 * np.sum(g * f["c2"])
    )
    IG = np.eye(k) - G
    third = float(np.sum(f["k3"]) + 8.0 * (np.trace(IG @ IG @ IG) - k))
    if not (var + 4.0 * allowance > 0 and mean + allowance > 0):
        return None
    if kind == "poisson":
        stat = float(np.sum(_unit_poisson_deviance(Yt, Mt)))
    else:
        stat = float(np.sum((Yt - mu.sum(axis)) ** 2 / Vt))
    return _component(name, k, stat, mean, var, third, allowance)


def _component(name, n_values, stat, mean, var, third, allowance):
    mean += allowance
    var += 4.0 * allowance
    third += 24.0 * allowance
    sd = math.sqrt(var)
    return GofComponent(
        name=name,
        n_values=int(n_values),
        deviance=float(stat),
        expected=float(mean),
        std=sd,
        skewness=third / var**1.5,
        z=(stat - mean) / sd,
        p_value=float(_upper_tail(stat, mean, var, third)),
    )


# --------------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True)
class GofComponent:
    """One statistic of the goodness-of-fit family (:func:`goodness_of_fit`): ``"all
    values"`` (the deviance), ``"range profile"`` (the deviance of the data summed over
    channels) or ``"channel totals"`` (summed over range bins); `n_values` the values it
    sums, `deviance` its value, `expected`, `std`, `skewness` its null law after the fit,
    `z` and `p_value` (upper tail) as in :class:`GoodnessOfFit`."""

    name: str
    n_values: int
    deviance: float
    expected: float
    std: float
    skewness: float
    z: float
    p_value: float


@dataclasses.dataclass(frozen=True)
class GoodnessOfFit:
    """The deviance at a fit against its null distribution (:func:`goodness_of_fit`).

    - `statistic`: ``"poisson_deviance"`` or ``"pearson_chi2"``; `deviance` its value.
    - `expected`, `std`, `skewness`: moments of its null distribution, after the fitted
      parameters (and any `allowance`).
    - `n_data`, `n_params`, `dof` = ``n_data - n_params`` (``dof`` is what the chi-squared rule
      of thumb would expect; `expected` is the exact value, smaller for sparse counts).
    - `z` = ``(deviance - expected) / std``.
    - `components`: every statistic tested (:class:`GofComponent`; module docstring,
      "Marginal tests"): the deviance (``"all values"``, first) and, for a fit of ``(C, B)``
      data with its Jacobian, the ``"range profile"`` and ``"channel totals"``.
    - `p_value`: the Bonferroni combination ``min(1, K min_k p_k)`` of the ``K`` components'
      upper tails (Pearson type III laws with their three null moments); with one component,
      the deviance's own tail.
    - `model_mismatch`: ``p_value < threshold`` (default 1e-3): the fitted expectation does
      not explain the data within their noise (a model unlike the target, or, for a fit, an
      optimum its search missed).
    - `allowance`: model error allowed for (0: the model is exact).
    - `lower_p_value`: the deviance's lower tail ``P(X <= deviance)`` under the same law;
      `underdispersed`: ``lower_p_value < threshold`` and ``z < -3`` (both under the exact
      model, without the `allowance`): the data scatter less
      than the noise model says they must (counts averaged, scaled or background-subtracted,
      or a variance too large): the noise settings do not describe the data, and the
      reported uncertainties, which rest on them, are not the data's.
    """

    statistic: str
    deviance: float
    expected: float
    std: float
    skewness: float
    n_data: int
    n_params: int
    dof: int
    z: float
    p_value: float
    threshold: float
    model_mismatch: bool
    allowance: float = 0.0
    components: tuple[GofComponent, ...] = ()
    lower_p_value: float = math.nan
    underdispersed: bool = False

    @property
    def strongest(self) -> GofComponent | None:
        """The component with the smallest p-value (the one a mismatch verdict rests on)."""
        if not self.components:
            return None
        return min(self.components, key=lambda c: (c.p_value, -c.z))

    def summary(self) -> str:
        name = "Poisson deviance" if self.statistic == "poisson_deviance" else "chi-square"
        allow = f", allowance {self.allowance:.4g}" if self.allowance > 0 else ""
        verdict = (
            f"MODEL MISMATCH (p < {self.threshold:g}: the fit does not explain the data: a "
            "model unlike the target, or a missed optimum)"
            if self.model_mismatch
            else "fit acceptable"
        )
        parts = ""
        if len(self.components) > 1:
            parts = (
                " (smallest of "
                + ", ".join(f"{c.name} z = {c.z:+.2f} p = {c.p_value:.3g}" for c in self.components)
                + f", times {len(self.components)})"
            )
        if self.underdispersed:
            verdict += (
                f"; DATA SCATTER BELOW THE NOISE MODEL (lower tail p = {self.lower_p_value:.3g}: "
                "counts averaged, scaled or background-subtracted? the noise settings do not "
                "describe these data, nor do the uncertainties that rest on them)"
            )
        return (
            f"goodness of fit: {name} {self.deviance:.6g}, expected {self.expected:.6g} +- "
            f"{self.std:.4g} ({self.n_data} values, {self.n_params} fitted{allow}), "
            f"z = {self.z:+.2f}, p = {self.p_value:.3g}{parts}: {verdict}"
        )

    def tail(self, deviance):
        """Upper-tail probability of the deviance's null law (the ``"all values"``
        component) at other deviance values (scalar or array): ``tail(self.deviance)`` is
        that component's p-value, equal to `p_value` when it is the only one."""
        var = self.std**2
        return _upper_tail(deviance, self.expected, var, self.skewness * var**1.5)

    def to_dict(self) -> dict:
        """Plain JSON-ready values (floats, ints, bools; no infinities)."""

        def clean(d):
            return {
                k: None if isinstance(v, float) and not math.isfinite(v) else v
                for k, v in d.items()
            }

        out = clean(dataclasses.asdict(self))
        out["components"] = [clean(c) for c in out["components"]]
        return out


def _pearson3(mean: float, var: float, k3: float):
    """``(loc, scale, shape)`` of the Pearson type III (shifted gamma) law with these
    cumulants, or None when it is symmetric (large counts: the normal limit)."""
    sd = math.sqrt(var)
    skew = k3 / var**1.5
    if not skew > 1e-4:
        return None
    shape = 4.0 / skew**2
    scale = 0.5 * sd * skew
    return mean - shape * scale, scale, shape


def _tail(x, mean: float, var: float, k3: float, *, upper: bool):
    """P(X >= x) (`upper`) or P(X <= x) for the Pearson type III law with the given
    cumulants (normal if unskewed), each computed directly; ``x`` scalar or array."""
    x = np.asarray(x, np.float64)
    law = _pearson3(mean, var, k3)
    if law is None:
        z = (x - mean) / math.sqrt(var)
        out = stats.norm.sf(z) if upper else stats.norm.cdf(z)
    else:
        loc, scale, shape = law
        t = np.maximum((x - loc) / scale, 0.0)
        out = special.gammaincc(shape, t) if upper else special.gammainc(shape, t)
    return float(out) if out.ndim == 0 else out


def _upper_tail(x, mean: float, var: float, k3: float):
    """P(X >= x) (:func:`_tail`)."""
    return _tail(x, mean, var, k3, upper=True)


def _lower_tail(x, mean: float, var: float, k3: float):
    """P(X <= x) (:func:`_tail`)."""
    return _tail(x, mean, var, k3, upper=False)


def _upper_quantile(alpha: float, mean: float, var: float, k3: float) -> float:
    """The ``x`` with ``P(X >= x) = alpha`` for the Pearson type III law of
    :func:`_upper_tail`."""
    law = _pearson3(mean, var, k3)
    if law is None:
        return mean + math.sqrt(var) * float(stats.norm.isf(alpha))
    loc, scale, shape = law
    return loc + scale * float(special.gammainccinv(shape, alpha))


def _check_power_args(noncentrality, alpha):
    lam = np.asarray(noncentrality, np.float64)
    if not (np.all(np.isfinite(lam)) and np.all(lam >= 0)):
        bad = lam[~(np.isfinite(lam) & (lam >= 0))].ravel()
        raise ValueError(f"noncentrality must be finite and >= 0, got {bad[:3]!r}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha!r}")
    return lam


def detection_power_bound(noncentrality, alpha: float = DEFAULT_MISMATCH_P):
    """Upper bound on the power of *any* level-``alpha`` test of a model against a true source
    whose expected data lie at deviance ``noncentrality`` from the closest model expectation
    (module docstring, "Detectability"): the Neyman-Pearson likelihood-ratio test between the
    two, ``Phi(sqrt(lambda) - z_alpha)`` (large-count normal limit; ``lambda`` the deviance
    of the noise-free data at the closest fit). Scalar or array, like ``noncentrality``."""
    lam = _check_power_args(noncentrality, alpha)
    out = stats.norm.cdf(np.sqrt(lam) - stats.norm.isf(alpha))
    return float(out) if out.ndim == 0 else out


def detection_power(noncentrality, dof, alpha: float = DEFAULT_MISMATCH_P):
    """Power of the goodness-of-fit test (reject when ``p < alpha``) against a model error
    of size ``noncentrality`` (``lambda``: deviance of the noise-free true data at the closest
    model expectation).

    - ``dof`` a number: the chi-square test with ``dof`` degrees of freedom (dense counts,
      Gaussian noise): ``P(chi'^2(dof, lambda) > chi^2_{1-alpha}(dof))``, the non-central
      chi-square exactly.
    - ``dof`` a :class:`GoodnessOfFit` (e.g. of the noise-free fit): its null law (Pearson
      type III with the exact null moments, sparse counts included) gives the critical
      value, and the alternative is that law with the non-central chi-square's extra
      cumulants ``lambda``, ``4 lambda``, ``24 lambda`` (as its ``allowance``).

    This is the power of the deviance over all values alone: the reported verdict
    (``model_mismatch``) tests it at ``alpha / K`` together with the ``K - 1`` marginal tests
    (:func:`goodness_of_fit`), which have more power against a misfit concentrated in the
    range profile or the channel totals and slightly less against one spread evenly.

    Below :func:`detection_power_bound` (no test beats Neyman-Pearson) for ``dof >= 1``; a
    null whose expected deviance is below 1 (almost no counts) is outside both
    approximations. Scalar or array, like ``noncentrality``."""
    lam = _check_power_args(noncentrality, alpha)
    if isinstance(dof, GoodnessOfFit):
        var = dof.std**2
        k3 = dof.skewness * var**1.5
        crit = _upper_quantile(alpha, dof.expected, var, k3)
        out = np.asarray(
            [_upper_tail(crit, dof.expected + x, var + 4 * x, k3 + 24 * x) for x in lam.ravel()]
        ).reshape(lam.shape)
    else:
        nu = float(dof)
        if not (math.isfinite(nu) and nu > 0):
            raise ValueError(f"dof must be a finite number > 0 or a GoodnessOfFit, got {dof!r}")
        crit = stats.chi2.isf(alpha, nu)
        # ncx2 at noncentrality 0 is the central law (scipy's ncx2 wants nc > 0 on some versions)
        pos = lam > 0
        out = np.where(pos, stats.ncx2.sf(crit, nu, np.where(pos, lam, 1.0)), alpha)
    return float(out) if np.ndim(out) == 0 else out


def goodness_of_fit(
    data,
    expected,
    noise,
    *,
    jacobian=None,
    n_params: int | None = None,
    phys=None,
    threshold: float = DEFAULT_MISMATCH_P,
    allowance: float = 0.0,
    rtol: float | None = None,
    marginals: bool = True,
) -> GoodnessOfFit:
    """Deviance of ``data`` at ``expected`` against its exact null distribution.

    **Arguments:**

    - `data`: observed values ``(C, B)`` (photo-counts for :class:`~inversion.PoissonCounts`).
    - `expected`: the model's expectation at the fit, ``model.expected(fit.params, aux)``
      (before the Poisson background, which `noise` adds).
    - `noise`: the noise model the fit used (:class:`~inversion.PoissonCounts`,
      :class:`~inversion.PoissonNoise`, :class:`~inversion.GaussianNoise`, or any model with
      only ``variance``).
    - `jacobian`: ``d expected / d theta`` at the fit, ``(C, B, P)`` or ``(C * B, P)`` (any
      coordinates ``theta`` of the fitted parameters). With it the fitted degrees of freedom
      are the observable directions of ``J^T W J`` (``rtol`` as :func:`inversion.observability`)
      and the estimation terms of the plug-in moments are included (:func:`_fitted_moments`:
      needed for sparse counts). :func:`inversion.fit_goodness_of_fit` passes it.
    - `n_params`: without a Jacobian, the number of fitted parameters: each removes one
      chi-square degree of freedom from the plug-in moments (``E - p``, ``Var - 2 p``).
      For sparse Poisson counts that overstates the variance (a conservative test).
    - `phys`: the fitted :class:`~inversion.PhysicalParams` (for a variance depending on the
      gain, ``PoissonNoise(counts_per_photon="gain")``).
    - `threshold`: p-value below which `model_mismatch` is set (default 1e-3).
    - `allowance`: model error (Pearson size, in deviance units) the test tolerates (default 0).
    - `marginals`: with a `jacobian`, ``(C, B)`` data (``C, B >= 2``) and Poisson counts or
      :class:`~inversion.GaussianNoise`, also test the data summed over channels (the range
      profile) and over range bins (the channel totals), and combine the p-values
      (module docstring, "Marginal tests"; default on).

    **Returns:** :class:`GoodnessOfFit`. Raises ``ValueError`` for mismatched shapes,
    non-finite values, negative counts under a Poisson model, or no degrees of freedom left.
    """
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"goodness_of_fit: threshold must lie in (0, 1), got {threshold!r}")
    if not (math.isfinite(allowance) and allowance >= 0.0):
        raise ValueError(f"goodness_of_fit: allowance must be finite and >= 0, got {allowance!r}")
    if jacobian is not None and n_params is not None:
        raise ValueError(
            "goodness_of_fit: pass jacobian (the fitted degrees of freedom are its observable "
            "rank) or n_params, not both"
        )
    terms = deviance_terms(data, expected, noise, phys)
    mu = np.asarray(expected, np.float64)
    n = int(terms.size)
    if jacobian is not None:
        jac = np.asarray(jacobian)
        shape_ok = jac.shape[:-1] in ((n,), mu.shape)
        if jac.ndim < 2 or not shape_ok:
            raise ValueError(
                f"goodness_of_fit: jacobian shape {jac.shape} does not match expected "
                f"{mu.shape} (use (C, B, P) or (C * B, P))"
            )
        mean, var, third, p = _fitted_moments(noise, mu, phys, jac, rtol)
    else:
        p = 0 if n_params is None else int(n_params)
        if p < 0:
            raise ValueError(f"goodness_of_fit: n_params must be >= 0, got {p}")
        e, v, k3 = deviance_moments(mu, noise, phys)
        mean = float(np.sum(e)) - p
        var = float(np.sum(v)) - 2.0 * p
        third = float(np.sum(k3)) - 8.0 * p
    dev = float(np.sum(terms))
    if not (var + 4.0 * allowance > 0 and mean + allowance > 0):
        raise ValueError(
            f"goodness_of_fit: {n} data values leave no degrees of freedom for {p} "
            f"fitted parameters (null mean {mean:.3g}, variance {var:.3g})"
        )
    comps = [_component("all values", n, dev, mean, var, third, allowance)]
    kind = _kind(noise)
    if (
        marginals
        and jacobian is not None
        and mu.ndim == 2
        and min(mu.shape) >= 2
        and (kind == "poisson" or isinstance(noise, _gaussian_noise_type()))
    ):
        y = np.asarray(data, np.float64)
        for name, axis in MARGINALS:
            c = _marginal(name, axis, y, mu, noise, phys, jac, rtol, allowance)
            if c is not None:
                comps.append(c)
    full = comps[0]
    pval = min(1.0, len(comps) * min(c.p_value for c in comps))
    # the lower tail under the exact model (no allowance: an allowance bounds model error
    # from above, and would make an exact fit read as too little scatter)
    lower = float(_lower_tail(dev, mean, var, third))
    z_exact = (dev - mean) / math.sqrt(var)
    return GoodnessOfFit(
        statistic="poisson_deviance" if kind == "poisson" else "pearson_chi2",
        deviance=dev,
        expected=full.expected,
        std=full.std,
        skewness=full.skewness,
        n_data=n,
        n_params=p,
        dof=n - p,
        z=full.z,
        p_value=pval,
        threshold=float(threshold),
        model_mismatch=bool(pval < threshold),
        allowance=float(allowance),
        components=tuple(comps),
        lower_p_value=lower,
        underdispersed=bool(lower < threshold and z_exact < -3.0),
    )


def _gaussian_noise_type():
    from ._refine import GaussianNoise

    return GaussianNoise


def fit_goodness_of_fit(
    model,
    data,
    fit,
    noise,
    *,
    threshold: float = DEFAULT_MISMATCH_P,
    rtol: float | None = None,
    marginals: bool = True,
) -> GoodnessOfFit:
    """:func:`goodness_of_fit` of a refined fit (:class:`~inversion.RefineResult`) of ``model``
    to ``data`` with the noise model it was refined with: the expectation and its Jacobian at
    ``fit.params`` (visibility recomputed, the refiner's compiled Jacobian program reused),
    the observable directions as fitted degrees of freedom. ``deviance`` equals
    ``fit.cost`` up to rounding. Raises ``ValueError`` for data the model cannot have
    produced (shape, NaN, negative counts) and ``FloatingPointError`` when the Jacobian at
    the fit is not finite."""
    from ._refine import _model_shape, check_observation, weighted_jacobian

    phys, par = fit.params, fit.parametrisation
    aux = model.prepare(phys)
    data = check_observation(data, _model_shape(model, phys, aux))
    J, inv_sigma, mu, *_ = weighted_jacobian(
        model, noise, data, phys, par.free, aux, par.range_scale
    )
    jac = -J / inv_sigma.reshape(-1)[:, None]
    return goodness_of_fit(
        data,
        mu,
        noise,
        jacobian=jac,
        phys=phys,
        threshold=threshold,
        rtol=rtol,
        marginals=marginals,
    )
