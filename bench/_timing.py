"""Shared timing helper of the bench scripts (imported as ``from _timing import median_time``:
each script runs with ``bench/`` as its first ``sys.path`` entry)."""

from __future__ import annotations

import time

import jax
import numpy as np


def median_time(fn, *args, repeats: int = 5) -> float:
    """Median wall time (s) of ``fn(*args)`` over ``repeats`` calls after one warm-up call
    (compilation), each waited for with ``jax.block_until_ready`` (a no-op on NumPy or
    ``None`` results)."""
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))
