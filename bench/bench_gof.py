"""Goodness of fit: calibration of the p-values, the fitted degrees of freedom, the
classifier's "no template fits" flag, and cost.

1. Null calibration, nothing fitted: 2e5 simulated deviances per profile (sparse Poisson
   counts, a 50-count return on a sparse background, dense counts, the counting noise of
   ``PoissonNoise`` with a small floor): the fraction of p-values below 0.1, 0.01, 1e-3, 1e-4
   for the Pearson type III reference (``inversion.goodness_of_fit``), a two-moment gamma, the
   normal, and the chi-squared rule of thumb (``n`` degrees of freedom).
2. Fitted parameters: a log-linear Poisson model (3 parameters; sparse, moderate, dense) and
   an identity-link model with counting noise fitted by re-weighted least squares, 2000 fits
   each: mean and variance of the z-score and the rejection rates, with the fit's Jacobian
   (the default of ``fit_goodness_of_fit``) and with the plug-in moments minus ``p``.
3. The classifier's flag (``classify(..., noise=...)``) on the smooth toy bank of
   ``tests/test_classifier.py`` (one shape, Hopf grid of 19 deg, 1944 templates): fraction of
   observations flagged, for the bank's shape (random attitudes, sub-bin offsets) and for a
   shape it lacks, at 1e4 and 1e6 counts, for resolution allowances 1, 0.5 and 0.25.
4. Cost: ``goodness_of_fit`` with a Jacobian on 16 x 64 bins; the template fit per
   observation (median of repeats after a warm-up).

Writes ``bench/results/gof_calibration.md``. Run: ``.venv/bin/python bench/bench_gof.py``
(~4 min on 2 cores; ``--quick``: 10x fewer draws).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy import special, stats  # noqa: E402

from inversion import PoissonCounts, PoissonNoise, classify, goodness_of_fit, prepare  # noqa: E402
from inversion._noise import shift_profile  # noqa: E402
from inversion._synthetic import point_lobe_bank, point_lobe_signatures  # noqa: E402

# the toy fits of the brute-force tests (a log-linear Poisson model fitted by Fisher scoring)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_gof import _glm_fit  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "gof_calibration.md"
LEVELS = (0.1, 0.01, 1e-3, 1e-4)


def _poisson_dev(y, lam):
    pos = y > 0
    return 2 * (np.where(pos, y * np.log(np.where(pos, y, 1) / lam), 0) - (y - lam)).sum(-1)


def null_calibration(r):
    rng = np.random.default_rng(0)
    cases = {
        "sparse (2000 bins, 1e-3..0.3 counts)": (
            np.exp(rng.uniform(np.log(1e-3), np.log(0.3), 2000)),
            PoissonCounts(1e-12),
        ),
        "return of 50 counts on 1e-3 background (256 bins)": (
            1e-3 + 50 * np.exp(-0.5 * ((np.arange(256) - 128) / 6.0) ** 2),
            PoissonCounts(1e-12),
        ),
        "dense (300 bins, 20..200 counts)": (rng.uniform(20, 200, 300), PoissonCounts(1e-12)),
        "counting noise, floor 0.01 (200 bins, 0.02..1 counts)": (
            np.exp(rng.uniform(np.log(0.02), np.log(1.0), 200)),
            PoissonNoise(floor=0.01),
        ),
    }
    rows = []
    for name, (mu, noise) in cases.items():
        devs = []
        for a in range(0, r, 20000):
            n = min(20000, r - a)
            y = rng.poisson(mu, size=(n, mu.size)).astype(float)
            if isinstance(noise, PoissonNoise):
                y = y + math.sqrt(noise.floor) * rng.normal(size=y.shape)
                devs.append(((y - mu) ** 2 / (mu + noise.floor)).sum(-1))
            else:
                devs.append(_poisson_dev(y, mu + 1e-12))
        dev = np.concatenate(devs)
        g = goodness_of_fit(
            np.zeros_like(mu) if isinstance(noise, PoissonCounts) else mu, mu, noise
        )
        var = g.std**2
        p3 = g.tail(dev)
        k, th = g.expected**2 / var, var / g.expected
        p2 = special.gammaincc(k, dev / th)
        pn = stats.norm.sf((dev - g.expected) / g.std)
        pc = stats.chi2.sf(dev, mu.size)
        for lab, p in (("Pearson III", p3), ("gamma", p2), ("normal", pn), ("chi2(n)", pc)):
            rows.append((name, lab, [float(np.mean(p < a)) for a in LEVELS]))
        print(name, "done", flush=True)
    return rows


def fitted_calibration(r):
    rng = np.random.default_rng(1)
    rows = []
    for n, beta, name in (
        (300, (-1.0, 0.5, -3.0), "Poisson, 56 counts in 300 bins"),
        (100, (0.0, 1.5, -1.0), "Poisson, 98 counts in 100 bins"),
        (40, (4.0, 0.3, -1.0), "Poisson, 1600 counts in 40 bins"),
    ):
        x = np.linspace(-1, 1, n)
        X = np.stack([np.ones(n), x, x * x], 1)
        y = rng.poisson(np.exp(X @ np.asarray(beta)), size=(r, n)).astype(float)
        fit = _glm_fit(y, X, np.asarray(beta))
        noise = PoissonCounts(1e-12)
        with_j = [
            goodness_of_fit(y[i], fit[i], noise, jacobian=fit[i][:, None] * X) for i in range(r)
        ]
        plug = [goodness_of_fit(y[i], fit[i], noise, n_params=3) for i in range(r)]
        for lab, res in (("Jacobian", with_j), ("plug-in - p", plug)):
            z = np.array([g.z for g in res])
            p = np.array([g.p_value for g in res])
            rows.append((name, lab, z.mean(), z.var(), [float(np.mean(p < a)) for a in LEVELS[:3]]))
        print(name, "done", flush=True)
    n = 120
    x = np.linspace(-1, 1, n)
    X = np.stack([np.ones(n), x, x * x], 1)
    noise = PoissonNoise(floor=0.02)
    mu = X @ np.array([0.6, 0.3, 0.5])
    y = rng.poisson(mu, size=(r, n)) + math.sqrt(0.02) * rng.normal(size=(r, n))
    b = np.tile([0.6, 0.3, 0.5], (r, 1))
    for _ in range(8):
        w = 1.0 / (np.maximum(b @ X.T, 0.0) + noise.floor)
        h = np.einsum("ri,ij,ik->rjk", w, X, X)
        b = np.linalg.solve(h, np.einsum("ri,ij,ri->rj", w, X, y)[..., None])[..., 0]
    fit = b @ X.T
    for lab, kw in (("Jacobian", {"jacobian": X}), ("plug-in - p", {"n_params": 3})):
        res = [goodness_of_fit(y[i], fit[i], noise, **kw) for i in range(r)]
        z = np.array([g.z for g in res])
        p = np.array([g.p_value for g in res])
        rows.append(
            (
                "counting noise, IRLS, 120 bins",
                lab,
                z.mean(),
                z.var(),
                [float(np.mean(p < a)) for a in LEVELS[:3]],
            )
        )
    return rows


def classifier_flag(n_obs):
    bank, shape_in, shape_out = point_lobe_bank()
    rng = np.random.default_rng(0)
    prep = prepare(bank)
    noise = PoissonCounts(1e-3)
    rows, per_obs = [], []
    for counts in (1e4, 1e6):
        q = rng.normal(size=(2 * n_obs, 4))
        y = np.concatenate(
            [
                point_lobe_signatures(*shape_in, q[:n_obs]),
                point_lobe_signatures(*shape_out, q[n_obs:]),
            ]
        )
        y = shift_profile(y, rng.uniform(-2, 2, (2 * n_obs, 1)))
        x = rng.poisson(counts * y + 1e-3).astype(float)
        for scale in (1.0, 0.5, 0.25):
            t0 = time.perf_counter()
            res = classify(prep, x, k=3, noise=noise, resolution_scale=scale)
            per_obs.append((time.perf_counter() - t0) / len(x))
            flags = res.no_template_fits
            rows.append((counts, scale, flags[:n_obs].mean(), flags[n_obs:].mean()))
        print(f"classifier flag at {counts:g} counts done", flush=True)
    return rows, float(np.median(per_obs[1:]))


def cost():
    rng = np.random.default_rng(2)
    mu = 1e-3 + 30 * np.exp(-0.5 * ((np.arange(64) - 30) / 4.0) ** 2) * rng.uniform(0.2, 1, (16, 1))
    y = rng.poisson(mu).astype(float)
    jac = np.stack([mu, np.gradient(mu, axis=-1), mu * np.linspace(-1, 1, 64)], -1)
    goodness_of_fit(y, mu, PoissonCounts(), jacobian=jac)
    times = []
    for _ in range(30):
        t0 = time.perf_counter()
        goodness_of_fit(y, mu, PoissonCounts(), jacobian=jac)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="10x fewer draws")
    args = ap.parse_args(argv)
    r_null, r_fit, n_obs = (20000, 200, 10) if args.quick else (200000, 2000, 40)
    t_all = time.perf_counter()
    null = null_calibration(r_null)
    fitted = fitted_calibration(r_fit)
    flag, t_flag = classifier_flag(n_obs)
    t_gof = cost()
    lines = [
        "# Goodness of fit: calibration and cost",
        "",
        f"`bench/bench_gof.py{' --quick' if args.quick else ''}` "
        f"({time.perf_counter() - t_all:.0f} s). Fraction of p-values below each level under the "
        "null (nominal: the level itself).",
        "",
        f"## 1. Nothing fitted ({r_null} simulated deviances per profile)",
        "",
        "| profile | reference | p<0.1 | p<0.01 | p<1e-3 | p<1e-4 |",
        "|---|---|---|---|---|---|",
    ]
    for name, lab, rates in null:
        lines.append(f"| {name} | {lab} | " + " | ".join(f"{v:.3g}" for v in rates) + " |")
    lines += [
        "",
        f"## 2. Fitted parameters ({r_fit} fits each; z = (D - E) / sd: ideally mean 0, "
        "variance 1)",
        "",
        "| model | moments | mean z | var z | p<0.1 | p<0.01 | p<1e-3 |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, lab, zm, zv, rates in fitted:
        lines.append(
            f"| {name} | {lab} | {zm:+.3f} | {zv:.3f} | "
            + " | ".join(f"{v:.3g}" for v in rates)
            + " |"
        )
    lines += [
        "",
        f"## 3. Classifier flag, toy bank of one shape on a 19 deg grid ({n_obs} observations "
        "each)",
        "",
        "| counts | resolution_scale | bank's shape flagged | other shape flagged |",
        "|---|---|---|---|",
    ]
    for counts, scale, fa, det in flag:
        lines.append(f"| {counts:g} | {scale:g} | {fa:.2f} | {det:.2f} |")
    lines += [
        "",
        "## 4. Cost",
        "",
        f"- `goodness_of_fit` with a Jacobian, 16 x 64 bins, 3 parameters: {1e3 * t_gof:.1f} ms "
        "(median of 30)",
        f"- `classify(..., noise=...)` on the toy bank: {1e3 * t_flag:.0f} ms per observation "
        "(median over the runs after the first; template fits of 3 candidates and 4 "
        "neighbours)",
        "",
    ]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
