"""How fast the posterior sampler mixes: ArviZ's R-hat and bulk ESS across walkers, and the
integrated autocorrelation time, against the starting ball, the emcee moves and the length.

Three held-out observations of ``bench_inversion`` (cubesat1u / aluminium SNR 1000,
cubesat3u / silver SNR 30, cylinder / gold SNR 100; m = 20; truths drawn with seed 3), each
refit from its truth (``inversion.refine``, free: attitude, m, range offset, gain), then
``inversion.sample_posterior`` with 24 walkers for each variant: ``init_scale`` (the ball is
``init_scale`` times the Laplace width; the default 0.1), ``moves`` (``stretch``, the default,
or ``de_snooker``), steps and burn-in. Columns: wall seconds of the sampling, the largest
integrated autocorrelation time (steps), ArviZ's worst R-hat and smallest bulk ESS over the
parameters (walkers as chains), and how many parameters' 68 % intervals hold the truth.

Also the deviance along the range offset at the first observation's fit (+-3 mm, other
parameters fixed): is the parameter that shows the largest R-hat most often special?

    .venv/bin/python bench/bench_mcmc_mixing.py

Writes ``bench/results/mcmc_mixing.md`` (~4 min on 2 cores).
"""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import arviz as az  # noqa: E402
import bench_inversion as B  # noqa: E402
import jax  # noqa: E402
from _timing import load_average, write_result  # noqa: E402

jax.config.update("jax_enable_x64", True)
import inversion  # noqa: E402

OBSERVATIONS = [("cubesat1u", 1000.0, "aluminium"), ("cubesat3u", 30.0, "silver"),
                ("cylinder", 100.0, "gold")]
VARIANTS = [  # init_scale, n_steps, burn_in, moves
    (0.1, 300, 100, "stretch"),
    (1.0, 300, 100, "stretch"),
    (1.0, 600, 200, "stretch"),
    (0.1, 300, 100, "de_snooker"),
    (1.0, 300, 100, "de_snooker"),
    (1.0, 500, 150, "de_snooker"),
]
FREE = ("attitude", "m", "range_offset", "gain")


def observation(shape, snr, material):
    model = B.make_model(B.SHAPES[shape]())
    t = B.random_truths(1, np.random.default_rng(3), [shape])[0]
    t["material"], t["m"] = material, 20.0
    truth, data = B.observe(model, t, snr, seed=11)
    return model, truth, data


def range_scan(model, data, fit) -> list[tuple[float, float]]:
    p0 = fit.params
    out = []
    for d in np.linspace(-3e-3, 3e-3, 7):
        p = dataclasses.replace(p0, range_offset=float(p0.range_offset + d))
        mu = np.asarray(model.expected(p, model.prepare(p)), np.float64)
        pos = data > 0
        dev = 2.0 * (np.sum(data[pos] * np.log(data[pos] / mu[pos])) - np.sum(data - mu))
        out.append((d, dev))
    base = min(v for _, v in out)
    return [(d, v - base) for d, v in out]


def main() -> None:
    rows, scan = [], None
    for shape, snr, material in OBSERVATIONS:
        model, truth, data = observation(shape, snr, material)
        fit = inversion.refine(model, data, truth, free=FREE)
        name = f"{shape}/{material} SNR {snr:g}"
        print(name, "refit success", fit.success, flush=True)
        if scan is None:
            scan = (name, range_scan(model, data, fit))
        for init, steps, burn, moves in VARIANTS:
            cfg = inversion.MCMCConfig.model_validate(
                {"sampler": {"n_walkers": 24, "n_steps": steps, "burn_in": burn,
                             "init_scale": init, "moves": moves, "progress": False}}
            )
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = inversion.sample_posterior(model, data, fit, config=cfg)
            wall = time.perf_counter() - t0
            idata = res.to_inference_data()
            rh, es = az.rhat(idata), az.ess(idata, method="bulk")
            rmax = max(float(np.max(rh[v].values)) for v in rh.data_vars)
            emin = min(float(np.min(es[v].values)) for v in es.data_vars)
            inside = res.contains(res.truth_vector(truth), 0.68)
            row = (name, init, moves, steps, burn, wall, float(np.max(res.tau)), rmax, emin,
                   f"{int(inside.sum())}/{inside.size}", fit.success)
            rows.append(row)
            print(row, flush=True)
    lines = [
        "# Sampler mixing: R-hat and ESS across walkers against start ball, moves, length",
        "",
        f"Command: `.venv/bin/python bench/bench_mcmc_mixing.py` (x64, 24 walkers; refit "
        f"from the truth; load average {load_average()} on 2 cores). R-hat and bulk ESS: "
        "ArviZ over the parameters, walkers as chains; tau: largest integrated "
        "autocorrelation time (steps); in 68 %: parameters whose 68 % interval holds the truth.",
        "",
        "| observation | init_scale | moves | steps / burn-in | s | max tau | worst R-hat "
        "| min bulk ESS | in 68 % |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, init, moves, steps, burn, wall, tau, rmax, emin, inside, ok in rows:
        lines.append(
            f"| {name}{'' if ok else ' (refit not converged)'} | {init:g} | {moves} "
            f"| {steps} / {burn} | {wall:.1f} | {tau:.1f} | {rmax:.2f} | {emin:.0f} "
            f"| {inside} |"
        )
    lines += ["", f"Deviance along the range offset at the fit of {scan[0]} (others fixed):",
              "", "| offset (mm) | deviance - min |", "|---|---|"]
    lines += [f"| {d * 1e3:+.1f} | {v:.1f} |" for d, v in scan[1]]
    write_result("mcmc_mixing", lines)


if __name__ == "__main__":
    main()
