"""XLA compiler options of the inversion's forward-model programs."""

from __future__ import annotations

import os

EMITTERS_ENV = "PPR_XLA_EMITTERS"


def model_compiler_options() -> dict[str, bool]:
    """XLA compiler options of the programs that hold a whole forward model and evaluate it at
    one parameter point: the refiner's solver round, bounded round and Jacobians, and the
    expected counts. They compile for tens of seconds and run for milliseconds, so they are
    compiled with XLA:CPU's elemental kernel emitters instead of its default fusion emitters,
    whose code generation takes most of a large program's compilation. Measured
    (``python bench/bench_xla_emitters.py``, ``bench/results/xla_emitters.md``): the first
    ``inversion.refine`` of the ``ppr invert`` example (solver round and Jacobians compiled)
    takes 68 s instead of 97 s, a later one 2.15 s instead of 2.02 s (the Fisher matrix 0.22 s
    instead of 0.20 s); on a cylinder with the single term 8.4 s instead of 15.7 s, later calls
    the same. The sampler's log-posterior over a batch of walkers and programs over many rows
    (``ppr.mueller_brdf`` on a large batch, database builds) keep the default, which runs them
    1.6-2x faster.

    ``PPR_XLA_EMITTERS=fusion`` (read when ``inversion`` is imported) compiles these programs
    with the default emitters too (a long session of many observations of one model gains the
    few per cent); ``elemental`` (or unset) is the choice above. The option is a field of
    XLA's debug options, which other backends than the CPU ignore."""
    v = os.environ.get(EMITTERS_ENV, "").strip().lower()
    if v not in ("", "elemental", "fusion"):
        raise ValueError(f"{EMITTERS_ENV}={v!r}: use 'elemental' (the default) or 'fusion'")
    return {"xla_cpu_use_fusion_emitters": v == "fusion"}


MODEL_PROGRAM = model_compiler_options()
"""``compiler_options`` of the forward-model programs (``jax.jit(..., compiler_options=...)``)."""
