r"""Does any template fit? The classifier's best template against the observation's noise.

The classifier's score is a cosine: it ranks templates but says nothing about whether the
best one explains the data. Here the classifier's first candidates ``y_t`` (normalized
signatures) are fitted to the observation ``x`` by maximum likelihood in their two
nuisances, a gain and a sub-bin range shift (``mu = g shift(y_t, s)``,
:func:`inversion.shift_profile`), and the deviance of the best of them is tested against its
exact null distribution (:func:`inversion.goodness_of_fit`, with the fit's Jacobian, so
sparse counts are handled).

A template bank is a grid: an observation of a shape in the bank, at an attitude and a
roughness between grid points, is not fitted exactly by any template, and at high signal
the deviance of that grid error exceeds the noise. The test therefore tolerates the bank's
resolution along its continuous dimensions at the best template, as an **allowance** (the
non-centrality of :mod:`inversion._gof`): the deviance, at the observation's fitted signal
level and shift, with which the grid's neighbours explain the noise-free best template,

- attitude: the largest over the ``neighbours`` nearest grid attitudes (geodesic angle
  modulo the shape's symmetry) of the same shape, material and finish;
- roughness: the largest over the adjacent finishes (next smoother and next rougher
  ``m``) of the same shape, attitude and material;

summed. An observation of a shape, material and roughness range the bank holds lies within
about a grid spacing of its best template; one that no template fits (another shape, a
material or a roughness outside the bank) lies further from the bank than its templates lie
from each other, and is flagged (``p < threshold``). Materials are categories, not a grid:
no allowance. ``resolution_scale`` multiplies the allowance (1: one grid spacing along each
dimension, conservative; smaller is stricter).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from ._gof import (
    DEFAULT_MISMATCH_P,
    _check_pair,
    _kind,
    _variance,
    deviance_function,
    goodness_of_fit,
)
from ._noise import _shift_profile

__all__ = ["template_goodness_of_fit", "fit_template"]

_GAIN_ITERATIONS = 12
_SHIFT_STEP = 1e-4  # bins, central difference of the shift derivative


def _shifted(y, s):
    return _shift_profile(y, np.float64(s), np)


def _gain(x, ys, noise):
    """Maximum-likelihood gain of ``g ys`` for data ``x`` (Poisson: Newton on the score;
    Gaussian models: re-weighted least squares, the refiner's fixed point)."""
    tot = float(np.sum(ys))
    if not tot > 0:
        return 0.0
    g = max(float(np.sum(x)) / tot, 1e-300)
    if _kind(noise) == "poisson":
        b = float(noise.background)
        if b == 0.0:
            return g  # sum(x) / sum(ys) is the exact maximum
        xs = x * ys
        for _ in range(_GAIN_ITERATIONS):
            lam = g * ys + b
            f = float(np.sum(xs / lam)) - tot
            df = -float(np.sum(xs * ys / (lam * lam)))
            if df >= 0:
                break
            new = max(g - f / df, 0.5 * g)
            done = abs(new - g) <= 1e-12 * g
            g = new
            if done:
                break
        return g
    for _ in range(_GAIN_ITERATIONS):
        w = 1.0 / _variance(noise, g * ys, None)
        den = float(np.sum(w * ys * ys))
        if not den > 0:
            break
        new = float(np.sum(w * x * ys)) / den
        done = abs(new - g) <= 1e-12 * abs(g)
        g = new
        if done:
            break
    return g


def _fit_at(s, x, y, noise, dev_of):
    """Deviance, expectation and gain of the template shifted by ``s`` (gain profiled out)."""
    ys = _shifted(y, s)
    g = _gain(x, ys, noise)
    mu = g * ys
    return dev_of(x, mu), mu, g


def _profile_deviance(s, x, y, noise, dev_of):
    return _fit_at(s, x, y, noise, dev_of)[0]


def fit_template(x, y, shift0: float, noise, *, window: float = 1.0):
    """Maximum-likelihood ``mu = g shift(y, s)`` for data ``x`` with the shift within
    ``shift0 +- window`` bins: ``(mu, gain, shift, deviance, jacobian)``, the Jacobian
    ``d mu / d (log g, s)`` of shape ``(C, B, 2)``."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    _check_pair(x, y)
    if _kind(noise) == "poisson":
        noise.check_data(x)
    args = (x, y, noise, deviance_function(noise))
    res = minimize_scalar(
        _profile_deviance,
        bounds=(shift0 - window, shift0 + window),
        args=args,
        method="bounded",
        options={"xatol": 1e-3},
    )
    s = float(res.x)
    dev, mu, g = _fit_at(s, *args)
    h = _SHIFT_STEP
    dmu_ds = g * (_shifted(y, s + h) - _shifted(y, s - h)) / (2 * h)
    return mu, g, s, dev, np.stack([mu, dmu_ds], axis=-1)


def _best_lag(z, y, center: float, radius: int = 2) -> float:
    """Integer shift within ``center +- radius`` maximizing the correlation of ``z`` with
    ``shift(y, k)`` (a start for :func:`fit_template`)."""
    best, arg = -np.inf, center
    for k in range(int(round(center)) - radius, int(round(center)) + radius + 1):
        c = float(np.sum(z * _shifted(y, k)))
        if c > best:
            best, arg = c, float(k)
    return arg


def _neighbour_rows(bank, t: int, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the ``neighbours`` nearest grid attitudes and of the adjacent finishes of
    template row ``t`` (module docstring)."""
    from ._classifier import attitude_error_deg

    s, a = int(bank.shape_id[t]), int(bank.attitude_id[t])
    m, f = int(bank.material_id[t]), int(bank.finish_id[t])
    same = (bank.shape_id == s) & (bank.material_id == m)
    rows = np.flatnonzero(same & (bank.finish_id == f) & (bank.attitude_id != a))
    att = rows[:0]
    if rows.size:
        sym = bank.names.get("symmetry", ["none"] * (s + 1))[s]
        q_t = np.broadcast_to(np.asarray(bank.quat[t], np.float64), (rows.size, 4))
        ang = attitude_error_deg(q_t, np.asarray(bank.quat[rows], np.float64), sym)
        att = rows[np.argsort(ang, kind="stable")[:neighbours]]
    fin = np.flatnonzero(same & (bank.attitude_id == a) & (bank.finish_id != f))
    m_of = np.log1p(np.asarray(bank.names.get("finish_m", []), np.float64))
    if fin.size and m_of.size:
        mf = m_of[bank.finish_id[fin]]
        below, above = fin[mf < m_of[f]], fin[mf > m_of[f]]
        fin = np.concatenate(
            [
                below[np.argsort(-m_of[bank.finish_id[below]])[:1]],
                above[np.argsort(m_of[bank.finish_id[above]])[:1]],
            ]
        )
    else:
        fin = fin[:0]
    return att, fin


def template_goodness_of_fit(
    prep,
    x,
    classification,
    noise,
    *,
    threshold: float = DEFAULT_MISMATCH_P,
    neighbours: int = 4,
    resolution_scale: float = 1.0,
    candidates: int = 3,
):
    """:class:`~inversion.GoodnessOfFit` of each observation's best template (the lowest
    deviance among the classifier's first `candidates`), with the bank's resolution as
    allowance (module docstring).

    **Arguments:**

    - `prep`: the :class:`~inversion.PreparedBank` classified against; `x`: the observations
      ``(N, C, B)`` in the units `noise` describes (photo-counts for
      :class:`~inversion.PoissonCounts`); `classification`: :func:`inversion.classify`'s result.
    - `noise`: the observations' noise model.
    - `threshold`: p-value below which no template fits; `neighbours`: nearest grid
      attitudes searched for the attitude allowance; `resolution_scale`: multiplies the
      allowance.

    **Returns:** a tuple of :class:`~inversion.GoodnessOfFit`, one per observation.
    """
    if neighbours < 1 or candidates < 1:
        raise ValueError(
            f"template fit: neighbours ({neighbours}) and candidates ({candidates}) must be >= 1"
        )
    if not resolution_scale >= 0:
        raise ValueError(f"template fit: resolution_scale must be >= 0, got {resolution_scale}")
    x = np.asarray(x, np.float64)
    bank = prep.bank
    sigs = bank.signatures
    out = []
    for j in range(len(x)):
        # the best template by likelihood among the classifier's first `candidates` (the
        # cosine score ranks, it is not the likelihood)
        fits = []
        for c in range(min(candidates, classification.index.shape[1])):
            t = int(classification.index[j, c])
            y = np.asarray(sigs[t], np.float64)
            shift0 = float(classification.shift_refined[j, c])
            fits.append((fit_template(x[j], y, shift0, noise), t))
        (mu, g, s, _, jac), t = min(fits, key=lambda f: f[0][3])
        allowance = 0.0
        if resolution_scale > 0 and g > 0:
            target = mu + (float(noise.background) if _kind(noise) == "poisson" else 0.0)
            for rows in _neighbour_rows(bank, t, neighbours):
                devs = []
                for row in rows:
                    yn = np.asarray(sigs[row], np.float64)
                    *_, d, _ = fit_template(target, yn, _best_lag(target, yn, s), noise)
                    devs.append(d)
                allowance += max(devs, default=0.0)
            allowance *= resolution_scale
        out.append(
            goodness_of_fit(x[j], mu, noise, jacobian=jac, threshold=threshold, allowance=allowance)
        )
    return tuple(out)
