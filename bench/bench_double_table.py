"""Double-bounce term at (near-)exact backscatter: the tables of ``ppr.brdf.double_table`` against
the quadrature of ``ppr.brdf.double``, error against evaluations/s, and full-BRDF throughput.

    .venv/bin/python bench/bench_double_table.py [--n 250000] [--repeats 5] [--n-numpy 20000]

1. Accuracy on random monostatic geometries (random normals, incidence 0-88 deg, random beam
   frames, bistatic angle 0, 3e-4 and PSI_MAX = 1e-3 rad in random azimuths), roughness m
   log-uniform in [0.02, 150], aluminium, gold, TiO2 and fused silica, against the quadrature
   at order (32, 128) (24576 paths, float64). ``err_full`` = max over elements of
   ``|M - M_ref| / M00(single + double_ref)`` (as in bench_double.py). The same measure for
   the quadrature at several orders on the same rows.
2. Evaluations/s (jit, N pairs, median of repeats after warm-up, block_until_ready) of the
   table term, float32 and float64, with one material for the batch and with a per-element
   material (as a mesh's facets have), against a plain NumPy implementation of the same
   lookup (Catmull-Rom gathers, node Fresnel, contraction, frame rotations) on a subset;
   the quadrature's evals/s at those orders; the full BRDF ``mueller_brdf`` at exact
   backscatter (single, single + double + multiple), float32, with the general kernel
   (``k_out`` a separate array) and the exact-backscatter kernel (``k_out`` is ``k_in``).

Writes bench/results/double_table.md and .png.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import median_time  # noqa: E402

from ppr import Material, mueller_brdf  # noqa: E402
from ppr.brdf import bistatic_geometry  # noqa: E402
from ppr.brdf import double as D  # noqa: E402
from ppr.brdf import double_table as T  # noqa: E402

OUT = os.path.join(os.path.dirname(__file__), "results")
REF_ORDER = (32, 128)
ORDERS = [(3, 12), (8, 32), (16, 64)]
NS = {"Al": 0.94 + 6.42j, "Au": 0.47 + 2.4j, "TiO2": 2.67 + 0j, "silica": 1.461 + 0j}
PSIS = (0.0, 3e-4, T.PSI_MAX)


def geometry(rng, n, psi):
    """Incidence uniform in 0-88 deg (:func:`ppr.brdf.bistatic_geometry`)."""
    return bistatic_geometry(rng, rng.uniform(0.0, 88.0, n), psi)


def rows(n_geo, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for psi in PSIS:
        for n in NS.values():
            g = geometry(rng, n_geo, psi)
            m = np.exp(rng.uniform(np.log(0.02), np.log(150.0), n_geo))
            out.append((*g, np.full(n_geo, n), m))
    return [np.concatenate(a) for a in zip(*out, strict=True)]


def quad(order):
    return jax.jit(
        lambda k, kp, n, mat, fi, fo: D.double_bounce_term(k, kp, n, mat, fi, fo, order=order)
    )


def accuracy(n_geo):
    nrm, k, kp, fi, fo, n, m = rows(n_geo)
    mat = Material(n=jnp.asarray(n), m=jnp.asarray(m))
    ref = np.asarray(quad(REF_ORDER)(k, kp, nrm, mat, fi, fo))
    single = np.asarray(mueller_brdf(k, kp, nrm, mat, terms=("single",), frame_in=fi, frame_out=fo))
    den = single[:, 0, 0] + ref[:, 0, 0]
    res = {}
    cands = {f"quadrature {o}": quad(o) for o in ORDERS}
    cands["table"] = jax.jit(T.double_backscatter_term)
    check = {}
    for name, f in cands.items():
        got = np.asarray(f(k, kp, nrm, mat, fi, fo))
        err = np.abs(got - ref).max(axis=(1, 2)) / den
        res[name] = err
    # the reference's own convergence: (24, 96) against (32, 128)
    err = np.abs(np.asarray(quad((24, 96))(k, kp, nrm, mat, fi, fo)) - ref).max(axis=(1, 2)) / den
    check["(24, 96)"] = err
    psi = np.repeat(PSIS, len(NS) * n_geo)
    mat_name = np.tile(np.repeat(list(NS), n_geo), len(PSIS))
    return res, check, psi, mat_name


def inputs(n, dt, per_element, seed=1):
    rng = np.random.default_rng(seed)
    nrm, k, _, fi, _ = geometry(rng, n, 0.0)
    cdt = jnp.complex64 if dt == jnp.float32 else jnp.complex128
    m = np.exp(rng.uniform(np.log(0.05), np.log(100.0), n))
    if per_element:
        mat = Material(n=jnp.full(n, NS["Al"], cdt), m=jnp.asarray(m, dt))
    else:
        mat = Material(n=jnp.asarray(NS["Al"], cdt), m=jnp.asarray(3.0, dt))
    a = [jnp.asarray(x, dt) for x in (k, nrm, fi)]
    return a[0], a[1], mat, a[2], m


# ------------------------------------------------------------------------------------ NumPy


def numpy_table_term(k, nrm, n, m, f):
    """Plain NumPy of the table lookup at exact backscatter (k' = k, frames f = f_in =
    f_out), coherent (gamma = 1): same table file, same formulas, written independently."""
    tab = T.load_table()
    c = np.clip(np.sum(k * nrm, -1), 0.0, 1.0)
    s = np.sqrt(np.clip(1.0 - c * c, 0.0, 1.0))
    x = np.arcsinh(T.TAU * s / np.maximum(c, 1e-300))
    u = np.sqrt(m + T.M_SHIFT) - np.sqrt(T.M_SHIFT)

    def cell(v, step, cnt):
        q = np.clip(v / step, 0.0, cnt - 1.0)
        i = np.clip(np.floor(q), 0, cnt - 2).astype(int)
        return i, q - i

    def crw(t):
        t2, t3 = t * t, t * t * t
        return [
            0.5 * (-t3 + 2 * t2 - t),
            0.5 * (3 * t3 - 5 * t2 + 2),
            0.5 * (-3 * t3 + 4 * t2 + t),
            0.5 * (t3 - t2),
        ]

    i, tx = cell(x, tab.dx, tab.nx)
    j, tu = cell(u, tab.du, tab.nu)
    wx, wu = crw(tx), crw(tu)
    vals = sum(
        wx[a][:, None] * sum(wu[b][:, None] * tab.vals[i + a, j + b] for b in range(4))
        for a in range(4)
    )
    slope = sum(wu[b] * tab.slope_pad[j + b] for b in range(4))
    log_e = vals[:, 0] + slope * np.maximum(x - T.X_MAX, 0.0)
    env = np.exp(np.minimum(log_e, 50.0)) * (m <= T.M_MAX)
    _, tj, _ = T.lobatto(tab.k)
    w = np.sqrt(n * n - np.sin(tj) ** 2 + 0j)
    rs = (np.cos(tj) - w) / (np.cos(tj) + w)
    rp = (n * n * np.cos(tj) - w) / (n * n * np.cos(tj) + w)
    a, b = rs * rs[::-1], rp * rp[::-1]
    ab = a * np.conj(b)
    g = np.stack([np.abs(a) ** 2, np.abs(b) ** 2, ab.real, ab.imag])  # (4, k)
    Tn = vals[:, 1:].reshape(-1, tab.k, tab.rank)
    M16 = np.einsum("njr,qj,rqe->ne", Tn, g, tab.V) * (2.0 * env)[:, None]
    e = np.cross(nrm, k)
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    cos_a = np.sum(f * e, -1)
    sin_a = np.sum(-k * np.cross(f, e), -1)
    r2 = cos_a**2 + sin_a**2
    c_in, s_in = (cos_a**2 - sin_a**2) / r2, 2 * cos_a * sin_a / r2
    cos_b = np.sum(e * f, -1)
    sin_b = np.sum(k * np.cross(e, f), -1)
    r2 = cos_b**2 + sin_b**2
    c_out, s_out = (cos_b**2 - sin_b**2) / r2, 2 * cos_b * sin_b / r2
    M = M16.reshape(-1, 4, 4)
    R = lambda c2, s2: np.stack(  # noqa: E731
        [
            np.stack([np.ones_like(c2), 0 * c2, 0 * c2, 0 * c2], -1),
            np.stack([0 * c2, c2, s2, 0 * c2], -1),
            np.stack([0 * c2, -s2, c2, 0 * c2], -1),
            np.stack([0 * c2, 0 * c2, 0 * c2, np.ones_like(c2)], -1),
        ],
        -2,
    )
    return R(c_out, s_out) @ M @ R(c_in, s_in)


def throughput(n, repeats, n_numpy):
    out = []
    table = jax.jit(lambda k, nrm, mat, f: T.double_backscatter_term(k, k, nrm, mat, f, f))
    for dt in (jnp.float32, jnp.float64):
        for per in (False, True):
            k, nrm, mat, f, _ = inputs(n, dt, per)
            t = median_time(table, k, nrm, mat, f, repeats=repeats)
            out.append(("table", dt.__name__, "per element" if per else "one", n / t))
    for order in ORDERS:
        nq = max(n // 50, 2000)
        k, nrm, mat, f, _ = inputs(nq, jnp.float32, False)
        fq = jax.jit(
            lambda k, nrm, mat, f, o=order: D.double_bounce_term(k, k, nrm, mat, f, f, order=o)
        )
        out.append(
            (
                f"quadrature {order}",
                "float32",
                "one",
                nq / median_time(fq, k, nrm, mat, f, repeats=repeats),
            )
        )
    # NumPy on a subset, float64, one material
    k, nrm, mat, f, _ = inputs(n_numpy, jnp.float64, False)
    args = [np.asarray(a) for a in (k, nrm, f)]
    mm = np.full(n_numpy, 3.0)
    t0 = time.perf_counter()
    ref_np = numpy_table_term(args[0], args[1], NS["Al"], mm, args[2])
    t_np = time.perf_counter() - t0
    got = np.asarray(table(k, nrm, mat, f))
    diff = np.max(np.abs(got - ref_np) / np.abs(ref_np[:, :1, :1]).clip(1e-300))
    return out, n_numpy / t_np, diff


SMALL_SIZES = (8, 16, 32, 64, 96, 128, 512)
WALKERS = 12


def small_batches(repeats=51):
    """One material per batch, small batches under ``vmap`` over ``WALKERS`` materials (an MCMC
    half-ensemble, a few facets each): the contracted-rows path against per-element row
    gathers with the material's map ``W`` shared, microseconds per call, float64.
    ``ONE_MATERIAL_MIN_BATCH`` is switched per row (a new traced function each time)."""
    rng = np.random.default_rng(4)
    keep = T.ONE_MATERIAL_MIN_BATCH
    out = []
    try:
        for size in SMALL_SIZES:
            k, nrm, _, f, _ = inputs(size, jnp.float64, False)
            ms = jnp.asarray(np.exp(rng.uniform(np.log(0.1), np.log(100.0), WALKERS)))
            ns = jnp.asarray(NS["Al"] + rng.uniform(-0.1, 0.1, WALKERS), jnp.complex128)
            row = {}
            for mode, limit in (("contracted", 0), ("gathered", 1 << 62)):
                T.ONE_MATERIAL_MIN_BATCH = limit
                fn = jax.jit(
                    jax.vmap(
                        lambda m, n, k, nrm, f: T.double_backscatter_term(
                            k, k, nrm, Material(n=n, m=m), f, f
                        ),
                        in_axes=(0, 0, None, None, None),
                    )
                )
                row[mode] = median_time(fn, ms, ns, k, nrm, f, repeats=repeats)
            out.append((size, row["contracted"], row["gathered"]))
    finally:
        T.ONE_MATERIAL_MIN_BATCH = keep
    return out


FULL_TERMS = (
    ("single",),
    ("single", "double:backscatter", "multiple"),
    ("single", "double", "multiple"),
)


def full_brdf(n, repeats):
    """evals/s of ``mueller_brdf`` at exact backscatter: the general kernel (``k_out`` a
    separate array with the same values) and the exact-backscatter kernel (``k_out`` is
    ``k_in``), default frames and given frames (as ``ppr.render`` passes them), one material
    and per-element materials. Returns ``{(terms, frames, material): (general, mono)}``."""
    res = {}
    for per in (False, True):
        k, nrm, mat, f, _ = inputs(n, jnp.float32, per)
        k2 = k + 0.0  # another buffer: the general kernel sees two arguments
        for frames in ("default", "given"):
            fr = {} if frames == "default" else None
            for terms in FULL_TERMS if not per else FULL_TERMS[1:2]:

                def gen(k, k2, nrm, mat, f, terms=terms, fr=fr):
                    kw = fr if fr is not None else dict(frame_in=f, frame_out=f)
                    return mueller_brdf(k, k2, nrm, mat, terms=terms, **kw)

                def mono(k, nrm, mat, f, terms=terms, fr=fr):
                    kw = fr if fr is not None else dict(frame_in=f, frame_out=f)
                    return mueller_brdf(k, k, nrm, mat, terms=terms, **kw)

                g = n / median_time(jax.jit(gen), k, k2, nrm, mat, f, repeats=repeats)
                mo = n / median_time(jax.jit(mono), k, nrm, mat, f, repeats=repeats)
                res[("+".join(terms), frames, "per element" if per else "one")] = (g, mo)
    return res


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=250_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--n-numpy", type=int, default=20_000)
    ap.add_argument("--n-geo", type=int, default=25)
    args = ap.parse_args()
    os.makedirs(OUT, exist_ok=True)
    acc, check, psi, mat_name = accuracy(args.n_geo)
    thr, np_rate, np_diff = throughput(args.n, args.repeats, args.n_numpy)
    full = full_brdf(args.n, args.repeats)
    small = small_batches()
    load = os.getloadavg()
    lines = [
        "# Double-bounce term near exact backscatter: tables vs quadrature",
        "",
        "Command: `.venv/bin/python bench/bench_double_table.py "
        f"--n {args.n} --repeats {args.repeats}`. "
        f"{os.cpu_count()} cores, load average {load[0]:.1f} at the end of the run. Table: "
        f"`ppr/data/double_backscatter.npz` ({T.load_table().info.split(' singular')[0]}).",
        "",
        f"## Accuracy ({len(psi)} rows: random normals and frames, incidence 0-88 deg, m in "
        f"[0.02, 150], {', '.join(NS)}; bistatic angle {', '.join(f'{p:g}' for p in PSIS)} rad)",
        "",
        f"Reference: quadrature order {REF_ORDER} (float64). err_full = max |M - M_ref| / "
        "M00(single + double_ref). Reference self-check: order (24, 96) against it: max "
        f"{check['(24, 96)'].max():.1e}.",
        "",
        "| method | err_full max | p95 | median | max at psi = 0 | max at psi = PSI_MAX |",
        "|---|---|---|---|---|---|",
    ]
    for name, err in acc.items():
        lines.append(
            f"| {name} | {err.max():.2e} | {np.percentile(err, 95):.2e} | {np.median(err):.1e} | "
            f"{err[psi == 0].max():.1e} | {err[psi == T.PSI_MAX].max():.1e} |"
        )
    lines += [
        "",
        "Table, max err_full per material: "
        + ", ".join(f"{nm} {acc['table'][mat_name == nm].max():.1e}" for nm in NS)
        + ".",
        "",
    ]
    lines += [
        f"## Throughput (N = {args.n}, jit, median of {args.repeats} after warm-up)",
        "",
        "| method | dtype | material | evals/s |",
        "|---|---|---|---|",
    ]
    for name, dt, per, rate in thr:
        lines.append(f"| {name} | {dt} | {per} | {rate:.3g} |")
    t64 = [r for nm, dt, per, r in thr if nm == "table" and dt == "float64" and per == "one"][0]
    lines += [
        "",
        f"NumPy implementation of the same lookup (float64, one material, {args.n_numpy} pairs): "
        f"{np_rate:.3g} evals/s; JAX float64 / NumPy = {t64 / np_rate:.1f}; max difference "
        f"{np_diff:.1e} of M00.",
        "",
        "## Full BRDF at exact backscatter (`mueller_brdf`, float32, m = 3 or per element)",
        "",
        "`general`: `k_out` a separate array with the values of `k_in` (the general kernel; "
        "`double` is then the run-time dispatch, one `lax.cond` between the table and the "
        "quadrature); `exact`: `k_out` is `k_in` (the exact-backscatter kernel of "
        "`ppr.mueller_brdf`, as a monostatic `ppr.Sensor` renders). Frames: `default` "
        "(the BRDF's own) or `given` (random beam frames, as `ppr.render` passes them).",
        "",
        "| terms | frames | material | general evals/s | exact evals/s | exact / general |",
        "|---|---|---|---|---|---|",
    ]
    for (terms, frames, per), (g, mo) in full.items():
        lines.append(f"| {terms} | {frames} | {per} | {g:.3g} | {mo:.3g} | {mo / g:.1f} |")
    fk = ("single+double+multiple", "given", "one")
    sk = ("single", "given", "one")
    lines += [
        "",
        f"Full / single-only time ratio, given frames, one material: general "
        f"{full[sk][0] / full[fk][0]:.1f}, exact {full[sk][1] / full[fk][1]:.1f}.",
    ]
    lines += [
        "",
        f"## One material, small batches (vmap over {WALKERS} materials, float64)",
        "",
        "Microseconds per call, median of 51 after warm-up: an MCMC half-ensemble of "
        f"{WALKERS} walkers, each with its own m and n and a few facets. `contracted`: the "
        "table's rows contracted with the material once, then interpolated in incidence; "
        "`gathered`: 16 rows gathered per element, contracted with the shared map. "
        f"`ppr` contracts from `ONE_MATERIAL_MIN_BATCH = {T.ONE_MATERIAL_MIN_BATCH}` elements "
        "up.",
        "",
        "| batch | contracted | gathered |",
        "|---|---|---|",
    ]
    lines += [f"| {n} | {1e6 * a:.0f} | {1e6 * b:.0f} |" for n, a, b in small]
    with open(os.path.join(OUT, "double_table.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, err in acc.items():
        rate = [r for nm, dt, per, r in thr if nm == name and dt == "float32" and per == "one"][0]
        ax.loglog(rate, err.max(), "o", label=f"{name}: max")
        ax.loglog(rate, np.percentile(err, 95), "x", color=ax.lines[-1].get_color())
    ax.axhline(1e-3, color="k", lw=0.8, ls="--")
    ax.set_xlabel("double-term evaluations/s (float32, one material)")
    ax.set_ylabel("err_full vs (32, 128) (o max, x p95)")
    ax.set_title("Double bounce near backscatter: error vs speed")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(OUT, "double_table.png"), dpi=120)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
