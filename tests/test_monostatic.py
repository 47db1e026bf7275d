"""The exact-backscatter kernel of ``ppr.mueller_brdf`` (``k_out`` the same array as ``k_in``,
``ppr._brdf._mono_core``).

Reference: the general kernel, which the rest of the suite checks against closed forms,
quadrature, brute force and the white furnace, called with ``k_in`` and ``k_out`` as two
separate traced arguments (so that it cannot take the monostatic kernel) and with the double
term from the same backscatter table (``"double:backscatter"``). The monostatic kernel
evaluates the same model in other algebra (every term as a function of ``k.n`` in the shared
frames ``e = normalize(n x k)``, then one rotation), so the two agree to rounding: values and
gradients, every term set, frame choice and material layout, including the stiff cases of
PHYSICS.md section 10.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr import Material, mueller_brdf
from ppr._brdf import _same_direction
from ppr._polarimetry import cloude_eigenvalues

AL = 0.94 + 6.42j  # aluminium 532 nm
TIO2 = 2.67 + 0.0j
FULL_TABLE = ("single", "double:backscatter", "multiple")


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def geometry(n=48, seed=0):
    """Random directions over the upper hemisphere of random normals, plus the stiff rows:
    normal incidence, grazing (k.n = 1e-4, 1e-7, exactly 0), and the z normal."""
    rng = np.random.default_rng(seed)
    nrm = unit(rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 2.0]))
    nrm[: n // 2] = [0.0, 0.0, 1.0]
    k = unit(rng.normal(size=(n, 3)))
    k = np.where(np.sum(k * nrm, -1, keepdims=True) < 0, -k, k)
    # stiff rows: normal incidence, grazing at three depths, along a tilted normal
    k[0] = nrm[0]
    for i, cz in zip((1, 2, 3), (1e-4, 1e-7, 0.0), strict=True):
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
    ("TiO2 m=0", ("single", "multiple"), "in"),
    ("ideal white", ("single", "double:backscatter"), "none"),
]


@pytest.mark.parametrize("name,terms,frames", CASES)
def test_monostatic_kernel_equals_general_kernel(name, terms, frames):
    """float64: the two kernels agree to 1e-12 of each matrix's largest entry (measured
    <= 1.5e-14), the outputs are realizable, and exactly grazing rows are 0."""
    k, nrm, fi, fo = geometry()
    mat = materials(len(k), np.float64)[name]
    fi_, fo_ = {"none": (None, None), "both": (fi, fo), "in": (fi, None)}[frames]
    mono = np.asarray(mueller_brdf(k, k, nrm, mat, terms=terms, frame_in=fi_, frame_out=fo_))
    gen_terms = FULL_TABLE if terms is None else terms
    ref = np.asarray(general(k, k.copy(), nrm, mat, fi_, fo_, terms=gen_terms))
    assert np.all(np.isfinite(mono))
    assert rel_err(mono, ref) <= 1e-12
    assert np.all(mono[3] == 0.0)  # k.n = 0 exactly
    if terms is None:
        lam = np.asarray(cloude_eigenvalues(mono))
        assert np.all(lam >= -1e-9 * np.abs(mono[..., 0, 0])[..., None])


def test_monostatic_kernel_float32():
    """float32 against float64 of the same kernel (one material, the float32 tabulated
    visibility): 2e-4 of each matrix's largest entry, away from grazing (measured 2e-6); and
    against the float32 general kernel: 1e-4."""
    k, nrm, fi, fo = geometry()
    ok = np.arange(len(k)) > 3  # grazing rows: float32 c has no digits left at 1e-7
    for name in ("Al m=3",):
        m64 = materials(len(k), np.float64)[name]
        m32 = materials(len(k), np.float32)[name]
        k32, n32, fi32, fo32 = (a.astype(np.float32) for a in (k, nrm, fi, fo))
        out32 = np.asarray(mueller_brdf(k32, k32, n32, m32, frame_in=fi32, frame_out=fo32))
        out64 = np.asarray(mueller_brdf(k, k, nrm, m64, frame_in=fi, frame_out=fo))
        assert out32.dtype == np.float32
        assert rel_err(out32[ok], out64[ok]) <= 2e-4
        gen32 = general(k32, k32.copy(), n32, m32, fi32, fo32, terms=FULL_TABLE)
        assert rel_err(out32[ok], gen32[ok]) <= 1e-4


def _loss(fn, w):
    def f(k, nrm, m, n_re, n_im):
        mat = Material(n_re + 1j * n_im, m)
        return jnp.sum(w * fn(k, nrm, mat))

    return jax.jit(jax.grad(f, argnums=(0, 1, 2, 3, 4)))


def test_monostatic_gradients_float64():
    """Gradients in the direction (through both k_in and k_out), the normal, m and n, per
    element (m = 0, 1e6 and between): finite on every row, the stiff ones included (normal
    incidence, grazing down to k.n = 0), and the directional derivative along a random
    direction of all inputs (the stiff rows held fixed, m scaled so that m = 0 stays 0) equal
    to central differences per row to 1e-5 relative. With the values equal to the general
    kernel's (above), the derivatives are then the same model's."""
    k, nrm, _, _ = geometry(24)
    mat = materials(len(k), np.float64)["per element"]
    args = (k, nrm, np.asarray(mat.m), np.asarray(jnp.real(mat.n)), np.asarray(jnp.imag(mat.n)))
    w = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)))
    fn = lambda k, n, mat: mueller_brdf(k, k, n, mat)  # noqa: E731
    grads = [np.asarray(g) for g in _loss(fn, w)(*args)]
    for g in grads:
        assert np.all(np.isfinite(g))
    rng = np.random.default_rng(3)
    smooth = np.ones(len(k))
    smooth[:4] = smooth[-1] = 0.0  # normal incidence (a cusp) and grazing rows
    dirs = [rng.normal(size=a.shape) * smooth.reshape((-1,) + (1,) * (a.ndim - 1)) for a in args]
    dirs[2] = dirs[2] * args[2]  # m: relative steps (m >= 0 is enforced)

    @jax.jit
    def rows(*a):  # the loss per row: rows are independent, so its gradient is per row
        mat = Material(a[3] + 1j * a[4], a[2])
        return jnp.sum(w * fn(a[0], a[1], mat), axis=(-2, -1))

    h = 1e-5
    plus = rows(*(a + h * d for a, d in zip(args, dirs, strict=True)))
    minus = rows(*(a - h * d for a, d in zip(args, dirs, strict=True)))
    fd = np.asarray(plus - minus) / (2.0 * h)
    ad = sum(np.sum((g * d).reshape(len(k), -1), axis=1) for g, d in zip(grads, dirs, strict=True))
    assert np.all(np.abs(ad - fd) <= 1e-5 * np.abs(ad) + 1e-9 * np.abs(ad).max())


def test_monostatic_gradients_finite_float32():
    """float32, one material (the tabulated visibility and double-term paths): finite
    gradients on the stiff rows at m = 0, 3 and 1e6."""
    k, nrm, _, _ = (a.astype(np.float32) for a in geometry(24))
    w = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)), jnp.float32)
    grad = _loss(lambda k, n, mat: mueller_brdf(k, k, n, mat), w)
    for m, n in ((0.0, TIO2), (3.0, AL), (1e6, AL)):
        f32 = np.float32
        for g in grad(k, nrm, f32(m), f32(n.real), f32(n.imag)):
            assert np.all(np.isfinite(np.asarray(g)))


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


def test_monostatic_sensor_renders_as_the_general_kernel():
    """``Sensor.make()`` at zero bistatic angle is exactly monostatic (``monostatic`` True,
    derived from its directions), and its rendered Mueller profile (the exact-backscatter
    kernel) equals that of the same sensor marked not monostatic (the general kernel) to
    1e-12 of the profile's peak (float64, a 3U CubeSat with panels in a random attitude,
    three materials). A sensor flagged monostatic with unequal directions is an error naming
    the field."""
    import dataclasses

    import ppr
    from ppr import shapes

    sensor = ppr.Sensor.make((0.3, -0.2, -1.0))
    assert sensor.monostatic
    assert not ppr.Sensor.make((0, 0, -1.0), bistatic_angle=1e-5).monostatic
    general_sensor = dataclasses.replace(sensor, monostatic=False)
    mesh = shapes.cubesat_with_panels(3)
    mats = [
        ppr.load_material(name, 532e-9, dtype=np.float64)
        for name in ("aluminium", "white_paint_tio2", "fused_silica")
    ]
    q = unit(np.random.default_rng(4).normal(size=4))
    prof = {}
    for label, s in (("mono", sensor), ("general", general_sensor)):
        scene = ppr.Scene(
            mesh,
            tuple(mats),
            ppr.Pose(q, (0.0, 0.0, 0.0)),
            s,
            ppr.Pulse.gaussian(100e-12),
            ppr.RangeBins.centred(0.01, 128, 1e6),
            4,
        )
        prof[label] = np.asarray(ppr.simulate(scene, dtype=np.float64).data)
    peak = np.abs(prof["general"]).max()
    assert peak > 0
    assert np.max(np.abs(prof["mono"] - prof["general"])) <= 1e-12 * peak
    with pytest.raises(ValueError, match="Sensor.monostatic"):
        ppr.Sensor([0, 0, 1.0], [0, 0.6, 0.8], [1.0, 0, 0], [1.0, 0, 0], monostatic=True)
