"""How much the test suite's programs are optimized when compiled.

Most tests compile a program (a BRDF variant, a stiff-case gradient, a render, a solver) and run
it once or a few times on a small batch: their cost is the compilation, and most of that is
LLVM optimizing the generated kernels. The suite therefore compiles with JAX's
``jax_disable_most_optimizations`` (XLA backend optimization level 0, no expensive LLVM
passes): the double term's value+gradient program compiles in 13 s instead of 24 s (user CPU
27 s instead of 45 s) and runs in 0.55 s instead of 0.07 s.

The suite also sets ``SUITE_XLA_FLAGS`` (``tests/conftest.py``, through ``XLA_FLAGS``, so
subprocesses and notebook kernels inherit it): XLA:CPU's legacy elemental kernel emitters
instead of its MLIR fusion emitters (``--xla_cpu_use_fusion_emitters=false``). The HLO is the
same; the MLIR emitters recompute a fused producer at each of its uses and take most of an
unoptimized compilation (measured on the double term's value+gradient, 1101 rows, float64: 34
CPU s with them, 13 s without; tests/test_grazing.py, two such programs and more: 187 CPU s
with them, 94 s without). Rounding differs in the last bits (contractions, evaluation order),
and three places in the tests depended on one compiler's rounding: a crossed polarization
channel that is exactly 0 came out as -0.2 float32 ``eps`` of the peak (so
``inversion.observe`` takes rounding-level negatives as 0, ``inversion._noise.ROUNDING_ULPS``);
sharded and unsharded database rows differ by 2.5e-4 of their peak (the lobe power amplifies a
direction's rounding by ``m``; within the documented float32 precision); the single term's
gradient in ``k_in`` alone at exact backscatter is a subgradient (docs/physics/numerics.md).
``USER_COMPILER_OPTIONS`` restores the user's default for one compilation
(``jax.jit(..., compiler_options=USER_COMPILER_OPTIONS)``); ``tests/test_compile_level.py``
compares the two settings.

Tests whose cost is running (Monte Carlo sums over large batches, MCMC chains, high-order
reference quadratures) are marked ``@pytest.mark.optimized`` and run with the defaults
(``tests/conftest.py``). XLA's HLO passes are the same either way, so values agree to
rounding; ``tests/test_compile_level.py`` checks that on the BRDF. Users, benchmarks and the
notebooks' own runs use the defaults.

JAX's jit cache does not key on this switch: a program compiled unoptimized by one test would
be reused as is by a later ``optimized`` test in the same worker (measured: the MCMC coverage
test took 74 s instead of 14 s that way). So when a worker switches to the defaults it first
calls ``jax.clear_caches()``; consecutive optimized tests (a marked module) share their
programs, and the optimized executables left behind are reused by later tests at no cost.
"""

from __future__ import annotations

import contextlib

import jax

SUITE_XLA_FLAGS: tuple[str, ...] = ("--xla_cpu_use_fusion_emitters=false",)
"""XLA flags of the test processes (module docstring)."""

USER_COMPILER_OPTIONS: dict = {"xla_cpu_use_fusion_emitters": True}
"""Per-compilation options that undo ``SUITE_XLA_FLAGS``: what users compile with."""

UNOPTIMIZED = {"jax_disable_most_optimizations": True}
DEFAULT = {"jax_disable_most_optimizations": False}


def apply(settings: dict) -> None:
    for name, value in settings.items():
        jax.config.update(name, value)


@contextlib.contextmanager
def compiled_with(settings: dict):
    """Compile with ``settings`` inside the block, then restore the previous setting."""
    before = {name: jax.config.read(name) for name in settings}
    apply(settings)
    try:
        yield
    finally:
        apply(before)


def optimized():
    """JAX's defaults inside the block (``with optimized(): ...``)."""
    return compiled_with(DEFAULT)


def unoptimized():
    """The suite's unoptimized setting inside the block."""
    return compiled_with(UNOPTIMIZED)
