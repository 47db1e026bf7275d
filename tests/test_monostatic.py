"""The exact-backscatter kernel of ``ppr.mueller_brdf`` (``k_out`` the same array as ``k_in``,
``ppr.brdf._brdf._mono_core``).

Reference: the general kernel, which the rest of the suite checks against closed forms,
quadrature, brute force and the white furnace, called with ``k_in`` and ``k_out`` as two
separate traced arguments (so that it cannot take the monostatic kernel) and with the double
term from the same backscatter table (``"double:backscatter"``). The monostatic kernel
evaluates the same model in other algebra (every term as a function of ``k.n`` in the shared
frames ``e = normalize(n x k)``, then one rotation), so the two agree to rounding: values and
gradients, every term set, frame choice and material layout, including the stiff cases of
docs/physics/numerics.md.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr import Material, mueller_brdf
from ppr.brdf._brdf import _same_direction
from ppr.optics.polarimetry import cloude_eigenvalues

AL = 0.94 + 6.42j  # aluminium 532 nm
TIO2 = 2.67 + 0.0j
FULL_TABLE = ("single", "double:backscatter", "multiple")


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


N_STIFF = 10
"""Rows 0 .. N_STIFF - 1 of :func:`geometry` are stiff (and the last one)."""


def geometry(n=48, seed=0):
    """Random directions over the upper hemisphere of random normals, plus the stiff rows:
    normal incidence, grazing (k.n = 1e-4, 1e-7, exactly 0, 1e-6, 1e-5, 1e-3, 1e-2, and 1e-20
    and 1e-180: not grazing for float32's and float64's range respectively, where the double
    term's incidence variable asinh(2 tan theta) overflowed its derivative), and the z normal."""
    rng = np.random.default_rng(seed)
    nrm = unit(rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 2.0]))
    nrm[: n // 2] = [0.0, 0.0, 1.0]
    k = unit(rng.normal(size=(n, 3)))
    k = np.where(np.sum(k * nrm, -1, keepdims=True) < 0, -k, k)
    # stiff rows: normal incidence, grazing at three depths, along a tilted normal
    k[0] = nrm[0]
    for i, cz in enumerate((1e-4, 1e-7, 0.0, 1e-6, 1e-5, 1e-3, 1e-2, 1e-20, 1e-180), start=1):
        k[i] = [np.sqrt(1.0 - cz * cz), 0.0, cz]
    k[-1] = nrm[-1]
    fi = unit(np.cross(k, rng.normal(size=(n, 3))))
    fo = unit(np.cross(k, rng.normal(size=(n, 3))))
    return k, nrm, fi, fo


def materials(n, dt):
    cdt = np.complex64 if dt == np.float32 else np.complex128
    rng = np.random.default_rng(1)
    m = np.exp(rng.uniform(np.log(0.01), np.log(500.0), n))
    m[::3] = 1e6  # the stiff ends of the exponent
    m[1::7] = 0.0
    per = Material(
        np.asarray(rng.uniform(1.3, 2.7, n) + 1j * rng.uniform(0.0, 4.0, n), cdt),
        np.asarray(m, dt),
    )
    return {
        "Al m=3": Material(np.asarray(AL, cdt), np.asarray(3.0, dt)),
        "TiO2 m=0": Material(np.asarray(TIO2, cdt), np.asarray(0.0, dt)),
        "Al m=1e6": Material(np.asarray(AL, cdt), np.asarray(1e6, dt)),
        "per element": per,
        "ideal white": Material.ideal_white(np.asarray(10.0, dt)),
    }


@functools.partial(jax.jit, static_argnames=("terms",))
def general(k_in, k_out, nrm, mat, fi, fo, *, terms):
    """The general kernel: k_in and k_out are different tracers."""
    return mueller_brdf(k_in, k_out, nrm, mat, terms=terms, frame_in=fi, frame_out=fo)


def rel_err(a, b):
    """Max |a - b| over each matrix's largest |b| entry (floored at 1e-12 of the batch's)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = np.abs(b).max(axis=(-2, -1), keepdims=True)
    scale = np.maximum(scale, 1e-12 * np.abs(b).max()) + 1e-300
    return float(np.max(np.abs(a - b) / scale))


# (material, terms, frames): frames "none" (defaults), "both" (random), "in" (frame_in only)
CASES = [
    ("Al m=3", None, "none"),
    ("per element", None, "both"),
    ("ideal white", ("single", "double:backscatter"), "in"),
]


@pytest.mark.parametrize("name,terms,frames", CASES)
def test_monostatic_kernel_equals_general_kernel(name, terms, frames):
    """float64: the two kernels agree to 1e-10 of each matrix's largest entry, the outputs
    are realizable, and exactly grazing rows are 0. Measured: <= 2e-15 compiled with JAX's
    defaults; 6.7e-12 under the suite's unoptimized compilation (tests/compile_level.py), on
    the normal-incidence row, where the double term's one-material table contraction (a
    low-rank basis whose terms cancel) rounds differently in the two programs (the double
    term there moves by 1.6e-11 of itself between programs compiled that way)."""
    k, nrm, fi, fo = geometry()
    mat = materials(len(k), np.float64)[name]
    fi_, fo_ = {"none": (None, None), "both": (fi, fo), "in": (fi, None)}[frames]
    mono = np.asarray(mueller_brdf(k, k, nrm, mat, terms=terms, frame_in=fi_, frame_out=fo_))
    gen_terms = FULL_TABLE if terms is None else terms
    ref = np.asarray(general(k, k.copy(), nrm, mat, fi_, fo_, terms=gen_terms))
    assert np.all(np.isfinite(mono))
    assert rel_err(mono, ref) <= 1e-10
    assert np.all(mono[3] == 0.0)  # k.n = 0 exactly
    if terms is None:
        lam = np.asarray(cloude_eigenvalues(mono))
        assert np.all(lam >= -1e-9 * np.abs(mono[..., 0, 0])[..., None])


def test_monostatic_gradients_float64():
    """Gradients in the direction (through both k_in and k_out), the normal, m and n, per
    element (m = 0, 1e6 and between): finite on every row, the stiff ones included (normal
    incidence, grazing from k.n = 1e-2 down to 0), and the directional derivative along a random
    direction of all inputs (the stiff rows held fixed, m scaled so that m = 0 stays 0) equal
    to central differences per row to 1e-5 relative. With the values equal to the general
    kernel's (above), the derivatives are then the same model's."""
    k, nrm, _, _ = geometry(24)
    mat = materials(len(k), np.float64)["per element"]
    args = (k, nrm, np.asarray(mat.m), np.asarray(jnp.real(mat.n)), np.asarray(jnp.imag(mat.n)))
    w = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)))

    @jax.jit
    def value_and_grad(*a):
        def f(k, nrm, m, n_re, n_im):
            M = mueller_brdf(k, k, nrm, Material(n_re + 1j * n_im, m))
            rows = jnp.sum(w * M, axis=(-2, -1))  # rows are independent: per-row gradients
            return jnp.sum(rows), rows

        return jax.value_and_grad(f, argnums=(0, 1, 2, 3, 4), has_aux=True)(*a)

    grads = [np.asarray(g) for g in value_and_grad(*args)[1]]
    for g in grads:
        assert np.all(np.isfinite(g))
    rng = np.random.default_rng(3)
    smooth = np.ones(len(k))
    smooth[:N_STIFF] = smooth[-1] = 0.0  # normal incidence (a cusp) and grazing rows
    dirs = [rng.normal(size=a.shape) * smooth.reshape((-1,) + (1,) * (a.ndim - 1)) for a in args]
    dirs[2] = dirs[2] * args[2]  # m: relative steps (m >= 0 is enforced)
    h = 1e-5
    plus = value_and_grad(*(a + h * d for a, d in zip(args, dirs, strict=True)))[0][1]
    minus = value_and_grad(*(a - h * d for a, d in zip(args, dirs, strict=True)))[0][1]
    fd = np.asarray(plus - minus) / (2.0 * h)
    ad = sum(np.sum((g * d).reshape(len(k), -1), axis=1) for g, d in zip(grads, dirs, strict=True))
    assert np.all(np.abs(ad - fd) <= 1e-5 * np.abs(ad) + 1e-9 * np.abs(ad).max())


def test_monostatic_float32_values_and_gradients():
    """float32, one material (the tabulated visibility and double-term paths), default
    frames: values within 2e-4 of each matrix's largest entry of float64 away from grazing
    (measured ~1e-5), and finite gradients in the direction, the normal, m and n on the stiff
    rows at m = 0, 3 and 1e6 (values and gradients from one compiled program)."""
    k, nrm, _, _ = geometry()
    ok = np.arange(len(k)) >= N_STIFF  # grazing rows: float32 c has no digits left at 1e-7
    k32, n32 = k.astype(np.float32), nrm.astype(np.float32)
    w = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)), jnp.float32)

    @jax.jit
    def value_and_grad(k, nrm, m, n_re, n_im):
        def f(k, nrm, m, n_re, n_im):
            M = mueller_brdf(k, k, nrm, Material(n_re + 1j * n_im, m))
            return jnp.sum(w * M), M

        return jax.value_and_grad(f, argnums=(0, 1, 2, 3, 4), has_aux=True)(
            k, nrm, m, n_re, n_im
        )

    for m, n in ((0.0, TIO2), (3.0, AL), (1e6, AL)):
        f32 = np.float32
        (_, out32), grads = value_and_grad(k32, n32, f32(m), f32(n.real), f32(n.imag))
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g)))
        assert np.asarray(out32).dtype == np.float32
        out64 = mueller_brdf(k, k, nrm, Material(n, np.float64(m)))
        assert rel_err(np.asarray(out32)[ok], np.asarray(out64)[ok]) <= 2e-4


def test_same_direction_detection():
    """The kernel is chosen for the same array, or concrete arrays with equal entries; never
    for different values, shapes or dtypes."""
    k = np.asarray([[0.0, 0.6, 0.8], [0.0, 0.0, 1.0]])
    assert _same_direction(k, k)
    assert _same_direction(k, k.copy())
    assert _same_direction(jnp.asarray(k), np.array(k))
    assert not _same_direction(k, k[::-1])
    assert not _same_direction(k, k[:1])
    assert not _same_direction(k, k.astype(np.float32))
    traced = []
    jax.jit(lambda a, b: traced.append((_same_direction(a, a), _same_direction(a, b))) or a)(
        k, k
    )
    assert traced == [(True, False)]


def test_monostatic_sensor_flag():
    """``Sensor.make()`` at zero bistatic angle is exactly monostatic (``receiver_dir`` a copy
    of ``laser_dir``, ``monostatic`` derived True: rendered with the exact-backscatter kernel;
    the render tests of tests/test_pulse.py run through it against their references); a
    bistatic sensor is not; ``monostatic=True`` with unequal directions is an error naming the
    field."""
    import ppr

    sensor = ppr.Sensor.make((0.3, -0.2, -1.0))
    assert sensor.monostatic
    assert np.array_equal(np.asarray(sensor.laser_dir), np.asarray(sensor.receiver_dir))
    assert not ppr.Sensor.make((0, 0, -1.0), bistatic_angle=1e-5).monostatic
    cast = jax.tree_util.tree_map(lambda a: a.astype(np.float32), sensor)
    assert cast.monostatic  # a static field: kept by tree maps and under jit
    with pytest.raises(ValueError, match="Sensor.monostatic"):
        ppr.Sensor([0, 0, 1.0], [0, 0.6, 0.8], [1.0, 0, 0], [1.0, 0, 0], monostatic=True)
