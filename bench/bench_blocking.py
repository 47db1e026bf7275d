"""Does evaluating a large BRDF batch in cache-sized blocks pay on XLA CPU?

    .venv/bin/python bench/bench_blocking.py [--n 245760] [--blocks 4096,8192,16384]
                                             [--rounds 30] [--terms single]

The same N random direction pairs (upper hemisphere; aluminium 532 nm, m = 300, float32) are
evaluated by one jitted ``ppr.mueller_brdf`` call on the whole batch, and by
``jax.lax.map`` over blocks of B rows calling ``ppr.mueller_brdf`` (traced input checks on:
one ``eqx.branched_error_if`` per block) and ``ppr.brdf.mueller_brdf_unchecked`` (no checks).
All programs are compiled first, then called in interleaved rounds (this VM's speed drifts
within minutes); the table gives the median and minimum ns per evaluation and the ratio of
medians to the whole batch.

What it shows (docs/DESIGN.md, "XLA CPU"): with the checks, each block's result passes a
side-effecting conditional and the blocks run from cache; without, XLA fuses the kernel's
last fusion (the rotation into the ``(..., 4, 4)`` layout) into the loop's in-place
dynamic-update-slice, which runs several times slower, and blocking does not pay. This is why
``ppr.mueller_brdf`` does not block internally. Writes bench/results/brdf_blocking.md.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import ppr
from ppr.brdf import mueller_brdf_unchecked

OUT = os.path.join(os.path.dirname(__file__), "results")


def directions(rng, n: int) -> np.ndarray:
    th = np.arccos(rng.uniform(0.0, 1.0, n))
    ph = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=245760)
    ap.add_argument("--blocks", default="4096,8192,16384")
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--terms", default="single")
    args = ap.parse_args(argv)
    n = args.n
    terms = tuple(args.terms.split(","))
    rng = np.random.default_rng(1)
    k_in = jnp.asarray(directions(rng, n), jnp.float32)
    k_out = jnp.asarray(directions(rng, n), jnp.float32)
    normal = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    mat = ppr.Material(np.complex64(0.94 + 6.42j), np.float32(300.0))

    def whole(brdf):
        return jax.jit(lambda a, b, m: brdf(a, b, normal, m, terms=terms))

    def blocked(brdf, size):
        def f(a, b, m):
            ab = (a.reshape(-1, size, 3), b.reshape(-1, size, 3))
            out = jax.lax.map(lambda x: brdf(x[0], x[1], normal, m, terms=terms), ab)
            return out.reshape(n, 4, 4)

        return jax.jit(f)

    variants = {"whole batch, checked": whole(ppr.mueller_brdf)}
    variants["whole batch, unchecked"] = whole(mueller_brdf_unchecked)
    for size in (int(b) for b in args.blocks.split(",")):
        if n % size:
            raise SystemExit(f"--n {n} is not a multiple of the block size {size}")
        variants[f"blocks of {size}, checked"] = blocked(ppr.mueller_brdf, size)
        variants[f"blocks of {size}, unchecked"] = blocked(mueller_brdf_unchecked, size)
    ref = None
    for name, f in variants.items():
        out = np.asarray(jax.block_until_ready(f(k_in, k_out, mat)))
        ref = out if ref is None else ref
        err = np.max(np.abs(out - ref)) / np.max(np.abs(ref))
        print(f"compiled {name:<30s} max rel diff to the whole batch {err:.1e}")
    times = {name: [] for name in variants}
    for _ in range(args.rounds):
        for name, f in variants.items():
            t = time.perf_counter()
            jax.block_until_ready(f(k_in, k_out, mat))
            times[name].append((time.perf_counter() - t) * 1e9 / n)
    base = {c: np.median(times[f"whole batch, {c}"]) for c in ("checked", "unchecked")}
    rows = []
    for name, ts in times.items():
        check = name.rsplit(", ", 1)[1]
        med = float(np.median(ts))
        rows.append(f"| {name} | {med:.1f} | {np.min(ts):.1f} | {base[check] / med:.2f} |")
    head = [
        "# Blocked BRDF evaluation on XLA CPU (bench/bench_blocking.py)",
        "",
        f"N = {n} random direction pairs, float32, aluminium m = 300, terms {terms}, "
        f"{args.rounds} interleaved rounds; {os.cpu_count()} cores, load average at the end "
        f"{os.getloadavg()[0]:.2f}. Speed-up: median of the whole batch (same checks) over "
        "this row's median.",
        "",
        "| variant | median ns/eval | min ns/eval | speed-up |",
        "|---|---|---|---|",
    ]
    text = "\n".join(head + rows) + "\n"
    print(text)
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, "brdf_blocking.md"), "w") as fh:
        fh.write(text)


if __name__ == "__main__":
    main()
