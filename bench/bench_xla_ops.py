"""Per-element cost of elementwise operations and kernel patterns on XLA CPU, next to NumPy.

Why this exists: the BRDF kernels' speed on this CPU is decided less by arithmetic than by
which operations XLA CPU vectorizes and how it fuses. This script measures the facts that
shaped ``ppr/microfacet.py``, ``ppr/optics/_frames.py`` and ``ppr/brdf/double_table.py`` (listed in
docs/DESIGN.md), so they can be re-checked on a new jax release:

- transcendental functions one by one (``jnp.arcsin`` lowers to an unvectorized ``atan2``;
  the visibility table therefore uses ``c / (1 + sqrt(1 - c^2))``);
- a Mueller frame rotation as the ``(16, N)`` monomial map plus the transposing copy to
  ``(N, 4, 4)`` (``rotate_mueller_flat``) against the trailing-layout reversals
  (``rotate_mueller_44``);
- a 4-point interpolation of 16-entry table rows: four row gathers against four column
  gathers of per-cell cubic coefficients.

float32, N = 250000 per call, jit, median of repeats after a warm-up with
``block_until_ready``; NumPy on the same inputs in the same process (ratio = NumPy time /
JAX time). Writes bench/results/xla_ops.md.

Run: ``.venv/bin/python bench/bench_xla_ops.py`` (about 30 s).
"""

from __future__ import annotations

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppr.brdf.albedo import _cr_cubics, _cr_eval, _cr_weights  # noqa: E402
from ppr.optics import rotate_mueller_44, rotate_mueller_flat  # noqa: E402

sys.path.insert(0, str(ROOT / "bench"))
from _timing import median_time  # noqa: E402

N = 250_000
REPEATS = 25


def median_ns(fn, *args) -> float:
    """Median wall time per element (ns) of ``fn(*args)`` (:func:`_timing.median_time`)."""
    return median_time(fn, *args, repeats=REPEATS) / N * 1e9


def elementwise_rows(x, y):
    xn, yn = np.asarray(x), np.asarray(y)
    ops = [
        ("multiply by 2 (memory bound)", lambda a: a * 2, lambda a: a * 2),
        ("exp", jnp.exp, np.exp),
        ("log", jnp.log, np.log),
        ("sqrt", jnp.sqrt, np.sqrt),
        ("divide", lambda a: 1.0 / a, lambda a: 1.0 / a),
        ("sin", jnp.sin, np.sin),
        ("arcsinh", jnp.arcsinh, np.arcsinh),
        ("arctan", jnp.arctan, np.arctan),
        ("arcsin", jnp.arcsin, np.arcsin),
        ("arccos", jnp.arccos, np.arccos),
        ("x ** 2.7", lambda a: a**2.7, lambda a: a**2.7),
        ("tan(asin(c) / 2) = c / (1 + sqrt(1 - c^2))",
         lambda a: a / (1.0 + jnp.sqrt((1.0 - a) * (1.0 + a))),
         lambda a: a / (1.0 + np.sqrt((1.0 - a) * (1.0 + a)))),
    ]
    rows = []
    for name, fj, fn_np in ops:
        tj = median_ns(jax.jit(fj), x)
        tn = median_ns(fn_np, xn)
        rows.append((name, tj, tn))
    tj = median_ns(jax.jit(jnp.arctan2), x, y)
    tn = median_ns(np.arctan2, xn, yn)
    rows.append(("arctan2", tj, tn))
    return rows


def rotation_rows(rng):
    M = jnp.asarray(rng.normal(size=(N, 4, 4)), jnp.float32)
    M16 = jnp.asarray(np.asarray(M).reshape(N, 16).T)
    ang = [jnp.asarray(f(rng.uniform(-np.pi, np.pi, N)), jnp.float32) for f in (np.cos, np.sin)]
    cs = [ang[0], ang[1], ang[1], ang[0]]

    def flat(m16, a, b, c, d):
        out = rotate_mueller_flat(m16, a, b, c, d)
        return jnp.moveaxis(out, 0, -1).reshape(N, 4, 4)

    t_flat = median_ns(jax.jit(flat), M16, *cs)
    t_44 = median_ns(jax.jit(rotate_mueller_44), M, *cs)
    err = float(jnp.max(jnp.abs(jax.jit(flat)(M16, *cs) - jax.jit(rotate_mueller_44)(M, *cs))))
    return t_flat, t_44, err


def interpolation_rows(rng):
    n = 84
    rows = jnp.asarray(rng.normal(size=(n + 3, 16)), jnp.float32)
    x = jnp.asarray(rng.uniform(0.0, n - 1.0, N), jnp.float32)

    def cell(x):
        i = jnp.clip(jnp.floor(x), 0, n - 2).astype(jnp.int32)
        return i, x - i

    def row_gathers(rows, x):
        i, t = cell(x)
        w = _cr_weights(t)
        return sum(w[a][:, None] * jnp.take(rows, i + a, axis=0, mode="clip") for a in range(4))

    def column_cubics(rows, x):
        i, t = cell(x)
        return _cr_eval(_cr_cubics(rows, n), i, t)

    t_rows = median_ns(jax.jit(row_gathers), rows, x)
    t_cols = median_ns(jax.jit(column_cubics), rows, x)
    err = float(jnp.max(jnp.abs(jax.jit(row_gathers)(rows, x) - jax.jit(column_cubics)(rows, x))))
    return t_rows, t_cols, err


def main():
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.uniform(0.05, 0.95, N), jnp.float32)
    y = jnp.asarray(rng.uniform(0.05, 0.95, N), jnp.float32)
    ew = elementwise_rows(x, y)
    t_flat, t_44, err_rot = rotation_rows(rng)
    t_rows, t_cols, err_int = interpolation_rows(rng)
    lines = [
        "# XLA CPU: per-element costs that shaped the BRDF kernels (bench/bench_xla_ops.py)",
        "",
        f"float32, N = {N} per call, jit, median of {REPEATS} after warm-up; jax "
        f"{jax.__version__}, NumPy {np.__version__}, 2 cores (XLA uses both, NumPy one). "
        "Absolute times move with this VM's load; compare rows of one run. A JAX row of one "
        "operation includes the call's dispatch (the memory-bound first row is the floor); "
        "inside a fused kernel the cheap operations cost a fraction of it, the unvectorized "
        "ones (arcsin, arccos, arctan, arctan2) their full time. NumPy's transcendental "
        "functions are SIMD-vectorized (NumPy >= 1.22); XLA CPU's exp, log, sqrt and divide "
        "are too, its inverse trigonometric functions are not.",
        "",
        "## Elementwise functions",
        "",
        "| operation | JAX ns/element | NumPy ns/element | NumPy / JAX |",
        "|---|---|---|---|",
    ]
    for name, tj, tn in ew:
        lines.append(f"| {name} | {tj:.2f} | {tn:.2f} | {tn / tj:.1f} |")
    lines += [
        "",
        "## Kernel patterns",
        "",
        "| pattern | ns/element | alternative | ns/element | max abs difference |",
        "|---|---|---|---|---|",
        f"| Mueller rotation: `(16, N)` monomial map + transposing copy | {t_flat:.1f} | "
        f"`(N, 4, 4)` reversals (`rotate_mueller_44`) | {t_44:.1f} | {err_rot:.1e} |",
        f"| Catmull-Rom, four 16-entry row gathers | {t_rows:.1f} | "
        f"four column gathers of cell cubics (`_cr_eval`) | {t_cols:.1f} | {err_int:.1e} |",
        "",
    ]
    out = ROOT / "bench" / "results" / "xla_ops.md"
    out.write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
