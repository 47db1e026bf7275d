"""The material stage of ``inversion.invert`` on held-out observations, against per-material
fits started at the truth: is a wrong material's probability the data's answer, or a fit
that stopped short?

For each chosen observation of ``bench/bench_inversion.py`` (same truths and noise: index
``i`` is truth ``i // 3`` at SNR ``(30, 100, 1000)[i % 3]``, in-bank), ``invert`` runs with
the right shape as the only candidate (the bench's materials, finishes and ``top_k``; no
sampling), and its material table (probability, log evidence, deviance, solver steps and
result, m) is printed next to a refinement of every library material started at the truth's
attitude, roughness, range offset and gain (100 steps x 3 rounds).

    .venv/bin/python bench/bench_material_fits.py [--obs 2 14]

Writes ``bench/results/material_fits.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--obs", type=int, nargs="+", default=[2, 14])
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import bench_inversion as B
    from _timing import load_average, write_result

    import inversion
    import ppr

    truths = B.random_truths(8, np.random.default_rng(2026), list(B.SHAPES))
    meshes = {k: f() for k, f in B.SHAPES.items()}
    models = {k: B.make_model(m) for k, m in meshes.items()}
    mats = {m: complex(np.asarray(ppr.load_material(m).n)) for m in B.MATERIALS}
    noise = inversion.PoissonCounts()
    free = ("attitude", "m", "range_offset", "gain")
    load = load_average()
    lines = [
        "# The material stage against per-material fits from the truth",
        "",
        f"Command: `.venv/bin/python bench/bench_material_fits.py --obs "
        f"{' '.join(map(str, args.obs))}` (observations of `bench/bench_inversion.py`; load "
        f"average {load}). Per material: `invert`'s fit (probability, log evidence, deviance, "
        "solver steps and result, m), then the refinement started at the truth (deviance, log "
        "evidence, steps, result, m).",
        "",
    ]
    for i in args.obs:
        j, s = divmod(i, 3)
        t, snr = truths[j], (30.0, 100.0, 1000.0)[s]
        model = models[t["shape"]]
        truth, data = B.observe(model, t, snr, seed=1000 + j)
        cfg = inversion.InvertConfig(
            materials=B.MATERIALS, finishes=B.FINISHES, top_k=4, mcmc=None, grid={"size": 2}
        )
        t0 = time.perf_counter()
        inv = inversion.invert(data, {t["shape"]: model}, config=cfg)
        wall = time.perf_counter() - t0
        lines += [
            f"## Observation {i}: {t['shape']}, {t['material']}, m = {t['m']:.1f}, SNR {snr:g}",
            "",
            f"`invert` ({wall:.1f} s): {inv.material[0]}, deviance {inv.fit.cost:.2f}.",
            "",
            "| material | invert: p | log Z | deviance | steps, result | m | from the truth: "
            "deviance | log Z | steps, result | m |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for mf in inv.materials[0]:
            f = mf.fit
            st = inversion.PhysicalParams(
                truth.quaternion,
                list(truth.m),
                [mats[mf.name]] * len(truth.m),
                range_offset=truth.range_offset,
                gain=truth.gain,
            )
            g = inversion.refine(model, data, [st], noise=noise, free=free, max_steps=100, rounds=3)
            lines.append(
                f"| {mf.name} | {mf.probability:.3f} | {mf.log_evidence:.2f} | {f.cost:.2f} | "
                f"{f.n_steps}, {f.result} | {np.asarray(f.params.m)[0]:.1f} | {g.cost:.2f} | "
                f"{inversion.log_evidence(g):.2f} | {g.n_steps}, {g.result} | "
                f"{np.asarray(g.params.m)[0]:.1f} |"
            )
            print(lines[-1], flush=True)
        lines.append("")
    write_result("material_fits", lines)


if __name__ == "__main__":
    main()
