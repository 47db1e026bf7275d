"""Does compiling a later stage's program in the background shorten a cold inversion?

``inversion.refine``'s first call compiles two large programs one after the other: the solver
round (``_solve_round``) and, for the covariance at the optimum, the residual Jacobian
(``_jacobians``). Warming the second in a background thread while the first compiles would
hide its compilation if XLA:CPU compiled on one core. Each setting runs in a fresh process
with the compilation cache off (``PPR_JAX_CACHE=0``), on the shipped ``ppr invert`` example
(3U CubeSat with panels, copolarized channels, full BRDF, macro double bounce):

- ``serial``: ``inversion.refine`` (one start, 20 steps, one round), as ``invert`` runs it;
- ``background``: ``inversion.fisher_at`` at the start (which compiles ``_jacobians``) in a
  thread started just before the same ``inversion.refine``.

    .venv/bin/python bench/bench_background_compile.py [--repeats 2]

Writes ``bench/results/background_compile.md`` (wall and process CPU seconds until the refine
returns and until both threads are done; the median over ``--repeats`` process pairs).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _timing import write_result

ROOT = Path(__file__).resolve().parents[1]


def child(mode: str) -> dict:
    import threading

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import inversion
    import ppr

    scene = ppr.load_scene(ROOT / "configs" / "scenes" / "cubesat3u_panels.toml")
    chm = inversion.MeasurementModel.preset("copol").channel_matrix()
    model = inversion.SimulatorModel(scene, chm)
    noise = inversion.PoissonCounts()
    free = ("attitude", "m", "range_offset", "gain")
    k = len(scene.mesh.parts)
    al = complex(np.asarray(ppr.load_material("aluminium").n))
    q = np.array([0.86, 0.31, -0.22, 0.35])
    q /= np.linalg.norm(q)
    truth = inversion.PhysicalParams(q, [30.0] * k, [al] * k, range_offset=0.003)
    x = float(np.asarray(model.expected(truth, model.prepare(truth))).sum())
    truth = inversion.PhysicalParams(q, [30.0] * k, [al] * k, range_offset=0.003, gain=1e5 / x)
    mu = np.asarray(model.expected(truth, model.prepare(truth)))
    data = np.random.default_rng(0).poisson(np.maximum(mu, 0.0)).astype(np.float64)
    q2 = q + 0.03
    q2 /= np.linalg.norm(q2)
    start = inversion.PhysicalParams(q2, [25.0] * k, [al] * k, range_offset=0.002, gain=truth.gain)

    t0, c0 = time.perf_counter(), time.process_time()
    worker = None
    if mode == "background":
        worker = threading.Thread(
            target=lambda: inversion.fisher_at(model, noise, data, start, free), daemon=True
        )
        worker.start()
    fit = inversion.refine(model, data, [start], noise=noise, free=free, max_steps=20, rounds=1)
    t1, c1 = time.perf_counter(), time.process_time()
    if worker is not None:
        worker.join()
    t2, c2 = time.perf_counter(), time.process_time()
    return {
        "refine_wall": t1 - t0,
        "refine_cpu": c1 - c0,
        "all_wall": t2 - t0,
        "all_cpu": c2 - c0,
        "cost": float(fit.cost),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--child", choices=("serial", "background"))
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return
    env = dict(os.environ, PPR_JAX_CACHE="0")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    res: dict[str, list[dict]] = {"serial": [], "background": []}
    loads = []
    for _ in range(args.repeats):
        for mode in res:
            out = subprocess.run(
                [sys.executable, __file__, "--child", mode],
                env=env,
                capture_output=True,
                text=True,
                check=True,
            )
            res[mode].append(json.loads(out.stdout.strip().splitlines()[-1]))
            loads.append(os.getloadavg()[0])
            print(mode, res[mode][-1], flush=True)
    med = {m: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for m, rs in res.items()}
    lines = [
        "# Background compilation of the covariance program (issue 30)",
        "",
        "Command: `python bench/bench_background_compile.py --repeats "
        f"{args.repeats}` (fresh process per run, compilation cache off; 2-core VM, load "
        f"average {min(loads):.2f}-{max(loads):.2f} at the runs' ends). Median of "
        f"{args.repeats} runs per setting.",
        "",
        "| setting | refine returns: wall / CPU s | both done: wall / CPU s | deviance |",
        "|---|---|---|---|",
    ]
    for m, r in med.items():
        lines.append(
            f"| {m} | {r['refine_wall']:.1f} / {r['refine_cpu']:.1f} | "
            f"{r['all_wall']:.1f} / {r['all_cpu']:.1f} | {r['cost']:.4f} |"
        )
    gain = 1.0 - med["background"]["all_wall"] / med["serial"]["all_wall"]
    lines += [
        "",
        f"Wall time saved by the background thread: {100 * gain:.0f} % (CPU/wall of the serial "
        f"run {med['serial']['all_cpu'] / med['serial']['all_wall']:.2f}: XLA:CPU already "
        "compiles one program on more than one core).",
    ]
    write_result("background_compile", lines)


if __name__ == "__main__":
    main()
