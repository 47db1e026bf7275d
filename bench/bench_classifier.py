"""Classification time per observation against ~1e5 templates with the full shift search.

Bank: the synthetic stand-in signature model (inversion._synthetic; 16 Mueller channels x 64
range bins, 4 shapes x Hopf grid x 3 materials x 3 finishes, ~1e5 rows). Methods:

- exact: every template's spectrum precomputed, channel sum as batched matmuls, irfft over
  all 2B-1 lags (inversion.classify with rank=None);
- low-rank K: SVD basis of the weighted templates, upper bounds A G + r for all templates,
  the top 64 rescored exactly, certificate checked (falls back to exhaustive if it fails);
- NumPy reference: the same exact FFT search in plain NumPy (rfft / einsum / irfft), timed
  on a 1e4-template slice and scaled linearly to the bank size.

Single observation (latency) and batches of 32 (throughput) are reported; median of repeats
after warm-up, block_until_ready via numpy conversion. Writes
bench/results/classifier_bench.{md,png}. Target (issue 5): <= 50 ms per observation.

Run: .venv/bin/python bench/bench_classifier.py [--templates 100000]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
from _timing import median_time

from inversion._classifier import _n_fft, classify, design_weights, prepare
from inversion._database import bank_in_memory, spec_from_dict
from inversion._noise import NoiseModel, observe

OUT = Path(__file__).resolve().parent / "results"


def spec_for(n_target: int, n_bins: int):
    # 4 shapes x 9 material/finish combos; symmetry-reduced Hopf grids. Choose nside.
    base = {
        "name": "bench",
        "shapes": [
            {"name": "cube", "symmetry": "none"},
            {"name": "box3u", "symmetry": "none"},
            {"name": "cylinder", "symmetry": "none"},
            {"name": "plate", "symmetry": "none"},
        ],
        "materials": ["aluminium", "white_paint", "silica"],
        "finishes": {"polished": 3000.0, "brushed": 100.0, "matte": 5.0},
        "grid": {
            "kind": "fibonacci",
            "size": max(1, round(n_target / 36)),
            "reduce_symmetry": False,
        },
        "sensor": {"channels": "full", "n_bins": n_bins, "bin_width_m": 0.01},
        "chunk_rows": 8192,
    }
    return spec_from_dict(base)


def numpy_exact(sigs, w, x, n_fft):
    """Plain NumPy exact search for one observation: best score per template."""
    wy = w * sigs
    nrm = np.sqrt(np.sum(wy * sigs, axis=(1, 2)))
    yf = np.fft.rfft(wy / nrm[:, None, None], n_fft, axis=-1)
    xf = np.fft.rfft(x, n_fft, axis=-1)
    x2f = np.fft.rfft(x * x, n_fft, axis=-1)
    wf = np.fft.rfft(w, n_fft, axis=-1)
    xn = np.sqrt(np.maximum(np.fft.irfft(np.sum(np.conj(wf) * x2f, 0), n_fft), 1e-30))
    corr = np.fft.irfft(np.einsum("tcf,cf->tf", np.conj(yf), xf), n_fft, axis=-1)
    return np.max(corr / xn, axis=-1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--templates", type=int, default=100_000)
    ap.add_argument("--bins", type=int, default=64)
    args = ap.parse_args()
    t0 = time.perf_counter()
    spec = spec_for(args.templates, args.bins)
    bank = bank_in_memory(spec, batch=8192)
    t_bank = time.perf_counter() - t0
    n = len(bank)
    print(f"bank: {n} x {bank.n_channels} ch x {bank.n_bins} bins, built in {t_bank:.1f} s")
    w = design_weights(bank, "fisher", "shape")
    rng = np.random.default_rng(0)
    noise = NoiseModel(
        snr=100.0, speckle_cells=50.0, max_offset_bins=4.0, gain_min=0.1, gain_max=10.0
    )
    truth_rows = rng.choice(n, 32, replace=False)
    obs = np.stack(
        [
            np.asarray(observe(bank.signatures[r].astype(np.float64), noise, seed=int(i)).data)
            for i, r in enumerate(truth_rows)
        ]
    ).astype(np.float32)

    rows = []
    for label, rank in (("exact", None), ("low-rank K=64", 64), ("low-rank K=128", 128)):
        t = time.perf_counter()
        prep = prepare(bank, w, chunk=8192, rank=rank)
        t_prep = time.perf_counter() - t
        single = median_time(lambda p=prep: classify(p, obs[0], k=5), repeats=7)
        batch = median_time(lambda p=prep: classify(p, obs, k=5), repeats=3) / len(obs)
        res = classify(prep, obs, k=5)
        acc = float(np.mean(res.index[:, 0] == truth_rows))
        resc = float(np.median(res.n_rescored)) if res.n_rescored is not None else float(n)
        rows.append((label, t_prep, 1e3 * single, 1e3 * batch, resc, acc))
        print(
            f"{label:16s} prepare {t_prep:6.1f} s  single {1e3 * single:8.1f} ms  batched "
            f"{1e3 * batch:7.1f} ms/obs  rescored {resc:.0f}  top1 {acc:.2f}"
        )
        del prep

    # NumPy reference on a slice, scaled
    m = min(10_000, n)
    n_fft = _n_fft(bank.n_bins)
    sl = bank.signatures[:m].astype(np.float32)
    t_np = median_time(lambda: numpy_exact(sl, w, obs[0], n_fft), repeats=3) * n / m
    print(
        f"numpy exact (scaled from {m}): {1e3 * t_np:.1f} ms per observation; "
        f"ratio numpy / jax exact single = {t_np / (rows[0][2] / 1e3):.1f}x"
    )

    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Classifier benchmark (issue 5)",
        "",
        f"{n} templates (synthetic stand-in model), {bank.n_channels} channels x "
        f"{bank.n_bins} range bins, shift search over all {2 * bank.n_bins - 1} lags, k = 5, "
        "Fisher weights for shape. Observations: SNR 100, speckle M = 50, offset <= 4 bins, "
        f"gain 0.1..10. Machine: {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores shared with other jobs "
        f"(load average {os.getloadavg()[0]:.1f} at the end of the run).",
        "",
        "| method | prepare (s) | single obs (ms) | batched, 32 obs (ms/obs) "
        "| templates scored exactly (median) | top-1 = true row |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]:.1f} | {r[2]:.1f} | {r[3]:.1f} | {r[4]:.0f} | {r[5]:.2f} |")
    lines += [
        f"| NumPy exact (scaled from {m}) | - | {1e3 * t_np:.1f} | - | - | - |",
        "",
        f"NumPy / JAX-exact single-observation ratio: {t_np / (rows[0][2] / 1e3):.1f}x. "
        "Target <= 50 ms per observation. Low-rank results equal the exhaustive search: every "
        "template whose upper bound reaches the k-th exact score is rescored exactly (count in "
        "the table). 'top-1 = true row' is low because neighbouring grid rows (about 4 deg "
        "apart) are closer than the noise.",
        "",
        "Reproduce: `.venv/bin/python bench/bench_classifier.py`",
    ]
    (OUT / "classifier_bench.md").write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.5))
    labels = [r[0] for r in rows] + ["NumPy exact"]
    single = [r[2] for r in rows] + [1e3 * t_np]
    batch = [r[3] for r in rows] + [np.nan]
    xs = np.arange(len(labels))
    ax.bar(xs - 0.2, single, 0.4, label="single observation")
    ax.bar(xs + 0.2, batch, 0.4, label="batched (per obs)")
    ax.axhline(50, color="k", ls=":", label="target 50 ms")
    ax.set_xticks(xs, labels, rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel("ms per observation")
    ax.set_title(f"classification against {n} templates")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "classifier_bench.png", dpi=110)
    print((OUT / "classifier_bench.md").read_text())


if __name__ == "__main__":
    main()
