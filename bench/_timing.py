"""Shared helpers of the bench scripts: timing, the machine's load, writing a results file
(imported as ``from _timing import median_time``: each script runs with ``bench/`` as its
first ``sys.path`` entry)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import jax
import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def median_time(fn, *args, repeats: int = 5) -> float:
    """Median wall time (s) of ``fn(*args)`` over ``repeats`` calls after one warm-up call
    (compilation), each waited for with ``jax.block_until_ready`` (a no-op on NumPy or
    ``None`` results)."""
    return first_and_median_time(fn, *args, repeats=repeats)[1]


def first_and_median_time(fn, *args, repeats: int = 5) -> tuple[float, float]:
    """Wall time (s) of the first call of ``fn(*args)`` (compilation and run) and the median
    of ``repeats`` calls after it, as :func:`median_time`."""
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return first, float(np.median(ts))


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, for a results file's header."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def write_result(stem: str, lines: list[str]) -> Path:
    """Write ``lines`` to ``bench/results/<stem>.md`` (ending in a newline), print them and
    the path; returns the path."""
    out = RESULTS / f"{stem}.md"
    text = "\n".join(lines)
    out.write_text(text if text.endswith("\n") else text + "\n")
    print(text)
    print(f"wrote {out}")
    return out
