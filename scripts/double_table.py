"""Double-bounce tables: (1) the white albedo of the runtime double term (used by
scripts/make_albedo_tables.py), (2) the measured "where does the double term matter" table
behind terms="auto", (3) the energy of the coherent backscatter cone.

    .venv/bin/python scripts/double_table.py --matter   # writes docs/double_bounce_table.md + PNG
    .venv/bin/python scripts/double_table.py --cone     # prints the table of (3) (~8 min)

(1) :func:`e_double_hv`: ``E_double(m, mu) = int M00_double(white, incoherent, default order)
(k'.n) d omega'`` by the half-vector rule of :func:`ppr.brdf.albedo.albedo_nodes` (HV_PHI x HV_W),
which resolves the double lobe at every m (at large m it sits next to the mirror direction: two
small facet tilts; at small m the rule covers the whole hemisphere). The deficit tables of the
multiple-scattering remainder are built by scripts/make_albedo_tables.py, which uses it for the
closure of the runtime double term's quadrature error (docs/physics/multiple_scattering.md).

(2) Relative contribution of the double term to the full BRDF vs bistatic angle and m,
maximized over incidence 0-80 deg and the bistatic azimuth, for aluminium, TiO2 paint
and fused silica: ``r00 = M00_double / M00_total`` and ``dDI = |DI(total) - DI(total
without double)|`` (depolarization index).

(3) ``C = int (M00 - M00_incoherent) (k'.n) d omega'``, the directional albedo the coherent
cone adds (``M - M_inc = gamma (M_coh - M_inc)``), against the double term's incoherent albedo
``E``, for every finish of configs/materials.toml, the ideal white reflector, aluminium and TiO2
paint, at 532 and 1064 nm and incidence 0-80 deg (float64; :func:`cone_energy`). Results and
convergence: docs/physics/double_bounce.md ("What the cone does not do").
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from ppr.brdf import albedo  # noqa: E402
from ppr.brdf.double import DEFAULT_ORDER, double_bounce_term  # noqa: E402
from ppr.materials import Material  # noqa: E402
from ppr.optics import default_frame  # noqa: E402

N_MU, N_PHI = 20, 16  # k' product rule of :func:`kprime_nodes` (tests, broad lobes)
HV_PHI, HV_W = 20, 10  # half-vector rule of ppr.brdf.albedo.albedo_nodes for the albedo table
CHUNK = 4096  # k' evaluations per jitted call (one compilation)


def kprime_nodes(n_mu=N_MU, n_phi=N_PHI):
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu = 0.5 * (x + 1)
    wmu = 0.5 * w
    xp, wp = np.polynomial.legendre.leggauss(n_phi)
    ph = 0.5 * np.pi * (xp + 1)
    wph = 0.5 * np.pi * wp * 2.0  # phi' in [0, pi], doubled by mirror symmetry
    MU, PH = np.meshgrid(mu, ph, indexing="ij")
    s = np.sqrt(1 - MU**2)
    kp = np.stack([s * np.cos(PH), s * np.sin(PH), MU], -1).reshape(-1, 3)
    wt = (wmu[:, None] * wph[None, :] * MU).reshape(-1)
    return kp, wt


@functools.cache
@functools.cache
def _white_double(order):
    """One jitted program per quadrature order (cached: every call of :func:`_eval_pairs`
    with the same order reuses its compilation)."""

    @jax.jit
    def f(k, kp, m):
        z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), k.shape)
        mat = Material.ideal_white(m)
        M = double_bounce_term(
            k, kp, z, mat, default_frame(-k, z), default_frame(kp, z), order=order, coherent=False
        )
        return M[..., 0, 0]

    return f


def _eval_pairs(k, kp, m, order):
    """M00 of the white incoherent double term for rows of (k, k', m), in fixed-size chunks."""
    f = _white_double(order)
    n = len(m)
    out = np.empty(n)
    for s in range(0, n, CHUNK):
        e = min(s + CHUNK, n)
        pad = CHUNK - (e - s)
        kk = np.concatenate([k[s:e], np.repeat(k[:1], pad, 0)])
        kq = np.concatenate([kp[s:e], np.repeat(kp[:1], pad, 0)])
        mm = np.concatenate([m[s:e], np.repeat(m[:1], pad)])
        v = f(jnp.asarray(kk), jnp.asarray(kq), jnp.asarray(mm))
        out[s:e] = np.asarray(v)[: e - s]
    return out


def e_double_hv(m_vals, mu_vals, order=DEFAULT_ORDER, n_phi=HV_PHI, n_w=HV_W):
    """``E_double(m, mu)`` by the half-vector rule of :func:`ppr.brdf.albedo.albedo_nodes`
    (adapted to the double lobe too: at large m it sits near the mirror direction; at small m
    the rule covers the whole hemisphere)."""
    m_vals = np.asarray(m_vals, float)
    mu_vals = np.maximum(np.asarray(mu_vals, float), 1e-9)
    k_in, k_out, wt = albedo.albedo_nodes(m_vals, mu_vals, n_phi, n_w)  # (N,3) (N,Q,3) (N,Q)
    Q = k_out.shape[-2]
    kk = np.repeat(k_in[:, None, :], Q, 1).reshape(-1, 3)
    v = _eval_pairs(kk, k_out.reshape(-1, 3), np.repeat(m_vals, Q), order)
    return np.sum(v.reshape(-1, Q) * wt, -1)


def e_double(m_vals, mu_vals, order=DEFAULT_ORDER, n_mu=N_MU, n_phi=N_PHI, chunk=16):
    """``E_double`` by the k' product rule (broad lobes, small m only)."""
    kp, wt = kprime_nodes(n_mu, n_phi)
    Q = len(kp)
    m_vals = np.asarray(m_vals, float)
    mu = np.maximum(np.asarray(mu_vals, float), 1e-9)
    k = np.stack([np.sqrt(1 - mu**2), np.zeros_like(mu), mu], -1)
    kk = np.repeat(k[:, None, :], Q, 1).reshape(-1, 3)
    kpp = np.broadcast_to(kp[None], (len(mu), Q, 3)).reshape(-1, 3)
    v = _eval_pairs(kk, kpp, np.repeat(m_vals, Q), order)
    return np.sum(v.reshape(-1, Q) * wt, -1)


MS = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)
PSIS = (0.0, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 30.0)
THETAS = (0.0, 20.0, 40.0, 60.0, 80.0)
AZ = (0.0, 90.0, 180.0)
MATS = (("Al", 0.94 + 6.42j), ("TiO2", 2.67 + 0j), ("silica", 1.461 + 0j))


def measure_matter_table(out_dir):
    from ppr import depolarization_index
    from ppr.brdf import mueller_brdf
    from ppr.brdf.double import AUTO_TOL

    rows = []
    for th in THETAS:
        for psi in PSIS:
            for az in AZ:
                t = np.deg2rad(th)
                k = np.array([np.sin(t), 0.0, np.cos(t)])
                # rotate k by psi toward direction at azimuth az in the plane _|_ k
                a = np.deg2rad(az)
                e1 = np.array([np.cos(t), 0.0, -np.sin(t)]) if th > 0 else np.array([1.0, 0, 0])
                e2 = np.cross(k, e1)
                p = np.deg2rad(psi)
                kp = np.cos(p) * k + np.sin(p) * (np.cos(a) * e1 + np.sin(a) * e2)
                if kp[2] < 1e-3:
                    continue
                rows.append((th, psi, az, k, kp / np.linalg.norm(kp)))
    K = np.stack([r[3] for r in rows])
    KP = np.stack([r[4] for r in rows])

    @jax.jit
    def f(k, kp, n, m):
        mat = Material(n=n, m=m)
        zz = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), k.shape)
        tot = mueller_brdf(k, kp, zz, mat, terms=("single", "double", "multiple"))
        nod = mueller_brdf(k, kp, zz, mat, terms=("single", "multiple"))
        return tot, nod

    res = {}
    for _mname, n in MATS:
        for m in MS:
            tot, nod = f(jnp.asarray(K), jnp.asarray(KP), jnp.full(len(K), n), jnp.full(len(K), m))
            tot, nod = np.asarray(tot), np.asarray(nod)
            r00 = (tot[:, 0, 0] - nod[:, 0, 0]) / tot[:, 0, 0]
            ddi = np.abs(
                np.asarray(depolarization_index(tot)) - np.asarray(depolarization_index(nod))
            )
            for i, (_th, psi, _az, _, _) in enumerate(rows):
                key = (m, psi)
                r = res.setdefault(key, [0.0, 0.0])
                r[0] = max(r[0], float(abs(r00[i])))
                r[1] = max(r[1], float(ddi[i]))
    # the rule: smallest m of the grid above which every (m', psi) stays below AUTO_TOL
    worst_m = {m: max(max(res[(m, p)]) for p in PSIS) for m in MS}
    m_ok = [m for m in MS if all(worst_m[mm] < AUTO_TOL for mm in MS if mm >= m)]
    m_rule = min(m_ok) if m_ok else float("inf")
    lines = [
        "# Where does the double-bounce term matter?",
        "",
        "Measured by `scripts/double_table.py --matter` with the default quadrature order.",
        "Each cell: max over incidence (" + ", ".join(f"{x:g}" for x in THETAS) + " deg), bistatic "
        "azimuth (" + ", ".join(f"{x:g}" for x in AZ) + " deg) and material (aluminium 532 nm, "
        "TiO2 paint, fused silica) of `r00 = |M00_double| / M00_total` / "
        "`dDI = |DI(total) - DI(total without double)|` (DI: depolarization index).",
        "",
        "| m \\ psi [deg] | " + " | ".join(f"{p:g}" for p in PSIS) + " |",
        "|---|" + "---|" * len(PSIS),
    ]
    for m in MS:
        lines.append(
            f"| {m:g} | "
            + " | ".join(f"{res[(m, p)][0]:.1e} / {res[(m, p)][1]:.1e}" for p in PSIS)
            + " |"
        )
    lines += [
        "",
        f'Rule for `terms="auto"` (tolerance AUTO_TOL = {AUTO_TOL:g} on both measures): '
        f"the double term matters for every m below {m_rule:g}; above it, both measures stay below "
        f"the tolerance at every geometry of the table (worst: "
        + ", ".join(f"m={m:g}: {worst_m[m]:.1e}" for m in MS)
        + "). The bistatic angle does not make the term negligible for rough surfaces "
        "(the incoherent double lobe is broad); only the coherent peak decays with psi. "
        "Near backscatter a double path needs two facets tilted ~45 deg (weight "
        "cos^m(45 deg)^2 = 2^-m), hence the sharp drop between m = 10 and 30. The table covers "
        "bistatic angles up to 30 deg only: at larger angles (toward the specular direction) "
        "the double term of moderately rough surfaces can be large (e.g. 0.1 /sr at m = 20, "
        "incidence 60 deg, exit 40 deg on the far side), so the rule keeps it there "
        "(ppr.brdf.double.AUTO_PSI_MAX). Large m (>= 1000) reads 0 partly because the default "
        "quadrature does not resolve the double lobe there (bench/results/double_quadrature.md).",
    ]
    os.makedirs(out_dir, exist_ok=True)
    md = os.path.join(out_dir, "double_bounce_table.md")
    with open(md, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
        for j, name in enumerate(["r00 = M00_double / M00_total", "dDI"]):
            ax = axes[j]
            for m in MS:
                ax.semilogy(
                    PSIS, [max(res[(m, p)][j], 1e-12) for p in PSIS], "o-", label=f"m={m:g}"
                )
            ax.axhline(AUTO_TOL, color="gray", lw=0.8)
            ax.set_xlabel("bistatic angle [deg]")
            ax.set_ylabel(name + " (max over geometry, material)")
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "double_bounce_table.png"), dpi=110)
    except Exception as err:  # pragma: no cover
        print("plot failed", err)
    return m_rule


CONE_ORDER = (8, 32)  # double-term quadrature order of --cone (checked against (16, 64))
CONE_THETAS = (0.0, 30.0, 60.0, 80.0)
CONE_MATERIALS = (None, "aluminium", "white_paint_tio2")  # None: the ideal white reflector
CONE_WAVELENGTHS = (532e-9, 1064e-9)
CONE_N_PSI, CONE_N_PHI, CONE_SPAN = 24, 16, 5.0  # polar rule about k: psi in [0, 5 psi_h]
CONE_HV = (10, 5)  # half-vector rule (n_phi, n_w) of the albedo


@functools.cache
def _double00(order, white):
    """M00 of the double term, coherent and incoherent, for rows of (k, k', n, m, d, lambda)
    (normal +z): one jitted program per (order, white)."""

    @jax.jit
    def f(k, kp, n, m, d, lam):
        z = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), k.shape)
        mat = Material(n=n, m=m, corr_length=d, white=white)
        fi, fo = default_frame(-k, z), default_frame(kp, z)
        coh = double_bounce_term(k, kp, z, mat, fi, fo, wavelength=lam, order=order)
        inc = double_bounce_term(k, kp, z, mat, fi, fo, order=order, coherent=False)
        return coh[..., 0, 0], inc[..., 0, 0]

    return f


def _eval_double00(k, kp, n, m, d, lam, order, white):
    """(coherent, incoherent) M00 for rows of inputs, in fixed-size chunks (one compilation)."""
    f = _double00(order, white)
    rows = [np.asarray(x) for x in (k, kp, n, m, d, lam)]
    size = len(rows[0])
    out = np.empty((2, size))
    for s in range(0, size, CHUNK):
        e = min(s + CHUNK, size)
        pad = CHUNK - (e - s)
        args = [jnp.asarray(np.concatenate([x[s:e], np.repeat(x[:1], pad, 0)])) for x in rows]
        coh, inc = f(*args)
        out[0, s:e] = np.asarray(coh)[: e - s]
        out[1, s:e] = np.asarray(inc)[: e - s]
    return out


def cone_nodes(theta, psi_h, n_psi=CONE_N_PSI, n_phi=CONE_N_PHI, span=CONE_SPAN):
    """Outgoing directions about ``k`` (incidence ``theta``, normal +z, ``k`` in the x-z
    plane) and weights ``w`` with ``int g(k') d omega' ~= sum w g``: Gauss-Legendre in the
    bistatic angle ``psi`` on ``[0, span psi_h]`` (``gamma < 1e-7`` beyond), the periodic
    trapezoid rule in its azimuth."""
    x, wx = np.polynomial.legendre.leggauss(n_psi)
    top = min(span * psi_h, np.pi / 2)
    psi, wpsi = 0.5 * top * (x + 1.0), 0.5 * top * wx * np.sin(0.5 * top * (x + 1.0))
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    k = np.array([np.sin(theta), 0.0, np.cos(theta)])
    e1 = np.array([np.cos(theta), 0.0, -np.sin(theta)])
    e2 = np.cross(k, e1)
    P, F = np.meshgrid(psi, phi, indexing="ij")
    kp = (
        np.cos(P)[..., None] * k
        + np.sin(P)[..., None] * (np.cos(F)[..., None] * e1 + np.sin(F)[..., None] * e2)
    ).reshape(-1, 3)
    w = (wpsi[:, None] * np.full(n_phi, 2.0 * np.pi / n_phi)[None, :]).reshape(-1)
    return k, kp, w


def cone_energy(cases, order=CONE_ORDER, hv=CONE_HV):
    """Energy of the coherent backscatter cone and the double term's albedo.

    ``cases``: tuples ``(m, d, n, lambda, theta, white)`` (``theta`` the incidence in rad).
    Per case, ``C = int (M00 - M00_incoherent) (k'.n) d omega'`` by :func:`cone_nodes` (the
    interference term ``gamma (M_coh - M_inc)`` lives inside ``~5 psi_h``),
    ``E = int M00_incoherent (k'.n) d omega'`` by the half-vector rule of
    :func:`ppr.brdf.albedo.albedo_nodes`, and the small-cone estimate
    ``C0 = M00_inc(k, k) cos(theta) pi psi_h^2 / ln 2`` (``M_coh = 2 M_inc`` at ``psi = 0``).
    All cases with the same ``white`` are evaluated in one chunked pass. Returns an array of
    ``(C, E, C0)`` rows."""
    out = np.zeros((len(cases), 3))
    for white in (True, False):
        idx = [i for i, c in enumerate(cases) if c[5] == white]
        if not idx:
            continue
        parts, spans = [], []
        for i in idx:
            m, d, n, lam, theta, _ = cases[i]
            k, kp, w = cone_nodes(theta, lam / (4.0 * d))
            mu = max(np.cos(theta), 1e-9)
            k_in, k_out, wt = albedo.albedo_nodes(np.array([m]), np.array([mu]), *hv)
            kk = np.concatenate([np.repeat(k[None], len(kp) + 1, 0)] + [k_in] * k_out.shape[-2])
            kq = np.concatenate([kp, k[None], k_out.reshape(-1, 3)])
            parts.append(
                (
                    kk,
                    kq,
                    np.full(len(kk), n, complex),
                    np.full(len(kk), float(m)),
                    np.full(len(kk), d),
                    np.full(len(kk), lam),
                )
            )
            spans.append((w, wt.reshape(-1), len(kp)))
        cols = [np.concatenate([p[j] for p in parts]) for j in range(6)]
        coh, inc = _eval_double00(*cols, order, white)
        a = 0
        for i, (w, wt, q) in zip(idx, spans, strict=True):
            m, d, n, lam, theta, _ = cases[i]
            kp_z = cols[1][a : a + q, 2]
            c = float(np.sum(w * np.maximum(kp_z, 0.0) * (coh[a : a + q] - inc[a : a + q])))
            e = float(np.sum(wt * inc[a + q + 1 : a + q + 1 + len(wt)]))
            c0 = float(inc[a + q] * np.cos(theta) * np.pi * (lam / (4 * d)) ** 2 / np.log(2.0))
            out[i] = (c, e, c0)
            a += q + 1 + len(wt)
    return out


def measure_cone(order=CONE_ORDER, hv=CONE_HV):
    """Print the coherent-cone energy relative to the double term's albedo for the library
    finishes (``configs/materials.toml``), materials and both laser lines (float64)."""
    from ppr.materials import load_library, load_material

    finishes = load_library().finishes
    t0 = time.perf_counter()
    keys, cases = [], []
    for fname, fin in finishes.items():
        for mat in CONE_MATERIALS:
            for lam in CONE_WAVELENGTHS:
                if mat is None:
                    n, white, label = 1.0 + 0j, True, "ideal white"
                else:
                    n = complex(np.asarray(load_material(mat, lam, fname).n))
                    white, label = False, mat
                for t in CONE_THETAS:
                    keys.append((fname, fin, label, lam, t))
                    cases.append((fin.m, fin.corr_length, n, lam, np.deg2rad(t), white))
    res = cone_energy(cases, order, hv)
    lines = [
        "| finish (m, d) | material | lambda [nm] | psi_h [deg] | "
        + " | ".join(f"C/E at {t:g} deg" for t in CONE_THETAS)
        + " | max C | max E |",
        "|---|---|---|---|" + "---|" * len(CONE_THETAS) + "---|---|",
    ]
    dev = 0.0
    nt = len(CONE_THETAS)
    for a in range(0, len(keys), nt):
        fname, fin, label, lam, _ = keys[a]
        r = res[a : a + nt]
        ratio = [c / e if e > 0 else 0.0 for c, e, _ in r]
        for c, e, c0 in r:
            if c > 1e-6 * e:  # C0 is the small-cone limit: compare where C is not negligible
                dev = max(dev, abs(c0 / c - 1.0))
        lines.append(
            f"| {fname} ({fin.m:g}, {fin.corr_length * 1e6:g} um) | {label} | "
            f"{lam * 1e9:.0f} | {np.rad2deg(lam / (4 * fin.corr_length)):.3g} | "
            + " | ".join(f"{x:.1e}" for x in ratio)
            + f" | {r[:, 0].max():.1e} | {r[:, 1].max():.2g} |"
        )
    print(
        f"C: cone energy, E: double-term albedo (incoherent), both per unit incident flux; "
        f"double-term order {order}, cone rule {CONE_N_PSI} x {CONE_N_PHI} on psi <= "
        f"{CONE_SPAN:g} psi_h, half-vector rule {hv}; small-cone estimate C0 within "
        f"{dev:.0%} of C where C > 1e-6 E; {time.perf_counter() - t0:.0f} s\n"
    )
    print("\n".join(lines))
    return keys, res


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--matter", action="store_true")
    ap.add_argument("--cone", action="store_true")
    args = ap.parse_args(argv)
    if args.matter:
        measure_matter_table(os.path.join(ROOT, "docs"))
    if args.cone:
        measure_cone()


if __name__ == "__main__":
    main()
