"""Compile time against run time for XLA:CPU's two kernel emitters: the MLIR fusion emitters
(JAX's default) and the older elemental ones (``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``).

Each setting runs in a fresh process (XLA reads ``XLA_FLAGS`` once, when its CPU backend
starts), with the compilation cache off (``PPR_JAX_CACHE=0``): the first call of each program
(compilation and run) and the median of ``--repeats`` calls after it, for

- ``ppr.mueller_brdf`` (aluminium, m = 300, float64) on random upper-hemisphere direction
  pairs: single + multiple on 2e5 rows, single + double + multiple on 2e4 rows;
- ``ppr.simulate`` of the 3U CubeSat with panels (configs/scenes/cubesat3u_panels.toml: facet
  sum and the macro double bounce).

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
    for name, flags in (("fusion emitters (default)", ""), ("elemental emitters", FLAG)):
        env = {**os.environ, "PPR_JAX_CACHE": "0"}
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
        "The elemental emitters compile the large programs faster (the refinement of "
        "`ppr invert`: 75.5 s instead of 116.6 s, bench/results/compile.md) and run them "
        "slower: a documented choice for cold, compile-bound runs (docs/cli.md), not a default.",
    ]
    write_result("xla_emitters", lines)


if __name__ == "__main__":
    main()
