"""Double-bounce term: quadrature error against evaluations/s, and full-BRDF throughput.

    .venv/bin/python bench/bench_double.py [--n 100000] [--repeats 3] [--n-numpy 2000] [--quick]

Orders are ``(n_u, n_phi)`` of the current rule of ``ppr.brdf.double`` (module docstring,
"Quadrature"): per half, three closed-form ``u`` panels per azimuth with ``n_u`` Gauss-Legendre
nodes each, and ``4 max(n_phi // 4, 1)`` azimuths packed near ``phi = +-pi/2``; paths per pair
``2 * 3 * n_u * 4 * max(n_phi // 4, 1)`` (:func:`n_paths`; 216 at the default (3, 12)).

1. Error of ``double_bounce_term`` at each static order against a converged reference
   (order (24, 96) = 13824 paths, float64) on a fixed random set of geometries (incidence
   0-85 deg, bistatic angle 0-30 deg with random azimuth), roughness m in {0.3, 1, 3, 10, 30,
   100}, aluminium and TiO2. Error measures: ``err_full`` = max over geometries and elements
   of ``|M_double - M_ref| / M00(single + double_ref)`` (the double term's error as a
   fraction of the BRDF it is part of: what a user of ``mueller_brdf`` sees; the
   multiple-scattering term would only enlarge the denominator), and the median / 95th
   percentile relative error of the double term's own M00 (p95 ~ 1 even at (8, 32): 80 of the
   720 rows, all at m = 30 and 100, where that M00 is <= 7e-6 of the BRDF's). The
   reference's own convergence is reported as the error of order (16, 64) against it.
2. Evaluations/s of the double term (jit, N pairs, one call, median of repeats after
   warm-up, block_until_ready) per order, float32 and float64, and of a plain NumPy
   implementation of the same quadrature (:func:`numpy_double_m00`: the node layout is
   rebuilt in NumPy, not taken from ``ppr.brdf.double``) on a subset, with the ratio.
3. Full BRDF ``mueller_brdf`` (single + double + multiple) and single-only evals/s, float32.

Writes bench/results/double_quadrature.md / .png (accuracy, error vs evals/s) and
bench/results/double_throughput.md (throughput, NumPy ratio, full BRDF).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import median_time  # noqa: E402

from ppr.brdf.double import DEFAULT_ORDER, INNER_ORDER, double_bounce_term  # noqa: E402
from ppr.materials import Material  # noqa: E402

OUT = os.path.join(os.path.dirname(__file__), "results")
ORDERS = [(1, 4), (2, 8), (2, 12), (3, 12), (4, 16), (6, 24), (8, 32), (12, 48)]
QUICK_ORDERS = ORDERS[:7]
THROUGHPUT_ORDERS = [(1, 4), (2, 8), (2, 12), (3, 12), (4, 16), (6, 24), (8, 32)]
QUICK_THROUGHPUT_ORDERS = QUICK_ORDERS
REF_ORDER = (24, 96)
REF_CHECK_ORDER = (16, 64)  # self-convergence of the reference: err of this order vs REF
MS = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
NS = (0.94 + 6.42j, 2.67 + 0j)


def n_paths(order):
    """Path evaluations per (k, k') pair: 2 halves x 3 u panels x n_u x 4 quarter panels x
    max(n_phi // 4, 1) azimuths."""
    n_u, n_phi = order
    return 2 * 3 * n_u * 4 * max(n_phi // 4, 1)


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
    from ppr.optics import default_frame

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
    from ppr.brdf import single_bounce_term

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
    orders = (QUICK_ORDERS if quick else ORDERS) + [REF_CHECK_ORDER]
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


def throughput(n, repeats, quick=False):
    rng = np.random.default_rng(1)
    k, kp = geometry(rng, n)
    rows = []
    orders = QUICK_THROUGHPUT_ORDERS if quick else THROUGHPUT_ORDERS
    for dt in (jnp.float32, jnp.float64):
        cdt = jnp.complex64 if dt == jnp.float32 else jnp.complex128
        args = (
            jnp.asarray(k, dt),
            jnp.asarray(kp, dt),
            jnp.full((n,), 0.94 + 6.42j, cdt),
            jnp.full((n,), 3.0, dt),
        )
        for order in orders:
            t = median_time(make_fn(order), *args, repeats=repeats)
            rows.append(dict(dtype=np.dtype(dt).name, order=order, evals_per_s=n / t))
            print(rows[-1])
    return rows


# ------------------------------------------------------------------------------ NumPy version


def numpy_double_m00(k, kp, n, m, order, inner_order=INNER_ORDER):
    """Plain NumPy reimplementation of the current quadrature (``ppr.brdf.double``, module
    docstring "Quadrature"), M00 only, float64, normal = +z: the same node layout is built
    here from scratch (Gauss-Legendre ``n_u`` nodes in ``u = cos^(m+1) t`` on each of the
    three closed-form panels ``[u(t_a), 1]``, ``[u(t_0), u(t_b)]``, ``[u(t_max), u(t_0)]``;
    ``4 max(n_phi // 4, 1)`` azimuths, Gauss-Legendre in ``log(delta + lambda)`` per quarter
    panel about ``phi = +-pi/2``), both balance halves, the visibility correlation ``rho``
    and the two-facet Jones chain reduced to M00. Only ``<h.u>+`` differs: it is the direct
    inner Gauss-Legendre rule at every node (not the Chebyshev interpolant of the JAX code,
    relative difference <= 3e-5 for m >= 1, 2e-4 at m = 0.3). Used for the JAX/NumPy
    throughput ratio (and checked against JAX, incoherent)."""
    xg, wg = np.polynomial.legendre.leggauss(inner_order)
    xg, wg = 0.5 * (xg + 1), 0.5 * wg
    n_u, n_phi = order
    xu, wu = np.polynomial.legendre.leggauss(n_u)
    tu, wtu = 0.5 * (xu + 1), 0.5 * wu
    nq = max(n_phi // 4, 1)
    xp, wp = np.polynomial.legendre.leggauss(nq)
    tp, wp = 0.5 * (xp + 1), 0.5 * wp
    ez = np.array([0.0, 0.0, 1.0])

    def mcp(mm, c):
        bmax = np.minimum(0.5 * np.pi, 7.0 / np.sqrt(mm + 1.0))
        b = bmax[..., None] * xg
        cb, sb = np.cos(b), np.sin(b)
        cc = c[..., None]
        lcb = np.log1p(-2.0 * np.sin(0.5 * b) ** 2)
        f = np.exp(mm[..., None] * lcb) * sb * (sb - cc * cb * np.arctan2(sb, cc * cb))
        s2 = np.clip((1 - c) * (1 + c), 0, 1)
        return c * (mm + 1) / (mm + 2) + (mm + 1) / np.pi * s2 ** (0.5 * (mm + 2)) * bmax * np.sum(
            wg * f, -1
        )

    def fres(cos_t):
        w = np.sqrt(n * n - 1 + cos_t**2 + 0j)
        return (cos_t - w) / (cos_t + w), (n * n * cos_t - w) / (n * n * cos_t + w)

    def ucos(mm, t):  # cos^(m+1) t, 0 at t >= pi/2
        ct = np.cos(t)
        with np.errstate(divide="ignore"):
            lg = np.where(t < 1.0, np.log1p(-2.0 * np.sin(0.5 * t) ** 2), np.log(np.maximum(ct, 0)))
        return np.where(ct > 1e-300, np.exp((mm + 1) * lg), 0.0)

    def azim_f(a, d):  # Ashikhmin f = |u_a + u_d| / 2 of the horizontal projections
        pa = a * np.array([1.0, 1.0, 0.0])
        pd = d * np.array([1.0, 1.0, 0.0])
        na = np.linalg.norm(pa, axis=-1, keepdims=True)
        nd = np.linalg.norm(pd, axis=-1, keepdims=True)
        ok = (na[..., 0] > 1e-12) & (nd[..., 0] > 1e-12)
        sm = pa / np.maximum(na, 1e-300) + pd / np.maximum(nd, 1e-300)
        return np.where(ok, np.clip(0.5 * np.linalg.norm(sm, axis=-1), 0, 1), 1.0)

    def rho(pa, pd, f):
        num = pa - ((1 - f) * pa * pd + f * np.minimum(pa, pd))
        den = pa * (1 - pd)
        ok = den > 1e-30
        return np.where(ok, np.clip(num / np.where(ok, den, 1.0), 0, 1), 1.0)

    def half(ka, kb):
        N = len(ka)
        c = np.clip(ka[:, 2], 0, 1)
        s = np.sqrt(np.clip((1 - c) * (1 + c), 0, 1))
        cp = np.clip(kb[:, 2], 0, 1)
        mm = m[:, None]
        # azimuths
        ok = s > 1e-6 * c
        lam = np.where(ok, c * (1.0 + 0.25 * np.sqrt(m + 1)) / np.where(ok, s, 1.0), 1e6)
        lam = np.minimum(lam, 1e6)
        L = np.log1p(0.5 * np.pi / lam)
        d = lam[:, None] * np.expm1(L[:, None] * tp)
        wd = L[:, None] * (d + lam[:, None]) * wp / (2 * np.pi)
        sd, cd = np.sin(d), np.cos(d)
        cph = np.concatenate([sd, -sd, -sd, sd], -1)
        sph = np.concatenate([cd, cd, -cd, -cd], -1)
        wph = np.concatenate([wd, wd, wd, wd], -1)
        # three u panels per azimuth
        scp = s[:, None] * cph
        alpha = np.arctan2(scp, c[:, None])
        R2 = c[:, None] ** 2 + scp**2
        t_max = np.minimum(0.5 * np.pi, 0.5 * np.pi + alpha)
        t_0 = 0.5 * alpha + 0.25 * np.pi
        beta = np.arctan2(np.sqrt(np.clip(R2 - cp[:, None] ** 2, 0, None)), cp[:, None])
        t_a = np.clip(0.5 * (alpha - beta), 0, t_0)
        t_b = np.clip(0.5 * (alpha + beta), 0, t_0)
        u_a, u_b, u_0, u_mx = (ucos(mm, x) for x in (t_a, t_b, t_0, t_max))
        lo = np.stack([u_a, u_0, u_mx], -1)
        hi = np.stack([np.ones_like(u_a), u_b, u_0], -1)
        u = (lo[..., None] + (hi - lo)[..., None] * tu).reshape(N, -1)
        w = (wph[..., None, None] * (hi - lo)[..., None] * wtu).reshape(N, -1)
        U = 3 * n_u
        cq = np.repeat(cph, U, -1)
        sq = np.repeat(sph, U, -1)
        logu = np.log(np.maximum(u, 1e-300))
        ct = np.exp(logu / (mm + 1))
        st = np.sqrt(np.clip(-np.expm1(logu / (mm + 1)) * (1 + ct), 0, None))
        t1 = ka - c[:, None] * ez
        t1n = np.linalg.norm(t1, axis=-1, keepdims=True)
        t1 = np.where(t1n > 1e-8, t1 / np.maximum(t1n, 1e-300), [1.0, 0, 0])
        t2 = np.cross(ez, t1)
        h = (
            (st * cq)[..., None] * t1[:, None]
            + (st * sq)[..., None] * t2[:, None]
            + ct[..., None] * ez
        )
        kaq, kbq = ka[:, None], kb[:, None]
        c1 = np.clip(np.sum(h * kaq, -1), 0, 1)
        d1 = 2 * c1[..., None] * h - kaq
        v = kbq - d1
        vn = np.linalg.norm(v, axis=-1)
        h2n = v[..., 2] / np.maximum(vn, 1e-300)
        valid = (vn > 1e-300) & (h2n > 1e-300) & (c1 > 0)
        with np.errstate(divide="ignore"):
            log_p2 = np.where(valid, mm * np.log(np.where(valid, h2n, 1.0)), -1e30)
        p2 = np.where(valid, np.exp(log_p2), 0.0)
        bal = 1.0 / (1.0 + np.exp(np.clip(log_p2 - mm * logu / (mm + 1), -700, 700)))
        dn = d1[..., 2]
        mb = np.broadcast_to(mm, dn.shape)
        inner = mcp(mb, np.abs(dn))
        hn = (mm + 1) / (mm + 2)
        p_d = np.clip(hn * np.abs(dn) / inner, 0, 1)
        p_a = np.clip(hn * c[:, None] / mcp(m, c)[:, None], 0, 1)
        p_b = np.clip(hn * cp[:, None] / mcp(m, cp)[:, None], 0, 1)
        up = dn > 0
        rh = np.where(up, rho(p_a, p_d, azim_f(kaq, d1)), rho(p_b, p_d, azim_f(kbq, -d1)))
        wgt = np.where(valid, w * bal * rh * c1 * (mm + 1) / (2 * np.pi) * p2 / (4 * inner), 0)
        rs1, rp1 = fres(c1)
        rs2, rp2 = fres(np.clip(vn / 2, 0, 1))
        # unpolarized two-facet M00 = |J|_F^2 / 2: the plane rotation between facets is the
        # angle between s1 and s2 (both _|_ d1)
        s1 = np.cross(kaq, d1)
        s1 /= np.maximum(np.linalg.norm(s1, axis=-1, keepdims=True), 1e-300)
        s2 = np.cross(-d1, kbq)
        s2 /= np.maximum(np.linalg.norm(s2, axis=-1, keepdims=True), 1e-300)
        ca2 = np.sum(s1 * s2, -1) ** 2
        sa2 = 1 - ca2
        a1s, a1p = np.abs(rs1) ** 2, np.abs(rp1) ** 2
        a2s, a2p = np.abs(rs2) ** 2, np.abs(rp2) ** 2
        m00 = 0.5 * (a2s * (ca2 * a1s + sa2 * a1p) + a2p * (sa2 * a1s + ca2 * a1p))
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
    t_jax = median_time(f, *args, repeats=3)
    err = float(np.max(np.abs(np_m00 / jax_m00 - 1)))
    return dict(
        n=n,
        order=order,
        numpy_evals_per_s=n / t_np,
        jax_f64_evals_per_s=n / t_jax,
        max_rel_diff=err,
    )


def full_brdf_throughput(n, repeats):
    from ppr.brdf import mueller_brdf

    rng = np.random.default_rng(3)
    k, kp = geometry(rng, n)
    out = []
    for terms in (("single",), ("single", "multiple"), ("single", "double", "multiple")):

        @jax.jit
        def f(k, kp, m, terms=terms):
            z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], k.dtype), k.shape)
            mat = Material(n=jnp.complex64(0.94 + 6.42j), m=m)
            return mueller_brdf(k, kp, z, mat, terms=terms)

        args = (
            jnp.asarray(k, jnp.float32),
            jnp.asarray(kp, jnp.float32),
            jnp.full((n,), 3.0, jnp.float32),
        )
        t = median_time(f, *args, repeats=repeats)
        out.append(dict(terms="+".join(terms), evals_per_s=n / t))
        print(out[-1])
    return out


def write(acc, thr, nprow, full, path_md, path_png, path_thr, meta):
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
        "| order (n_u, n_phi) | paths | err_full max | err_full p95 "
        "| rel. err M00_double median | p95 | "
        + " | ".join(f"err_full m={x:g}" for x in MS)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(MS),
    ]
    for r in acc:
        o = r["order"]
        if o == REF_CHECK_ORDER:
            continue
        lines.append(
            f"| {o} | {n_paths(o)} | {r['err_full']:.2e} | {r['err_full_p95']:.2e} | "
            f"{r['rel00_med']:.2e} | "
            f"{r['rel00_p95']:.2e} | " + " | ".join(f"{r['per_m'][x]:.1e}" for x in MS) + " |"
        )
    chk = [r for r in acc if r["order"] == REF_CHECK_ORDER]
    if chk:
        lines += [
            "",
            f"Reference self-convergence: order {REF_CHECK_ORDER} ({n_paths(REF_CHECK_ORDER)} "
            f"paths) against the reference {REF_ORDER}: err_full max {chk[0]['err_full']:.1e}, "
            f"p95 {chk[0]['err_full_p95']:.1e}.",
        ]
    lines += [
        "",
        f"## Error vs evaluations/s (double term alone, jit, one call of N = {meta['n']} pairs, "
        f"m = 3, Al; median of {meta['repeats']} after warm-up; {meta['cores']} cores)",
        "",
        "| order | paths | err_full max | evals/s float32 | evals/s float64 |",
        "|---|---|---|---|---|",
    ]
    acc_by = {r["order"]: r for r in acc}
    thr_by = {(r["dtype"], r["order"]): r["evals_per_s"] for r in thr}
    for o in sorted(({r["order"] for r in thr} | set(acc_by)) - {REF_CHECK_ORDER}, key=n_paths):
        e = f"{acc_by[o]['err_full']:.2e}" if o in acc_by else "-"
        f32 = thr_by.get(("float32", o))
        f64 = thr_by.get(("float64", o))
        lines.append(
            f"| {o} | {n_paths(o)} | {e} | "
            + " | ".join(f"{x:.3g}" if x else "-" for x in (f32, f64))
            + " |"
        )
    tl = [
        "# Double-bounce term and full-BRDF throughput",
        "",
        f"Command: `{meta['command']}`. N = {meta['n']} (k, k') pairs per call, jit, median of "
        f"{meta['repeats']} after warm-up, block_until_ready; {meta['cores']} cores. "
        f"Default order {DEFAULT_ORDER} = {n_paths(DEFAULT_ORDER)} paths.",
        "",
        "## Double term alone (m = 3, Al)",
        "",
        "| dtype | order | paths | evals/s |",
        "|---|---|---|---|",
    ]
    for r in thr:
        tl.append(
            f"| {r['dtype']} | {r['order']} | {n_paths(r['order'])} | {r['evals_per_s']:.3g} |"
        )
    if nprow:
        tl += [
            "",
            f"NumPy (same nodes built independently, M00 only, float64, {nprow['n']} pairs, one "
            f"call) at order {nprow['order']}: {nprow['numpy_evals_per_s']:.3g} evals/s; JAX "
            f"float64 full 4x4 (incoherent): {nprow['jax_f64_evals_per_s']:.3g} evals/s; ratio "
            f"JAX/NumPy = {nprow['jax_f64_evals_per_s'] / nprow['numpy_evals_per_s']:.1f}; max "
            f"rel. diff of M00 {nprow['max_rel_diff']:.1e}.",
        ]
    if full:
        tl += [
            "",
            f"## Full BRDF `mueller_brdf` (float32, default order {DEFAULT_ORDER}, m = 3, Al)",
            "",
            "| terms | evals/s |",
            "|---|---|",
        ]
        for r in full:
            tl.append(f"| {r['terms']} | {r['evals_per_s']:.3g} |")
    lines += ["", "Throughput details, NumPy ratio, full BRDF: double_throughput.md."]
    with open(path_thr, "w") as fh:
        fh.write("\n".join(tl) + "\n")
    print("\n".join(tl))
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
                if r["dtype"] != dt or r["order"] == REF_CHECK_ORDER:
                    continue
                a = [x for x in acc if x["order"] == r["order"]]
                if not a:
                    continue
                xs.append(r["evals_per_s"])
                ys.append(a[0]["err_full"])
                labs.append(r["order"])
            ax.loglog(xs, ys, mk, label=dt)
            for x, y, lab in zip(xs, ys, labs, strict=True):
                ax.annotate(f"{lab[0]}x{lab[1]}", (x, y), fontsize=7)
        ax.axhline(1e-3, color="gray", lw=0.8)
        ax.set_xlabel(f"double-term evaluations / s (N = {meta['n']}, {meta['cores']} cores)")
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
    ap.add_argument("--n-numpy", type=int, default=2000)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-full", action="store_true")
    args = ap.parse_args()
    os.makedirs(OUT, exist_ok=True)
    acc = accuracy(quick=args.quick)
    thr = throughput(args.n, args.repeats, quick=args.quick)
    nprow = numpy_ratio(DEFAULT_ORDER, n=args.n_numpy)
    print(nprow)
    full = None if args.no_full else full_brdf_throughput(args.n, args.repeats)
    write(
        acc,
        thr,
        nprow,
        full,
        os.path.join(OUT, "double_quadrature.md"),
        os.path.join(OUT, "double_quadrature.png"),
        os.path.join(OUT, "double_throughput.md"),
        dict(
            n=args.n,
            repeats=args.repeats,
            cores=os.cpu_count(),
            command=".venv/bin/python bench/bench_double.py " + " ".join(sys.argv[1:]),
        ),
    )


if __name__ == "__main__":
    main()
