"""Benchmark of the facet-sum pulse synthesis (issue 4).

1. Poses per second of ``ppr.render`` (16 Mueller channels x 256 bins, float32) for a ~1k and a
   ~14k facet CubeSat-with-panels mesh, batched with ``jax.vmap``; visibility (Embree ray casts
   on the host) excluded from poses/s and reported separately. The range kernel is timed
   with the Lambertian stand-in BRDF next to a plain NumPy (+ scipy.special.erfc)
   implementation of the same windowed algorithm in this process, and end to end with the
   real ``ppr.mueller_brdf``.
2. Error against run time for the visibility sub-sampling count (samples per face) and for
   facet subdivision (icosphere vs the analytic Lambertian sphere profile; subdivided
   panels vs a finely sampled reference).

Writes ``bench/results/pulse_bench.md`` and ``bench/results/pulse_bench.png``.
Run: ``.venv/bin/python bench/bench_pulse.py`` (about 1-2 minutes on 2 idle cores).
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import median_time
from scipy import integrate, special, stats

import ppr
from ppr import shapes
from ppr.geometry import n_normal_groups
from ppr.materials import stack_materials
from ppr.optics.conventions import C_LIGHT
from ppr.pulse import (
    NSIG,
    lambertian_mueller,
    render,
    visible_faces,
    window_size,
)

OUT = Path(__file__).resolve().parent / "results"
N_BINS, WIDTH = 256, 0.005
SIGMA_R = 0.5 * C_LIGHT * math.hypot(100e-12 / 2.3548200450309493, 20e-12)
BATCH = 8  # vmap batch: the dense (F, n_bins) placement matrix is per pose (memory)


def random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ----------------------------------------------------------------------------- NumPy reference


def _np_q(u, c, p):
    return (u * u + 1.0) * c + u * p


def np_tent_cdf(x, d0, d1, d2, sigma, tau=0.25, tau1=0.5):
    """NumPy port of ppr.pulse.tent_gaussian_cdf (float32 thresholds)."""
    inv = 1.0 / sigma
    g01, g12 = (d1 - d0) * inv, (d2 - d1) * inv
    left = x <= (d0 + d1 + d2) / 3.0
    sg = np.where(left, 1.0, -1.0).astype(x.dtype)
    us = [sg * (x - d) * inv for d in (d0, d1, d2)]
    cdf = [0.5 * special.erfc(-u / math.sqrt(2)) for u in us]
    pdf = [np.exp(-0.5 * u * u) / math.sqrt(2 * math.pi) for u in us]
    q = [_np_q(u, c, p) for u, c, p in zip(us, cdf, pdf, strict=True)]
    u0, u1, u2 = us
    u = u1
    c, p = cdf[1], pdf[1]
    he = [1.0, u, u * u - 1, u**3 - 3 * u, u**4 - 6 * u * u + 3, u**5 - 10 * u**3 + 15 * u]
    d = [2 * (u * c + p), 2 * c] + [2 * (-1.0) ** j * he[j] * p for j in range(6)]
    e0, e2 = u0 - u1, u2 - u1
    fact = [math.factorial(k) for k in range(9)]

    def first(e):
        return sum(d[k - 1] * e ** (k - 1) / fact[k] for k in range(1, 9))

    with np.errstate(divide="ignore", invalid="ignore"):
        dd01 = np.where(g01 < tau1, first(e0), (q[0] - q[1]) / (u0 - u1))
        dd12 = np.where(g12 < tau1, first(e2), (q[1] - q[2]) / (u1 - u2))
        direct = (dd01 - dd12) / (u0 - u2)
    h = [np.ones_like(e0)]
    for j in range(1, 7):
        h.append(e0**j + e2 * h[-1])
    series = sum(d[k - 1] * h[k - 2] / fact[k] for k in range(2, 9))
    val = np.where((g01 + g12) < tau, series, direct)
    return np.where(left, val, 1.0 - val)


def np_render(tri, normals, areas, vis, q, u, window):
    """Plain NumPy render of the Lambertian stand-in, 16 channels, same windowed algorithm."""
    rot = np.asarray(ppr.quat_to_matrix(q), np.float32)
    ub = rot.T @ u
    cos = normals @ ub
    front = (cos > 1e-6) & (vis > 0)
    wgt = np.where(front, cos * cos * areas * vis, 0.0).astype(np.float32)
    mueller = np.zeros(16, np.float32)
    mueller[0] = 1 / np.pi
    wch = wgt[:, None] * mueller[None, :]  # (F, 16)
    depth = np.sort(-(tri @ ub), axis=1)
    d0, d1, d2 = depth[:, :1], depth[:, 1:2], depth[:, 2:3]
    start = -0.5 * WIDTH * N_BINS
    j0 = np.floor((d0 - NSIG * SIGMA_R - start) / WIDTH).astype(np.int64)
    j = j0 + np.arange(window + 1)[None, :]
    edges = (start + j * WIDTH).astype(np.float32)
    cdf = np_tent_cdf(edges, d0, d1, d2, np.float32(SIGMA_R))
    dc = np.diff(cdf, axis=1)
    bins = j[:, :-1]
    ok = (bins >= 0) & (bins < N_BINS)
    dense = np.zeros((tri.shape[0], N_BINS), np.float32)
    rows = np.broadcast_to(np.arange(tri.shape[0])[:, None], bins.shape)
    np.add.at(dense, (rows[ok], bins[ok]), dc[ok])
    return wch.T @ dense


# ----------------------------------------------------------------------------- throughput


def throughput(mesh, label):
    sensor = ppr.Sensor.make((0, 0, -1.0))
    u = np.array([0, 0, 1.0])
    arrays = ppr.mesh_arrays(mesh, dtype=jnp.float32)
    cap = arrays.valid.shape[0]
    qs = random_quats(BATCH, 1)
    caster = ppr.VisibilityCaster(mesh, 16)
    caster.fractions(u)  # warm-up: Embree builds its BVH on the first query
    t0 = time.perf_counter()
    vis = []
    for q in qs:
        rot = np.asarray(ppr.quat_to_matrix(q))
        vis.append(caster.fractions(rot.T @ u))
    t_vis = (time.perf_counter() - t0) / BATCH
    vis_p = np.zeros((BATCH, cap), np.float32)
    vis_p[:, : mesh.n_faces] = np.asarray(vis)
    # pruning: per-pose indices of the lit-and-visible facets, one padded capacity per batch
    n_vis = int((vis_p > 0).sum(1).max())
    fcap = ppr.geometry.capacity_for(n_vis)
    faces = np.stack([visible_faces(v, fcap) for v in vis_p])
    window = window_size(mesh.max_edge(), SIGMA_R, WIDTH, N_BINS)
    mats = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.complex64 if jnp.iscomplexobj(a) else jnp.float32),
        stack_materials(
            [
                ppr.Material(0.94 + 6.42j, 200.0),
                ppr.Material(1.46 + 0j, 2000.0),
                ppr.Material(2.67 + 0j, 5.0),
            ]
        ),
    )
    sensor32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), sensor)
    rows = []
    from ppr.brdf import mueller_brdf

    for brdf_name, brdf in (
        ("lambertian stand-in", lambertian_mueller),
        ("ppr.mueller_brdf", mueller_brdf),
    ):

        def one(q, v, f, brdf=brdf):
            return render(
                arrays,
                v,
                ppr.Pose(q),
                mats,
                sensor32,
                SIGMA_R,
                -0.5 * WIDTH * N_BINS,
                WIDTH,
                n_bins=N_BINS,
                window=window,
                brdf=brdf,
                faces=f,
            )

        batched = jax.jit(jax.vmap(one))
        single = jax.jit(one)
        qj = jnp.asarray(qs, jnp.float32)
        vj = jnp.asarray(vis_p)
        fj = jnp.asarray(faces)
        t = time.perf_counter()
        batched(qj, vj, fj).block_until_ready()
        t_compile = time.perf_counter() - t
        t_batch = median_time(
            lambda qj=qj, vj=vj, fj=fj, b=batched: b(qj, vj, fj).block_until_ready(), repeats=5
        )
        t_single = (
            median_time(
                lambda qj=qj, vj=vj, fj=fj, s1=single: [
                    s1(qj[i], vj[i], fj[i]).block_until_ready() for i in range(BATCH)
                ],
                repeats=3,
            )
            / BATCH
        )
        for mode, tp in ((f"vmap {BATCH}", t_batch / BATCH), ("single calls", t_single)):
            rows.append(
                dict(
                    mesh=label,
                    faces=mesh.n_faces,
                    impl=f"JAX {mode}, {brdf_name}",
                    per_pose_ms=1e3 * tp,
                    poses_s=1 / tp,
                    compile_s=t_compile,
                )
            )

    # NumPy reference (Lambertian), fewer poses
    tri = mesh.triangles().astype(np.float32)
    _, nrm = ppr.geometry.face_areas_normals(mesh.triangles())
    areas = ppr.geometry.face_areas_normals(mesh.triangles())[0].astype(np.float32)
    nrm = nrm.astype(np.float32)
    n_np = 4
    t_np = (
        median_time(
            lambda: [
                np_render(tri, nrm, areas, np.asarray(vis[i], np.float32), qs[i], u, window)
                for i in range(n_np)
            ],
            repeats=3,
        )
        / n_np
    )
    # check agreement of the two implementations (float32)
    ref = np_render(tri, nrm, areas, np.asarray(vis[0], np.float32), qs[0], u, window)
    got = np.asarray(
        render(
            arrays,
            jnp.asarray(vis_p[0]),
            ppr.Pose(jnp.asarray(qs[0], jnp.float32)),
            mats,
            sensor32,
            SIGMA_R,
            -0.5 * WIDTH * N_BINS,
            WIDTH,
            n_bins=N_BINS,
            window=window,
            brdf=lambertian_mueller,
        )
    )
    err = float(np.abs(got - ref).max() / np.abs(ref).max())
    rows.append(
        dict(
            mesh=label,
            faces=mesh.n_faces,
            impl="NumPy, lambertian stand-in",
            per_pose_ms=1e3 * t_np,
            poses_s=1 / t_np,
            compile_s=0.0,
        )
    )
    return rows, t_vis, err, window, fcap


# ----------------------------------------------------------------------------- accuracy vs time


def lambert_profile(mesh, q, samples, n_bins=N_BINS, width=WIDTH):
    sc = ppr.Scene(
        mesh,
        tuple([ppr.Material(1.5, 10.0)] * len(mesh.parts)),
        ppr.Pose(q),
        ppr.Sensor.make((0, 0, -1.0)),
        ppr.Pulse.gaussian(100e-12, 20e-12),
        ppr.RangeBins.centred(width, n_bins, 1e6),
        samples,
    )
    t = time.perf_counter()
    p = ppr.simulate(sc, brdf=lambertian_mueller)
    p.data.block_until_ready()
    return np.asarray(p.data[0, 0], np.float64), time.perf_counter() - t, p


def visibility_sweep():
    mesh = shapes.cubesat_with_panels(3)
    qs = random_quats(6, 7)
    u = np.array([0, 0, 1.0])
    rows = []
    refs = []
    caster_ref = ppr.VisibilityCaster(mesh, 1024)
    tri = mesh.triangles()
    area, nrm = ppr.geometry.face_areas_normals(tri)
    for q in qs:
        rot = np.asarray(ppr.quat_to_matrix(q))
        refs.append(caster_ref.fractions(rot.T @ u))
    for s in (1, 4, 9, 16, 36, 64, 144, 256):
        caster = ppr.VisibilityCaster(mesh, s)
        errs, ts = [], []
        for q, ref in zip(qs, refs, strict=True):
            rot = np.asarray(ppr.quat_to_matrix(q))
            t = time.perf_counter()
            v = caster.fractions(rot.T @ u)
            ts.append(time.perf_counter() - t)
            w = np.clip(nrm @ (rot.T @ u), 0, None) ** 2 * area / np.pi
            errs.append(abs(((v - ref) * w).sum()) / (ref * w).sum())
        rows.append(dict(samples=s, rel_err=float(np.mean(errs)), ms=1e3 * float(np.median(ts))))
    return rows


def sphere_sweep():
    a = 0.3
    r = np.linspace(-a, 0.0, 20001)
    rows = []
    ref = None
    for sub in (1, 2, 3, 4, 5):
        prof, _, p = lambert_profile(shapes.sphere(a, subdivisions=sub), [1.0, 0, 0, 0], 1)
        if ref is None:
            sig = SIGMA_R
            edges = np.asarray(p.edges_m)
            cdf = np.array(
                [
                    integrate.simpson(2 * r**2 / a * stats.norm.cdf((x - r) / sig), x=r)
                    for x in edges
                ]
            )
            ref = np.diff(cdf)
        _, t, _ = lambert_profile(shapes.sphere(a, subdivisions=sub), [1.0, 0, 0, 0], 1)
        rows.append(
            dict(faces=20 * 4**sub, rel_l1=float(np.abs(prof - ref).sum() / ref.sum()), ms=1e3 * t)
        )
    return rows


def panel_subdivision_sweep():
    q = random_quats(1, 3)[0]
    ref, _, _ = lambert_profile(shapes.cubesat_with_panels(3, max_edge=0.0125), q, 16)
    rows = []
    for me in (None, 0.1, 0.05, 0.025):
        mesh = shapes.cubesat_with_panels(3, max_edge=me)
        prof, _, _ = lambert_profile(mesh, q, 16)
        _, t, _ = lambert_profile(mesh, q, 16)
        rows.append(
            dict(
                max_edge=me,
                faces=mesh.n_faces,
                rel_l1=float(np.abs(prof - ref).sum() / ref.sum()),
                ms=1e3 * t,
            )
        )
    return rows


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# Pulse synthesis benchmark (bench/bench_pulse.py)", ""]
    lines.append(
        f"Machine: {os.cpu_count()} cores; jax {jax.__version__}; float32; 16 Mueller "
        f"channels x {N_BINS} bins of {WIDTH * 1e3:g} mm; pulse sigma "
        f"{SIGMA_R * 1e3:.2f} mm (100 ps FWHM + 20 ps jitter); vmap batch {BATCH} poses."
    )
    lines.append(f"Load average at start (machine shared with other jobs): {os.getloadavg()}.")
    lines.append("")
    lines.append("## Throughput (visibility excluded; reported separately)")
    lines.append("")
    lines.append("| mesh | faces | implementation | ms / pose | poses / s | compile s |")
    lines.append("|---|---|---|---|---|---|")
    summary = []
    meshes = (
        (shapes.cubesat_with_panels(3, max_edge=0.08), "~1k"),
        (shapes.cubesat_with_panels(3, max_edge=0.02), "~14k"),
        # every normal distinct: no (normal, part) groups to share BRDF evaluations
        (shapes.sphere(0.3, subdivisions=5), "~20k sphere"),
    )
    for mesh, label in meshes:
        rows, t_vis, err, window, fcap = throughput(mesh, label)
        for r in rows:
            lines.append(
                f"| {r['mesh']} | {r['faces']} | {r['impl']} | {r['per_pose_ms']:.3f} | "
                f"{r['poses_s']:.0f} | {r['compile_s']:.1f} |"
            )
        best = max(r["poses_s"] for r in rows if "lambertian" in r["impl"] and "JAX" in r["impl"])
        ratio = best / rows[-1]["poses_s"]
        summary.append(
            (label, mesh.n_faces, t_vis, ratio, err, window, rows, fcap, n_normal_groups(mesh))
        )
        print(label, rows, f"vis {t_vis * 1e3:.1f} ms/pose", f"JAX/NumPy {ratio:.1f}x", flush=True)
    lines.append("")
    for label, nf, t_vis, ratio, err, window, _, fcap, n_grp in summary:
        gcap = ppr.geometry.capacity_for(n_grp)
        lines.append(
            f"- {label} ({nf} faces, {n_grp} distinct (normal, part) groups, so "
            f"{gcap if gcap < fcap else fcap} BRDF evaluations per pose; pruned per pose to "
            f"{fcap} facet "
            f"slots, window {window} "
            f"bins): JAX/NumPy speed ratio "
            f"{ratio:.1f}x (same algorithm, Lambertian stand-in; max rel. difference "
            f"{err:.1e}); visibility (16 samples/face, Embree) {t_vis * 1e3:.1f} ms/pose."
        )
    lines.append("")
    vrows = visibility_sweep()
    print("vis", vrows, flush=True)
    lines += [
        "## Visibility sub-sampling (CubeSat with panels, 36 faces, 6 random poses)",
        "",
        "Error: |total Lambertian return - reference (1024 samples/face)| / reference.",
        "",
        "| samples / face | mean rel. error | ms / pose |",
        "|---|---|---|",
    ]
    lines += [f"| {r['samples']} | {r['rel_err']:.2e} | {r['ms']:.2f} |" for r in vrows]
    srows = sphere_sweep()
    print("sphere", srows, flush=True)
    lines += [
        "",
        "## Facet subdivision: icosphere (r = 0.3 m) vs analytic Lambertian sphere",
        "",
        "| faces | rel. L1 error of the profile | simulate ms |",
        "|---|---|---|",
    ]
    lines += [f"| {r['faces']} | {r['rel_l1']:.2e} | {r['ms']:.1f} |" for r in srows]
    prows = panel_subdivision_sweep()
    print("panels", prows, flush=True)
    lines += [
        "",
        "## Facet subdivision: CubeSat with panels (partial shadows, 16 samples/face)",
        "",
        "Reference: max edge 12.5 mm.",
        "",
        "| max edge (m) | faces | rel. L1 error | simulate ms |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['max_edge']} | {r['faces']} | {r['rel_l1']:.2e} | {r['ms']:.1f} |" for r in prows
    ]
    (OUT / "pulse_bench.md").write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].loglog([r["ms"] for r in vrows], [max(r["rel_err"], 1e-9) for r in vrows], "o-")
    for r in vrows:
        ax[0].annotate(str(r["samples"]), (r["ms"], max(r["rel_err"], 1e-9)))
    ax[0].set(
        xlabel="visibility ms / pose",
        ylabel="rel. error of total return",
        title="visibility samples per face",
    )
    ax[1].loglog([r["faces"] for r in srows], [r["rel_l1"] for r in srows], "o-", label="error")
    ax[1].set(xlabel="faces", ylabel="rel. L1 error", title="icosphere vs analytic sphere")
    ax2 = ax[1].twinx()
    ax2.semilogx([r["faces"] for r in srows], [r["ms"] for r in srows], "s--", color="C1")
    ax2.set_ylabel("simulate ms (incl. visibility)", color="C1")
    labels = [s[0] for s in summary]
    width = 0.25
    labels_impl = ["JAX, lambertian stand-in", "JAX, ppr.mueller_brdf", "NumPy, lambertian"]
    for k, impl in enumerate(["lambertian stand-in", "ppr.mueller_brdf", "NumPy"]):
        vals = [
            max(
                r["poses_s"]
                for r in s[6]
                if impl in r["impl"] and ("NumPy" in r["impl"]) == (impl == "NumPy")
            )
            for s in summary
        ]
        ax[2].bar(np.arange(len(labels)) + (k - 1) * width, vals, width, label=labels_impl[k])
    ax[2].axhline(200, color="k", ls=":", label="target 200 poses/s")
    ax[2].set_yscale("log")
    ax[2].set_xticks(np.arange(len(labels)), [f"{s[0]} ({s[1]} faces)" for s in summary])
    ax[2].set(ylabel="poses / s (16 ch x 256 bins, f32)", title="throughput")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "pulse_bench.png", dpi=110)
    print((OUT / "pulse_bench.md").read_text())


if __name__ == "__main__":
    sys.exit(main())
