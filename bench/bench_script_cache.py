"""Compilation of a library script, cold against warm: what ``ppr.compile_cache()`` at the top
of a script or notebook saves in the next process.

The script (:data:`SCRIPT`, public names only): a 1U CubeSat (one 0.1 m cube, aluminium) seen
through the copol measurement, its expected counts as data, and one ``inversion.refine`` from a
perturbed start, in float64. Per repeat, a new empty cache folder (``PPR_JAX_CACHE_DIR``) and
two fresh processes: **cold** (every program compiled and written) and **warm** (the same
script again: programs read from the folder). Reported: the process's wall seconds (start to
exit, imports included) and CPU seconds (less inflated by other jobs' load), the ``refine``
call's wall seconds, the programs compiled and the
persistent-cache hits (``jax.monitoring`` event ``/jax/compilation_cache/cache_hits``); median
over the repeats, and the load average.

    .venv/bin/python bench/bench_script_cache.py [--repeats 2]

Writes the section "library scripts" of ``bench/results/compile.md`` (replacing it; the
command tables above it are ``bench/bench_compile.py``'s, which keeps this section).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULT = HERE / "results" / "compile.md"
SECTION = "## library scripts"

SCRIPT = r"""
import json, time
t_start = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ppr, inversion

folder = ppr.compile_cache()
events = {"hits": 0, "programs": 0}
def count(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        events["hits"] += 1
def dur(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        events["programs"] += 1
jax.monitoring.register_event_listener(count)
jax.monitoring.register_event_duration_secs_listener(dur)

al = ppr.load_material("aluminium", 532e-9, "rough")
scene = ppr.Scene(ppr.shapes.cubesat(1), (al,), ppr.Pose([1.0, 0, 0, 0]), ppr.Sensor.make(),
                  ppr.Pulse.gaussian(100e-12), ppr.RangeBins.centred(0.012, 32))
chm = inversion.MeasurementModel.preset("copol").channel_matrix()
model = inversion.SimulatorModel(scene, chm)
q = np.array([0.86, 0.31, -0.22, 0.35]); q /= np.linalg.norm(q)
truth = inversion.PhysicalParams(q, [float(al.m)], [complex(al.n)], gain=1e7)
data = np.asarray(model.expected(truth, model.prepare(truth)))
q2 = q + 0.02; q2 /= np.linalg.norm(q2)
start = inversion.PhysicalParams(q2, [float(al.m) * 1.2], [complex(al.n)], gain=1.1e7)
t = time.perf_counter()
fit = inversion.refine(model, data, [start], max_steps=20, rounds=1)
t_refine = time.perf_counter() - t
print(json.dumps(dict(folder=str(folder), refine=t_refine, script=time.perf_counter() - t_start,
                      cpu=time.process_time(), cost=float(fit.cost), **events)))
"""


def run(env: dict) -> dict:
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=REPO, check=True,
                         capture_output=True, text=True).stdout
    rec = json.loads(out.strip().splitlines()[-1])
    rec["wall"] = time.perf_counter() - t
    return rec


def median(xs: list[float]) -> float:
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def write_section(text: str) -> None:
    """Replace (or append) the section :data:`SECTION` of ``compile.md``."""
    old = RESULT.read_text() if RESULT.exists() else ""
    pattern = re.compile(rf"^{re.escape(SECTION)}\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(old):
        new = pattern.sub(lambda _: text, old)
    else:
        new = old.rstrip("\n") + "\n\n" + text
    RESULT.write_text(new)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args()
    base = {k: v for k, v in os.environ.items()
            if k not in ("PPR_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR",
                         "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "PPR_SMALL")}
    base["PYTHONPATH"] = str(REPO)
    rows: dict[str, list[dict]] = {"cold": [], "warm": []}
    loads = []
    for i in range(args.repeats):
        folder = Path(tempfile.mkdtemp(prefix="ppr_bench_script_cache_"))
        try:
            env = dict(base, PPR_JAX_CACHE_DIR=str(folder))
            for kind in ("cold", "warm"):
                loads.append(os.getloadavg()[0])
                rec = run(env)
                rows[kind].append(rec)
                print(f"[{i}] {kind}: {json.dumps(rec)}", flush=True)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    lines = [
        SECTION,
        "",
        "`.venv/bin/python bench/bench_script_cache.py` -- a Python script (not the CLI) that "
        "calls `ppr.compile_cache()` after enabling x64 and runs one `inversion.refine` of a "
        "1U CubeSat (aluminium, copol, 32 bins, 20 steps). Per repeat a new empty cache "
        "folder; cold: first process, warm: second process on that folder. Median of "
        f"{args.repeats} repeats; load average {min(loads):.1f}-{max(loads):.1f} on 2 cores "
        "(wall seconds inflated by it). Programs: XLA compile requests (JAX's backend-compile "
        "events, cache reads included); the cold process started on an empty folder, so its hits "
        "are programs it compiled again and read back from what it had written.",
        "",
        "| process | script wall s (imports included) | script CPU s | refine call s "
        "| programs (compiled or read) | persistent-cache hits |",
        "|---|---|---|---|---|---|",
    ]
    for kind, recs in rows.items():
        lines.append(
            f"| {kind} | {median([r['wall'] for r in recs]):.1f} | "
            f"{median([r['cpu'] for r in recs]):.1f} | "
            f"{median([r['refine'] for r in recs]):.1f} | "
            f"{median([r['programs'] for r in recs]):.0f} | "
            f"{median([r['hits'] for r in recs]):.0f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        write_section(text)


if __name__ == "__main__":
    main()
