"""Posterior calibration with search and chain length taken out.

``bench_inversion``'s coverage (0.56 / 0.87 at 68 % / 95 %) mixes three things: the search
(a wrong mode or material), unconverged chains, and the posterior itself. Here one truth is
observed many times (independent Poisson draws at one SNR), the refiner starts at the truth
(no search), and the same draws are sampled with short and long chains. Per draw and
parameter: is the truth inside the equal-tailed 68 % / 95 % interval, and
``z = (truth - median) / (68 % half-width)``. A calibrated posterior in its Gaussian regime
gives coverage 0.68 / 0.95 and ``mean z^2`` about 1.

Coverage is pooled over draws; its 95 % binomial interval (Wilson) treats the draws as
independent (they are) but the parameters of one draw as one trial each, per parameter.

Writes ``bench/results/coverage.md`` and ``bench/results/coverage_z.png``. Run:
``.venv/bin/python bench/bench_coverage.py [--draws 24] [--snr 1000] [--truth 1]``
(x64; ~10 min on 2 cores, ~4 of them compilation).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_inversion as B  # noqa: E402  (sets x64 and the shared models)

from inversion import cramer_rao  # noqa: E402
from inversion._mcmc import ChainTooShortWarning, sample_posterior  # noqa: E402
from inversion._noise import NoiseModel, observe  # noqa: E402
from inversion._refine import refine  # noqa: E402

LEVELS = (0.68, 0.95)


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion ``k / n``."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return float(mid - half), float(mid + half)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=24, help="independent noise draws")
    ap.add_argument("--snr", type=float, default=1000.0)
    ap.add_argument("--truth", type=int, default=1, help="index of bench_inversion's truths")
    ap.add_argument("--steps", type=int, nargs="+", default=[300, 1500])
    ap.add_argument("--init-scale", type=float, default=0.5, help="starting ball / Laplace")
    ap.add_argument("--tag", default="", help="suffix of the output files")
    args = ap.parse_args()

    brdf, brdf_name = B.choose_brdf("auto")
    models = B.make_models(brdf)
    o = B.make_observations(models, 6, [args.snr], 7)[args.truth]
    model, truth, sym = models[o["shape"]], o["truth"], B.SHAPES[o["shape"]][1]
    x = np.maximum(np.asarray(model.expected(truth, model.prepare(truth))), 0.0)
    crb = cramer_rao(model, truth, B.NOISE)
    case = (
        f"{o['shape']} / {o['material']} (n = {complex(truth.n[0]):.3g}), m = "
        f"{float(truth.m[0]):.3g}, SNR {args.snr:g} ({args.snr**2:.3g} expected counts)"
    )
    print(case, "| attitude CRB", crb.attitude_sigma_deg, "deg", flush=True)
    on_floor = {"n_im[0]"} if abs(complex(truth.n[0]).imag) <= 1e-9 else set()

    t_all = time.perf_counter()
    recs = {s: [] for s in args.steps}
    for d in range(args.draws):
        data = np.asarray(observe(x, NoiseModel(snr=args.snr), seed=5000 + d).data, np.float64)
        fit = refine(model, data, [truth], noise=B.NOISE, max_steps=100, rounds=3)
        for steps in args.steps:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ChainTooShortWarning)
                post = sample_posterior(
                    model,
                    data,
                    fit,
                    config=B.chain_config(steps, init_scale=args.init_scale),
                    noise=B.NOISE,
                )
            dt = time.perf_counter() - t0
            t_eq = B.truth_for_posterior(post, truth, sym)
            z = B.z_scores(post, t_eq)[0]
            tv = post.truth_vector(t_eq)
            keep = [i for i, lab in enumerate(post.labels) if lab != "gain" and lab not in on_floor]
            recs[steps].append(
                dict(
                    labels=[post.labels[i] for i in keep],
                    z=z[keep],
                    inside={lv: post.contains(tv, lv)[keep] for lv in LEVELS},
                    tau=float(np.max(post.tau)),
                    converged=bool(post.converged),
                    acc=float(np.mean(post.acceptance_fraction)),
                    time=dt,
                )
            )
            r = recs[steps][-1]
            print(
                f"draw {d} steps {steps}: {dt:.1f} s tau {r['tau']:.0f} max|z| "
                f"{np.max(np.abs(r['z'])):.2f} in68 {r['inside'][0.68].mean():.2f} "
                f"in95 {r['inside'][0.95].mean():.2f}",
                flush=True,
            )
    total = time.perf_counter() - t_all

    labels = recs[args.steps[0]][0]["labels"]
    lines = [
        "# Posterior calibration: coverage with the search and the chain length taken out",
        "",
        f"Command: `.venv/bin/python bench/bench_coverage.py --draws {args.draws} --snr "
        f"{args.snr:g} --truth {args.truth} --steps {' '.join(map(str, args.steps))}"
        + (f" --init-scale {args.init_scale:g}" if args.init_scale != 0.5 else "")
        + (f" --tag {args.tag}" if args.tag else "")
        + "` (x64). "
        f"BRDF: {brdf_name}. Run time {total:.0f} s after compilation.",
        "",
        f"Truth: bench_inversion's truth {args.truth} (seed 7): {case}. Cramer-Rao bound on "
        f"the attitude {crb.attitude_sigma_deg:.3g} deg. {args.draws} independent Poisson "
        "draws; the refiner starts at the truth (3 rounds); emcee 24 walkers, a third of the "
        f"steps burned in, the walkers started in a ball of {args.init_scale:g} x the Laplace "
        "scale about the optimum, the same start for every chain length. The truth is scored "
        "through "
        "the one of its exact symmetry images nearest the posterior (`truth_for_posterior`). "
        + (
            f"Left out: {sorted(on_floor)} (truth on the parameter's hard boundary). "
            if on_floor
            else ""
        )
        + "Interval on a coverage: 95 % Wilson. Pooled rows count every (draw, parameter) "
        "as a trial, which overstates their independence (the parameters of one draw are "
        "correlated); the per-parameter rows are over independent draws.",
        "",
        "| steps | median s | median max tau | converged | 68 % coverage (95 % CI) | "
        "95 % coverage (95 % CI) | mean z^2 | median abs(z) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for steps in args.steps:
        rs = recs[steps]
        z = np.stack([r["z"] for r in rs])
        cells = []
        for lv in LEVELS:
            ins = np.stack([r["inside"][lv] for r in rs])
            k, n = int(ins.sum()), ins.size
            lo, hi = wilson(k, n)
            cells.append(f"{k / n:.2f} ({lo:.2f}-{hi:.2f}, n={n})")
        conv = np.mean([r["converged"] for r in rs])
        lines.append(
            f"| {steps} | {np.median([r['time'] for r in rs]):.1f} | "
            f"{np.median([r['tau'] for r in rs]):.0f} | {conv:.2f} | "
            f"{cells[0]} | {cells[1]} | {np.mean(z**2):.2f} | {np.median(np.abs(z)):.2f} |"
        )
    lines += [
        "",
        "Per parameter (longest chains): coverage at 68 % / 95 % with the Wilson interval of "
        "each (n = draws), mean z, mean z^2 (calibrated: 0.68 / 0.95, 0, 1).",
        "",
        "| parameter | 68 % | 95 % | mean z | mean z^2 |",
        "|---|---|---|---|---|",
    ]
    rs = recs[args.steps[-1]]
    z = np.stack([r["z"] for r in rs])
    for j, lab in enumerate(labels):
        cells = []
        for lv in LEVELS:
            ins = np.array([r["inside"][lv][j] for r in rs])
            lo, hi = wilson(int(ins.sum()), ins.size)
            cells.append(f"{ins.mean():.2f} ({lo:.2f}-{hi:.2f})")
        zj = z[:, j]
        lines.append(
            f"| {lab} | {cells[0]} | {cells[1]} | {zj.mean():+.2f} | {np.mean(zj**2):.2f} |"
        )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    fig, axes = plt.subplots(1, len(args.steps), figsize=(5 * len(args.steps), 4), squeeze=False)
    for ax, steps in zip(axes[0], args.steps, strict=True):
        zz = np.sort(np.concatenate([r["z"] for r in recs[steps]]))
        # the 68 % half-width is 0.994 sigma for a Gaussian: z ~ N(0, 1) when calibrated
        qn = stats.norm.ppf((np.arange(len(zz)) + 0.5) / len(zz))
        ax.plot(qn, zz, ".", ms=3)
        ax.plot([-3, 3], [-3, 3], "k--", lw=1, label="calibrated")
        ax.set_xlabel("normal quantile")
        ax.set_ylabel("z = (truth - median) / 68 % half-width")
        ax.set_title(f"{steps} steps: mean z^2 = {np.mean(zz**2):.2f}")
        ax.legend()
    fig.suptitle(case, fontsize=9)
    fig.tight_layout()
    res = Path(__file__).resolve().parent / "results"
    fig.savefig(res / f"coverage_z{args.tag}.png", dpi=120)
    lines += ["", f"Plot: `bench/results/coverage_z{args.tag}.png` (z against normal quantiles)."]
    (res / f"coverage{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
