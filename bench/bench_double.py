"""Double-bounce term: quadrature error against evaluations/s, and full-BRDF throughput.

    .venv/bin/python bench/bench_double.py [--n 100000] [--repeats 3] [--quick]

1. Error of ``double_bounce_term`` at each static order ``(n_u, n_phi)`` against a converged
   reference (order (160, 160), float64) on a fixed random set of geometries (incidence
   0-85 deg, bistatic angle 0-30 deg with random azimuth), roughness m in {0.3, 1, 3, 10, 30,
   100}, aluminium and TiO2. Error measures: ``err_full`` = max over geometries and elements
   of ``|M_double - M_ref| / M00(single + double_ref)`` (the double term's error as a
   fraction of the BRDF it is part of: what a user of ``mueller_brdf`` sees; the
   multiple-scattering term would only enlarge the denominator), and the median / 95th
   percentile relative error of the double term's own M00.
2. Evaluations/s of the double term (jit, N pairs, one call, median of repeats after
   warm-up, block_until_ready) per order, float32 and float64, and of a plain NumPy
   implementation of the same quadrature (same nodes) on a subset, with the ratio.
3. Full BRDF ``mueller_brdf`` (single + double + multiple) and single-only evals/s, float32.

Writes bench/results/double_quadrature.md / .png and bench/results/double_throughput.md.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ppr._double import DEFAULT_ORDER, INNER_ORDER, double_bounce_term  # noqa: E402
from ppr._material import Material  # noqa: E402

OUT = os.path.join(os.path.dirname(__file__), "results")
ORDERS = [(4, 4), (4, 8), (6, 8), (8, 8), (8, 12), (12, 12), (16, 16), (24, 24), (32, 32), (48, 48)]
REF_ORDER = (160, 160)
MS = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
NS = (0.94 + 6.42j, 2.67 + 0j)


def geometry(rng, n, max_inc=85.0, max_psi=30.0):
    """k uniform in solid angle up to max_inc, k' at bistatic angle psi (uniform in [0, max])
    from k with random azimuth, reflected into the upper hemisphere if needed."""
    ci = rng.uniform(np.cos(np.deg2rad(max_inc)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    si = np.sqrt(1 - ci**2)
    k = np.stack([si * np.cos(phi), si * np.sin(phi), ci], -1)
    psi = np.deg2rad(rng.uniform(0, max_psi, n))
    psi[: n // 8] = 0.0  # exact backscatter subset
    a = rng.uniform(0, 2 * np.pi, n)
    t1 = np.cross(k, [0.3, 0.2, 0.9])
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(k, t1)
    kp = np.cos(psi)[:, None] * k + np.sin(psi)[:, None] * (
        np.cos(a)[:, None] * t1 + np.sin(a)[:, None] * t2
    )
    kp[:, 2] = np.abs(kp[:, 2])
    kp /= np.linalg.norm(kp, axis=-1, keepdims=True)
    kp[:, 2] = np.maximum(kp[:, 2], 1e-3)
    kp /= np.linalg.norm(kp, axis=-1, keepdims=True)
    return k, kp


def frames(k, kp):
    from ppr._frames import default_frame

    z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], k.dtype), k.shape)
    return default_frame(-k, z), default_frame(kp, z), z


def make_fn(order, coherent=True):
    @jax.jit
    def f(k, kp, n, m):
        fi, fo, z = frames(k, kp)
        return double_bounce_term(
            k, kp, z, Material(n=n, m=m), fi, fo, order=order, coherent=coherent
        )

    return f


def single_fn():
    from ppr._brdf import single_bounce_term

    @jax.jit
    def f(k, kp, n, m):
        fi, fo, z = frames(k, kp)
        return single_bounce_term(k, kp, z, Material(n=n, m=m), fi, fo)

    return f


def accuracy(n_geo=60, quick=False, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    k0, kp0 = geometry(rng, n_geo)
    ks, kps, ns, ms = [], [], [], []
    for n in NS:
        for m in MS:
            ks.append(k0)
            kps.append(kp0)
            ns.append(np.full(n_geo, n))
            ms.append(np.full(n_geo, m))
    k = jnp.asarray(np.concatenate(ks))
    kp = jnp.asarray(np.concatenate(kps))
    n = jnp.asarray(np.concatenate(ns))
    m = jnp.asarray(np.concatenate(ms))
    ref = np.asarray(make_fn(REF_ORDER)(k, kp, n, m))
    sgl = np.asarray(single_fn()(k, kp, n, m))
    denom = sgl[:, 0, 0] + ref[:, 0, 0]
    orders = ORDERS[:6] if quick else ORDERS
    m_np = np.asarray(m)
    for order in orders:
        got = np.asarray(make_fn(order)(k, kp, n, m))
        err_full = np.max(np.abs(got - ref), axis=(-1, -2)) / denom
        rel00 = np.abs(got[:, 0, 0] / ref[:, 0, 0] - 1)
        per_m = {mm: float(np.max(err_full[m_np == mm])) for mm in MS}
        rows.append(
            dict(
                order=order,
                err_full=float(np.max(err_full)),
                err_full_p95=float(np.percentile(err_full, 95)),
                rel00_med=float(np.median(rel00)),
                rel00_p95=float(np.percentile(rel00, 95)),
                per_m=per_m,
            )
        )
        print(
            order,
            {
                k_: (f"{v:.2e}" if isinstance(v, float) else v)
                for k_, v in rows[-1].items()
                if k_ != "per_m"
            },
        )
    return rows


def timeit(f, args, repeats):
    jax.block_until_ready(f(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def throughput(n, repeats, quick=False):
    rng = np.random.default_rng(1)
    k, kp = geometry(rng, n)
    rows = []
    orders = [(4, 8), (8, 8), (8, 12), (12, 12), (16, 16)] if quick else ORDERS[:8]
    for dt in (jnp.float32, jnp.float64):
        cdt = jnp.complex64 if dt == jnp.float32 else jnp.complex128
        args = (
            jnp.asarray(k, dt),
            jnp.asarray(kp, dt),
            jnp.full((n,), 0.94 + 6.42j, cdt),
            jnp.full((n,), 3.0, dt),
        )
        for order in orders:
            t = timeit(make_fn(order), args, repeats)
            rows.append(dict(dtype=np.dtype(dt).name, order=order, evals_per_s=n / t))
            print(rows[-1])
    return rows


# ------------------------------------------------------------------------------ NumPy version


def numpy_double_m00(k, kp, n, m, order, inner_order=INNER_ORDER):
    """Plain NumPy of the same quadrature (same nodes, both balance halves), scalar M00 only
    with the Jones chain: used for the throughput ratio (and checked against JAX)."""
    from ppr._double import _nodes as nodes_fn

    t, wt, cph, sph, wph = nodes_fn(*order)
    xg, wg = np.polynomial.legendre.leggauss(inner_order)
    xg, wg = 0.5 * (xg + 1), 0.5 * wg

    def mcp(mm, c):
        bmax = np.minimum(0.5 * np.pi, 7.0 / np.sqrt(mm + 1.0))
        b = bmax[..., None] * xg
        cb, sb = np.cos(b), np.sin(b)
        cc = c[..., None]
        f = cb ** mm[..., None] * sb * (sb - cc * cb * np.arctan2(sb, cc * cb))
        s2 = np.clip(1 - c * c, 0, 1)
        return c * (mm + 1) / (mm + 2) + (mm + 1) / np.pi * s2 ** (0.5 * (mm + 2)) * bmax * np.sum(
            wg * f, -1
        )

    def fres(cos_t):
        w = np.sqrt(n * n - 1 + cos_t**2 + 0j)
        return (cos_t - w) / (cos_t + w), (n * n * cos_t - w) / (n * n * cos_t + w)

    def half(ka, kb):
        c = ka[:, 2]
        s = np.sqrt(np.clip(1 - c * c, 0, 1))
        xneg = np.maximum(-cph, 0)
        sx = s[:, None] * xneg
        with np.errstate(divide="ignore", invalid="ignore"):
            lcm = np.where(
                sx > 0, -0.5 * np.log1p((c[:, None] / np.where(sx > 0, sx, 1)) ** 2), -np.inf
            )
        umin = np.exp((m[:, None] + 1) * lcm)
        u = umin[..., None] + (1 - umin[..., None]) * t
        w = wph[:, None] * (1 - umin[..., None]) * wt
        u = u.reshape(len(c), -1)
        w = w.reshape(len(c), -1)
        cp_ = np.repeat(cph, len(t))
        sp_ = np.repeat(sph, len(t))
        mm = m[:, None]
        ct = u ** (1 / (mm + 1))
        st = np.sqrt(np.clip(1 - ct * ct, 0, 1))
        t1 = ka - c[:, None] * np.array([0, 0, 1.0])
        t1n = np.linalg.norm(t1, axis=-1, keepdims=True)
        t1 = np.where(t1n > 1e-9, t1 / np.maximum(t1n, 1e-300), [1.0, 0, 0])
        t2 = np.cross([0, 0, 1.0], t1)
        h = st[..., None] * (cp_[:, None] * t1[:, None] + sp_[:, None] * t2[:, None]) + ct[
            ..., None
        ] * np.array([0, 0, 1.0])
        c1 = np.clip(np.sum(h * ka[:, None], -1), 0, 1)
        d1 = 2 * c1[..., None] * h - ka[:, None]
        v = kb[:, None] - d1
        vn = np.linalg.norm(v, axis=-1)
        h2 = v / np.maximum(vn, 1e-300)[..., None]
        h2n = h2[..., 2]
        p2 = np.where(h2n > 0, np.clip(h2n, 0, 1) ** mm, 0)
        p1 = ct**mm
        bal = p1 / np.maximum(p1 + p2, 1e-300)
        wgt = (
            w
            * bal
            * c1
            * (mm + 1)
            / (2 * np.pi)
            * p2
            / (4 * mcp(np.broadcast_to(mm, d1[..., 2].shape), np.abs(d1[..., 2])))
        )
        rs1, rp1 = fres(c1)
        rs2, rp2 = fres(np.clip(vn / 2, 0, 1))
        # unpolarized two-facet M00 needs the plane rotation: cos/sin of the angle between
        # s1 and s2 (both _|_ d1)
        s1 = np.cross(ka[:, None], d1)
        s1 /= np.maximum(np.linalg.norm(s1, axis=-1, keepdims=True), 1e-300)
        s2 = np.cross(-d1, kb[:, None])
        s2 /= np.maximum(np.linalg.norm(s2, axis=-1, keepdims=True), 1e-300)
        ca = np.sum(s1 * s2, -1)
        sa2 = 1 - ca * ca
        a2 = [np.abs(rs2) ** 2, np.abs(rp2) ** 2]
        a1 = [np.abs(rs1) ** 2, np.abs(rp1) ** 2]
        m00 = 0.5 * (a2[0] * (ca**2 * a1[0] + sa2 * a1[1]) + a2[1] * (sa2 * a1[0] + ca**2 * a1[1]))
        return np.sum(wgt * m00, -1)

    hn = (m + 1) / (m + 2)
    pref = hn / (mcp(m, k[:, 2]) * mcp(m, kp[:, 2]))
    return pref * (half(k, kp) + half(kp, k))


def numpy_ratio(order, n=2000):
    rng = np.random.default_rng(2)
    k, kp = geometry(rng, n)
    nn = 0.94 + 6.42j
    m = np.full(n, 3.0)
    f = make_fn(order, coherent=False)
    args = (jnp.asarray(k), jnp.asarray(kp), jnp.full((n,), nn), jnp.asarray(m))
    jax_m00 = np.asarray(f(*args))[:, 0, 0]
    t0 = time.perf_counter()
    np_m00 = numpy_double_m00(k, kp, nn, m, order)
    t_np = time.perf_counter() - t0
    t_jax = timeit(f, args, 3)
    err = float(np.max(np.abs(np_m00 / jax_m00 - 1)))
    return dict(
        order=order, numpy_evals_per_s=n / t_np, jax_f64_evals_per_s=n / t_jax, max_rel_diff=err
    )


def full_brdf_throughput(n, repeats):
    from ppr._brdf import mueller_brdf

    rng = np.random.default_rng(3)
    k, kp = geometry(rng, n)
    out = []
    for terms in (("single",), ("single", "multiple"), ("single", "double", "multiple")):

        @jax.jit
        def f(k, kp, m):
            z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], k.dtype), k.shape)
            return mueller_brdf(k, kp, z, Material(n=jnp.complex64(0.94 + 6.42j), m=m), terms=terms)

        args = (
            jnp.asarray(k, jnp.float32),
            jnp.asarray(kp, jnp.float32),
            jnp.full((n,), 3.0, jnp.float32),
        )
        t = timeit(f, args, repeats)
        out.append(dict(terms="+".join(terms), evals_per_s=n / t))
        print(out[-1])
    return out


def write(acc, thr, nprow, full, path_md, path_png):
    lines = [
        "# Double-bounce quadrature: error vs evaluations/s",
        "",
        f"Reference: order {REF_ORDER} float64. Geometries: incidence 0-85 deg, bistatic 0-30 deg "
        "(1/8 exact backscatter), m in "
        + ", ".join(f"{x:g}" for x in MS)
        + ", Al 532 nm and TiO2. "
        "`err_full` = max |M_double - M_ref| / M00(single + double): the double term's error as a "
        "fraction of the BRDF. Default order: " + f"{DEFAULT_ORDER}.",
        "",
        "| order (n_u, n_phi) | nodes | err_full max | err_full p95 | rel. err M00_double median | p95 | "
        + " | ".join(f"err_full m={x:g}" for x in MS)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(MS),
    ]
    for r in acc:
        o = r["order"]
        lines.append(
            f"| {o} | {2 * o[0] * (o[1] // 4) * 4} | {r['err_full']:.2e} | {r['err_full_p95']:.2e} | {r['rel00_med']:.2e} | "
            f"{r['rel00_p95']:.2e} | " + " | ".join(f"{r['per_m'][x]:.1e}" for x in MS) + " |"
        )
    lines += [
        "",
        "## Throughput of the double term alone (jit, one call of N pairs, m = 3, Al)",
        "",
    ]
    lines += ["| dtype | order | evals/s |", "|---|---|---|"]
    for r in thr:
        lines.append(f"| {r['dtype']} | {r['order']} | {r['evals_per_s']:.3g} |")
    if nprow:
        lines += [
            "",
            f"NumPy (same quadrature, M00 only, float64) at order {nprow['order']}: "
            f"{nprow['numpy_evals_per_s']:.3g} evals/s; JAX float64 full 4x4: "
            f"{nprow['jax_f64_evals_per_s']:.3g} evals/s; ratio JAX/NumPy = "
            f"{nprow['jax_f64_evals_per_s'] / nprow['numpy_evals_per_s']:.1f}; max rel. diff of M00 "
            f"{nprow['max_rel_diff']:.1e}.",
        ]
    if full:
        lines += [
            "",
            "## Full BRDF (float32, default order, m = 3, Al)",
            "",
            "| terms | evals/s |",
            "|---|---|",
        ]
        for r in full:
            lines.append(f"| {r['terms']} | {r['evals_per_s']:.3g} |")
    with open(path_md, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for dt, mk in (("float32", "o-"), ("float64", "s--")):
            xs, ys, labs = [], [], []
            for r in thr:
                if r["dtype"] != dt:
                    continue
                a = [x for x in acc if x["order"] == r["order"]]
                if not a:
                    continue
                xs.append(r["evals_per_s"])
                ys.append(a[0]["err_full"])
                labs.append(r["order"])
            ax.loglog(xs, ys, mk, label=dt)
            for x, y, lab in zip(xs, ys, labs):
                ax.annotate(f"{lab[0]}x{lab[1]}", (x, y), fontsize=7)
        ax.axhline(1e-3, color="gray", lw=0.8)
        ax.set_xlabel("double-term evaluations / s (N = 1e5, 2 cores)")
        ax.set_ylabel("max |dM| / M00(single + double)")
        ax.set_title("double bounce: quadrature error vs throughput")
        ax.legend()
        fig.tight_layout()
        fig.savefig(path_png, dpi=120)
    except Exception as err:  # pragma: no cover
        print("plot failed:", err)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-full", action="store_true")
    args = ap.parse_args()
    os.makedirs(OUT, exist_ok=True)
    acc = accuracy(quick=args.quick)
    thr = throughput(args.n, args.repeats, quick=args.quick)
    nprow = numpy_ratio(DEFAULT_ORDER)
    print(nprow)
    full = None if args.no_full else full_brdf_throughput(args.n, args.repeats)
    write(
        acc,
        thr,
        nprow,
        full,
        os.path.join(OUT, "double_quadrature.md"),
        os.path.join(OUT, "double_quadrature.png"),
    )


if __name__ == "__main__":
    main()
