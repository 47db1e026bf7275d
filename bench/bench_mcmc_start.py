"""MCMC starting ball and sampler coordinates: the pseudo-inverse Laplace ball against the
prior-regularized one, and the reflectance shear of the gain (``sample_posterior(shear=)``).

Two held-out observations of ``bench_inversion`` at SNR 1000 (a matte 3U silica CubeSat and a
glossy gold cylinder, the refiner started at the truth), emcee 24 walkers, 300 and 1500
steps (a third burned in). For each starting ball: the largest integrated autocorrelation
time, the acceptance fraction, the 68% interval widths of the roll (``rot_z``, about the line
of sight) and of ``n'``, and the truth's offset from the posterior median in units of the
68% half-width (``z``; about +-1 if the interval is right).

- ``pinv``: the ball before: ``init_scale * N(0, cov_theta)`` with ``cov_theta`` the
  pseudo-inverse of ``J^T J`` (0 in unconstrained directions, sd floored at 1e-5);
- ``regularized``: ``inversion._mcmc._ball_root`` now, ``(pinv(cov) + I / 0.5^2)^-1``;
- ``regularized + shear``: and the walkers move in coordinates whose log gain is shifted by
  the log normal-incidence reflectance (``inversion._mcmc._ReflectanceShear``).

Writes ``bench/results/mcmc_start_ball.md``. Run: ``.venv/bin/python bench/bench_mcmc_start.py``
(x64; ~6 min on 2 cores, most of it compilation).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_inversion as B  # noqa: E402  (sets x64 and the shared models)

import inversion._mcmc as MC  # noqa: E402
from inversion._mcmc import ChainTooShortWarning, sample_posterior  # noqa: E402
from inversion._params import PhysicalParams  # noqa: E402
from inversion._refine import refine  # noqa: E402


def pinv_ball_root(cov, ndim, prior_scale=None):
    """The starting ball before: the pseudo-inverse covariance, sd clipped to [1e-5, 1]."""
    if cov is None or not np.all(np.isfinite(cov)):
        return np.eye(ndim) * 1e-2
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    return v * np.clip(np.sqrt(np.clip(w, 0.0, None)), 1e-5, 1.0)


def main():
    brdf, brdf_name = B.choose_brdf("auto")
    models = B.make_models(brdf)
    obs = B.make_observations(models, 6, [1000.0], 7)
    regularized = MC._ball_root
    rows = []
    for idx in (1, 5):
        o = obs[idx]
        model, truth = models[o["shape"]], o["truth"]
        fit = refine(model, o["data"], [truth], noise=B.NOISE, max_steps=100, rounds=3)
        sym = B.SHAPES[o["shape"]][1]
        tq = B.truth_in_symmetry(
            np.asarray(truth.quaternion), np.asarray(fit.params.quaternion), sym
        )
        t_eq = PhysicalParams(
            tq, truth.m, truth.n, truth.corr_length, truth.range_offset, truth.gain
        )
        for name, root, shear in (
            ("pinv", pinv_ball_root, False),
            ("regularized", regularized, False),
            ("regularized + shear", regularized, True),
        ):
            MC._ball_root = root
            for steps in (300, 1500):
                cfg = B.chain_config(steps)
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", ChainTooShortWarning)
                    post = sample_posterior(
                        model, o["data"], fit, config=cfg, noise=B.NOISE, shear=shear
                    )
                dt = time.perf_counter() - t0
                z, lo, hi = B.z_scores(post, t_eq)
                lab = post.labels
                i_roll, i_n = lab.index("rot_z [deg]"), lab.index("n_re[0]")
                zs = " ".join(f"{lb.split()[0]} {v:+.1f}" for lb, v in zip(lab, z, strict=True))
                rows.append(
                    B.chain_row(
                        f"{o['shape']}/{o['material']} m={float(truth.m[0]):.0f}",
                        name,
                        steps,
                        dt,
                        post,
                        float(hi[i_roll] - lo[i_roll]),
                        float(hi[i_n] - lo[i_n]),
                        zs,
                    )
                )
                print(rows[-1], flush=True)
        MC._ball_root = regularized
    lines = [
        "# MCMC starting ball (pseudo-inverse against prior-regularized) and reflectance shear",
        "",
        "Command: `.venv/bin/python bench/bench_mcmc_start.py` (x64). BRDF: " + brdf_name + ".",
        "Observations of bench_inversion (seed 7) at SNR 1000, refiner started at the truth; "
        "emcee 24 walkers, a third of the steps burned in. z: (truth - median) / 68% half-width.",
        "",
        "| observation | ball | steps | s | max tau | acceptance | roll 68% width (deg) | "
        "n' 68% width | z per parameter |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.1f} | {r[4]:.0f} | {r[5]:.2f} | {r[6]:.3g} | "
            f"{r[7]:.3g} | {r[8]} |"
        )
    lines += [
        "",
        "The roll of the glossy gold cylinder is unconstrained (its Cramer-Rao bound is "
        "infinite): its posterior is flat. The estimated tau grows with the chain (300 -> 1500 "
        "steps) in every row: no chain here is converged, and short chains underestimate tau.",
    ]
    out = Path(__file__).resolve().parent / "results" / "mcmc_start_ball.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
