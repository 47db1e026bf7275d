"""No NaN anywhere near the horizon: values and gradients of every BRDF term on a dense grid of
grazing and stiff geometries, float32 and float64 (docs/physics/numerics.md's stiff set).

One jitted value-and-gradient program per dtype evaluates, on the same rows,

* the single bounce and the multiple-scattering remainder with a per-element material (the
  lobe-average quadrature of ``ppr.microfacet`` and the per-element deficit table),
* the same with one (scalar) material per call, ``vmap``-ed over the materials (the
  one-material paths: the per-call visibility table in float32, the deficit row),
* the double term with a per-element material (its quadrature, ``"double:quadrature"``: the
  branch ``"double"`` takes on these rows, which are not all within ``PSI_MAX`` of
  backscatter),

and the reverse-mode gradient of everything with respect to ``k_in``, ``k_out``, the normal,
``m`` and both parts of ``n``. The exact-backscatter kernel and the double term's table
are covered on the same grazing cosines by tests/test_monostatic.py and
tests/test_double_table.py. Rows:

* grazing: ``k.n`` in {1e-6, 1e-5, 1e-4, 1e-3, 1e-2} for one or both directions (the other at
  60 deg or along the normal), bistatic azimuths 0 (toward backscatter), 90 deg and 180 deg
  (forward: with equal cosines the specular direction), plus exact backscatter given as two
  arrays (the general kernel) and near-specular rows whose out-of-plane component is the
  1e-16 that ``sin(pi)`` leaves;
* stiff: normal incidence, 89.9 and 89.999 deg, exactly tangent (``k.n = 0``: the BRDF is
  0), cosines of 1e-20 (not grazing for float32's range: the specular value stays positive),
  the exact forward direction (degenerate half vector);
* ``m`` in {0, 1e-3, 1, 30, 1e3, 1e4, 1e6}, indices aluminium, glass, 0.2 + 7i, 1 + 10i and 1
  (no contrast);
* 16 random geometries (4 at exact backscatter) on which float32 agrees with float64.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ppr import Material
from ppr.brdf._brdf import mueller_brdf

AL = 0.94 + 6.42j  # aluminium 532 nm
INDICES = [AL, 1.5 + 0j, 0.2 + 7j, 1.0 + 10j, 1.0 + 0j]
GRAZING = [1e-6, 1e-5, 1e-4, 1e-3, 1e-2]
OTHER = [0.5, 1.0]
AZIMUTHS = [0.0, 0.5 * np.pi, np.pi]
M_VALUES = [0.0, 1e-3, 1.0, 30.0, 1e3, 1e4, 1e6]
CORE = ("single", "multiple")
NAMES = ("k_in", "k_out", "normal", "m", "n_re", "n_im")


def _dir(c, phi):
    s = np.sqrt((1.0 - c) * (1.0 + c))
    return np.array([s * np.cos(phi), s * np.sin(phi), c])


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def geometries():
    """``(k_in, k_out)`` pairs of the grid and the stiff rows (module docstring)."""
    pairs = []
    for ci, co, ph in itertools.product(GRAZING, GRAZING + OTHER, AZIMUTHS):
        pairs.append((_dir(ci, 0.0), _dir(co, ph)))
    for ci, co, ph in itertools.product(OTHER, GRAZING, AZIMUTHS):
        pairs.append((_dir(ci, 0.0), _dir(co, ph)))
    for c in GRAZING + OTHER:
        k = _dir(c, 0.7)
        pairs.append((k, k.copy()))  # exact backscatter, two arrays: the general kernel
    for c in np.cos(np.deg2rad([0.0, 89.9, 89.999])):
        k = _dir(c, 0.0)
        pairs.append((k, _dir(c, 0.0)))
        pairs.append((k, np.array([-k[0], 0.0, k[2]])))  # specular, exactly in plane
        pairs.append((k, _dir(np.cos(np.deg2rad(40.0)), 2.0)))
    pairs.append((np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])))  # tangent, forward
    pairs.append((np.array([1.0, 0.0, 0.0]), _unit([0.2, 0.1, 1.0])))  # one tangent
    pairs.append((_unit([1.0, 0.0, 1e-20]), _unit([-1.0, 0.0, 1e-20])))  # 1e-20, specular
    pairs.append((_unit([1.0, 0.0, 1e-20]), _unit([1.0, 0.0, 1e-20])))  # 1e-20, backscatter
    ki = np.stack([p[0] for p in pairs])
    ko = np.stack([p[1] for p in pairs])
    return ki, ko


def random_rows(n=16, seed=8):
    """Random geometries (the first 4 at exact backscatter) and materials for the float32 vs
    float64 comparison."""
    rng = np.random.default_rng(seed)
    def draw():  # incidence 0-80 deg, any azimuth
        t, p = rng.uniform(0.0, np.deg2rad(80.0), n), rng.uniform(0.0, 2.0 * np.pi, n)
        return np.stack([_dir(np.cos(a), b) for a, b in zip(t, p, strict=True)])

    ki, ko = draw(), draw()
    ko[:4] = ki[:4]
    return ki, ko, np.array([0.5, 2.0, 10.0, 50.0] * (n // 4)), np.full(n, AL)


def rows():
    """Per-element rows: every geometry at every m (indices cycling), then the random rows."""
    ki, ko = geometries()
    g = len(ki)
    m = np.repeat(M_VALUES, g)
    n = np.array([INDICES[i % len(INDICES)] for i in range(len(m))])
    ki, ko = np.tile(ki, (len(M_VALUES), 1)), np.tile(ko, (len(M_VALUES), 1))
    rk, rko, rm, rn = random_rows()
    return (
        np.concatenate([ki, rk]),
        np.concatenate([ko, rko]),
        np.concatenate([m, rm]),
        np.concatenate([n, rn]),
        len(rk),
    )


@functools.cache
def _program(dtype):
    cdt = jnp.complex64 if dtype == jnp.float32 else jnp.complex128

    def material(m, n_re, n_im):
        return Material(n=(n_re + 1j * n_im).astype(cdt), m=m)

    def terms(per_element, one_material):
        ki, ko, nrm, m, n_re, n_im = per_element
        mat = material(m, n_re, n_im)
        core = mueller_brdf(ki, ko, nrm, mat, terms=CORE)
        # the quadrature: what "double" runs on this mixed batch (not every row is within
        # PSI_MAX of backscatter), without the table branch its lax.cond would also trace,
        # differentiate and compile (3-4x the trace time) but never run here
        double = mueller_brdf(ki, ko, nrm, mat, terms=("double:quadrature",))
        gk, gko, gn, ms, ns_re, ns_im = one_material

        def one(m, n_re, n_im):  # a scalar material: the one-material paths
            return mueller_brdf(gk, gko, gn, material(m, n_re, n_im), terms=CORE)

        return core, double, jax.vmap(one)(ms, ns_re, ns_im)

    @jax.jit
    def values_and_gradients(per_element, one_material):
        # every output entry, and the gradient of their sum with respect to every input
        # (reverse mode, as jax.grad), from the same linearization
        out, pullback = jax.vjp(terms, per_element, one_material)
        return out, pullback(jax.tree_util.tree_map(jnp.ones_like, out))

    return values_and_gradients


@functools.cache
def run(dtype):
    """Values and gradients of the grid in ``dtype`` (one compilation per dtype)."""
    ki, ko, m, n, _ = rows()
    gk, gko = geometries()
    z = np.broadcast_to([0.0, 0.0, 1.0], ki.shape)
    gz = np.broadcast_to([0.0, 0.0, 1.0], gk.shape)
    ns = np.array([INDICES[i % len(INDICES)] for i in range(len(M_VALUES))])
    per_element = tuple(jnp.asarray(a, dtype) for a in (ki, ko, z, m, n.real, n.imag))
    one = tuple(jnp.asarray(a, dtype) for a in (gk, gko, gz, M_VALUES, ns.real, ns.imag))
    out, grads = _program(dtype)(per_element, one)
    return jax.tree_util.tree_map(np.asarray, (out, grads))


def test_grazing_and_stiff_geometry_finite_values_and_gradients_float32_matches_float64():
    """Finite values and gradients (every input) on every row, both dtypes; exactly tangent
    directions give 0; the 1e-20 specular rows keep a positive value in float32; M00 >= 0;
    on the random rows the double term in float32 agrees with float64 to 1e-4 of its M00
    (float32 rounding through the 216-node sum and the lobe powers)."""
    ki, ko, m, _, n_random = rows()
    gk, gko = geometries()
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        (core, double, one), (g_el, g_one) = run(dtype)
        for name, v in (("core", core), ("double", double), ("one material", one)):
            assert v.dtype == np.dtype(dtype)
            bad = ~np.isfinite(v).all(axis=(-2, -1))
            assert not bad.any(), (dtype, name, np.argwhere(bad)[:5].tolist())
            # M00 >= 0 up to the float rounding of a sum of positive terms
            assert np.all(v[..., 0, 0] >= -1e-6 * np.abs(v[..., 0, 0]).max()), (dtype, name)
        for which, grads in (("per element", g_el), ("one material", g_one)):
            for name, g in zip(NAMES, grads, strict=True):
                assert g.dtype == np.dtype(dtype)
                bad = ~np.isfinite(g)
                assert not bad.any(), (dtype, which, name, np.argwhere(bad)[:5].tolist())
        tangent = (ki[:, 2] == 0.0) | (ko[:, 2] == 0.0)
        assert np.all(core[tangent] == 0.0) and np.all(double[tangent] == 0.0)
        g_tangent = (gk[:, 2] == 0.0) | (gko[:, 2] == 0.0)
        assert np.all(one[:, g_tangent] == 0.0)
        # cosines of 1e-20 are not grazing (> _grazing(dtype)): at the specular direction
        # (h = n, the lobe's peak) the log-space products keep a positive value in float32
        tiny_spec = (ki[:, 2] < 1e-19) & (ki[:, 2] > 0) & (ko[:, 0] == -ki[:, 0])
        assert tiny_spec.sum() == len(M_VALUES) and np.all(core[tiny_spec, 0, 0] > 0)
        out[dtype] = double[-n_random:]
    a, b = out[jnp.float32], out[jnp.float64]
    scale = b[:, 0, 0][:, None, None]
    assert np.all(scale > 0)
    np.testing.assert_allclose(a / scale, b / scale, atol=1e-4)
