"""Where the time of one compiled ``ppr.mueller_brdf`` call goes: XLA fusions ranked by time.

XLA CPU runs a jitted function as a sequence of *fusions* (kernels). This script traces one
call with ``jax.profiler`` and prints the fusions that took the most time, in ns per BRDF
evaluation, with the operation counts of the top ones read from the compiled HLO. It is how
the scalar concatenate loop of the double-bounce term's frame angles was found (320 of 510 ns
per evaluation; ``ppr.optics.rotate_mueller_flat``). Timings under the tracer run ~1.5x
slower than plain calls; read the ranking, not the totals.

Run: ``.venv/bin/python bench/profile_brdf.py --terms single,double:backscatter,multiple``
(options: ``--n`` batch size, ``--float64``, ``--top`` rows). Prints only; writes nothing.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import re
import tempfile

import jax
import jax.numpy as jnp
import numpy as np


def inputs(n: int, dt, seed: int = 1):
    """Random incidence over the upper hemisphere (k.n >= 0.05), exact backscatter."""
    rng = np.random.default_rng(seed)
    th = np.arccos(rng.uniform(0.05, 1.0, n))
    ph = rng.uniform(0.0, 2.0 * np.pi, n)
    k = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    nrm = np.zeros((n, 3))
    nrm[:, 2] = 1.0
    # two separate buffers for k_in and k_out: the same array would let XLA share their work
    return jnp.asarray(k, dt), jnp.asarray(k.copy(), dt), jnp.asarray(nrm, dt)


def fusion_ops(hlo: str, name: str) -> str:
    """Operation counts of the fused computation called by instruction ``name``."""
    m = re.search(r"\n  %" + re.escape(name) + r" = [^\n]*calls=%([\w.\-]+)", hlo)
    if not m:
        return ""
    body = re.search(r"\n%" + re.escape(m.group(1)) + r" [^\n]*\{\n(.*?)\n\}", hlo, re.S)
    if not body:
        return ""
    ops = collections.Counter(re.findall(r"= \S+ ([a-z][\w\-]*)\(", body.group(1)))
    for skip in ("parameter", "constant", "broadcast", "bitcast"):
        ops.pop(skip, None)
    return ", ".join(f"{k} {v}" for k, v in ops.most_common(6))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--terms", default="single,double:backscatter,multiple")
    ap.add_argument("--n", type=int, default=250_000)
    ap.add_argument("--float64", action="store_true")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--same-k",
        action="store_true",
        help="pass one array as k_in and k_out (as monostatic callers do: XLA then shares "
        "their work, which changes its fusion decisions)",
    )
    args = ap.parse_args(argv)
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import ppr

    dt = jnp.float64 if args.float64 else jnp.float32
    k_in, k_out, nrm = inputs(args.n, dt)
    if args.same_k:
        k_out = k_in
    mat = ppr.Material(
        np.asarray(1.46 + 0.0j, np.complex128 if args.float64 else np.complex64),
        np.asarray(3.0, dt),
    )
    terms = tuple(args.terms.split(","))
    fn = jax.jit(lambda a, b, c, m: ppr.mueller_brdf(a, b, c, m, terms=terms))
    jax.block_until_ready(fn(k_in, k_out, nrm, mat))
    hlo = fn.lower(k_in, k_out, nrm, mat).compile().as_text()
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(args.repeats):
                jax.block_until_ready(fn(k_in, k_out, nrm, mat))
        path = glob.glob(f"{tmp}/**/*.trace.json.gz", recursive=True)[0]
        trace = json.load(gzip.open(path))
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    per = collections.Counter()
    total = 0.0
    for e in events:
        if e.get("ph") != "X":
            continue
        if e["name"] == "ThunkExecutor::Execute":
            total += e.get("dur", 0.0)
        elif not e["name"].startswith(("$", "Thunk", "Pjit", "Common")):
            per[e["name"]] += e.get("dur", 0.0)
    scale = 1e3 / (args.repeats * args.n)  # us -> ns per evaluation
    print(
        f"mueller_brdf terms={terms} n={args.n} {np.dtype(dt).name}: {len(per)} kernels, "
        f"{total * scale:.0f} ns per evaluation under the tracer"
    )
    print(f"{'ns/eval':>8}  {'kernel':<32}  operations (fused)")
    for name, dur in per.most_common(args.top):
        print(f"{dur * scale:8.1f}  {name:<32}  {fusion_ops(hlo, name)}")


if __name__ == "__main__":
    main()
