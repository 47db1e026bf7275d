"""Compile cost of the double term's run-time dispatch against its quadrature alone.

    .venv/bin/python bench/bench_double_branch.py [--repeats 2] [--n 64]

``terms=("double",)`` on traced inputs is a ``lax.cond`` of the backscatter table and the
quadrature: a compiled program holds both, and a gradient linearizes both.
``terms=("double:quadrature",)`` holds the quadrature only; ``ppr.sensor_terms`` (hence
``ppr.render`` and ``inversion.SimulatorModel``) picks it for a concrete bistatic sensor beyond
``PSI_MAX``. Each variant runs in a fresh interpreter (no in-process or persistent cache), x64,
JAX's default optimization; a bistatic batch of ``n`` random geometries (bistatic angle 0.3
rad), one material. Columns: seconds tracing (``jit(...).trace``), lowering and compiling
the value and the gradient (with respect to ``k_in`` and ``m``), and the steady run time of
the compiled gradient (median of 20 after a warm-up). Medians over ``--repeats`` processes.
Writes ``bench/results/double_branch_compile.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from _timing import load_average, write_result

HERE = Path(__file__).resolve().parent

CHILD = r"""
import json, sys, time
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import ppr
sys.path.insert(0, {here!r})
from _timing import median_time

names, n = tuple(sys.argv[1].split(",")), int(sys.argv[2])
rng = np.random.default_rng(0)
z = np.array([0.0, 0.0, 1.0])
th = rng.uniform(0.1, 1.3, n); ph = rng.uniform(0, 2 * np.pi, n)
k = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
ax = np.cross(k, z) / np.linalg.norm(np.cross(k, z), axis=-1, keepdims=True)
kp = k * np.cos(0.3) + ax * np.sin(0.3)
kp[:, 2] = np.abs(kp[:, 2]); kp /= np.linalg.norm(kp, axis=-1, keepdims=True)
nrm = np.broadcast_to(z, k.shape)
k, kp, nrm = map(jnp.asarray, (k, kp, nrm))
def value(a, m):
    return ppr.mueller_brdf(a, kp, nrm, ppr.Material(n=0.94 + 6.42j, m=m), terms=names)
def total(a, m):
    return jnp.sum(value(a, m))
out = {{}}
for key, fn in (("value", jax.jit(value)), ("grad", jax.jit(jax.grad(total, argnums=(0, 1))))):
    t = time.perf_counter(); tr = fn.trace(k, 10.0); t1 = time.perf_counter()
    lo = tr.lower(); t2 = time.perf_counter(); co = lo.compile(); t3 = time.perf_counter()
    out[key] = dict(trace=t1 - t, lower=t2 - t1, compile=t3 - t2)
    if key == "grad":
        out[key]["run_ms"] = 1e3 * median_time(co, k, 10.0, repeats=20)
print("RESULT", json.dumps(out))
"""


def run(names: str, n: int) -> dict:
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR="", JAX_ENABLE_COMPILATION_CACHE="false")
    r = subprocess.run(
        [sys.executable, "-c", CHILD.format(here=str(HERE)), names, str(n)],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT ") :])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--n", type=int, default=64)
    args = ap.parse_args()
    rows = []
    for names in ("double", "double:quadrature"):
        res = [run(names, args.n) for _ in range(args.repeats)]
        med = {
            k: {q: float(np.median([r[k][q] for r in res])) for q in res[0][k]}
            for k in res[0]
        }
        rows.append((names, med))
        print(names, json.dumps(med), flush=True)
    lines = [
        "# Double term: run-time dispatch (`lax.cond`) against the quadrature alone",
        "",
        f"Command: `.venv/bin/python bench/bench_double_branch.py --repeats {args.repeats} "
        f"--n {args.n}` (fresh interpreter per variant, x64, default optimization, "
        f"bistatic batch of {args.n}, bistatic angle 0.3 rad; medians of {args.repeats}; "
        f"load average {load_average()} on 2 cores).",
        "",
        "| terms | value: trace / lower / compile s | gradient: trace / lower / compile s "
        "| gradient run ms |",
        "|---|---|---|---|",
    ]
    for names, med in rows:
        v, g = med["value"], med["grad"]
        lines.append(
            f"| `{names}` | {v['trace']:.2f} / {v['lower']:.2f} / {v['compile']:.1f} "
            f"| {g['trace']:.2f} / {g['lower']:.2f} / {g['compile']:.1f} | {g['run_ms']:.2f} |"
        )
    lines += [
        "",
        "Both give the same values (tests/test_double_table.py); `ppr.sensor_terms` picks "
        "`double:quadrature` for a concrete bistatic sensor beyond `PSI_MAX`, the table for a "
        "monostatic one.",
        "",
    ]
    write_result("double_branch_compile", lines)


if __name__ == "__main__":
    main()
