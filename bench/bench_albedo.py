"""White-surface albedo E(m, mu): interpolated table vs on-the-fly quadrature, error vs speed.

    .venv/bin/python bench/bench_albedo.py

Reference: the half-vector quadrature (ppr.brdf.albedo.albedo_nodes) at (n_phi, n_w) = (32, 16)
at 48 random off-node points (m log-uniform in [0, 1e6], mu = U^2). Candidates:
Catmull-Rom tables of nx x nv nodes (built here for the small sizes, the shipped table for the
production size) and on-the-fly quadrature at lower orders. Error = max |E - E_ref|;
speed = E evaluations/s (float32, jit, 1e6 points for tables; the quadrature's rate is per
E value, each costing 2 n_phi * 8 n_w BRDF evaluations; median over blocks of 16 values
after a first, compiling block). Writes bench/results/albedo_tradeoff.md and .png.
"""

from __future__ import annotations

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "scripts"))
from make_albedo_tables import node_values  # noqa: E402

from ppr.brdf import albedo, explicit_terms  # noqa: E402

OUT = os.path.join(os.path.dirname(__file__), "results")
QUAD_CHUNK = 16  # E values per call in make_albedo_tables.node_values (its fixed chunk)


def main():
    t_start = time.perf_counter()
    terms = explicit_terms()
    rng = np.random.default_rng(0)
    n_ref = 48
    m = np.expm1(rng.uniform(0, np.log1p(1e6), n_ref))
    mu = rng.uniform(0, 1, n_ref) ** 2
    t0 = time.perf_counter()
    D_ref = node_values(terms, m, mu, 32, 16)
    print(f"reference: {time.perf_counter() - t0:.1f} s", flush=True)
    rows = []
    # tables
    shipped = albedo.load_table(terms)
    for nx, nv in ((10, 12), (20, 24), (shipped.nx, shipped.nv)):
        if (nx, nv) == (shipped.nx, shipped.nv):
            table = shipped
        else:
            _, _, mg, mug = albedo.grid_nodes(nx, nv)
            t0 = time.perf_counter()
            table = albedo.build_table(terms, node_values(terms, mg[:, None], mug[None, :]))
            print(f"table {nx}x{nv}: built in {time.perf_counter() - t0:.1f} s", flush=True)
        err = float(np.max(np.abs(np.asarray(albedo.deficit(table, m, mu)) - D_ref)))
        N = 1_000_000
        mm = jnp.asarray(np.expm1(rng.uniform(0, np.log1p(1e6), N)), jnp.float32)
        uu = jnp.asarray(rng.uniform(0, 1, N), jnp.float32)
        f = jax.jit(lambda a, b, t=table: albedo.deficit(t, a, b))
        f(mm, uu).block_until_ready()
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            f(mm, uu).block_until_ready()
            ts.append(time.perf_counter() - t0)
        rate = N / np.median(ts)
        kb = table.D_pad.nbytes / 1024
        rows.append((f"table {nx}x{nv} ({kb:.1f} KiB)", err, rate))
        print(rows[-1], flush=True)
    # on-the-fly quadrature, in blocks of node_values' fixed chunk (one compiled shape per
    # order): the first block compiles (warm-up), the rate is the median over the others
    for n_phi, n_w in ((4, 2), (8, 4), (16, 8), (24, 12)):
        D, ts = np.empty(n_ref), []
        for s in range(0, n_ref, QUAD_CHUNK):
            t0 = time.perf_counter()
            D[s : s + QUAD_CHUNK] = node_values(
                terms, m[s : s + QUAD_CHUNK], mu[s : s + QUAD_CHUNK], n_phi, n_w
            )
            ts.append(time.perf_counter() - t0)
        err = float(np.max(np.abs(D - D_ref)))
        rate = QUAD_CHUNK / float(np.median(ts[1:]))
        rows.append((f"quadrature {2 * n_phi}x{8 * n_w} nodes (float64)", err, rate))
        print(rows[-1], flush=True)
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, "albedo_tradeoff.md"), "w") as fh:
        fh.write("# White albedo E(m, mu): error vs speed (bench/bench_albedo.py)\n\n")
        fh.write(f"Explicit terms {terms}; error = max |E - E_ref| over {n_ref} random off-node "
                 "points; E_ref = quadrature 64 x 128 nodes. Table rates: float32, jit, 1e6 "
                 "points, median of 5 after warm-up; quadrature rates: E values/s in float64 "
                 "(each value integrates the BRDF over its nodes), median over blocks of "
                 f"{QUAD_CHUNK} values after a compiling one. Shared 2-core machine: rates are "
                 "noisy.\n\n")
        fh.write(f"Command: `.venv/bin/python bench/bench_albedo.py`; "
                 f"{time.perf_counter() - t_start:.0f} s wall, load average "
                 f"{os.getloadavg()[0]:.1f} at the end.\n\n")
        fh.write("| method | max abs error | E evals/s |\n|---|---|---|\n")
        for r in rows:
            fh.write(f"| {r[0]} | {r[1]:.1e} | {r[2]:.3g} |\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for r in rows:
        mk = "o" if r[0].startswith("table") else "s"
        ax.loglog(r[2], max(r[1], 1e-12), mk)
        ax.annotate(r[0], (r[2], max(r[1], 1e-12)), fontsize=7)
    ax.axhline(1e-3, color="k", ls=":", lw=1)
    ax.text(ax.get_xlim()[0], 1.1e-3, "white-furnace tolerance", fontsize=7)
    ax.set_xlabel("E evaluations / s")
    ax.set_ylabel("max |E - E_ref|")
    ax.set_title("albedo table vs on-the-fly quadrature")
    fig.tight_layout()
    fig.savefig(os.path.join(OUT, "albedo_tradeoff.png"), dpi=120)
    print("wrote", os.path.join(OUT, "albedo_tradeoff.md"))


if __name__ == "__main__":
    main()
