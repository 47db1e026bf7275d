"""Jitted programs that a test runs once or a few times, compiled without LLVM optimization.

A test's own program (a stiff-case gradient, a float32 comparison) is compiled, run once on a
small batch, and dropped; its compilation is the test's cost, and most of that is LLVM's
optimization of the generated kernels. ``jit_once`` compiles at XLA's backend optimization
level 0 instead: the double term's value+gradient program compiles in 13.4 s instead of 23.7 s
(user CPU 27 s instead of 45 s) and runs in 0.55 s instead of 0.07 s. XLA's HLO passes are
the same at every level, so values are the same up to rounding;
``tests/test_compile_once.py`` checks that on the BRDF. Programs that run many times (MCMC,
furnace sums over large batches, the library's own jits called eagerly) keep the default.
"""

from __future__ import annotations

import functools

import jax

ONCE = {"xla_backend_optimization_level": 0}


def jit_once(fun=None, **kwargs):
    """``jax.jit(fun, **kwargs)`` compiled at XLA backend optimization level 0 (decorator or
    call, like ``jax.jit``)."""
    if fun is None:
        return functools.partial(jit_once, **kwargs)
    return jax.jit(fun, compiler_options=ONCE, **kwargs)
