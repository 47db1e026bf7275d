"""How much the data constrain the complex index: the profile likelihood at the true index.

For the held-out observations of ``bench_inversion`` (seed 7) at SNR 1000 and 100: the
refiner started at the truth with every parameter free, and again with the index fixed at
the truth (attitude, m, range offset and gain free). The deviance difference is the profile
likelihood ratio of the true index (2 degrees of freedom: 95% at 5.99). Small differences
with a refined index far from the truth mean a flat ridge in the likelihood (the index
trades against the gain through the normal-incidence reflectance): the posterior there is
broad, and an MCMC interval that excludes the truth has not explored it.

Writes ``bench/results/index_profile.md``. Run: ``.venv/bin/python bench/bench_index_profile.py``
(x64; ~5 min on 2 cores).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_inversion as B  # noqa: E402  (sets x64 and the shared models)

from inversion._refine import refine  # noqa: E402


def main():
    brdf, brdf_name = B.choose_brdf("auto")
    models = B.make_models(brdf)
    lines = [
        "# Profile likelihood of the true index",
        "",
        "Command: `.venv/bin/python bench/bench_index_profile.py` (x64). BRDF: "
        + brdf_name
        + ". Refiner (Poisson deviance) from the truth, all free vs index fixed at the truth.",
        "",
        "| SNR | observation | refined n | true n | deviance, all free | index fixed | "
        "difference (95%: 5.99) |",
        "|---|---|---|---|---|---|---|",
    ]
    for snr in (1000.0, 100.0):
        for o in B.make_observations(models, 6, [snr], 7):
            model, truth = models[o["shape"]], o["truth"]
            full = refine(model, o["data"], [truth], noise=B.NOISE, max_steps=100, rounds=3)
            fixed = refine(
                model,
                o["data"],
                [truth],
                noise=B.NOISE,
                max_steps=100,
                rounds=3,
                free=("attitude", "m", "range_offset", "gain"),
            )
            n_fit, n_true = complex(full.params.n[0]), complex(truth.n[0])
            lines.append(
                f"| {snr:g} | {o['shape']}/{o['material']} | {n_fit.real:.3f}{n_fit.imag:+.3f}j | "
                f"{n_true.real:.3f}{n_true.imag:+.3f}j | {full.cost:.2f} | {fixed.cost:.2f} | "
                f"{fixed.cost - full.cost:.2f} |"
            )
            print(lines[-1], flush=True)
    out = Path(__file__).resolve().parent / "results" / "index_profile.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
