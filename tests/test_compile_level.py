"""The test suite's compilations (tests/compile_level.py: unoptimized, XLA:CPU's legacy
kernel emitters) compute what users' compilations (JAX's defaults) compute, to rounding: the
double-bounce term (the largest program: Fresnel along both paths, visibilities, the coherent
sum; per-element materials, random beam frames) in float64, and the single term's gradients
in float32 (where rounding differences are largest), each program compiled as the suite does
and as users do.

The gradients are taken off exact backscatter: there the single term's joint visibility
``min(P(k), P(k'))`` has a kink in ``k_in`` alone (``k' = k`` is where the two sides
swap), so the gradient with respect to ``k_in`` only is a subgradient that rounding picks
(measured: the two one-sided values and their mean from three compilations of one row). The
derivative along ``k_out = k_in`` (a monostatic sensor) is smooth and is what the renderers
use.

The two differ by a few ulps per operation (multiply-adds contracted or not, vectorized or
scalar math functions), amplified where an operation cancels. Measured: the double term
3e-16 of the largest entry; float32 gradients of single + multiple 3e-6 (9e-6 on another
batch). The pair of compilations costs ~15 s, so this checks the two heaviest pieces, not
every program the tests build."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compile_level import USER_COMPILER_OPTIONS, optimized, unoptimized

from ppr import Material
from ppr.brdf._brdf import mueller_brdf


def _upper(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _perp(rng, k):
    a = rng.normal(size=k.shape)
    a -= np.sum(a * k, -1, keepdims=True) * k
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _both(fn, *args):
    """``fn(*args)`` compiled as the suite compiles (unoptimized, legacy emitters) and as
    users do (JAX's defaults, MLIR emitters): leaves, as float64. (JAX's jit cache does not
    key on the optimization switch, so each level jits its own wrapper.)"""
    out = []
    for level, options in ((unoptimized, None), (optimized, USER_COMPILER_OPTIONS)):
        with level():
            compiled = jax.jit(lambda *a: fn(*a), compiler_options=options)
            leaves = jax.tree_util.tree_leaves(compiled(*args))
        out.append([np.asarray(x, np.float64) for x in leaves])
    return out


def _rel(a, b):
    return max(np.abs(x - y).max() / np.abs(y).max() for x, y in zip(a, b, strict=True))


def test_unoptimized_compilation_gives_the_same_values_and_gradients():
    rng = np.random.default_rng(0)
    n = 64
    ki, ko = _upper(rng, n), _upper(rng, n)
    ko[:8] = ki[:8]  # exact backscatter: the coherent double-bounce peak
    fi, fo = _perp(rng, ki), _perp(rng, ko)
    m = 10.0 ** rng.uniform(-1.0, 3.0, n)
    nc = rng.uniform(0.2, 2.5, n) + 1j * rng.uniform(0.0, 7.0, n)
    z = np.array([0.0, 0.0, 1.0])

    def full(ki, ko, fi, fo, m, nc):
        mat = Material(n=nc, m=m)
        return mueller_brdf(ki, ko, z, mat, frame_in=fi, frame_out=fo, terms=("double",))

    lvl0, default = _both(full, ki, ko, fi, fo, m, nc)
    assert np.all(np.isfinite(lvl0[0])) and np.abs(default[0]).max() > 0
    assert _rel(lvl0, default) < 1e-13, _rel(lvl0, default)

    f32 = np.float32

    def core_grads(ki, ko, m, n_re, n_im):
        def total(*a):
            k1, k2, mm, nr, ni = a
            mat = Material(n=(nr + 1j * ni).astype(jnp.complex64), m=mm)
            M = mueller_brdf(k1, k2, z.astype(f32), mat, terms=("single",))
            return jnp.sum(M * jnp.arange(16, dtype=f32).reshape(4, 4))

        return jax.grad(total, argnums=(0, 1, 2, 3, 4))(ki, ko, m, n_re, n_im)

    ko[:8] = _upper(rng, 8)  # bistatic rows only (module docstring)
    args = [np.asarray(a, f32) for a in (ki, ko, m, nc.real, nc.imag)]
    lvl0, default = _both(core_grads, *args)
    assert all(np.all(np.isfinite(x)) for x in lvl0)
    # not bitwise equal: two programs were compiled (the switch reached the compiler and the
    # jit cache kept them apart)
    assert 0.0 < _rel(lvl0, default) < 1e-4, _rel(lvl0, default)


def test_model_program_emitters_setting_is_read_and_checked(monkeypatch):
    """``PPR_XLA_EMITTERS`` picks the kernel emitters of the inversion's forward-model programs
    (elemental unless ``fusion``); another value is refused by name and value."""
    from inversion._xla import EMITTERS_ENV, model_compiler_options

    monkeypatch.delenv(EMITTERS_ENV, raising=False)
    assert model_compiler_options() == {"xla_cpu_use_fusion_emitters": False}
    monkeypatch.setenv(EMITTERS_ENV, " Fusion ")
    assert model_compiler_options() == {"xla_cpu_use_fusion_emitters": True}
    monkeypatch.setenv(EMITTERS_ENV, "llvm")
    with pytest.raises(ValueError, match="PPR_XLA_EMITTERS='llvm'"):
        model_compiler_options()
