"""Database build rate (signatures/s): storage plumbing and the ppr forward model.

1. Plumbing (synthetic stand-in signatures, cheap): rows/s of the bare signature function
   (sharded evaluation + normalization, no storage) against ``build_database`` (zarr writes,
   read-back, BLAKE2b digests, atomic markers); the difference is the storage overhead. NumPy
   reference for the storage path: ``np.save`` per chunk plus the same digest.
2. ppr forward model: a 3U CubeSat with deployed panels subdivided to ~1.3k facets
   (``ppr.shapes.cubesat_with_panels(3, max_edge=0.06)``), 16 Mueller channels x 128 bins,
   full ``ppr.mueller_brdf``; host ray-cast visibility and the jitted vmapped render timed
   separately (compile excluded and reported), then extrapolated to 1e5 signatures
   (target <= 10 min).

Writes bench/results/classifier_database_build.{md,png}.
Run: .venv/bin/python bench/bench_database.py
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from inversion._database import (
    build_database,
    device_mesh,
    enumerate_rows,
    evaluate_rows,
    make_signature_fn,
    spec_from_dict,
)
from inversion._grid import fibonacci_grid
from inversion._noise import MeasurementModel

OUT = Path(__file__).resolve().parent / "results"


def plumbing(tmp: Path):
    spec = spec_from_dict(
        {
            "name": "plumbing",
            "shapes": [{"name": n} for n in ("cube", "box3u", "cylinder", "plate")],
            "materials": ["aluminium", "white_paint", "silica"],
            "finishes": {"polished": 3000.0, "brushed": 100.0, "matte": 5.0},
            "grid": {"kind": "hopf", "size": 2, "reduce_symmetry": False},
            "sensor": {"channels": "full", "n_bins": 128, "bin_width_m": 0.01},
            "chunk_rows": 1024,
        }
    )
    fn = make_signature_fn(spec)
    rows = enumerate_rows(spec)
    n = len(rows["quat"])
    mesh = device_mesh()
    cr = spec.chunk_rows

    def chunks():
        for a in range(0, n, cr):
            yield evaluate_rows(
                fn, {k: v[a : a + cr] for k, v in rows.items()}, mesh, np.float32, pad_to=cr
            )

    next(chunks())  # compile
    t = time.perf_counter()
    sigs = list(chunks())
    t_raw = time.perf_counter() - t
    # NumPy storage reference: np.save per chunk + digest
    ref = tmp / "npy"
    ref.mkdir()
    t = time.perf_counter()
    for i, (s, e) in enumerate(sigs):
        np.save(ref / f"{i}.npy", s)
        np.save(ref / f"{i}_e.npy", e)
        hashlib.blake2b(s.tobytes() + e.tobytes(), digest_size=20).hexdigest()
    t_np = time.perf_counter() - t + t_raw
    t = time.perf_counter()
    rep = build_database(spec, tmp / "db", fn, progress=False)
    t_build = time.perf_counter() - t
    return {
        "rows": n,
        "raw_rows_per_s": n / t_raw,
        "build_rows_per_s": n / t_build,
        "numpy_store_rows_per_s": n / t_np,
        "build_seconds": t_build,
        "n_devices": rep.n_devices,
    }


def ppr_rate(batch: int = 256, n_batches: int = 2):
    from inversion._ppr_adapter import PprSignatures

    mm = MeasurementModel.preset("full")
    fn = PprSignatures(
        [("cubesat_with_panels", {"units": 3, "max_edge": 0.06})],
        ["aluminium"],
        [300.0],
        mm,
        n_bins=128,
        bin_width_m=0.01,
    )
    faces = fn.meshes[0].n_faces
    q = fibonacci_grid(batch * (n_batches + 1)).astype(np.float32)
    mesh = device_mesh()

    def params(i):
        sl = slice(i * batch, (i + 1) * batch)
        return {
            "shape_id": np.zeros(batch, np.int32),
            "attitude_id": np.arange(batch, dtype=np.int32),
            "material_id": np.zeros(batch, np.int32),
            "finish_id": np.zeros(batch, np.int32),
            "quat": q[sl],
        }

    t = time.perf_counter()
    evaluate_rows(fn, params(0), mesh, np.float32, pad_to=batch)
    t_compile = time.perf_counter() - t
    t_vis = t_all = 0.0
    for i in range(1, n_batches + 1):
        p = params(i)
        t = time.perf_counter()
        fn.visibility(p["shape_id"], p["quat"])
        t_vis += time.perf_counter() - t
        t = time.perf_counter()
        evaluate_rows(fn, p, mesh, np.float32, pad_to=batch)
        t_all += time.perf_counter() - t
    n = batch * n_batches
    rate = n / t_all
    return {
        "faces": faces,
        "rows": n,
        "compile_s": t_compile,
        "rows_per_s": rate,
        "visibility_share": t_vis / t_all,
        "minutes_per_1e5": 1e5 / rate / 60,
    }


def main():
    tmp = Path(tempfile.mkdtemp(prefix="bench_db_"))
    try:
        pl = plumbing(tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(pl)
    pp = ppr_rate()
    print(pp)
    load = os.getloadavg()[0]
    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Database build rate (issue 5)",
        "",
        f"{jax.device_count()} JAX device(s), {os.cpu_count()} cores "
        f"(load average {load:.1f} at the end of the run). Monostatic sensor: the double term "
        "comes from the exact-backscatter table (ppr.sensor_terms).",
        "",
        "## Storage plumbing (synthetic stand-in signatures, 16 channels x 128 bins)",
        "",
        "| path | rows/s |",
        "|---|---|",
        f"| signature function only (sharded eval + normalize) | {pl['raw_rows_per_s']:.0f} |",
        f"| NumPy reference: eval + np.save + digest | {pl['numpy_store_rows_per_s']:.0f} |",
        f"| build_database (zarr + read-back + digest + marker) | {pl['build_rows_per_s']:.0f} |",
        "",
        f"{pl['rows']} rows; storage overhead of build_database relative to bare evaluation: "
        f"{pl['raw_rows_per_s'] / pl['build_rows_per_s']:.2f}x the time; against the NumPy "
        f"storage path: {pl['numpy_store_rows_per_s'] / pl['build_rows_per_s']:.2f}x.",
        "",
        f"## ppr forward model: 3U CubeSat with panels, {pp['faces']} facets, 16 x 128",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| compile (first batch) | {pp['compile_s']:.1f} s |",
        f"| signatures/s (visibility + render + normalize) | {pp['rows_per_s']:.0f} |",
        f"| share of host ray-cast visibility | {100 * pp['visibility_share']:.0f}% |",
        f"| extrapolated time for 1e5 signatures | {pp['minutes_per_1e5']:.1f} min "
        "(target <= 10 min) |",
        "",
        "Reproduce: `.venv/bin/python bench/bench_database.py`",
    ]
    (OUT / "classifier_database_build.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    labels = [
        "synthetic\neval only",
        "synthetic\nNumPy store",
        "synthetic\nbuild_database",
        f"ppr {pp['faces']} facets\neval",
    ]
    vals = [
        pl["raw_rows_per_s"],
        pl["numpy_store_rows_per_s"],
        pl["build_rows_per_s"],
        pp["rows_per_s"],
    ]
    ax.bar(range(4), vals, color=["C0", "C1", "C2", "C3"])
    ax.axhline(1e5 / 600, color="k", ls=":", label="1e5 in 10 min")
    ax.set_xticks(range(4), labels, fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("signatures / s")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "classifier_database_build.png", dpi=110)
    print((OUT / "classifier_database_build.md").read_text())


if __name__ == "__main__":
    main()
