"""emcee proposal moves: the stretch move against differential evolution + snooker.

Held-out observations of ``bench_inversion`` (seed 7): a matte 3U silica CubeSat, a glossy
gold cylinder and a matte 1U aluminium cube, at SNR 1000 and 100, the refiner started at the
truth. emcee 24 walkers from the same starting ball (``inversion._mcmc._ball_root``, shear
on), 300 and 1500 steps (a third burned in), ``SamplerConfig.moves`` = ``"stretch"`` or
``"de_snooker"`` (DEMove 0.8 + DESnookerMove 0.2). For each: wall time, the largest
integrated autocorrelation time (emcee's estimator, tol 0), the acceptance fraction, the
smallest effective sample size per second, and the truth's offset from the posterior median
in 68 % half-widths (``|z|`` max over the parameters; about 1 or less when the interval is
right).

Writes ``bench/results/mcmc_moves.md``. Run: ``.venv/bin/python bench/bench_mcmc_moves.py``
(x64; ~5 min on 2 cores).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_inversion as B  # noqa: E402  (sets x64 and the shared models)

from inversion._mcmc import ChainTooShortWarning, sample_posterior  # noqa: E402
from inversion._refine import refine  # noqa: E402

CASES = ((1, 1000.0), (5, 1000.0), (3, 1000.0), (1, 100.0), (5, 100.0))  # (truth index, SNR)


def run(model, data, fit, moves, steps):
    cfg = B.chain_config(steps, moves)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ChainTooShortWarning)
        post = sample_posterior(model, data, fit, config=cfg, noise=B.NOISE)
    return post, time.perf_counter() - t0


def main():
    brdf, brdf_name = B.choose_brdf("auto")
    models = B.make_models(brdf)
    obs = {snr: B.make_observations(models, 6, [snr], 7) for snr in sorted({c[1] for c in CASES})}
    rows = []
    for idx, snr in CASES:
        o = obs[snr][idx]
        model, truth = models[o["shape"]], o["truth"]
        fit = refine(model, o["data"], [truth], noise=B.NOISE, max_steps=100, rounds=3)
        for steps in (300, 1500):
            for moves in ("stretch", "de_snooker"):
                post, dt = run(model, o["data"], fit, moves, steps)
                t_eq = B.truth_for_posterior(post, truth, B.SHAPES[o["shape"]][1])
                z = B.z_scores(post, t_eq)[0]
                keep = [i for i, lab in enumerate(post.labels) if lab != "gain"]
                case = f"{o['shape']}/{o['material']} m={float(truth.m[0]):.0f} SNR {snr:g}"
                az = np.abs(z[keep])
                rows.append(
                    B.chain_row(
                        case,
                        moves,
                        steps,
                        dt,
                        post,
                        float(np.min(post.ess)) / dt,
                        float(np.max(az)),
                        int(np.sum(az <= 1.0)),
                        len(keep),
                    )
                )
                print(rows[-1], flush=True)
    lines = [
        "# emcee moves: stretch against differential evolution + snooker",
        "",
        "Command: `.venv/bin/python bench/bench_mcmc_moves.py` (x64). BRDF: " + brdf_name + ".",
        "Observations of bench_inversion (seed 7), refiner started at the truth; emcee 24 "
        "walkers, the same starting ball, a third of the steps burned in. tau: largest "
        "integrated autocorrelation time (steps; short chains underestimate it); ESS/s: "
        "smallest effective sample size per wall second; z: (truth - median) / 68% "
        "half-width over the parameters except the gain.",
        "",
        "| observation | moves | steps | s | max tau | acceptance | min ESS/s | max abs(z) | "
        "abs(z) <= 1 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.1f} | {r[4]:.0f} | {r[5]:.2f} | {r[6]:.1f} | "
            f"{r[7]:.2f} | {r[8]} of {r[9]} |"
        )
    out = Path(__file__).resolve().parent / "results" / "mcmc_moves.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
