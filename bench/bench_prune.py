"""Facet pruning (``SimulatorModel(prune=True)``, :class:`ppr.FaceSubset`): is it safe, and
what does it save?

A solver round and an MCMC chain hold the visibility fixed at one pose; the facets with zero
lit-and-visible fraction there contribute exactly zero, so the pruned model renders only the
lit and visible facets (padded to 8, 16, 32, ...) instead of the whole padded mesh (64 on the
inversion bench). On the observations of ``bench_inversion.py`` (same shapes, materials,
sensor, seed) this measures, pruned against unpruned:

- the largest difference of the expected counts and of the residual Jacobian (forward-mode,
  every free parameter), relative to their largest entry, at the truth;
- the refiner (3 rounds from the truth) and an emcee chain (24 walkers x 300 steps) wall
  time, and the refined cost and posterior medians of both (same answers expected);
- the per-call cost of the walker-batched log-posterior.

Median of repeated runs after a warm-up (compilation excluded and reported). Writes
``bench/results/prune.md``.

Run: ``.venv/bin/python bench/bench_prune.py`` (x64; ~4 min on 2 cores).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import bench_inversion as B  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import median_time  # noqa: E402

from inversion._mcmc import ChainTooShortWarning, make_log_prob, sample_posterior  # noqa: E402
from inversion._params import Parametrisation  # noqa: E402
from inversion._refine import (  # noqa: E402
    _from_physical,
    _jacobians,
    _pure,
    _weights,
    refine,
)

OUT = Path(__file__).resolve().parent / "results"


def rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def compare(o, full, pruned, steps):
    truth, data = o["truth"], o["data"]
    aux_f, aux_p = full.prepare(truth), pruned.prepare(truth)
    d_mu = rel(pruned.expected(truth, aux_p), full.expected(truth, aux_f))
    free = ("attitude", "m", "n", "range_offset", "gain")
    par = Parametrisation(truth, free, 0.01)
    th = _from_physical(par, truth)
    jac = {}
    for name, mdl, aux in (("full", full, aux_f), ("pruned", pruned, aux_p)):
        inv_sigma, _ = _weights(_pure(mdl), B.NOISE, truth, aux)
        jac[name] = np.asarray(
            _jacobians(_pure(mdl), par, aux, inv_sigma, jnp.asarray(data), th, B.NOISE)[0]
        )
    d_jac = rel(jac["pruned"], jac["full"])
    out = dict(
        faces=f"{int(np.sum(np.asarray(aux_f) > 0))} of {aux_f.shape[0]} -> {aux_p.n_faces}",
        d_mu=d_mu,
        d_jac=d_jac,
    )
    cfg = B.chain_config(steps)
    for name, mdl in (("full", full), ("pruned", pruned)):

        def fit(mdl=mdl):
            return refine(mdl, data, [truth], noise=B.NOISE, max_steps=100, rounds=3)

        out[f"t_ref_{name}"] = median_time(fit, repeats=3)
        f = fit()
        out[f"cost_{name}"] = f.cost
        par_f = Parametrisation(f.params, tuple(f.parametrisation.free), 0.01)
        lp = make_log_prob(mdl, data, par_f, cfg.priors, noise=B.NOISE)
        x = np.tile(np.asarray(_from_physical(par_f, f.params)), (12, 1))
        out[f"t_lp_{name}"] = median_time(lp, x, repeats=20)

        def chain(mdl=mdl, f=f):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ChainTooShortWarning)
                return sample_posterior(mdl, data, f, config=cfg, noise=B.NOISE)

        out[f"t_mc_{name}"] = median_time(chain, repeats=3)
        out[f"median_{name}"] = chain().median()
    scale = np.abs(out["median_full"]) + 1e-300
    out["d_median"] = float(np.max(np.abs(out["median_pruned"] - out["median_full"]) / scale))
    return out


def main():
    brdf, brdf_name = B.choose_brdf("auto")
    full, pruned = B.make_models(brdf, prune=False), B.make_models(brdf, prune=True)
    obs = B.make_observations(full, 3, [30.0, 1000.0], 7)
    t0 = time.perf_counter()
    compare(obs[0], full[obs[0]["shape"]], pruned[obs[0]["shape"]], 300)
    t_warm = time.perf_counter() - t0
    rows = []
    for o in obs:
        r = compare(o, full[o["shape"]], pruned[o["shape"]], 300)
        case = f"{o['shape']}/{o['material']} SNR {o['snr']:g}"
        rows.append((case, r))
        print(
            f"{case}: faces {r['faces']}, d_mu {r['d_mu']:.1e} d_jac {r['d_jac']:.1e} | "
            f"refine {r['t_ref_full']:.2f} -> {r['t_ref_pruned']:.2f} s | "
            f"mcmc {r['t_mc_full']:.2f} -> {r['t_mc_pruned']:.2f} s",
            flush=True,
        )
    lines = [
        "# Facet pruning: pruned against unpruned forward model",
        "",
        f"Command: `.venv/bin/python bench/bench_prune.py` (x64). BRDF: {brdf_name}. "
        "Observations of bench_inversion (seed 7; 64-facet padded meshes, 64 bins, 16 "
        "channels, Poisson counts). Refiner: 3 rounds from the truth. MCMC: 24 walkers x "
        "300 steps from the refined optimum. log-prob: one call on 12 walkers (emcee's "
        "half-ensemble). Times: medians after a warm-up "
        f"({t_warm:.0f} s incl. compilation, once).",
        "",
        "`d mu`, `d J`: largest difference of the expected counts / residual Jacobian, "
        "relative to the largest entry; `d cost`: relative difference of the refined costs; "
        "`d median`: largest relative difference of the posterior medians (same seed).",
        "",
        "| observation | facets (lit of padded -> subset) | d mu | d J | d cost | refine s full | "
        "refine s pruned | speed-up | log-prob ms full | pruned | MCMC s full | MCMC s pruned "
        "| speed-up | d median |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, r in rows:
        d_cost = abs(r["cost_pruned"] - r["cost_full"]) / max(abs(r["cost_full"]), 1e-300)
        lines.append(
            f"| {case} | {r['faces']} | {r['d_mu']:.1e} | {r['d_jac']:.1e} | {d_cost:.1e} | "
            f"{r['t_ref_full']:.2f} | {r['t_ref_pruned']:.2f} | "
            f"{r['t_ref_full'] / r['t_ref_pruned']:.1f}x | {r['t_lp_full'] * 1e3:.2f} | "
            f"{r['t_lp_pruned'] * 1e3:.2f} | {r['t_mc_full']:.2f} | {r['t_mc_pruned']:.2f} | "
            f"{r['t_mc_full'] / r['t_mc_pruned']:.1f}x | {r['d_median']:.1e} |"
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "prune.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
