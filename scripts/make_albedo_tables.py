"""Regenerate the white-surface albedo tables ``ppr/data/albedo_<terms>.npz``.

    python scripts/make_albedo_tables.py                 # explicit terms implemented now
    python scripts/make_albedo_tables.py --terms single  # a given set of explicit terms

For every grid node ``(m, mu)`` of :func:`ppr.brdf.albedo.grid_nodes` it integrates the M00 of
``ppr.mueller_brdf(..., Material.ideal_white(m), terms=<explicit terms>)`` times ``k'.n`` over
the outgoing hemisphere with the half-vector quadrature of :func:`ppr.brdf.albedo.albedo_nodes`
(float64), stores the deficit ``D = 1 - E`` and its hemispherical average, and reports the
quadrature's self-convergence (the same nodes at doubled order).
"""

from __future__ import annotations

import argparse
import functools
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ppr.brdf import (  # noqa: E402
    albedo,  # noqa: E402
    explicit_terms,
    mueller_brdf,
)
from ppr.brdf._brdf import _single_scalar3  # noqa: E402  (the white single-term kernel)
from ppr.materials import Material  # noqa: E402

NX, NV = 40, 48
N_PHI, N_W = 24, 12


@functools.cache
def make_f00(terms):
    """Scalar white BRDF of the explicit terms. The single term's white M00 is exactly its
    scalar factor (the perfect-conductor facet has M00 = 1), evaluated by the same kernel
    without the 4x4 assembly; other terms go through ``mueller_brdf``."""

    @jax.jit
    def f00(k_in, k_out, m):
        k_in, k_out, m = jnp.broadcast_arrays(k_in, k_out, m[..., None])
        m = m[..., 0]
        normal = jnp.zeros_like(k_in).at[..., 2].set(1.0)
        split = lambda v: (v[..., 0], v[..., 1], v[..., 2])  # noqa: E731
        out = jnp.zeros(m.shape, k_in.dtype)
        for t in terms:
            if t == "single":
                out = out + _single_scalar3(split(k_in), split(k_out), split(normal), m)[0]
            else:
                mat = Material.ideal_white(m)
                out = out + mueller_brdf(k_in, k_out, normal, mat, terms=(t,))[..., 0, 0]
        return out

    return f00


def node_values(terms, m, mu, n_phi=N_PHI, n_w=N_W):
    """Deficit ``1 - E`` at each ``(m, mu)`` (broadcast) by the half-vector quadrature."""
    f00 = make_f00(terms)
    m, mu = np.broadcast_arrays(np.asarray(m, float), np.asarray(mu, float))
    out = np.empty(m.shape)
    flat_m, flat_mu, flat_out = m.ravel(), mu.ravel(), out.reshape(-1)
    chunk = 16
    for s in range(0, flat_m.size, chunk):
        sl = slice(s, s + chunk)
        # mu = 0 exactly is grazing (BRDF masked to 0): tabulate the limit mu -> 0+
        mu_q = np.maximum(flat_mu[sl], 1e-9)
        E = albedo.directional_albedo(f00, flat_m[sl], mu_q, n_phi, n_w)
        flat_out[sl] = 1.0 - E
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--terms", default=None, help="comma-separated explicit terms")
    ap.add_argument("--nx", type=int, default=NX)
    ap.add_argument("--nv", type=int, default=NV)
    args = ap.parse_args(argv)
    terms = tuple(sorted(args.terms.split(","))) if args.terms else explicit_terms()
    x, v, m, mu = albedo.grid_nodes(args.nx, args.nv)
    t0 = time.perf_counter()
    D = node_values(terms, m[:, None], mu[None, :])
    t1 = time.perf_counter()
    # self-convergence on a sub-grid: doubled quadrature orders
    sub = (slice(None, None, 5), slice(None, None, 6))
    D2 = node_values(terms, m[:, None][sub[0]], mu[None, :][:, sub[1]], 2 * N_PHI, 2 * N_W)
    conv = float(np.max(np.abs(D2 - D[sub])))
    info = (
        f"terms={terms} nx={args.nx} nv={args.nv} n_phi={N_PHI} n_w={N_W} "
        f"max |E(order) - E(2 x order)| on a sub-grid = {conv:.2e}"
    )
    table = albedo.build_table(terms, D, info=info)
    path = albedo.save_table(table)
    print(f"{path}: {info}; {t1 - t0:.1f} s")
    print("D_avg(m) at m = 0, 1, 10, 100, 1e3, 1e4, 1e5, 1e6:")
    for mm in (0, 1, 10, 100, 1e3, 1e4, 1e5, 1e6):
        print(f"  {mm:>8g}: {float(albedo.deficit_avg(table, jnp.asarray(mm))):.6e}")


if __name__ == "__main__":
    main()
