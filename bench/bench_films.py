"""Coated facets (thin-film stacks, ppr/optics/_films.py; docs/physics/thin_films.md): measurements.

1. Thick-film treatments against brute-force lobe averaging: for the library's thick films
   (Kapton over aluminium at 1064 nm, clear, and 532 nm, absorbing; silica over silver at
   532 nm) and Blinn-Phong exponents 10-1e5, the largest error of the facet Mueller parameters
   ``(a, b, c, d)`` over incidence 0-88 deg of ``film_mode`` ``"coherent"``,
   ``"incoherent"`` and ``"lobe"`` (``ppr.facet_mueller_params``) against a NumPy quadrature
   of the lobe average (the lobe mode's model: the thick layer's phase at every tilted facet
   of the exact Blinn-Phong tilt distribution, the interfaces at the nominal facet), with the
   run time per evaluation of each (and of the quadrature). Also: how far that model is from
   averaging the whole reflectance (interfaces too), and the lobe/incoherent difference at
   the rough finishes where the double bounce matters (its quadrature uses the incoherent
   facets, ``ppr.brdf.double.DOUBLE_THICK_MODE``).
2. BRDF throughput (``ppr.mueller_brdf``, float32) with 0, 1, 2 and 4 coherent films and the
   lobe-averaged MLI, against the bare material: single + multiple at random bistatic
   geometries, and every term at exact backscatter.
3. Figure: retardance, diattenuation and depolarization index of one facet against incidence
   for each coated library material and its bare substrate, at 532 and 1064 nm.
4. ``--cubesat``: the coated CubeSat (configs/scenes/cubesat_coated.toml) through
   ``ppr simulate`` and ``ppr image`` (wall time, energies; PNGs copied to bench/results).

Writes ``bench/results/films.md``, ``films_polarimetry.png`` (and with ``--cubesat``
``films_cubesat_simulate.png``, ``films_cubesat_image.png``).
Run: ``.venv/bin/python bench/bench_films.py [--quick] [--cubesat]``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import median_time  # noqa: E402

import ppr  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results"


# ----------------------------------------------------------------------------- 1. treatments


def _w(n, c):
    w = np.sqrt(n * n - 1 + c * c + 0j)
    return np.where(w.imag < 0, -w, w)


def _gram_of_r(rs, rp, wgt):
    W = wgt.sum()
    gss = (abs(rs) ** 2 * wgt).sum() / W
    gpp = (abs(rp) ** 2 * wgt).sum() / W
    gsp = (rs * np.conj(rp) * wgt).sum() / W
    return np.array([0.5 * (gss + gpp), 0.5 * (gss - gpp), gsp.real, gsp.imag])


def brute_params(nf, t, n_sub, lam, m, c0, nu, nphi, full=False):
    """NumPy lobe average of one film on a substrate at facet cosine ``c0``: tilts with
    ``cos beta = u^(1/(m+1))`` (u uniform: the Blinn-Phong density exactly), uniform azimuth,
    back-facing tilts left out. ``full``: the interfaces at the tilted facet too."""
    kt = 2 * math.pi * t / lam
    u = (np.arange(nu) + 0.5) / nu
    cb = u ** (1.0 / (m + 1.0))
    sb = np.sqrt(1 - cb * cb)
    ph = (np.arange(nphi) + 0.5) / nphi * math.pi
    s0 = math.sqrt(max(1 - c0 * c0, 0.0))
    cp = c0 * cb[:, None] + s0 * sb[:, None] * np.cos(ph)[None, :]
    wgt = (cp > 0).astype(float)
    cp = np.clip(cp, 1e-9, 1.0)
    ci = cp if full else np.full_like(cp, c0)
    w0, w1, w2 = ci + 0j, _w(nf, ci), _w(n_sub, ci)
    e1, e2 = nf * nf, n_sub * n_sub
    r01 = ((w0 - w1) / (w0 + w1), (e1 * w0 - w1) / (e1 * w0 + w1))
    r12 = ((w1 - w2) / (w1 + w2), (e2 * w1 - e1 * w2) / (e2 * w1 + e1 * w2))
    z = np.exp(2j * kt * _w(nf, cp))
    rs, rp = ((a + b * z) / (1 + a * b * z) for a, b in zip(r01, r12, strict=True))
    return _gram_of_r(rs, rp, wgt)


CASES = [
    ("MLI 1064 nm (Kapton 50.8 um / Al)", "mli_kapton_aluminium", 1064e-9),
    ("MLI 532 nm (absorbing Kapton)", "mli_kapton_aluminium", 532e-9),
    ("OSR 532 nm (silica 200 um / Ag)", "osr_silica_silver", 532e-9),
]


def _material(name, lam, m, mode):
    base = ppr.load_material(name, lam, dtype=jnp.float64)
    return ppr.Material(
        base.n,
        m,
        films=base.films,
        wavelength=lam,
        film_mode=mode,
        thick_layer=-1 if mode == "coherent" else 0,
    )


def _spread(name, lam, m, c):
    """Phase spread (radians) of the thick layer over the lobe (docs: the criterion)."""
    base = ppr.load_material(name, lam, dtype=jnp.float64)
    n, t = (complex(np.asarray(base.films[0][0])), float(np.asarray(base.films[0][1])))
    kt = 2 * math.pi * t / lam
    w = _w(n, c)
    gu = kt * w.real / abs(w) ** 2
    v = 1.0 / (m + 1.0)
    s2 = 1 - c * c
    a = s2 - c * c
    return abs(gu) * np.sqrt(4 * c * c * s2 * v + 2 * (a * a + c**4) * v * v)


def treatments(quick: bool) -> tuple[list[str], dict]:
    deg = np.array([0, 5, 10, 20, 30, 45, 60, 70, 80, 85, 88], float)
    c = np.cos(np.radians(deg))
    ms = [10.0, 300.0, 1e4, 1e5]
    nu, nphi = (1500, 128) if quick else (3000, 256)
    rows = [
        "| film | m | max phase spread [rad] | coherent | incoherent | lobe | lobe, 0-80 deg |"
        " full vs phase-only average |",
        "|---|---|---|---|---|---|---|---|",
    ]
    t_brute = []
    for label, name, lam in CASES:
        base = ppr.load_material(name, lam, dtype=jnp.float64)
        nf = complex(np.asarray(base.films[0][0]))
        t = float(np.asarray(base.films[0][1]))
        n_sub = complex(np.asarray(base.n))
        for m in ms:
            t0 = time.perf_counter()
            ref = np.array([brute_params(nf, t, n_sub, lam, m, ci, nu, nphi) for ci in c])
            t_brute.append((time.perf_counter() - t0) / len(c))
            full = np.array(
                [brute_params(nf, t, n_sub, lam, m, ci, nu, nphi, full=True) for ci in c]
            )
            err = {}
            for mode in ("coherent", "incoherent", "lobe"):
                got = np.array(ppr.facet_mueller_params(_material(name, lam, m, mode), c)).T
                e = np.abs(got - ref).max(axis=1)
                err[mode] = (e.max(), e[deg <= 80].max())
            S = _spread(name, lam, m, c).max()
            rows.append(
                f"| {label} | {m:g} | {S:.3g} | {err['coherent'][0]:.1e} | "
                f"{err['incoherent'][0]:.1e} | {err['lobe'][0]:.1e} | {err['lobe'][1]:.1e} | "
                f"{np.abs(full - ref).max():.1e} |"
            )
    # run time per evaluation of each treatment (one material, N facet cosines)
    n_eval = 20_000 if quick else 100_000
    cc = jnp.asarray(np.random.default_rng(0).uniform(0, 1, n_eval))
    times = {}
    for dt in (jnp.float32, jnp.float64):
        for mode in ("bare", "coherent", "incoherent", "lobe"):
            if mode == "bare":
                mat = ppr.load_material("aluminium", 1064e-9, dtype=dt)
            else:
                mat = _material("mli_kapton_aluminium", 1064e-9, 300.0, mode)
                mat = jax.tree.map(
                    lambda a, dt=dt: a.astype(
                        jnp.result_type(dt, jnp.complex64) if jnp.iscomplexobj(a) else dt
                    ),
                    mat,
                )
            fn = jax.jit(lambda mt, x: ppr.facet_mueller_params(mt, x))
            times[(mode, np.dtype(dt).name)] = (
                median_time(fn, mat, cc.astype(dt), repeats=5) / n_eval
            )
    return rows, dict(times=times, t_brute=float(np.median(t_brute)), nu=nu, nphi=nphi)


def double_bound(quick: bool) -> list[str]:
    """Largest |lobe - incoherent| facet parameters at rough finishes (the double bounce's
    facets use the incoherent treatment)."""
    deg = np.linspace(0, 88, 23 if quick else 89)
    c = np.cos(np.radians(deg))
    rows = [
        "| film | m | max abs difference (a, b, c, d), 0-88 deg | same, 10-88 deg |",
        "|---|---|---|---|",
    ]
    for label, name, lam in CASES:
        for m in (1.0, 3.0, 10.0, 30.0):
            p = {
                mode: np.array(ppr.facet_mueller_params(_material(name, lam, m, mode), c)).T
                for mode in ("lobe", "incoherent")
            }
            e = np.abs(p["lobe"] - p["incoherent"]).max(axis=1)
            rows.append(f"| {label} | {m:g} | {e.max():.1e} | {e[deg >= 10].max():.1e} |")
    return rows


# ----------------------------------------------------------------------------- 2. throughput


def throughput(quick: bool) -> list[str]:
    n = 10_000 if quick else 40_000
    rng = np.random.default_rng(1)

    def hemi(k):
        v = rng.normal(size=(k, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)

    ki, ko = hemi(n), hemi(n)
    z = np.array([0.0, 0.0, 1.0], np.float32)
    al = ppr.load_material("aluminium", 532e-9, "rough", dtype=jnp.float32)
    thin = [(1.38, 97e-9), (2.3, 60e-9), (1.46, 110e-9), (2.05, 75e-9)]
    mats = [("bare aluminium", al)]
    for L in (1, 2, 4):
        mats.append(
            (
                f"{L} coherent film(s)",
                ppr.Material(al.n, al.m, films=thin[:L], wavelength=532e-9),
            )
        )
    mats.append(
        (
            "MLI (thick Kapton, lobe)",
            ppr.load_material("mli_kapton_aluminium", 532e-9, "rough", dtype=jnp.float32),
        )
    )
    rows = [
        "| material | single + multiple, bistatic [M evals/s] | x bare "
        "| all terms, exact backscatter [M evals/s] | x bare |",
        "|---|---|---|---|---|",
    ]
    base = None
    for label, mat in mats:
        mat = jax.tree.map(
            lambda a: a.astype(jnp.complex64 if jnp.iscomplexobj(a) else jnp.float32), mat
        )
        t1 = median_time(
            lambda mat=mat: ppr.mueller_brdf(
                ki, ko, z, mat, terms=("single", "multiple"), wavelength=532e-9
            ),
            repeats=3,
        )
        t2 = median_time(
            lambda mat=mat: ppr.mueller_brdf(ki, ki, z, mat, wavelength=532e-9), repeats=3
        )
        if base is None:
            base = (t1, t2)
        rows.append(
            f"| {label} | {n / t1 / 1e6:.2f} | {t1 / base[0]:.2f} | {n / t2 / 1e6:.2f} | "
            f"{t2 / base[1]:.2f} |"
        )
    return rows


# ----------------------------------------------------------------------------- 3. figure


def figure(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    deg = np.linspace(0, 89, 179)
    c = np.cos(np.radians(deg))
    mats = [
        ("MLI: Kapton 50.8 um / Al", "mli_kapton_aluminium", "aluminium"),
        ("OSR: silica 200 um / Ag", "osr_silica_silver", "silver"),
        ("Si cell + 75 nm SiN AR", "solar_cell_si_ar", "silicon"),
    ]
    fig, axes = plt.subplots(3, 3, figsize=(13, 9), sharex=True)
    for col, (label, name, sub) in enumerate(mats):
        for lam, color in ((532e-9, "tab:green"), (1064e-9, "tab:red")):
            for mat, ls, tag in (
                (ppr.load_material(name, lam, dtype=jnp.float64), "-", "coated"),
                (ppr.load_material(sub, lam, dtype=jnp.float64), ":", "bare substrate"),
            ):
                a, b, cc, d = (np.asarray(x) for x in ppr.facet_mueller_params(mat, c))
                M = np.zeros(c.shape + (4, 4))
                M[:, 0, 0] = M[:, 1, 1] = a
                M[:, 0, 1] = M[:, 1, 0] = b
                M[:, 2, 2] = M[:, 3, 3] = cc
                M[:, 2, 3], M[:, 3, 2] = d, -d
                fns = (ppr.retardance, ppr.diattenuation, ppr.depolarization_index)
                for row, fn in enumerate(fns):
                    axes[row, col].plot(
                        deg,
                        np.asarray(fn(jnp.asarray(M))),
                        ls,
                        color=color,
                        label=f"{lam * 1e9:.0f} nm {tag}",
                    )
        axes[0, col].set_title(f"{label} ({ppr.load_material(name).film_mode})")
        axes[2, col].set_xlabel("facet incidence [deg]")
    for row, lab in enumerate(("retardance [rad]", "diattenuation", "depolarization index")):
        axes[row, 0].set_ylabel(lab)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        "one facet of each coated library material (lobe-averaged thick films at the default "
        "finish) against its bare substrate"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- 4. CubeSat


def cubesat() -> list[str]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for cmd, cfg, name in (
            ("simulate", "configs/scenes/cubesat_coated.toml", "simulate"),
            ("image", "configs/cli/image_coated.toml", "image"),
        ):
            out = Path(tmp) / name
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "ppr.cli", cmd, "-c", cfg, "--out", str(out)]
                + (["--states", "H,R"] if cmd == "simulate" else []),
                cwd=ROOT,
                check=True,
                capture_output=True,
            )
            wall = time.perf_counter() - t0
            js = json.loads((out / f"{name}.json").read_text())
            shutil.copy(out / f"{name}.png", OUT / f"films_cubesat_{name}.png")
            if cmd == "simulate":
                e = np.asarray(js["energy"])
                rows.append(
                    f"- `ppr simulate -c {cfg} --states H,R`: {wall:.0f} s wall "
                    f"({js['seconds']:.0f} s in the command), {js['lit_visible_faces']} lit and "
                    f"visible facets; energy H in -> (S0, S1, S2, S3) = "
                    f"{', '.join(f'{x:.3g}' for x in e[0])} m^2/sr, R in -> "
                    f"{', '.join(f'{x:.3g}' for x in e[1])} m^2/sr"
                )
            else:
                parts = ", ".join(
                    f"{k}: {v['lit_pixels']} px, mean M00 cos {v['mean_reflectance']:.3g}/sr, "
                    f"depolarization index {v['mean_depolarization_index']:.3f}"
                    for k, v in js["parts"].items()
                    if v["lit_pixels"]
                )
                rows.append(f"- `ppr image -c {cfg}`: {wall:.0f} s wall; {parts}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller batches and quadratures")
    ap.add_argument("--cubesat", action="store_true", help="also run the coated CubeSat CLI")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows, tinfo = treatments(args.quick)
    drows = double_bound(args.quick)
    trows = throughput(args.quick)
    figure(OUT / "films_polarimetry.png")
    crows = cubesat() if args.cubesat else []
    times = tinfo["times"]
    lines = [
        "# Coated facets: thick-film treatments, throughput, demo",
        "",
        f"`python bench/bench_films.py{' --quick' if args.quick else ''}"
        f"{' --cubesat' if args.cubesat else ''}` ({time.perf_counter() - t_start:.0f} s; "
        "2-core VM shared with other jobs: absolute times are upper bounds, ratios hold). "
        "Physics: docs/physics/thin_films.md.",
        "",
        "## 1. Thick films: each treatment against the brute-force lobe average",
        "",
        "Largest absolute error of the facet's Mueller parameters (a, b, c, d) over incidence "
        "0, 5, 10, 20, 30, 45, 60, 70, 80, 85, 88 deg (a <= 1); reference: NumPy quadrature "
        f"of the lobe average ({tinfo['nu']} x {tinfo['nphi']} tilts per angle). The last "
        "column is the model choice, not an error: averaging the interfaces' reflection too "
        "(zero thickness would then no longer equal the bare facet).",
        "",
        *rows,
        "",
        "Run time per facet evaluation (`ppr.facet_mueller_params`, jitted, 1e5 cosines, "
        "median of 5), against the quadrature reference (NumPy, per angle):",
        "",
        "| treatment | float32 [ns] | float64 [ns] |",
        "|---|---|---|",
        *(
            f"| {mode} | {times[(mode, 'float32')] * 1e9:.0f} | "
            f"{times[(mode, 'float64')] * 1e9:.0f} |"
            for mode in ("bare", "coherent", "incoherent", "lobe")
        ),
        f"| brute-force quadrature (NumPy) | -- | {tinfo['t_brute'] * 1e9:.3g} |",
        "",
        "The double bounce's quadrature uses the incoherent facets for a thick layer "
        "(`ppr.brdf.double.DOUBLE_THICK_MODE`): the lobe/incoherent difference of one facet at the "
        "rough finishes where the double term matters (m <= 30):",
        "",
        *drows,
        "",
        "## 2. BRDF throughput (float32, `ppr.mueller_brdf`)",
        "",
        *trows,
        "",
        "## 3. Retardance and diattenuation against incidence",
        "",
        "![films_polarimetry](films_polarimetry.png)",
        "",
    ]
    if crows:
        lines += [
            "## 4. Coated CubeSat (MLI-wrapped bus, AR-coated cells)",
            "",
            *crows,
            "",
            "![simulate](films_cubesat_simulate.png)",
            "",
            "![image](films_cubesat_image.png)",
            "",
        ]
    (OUT / "films.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
