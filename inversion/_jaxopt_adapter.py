"""The only place ppr/inversion touches jaxopt: a box-bounded L-BFGS-B minimiser.

jaxopt is archived upstream ("JAXopt is no longer maintained") but fills a gap optimistix
leaves: box-constrained minimisation (physical bounds on ``n'``, ``n''``, ``m``). Everything
jaxopt-specific sits behind :func:`lbfgsb_minimize`, a pure function of arrays returning a
:class:`BoundedSolve`; swapping the backend (e.g. for optax's L-BFGS with projection, or
SciPy's L-BFGS-B on the host) means rewriting this one file. The version that works is
pinned by ``tests/test_refine.py::test_jaxopt_version_pinned`` (:data:`JAXOPT_TESTED`).

The import of jaxopt emits a ``DeprecationWarning``; it is silenced here, at the import, and
filtered in ``pyproject.toml`` for pytest.
"""

from __future__ import annotations

import importlib.metadata
import warnings
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import jaxopt

__all__ = ["JAXOPT_TESTED", "BoundedSolve", "jaxopt_version", "lbfgsb_minimize"]

JAXOPT_TESTED = ("0.8.5",)
"""jaxopt versions this adapter is tested with (pinned by a test)."""


def jaxopt_version() -> str:
    return importlib.metadata.version("jaxopt")


class BoundedSolve(eqx.Module):
    """Outcome of a bounded minimisation (all arrays; jit-friendly).

    - `x`: minimiser; `value`: objective there; `n_iter`: iterations used;
    - `error`: projected-gradient norm at ``x`` (the stopping quantity);
    - `converged`: ``error <= tol``; `failed_linesearch`: the last line search failed.
    """

    x: Array
    value: Array
    n_iter: Array
    error: Array
    converged: Array
    failed_linesearch: Array


def lbfgsb_minimize(
    fun: Callable[[Array], Array],
    x0: Float[Array, " P"],
    lower: Float[Array, " P"],
    upper: Float[Array, " P"],
    *,
    maxiter: int = 500,
    tol: float = 1e-8,
    history_size: int = 10,
) -> BoundedSolve:
    """Minimise scalar ``fun(x)`` subject to ``lower <= x <= upper`` (L-BFGS-B, jaxopt).

    Traceable: call it inside ``jit``. ``x0`` is clipped into the box first.
    """
    solver = jaxopt.LBFGSB(fun=fun, maxiter=maxiter, tol=tol, history_size=history_size, jit=True)
    x0 = jnp.clip(x0, lower, upper)
    x, state = solver.run(x0, bounds=(lower, upper))
    return BoundedSolve(
        x=x,
        value=state.value,
        n_iter=state.iter_num,
        error=state.error,
        converged=state.error <= tol,
        failed_linesearch=jnp.asarray(state.failed_linesearch),
    )
