"""The multiple-scattering remainder: accuracy against the independent reference, and cost.

    .venv/bin/python bench/bench_albedo.py

Accuracy. The deficit tables (``ppr/data/albedo_double_single.npz``) against
``tests/data/deficit_reference.npz`` (scripts/deficit_reference.py: positive-integral deficit
and its hemispherical average, independent of ppr's BRDF code), on the reference's (m, incidence)
grid, most of it off the table nodes: the model deficit's interpolant ``D_model``, the deficit
the BRDF uses ``D`` (model + closure of the double term's quadrature error,
docs/physics/multiple_scattering.md), and the white remainder at exact backscatter through
``ppr.mueller_brdf(terms=("multiple",))``, ``R = D^2 / (pi D_avg)``, against
``R_ref = D_ref^2 / (pi D_avg,ref)``. Relative errors, per band of ``D_ref``.

Cost. ``M00`` of the remainder for 2^18 random (k, k') pairs, jit, median of 5 after a warm-up:
the shipped kernel (Catmull-Rom of ``log D``, one ``exp``) against the former one (Catmull-Rom
of ``D``, clamp at 0, product over ``pi D_avg``), re-implemented here on the same table, for one
material (the table's m-row interpolated once) and per-element ``m``, float32 and float64; and
the share of the remainder in ``mueller_brdf(terms=("single", "multiple"))``.

Writes bench/results/albedo_remainder.md.
"""

from __future__ import annotations

import math
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _timing import median_time  # noqa: E402

from ppr.brdf import (  # noqa: E402
    albedo,  # noqa: E402
    explicit_terms,
    mueller_brdf,
)
from ppr.materials import Material  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "bench", "results")
REF = os.path.join(ROOT, "tests", "data", "deficit_reference.npz")
N = 1 << 18
BANDS = ((1e-8, 1.0), (1e-40, 1e-8), (1e-250, 1e-40))


def model_table(table):
    from dataclasses import replace

    return replace(table, L_pad=table.Lm_pad)


def accuracy():
    ref = np.load(REF)
    table = albedo.load_table(explicit_terms())
    tm = model_table(table)
    rows = []
    z = jnp.asarray([0.0, 0.0, 1.0])
    for i, m in enumerate(ref["m"]):
        th = np.deg2rad(ref["theta_deg"])
        mu = np.cos(th)
        d_ref = ref["D"][i]
        d_mod = np.asarray(albedo.deficit(tm, np.full_like(mu, m), mu))
        d_tab = np.asarray(albedo.deficit(table, np.full_like(mu, m), mu))
        k = np.stack([np.sin(th), 0 * th, mu], -1)
        r = np.asarray(
            mueller_brdf(k, k, z, Material.ideal_white(float(m)), terms=("multiple",))[..., 0, 0]
        )
        r_ref = d_ref**2 / (math.pi * ref["D_avg"][i])
        for lo, hi in BANDS:
            sel = (d_ref >= lo) & (d_ref < hi)
            if not sel.any():
                continue
            ok = r_ref[sel] > 1e-300
            rows.append(
                (
                    float(m),
                    f"{lo:.0e} - {hi:.0e}",
                    int(sel.sum()),
                    float(np.max(np.abs(d_mod[sel] / d_ref[sel] - 1))),
                    float(np.max(np.abs(d_tab[sel] / d_ref[sel] - 1))),
                    float(np.max(np.abs(r[sel][ok] / r_ref[sel][ok] - 1))) if ok.any() else 0.0,
                )
            )
    return rows


def old_kernel(table, one_material: bool):
    """The former remainder: Catmull-Rom of ``D`` (here ``exp`` of the same nodes), clamp,
    product over ``pi D_avg``."""
    D_pad = np.exp(table.L_pad)

    def deficit(m, mu):
        return albedo.interpolate_nodes(table, D_pad, m, mu)

    def deficit_row(m0, mu):
        dt = mu.dtype
        x = jnp.log1p(jnp.clip(m0, 0.0, albedo.M_MAX))
        i, t = albedo._cell(x, table.x_lo, table.dx, table.nx)
        rows = jax.lax.dynamic_slice_in_dim(jnp.asarray(D_pad, dt), i, 4, axis=0)
        row = jnp.stack(albedo._cr_weights(t)) @ rows
        v = albedo.warp_mu(jnp.clip(mu, 0.0, 1.0))
        j, s = albedo._cell(v, table.v_lo, table.dv, table.nv)
        return albedo._cr_eval(albedo._cr_cubics(row, table.nv), j, s)

    @jax.jit
    def f(ci, co, m):
        d_avg = jnp.exp(albedo.log_deficit_avg(table, m if one_material else m[0]))
        if one_material:
            di, do = deficit_row(m, ci), deficit_row(m, co)
        else:
            di, do = deficit(m, ci), deficit(m, co)
        return jnp.maximum(di, 0.0) * jnp.maximum(do, 0.0) / (math.pi * d_avg)

    return f


def new_kernel(table, one_material: bool):
    @jax.jit
    def f(ci, co, m):
        la = albedo.log_deficit_avg(table, m if one_material else m[0])
        if one_material:
            li = albedo.log_deficit_one_material(table, m, ci)
            lo = albedo.log_deficit_one_material(table, m, co)
        else:
            li, lo = albedo.log_deficit(table, m, ci), albedo.log_deficit(table, m, co)
        return jnp.exp(li + lo - la) / math.pi

    return f


def cost():
    table = albedo.load_table(explicit_terms())
    rng = np.random.default_rng(0)
    rows = []
    for dt in (np.float32, np.float64):
        ci = jnp.asarray(rng.uniform(0, 1, N), dt)
        co = jnp.asarray(rng.uniform(0, 1, N), dt)
        for one in (True, False):
            m = jnp.asarray(300.0, dt) if one else jnp.asarray(np.full(N, 300.0), dt)
            t_old = median_time(old_kernel(table, one), ci, co, m)
            t_new = median_time(new_kernel(table, one), ci, co, m)
            label = "one material" if one else "per-element m"
            rows.append((np.dtype(dt).name, label, t_old / N * 1e9, t_new / N * 1e9))
    # share in the single + multiple BRDF (one material, float32)
    n = N // 4

    def upper():
        mu = rng.uniform(0.01, 1, n)
        ph = rng.uniform(-np.pi, np.pi, n)
        s = np.sqrt(1 - mu**2)
        return jnp.asarray(np.stack([s * np.cos(ph), s * np.sin(ph), mu], -1), jnp.float32)

    ki, ko = upper(), upper()
    z = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    mat = Material(n=jnp.asarray(0.94 + 6.42j, jnp.complex64), m=jnp.asarray(300.0, jnp.float32))
    share = []
    for terms in (("single",), ("single", "multiple")):
        f = jax.jit(lambda a, b, t=terms: mueller_brdf(a, b, z, mat, terms=t))
        share.append(median_time(f, ki, ko) / n * 1e9)
    return rows, share, n


def main():
    t0 = time.perf_counter()
    acc = accuracy()
    for r in acc:
        print(r, flush=True)
    rows, share, n = cost()
    for r in rows:
        print(r, flush=True)
    print("single, single+multiple ns/pair:", share)
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, "albedo_remainder.md"), "w") as fh:
        fh.write("# Multiple-scattering remainder: accuracy and cost (bench/bench_albedo.py)\n\n")
        fh.write(
            f"Command: `.venv/bin/python bench/bench_albedo.py`; {time.perf_counter() - t0:.0f} "
            f"s wall, load average {os.getloadavg()[0]:.1f} at the end (shared 2-core machine: "
            "timings are noisy).\n\n"
        )
        fh.write(
            "## Accuracy against tests/data/deficit_reference.npz\n\n"
            "Max relative error over the reference's incidences (0-89.98 deg) in each band of "
            "the reference deficit `D_ref`: the model deficit's interpolant, the deficit the "
            "BRDF uses (model + closure), and the white remainder at exact backscatter through "
            "`ppr.mueller_brdf` (float64) against `D_ref^2 / (pi D_avg,ref)`.\n\n"
            "| m | D_ref band | points | D_model | D (with closure) | remainder |\n"
            "|---|---|---|---|---|---|\n"
        )
        for m, band, npts, e1, e2, e3 in acc:
            fh.write(f"| {m:g} | {band} | {npts} | {e1:.1e} | {e2:.1e} | {e3:.1e} |\n")
        fh.write(
            f"\n## Cost\n\n`M00` of the remainder for {N} random (k, k') pairs at m = 300, jit, "
            "median of 5 after a warm-up, ns per pair. Former: Catmull-Rom of `D`, clamp, "
            "product over `pi D_avg`; shipped: Catmull-Rom of `log D`, one `exp`.\n\n"
            "| dtype | material | former (ns) | shipped (ns) |\n|---|---|---|---|\n"
        )
        for dt, label, a, b in rows:
            fh.write(f"| {dt} | {label} | {a:.2f} | {b:.2f} |\n")
        fh.write(
            f"\n`ppr.mueller_brdf`, aluminium m = 300 (one material), float32, {n} pairs: "
            f"`terms=('single',)` {share[0]:.1f} ns/pair, `('single', 'multiple')` "
            f"{share[1]:.1f} ns/pair.\n"
        )
    print("wrote", os.path.join(OUT, "albedo_remainder.md"))


if __name__ == "__main__":
    main()
