"""Build ``ppr/data/double_backscatter.npz``: the material-independent tables of the
double-bounce term at exact backscatter (:mod:`ppr.brdf.double_table`).

    .venv/bin/python scripts/double_backscatter_table.py [--nx 84] [--nu 100]

About 2-3 minutes on 2 cores at the default order ``BUILD_ORDER``. Prints the singular values
behind the stored rank and the rank residual; the table's error against the quadrature is
measured by tests/test_double_table.py and bench/bench_double.py.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

from ppr.brdf import double_table as T  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--nx", type=int, default=84)
    ap.add_argument("--nu", type=int, default=100)
    ap.add_argument("--k", type=int, default=T.K_NODES)
    args = ap.parse_args()
    t0 = time.perf_counter()
    tab = T.build_table(args.nx, args.nu, order=T.BUILD_ORDER, k=args.k)
    path = T.save_table(tab)
    print(f"wrote {path} in {time.perf_counter() - t0:.0f} s")
    print(str(tab["info"]))


if __name__ == "__main__":
    main()
