"""The NaN-safe primitives: finite values AND gradients exactly at the singular points."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ppr import _safe


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_safe_sqrt_value_and_grad_at_zero(dtype):
    # Below the guard threshold (1e3 x smallest normal) both value and gradient are zero.
    x = jnp.asarray([0.0, np.finfo(dtype).tiny, 4.0], dtype)
    v = _safe.safe_sqrt(x)
    g = jax.vmap(jax.grad(_safe.safe_sqrt))(x)
    assert v.dtype == dtype
    np.testing.assert_allclose(np.asarray(v), [0.0, 0.0, 2.0])
    # d sqrt(x)/dx = 1/(2 sqrt x) = 0.25 at 4; zero (not inf/NaN) where masked.
    np.testing.assert_allclose(np.asarray(g), [0.0, 0.0, 0.25], rtol=1e-6)


def test_safe_normalize_zero_vector_gradient_is_zero_not_nan():
    f = lambda v: _safe.safe_normalize(v)[0].sum()
    g = jax.grad(f)(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))
    u, ok = _safe.safe_normalize(jnp.asarray([3.0, 0.0, 4.0]))
    np.testing.assert_allclose(np.asarray(u), [0.6, 0.0, 0.8], rtol=1e-12)
    assert bool(ok)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_safe_pow_zero_to_zero_and_gradients(dtype):
    # 0**0 = 1 (m = 0 lobe at grazing), 0**m = 0 for m > 0, log-space accuracy at large m.
    base = jnp.asarray([0.0, 0.0, 0.5, 1.0 - 1e-6], dtype)
    expo = jnp.asarray([0.0, 3.0, 2.0, 1e6], dtype)
    v = _safe.safe_pow(base, expo)
    ref = np.array([1.0, 0.0, 0.25, (1 - 1e-6) ** 1e6])
    # float32: 1 - 1e-6 is itself rounded (ulp 6e-8), exponentiated by 1e6 -> ~6% relative.
    rtol = 1e-12 if dtype == jnp.float64 else 7e-2
    np.testing.assert_allclose(np.asarray(v, np.float64), ref, rtol=rtol)
    gb, ge = jax.vmap(jax.grad(_safe.safe_pow, argnums=(0, 1)))(base, expo)
    assert np.all(np.isfinite(np.asarray(gb))) and np.all(np.isfinite(np.asarray(ge)))


def test_safe_div_masks_gradient():
    f = lambda d: _safe.safe_div(1.0, d)
    assert float(f(0.0)) == 0.0
    assert np.isfinite(float(jax.grad(f)(0.0)))
    np.testing.assert_allclose(float(jax.grad(f)(2.0)), -0.25)
