"""Compile and run time of the refiner's solver round, with the solvers' linearization through
a materialized forward-mode Jacobian (``inversion._refine._expected_forward_jac``, the default)
against plain autodiff of the renderer (optimistix then transposes the renderer's JVP: a
reverse-mode program).

Each variant runs in a fresh subprocess (no compilation is shared): the first ``refine`` call
(compilation + run) and the median of later calls, on the 3U CubeSat of
``tests/test_refine.py``'s mirror check (16 PSG/PSA channels, double term, monostatic).

    .venv/bin/python bench/bench_refine_compile.py [--repeats 5]

Writes ``bench/results/refine_compile.md``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys, time
import numpy as np, jax
jax.config.update("jax_enable_x64", True)
import ppr
from inversion import _refine
from inversion._noise import MeasurementModel
from inversion._params import PhysicalParams
from inversion._refine import PoissonCounts, SimulatorModel, refine

variant, repeats = sys.argv[1], int(sys.argv[2])
if variant == "plain":
    _refine._expected_forward_jac = lambda t, p, mo, a: mo.expected(p.to_physical(t), a)
scene = ppr.Scene(ppr.shapes.cubesat(3), (ppr.Material(1.5, 10.0),), ppr.Pose([1.0, 0, 0, 0]),
                  ppr.Sensor.make(), ppr.Pulse.gaussian(100e-12), ppr.RangeBins.centred(0.012, 32))
chm = MeasurementModel.preset("full").channel_matrix()
q = np.array([0.86, 0.31, -0.22, 0.35]); q /= np.linalg.norm(q)
noise = PoissonCounts(background=1e-3)
model = SimulatorModel(scene, chm, dense=True, terms=("double",))
truth = PhysicalParams(q, [4.0], [0.94 + 6.42j], range_offset=0.003, gain=1.0)
x = np.asarray(model.expected(truth, model.prepare(truth)))
truth = PhysicalParams(q, [4.0], [0.94 + 6.42j], range_offset=0.003, gain=1e7 / x.sum())
data = np.maximum(np.asarray(model.expected(truth, model.prepare(truth))), 0.0)
q2 = q + 0.02; q2 /= np.linalg.norm(q2)
start = PhysicalParams(q2, [5.0], [0.94 + 6.42j], range_offset=0.002, gain=1e7 / x.sum())
t = time.perf_counter()
fit = refine(model, data, [start], noise=noise, max_steps=20, rounds=1)
first = time.perf_counter() - t
runs = []
for _ in range(repeats):
    t = time.perf_counter()
    again = refine(model, data, [start], noise=noise, max_steps=20, rounds=1)
    runs.append(time.perf_counter() - t)
print(json.dumps(dict(first=first, run=float(np.median(runs)), cost=fit.cost,
                      steps=fit.n_steps, cost_again=again.cost)))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rows = {}
    for variant in ("forward_jacobian", "plain"):
        out = subprocess.run([sys.executable, "-c", CHILD, variant, str(args.repeats)],
                             check=True, capture_output=True, text=True).stdout
        rows[variant] = json.loads(out.strip().splitlines()[-1])
    lines = [
        "| linearization | first refine call (compile + run) s | later calls, median s "
        "| cost | steps |",
        "|---|---|---|---|---|",
    ]
    for k, r in rows.items():
        lines.append(
            f"| {k} | {r['first']:.1f} | {r['run']:.3f} | {r['cost']:.9g} | {r['steps']} |"
        )
    table = "\n".join(lines)
    print(table)
    res = Path(__file__).resolve().parent / "results" / "refine_compile.md"
    res.parent.mkdir(exist_ok=True)
    res.write_text(
        "# Refiner solver round: forward-Jacobian linearization vs plain autodiff\n\n"
        "`.venv/bin/python bench/bench_refine_compile.py` (3U CubeSat, 16 channels, double term, "
        "float64, 2-core VM; each variant in its own process)\n\n" + table + "\n"
    )


if __name__ == "__main__":
    main()
