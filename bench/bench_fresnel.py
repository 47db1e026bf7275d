"""Throughput of the Fresnel / facet-Mueller kernels (ppr/optics/_fresnel.py, _frames.py).

Compares, on N random samples in the same process (median of repeats after a warm-up,
``block_until_ready``):

- ``fresnel_mueller_params`` (explicit real arithmetic) vs the same formulas with JAX complex
  dtypes vs plain NumPy complex;
- the facet Mueller matrix in beam frames: structure-of-arrays ``facet_mueller_rows`` (tuple
  of 16 arrays), the ``(N, 4, 4)`` ``facet_mueller_in_beam_frames``, and a NumPy version.

Writes ``bench/results/fresnel.md`` and ``bench/results/fresnel.png``.
Run: ``.venv/bin/python bench/bench_fresnel.py [--n 1000000]`` (~1 min on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import median_time  # noqa: E402

from ppr.optics import (  # noqa: E402
    facet_mueller_in_beam_frames,
    facet_mueller_rows,
    fresnel_mueller_params,  # noqa: E402
)

OUT = Path(__file__).resolve().parent / "results"


def fresnel_complex_jax(n_re, n_im, c):
    n = n_re + 1j * n_im
    w = jnp.sqrt(n * n - (1 - c * c))
    rs = (c - w) / (c + w)
    rp = (n * n * c - w) / (n * n * c + w)
    a2, b2 = jnp.abs(rs) ** 2, jnp.abs(rp) ** 2
    x = rs * jnp.conj(rp)
    return 0.5 * (a2 + b2), 0.5 * (a2 - b2), jnp.real(x), jnp.imag(x)


def fresnel_numpy(n, c):
    w = np.sqrt(n * n - (1 - c * c) + 0j)
    rs = (c - w) / (c + w)
    rp = (n * n * c - w) / (n * n * c + w)
    a2, b2 = np.abs(rs) ** 2, np.abs(rp) ** 2
    x = rs * np.conj(rp)
    return 0.5 * (a2 + b2), 0.5 * (a2 - b2), x.real, x.imag


def facet_numpy(n, ki, ko, h, xi, xo):
    c = np.clip(np.sum(ki * h, -1), 0, 1)
    a, b, cc, d = fresnel_numpy(n, c)
    s = np.cross(ki, ko)
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    yi = np.cross(-ki, xi)
    po = np.cross(ko, s)
    ca, sa = np.sum(s * xi, -1), np.sum(s * yi, -1)
    cb, sb = np.sum(xo * s, -1), np.sum(xo * po, -1)
    Ca, Sa, Cb, Sb = ca * ca - sa * sa, 2 * ca * sa, cb * cb - sb * sb, 2 * cb * sb
    M = np.zeros(c.shape + (4, 4))
    M[:, 0] = np.stack([a, b * Ca, b * Sa, 0 * a], -1)
    M[:, 1] = np.stack([Cb * b, Cb * a * Ca - Sb * cc * Sa, Cb * a * Sa + Sb * cc * Ca, Sb * d], -1)
    M[:, 2] = np.stack(
        [-Sb * b, -Sb * a * Ca - Cb * cc * Sa, -Sb * a * Sa + Cb * cc * Ca, Cb * d], -1
    )
    M[:, 3] = np.stack([0 * a, d * Sa, -d * Ca, cc], -1)
    return M


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    N = ap.parse_args().n
    rng = np.random.default_rng(0)

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    ki = unit(rng.normal(size=(N, 3)))
    ko = unit(rng.normal(size=(N, 3)))
    h = unit(ki + ko)
    xi = unit(np.cross(ki, rng.normal(size=(N, 3))))
    xo = unit(np.cross(ko, rng.normal(size=(N, 3))))
    cos_t = rng.uniform(0, 1, N)
    n = 0.94 + 6.42j
    rows = []
    load = os.getloadavg()[0]
    for dt in (np.float32, np.float64):
        c = cos_t.astype(dt)
        nr, ni = dt(n.real), dt(n.imag)
        t_real = median_time(jax.jit(fresnel_mueller_params), nr, ni, c)
        t_cplx = median_time(jax.jit(fresnel_complex_jax), nr, ni, c)
        vecs = [v.astype(dt) for v in (ki, ko, h, xi, xo)]
        soa = [tuple(np.ascontiguousarray(v[:, i]) for i in range(3)) for v in vecs]
        t_rows = median_time(jax.jit(facet_mueller_rows), nr, ni, *soa)
        t_full = median_time(jax.jit(facet_mueller_in_beam_frames), nr, ni, *vecs)
        rows.append((dt.__name__, t_real, t_cplx, t_rows, t_full))
    t0 = time.perf_counter()
    fresnel_numpy(n, cos_t)
    t_np = time.perf_counter() - t0
    t0 = time.perf_counter()
    facet_numpy(n, ki, ko, h, xi, xo)
    t_np_facet = time.perf_counter() - t0

    lines = [
        f"# Fresnel / facet Mueller throughput (N = {N:.0e}, load average {load:.1f} on "
        f"{os.cpu_count()} cores at start)",
        "",
        "M evaluations per second (median of 5 after warm-up); NumPy float64 complex in the "
        "same process.",
        "",
        "| dtype | Fresnel params (real arith.) | Fresnel (JAX complex) | facet rows (SoA) "
        "| facet (N,4,4) | x NumPy Fresnel | x NumPy facet |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, a, b, c_, d in rows:
        lines.append(
            f"| {name} | {N / a / 1e6:.1f} | {N / b / 1e6:.1f} | {N / c_ / 1e6:.1f} | "
            f"{N / d / 1e6:.1f} | {t_np / a:.1f}x | {t_np_facet / d:.1f}x |"
        )
    lines += ["", f"NumPy: Fresnel {N / t_np / 1e6:.2f} M/s, facet {N / t_np_facet / 1e6:.2f} M/s."]
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "fresnel.md").write_text(text)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    labels = ["Fresnel real", "Fresnel complex", "facet SoA", "facet (N,4,4)"]
    x = np.arange(len(labels))
    for i, (name, *ts) in enumerate(rows):
        ax.bar(x + 0.38 * i, [N / t / 1e6 for t in ts], 0.38, label=name)
    ax.axhline(N / t_np / 1e6, color="k", ls="--", lw=1, label="NumPy Fresnel")
    ax.axhline(N / t_np_facet / 1e6, color="gray", ls=":", lw=1, label="NumPy facet")
    ax.set_xticks(x + 0.19, labels)
    ax.set_ylabel("M evaluations / s")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title(f"N = {N:.0e}, load {load:.1f}")
    fig.tight_layout()
    fig.savefig(OUT / "fresnel.png", dpi=120)


if __name__ == "__main__":
    main()
