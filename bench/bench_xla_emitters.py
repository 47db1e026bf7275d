"""Compile time against run time for XLA:CPU's two kernel emitters: the MLIR fusion emitters
(JAX's default) and the older elemental ones (``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``).

Each setting runs in a fresh process (XLA reads ``XLA_FLAGS`` once, when its CPU backend
starts), with the compilation cache off (``PPR_JAX_CACHE=0``): the first call of each program
(compilation and run) and the median of ``--repeats`` calls after it, for

- ``ppr.mueller_brdf`` (aluminium, m = 300, float64) on random upper-hemisphere direction
  pairs: single + multiple on 2e5 rows, single + double + multiple on 2e4 rows;
- ``ppr.simulate`` of the 3U CubeSat with panels (configs/scenes/cubesat3u_panels.toml: facet
  sum and the macro double bounce);
- the inversion's forward-model programs (compiled with the emitters of
  ``PPR_XLA_EMITTERS``, :func:`inversion_programs`): a refinement, the Fisher matrix and a
  short chain, on the ``ppr invert`` example and on a cylinder with the single term only.

    .venv/bin/python bench/bench_xla_emitters.py [--repeats 3]

Writes ``bench/results/xla_emitters.md``. The same comparison on ``ppr invert`` (a cold run
dominated by compilation) is in ``bench/results/compile.md``, section "invert".
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

from _timing import load_average, write_result

ROOT = Path(__file__).resolve().parents[1]
FLAG = "--xla_cpu_use_fusion_emitters=false"


def child(repeats: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from _timing import first_and_median_time

    import ppr

    rng = np.random.default_rng(0)

    def dirs(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2])
        return jnp.asarray(v / np.linalg.norm(v, axis=1, keepdims=True))

    mat = ppr.Material(complex(0.94, 6.42), 300.0)
    out = {}
    for terms, n in ((("single", "multiple"), 200_000), (("single", "double", "multiple"), 20_000)):
        k_in, k_out = dirs(n), dirs(n)
        nrm = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), (n, 3))
        fn = jax.jit(lambda a, b, c, terms=terms: ppr.mueller_brdf(a, b, c, mat, terms=terms))
        out[f"ppr.mueller_brdf {' + '.join(terms)}, {n} rows"] = first_and_median_time(
            fn, k_in, k_out, nrm, repeats=repeats
        )
    scene = ppr.load_scene(ROOT / "configs" / "scenes" / "cubesat3u_panels.toml")
    out["ppr.simulate, 3U CubeSat with panels"] = first_and_median_time(
        lambda: ppr.simulate(scene).data, repeats=repeats
    )
    out.update(inversion_programs(scene, repeats))
    return out


def inversion_programs(scene, repeats: int) -> dict:
    """The inversion's forward-model programs (``inversion._xla.MODEL_PROGRAM``: the emitters
    of ``PPR_XLA_EMITTERS``) on two models: the shipped ``ppr invert`` example (3U CubeSat
    with panels, copolarized channels, full BRDF, macro double bounce) and a 64-sided
    cylinder with the single term only and 16 channels (a cheap BRDF on more facets, where
    the fusion emitters' faster kernels would show): one refinement (one start, 20 steps, one
    round), the Fisher matrix at its optimum, a short chain (24 walkers x 20 steps)."""
    import numpy as np
    from _timing import first_and_median_time

    import inversion
    import ppr

    out = {}
    noise = inversion.PoissonCounts()
    free = ("attitude", "m", "range_offset", "gain")
    cyl = ppr.Scene(
        ppr.shapes.cylinder(0.06, 0.25, sections=64),
        (ppr.Material(1.5, 10.0),),
        ppr.Pose([1.0, 0.0, 0.0, 0.0]),
        ppr.Sensor.make(),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.01, 48),
    )
    cases = {
        "3U CubeSat with panels, copol, full BRDF": (scene, "copol", {}),
        "cylinder (64 sides), 16 channels, single term": (cyl, "full", {"terms": ("single",)}),
    }
    al = complex(np.asarray(ppr.load_material("aluminium").n))
    for label, (sc, channels, kw) in cases.items():
        chm = inversion.MeasurementModel.preset(channels).channel_matrix()
        model = inversion.SimulatorModel(sc, chm, **kw)
        k = len(sc.mesh.parts)
        q = np.array([0.86, 0.31, -0.22, 0.35])
        q /= np.linalg.norm(q)
        truth = inversion.PhysicalParams(q, [30.0] * k, [al] * k, range_offset=0.003)
        x = np.asarray(model.expected(truth, model.prepare(truth))).sum()
        truth = inversion.PhysicalParams(q, [30.0] * k, [al] * k, range_offset=0.003, gain=1e5 / x)
        data = (
            np.random.default_rng(0)
            .poisson(np.maximum(np.asarray(model.expected(truth, model.prepare(truth))), 0.0))
            .astype(np.float64)
        )
        q2 = q + 0.03
        q2 /= np.linalg.norm(q2)
        start = inversion.PhysicalParams(
            q2, [25.0] * k, [al] * k, range_offset=0.002, gain=truth.gain
        )

        def fit(start=start, model=model, data=data, free=free, noise=noise):
            return inversion.refine(
                model, data, [start], noise=noise, free=free, max_steps=20, rounds=1
            ).cost

        out[f"inversion.refine, {label}"] = first_and_median_time(fit, repeats=repeats)
        best = inversion.refine(
            model, data, [start], noise=noise, free=free, max_steps=20, rounds=1
        ).params
        out[f"inversion.fisher_at, {label}"] = first_and_median_time(
            lambda best=best, model=model, data=data: inversion.fisher_at(
                model, noise, data, best, free
            )[0],
            repeats=repeats,
        )
        cfg = inversion.MCMCConfig(
            sampler={"n_walkers": 24, "n_steps": 20, "burn_in": 0, "independence_move": 0.0}
        )

        def chain(best=best, model=model, data=data, cfg=cfg):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", inversion.ChainTooShortWarning)
                return inversion.sample_posterior(
                    model, data, best, config=cfg, noise=noise, free=free
                ).samples

        out[f"inversion.sample_posterior (24 walkers x 20 steps), {label}"] = first_and_median_time(
            chain, repeats=repeats
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.repeats)))
        return
    load = load_average()
    runs = {}
    for name, flags, inv in (
        ("fusion emitters", "", "fusion"),
        ("elemental emitters", FLAG, "elemental"),
    ):
        env = {**os.environ, "PPR_JAX_CACHE": "0", "PPR_XLA_EMITTERS": inv}
        env["XLA_FLAGS"] = " ".join(x for x in (env.get("XLA_FLAGS", ""), flags) if x)
        res = subprocess.run(
            [sys.executable, __file__, "--child", "--repeats", str(args.repeats)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        runs[name] = json.loads(res.stdout.strip().splitlines()[-1])
        print(name, runs[name], flush=True)
    names = list(runs)
    lines = [
        "# XLA:CPU kernel emitters: compile time against run time",
        "",
        f"Command: `.venv/bin/python bench/bench_xla_emitters.py --repeats {args.repeats}` "
        f"(fresh process per setting, compilation cache off, float64; load average {load} "
        "on 2 cores). First call: compilation and one run; steady: median of the repeats.",
        "",
        "| program | "
        + " | ".join(f"{n}: first s / steady ms" for n in names)
        + " | steady ratio |",
        "|---|---|---|---|",
    ]
    for prog in runs[names[0]]:
        cells = [f"{runs[n][prog][0]:.2f} / {1e3 * runs[n][prog][1]:.1f}" for n in names]
        ratio = runs[names[1]][prog][1] / runs[names[0]][prog][1]
        lines.append(f"| {prog} | " + " | ".join(cells) + f" | {ratio:.2f} |")
    lines += [
        "",
        "The elemental emitters compile the large programs faster and run some of them "
        "slower: the BRDF on many rows and the sampler's batch of walkers (default fusion "
        "emitters kept there), the single-point programs of the refiner a few per cent (the "
        "elemental emitters are the default there: `inversion._xla.model_compiler_options`, "
        "`PPR_XLA_EMITTERS`).",
    ]
    write_result("xla_emitters", lines)


if __name__ == "__main__":
    main()
