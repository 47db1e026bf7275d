"""Regenerate the white-surface deficit tables ``ppr/data/albedo_single.npz`` and
``ppr/data/albedo_double_single.npz`` (the multiple-scattering remainder's input).

    python scripts/make_albedo_tables.py                      # both tables (about 1-2 h)
    python scripts/make_albedo_tables.py --closure-budget inf # pure model deficit

At every node ``(m, mu)`` of :func:`ppr.brdf.albedo.grid_nodes` it computes the model's deficit
``D_model = 1 - E_single - E_double`` of the ideal white surface as a positive integral (the
probability that light is still inside the surface after one or two facets), with the
machinery of scripts/deficit_reference.py at build rules (lobe and second-bounce splines of
``N_LOBE`` and ``NZ`` nodes, without their midpoint checks: the reference's own checks and
tests/test_multiple_scattering.py measure the result off the nodes); ``D_single`` likewise.
``albedo_single.npz`` stores ``log D_single``.

Closure (``albedo_double_single.npz``). The runtime double term is a quadrature of fixed order
(``ppr.brdf.double.DEFAULT_ORDER``) whose directional albedo ``E_double,rt`` differs from the
model's ``E_double`` by ``delta = E_double - E_double,rt``: up to 1e-2 of the incident flux for
m = 0 near grazing and 1.6e-3 for m = 1000 at 88 deg (docs/physics/multiple_scattering.md). A
remainder built from ``D_model`` leaves that error in the white furnace; one built from
``1 - E_single - E_double,rt`` (the former tables) carries it into the remainder's lobe,
where it is the size of ``D`` itself for m >= 10. The table stores

    D = D_model + S_a(delta),   S_a(delta) = sign(delta) max(|delta| - a, 0),

so the white furnace of the evaluated BRDF closes to within the budget ``a``
(``--closure-budget``, default ``A_BUDGET``) and the remainder is the model's wherever the double
term's quadrature error is below it; ``a = inf`` gives the model's deficit everywhere.
``E_double,rt`` is integrated (half-vector rule (HV_PHI, HV_W) of
:func:`scripts.double_table.e_double_hv`) at the nodes where ``E_double >= a / 4``; at the first
node below in each row it is integrated too and the largest ``|delta|`` there is reported (the
part assumed below the budget). Where ``D_model + S_a(delta) < D_model / 2`` (the default-order
double term overshoots in the last hundredths of a degree before the horizon) the table keeps
``D_model / 2``; the count is reported.

Node values are cached per row in ``--cache`` (an interrupted build resumes).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

import deficit_reference as ref  # noqa: E402

from ppr.brdf import albedo  # noqa: E402

NX, NV = 40, 48
N_LOBE, NZ = 80, 60
A_BUDGET = 3e-4
MU_MIN = 1e-9  # the mu = 0 column holds the limit mu -> 0+


def model_rows(m_nodes, mu_nodes, cache: str, log=print):
    """``(D_model, D_single)`` of shape ``(nx, nv)``, row by row, cached."""
    nx, nv = len(m_nodes), len(mu_nodes)
    D = np.full((nx, nv), np.nan)
    Ds = np.full((nx, nv), np.nan)
    if cache and os.path.exists(cache):
        with np.load(cache) as z:
            if z["D"].shape == D.shape and np.allclose(z["m"], m_nodes):
                D, Ds = z["D"].copy(), z["Ds"].copy()
    for i, m in enumerate(m_nodes):
        if np.all(np.isfinite(D[i])):
            continue
        t0 = time.perf_counter()
        lobe = ref.Lobe(m, N_LOBE, check=False)
        second = ref.SecondBounce(lobe, NZ, check=False)
        for j, mu in enumerate(mu_nodes):
            D[i, j], Ds[i, j], _ = ref.deficit(lobe, second, max(float(mu), MU_MIN))
        log(f"row {i} m={m:.4g}: {time.perf_counter() - t0:.0f} s", flush=True)
        if cache:
            np.savez(cache, m=m_nodes, D=D, Ds=Ds)
    return D, Ds


def runtime_double(m, mu):
    """``E_double`` of the runtime double term (default order, white, incoherent)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import double_table as dt  # noqa: PLC0415

    return dt.e_double_hv(np.asarray(m, float), np.maximum(np.asarray(mu, float), MU_MIN))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--closure-budget", type=float, default=A_BUDGET)
    ap.add_argument("--cache", default=os.path.join("/tmp", "albedo_build_cache.npz"))
    args = ap.parse_args(argv)
    a = args.closure_budget
    x, v, m_nodes, mu_nodes = albedo.grid_nodes(NX, NV)
    t0 = time.perf_counter()
    D, Ds = model_rows(m_nodes, mu_nodes, args.cache)
    t1 = time.perf_counter()
    Ed = Ds - D
    M, MU = np.meshgrid(m_nodes, mu_nodes, indexing="ij")
    delta = np.zeros_like(D)
    probe_max = 0.0
    if np.isfinite(a):
        sel = Ed >= 0.25 * a
        probe = np.zeros_like(sel)
        for i in range(NX):  # first node below the threshold in each row (mu descending)
            j = np.nonzero(~sel[i])[0]
            if j.size:
                probe[i, j[0]] = True
        todo = sel | probe
        dcache = args.cache.replace(".npz", "_delta.npz") if args.cache else ""
        if dcache and os.path.exists(dcache):
            with np.load(dcache) as z:
                if z["todo"].shape == todo.shape and np.array_equal(z["todo"], todo):
                    delta[todo] = z["delta"][todo]
        if not np.any(delta[todo]):
            delta[todo] = Ed[todo] - runtime_double(M[todo], MU[todo])
            if dcache:
                np.savez(dcache, todo=todo, delta=delta)
        probe_max = float(np.max(np.abs(delta[probe]))) if probe.any() else 0.0
        delta[~sel] = 0.0
    shrink = np.sign(delta) * np.maximum(np.abs(delta) - a, 0.0) if np.isfinite(a) else 0 * D
    Dt = D + shrink
    floored = Dt < 0.5 * D
    Dt = np.where(floored, 0.5 * D, Dt)
    t2 = time.perf_counter()
    common = (
        f"nx={NX} nv={NV}; model deficit by scripts/deficit_reference.py (positive integral; "
        f"lobe spline {N_LOBE} nodes, second-bounce spline {NZ}, dy={ref.DY}, "
        f"dphi={ref.DPHI}; mu = 0 column at mu = {MU_MIN:g})"
    )
    single = albedo.build_table(("single",), Ds, info="terms=('single',) " + common, D_model=Ds)
    path_s = albedo.save_table(single)
    info = (
        f"terms=('double','single') {common}; closure budget a = {a:g}: D = D_model + "
        f"S_a(E_double - E_double,rt), E_double,rt at the runtime default order by the "
        f"half-vector rule at {int(np.sum(np.abs(delta) > 0))} nodes with E_double >= a/4; "
        f"max |delta| = {np.max(np.abs(delta)):.2e}, at the first node below a/4 "
        f"{probe_max:.2e}; nodes changed by the closure {int(np.sum(shrink != 0))}, floored at "
        f"D_model/2 {int(np.sum(floored))}"
    )
    table = albedo.build_table(("double", "single"), Dt, info=info, D_model=D)
    path = albedo.save_table(table)
    print(f"{path_s}\n{path}: {info}\nmodel {t1 - t0:.0f} s, closure {t2 - t1:.0f} s")
    print("D_avg(m) at m = 0, 1, 10, 100, 1e3, 1e4, 1e5, 1e6:")
    for mm in (0, 1, 10, 100, 1e3, 1e4, 1e5, 1e6):
        print(f"  {mm:>8g}: {float(np.exp(albedo.log_deficit_avg(table, mm))):.6e}")


if __name__ == "__main__":
    main()
