"""Detection time and result of ``ppr.mesh_symmetries`` on the library's shapes, the example
satellite and ~10k-face meshes (NumPy/SciPy on the host, one thread of work).

For each mesh: faces, point group found (proper + improper elements), largest residual
(relative to the mesh size), and the median wall time of ``repeats`` calls after one warm-up
call (``median_time``). The CPU time of the process over the same calls is printed too:
on a shared machine the wall time includes waiting for a core.

    python bench/bench_symmetry.py [--repeats 3] [--quick]

writes ``bench/results/symmetry.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import median_time  # noqa: E402

import ppr  # noqa: E402

SATELLITE = ppr.image.EXAMPLE_SATELLITE


def cases(quick: bool):
    out = [
        ("box 0.1 x 0.2 x 0.3", lambda: ppr.shapes.box((0.1, 0.2, 0.3)), 1e-6),
        ("cube (1U)", lambda: ppr.shapes.cubesat(1), 1e-6),
        ("3U CubeSat", lambda: ppr.shapes.cubesat(3), 1e-6),
        ("plate", lambda: ppr.shapes.plate(), 1e-6),
        ("cylinder, 32 sections", lambda: ppr.shapes.cylinder(), 1e-6),
        ("cone, 32 sections", lambda: ppr.shapes.cone(), 1e-6),
        ("icosphere, 3 subdivisions", lambda: ppr.shapes.sphere(), 1e-6),
        ("3U CubeSat with panels", lambda: ppr.shapes.cubesat_with_panels(), 1e-6),
        ("example satellite", lambda: ppr.load_mesh(SATELLITE), 1e-6),
        ("example satellite, tol 1e-2", lambda: ppr.load_mesh(SATELLITE), 1e-2),
        ("example satellite, tol 3e-2", lambda: ppr.load_mesh(SATELLITE), 3e-2),
    ]
    if not quick:
        out += [
            ("3U CubeSat, max edge 12 mm", lambda: ppr.shapes.cubesat(3, max_edge=0.012), 1e-6),
            ("cube, max edge 5 mm", lambda: ppr.shapes.box((0.1,) * 3, max_edge=0.005), 1e-6),
            (
                "3U CubeSat with panels, max edge 22 mm",
                lambda: ppr.shapes.cubesat_with_panels(max_edge=0.022),
                1e-6,
            ),
            ("icosphere, 5 subdivisions", lambda: ppr.shapes.sphere(subdivisions=5), 1e-6),
        ]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="library shapes only")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "symmetry.md"))
    args = ap.parse_args(argv)
    rows = []
    for name, make, tol in cases(args.quick):
        mesh = make()
        sym = ppr.mesh_symmetries(mesh, tol=tol)
        c0 = time.process_time()
        wall = median_time(
            lambda mesh=mesh, tol=tol: ppr.mesh_symmetries(mesh, tol=tol), repeats=args.repeats
        )
        cpu = (time.process_time() - c0) / (args.repeats + 1)
        n_p = len(sym.rotations)
        row = (
            f"| {name} | {mesh.n_faces} | {sym.point_group} | {n_p} + {len(sym) - n_p} | "
            f"{tol:.0e} | {float(np.max(sym.residuals)):.1e} | {wall:.3f} | {cpu:.3f} |"
        )
        print(row, flush=True)
        rows.append(row)
    head = [
        "# Mesh symmetry detection (`ppr.mesh_symmetries`)",
        "",
        f"`python bench/bench_symmetry.py --repeats {args.repeats}"
        f"{' --quick' if args.quick else ''}`: median wall time of {args.repeats} calls after a "
        "warm-up call, and the process CPU time per call (the machine is shared: the wall "
        "time includes waiting for a core).",
        "",
        "| mesh | faces | group | proper + improper | tol | max residual | wall (s) | CPU (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    Path(args.out).write_text("\n".join(head + rows) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
