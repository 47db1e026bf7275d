"""The multiple-scattering remainder and the deficit it is built from, against an independent
high-precision reference (docs/physics/multiple_scattering.md).

Reference: ``tests/data/deficit_reference.npz``, written by ``scripts/deficit_reference.py``:
the white deficit ``D = 1 - E_single - E_double`` of the model as a positive integral (the
probability that light is still inside the surface after one or two facets), lobe integrals
from their definition in mpmath, kink-aligned composite Gauss-Legendre, its hemispherical
average ``D_avg``; no code of ppr's BRDF, tables or quadratures. Grid: m in {0, 1, 10, 100,
1000, 1e4} (all but 0 off the table's nodes) and 24 incidences 0-89.98 deg (m = 1000 included:
60-89.98 deg in 20 steps).

Tolerances (relative, by band of the reference deficit): the table's interpolation of ``log D``
is measured at <= 4e-3 where ``D >= 1e-8`` (the physically visible range: the remainder there
is at least 1e-16 / D_avg), a few percent down to 1e-40 and within a factor 2 down to 1e-250
(the deepest tails, e.g. normal incidence at m = 1e4, where nothing can see it). The remainder
``D(k) D(k') / (pi D_avg)`` compounds two deficits and ``D_avg``.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr.brdf import albedo as _albedo
from ppr.brdf import explicit_terms, mueller_brdf
from ppr.materials import Material

Z = np.array([0.0, 0.0, 1.0])
# (lower end of the band of D_ref, relative tolerance of D)
TIERS = ((1e-8, 5e-3), (1e-40, 5e-2), (1e-250, 1.0))


@functools.cache
def _ref():
    with np.load(os.path.join(os.path.dirname(__file__), "data", "deficit_reference.npz")) as z:
        return {k: z[k] for k in z.files}


def _tables():
    table = _albedo.load_table(explicit_terms())
    return table, replace(table, L_pad=table.Lm_pad)


def _model_log_avg(model, m):
    """``log D_avg`` of the model deficit's own interpolant (the table's ``log D_avg`` nodes
    integrate the deficit with the closure)."""
    x = np.log1p(np.atleast_1d(np.asarray(m, float)))
    return float(
        _albedo._log_avg_at_x(model.L_pad, model.x_lo, model.dx, model.nx, model.v_nodes, x)[0]
    )


def _check_tiers(got, want, mult=1.0, what=""):
    """Relative error within the tier of ``want`` (the reference deficit's band)."""
    for lo, tol in TIERS:
        hi = {1e-8: np.inf, 1e-40: 1e-8, 1e-250: 1e-40}[lo]
        sel = (want[1] >= lo) & (want[1] < hi)
        if sel.any():
            err = np.abs(got[sel] / want[0][sel] - 1.0)
            assert err.max() <= mult * tol, (what, lo, err.max(), np.nonzero(sel)[0][err.argmax()])


def test_model_deficit_against_reference():
    """The tabulated model deficit (single + double, and single alone) against the reference
    at every (m, incidence) of the reference grid, by tiers of D (module docstring); positive
    everywhere (no holes)."""
    REF = _ref()
    _, model = _tables()
    single = _albedo.load_table(("single",))
    for i, m in enumerate(REF["m"]):
        mu = np.cos(np.deg2rad(REF["theta_deg"]))
        mm = np.full_like(mu, m)
        d = np.asarray(_albedo.deficit(model, mm, mu))
        ds = np.asarray(_albedo.deficit(single, mm, mu))
        assert np.all(d > 0) and np.all(ds > 0)
        _check_tiers(d, (REF["D"][i], REF["D"][i]), what=f"D, m={m:g}")
        # the single term's deficit is steeper in the tails (kappa_single < kappa): measured
        # 1.0e-2 at m = 100, 30 deg
        _check_tiers(
            ds, (REF["D_single"][i], REF["D_single"][i]), mult=3.0, what=f"D_single, m={m:g}"
        )


def test_deficit_avg_against_reference():
    """``D_avg(m)`` of the model table (integral of its interpolant) against the reference's
    own integral of the reference deficit."""
    REF = _ref()
    _, model = _tables()
    x = np.log1p(REF["m"])
    la = _albedo._log_avg_at_x(model.L_pad, model.x_lo, model.dx, model.nx, model.v_nodes, x)
    np.testing.assert_allclose(np.exp(la), REF["D_avg"], rtol=2e-3)


def test_remainder_at_backscatter_against_reference():
    """White remainder at exact backscatter, ``ppr.mueller_brdf(terms=("multiple",))``, in
    float64, against ``R_ref = D_ref^2 / (pi D_avg,ref)`` times the closure factor of the table
    (``(D / D_model)^2 D_avg,model / D_avg`` from the table's two interpolants: the part of the
    double term's quadrature error the remainder absorbs, docs/physics/multiple_scattering.md);
    positive everywhere. Where the closure is inactive (the factor is 1) this is the reference
    itself up to the ratio of the two D_avg; m = 1000, 60-75 deg are checked to be so (the closure
    starts at 77.5 deg there: factor 1.0002, 1.004 at 80 deg)."""
    REF = _ref()
    table, model = _tables()
    for i, m in enumerate(REF["m"]):
        th = np.deg2rad(REF["theta_deg"])
        mu = np.cos(th)
        k = np.stack([np.sin(th), 0.0 * th, mu], -1)
        r = np.asarray(mueller_brdf(k, k, Z, Material.ideal_white(float(m)), terms=("multiple",)))
        assert np.all(r[:, 1:, :] == 0) and np.all(r[:, :, 1:] == 0)  # ideal depolarizer
        r = r[:, 0, 0]
        mm = np.full_like(mu, m)
        closure = np.exp(
            2 * (_albedo.log_deficit(table, mm, mu) - _albedo.log_deficit(model, mm, mu))
        ) * float(np.exp(_model_log_avg(model, m) - _albedo.log_deficit_avg(table, m)))
        d_ref = REF["D"][i]
        r_ref = d_ref**2 / (math.pi * REF["D_avg"][i])
        # positive wherever float64 holds the reference value (D^2 underflows below 1e-308:
        # m = 1e4 below 45 deg, where D_ref < 1e-150)
        ok = closure * r_ref > 1e-300
        assert np.all(r[ok] > 0), m
        # two deficits and D_avg: twice the deficit's tolerance (and the model table's D_avg)
        _check_tiers(
            r[ok], ((closure * r_ref)[ok], d_ref[ok]), mult=2.0 + 1.0, what=f"R, m={m:g}"
        )
        if m == 1000.0:
            band = (REF["theta_deg"] >= 60) & (REF["theta_deg"] <= 75)
            np.testing.assert_allclose(closure[band], closure[band][0], rtol=1e-12)


@jax.jit
def _remainder_and_grads(k, kp, m):
    """White remainder at backscatter (the exact-backscatter kernel) and the gradient of a
    bistatic total with respect to ``k_in`` and ``m`` (the general kernel)."""
    z = jnp.zeros_like(k).at[..., 2].set(1.0)

    def total(k, m):
        f = mueller_brdf(k, kp, z, Material.ideal_white(m), terms=("multiple",))[..., 0, 0]
        return jnp.sum(jnp.log1p(f))

    grads = jax.grad(total, argnums=(0, 1))(k, m)
    mono = mueller_brdf(k, k, z, Material.ideal_white(m), terms=("multiple",))[..., 0, 0]
    return mono, grads


def test_remainder_positive_smooth_no_nan_float32_matches_float64():
    """m = 10, 1000 (the issue's case) and 1e4: the remainder at backscatter on a dense
    incidence grid 0-89.99 deg is positive wherever the float32 range holds it (no zero run
    like the former table's clamped holes at 62-75 deg), value and gradient of a bistatic total
    (d/dk_in, d/dm) are finite in both dtypes, and float32 matches float64 to 1e-4 relative
    where the value is above 1e-30 /sr (2e-4 relative)."""
    th = np.deg2rad(np.linspace(0.0, 89.99, 181))
    k = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    kp = np.stack([np.sin(th) * np.cos(1.0), np.sin(th) * np.sin(1.0), np.cos(th)], -1)
    for m in (10.0, 1000.0, 1e4):
        out = {}
        for dt in (np.float32, np.float64):
            mono, (gk, gm) = _remainder_and_grads(
                jnp.asarray(k, dt), jnp.asarray(kp, dt), jnp.asarray(m, dt)
            )
            assert np.all(np.isfinite(np.asarray(gk))) and np.isfinite(float(gm)), (m, dt)
            mono = np.asarray(mono, np.float64)
            assert np.all(np.isfinite(mono)) and np.all(mono >= 0)
            out[dt] = mono
        r64, r32 = out[np.float64], out[np.float32]
        big = r64 > 1e-30
        assert np.all(r32[big] > 0), m
        # log D ~ -300 in float32 carries ~2e-5 relative; measured 1.07e-4 (m = 1e4, 60 deg)
        np.testing.assert_allclose(r32[big], r64[big], rtol=2e-4, err_msg=f"m={m}")
        # strictly positive in float64 wherever D^2 / D_avg stays above the float64 range
        # (from 30 deg at m <= 1000, from 60 deg at m = 1e4: D(1e4, 60 deg) = 3.6e-141)
        assert np.all(r64[th > (0.5 if m <= 1000 else 1.05)] > 0), m


@pytest.mark.parametrize("m", [0.0, 30.0, 1000.0])
def test_remainder_white_albedo_is_the_deficit(m):
    """``int f_ms (k'.n) d omega' = D(k)`` (white): the remainder's energy is the tabulated
    deficit, independently of the table's error (D_avg is the integral of the interpolant;
    the fine D_avg grid's interpolation is the only slack, measured <= 2e-6 relative)."""
    table, _ = _tables()
    x, w = np.polynomial.legendre.leggauss(64)
    v0, v1 = table.v_lo, table.v_lo + table.dv * (table.nv - 1)
    edges = np.linspace(v0, v1, table.nv)
    a, b = edges[:-1, None], edges[1:, None]
    v = (0.5 * (b - a) * x + 0.5 * (a + b)).ravel()
    wv = (0.5 * (b - a) * w).ravel()
    mu_o = _albedo.unwarp_v(v)
    dmu = 1.0 / (1.0 / (mu_o + _albedo.MU0) + _albedo.ALPHA)
    s = np.sqrt(1 - mu_o**2)
    ko = np.stack([s, 0 * s, mu_o], -1)
    for th in (20.0, 70.0, 85.0, 89.5):
        ki = np.broadcast_to([np.sin(np.deg2rad(th)), 0.0, np.cos(np.deg2rad(th))], ko.shape)
        f = np.asarray(
            mueller_brdf(ki, ko, Z, Material.ideal_white(m), terms=("multiple",))[..., 0, 0]
        )
        e = 2 * math.pi * np.sum(f * mu_o * dmu * wv)  # azimuth-independent lobe
        d = float(_albedo.deficit(table, m, np.cos(np.deg2rad(th))))
        np.testing.assert_allclose(e, d, rtol=5e-6, atol=1e-300)
