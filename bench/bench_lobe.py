"""Error against speed of ``ppr.microfacet.mean_cosine_plus`` (<h.k>+) per quadrature order.

For each quadrature order and dtype: the maximum relative error over the mpmath reference
grid (tests/data/lobe_reference.npz: m in {0, 1e-3, ..., 1e6}, incidence 0..89.999 deg with
the grazing band resolved) and evaluations per second on N = 1e6 random inputs (m
log-uniform in [1e-3, 1e6], cos_theta uniform in [0, 1], so nearly every batch needs the
quadrature), jit, median of repeats after warm-up with ``block_until_ready``. A plain NumPy
implementation of the same formula (trapezoid in y = asinh(x / c), chunked) runs in the same
process at the default orders; the ratio is printed. The fast path (whole batch away from
grazing, m = 1e6, cos_theta in [0.2, 1]: the quadrature is skipped) is timed too.

Choice of the defaults (the measured curve is in bench/results/lobe_error_vs_speed.md):
the error falls like exp(-pi^2 (order - 1) / Y) (trapezoid on an integrand analytic in a
strip of half-width pi/2, Y <= ~21 for incidence <= 89.999 deg), i.e. about 10x per 4 nodes
at the end of the curve. In float64 order 56 reaches ~1.6e-10 (6x margin on the 1e-9
requirement) and order 64 reaches 2e-12 (500x margin) at ~12% more time: 64 is the default,
the smallest order with a comfortable margin. In float32 the rounding floor is ~3e-7;
order 32 reaches ~8e-7 (order 24: 2.5e-5), so 32 is the float32 default.

Run:  .venv/bin/python bench/bench_lobe.py      (about 1-2 minutes)
"""

from __future__ import annotations

import math
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # script: float64 runs next to float32

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ppr.microfacet as mf_i  # noqa: E402
from ppr import microfacet as mf  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results"
N = 1_000_000
REPEATS = 3
TABLE_NODES = [32, 64, 128, 256, 512, 1024]
ORDERS = {np.float64: [16, 24, 32, 40, 48, 56, 64, 80], np.float32: [12, 16, 20, 24, 28, 32, 40]}


def numpy_mean_cosine_plus(m, c, order, log_tail, c_small, chunk=100_000):
    """Plain NumPy of the same formula (module docstring of ppr.microfacet), float64."""
    out = np.empty_like(c)
    j = np.arange(order)
    w = np.ones(order)
    w[0] = w[-1] = 0.5
    for a in range(0, len(c), chunk):
        mm, cc = m[a : a + chunk], c[a : a + chunk]
        big_m = mm + 2.0
        c1 = c_small / np.sqrt(big_m)
        cq = np.maximum(cc, c1)
        s2 = (1 - cq) * (1 + cq)
        log_s2 = np.where(cq < 0.5, np.log1p(-cq * cq), np.log(np.maximum(s2, 1e-300)))
        log_sm = 0.5 * big_m * log_s2
        x_max = np.sqrt(np.expm1(2 * log_tail / (big_m + 1)))
        y_max = np.arcsinh(x_max / cq)
        h = y_max / (order - 1)
        y = h[:, None] * j
        sh2 = np.sinh(y) ** 2
        q = (cq * cq)[:, None] * sh2
        num = s2[:, None] * sh2 + (1 + q) / big_m[:, None]
        f = num / np.cosh(y) * np.exp(log_sm[:, None] - 0.5 * (big_m[:, None] + 2) * np.log1p(q))
        corr = cq * h * (f @ w) / math.pi
        corr += np.exp(log_sm) * 0.5 * (1 - 1 / big_m) * (cq - cc)
        out[a : a + chunk] = cc * (mm + 1) / big_m + corr
    return out


def timed(fn, *args, repeats=None):
    fn(*args).block_until_ready()  # warm-up (compile)
    ts = []
    for _ in range(REPEATS if repeats is None else repeats):
        t0 = time.perf_counter()
        fn(*args).block_until_ready()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


SMALL_SIZES = (16, 64, 256, 512, 1024, 4096)


def small_batches() -> list[str]:
    """Small batches (a few facets per MCMC walker, a few hundred per call): the float64
    quadrature's nodes on a node axis against the loop over the nodes, values and gradient,
    microseconds per call. ``NODE_AXIS_MAX`` is switched per row (caches cleared)."""
    rng = np.random.default_rng(1)
    order = mf.DEFAULT_ORDER
    keep = mf_i.NODE_AXIS_MAX, mf_i.NODE_AXIS_PARTIALS
    out = []
    try:
        for size in SMALL_SIZES:
            m = jnp.asarray(10.0 ** rng.uniform(-1, 3, size))
            c = jnp.asarray(rng.uniform(0, 1, size))
            row = {}
            for mode, limit in (("axis", 1 << 62), ("loop", 0)):
                mf_i.NODE_AXIS_MAX, mf_i.NODE_AXIS_PARTIALS = limit, limit > 0
                jax.clear_caches()
                val = jax.jit(lambda m, c: mf.mean_cosine_plus(m, c))
                grad = jax.jit(
                    lambda m, c: jnp.stack(
                        jax.grad(lambda m, c: jnp.sum(mf.visibility(m, c)), (0, 1))(m, c)
                    )
                )
                row[mode] = (timed(val, m, c, repeats=51), timed(grad, m, c, repeats=51))
            out.append(
                f"| {size} | {size * order} | {1e6 * row['axis'][0]:.0f} | "
                f"{1e6 * row['loop'][0]:.0f} | {1e6 * row['axis'][1]:.0f} | "
                f"{1e6 * row['loop'][1]:.0f} |"
            )
            print(out[-1], flush=True)
    finally:
        mf_i.NODE_AXIS_MAX, mf_i.NODE_AXIS_PARTIALS = keep
        jax.clear_caches()
    return [
        "",
        "## Small batches: the nodes on an axis or in a loop (float64, order "
        f"{order})",
        "",
        "Microseconds per call, jit, median of 51 calls after warm-up; random m in "
        "[0.1, 1e3], cos in [0, 1] (the correction is needed for some elements of every "
        "batch). XLA CPU pays a few microseconds per loop iteration; one fused sum over a "
        "node axis avoids them but keeps `size x order` intermediates. The gradient columns "
        "time the custom-JVP partials, summed by the same two methods. `ppr` sums values on "
        f"the node axis up to `size x order <= NODE_AXIS_MAX = {keep[0]}`, and the partials "
        f"in the loop (`NODE_AXIS_PARTIALS = {keep[1]}`).",
        "",
        "| batch | batch x order | values, axis | values, loop | gradient, axis | "
        "gradient, loop |",
        "|---|---|---|---|---|---|",
        *out,
    ]


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    small = small_batches()
    ref = np.load(ROOT / "tests" / "data" / "lobe_reference.npz")
    rm, rc, rv = ref["m"], ref["cos_theta"], ref["mean_cosine_plus"]
    rng = np.random.default_rng(0)
    m_in = 10.0 ** rng.uniform(-3, 6, N)
    c_in = rng.uniform(0, 1, N)
    c_fast = rng.uniform(0.2, 1, N)
    rows = []
    for dt, orders in ORDERS.items():
        name = np.dtype(dt).name
        m, c = jnp.asarray(m_in, dt), jnp.asarray(c_in, dt)
        for order in orders:
            f = jax.jit(lambda m, c, o=order: mf.mean_cosine_plus(m, c, order=o))
            got = np.asarray(f(jnp.asarray(rm, dt), jnp.asarray(rc, dt)), np.float64)
            err = float(np.max(np.abs(got - rv) / rv))
            t = timed(f, m, c)
            rows.append(dict(dtype=name, order=order, err=err, rate=N / t))
            print(f"{name} order {order:3d}: max rel err {err:.2e}, {N / t / 1e6:6.2f} M evals/s")
    # fast path: no element of the batch in the grazing band
    fast = {}
    for dt in ORDERS:
        f = jax.jit(lambda m, c: mf.mean_cosine_plus(m, c))
        t = timed(f, jnp.full(N, 1e6, dt), jnp.asarray(c_fast, dt))
        fast[np.dtype(dt).name] = N / t
        print(f"{np.dtype(dt).name} fast path (m=1e6, c in [0.2,1]): {N / t / 1e6:.1f} M evals/s")
    # NumPy reference of the same formula at the default orders (float64 arithmetic)
    n_np = 200_000
    np_rates = {}
    for dt, order, tail, cs in (
        (np.float64, mf.DEFAULT_ORDER, 28.0, 1e-5),
        (np.float32, mf.DEFAULT_ORDER_F32, 16.0, 3e-4),
    ):
        t0 = time.perf_counter()
        v = numpy_mean_cosine_plus(m_in[:n_np], c_in[:n_np], order, tail, cs)
        rate = n_np / (time.perf_counter() - t0)
        jx = np.asarray(
            mf.mean_cosine_plus(jnp.asarray(m_in[:n_np], dt), jnp.asarray(c_in[:n_np], dt)),
            np.float64,
        )
        agree = float(np.max(np.abs(v - jx) / v))
        jrate = next(
            r["rate"] for r in rows if r["dtype"] == np.dtype(dt).name and r["order"] == order
        )
        np_rates[np.dtype(dt).name] = (order, rate, jrate, agree)
        print(
            f"NumPy order {order} ({np.dtype(dt).name} settings): {rate / 1e6:.2f} M evals/s; "
            f"JAX {np.dtype(dt).name} / NumPy = {jrate / rate:.1f}x; max rel diff {agree:.1e}"
        )

    # one material per batch: the per-call table of the correction (visibility_one_material)
    p_ref = rc * (rm + 1.0) / (rm + 2.0) / rv  # P(k) on the mpmath grid
    tab_rows = []
    for dt in ORDERS:
        name = np.dtype(dt).name
        c1 = jnp.asarray(c_in, dt)
        fq = jax.jit(lambda m, c: mf.visibility(m, c))
        tq = timed(fq, dt(30.0), c1)
        for n_nodes in TABLE_NODES:
            f = jax.jit(lambda m, c, n=n_nodes: mf_i.visibility_one_material(m, c, n_nodes=n))
            err = 0.0
            for m in np.unique(rm):
                sel = rm == m
                got = np.asarray(f(dt(m), jnp.asarray(rc[sel], dt)), np.float64)
                err = max(err, float(np.max(np.abs(got - p_ref[sel]) / p_ref[sel])))
            t = timed(f, dt(30.0), c1)
            tab_rows.append(dict(dtype=name, nodes=n_nodes, err=err, rate=N / t, quad=N / tq))
            print(f"{name} table {n_nodes:5d} nodes: P(k) max rel err {err:.2e}, "
                  f"{N / t / 1e6:6.2f} M evals/s (quadrature visibility {N / tq / 1e6:.2f})")

    lines = [
        "# <h.k>+ quadrature: error vs speed",
        "",
        f"`bench/bench_lobe.py`, N = {N:.0e} random (m log-uniform 1e-3..1e6, cos uniform), "
        f"median of {REPEATS} after warm-up, jit, this machine (2 cores, shared: "
        f"load average {open('/proc/loadavg').read().split()[0]} at the end of the run).",
        "Error: max relative error over the 282-point mpmath grid (tests/data/lobe_reference.npz).",
        "",
        "| dtype | order | max rel. error | M evals/s |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['dtype']} | {r['order']} | {r['err']:.1e} | {r['rate'] / 1e6:.2f} |" for r in rows
    ]
    lines += [
        "",
        "| dtype | fast path (m = 1e6, cos in [0.2, 1], quadrature skipped) M evals/s |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v / 1e6:.1f} |" for k, v in fast.items()]
    lines += [
        "",
        "| settings | order | NumPy M evals/s | JAX M evals/s | JAX / NumPy | max rel. diff |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {k} | {o} | {r / 1e6:.2f} | {j / 1e6:.2f} | {j / r:.1f}x | {a:.1e} |"
        for k, (o, r, j, a) in np_rates.items()
    ]
    lines += [
        "",
        "## One material per batch: tabulated correction (`visibility_one_material`)",
        "",
        "The correction tabulated per call at `nodes` points equispaced in tan(asin(cos) / 2) "
        "by the "
        "quadrature (with its partials), cubic Hermite per element. Error: max relative error "
        "of P(k) over the mpmath grid; speed: N random cosines, m = 30, against the quadrature "
        "`visibility` on the same input. `ppr.mueller_brdf` uses it in float32 with "
        f"{mf_i.TABLE_NODES[32]} nodes (the float32 quadrature's own error is ~1e-6).",
        "",
        "| dtype | nodes | P(k) max rel. error | M evals/s | quadrature M evals/s |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['dtype']} | {r['nodes']} | {r['err']:.1e} | {r['rate'] / 1e6:.2f} | "
        f"{r['quad'] / 1e6:.2f} |"
        for r in tab_rows
    ]
    lines += [
        "",
        f"Defaults: float64 order {mf.DEFAULT_ORDER}, float32 order {mf.DEFAULT_ORDER_F32} "
        "(reasoning in the docstring of bench/bench_lobe.py).",
        *small,
    ]
    (OUT / "lobe_error_vs_speed.md").write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for name, mk in (("float64", "o-"), ("float32", "s-")):
        rr = [r for r in rows if r["dtype"] == name]
        ax.loglog([r["rate"] / 1e6 for r in rr], [r["err"] for r in rr], mk, label=name)
        for r in rr:
            ax.annotate(
                str(r["order"]),
                (r["rate"] / 1e6, r["err"]),
                fontsize=7,
                xytext=(3, 3),
                textcoords="offset points",
            )
    ax.axhline(1e-9, color="k", lw=0.8, ls="--", label="1e-9 requirement")
    ax.set_xlabel("M evaluations / s (N = 1e6, jit)")
    ax.set_ylabel("max relative error vs mpmath")
    ax.set_title("<h.k>+: error vs speed per quadrature order")
    ax.legend()
    for name, mk in (("float64", "o-"), ("float32", "s-")):
        rr = [r for r in tab_rows if r["dtype"] == name]
        ax2.loglog([r["rate"] / 1e6 for r in rr], [r["err"] for r in rr], mk, label=name)
        for r in rr:
            ax2.annotate(str(r["nodes"]), (r["rate"] / 1e6, r["err"]), fontsize=7,
                         xytext=(3, 3), textcoords="offset points")
    ax2.set_xlabel("M evaluations / s (one m, N = 1e6, jit)")
    ax2.set_ylabel("P(k): max relative error vs mpmath")
    ax2.set_title("one material: tabulated correction per node count")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(OUT / "lobe_error_vs_speed.png", dpi=120)
    print(f"wrote {OUT / 'lobe_error_vs_speed.md'} and .png")


if __name__ == "__main__":
    main()
