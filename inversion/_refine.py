r"""Gradient refiners: weighted least squares on the continuous parameters, multi-start.

**Forward-model interface.** A forward model is any object (ideally an ``eqx.Module`` holding
its arrays, so that jit traces rather than bakes them in) with

- ``prepare(phys: PhysicalParams) -> aux``: host-side, *not* traced, no gradients. Returns a
  pytree of arrays the pure model needs and that is piecewise constant in the parameters
  (per-face visibility fractions from ray casting). Called between refinement rounds.
- ``expected(phys: PhysicalParams, aux) -> Float[Array, "C B"]``: pure, jittable,
  differentiable expected counts per channel and range bin.

A noise model is any object with ``variance(expected, phys) -> Float[Array, "C B"]`` (jittable),
optionally ``residuals(data, expected, inv_sigma)`` (what the solver minimises; default the
Gaussian ``(data - expected) * inv_sigma``), ``log_likelihood(data, expected, phys)`` (for the
MCMC; default Gaussian with that variance) and ``check_data(data)``. Provided:
:class:`PoissonCounts` (exact Poisson likelihood: deviance residuals; the right choice for
photo-counts), :class:`PoissonNoise` (Gaussian approximation ``mu + floor``, for scaled or
background-subtracted data) and :class:`GaussianNoise` (known sigma).

**Algorithm.** Each start (e.g. one of the classifier's top-k candidates) is refined in a few
*rounds*. At the start of a round the host recomputes ``aux`` (visibility) and the weights
``1/sigma = 1/sqrt(variance(expected))`` at the current parameters; inside the round the
residuals ``(data - expected(theta)) / sigma`` have fixed weights and are minimised with
``optimistix.least_squares`` (Levenberg-Marquardt by default, Dogleg optional) with
``throw=False``. Re-weighting between rounds is iteratively re-weighted least squares: for
Poisson counts its fixed point is the maximum-likelihood estimate. The solver's result code
is surfaced in :class:`RefineResult` (``success``, ``result``, ``message``), never swallowed.

The covariance at the optimum is the Gauss-Newton inverse ``(J^T J)^{-1}`` of the weighted
residual Jacobian in the solver coordinates, propagated to physical units (attitude as a
rotation vector in degrees, ``m``, ``n'``, ``n''``, metres, gain) with the delta method.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float

from ppr.config import first_nonfinite

from ._params import (
    DEFAULT_FREE,
    GAIN_RANGE,
    GROUPS,
    Parametrisation,
    PhysicalParams,
    group_sizes,
    lift_start,
)
from ._xla import MODEL_PROGRAM

__all__ = [
    "GaussianNoise",
    "PoissonNoise",
    "PoissonCounts",
    "noise_residuals",
    "noise_log_likelihood",
    "cramer_rao",
    "CramerRao",
    "RefineResult",
    "StartSummary",
    "check_observation",
    "refine",
    "covariance_at",
    "fisher_at",
    "weighted_jacobian",
    "PhysicalBounds",
    "refine_bounded",
    "predicted",
    "ModeFit",
    "ModeCheck",
    "mode_check",
    "SimulatorModel",
    "SimulatorKernel",
]


# --------------------------------------------------------------------------- noise models
class PoissonNoise(eqx.Module):
    """Photon counting (+ optional speckle) variance: ``mu + mu^2 / M + floor``.

    **Arguments:**

    - `floor`: variance floor in counts^2 (background, read noise; keeps weights finite where
      the model predicts no signal). Default 1.
    - `speckle_cells`: number of speckle cells per bin ``M`` (gamma-distributed intensity adds
      ``mu^2 / M``); ``None`` for pure Poisson.
    - `counts_per_photon`: ``"one"`` (data are photo-counts) or ``"gain"`` (data are
      photo-counts times the fitted overall gain, as in :mod:`inversion._noise`: the Poisson
      part of the variance is then ``gain * mu``).
    """

    floor: float = 1.0
    speckle_cells: float | None = None
    counts_per_photon: str = eqx.field(static=True, default="one")

    def __check_init__(self):
        if self.counts_per_photon not in ("one", "gain"):
            raise ValueError(
                "PoissonNoise.counts_per_photon must be 'one' or 'gain', "
                f"got {self.counts_per_photon!r}"
            )

    def variance(self, expected: Array, phys: PhysicalParams | None = None) -> Array:
        mu = jnp.maximum(expected, 0.0)
        g = 1.0
        if self.counts_per_photon == "gain" and phys is not None:
            g = phys.gain
        var = g * mu + self.floor
        if self.speckle_cells is not None:
            var = var + mu * mu / self.speckle_cells
        return var


class PoissonCounts(eqx.Module):
    r"""Exact Poisson likelihood for photo-counts: the refiner minimises the Poisson deviance.

    The data are counts ``k >= 0`` (not multiplied by a gain) with expectation
    ``lam = mu + background``. Non-integer ``k >= 0`` (dead-time or flat-field corrected
    counts) are accepted: the deviance below and ``log k! = ln Gamma(k + 1)`` are defined for
    any real ``k >= 0``; negative ``k`` are refused (:meth:`check_data`). The least-squares
    residuals are the *deviance residuals*

        r = sign(k - lam) sqrt(2 (lam - k + k log(k / lam)))      (r = -sqrt(2 lam) at k = 0)

    so ``sum(r^2) = -2 log L + const`` and the Levenberg-Marquardt optimum is the
    maximum-likelihood estimate directly (no Gaussian approximation, no variance floor: the
    Gaussian models' floor swamps the weights of bins with a fraction of a count, which is most
    bins of a photon-starved PPR return). The MCMC uses the exact log-likelihood
    ``sum(k log lam - lam - log k!)``. Covariances use the expected Fisher information
    ``J^T diag(1/lam) J`` (``variance`` below), i.e. the Cramer-Rao bound at the optimum.

    Written as ``(k - lam) / sqrt(k) * sqrt(g(x))`` with ``x = lam / k - 1`` and
    ``g(x) = 2 (x - log1p(x)) / x^2`` (``g(0) = 1``; a series below ``|x| < 1e-4``): finite values
    and gradients at ``lam = k`` and at ``k = 0`` (double-``where`` guards).

    **Arguments:**

    - `background`: expected background (dark, sky) counts per channel and bin, > 0. It keeps
      the likelihood finite where the model predicts no signal but a count was recorded.
      Default 1e-3.
    """

    background: float = 1e-3

    def __check_init__(self):
        if not (math.isfinite(self.background) and self.background > 0):
            raise ValueError(
                f"PoissonCounts.background must be finite and > 0 (counts per bin), "
                f"got {self.background!r}"
            )

    def check_data(self, data: np.ndarray, name: str = "data") -> None:
        """Counts must be >= 0 (a gain-scaled or background-subtracted profile is not)."""
        bad = np.argwhere(data < 0)
        if len(bad):
            first = tuple(int(i) for i in bad[0])
            raise ValueError(
                f"{name}: PoissonCounts needs photo-counts >= 0, but {len(bad)} entries are "
                f"negative (first at {first}: {float(data[first])}); "
                "use PoissonNoise/GaussianNoise for background-subtracted or scaled data"
            )

    def _lam(self, expected):
        lam = expected + self.background
        ok = lam > 0.5 * self.background  # a model dipping below 0 by more than round-off
        return jnp.where(ok, lam, self.background)

    def variance(self, expected: Array, phys: PhysicalParams | None = None) -> Array:
        return self._lam(expected)

    def residuals(self, data: Array, expected: Array, inv_sigma: Array | None = None) -> Array:
        lam = self._lam(expected)
        pos = data > 0
        k = jnp.where(pos, data, 1.0)
        x = lam / k - 1.0
        small = jnp.abs(x) < 1e-4
        xs = jnp.where(small, 0.5, x)
        g_big = 2.0 * (xs - jnp.log1p(xs)) / (xs * xs)
        g_small = 1.0 - 2.0 * x / 3.0 + 0.5 * x * x
        g = jnp.where(small, g_small, g_big)
        r_pos = (k - lam) / jnp.sqrt(k) * jnp.sqrt(g)
        r_zero = -jnp.sqrt(2.0 * lam)
        return jnp.where(pos, r_pos, r_zero)

    def log_likelihood(self, data: Array, expected: Array, phys=None) -> Array:
        lam = self._lam(expected)
        return jnp.sum(data * jnp.log(lam) - lam - jax.scipy.special.gammaln(data + 1.0))


def noise_residuals(noise, data, expected, inv_sigma):
    """The residuals a noise model hands the least-squares solver.

    Models with a ``residuals(data, expected, inv_sigma)`` method (:class:`PoissonCounts`)
    define their own; otherwise the Gaussian ``(data - expected) * inv_sigma`` with weights
    fixed per round (iteratively re-weighted least squares).
    """
    f = getattr(noise, "residuals", None)
    return (data - expected) * inv_sigma if f is None else f(data, expected, inv_sigma)


def noise_log_likelihood(noise, data, expected, phys):
    """Log-likelihood of a noise model: its own ``log_likelihood`` if it has one, otherwise
    Gaussian with ``variance(expected, phys)`` (including ``-1/2 log(2 pi var)``)."""
    f = getattr(noise, "log_likelihood", None)
    if f is not None:
        return f(data, expected, phys)
    var = noise.variance(expected, phys)
    return -0.5 * jnp.sum((data - expected) ** 2 / var + jnp.log(2 * jnp.pi * var))


class GaussianNoise(eqx.Module):
    """Known Gaussian noise: ``variance = sigma**2`` (broadcast to the data shape)."""

    sigma: Array = eqx.field(converter=jnp.asarray)

    def variance(self, expected: Array, phys: PhysicalParams | None = None) -> Array:
        return jnp.broadcast_to(self.sigma**2, expected.shape).astype(expected.dtype)


# --------------------------------------------------------------------------- validation
def check_observation(data: Any, shape: tuple[int, ...], name: str = "data") -> np.ndarray:
    """Validate an observation against the model's output shape; return it as float64 NumPy.

    Raises ``ValueError`` naming the problem: wrong number of channels or range bins, or
    non-finite entries (with the count and the first position).
    """
    arr = np.asarray(data)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    if arr.shape != tuple(shape):
        if arr.ndim == len(shape) and arr.shape[:-1] == tuple(shape[:-1]):
            raise ValueError(
                f"{name}: observation has {arr.shape[-1]} range bins but the model predicts "
                f"{shape[-1]} (shape {arr.shape} vs {tuple(shape)}); re-bin the observation or "
                f"build the model with the observation's range bins"
            )
        raise ValueError(
            f"{name}: observation shape {arr.shape} does not match the model's (channels, bins) "
            f"= {tuple(shape)}"
        )
    bad = first_nonfinite(arr)
    if bad is not None:
        raise ValueError(
            f"{name}: observation contains {bad[0]} non-finite value(s) (NaN/inf), "
            f"first at index {bad[1]} (channel, bin); mask or drop those bins before fitting"
        )
    return arr.astype(np.float64)


# --------------------------------------------------------------------------- results
RESULT_NAMES = {int(v._value): k for k, v in optx.RESULTS._name_to_item.items()}


@dataclasses.dataclass(frozen=True)
class StartSummary:
    """Outcome of one start of a multi-start refinement."""

    index: int
    start: PhysicalParams
    params: PhysicalParams
    cost: float
    success: bool
    result: str
    message: str
    n_steps: int
    n_rounds: int


class _ReportedSigma:
    """The `sigma` of a result with `covariance`, `labels`, `parametrisation`,
    `fisher_theta` and `physical_jacobian` (:class:`RefineResult`, :class:`CramerRao`)."""

    @property
    def sigma(self) -> np.ndarray:
        """1-sigma of each entry of `labels` (:func:`_sigma_reported`: ``inf`` where a
        parameter is unobservable on its own, a roughness or extinction near its floor 0
        included)."""
        return _sigma_reported(self)


@dataclasses.dataclass(frozen=True)
class RefineResult(_ReportedSigma):
    """Best fit of a (multi-start) refinement, with the solver's verdict and uncertainties.

    - `params`: best physical parameters; `theta` their solver coordinates in
      `parametrisation` (whose reference is ``params``, so the attitude entries are 0).
    - `cost`: ``sum(residual^2)`` at the optimum (``chi^2``; for :class:`PoissonCounts` the
      Poisson deviance, ``-2 log L`` up to a constant); `dof` = n_data - n_params (every
      free parameter counted; :class:`~inversion.GoodnessOfFit`'s ``dof`` counts only those
      the data determine, the rank of the Jacobian, so it is larger where a direction is
      unobservable);
      `reduced_chi2` = cost / dof (about 1 when a Gaussian noise model is right and counts are
      large; the deviance of sparse counts is smaller).
    - `success`: the solver reported success and the cost is finite; `result` the optimistix
      (or adapter) result name; `message` a human-readable explanation; `n_steps` total solver
      steps over all rounds; `n_rounds` visibility/weight rounds used.
    - `covariance`: ``(J^T J)^{-1}`` in physical units (`labels`); `covariance_theta` the same
      in solver coordinates; `sigma` the 1-sigma errors (marginal: infinite for a parameter
      with weight in an unconstrained direction); `condition` the condition number of
      ``J^T J`` (large: some parameter is not constrained by the data); `fisher_theta` the
      matrix ``J^T J`` itself and `physical_jacobian` ``d physical_vector / d theta``.
      :meth:`observability` names the unconstrained directions and gives finite
      uncertainties in the observable subspace.
    - `decrement`: how much further the deviance can drop from here by the Fisher-scoring
      (Gauss-Newton) model, ``g^T F^+ g`` with ``g = J^T r`` (``r`` the Pearson residuals
      at the point): about 0 at an optimum; for a fit the solver left unconverged, what
      polishing it can gain, to second order. ``None`` when not evaluated.
    - `jacobian_r`: the ``R`` factor of a QR decomposition of the weighted residuals'
      Jacobian ``J`` (``fisher_theta = R^T R`` without squaring ``J``'s condition number:
      :func:`inversion.log_evidence` takes its determinant from the singular values of
      ``R S``); ``None`` when not evaluated.
    - `starts`: summaries of every start, best first; `elapsed_s`: wall time.
    """

    params: PhysicalParams
    theta: np.ndarray
    parametrisation: Parametrisation
    cost: float
    dof: int
    success: bool
    result: str
    message: str
    n_steps: int
    n_rounds: int
    covariance: np.ndarray
    covariance_theta: np.ndarray
    labels: list[str]
    condition: float
    starts: tuple[StartSummary, ...]
    elapsed_s: float
    method: str = "levenberg_marquardt"
    fisher_theta: np.ndarray | None = None
    physical_jacobian: np.ndarray | None = None
    decrement: float | None = None
    jacobian_r: np.ndarray | None = None

    @property
    def reduced_chi2(self) -> float:
        return self.cost / max(self.dof, 1)

    def observability(self, line_of_sight=None, rtol: float | None = None):
        """:func:`inversion.observability` of this fit: the directions the data do not
        constrain, by name, and finite uncertainties in the observable subspace."""
        from ._observability import observability

        return observability(self, line_of_sight=line_of_sight, rtol=rtol)

    @property
    def attitude_sigma_deg(self) -> float | None:
        """Root-sum-square 1-sigma attitude error (degrees), if the attitude was fitted."""
        if "attitude" not in self.parametrisation.free:
            return None
        i = self.labels.index("rot_x [deg]")
        return float(np.sqrt(np.trace(self.covariance[i : i + 3, i : i + 3])))

    def outside_bounds(self, bounds: PhysicalBounds | None = None) -> list[str]:
        """Parameters of the optimum outside a physical box (default :class:`PhysicalBounds`),
        e.g. ``"n_re[0] = 7.3 outside [0.05, 5]"``. The unbounded solvers can leave it (the
        index trades against the unknown gain): refit with :func:`refine_bounded` then."""
        b = PhysicalBounds() if bounds is None else bounds
        p = self.params
        vals = []
        for i, n in enumerate(np.asarray(p.n)):
            vals += [(f"n_re[{i}]", n.real, b.n_re), (f"n_im[{i}]", n.imag, b.n_im)]
        vals += [(f"m[{i}]", v, b.m) for i, v in enumerate(np.asarray(p.m))]
        vals += [
            (f"corr_length[{i}]", v, b.corr_length) for i, v in enumerate(np.asarray(p.corr_length))
        ]
        vals += [
            ("range_offset", float(p.range_offset), b.range_offset),
            ("gain", float(p.gain), b.gain),
        ]
        return [
            f"{lab} = {float(v):.4g} outside [{lo:g}, {hi:g}]"
            for lab, v, (lo, hi) in vals
            if not lo <= float(v) <= hi
        ]

    def summary(self) -> str:
        lines = [
            f"refine[{self.method}]: success={self.success} ({self.result}) cost={self.cost:.4g} "
            f"reduced_chi2={self.reduced_chi2:.3g} steps={self.n_steps} rounds={self.n_rounds} "
            f"time={self.elapsed_s:.2f}s cond={self.condition:.2g}"
        ]
        if not self.success:
            lines.append(f"  solver message: {self.message}")
        out = self.outside_bounds()
        if out:
            lines.append(
                "  outside the physical box (refit with refine_bounded): " + "; ".join(out)
            )
        vec = np.asarray(self.parametrisation.physical_vector(jnp.asarray(self.theta)))
        sigma, own, det = self.sigma, np.zeros(len(vec), bool), np.ones(len(vec), bool)
        fisher = self.fisher_theta
        if fisher is not None and np.all(np.isfinite(fisher)):
            # finite uncertainties in the observable subspace, the null directions named
            ob = self.observability()
            sigma, own, det = ob.sigma, ~ob.observable, ob.determined
            if ob.unobservable:
                lines.append("  unobservable: " + "; ".join(ob.names))
        from ._observability import box_edges

        edges = box_edges(self.labels, vec)
        for lab, v, s, o, d in zip(self.labels, vec, sigma, own, det, strict=True):
            if lab in edges:
                lines.append(f"  {lab:>22s} = {v: .6g}  ({edges[lab]}: no Gaussian sigma)")
            elif o:
                lines.append(f"  {lab:>22s} = {v: .6g}  (unobservable on its own)")
            else:
                note = "" if d else "  (in the observable subspace)"
                lines.append(f"  {lab:>22s} = {v: .6g} +- {s:.3g}{note}")
        return "\n".join(lines)


# --------------------------------------------------------------------------- core
def _solver_residuals(theta, param, model, aux, inv_sigma, data, noise):
    """What the solver minimises: the noise model's residuals (Poisson deviance or Pearson).

    The expected counts go through :func:`_expected_forward_jac`, so the solvers' linearization
    is a materialized forward-mode Jacobian and its transpose a matrix transpose."""
    mu = _expected_forward_jac(theta, param, model, aux)
    return noise_residuals(noise, data, mu, inv_sigma)


def _expected_forward_jac(theta, param, model, aux):
    """``model.expected(param.to_physical(theta), aux)``, differentiable in ``theta`` only, whose
    JVP materializes the Jacobian in forward mode (one batched JVP over the basis of the few
    parameters) and applies it: ``d mu = J d theta``.

    Why: optimistix's least-squares solvers linearize the residuals (``jax.linearize``) and also
    *transpose* that linearization for ``J^T r``. Transposing the renderer's JVP is a reverse-mode
    program of the whole forward model, the largest part of a solver's compilation. Here the
    linearization is ``J @ d theta`` with ``J`` computed from the primal, so its transpose is
    ``J^T @ r``, and the solver compiles no reverse-mode renderer. ``refine`` on a 3U CubeSat
    (16 channels, double term) takes 29.5 s on its first call instead of 48.4 s, later calls
    0.049 s instead of 0.062 s, with the same steps and cost (``bench/bench_refine_compile.py``,
    ``bench/results/refine_compile.md``): the solvers' QR materializes ``J`` from the
    linearization in forward mode anyway.

    Other arguments (model arrays, aux) get symbolic-zero tangents inside the solvers; a
    non-zero tangent there raises instead of being dropped."""
    dyn, static = eqx.partition((param, model, aux), eqx.is_array)

    def f(dyn, theta):
        p, mo, a = eqx.combine(dyn, static)
        return mo.expected(p.to_physical(theta), a)

    def jvp(primals, tangents):
        dyn, theta = primals
        t_dyn, t_theta = tangents
        leaves = jax.tree_util.tree_leaves(t_dyn, is_leaf=lambda t: isinstance(t, SymbolicZero))
        if not all(isinstance(t, SymbolicZero) for t in leaves):
            raise NotImplementedError(
                "_expected_forward_jac is differentiable in theta only (model, parametrisation "
                "and aux arrays must not carry tangents)"
            )
        mu, lin = jax.linearize(lambda t: f(dyn, t), theta)
        if isinstance(t_theta, SymbolicZero):
            return mu, jnp.zeros_like(mu)
        J = jax.vmap(lin, out_axes=-1)(jnp.eye(theta.shape[-1], dtype=theta.dtype))
        return mu, J @ t_theta

    g = jax.custom_jvp(f)
    g.defjvp(jvp, symbolic_zeros=True)
    return g(dyn, theta)


def _make_solver(solver, rtol, atol):
    # Tolerances as arrays: traced under filter_jit, so changing them does not recompile.
    rtol = jnp.asarray(rtol, jnp.result_type(float))
    atol = jnp.asarray(atol, jnp.result_type(float))
    if isinstance(solver, str):
        key = solver.lower()
        if key in ("lm", "levenberg_marquardt", "levenbergmarquardt"):
            return optx.LevenbergMarquardt(rtol=rtol, atol=atol)
        # rank-revealing linear solves: a parameter the data do not constrain (or one sitting
        # on a reparametrisation clamp) makes J singular, which the default (QR) turns into NaN
        if key == "dogleg":
            return optx.Dogleg(
                rtol=rtol, atol=atol, linear_solver=lx.AutoLinearSolver(well_posed=False)
            )
        if key in ("gauss_newton", "gn"):
            return optx.GaussNewton(
                rtol=rtol, atol=atol, linear_solver=lx.AutoLinearSolver(well_posed=False)
            )
        raise ValueError(
            f"solver={solver!r}: expected 'lm', 'dogleg', 'gauss_newton' or an optimistix solver"
        )
    return solver


@eqx.filter_jit(compiler_options=MODEL_PROGRAM)
def _solve_round(model, param, aux, inv_sigma, data, theta0, solver, max_steps, noise):
    def fn(theta, args):
        return _solver_residuals(theta, param, model, aux, inv_sigma, data, noise)

    sol = optx.least_squares(fn, solver, theta0, None, max_steps=max_steps, throw=False)
    # the residuals at the returned point, as the solver last evaluated them there (its state
    # holds the accepted point's): no further copy of the forward model in this program
    r = _final_residuals(sol, fn)
    return sol.value, sol.result, sol.stats["num_steps"], jnp.sum(r * r)


def _final_residuals(sol, fn):
    """Residuals at ``sol.value``: the Gauss-Newton family's state (``f_info``, updated with
    the accepted point, which is the value returned) when it has one, else evaluated."""
    f_info = getattr(sol.state, "f_info", None)
    r = getattr(f_info, "residual", None)
    if r is None:
        return fn(sol.value, None)
    return r


@eqx.filter_jit
def _to_physical(param, theta):
    return param.to_physical(theta)


@eqx.filter_jit
def _from_physical(param, phys):
    return param.from_physical(phys)


def _weights(model, noise, phys, aux):
    """``(1 / sqrt(var(mu)), mu)`` at ``phys``: the expected counts from the forward model's
    own program (:func:`_expected_jit`, shared with every other caller of ``expected``), the
    weights from a small one, so that no second copy of the forward model is compiled."""
    mu = _expected_jit(model, phys, aux)
    return _inv_sigma(noise, mu, phys), mu


@eqx.filter_jit
def _inv_sigma(noise, mu, phys):
    return 1.0 / jnp.sqrt(noise.variance(mu, phys))


@eqx.filter_jit(compiler_options=MODEL_PROGRAM)
def _jacobians(model, param, aux, inv_sigma, data, theta, noise=None):
    # one forward-mode pass gives mu and d mu / d theta: the Pearson residuals' Jacobian
    # (fixed weights) is -inv_sigma d mu / d theta, and the solver's cost comes from the same mu
    def f(t):
        mu = model.expected(param.to_physical(t), aux)
        return mu, mu

    dmu, mu = jax.jacfwd(f, has_aux=True)(theta)
    J = (-jnp.asarray(inv_sigma)[..., None] * dmu).reshape(-1, theta.shape[-1])
    G = jax.jacfwd(param.physical_vector)(theta)
    r = noise_residuals(noise, data, mu, inv_sigma)
    return J, G, jnp.sum(r * r)


def fisher_at(
    model, noise, data, phys: PhysicalParams, free=DEFAULT_FREE, aux=None, range_scale=0.01
):
    """Gauss-Newton (Fisher) information at ``phys``: ``(JTJ, G, parametrisation, chi2)``.

    ``JTJ = J^T J`` of the weighted residuals ``(data - mu) / sqrt(var(mu))`` in the solver
    coordinates ``theta`` of ``parametrisation`` (reference ``phys``): the expected Fisher
    information of the noise model at ``mu``. ``G = d physical_vector / d theta``. ``aux``
    (visibility) is recomputed with ``model.prepare`` when not given; ``chi2`` is the solver's
    cost at ``phys``.
    """
    J, _, _, G, param, chi2 = weighted_jacobian(model, noise, data, phys, free, aux, range_scale)
    return J.T @ J, G, param, chi2


def weighted_jacobian(
    model, noise, data, phys: PhysicalParams, free=DEFAULT_FREE, aux=None, range_scale=0.01
):
    """Jacobian of the weighted residuals at ``phys``: ``(J, inv_sigma, mu, G, param, chi2)``.

    ``J = d [(data - mu) inv_sigma] / d theta`` flattened to ``(C * B, P)`` (so
    ``d mu / d theta = -J / inv_sigma``), ``inv_sigma = 1 / sqrt(var(mu))`` and ``mu`` the
    expected values ``(C, B)`` at ``phys``, ``G = d physical_vector / d theta``, the
    :class:`Parametrisation` (reference ``phys``) and the solver's cost. One compiled program
    per model, shared with the refiners' covariance: the Jacobian is computed with the groups
    of ``free`` and :data:`~inversion._params.DEFAULT_FREE` free and ``free``'s columns are
    kept (a group's coordinates do not depend on which others are free), so fits with
    different free groups (``ppr invert``'s refinement without the index, its index stage
    with it) share one program; the few extra forward-mode columns cost little next to a
    compilation of the forward model's JVP.
    """
    free = tuple(free)
    param = Parametrisation(phys, free, range_scale)
    wide = Parametrisation(
        phys, tuple(g for g in GROUPS if g in free or g in DEFAULT_FREE), range_scale
    )
    cols = _columns_of(wide, free)
    if aux is None:
        aux = model.prepare(phys)
    inv_sigma, mu = _weights(_pure(model), noise, phys, aux)
    theta = _from_physical(wide, phys)
    J, G, chi2 = _jacobians(_pure(model), wide, aux, inv_sigma, jnp.asarray(data), theta, noise)
    J = np.asarray(J, np.float64)[:, cols]
    G = np.asarray(G, np.float64)[np.ix_(cols, cols)]
    if not np.all(np.isfinite(J)):
        raise FloatingPointError(
            "covariance_at: the residual Jacobian has non-finite entries at the optimum "
            f"(columns {sorted(set(np.argwhere(~np.isfinite(J))[:, 1].tolist()))})"
        )
    return (
        J,
        np.asarray(inv_sigma, np.float64),
        np.asarray(mu, np.float64),
        G,
        param,
        float(chi2),
    )


def _columns_of(wide: Parametrisation, free) -> np.ndarray:
    """Indices in ``wide``'s ``theta`` (and ``physical_vector``) of the groups ``free``."""
    sizes = group_sizes(wide.reference)
    cols, i = [], 0
    for g in wide.ordered_free:
        if g in free:
            cols += range(i, i + sizes[g])
        i += sizes[g]
    return np.asarray(cols, np.int64)


def covariance_at(
    model, noise, data, phys: PhysicalParams, free=DEFAULT_FREE, aux=None, range_scale=0.01
):
    """Gauss-Newton covariance at ``phys``: ``(cov_physical, cov_theta, labels, condition, chi2)``.

    ``aux`` (visibility) is recomputed with ``model.prepare`` when not given. Uses a
    pseudo-inverse (relative cutoff 1e-12), so an unconstrained direction does not crash: it
    shows as a huge condition number, and every physical parameter with weight in an exactly
    unconstrained direction gets an infinite variance in ``cov_physical`` (``cov_theta`` keeps
    the finite pseudo-inverse, e.g. for sizing an MCMC starting ball). These are the marginal
    variances; :func:`inversion.observability` names the unconstrained directions and gives
    finite uncertainties in the observable subspace.
    """
    JTJ, G, param, chi2 = fisher_at(model, noise, data, phys, free, aux, range_scale)
    cov, cov_theta, cond = _covariance_from_fisher(JTJ, G, param)
    return cov, cov_theta, param.labels, cond, chi2


def _covariance_from_fisher(JTJ, G, param: Parametrisation):
    """``(cov_physical, cov_theta, condition)`` of a Fisher matrix (see :func:`covariance_at`)."""
    ev, V = np.linalg.eigh(JTJ)
    with np.errstate(over="ignore"):  # singular (exact symmetry): condition number inf
        cond = float(ev[-1] / ev[0]) if ev[-1] > 0 and ev[0] > 0 else np.inf
    cov_theta = np.linalg.pinv(JTJ, rcond=1e-12, hermitian=True)
    cov = G @ cov_theta @ G.T
    # The pseudo-inverse gives a direction the data do not constrain at all (an exact
    # symmetry, e.g. the roll about the line of sight when every return is a normal-incidence
    # Fresnel reflection) zero variance. Report it as infinite instead: every physical
    # parameter with weight in such a null direction gets an infinite variance.
    null = ev <= 1e-12 * max(ev[-1], 1e-300)
    if np.any(null):
        theta = _from_physical(param, param.reference)
        phys_vec = np.asarray(param.physical_vector(theta))
        moved = np.abs(G @ V[:, null])  # physical change along each unit null direction
        # (a parameter pinned on a boundary by its reparametrisation, n'' = softplus(u) or
        # m = e^x at their floors of 1e-9, moves by ~1e-9 along a null direction: not loose)
        loose = np.any(moved > 1e-6 * (1.0 + np.abs(phys_vec))[:, None], axis=1)
        cov = cov.copy()
        cov[loose, loose] = np.inf
    return cov, cov_theta, cond


def _sigma_reported(result) -> np.ndarray:
    """``sqrt(diag(covariance))``, with ``inf`` for a roughness or extinction (``m[j]``,
    ``n_im[j]``, fitted as logarithms) that :func:`inversion.observability` finds
    unobservable on its own. The covariance keeps such a parameter finite near its floor 0
    (:func:`_covariance_from_fisher`: a unit step of its logarithm is a small absolute
    change there), which made its sigma ~1e-23: the opposite of what the observability
    says. Where the observability's floor rule errs (a parameter at its floor that the data
    do determine to first order), this errs the same way: inf, conservative."""
    s = np.sqrt(np.clip(np.diag(np.asarray(result.covariance, np.float64)), 0.0, None))
    if result.fisher_theta is None or result.parametrisation is None:
        return s
    logp = np.array([lab.startswith(("m[", "n_im[")) for lab in result.labels], bool)
    if not logp.any():
        return s
    from ._observability import observability  # noqa: PLC0415

    try:
        ob = observability(result)
    except (ValueError, np.linalg.LinAlgError):
        return s
    own = dict(zip(ob.labels, ob.observable, strict=True))
    free = np.array([logp[i] and not own.get(lab, True) for i, lab in enumerate(result.labels)])
    return np.where(free, np.inf, s)


@dataclasses.dataclass(frozen=True)
class CramerRao(_ReportedSigma):
    """The Cramer-Rao bound at a parameter point: inverse expected Fisher information.

    - `covariance`: in physical units (`labels`, as :class:`RefineResult`); `sigma` the 1-sigma
      bounds; `attitude_sigma_deg` the root-sum-square attitude bound (degrees).
    - `condition`: condition number of the Fisher matrix (huge: a parameter the measurement
      cannot determine at all, e.g. the attitude about a symmetry axis).
    - `fisher_theta`: the Fisher matrix in the solver coordinates of `parametrisation`
      (reference: the point), `physical_jacobian` ``d physical_vector / d theta`` there;
      :meth:`observability` names the unobservable directions.
    """

    covariance: np.ndarray
    labels: list[str]
    condition: float
    fisher_theta: np.ndarray | None = None
    parametrisation: Parametrisation | None = None
    physical_jacobian: np.ndarray | None = None

    def observability(self, line_of_sight=None, rtol: float | None = None):
        """:func:`inversion.observability` of this bound: the unobservable directions by name
        and finite bounds in the observable subspace."""
        from ._observability import observability

        return observability(self, line_of_sight=line_of_sight, rtol=rtol)

    @property
    def attitude_sigma_deg(self) -> float | None:
        if "rot_x [deg]" not in self.labels:
            return None
        i = self.labels.index("rot_x [deg]")
        return float(np.sqrt(np.trace(self.covariance[i : i + 3, i : i + 3])))


def cramer_rao(
    model, phys: PhysicalParams, noise=None, free=DEFAULT_FREE, range_scale=0.01
) -> CramerRao:
    """Cramer-Rao bound of the free parameters at ``phys`` (the truth, in a simulation study).

    The expected Fisher information of the noise model, ``J^T diag(1/var(mu)) J`` with
    ``J = d mu / d theta`` at the noise-free expectation ``mu``: no unbiased estimator of these
    data can do better, so it separates what the measurement can tell (information) from
    what a search finds (local optima, grid resolution). For Poisson counts it scales as
    ``1/SNR`` (the Fisher information is proportional to the number of photons).
    """
    noise = PoissonCounts() if noise is None else noise
    aux = model.prepare(phys)
    mu = model.expected(phys, aux)
    JTJ, G, param, _ = fisher_at(model, noise, mu, phys, free, aux, range_scale)
    cov, _, cond = _covariance_from_fisher(JTJ, G, param)
    return CramerRao(
        covariance=cov,
        labels=list(param.labels),
        condition=cond,
        fisher_theta=JTJ,
        parametrisation=param,
        physical_jacobian=G,
    )


def _as_starts(starts) -> list[PhysicalParams]:
    if isinstance(starts, PhysicalParams):
        return [starts]
    starts = list(starts)
    if not starts:
        raise ValueError(
            "refine: starts is empty; pass at least one PhysicalParams "
            "(e.g. the classifier's top-k)"
        )
    for i, s in enumerate(starts):
        if not isinstance(s, PhysicalParams):
            raise ValueError(f"refine: starts[{i}] is {type(s).__name__}, expected PhysicalParams")
    return starts


def _model_shape(model, phys, aux):
    out = jax.eval_shape(_pure(model).expected, phys, aux)
    return tuple(out.shape)


def refine(
    model,
    data,
    starts: PhysicalParams | Sequence[PhysicalParams],
    *,
    noise=None,
    free: Sequence[str] = DEFAULT_FREE,
    solver: str | Any = "lm",
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    rounds: int = 4,
    range_scale: float = 0.01,
    keep: int | None = None,
    screen_tol: float = 1e-3,
    bounds: PhysicalBounds | None = None,
) -> RefineResult:
    """Multi-start weighted least-squares refinement (see the module docstring).

    **Arguments:**

    - `model`: forward model (``prepare``/``expected``, module docstring).
    - `data`: observed counts ``(C, B)``; checked against the model's output shape and for NaN.
    - `starts`: one or several starting points (e.g. the classifier's top-k candidates
      converted to :class:`PhysicalParams`).
    - `noise`: noise model with ``variance(expected)``; default ``PoissonNoise(floor=1)``.
    - `free`: parameter groups to fit (see :mod:`inversion._params`).
    - `solver`: ``"lm"`` (Levenberg-Marquardt, default), ``"dogleg"``, ``"gauss_newton"`` or
      an optimistix least-squares solver instance; `rtol`/`atol` its tolerances.
    - `max_steps`: solver steps per round; `rounds`: max visibility/weight rounds per start.
    - `keep`: screening. With more starts than `keep`, every start first runs one round with
      the loose tolerances ``rtol = atol = screen_tol`` (same compiled solver: tolerances are
      traced), and only the `keep` lowest-cost ones are refined on, from where their
      screening ended, with the full tolerances and rounds. The others are reported in
      ``starts`` with ``result = "screened_out"`` and their screening cost. ``None`` (default)
      refines every start fully. A solver given as an instance screens with its own
      tolerances.
    - `bounds`: a physical box (:class:`PhysicalBounds`) the solver is kept in: the
      parametrisation clamps the free groups into it (:class:`Parametrisation`'s ``bounds``),
      so a parameter whose optimum lies beyond a bound stops on it (named in the start's
      message, ``"at bounds: m[0]"``) and the fit never leaves the box. The same compiled
      solver as the unbounded fit (the box is a traced array); an optimum inside the box is
      the unbounded one. ``None`` (default): unbounded.

    **Returns:** :class:`RefineResult` for the lowest-cost start (successful starts preferred),
    with every start summarised in ``starts``.
    """
    t0 = time.perf_counter()
    noise = PoissonNoise() if noise is None else noise
    starts = _as_starts(starts)
    solv = _make_solver(solver, rtol, atol)
    free = tuple(free)
    if rounds < 1 or max_steps < 1:
        raise ValueError(f"refine: rounds={rounds} and max_steps={max_steps} must be >= 1")
    if keep is not None and int(keep) < 1:
        raise ValueError(f"refine: keep={keep} must be >= 1 (or None: no screening)")
    if not screen_tol > 0:
        raise ValueError(f"refine: screen_tol={screen_tol} must be > 0")

    aux0 = model.prepare(starts[0])
    shape = _model_shape(model, starts[0], aux0)
    data_np = check_observation(data, shape)
    if hasattr(noise, "check_data"):
        noise.check_data(data_np)
    dt = starts[0].m.dtype
    data_j = jnp.asarray(data_np, dt)
    run = functools.partial(
        _refine_start,
        model,
        noise,
        data_j,
        free,
        range_scale,
        max_steps=max_steps,
        bounds=bounds,
    )

    screened = {}
    if keep is not None and len(starts) > int(keep):
        loose = _make_solver(solver, screen_tol, screen_tol) if isinstance(solver, str) else solv
        for idx, start in enumerate(starts):
            screened[idx] = run(idx, start, lift_start(start), loose, 1, aux0 if idx == 0 else None)
        ranked = sorted(screened, key=lambda i: screened[i].cost)
        go_on = set(ranked[: int(keep)])
    else:
        go_on = set(range(len(starts)))

    summaries = []
    for idx, start in enumerate(starts):
        if idx not in go_on:
            sc = screened[idx]
            summaries.append(
                dataclasses.replace(
                    sc,
                    success=False,
                    result="screened_out",
                    message=f"screened out (one round at tolerance {screen_tol:g}, cost "
                    f"{sc.cost:.6g}; not among the keep={keep} lowest)",
                )
            )
            continue
        first = screened[idx] if idx in screened else None
        phys = first.params if first is not None else lift_start(start)
        aux = aux0 if (idx == 0 and first is None) else None
        s = run(idx, start, phys, solv, rounds, aux)
        if first is not None:
            s = dataclasses.replace(
                s, n_steps=s.n_steps + first.n_steps, n_rounds=s.n_rounds + first.n_rounds
            )
        summaries.append(s)

    order = sorted(
        range(len(summaries)), key=lambda i: (not summaries[i].success, summaries[i].cost)
    )
    ordered = tuple(summaries[i] for i in order)
    best = ordered[0]
    return _finish(
        model,
        noise,
        data_j,
        best,
        ordered,
        free,
        range_scale,
        t0,
        "levenberg_marquardt" if isinstance(solv, optx.LevenbergMarquardt) else type(solv).__name__,
    )


def _refine_start(
    model,
    noise,
    data_j,
    free,
    range_scale,
    idx,
    start,
    phys,
    solv,
    rounds,
    aux,
    *,
    max_steps,
    bounds=None,
) -> StartSummary:
    """Refine one start from ``phys`` in up to ``rounds`` visibility/weight rounds (kept in
    the physical box ``bounds`` when given: see :func:`refine`)."""
    if bounds is not None:
        phys = _clip_to(phys, bounds)
    param = Parametrisation(phys, free, range_scale, bounds)
    total_steps, used_rounds = 0, 0
    prev_cost = np.inf
    res_code, cost = 0, np.inf
    for rnd in range(rounds):
        if rnd > 0 or aux is None:
            aux = model.prepare(phys)
        inv_sigma, _ = _weights(_pure(model), noise, phys, aux)
        theta0 = _from_physical(param, phys)
        theta, result, nsteps, cost_j = _solve_round(
            _pure(model), param, aux, inv_sigma, data_j, theta0, solv, max_steps, noise
        )
        used_rounds += 1
        total_steps += int(nsteps)
        res_code = int(result._value)
        cost = float(cost_j)
        if not np.all(np.isfinite(np.asarray(theta))):
            res_code = RESULT_NAMES_INV["nonfinite"]
            cost = np.inf
            break
        phys = _to_physical(param, theta)
        param = param.recentred(phys)
        if abs(prev_cost - cost) <= 1e-9 * max(cost, 1.0) and rnd > 0:
            break
        prev_cost = cost
    name = RESULT_NAMES.get(res_code, str(res_code))
    ok = name == "successful" and np.isfinite(cost)
    msg = _message(res_code)
    at = _on_bounds(phys, free, bounds) if bounds is not None else []
    if at:
        msg = f"{msg}; at bounds: {', '.join(at)}"
    return StartSummary(
        index=idx,
        start=start,
        params=phys,
        cost=cost,
        success=bool(ok),
        result=name,
        message=msg,
        n_steps=total_steps,
        n_rounds=used_rounds,
    )


RESULT_NAMES_INV = {v: k for k, v in RESULT_NAMES.items()}


def _physical_entries(phys: PhysicalParams, free) -> list[tuple[str, str, float]]:
    """``(label, BOX_FIELDS name, value)`` of the bounded physical values of the free groups."""
    out = []
    n = np.asarray(phys.n)
    for g in GROUPS:
        if g not in free:
            continue
        if g == "m":
            out += [(f"m[{i}]", "m", v) for i, v in enumerate(np.asarray(phys.m))]
        elif g == "n":
            out += [(f"n_re[{i}]", "n_re", v) for i, v in enumerate(n.real)]
            out += [(f"n_im[{i}]", "n_im", v) for i, v in enumerate(n.imag)]
        elif g == "corr_length":
            cl = np.asarray(phys.corr_length)
            out += [(f"corr_length[{i}]", "corr_length", v) for i, v in enumerate(cl)]
        elif g in ("range_offset", "gain"):
            out.append((g, g, float(np.asarray(getattr(phys, g)))))
        elif g == "thickness":
            t = np.asarray(phys.thickness)
            out += [(f"thickness[{i}]", "thickness", t[i]) for i in phys.thickness_slots]
    return out


def _on_bounds(phys: PhysicalParams, free, bounds: PhysicalBounds) -> list[str]:
    """Labels of the free physical values on a bound of ``bounds`` (to 1e-9 relative)."""
    hits = []
    for lab, field, v in _physical_entries(phys, free):
        lo, hi = getattr(bounds, field)
        tol = 1e-9 * max(1.0, abs(float(v)))
        if abs(float(v) - lo) <= tol or abs(float(v) - hi) <= tol:
            hits.append(lab)
    return hits


def _clip_to(phys: PhysicalParams, bounds: PhysicalBounds) -> PhysicalParams:
    """``phys`` with every value clipped into ``bounds`` (a start for a bounded fit); ``phys``
    itself when it is inside."""
    if not any(
        not getattr(bounds, f)[0] <= float(v) <= getattr(bounds, f)[1]
        for _, f, v in _physical_entries(phys, GROUPS)
    ):
        return phys
    dt = phys.m.dtype
    n = np.asarray(phys.n)
    n = np.clip(n.real, *bounds.n_re) + 1j * np.clip(n.imag, *bounds.n_im)
    thick = np.asarray(phys.thickness).copy()
    slots = list(phys.thickness_slots)
    if slots:
        thick[slots] = np.clip(thick[slots], *bounds.thickness)
    return PhysicalParams(
        phys.quaternion,
        jnp.asarray(np.clip(np.asarray(phys.m), *bounds.m), dt),
        jnp.asarray(n, phys.n.dtype),
        jnp.asarray(np.clip(np.asarray(phys.corr_length), *bounds.corr_length), dt),
        jnp.asarray(np.clip(np.asarray(phys.range_offset), *bounds.range_offset), dt),
        jnp.asarray(np.clip(np.asarray(phys.gain), *bounds.gain), dt),
        jnp.asarray(thick, phys.thickness.dtype),
        phys.thickness_slots,
    )


def _message(code: int) -> str:
    name = RESULT_NAMES.get(code)
    if name is None:
        return f"unknown result code {code}"
    if name == "successful":
        return "converged"
    return str(optx.RESULTS[getattr(optx.RESULTS, name)])


def _finish(model, noise, data_j, best: StartSummary, ordered, free, range_scale, t0, method):
    phys = best.params
    decrement = jac_r = None
    success, result, message = best.success, best.result, best.message
    if np.isfinite(best.cost):
        J, inv_sigma, mu, G, param, chi2 = weighted_jacobian(
            model, noise, data_j, phys, free, None, range_scale
        )
        # the model's own constant background (a SimulatorModel's) is not the target's signal
        signal = np.asarray(mu) - np.asarray(getattr(_pure(model), "background", 0.0))
        if success and not np.any(signal > 0) and np.any(np.asarray(data_j) > 0):
            # a zero gradient because nothing is predicted, not an optimum
            success, result = False, "no_signal"
            message = (
                "the model predicts no signal at this point (the object outside the range "
                "window, or unlit): the solver had no gradient to follow"
            )
        fisher = J.T @ J
        decrement = _decrement(J, inv_sigma, mu, np.asarray(data_j, np.float64), noise)
        jac_r = np.linalg.qr(J, mode="r") if J.shape[0] >= J.shape[1] else None
        cov, cov_theta, cond = _covariance_from_fisher(fisher, G, param)
        labels = param.labels
    else:
        param = Parametrisation(phys, free, range_scale)
        p = param.size
        cov = cov_theta = fisher = G = np.full((p, p), np.nan)
        labels, cond, chi2 = param.labels, np.inf, np.inf
    param = Parametrisation(phys, free, range_scale)
    n_data = int(np.prod(data_j.shape))
    return RefineResult(
        params=phys,
        theta=np.asarray(_from_physical(param, phys)),
        parametrisation=param,
        cost=float(chi2),
        dof=n_data - param.size,
        success=success,
        result=result,
        message=message,
        n_steps=best.n_steps,
        n_rounds=best.n_rounds,
        covariance=cov,
        covariance_theta=cov_theta,
        labels=labels,
        condition=cond,
        starts=ordered,
        elapsed_s=time.perf_counter() - t0,
        method=method,
        fisher_theta=fisher,
        physical_jacobian=G,
        decrement=decrement,
        jacobian_r=jac_r,
    )


def _decrement(J, inv_sigma, mu, data, noise) -> float:
    """``g^T (J^T J)^+ g`` with ``g = J^T r``, ``r`` the Pearson residuals ``(y - lam) / sd``
    (``lam`` the expectation with the background of :class:`PoissonCounts`): the deviance
    decrease one Fisher-scoring step predicts (the score of the log-likelihood is ``-g`` and
    its Fisher information ``J^T J``), i.e. the squared norm of ``r`` projected onto the
    columns of ``J``. ``nan`` if not finite."""
    lam = mu + (noise.background if isinstance(noise, PoissonCounts) else 0.0)
    r = ((data - lam) * inv_sigma).reshape(-1)
    x, *_ = np.linalg.lstsq(J, r, rcond=1e-12)
    v = J @ x
    dec = float(v @ v)
    return dec if np.isfinite(dec) else math.nan


def predicted(model, phys: PhysicalParams) -> Float[Array, "C B"]:
    """Expected counts at ``phys`` (visibility recomputed on the host)."""
    return model.expected(phys, model.prepare(phys))


# --------------------------------------------------------------------------- bounded (jaxopt)
@dataclasses.dataclass(frozen=True)
class MirrorCheck:
    """The mirror ambiguity of a fit (:func:`mirror_check`).

    - `fit`: the fit checked; `mirror`: the refiner's optimum started at its mirror image
      (:func:`inversion.mirror_attitude`).
    - `delta_deviance`: ``mirror.cost - fit.cost`` (``-2 log`` of the likelihood ratio for
      :class:`PoissonCounts`); negative when the mirror image fits better.
    - `separation_deg`: angle between the two optima's body-frame lines of sight, modulo the
      shape's rotations. Near 0 the mirror start fell back into the fit's own mode (or the
      line of sight lies in the mirror plane): there is no second mode.
    - `mirror_probability`: posterior probability of the mirror mode against the fit's,
      ``1 / (1 + exp(delta / 2))``, for equal prior mass and equal posterior volume of the two
      modes (exact when the parity symmetry is, i.e. the off-block Mueller elements vanish).
    """

    fit: RefineResult
    mirror: RefineResult
    delta_deviance: float
    separation_deg: float

    @property
    def mirror_probability(self) -> float:
        d = self.delta_deviance
        if not np.isfinite(d):
            return 0.0 if d > 0 else 1.0
        return float(1.0 / (1.0 + math.exp(min(0.5 * d, 700.0))))

    def ambiguous(self, level: float = 0.05, min_separation_deg: float = 0.5) -> bool:
        """Two distinct modes (lines of sight more than `min_separation_deg` apart) that both
        keep posterior probability above `level`."""
        p = self.mirror_probability
        return bool(level < p < 1.0 - level and self.separation_deg > min_separation_deg)

    @property
    def best(self) -> RefineResult:
        """The fit with the lower cost (the mirror's when it fits better)."""
        return self.mirror if self.delta_deviance < 0 else self.fit

    def summary(self) -> str:
        note = " (ambiguous: the data hardly tell the mirror image apart)"
        return (
            f"mirror check: delta deviance {self.delta_deviance:+.4g}, mirror mode probability "
            f"{self.mirror_probability:.3g}, lines of sight {self.separation_deg:.3g} deg apart"
            + (note if self.ambiguous() else "")
        )


def mirror_check(
    model,
    data,
    fit: RefineResult,
    symmetry,
    *,
    noise=None,
    world_normal=(0.0, 1.0, 0.0),
    max_steps: int = 200,
    rounds: int = 2,
    solver: str | Any = "lm",
    bounds: PhysicalBounds | None = None,
) -> MirrorCheck:
    """Refine from the mirror image of ``fit`` and compare the two optima.

    A body with a mirror plane (the named `symmetry` class's, e.g. ``"dihedral:4"`` for a 3U
    CubeSat, or the first of a :class:`ppr.MeshSymmetry` or :class:`ppr.Mesh`:
    :func:`inversion.body_mirror_normal`) at attitude ``P R sigma`` is the mirror
    image of the scene at ``R``: identical range profiles, and Mueller profiles that differ
    only by the sign of the off-block elements (:func:`inversion.mirror_attitude`). Glossy
    returns have no off-block elements, so a local fit cannot tell the two attitudes apart,
    and its Cramer-Rao bound (local curvature) does not show the ambiguity either. This
    refines a start at the mirror image (same material, offset and gain; the free groups of
    ``fit``) and reports the deviance difference.

    `noise`: the noise model `fit` was refined with (default as :func:`refine`).
    `world_normal`: normal of the world mirror plane, which must hold the line of sight and the
    sensor's x polarization reference (``+y`` for the canonical sensor; for a bistatic
    sensor the receiver direction too). `max_steps`, `rounds`, `solver`: as in :func:`refine`
    (the same `max_steps` as the fit's reuses its compilation). `bounds`: a physical box
    (:class:`PhysicalBounds`); when the unbounded mirror refit leaves it
    (:meth:`RefineResult.outside_bounds`), the mirror is refit from the same start with
    :func:`refine_bounded`, as one would the fit itself.
    """
    from ppr.geometry import quat_to_matrix_host

    from ._classifier import _describe, line_of_sight_error_deg
    from ._grid import as_symmetry, body_mirror_normal, mirror_attitude

    normal = body_mirror_normal(symmetry)
    if normal is None:
        raise ValueError(
            f"mirror_check: symmetry {_describe(symmetry)} implies no mirror plane "
            "(use dihedral:n or octahedral for bodies that have one, or mode_check)"
        )
    p = fit.params
    q_m = mirror_attitude(np.asarray(p.quaternion), normal, world_normal)
    # a mesh's mirror plane passes through its centre c: the image moves by R (sigma c - c)
    c = as_symmetry(symmetry).centre
    sigma = np.eye(3) - 2.0 * np.outer(normal, normal)
    rot = quat_to_matrix_host(np.asarray(p.quaternion, np.float64))
    shift = float(rot[2] @ (sigma @ c - c))  # the line of sight is world +z
    mirror = _refit_from(
        model,
        data,
        fit,
        q_m,
        shift,
        noise=noise,
        max_steps=max_steps,
        rounds=rounds,
        solver=solver,
        bounds=bounds,
    )
    sep = line_of_sight_error_deg(
        np.asarray(p.quaternion),
        np.asarray(mirror.params.quaternion),
        symmetry if isinstance(symmetry, str) else as_symmetry(symmetry),
    )[0]
    return MirrorCheck(
        fit=fit,
        mirror=mirror,
        delta_deviance=float(mirror.cost - fit.cost),
        separation_deg=float(sep),
    )


def _refit_from(
    model,
    data,
    fit: RefineResult,
    q_start,
    range_shift: float,
    *,
    noise,
    max_steps,
    rounds,
    solver,
    bounds,
    start: PhysicalParams | None = None,
) -> RefineResult:
    """Refine from ``fit``'s parameters with the attitude ``q_start`` and the range offset
    moved by ``range_shift`` (same free groups and range scale as ``fit``), kept inside
    ``bounds`` when given (:func:`refine`'s box: the same compiled solver); refit with
    :func:`refine_bounded` should the optimum still leave it. ``start``: refine from these
    parameters instead (``q_start`` and ``range_shift`` are then its own)."""
    p = fit.params
    if start is None:
        start = PhysicalParams(
            jnp.asarray(q_start, p.m.dtype),
            p.m,
            p.n,
            p.corr_length,
            p.range_offset + jnp.asarray(range_shift, p.range_offset.dtype),
            p.gain,
            p.thickness,
            p.thickness_slots,
        )
    out = refine(
        model,
        data,
        [start],
        noise=noise,
        free=fit.parametrisation.free,
        solver=solver,
        max_steps=max_steps,
        rounds=rounds,
        range_scale=fit.parametrisation.range_scale,
        bounds=bounds,
    )
    if bounds is not None and out.outside_bounds(bounds):
        out = refine_bounded(
            model,
            data,
            [start],
            noise=noise,
            bounds=bounds,
            free=fit.parametrisation.free,
            rounds=rounds,
            range_scale=fit.parametrisation.range_scale,
        )
    return out


@dataclasses.dataclass(frozen=True)
class ModeFit:
    """One candidate mode of a fit refined (:func:`mode_check`).

    - `mode`: the candidate (:class:`inversion.Mode`: start attitude, label, kind).
    - `fit`: the refiner's optimum from that start.
    - `delta_deviance`: ``fit.cost - (the checked fit).cost`` (``-2 log`` likelihood ratio
      for :class:`PoissonCounts`).
    - `separation_deg`: attitude angle of the optimum from the checked fit, modulo the exact
      equivalences; `los_separation_deg`: the same for the body-frame line of sight (modulo
      the exact rotations only).
    - `duplicate_of`: index (in :attr:`ModeCheck.modes`) of the mode this optimum shares a
      basin with (within the check's ``min_separation_deg`` modulo the exact equivalences),
      the one of the group with the lowest deviance; ``None`` for that one itself.
    - `weight`: posterior weight ``exp(-deviance / 2)`` normalized over the distinct modes
      (0 for a duplicate): equal prior mass and equal posterior volume per mode, exact for
      a parity or symmetry image whose data are the same up to the noise.
    """

    mode: Any
    fit: RefineResult
    delta_deviance: float
    separation_deg: float
    los_separation_deg: float
    duplicate_of: int | None
    weight: float

    @property
    def label(self) -> str:
        return self.mode.label

    @property
    def kind(self) -> str:
        return self.mode.kind

    def to_dict(self) -> dict:
        return {
            **self.mode.to_dict(),
            "deviance": float(self.fit.cost),
            "delta_deviance": float(self.delta_deviance),
            "separation_deg": float(self.separation_deg),
            "los_separation_deg": float(self.los_separation_deg),
            "duplicate_of": self.duplicate_of,
            "weight": float(self.weight),
            "refined_quaternion": [float(x) for x in np.asarray(self.fit.params.quaternion)],
            "converged": bool(self.fit.success),
        }


@dataclasses.dataclass(frozen=True)
class ModeCheck:
    """Every candidate mode of a fit, refined and weighted (:func:`mode_check`).

    ``modes[0]`` is the checked fit itself (label ``"fit"``). :attr:`weights` are the
    posterior weights of the modes (0 for duplicates), :meth:`fits` the distinct optima to
    sample (:func:`inversion.sample_modes`).
    """

    fit: RefineResult
    modes: tuple[ModeFit, ...]

    @property
    def weights(self) -> np.ndarray:
        return np.array([m.weight for m in self.modes])

    @property
    def distinct(self) -> tuple[ModeFit, ...]:
        return tuple(m for m in self.modes if m.duplicate_of is None)

    def fits(self) -> list[RefineResult]:
        """The distinct optima, in mode order (for :func:`inversion.sample_modes`)."""
        return [m.fit for m in self.distinct]

    @property
    def best(self) -> RefineResult:
        """The optimum with the lowest deviance."""
        return min((m.fit for m in self.modes), key=lambda f: f.cost)

    def ambiguous(self, level: float = 0.05) -> bool:
        """More than one distinct mode keeps a posterior weight above `level`."""
        return int(np.sum(self.weights > level)) > 1

    def summary(self) -> str:
        lines = [f"mode check: {len(self.distinct)} distinct of {len(self.modes)} modes"]
        for j, m in enumerate(self.modes):
            dup = "" if m.duplicate_of is None else f", same mode as {m.duplicate_of}"
            lines.append(
                f"  {j}: {m.label}: weight {m.weight:.3g}, delta deviance "
                f"{m.delta_deviance:+.4g}, {m.separation_deg:.3g} deg from the fit "
                f"(line of sight {m.los_separation_deg:.3g} deg){dup}"
            )
        if self.ambiguous():
            lines.append("  ambiguous: the data do not single out one mode")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "n_distinct": len(self.distinct),
            "ambiguous": self.ambiguous(),
            "modes": [m.to_dict() for m in self.modes],
        }


def mode_check(
    model,
    data,
    fit: RefineResult,
    symmetry,
    *,
    noise=None,
    mirror: bool = True,
    near: bool = True,
    half_turn_exact: bool = True,
    los=(0.0, 0.0, 1.0),
    world_normal=(0.0, 1.0, 0.0),
    exact_tol: float = 1e-6,
    min_separation_deg: float = 1.0,
    max_steps: int = 200,
    rounds: int = 2,
    solver: str | Any = "lm",
    bounds: PhysicalBounds | None = None,
    modes=None,
) -> ModeCheck:
    """Refine every candidate mode of ``fit`` and weight the optima.

    The candidates (:func:`inversion.candidate_modes`) are the mirror images of the scene
    through the body's improper elements, the attitudes its near symmetries map the fit to,
    and (``half_turn_exact=False``, a bistatic sensor) the half turn about the line of
    sight; exactly equivalent attitudes give the same data and are not refit. Each is
    refined from ``fit``'s parameters with its attitude and range offset
    (:attr:`inversion.Mode.range_shift`), like :func:`mirror_check` does for the one mirror
    image of a named class, which this generalizes: ``symmetry`` may be a named class, a
    :class:`ppr.MeshSymmetry` or a :class:`ppr.Mesh` (its own group; pass
    ``ppr.mesh_symmetries(mesh, tol=1e-2)`` to include near symmetries). Optima within
    ``min_separation_deg`` of each other modulo the exact equivalences are one mode; each
    distinct mode is weighted by ``exp(-deviance / 2)`` (:class:`ModeFit`).

    `modes`: the candidates to refit (default :func:`inversion.candidate_modes` with these
    settings; the fit must be first). `noise`, `max_steps`, `rounds`, `solver`, `bounds`:
    as in :func:`mirror_check`.
    """
    from ._classifier import line_of_sight_error_deg
    from ._grid import as_symmetry
    from ._modes import candidate_modes, mode_separation_deg

    sym = as_symmetry(symmetry)
    q_fit = np.asarray(fit.params.quaternion, np.float64)
    if modes is None:
        modes = candidate_modes(
            q_fit,
            sym,
            mirror=mirror,
            near=near,
            half_turn_exact=half_turn_exact,
            los=los,
            world_normal=world_normal,
            exact_tol=exact_tol,
            min_separation_deg=min_separation_deg,
        )
    modes = list(modes)
    if not modes or modes[0].kind != "fit":
        raise ValueError("mode_check: modes must start with the fit itself (kind 'fit')")
    exact_rot = sym.quaternions()[sym.residuals[sym.determinants > 0] <= exact_tol]

    sep_kw = {"half_turn_exact": half_turn_exact, "los": los, "exact_tol": exact_tol}

    fits = [fit]
    for m in modes[1:]:
        fits.append(
            _refit_from(
                model,
                data,
                fit,
                m.quaternion,
                m.range_shift,
                start=m.start,
                noise=noise,
                max_steps=max_steps,
                rounds=rounds,
                solver=solver,
                bounds=bounds,
            )
        )
    quats = [np.asarray(f.params.quaternion, np.float64) for f in fits]
    costs = np.array([f.cost for f in fits], float)
    # group optima that share a basin; each group is represented by its lowest deviance
    group = list(range(len(fits)))
    for j in range(1, len(fits)):
        for i in range(j):
            sep = mode_separation_deg(quats[i], quats[j], sym, **sep_kw)
            if group[i] == i and sep <= min_separation_deg:
                group[j] = i
                break
    rep = {}
    for j, g in enumerate(group):
        if g not in rep or costs[j] < costs[rep[g]]:
            rep[g] = j
    distinct = sorted(rep.values())
    finite = [j for j in distinct if np.isfinite(costs[j])]
    weights = np.zeros(len(fits))
    if finite:
        c0 = min(costs[j] for j in finite)
        for j in finite:
            weights[j] = math.exp(-0.5 * (costs[j] - c0))
        weights /= weights.sum()
    out = []
    for j, (m, f) in enumerate(zip(modes, fits, strict=True)):
        r = rep[group[j]]
        los_sep = line_of_sight_error_deg(q_fit, quats[j], exact_rot, los=los)[0]
        out.append(
            ModeFit(
                mode=m,
                fit=f,
                delta_deviance=float(f.cost - fit.cost),
                separation_deg=mode_separation_deg(q_fit, quats[j], sym, **sep_kw),
                los_separation_deg=float(los_sep),
                duplicate_of=None if r == j else r,
                weight=float(weights[j]),
            )
        )
    return ModeCheck(fit=fit, modes=tuple(out))


@dataclasses.dataclass(frozen=True)
class PhysicalBounds:
    """Box bounds in physical units for :func:`refine_bounded` (``(low, high)`` pairs).

    Defaults: ``n'`` in [0.05, 5] (not [1, 5]: metals have ``n' < 1``, e.g. aluminium 0.94,
    gold 0.54, silver 0.054 at 532 nm, docs/physics.md#materials), ``n''`` in [0, 15], ``m`` in
    [0, 1e6], correlation length in [1e-8, 1e-2] m, range offset in [-1, 1] m, gain in
    :data:`~inversion._params.GAIN_RANGE` = [1e-6, 1e18] counts per (m^2 sr^-1) (wide: any
    real measurement is inside), film thickness in [1e-9, 1e-3] m; the attitude rotation
    vector is bounded by ``max_rotation_deg`` about the start.
    """

    n_re: tuple[float, float] = (0.05, 5.0)
    n_im: tuple[float, float] = (0.0, 15.0)
    m: tuple[float, float] = (0.0, 1e6)
    corr_length: tuple[float, float] = (1e-8, 1e-2)
    range_offset: tuple[float, float] = (-1.0, 1.0)
    gain: tuple[float, float] = GAIN_RANGE
    thickness: tuple[float, float] = (1e-9, 1e-3)
    max_rotation_deg: float = 180.0

    def __post_init__(self):
        for f in ("n_re", "n_im", "m", "corr_length", "range_offset", "gain", "thickness"):
            lo, hi = getattr(self, f)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(
                    f"PhysicalBounds.{f} must be finite with low < high, got {(lo, hi)}"
                )
        for f in ("n_re", "corr_length", "gain", "thickness"):
            if getattr(self, f)[0] <= 0:
                raise ValueError(
                    f"PhysicalBounds.{f} lower bound must be > 0, got {getattr(self, f)}"
                )
        if self.n_im[0] < 0 or self.m[0] < 0:
            raise ValueError(
                f"PhysicalBounds: n_im and m lower bounds must be >= 0, got {self.n_im}, {self.m}"
            )


class _BoxMap(eqx.Module):
    """Bounded coordinates z: rotvec (rad), log1p(m), n', n'', log d, offset/scale, log g."""

    reference: PhysicalParams
    free: tuple[str, ...] = eqx.field(static=True)
    range_scale: float = eqx.field(static=True)

    def _sizes(self):
        return group_sizes(self.reference)

    def ordered(self):
        from ._params import GROUPS

        return tuple(g for g in GROUPS if g in self.free)

    def to_physical(self, z):
        from ppr.geometry import quat_from_rotvec, quat_multiply

        ref, k, i, parts = self.reference, self.reference.n_materials, 0, {}
        for g in self.ordered():
            parts[g] = z[i : i + self._sizes()[g]]
            i += self._sizes()[g]
        q = ref.unit_quaternion().astype(z.dtype)
        if "attitude" in parts:
            q = quat_multiply(quat_from_rotvec(parts["attitude"]), q)
        # L-BFGS-B's line search can probe a rounding error beyond the box; the material's
        # domain (m >= 0, n' > 0, n'' >= 0) is part of the box, so project onto it here
        m = jnp.expm1(jnp.maximum(parts["m"], 0.0)) if "m" in parts else ref.m
        n = (
            jax.lax.complex(jnp.maximum(parts["n"][:k], 1e-6), jnp.maximum(parts["n"][k:], 0.0))
            if "n" in parts
            else ref.n
        )
        d = jnp.exp(parts["corr_length"]) if "corr_length" in parts else ref.corr_length
        off = (
            parts["range_offset"][0] * self.range_scale
            if "range_offset" in parts
            else ref.range_offset
        )
        gain = jnp.exp(parts["gain"][0]) if "gain" in parts else ref.gain
        thick = ref.thickness.astype(z.dtype)
        if "thickness" in parts and ref.thickness_slots:
            thick = thick.at[jnp.asarray(ref.thickness_slots)].set(jnp.exp(parts["thickness"]))
        return PhysicalParams(q, m, n, d, off, gain, thick, ref.thickness_slots)

    def from_physical(self, phys):
        from ppr.geometry import quat_conjugate, quat_multiply, rotvec_from_quat

        out = []
        for g in self.ordered():
            if g == "attitude":
                q_ref = self.reference.unit_quaternion()
                dq = quat_multiply(phys.unit_quaternion(), quat_conjugate(q_ref))
                out.append(rotvec_from_quat(dq))
            elif g == "m":
                out.append(jnp.log1p(phys.m))
            elif g == "n":
                out += [jnp.real(phys.n), jnp.imag(phys.n)]
            elif g == "corr_length":
                out.append(jnp.log(phys.corr_length))
            elif g == "range_offset":
                out.append(jnp.reshape(phys.range_offset / self.range_scale, (1,)))
            elif g == "gain":
                out.append(jnp.reshape(jnp.log(phys.gain), (1,)))
            elif g == "thickness":
                t = phys.thickness[jnp.asarray(self.reference.thickness_slots, jnp.int32)]
                out.append(jnp.log(jnp.maximum(t, 1e-12)))
        return jnp.concatenate([jnp.asarray(o, phys.m.dtype) for o in out])

    def bounds(self, b: PhysicalBounds):
        k = self.reference.n_materials
        lo, hi = [], []
        for g in self.ordered():
            if g == "attitude":
                r = np.radians(b.max_rotation_deg)
                lo += [-r] * 3
                hi += [r] * 3
            elif g == "m":
                lo += [np.log1p(b.m[0])] * k
                hi += [np.log1p(b.m[1])] * k
            elif g == "n":
                lo += [b.n_re[0]] * k + [b.n_im[0]] * k
                hi += [b.n_re[1]] * k + [b.n_im[1]] * k
            elif g == "corr_length":
                lo += [np.log(b.corr_length[0])] * k
                hi += [np.log(b.corr_length[1])] * k
            elif g == "range_offset":
                lo.append(b.range_offset[0] / self.range_scale)
                hi.append(b.range_offset[1] / self.range_scale)
            elif g == "gain":
                lo.append(np.log(b.gain[0]))
                hi.append(np.log(b.gain[1]))
            elif g == "thickness":
                n_t = len(self.reference.thickness_slots)
                lo += [np.log(b.thickness[0])] * n_t
                hi += [np.log(b.thickness[1])] * n_t
        return np.asarray(lo), np.asarray(hi)


@eqx.filter_jit(compiler_options=MODEL_PROGRAM)
def _bounded_round(model, box, aux, inv_sigma, data, z0, lower, upper, maxiter, tol, noise):
    from ._jaxopt_adapter import lbfgsb_minimize

    def chi2(z):
        r = noise_residuals(noise, data, model.expected(box.to_physical(z), aux), inv_sigma)
        return jnp.sum(r * r)

    scale = jnp.maximum(chi2(z0), 1.0)
    sol = lbfgsb_minimize(lambda z: chi2(z) / scale, z0, lower, upper, maxiter=maxiter, tol=tol)
    return sol, chi2(sol.x)


@eqx.filter_jit
def _box_from(box, phys):
    return box.from_physical(phys)


@eqx.filter_jit
def _box_to(box, z):
    return box.to_physical(z)


def refine_bounded(
    model,
    data,
    starts: PhysicalParams | Sequence[PhysicalParams],
    *,
    noise=None,
    bounds: PhysicalBounds | None = None,
    free: Sequence[str] = DEFAULT_FREE,
    maxiter: int = 500,
    tol: float = 1e-7,
    rounds: int = 3,
    range_scale: float = 0.01,
) -> RefineResult:
    """Box-bounded weighted least squares with L-BFGS-B (jaxopt, via :mod:`._jaxopt_adapter`).

    Same interface, rounds and result as :func:`refine`; the parameters are kept inside
    ``bounds`` (:class:`PhysicalBounds`). ``result`` is ``"successful"`` when the projected
    gradient of ``chi^2 / max(chi^2_start, 1)`` fell below ``tol``, ``"max_steps_reached"`` or
    ``"linesearch_failed"`` otherwise. The covariance is the unconstrained Gauss-Newton one at
    the optimum (not meaningful for a parameter sitting on a bound: check ``at_bounds`` in
    the message).
    """
    t0 = time.perf_counter()
    noise = PoissonNoise() if noise is None else noise
    bounds = PhysicalBounds() if bounds is None else bounds
    starts = _as_starts(starts)
    free = tuple(free)
    aux0 = model.prepare(starts[0])
    data_np = check_observation(data, _model_shape(model, starts[0], aux0))
    if hasattr(noise, "check_data"):
        noise.check_data(data_np)
    dt = starts[0].m.dtype
    data_j = jnp.asarray(data_np, dt)

    summaries = []
    for idx, start in enumerate(starts):
        phys = start
        steps, used, name, cost, msg = 0, 0, "successful", np.inf, ""
        for rnd in range(rounds):
            box = _BoxMap(phys, free, range_scale)
            lower, upper = (jnp.asarray(a, dt) for a in box.bounds(bounds))
            aux = aux0 if (idx == 0 and rnd == 0) else model.prepare(phys)
            inv_sigma, _ = _weights(_pure(model), noise, phys, aux)
            z0 = _box_from(box, phys)
            sol, cost_j = _bounded_round(
                _pure(model), box, aux, inv_sigma, data_j, z0, lower, upper, maxiter, tol, noise
            )
            used += 1
            steps += int(sol.n_iter)
            new_cost = float(cost_j)
            if not np.all(np.isfinite(np.asarray(sol.x))) or not np.isfinite(new_cost):
                name, msg, cost = (
                    "nonfinite",
                    "non-finite parameters or cost during L-BFGS-B",
                    np.inf,
                )
                break
            phys = _box_to(box, sol.x)
            if bool(sol.converged):
                name, msg = "successful", "converged"
            elif bool(sol.failed_linesearch):
                name, msg = (
                    "linesearch_failed",
                    (
                        "L-BFGS-B line search failed (projected gradient "
                        f"{float(sol.error):.3g} > tol {tol:g})"
                    ),
                )
            else:
                name, msg = (
                    "max_steps_reached",
                    (
                        f"L-BFGS-B reached maxiter={maxiter} (projected gradient "
                        f"{float(sol.error):.3g} > tol {tol:g})"
                    ),
                )
            done = abs(cost - new_cost) <= 1e-9 * max(new_cost, 1.0)
            cost = new_cost
            if done:
                break
        at = _at_bounds(_BoxMap(phys, free, range_scale), phys, bounds)
        if at and name == "successful":
            msg = f"converged; at bounds: {', '.join(at)}"
        summaries.append(
            StartSummary(idx, start, phys, cost, name == "successful", name, msg, steps, used)
        )
    order = sorted(
        range(len(summaries)), key=lambda i: (not summaries[i].success, summaries[i].cost)
    )
    ordered = tuple(summaries[i] for i in order)
    return _finish(
        model, noise, data_j, ordered[0], ordered, free, range_scale, t0, "lbfgsb_jaxopt"
    )


def _at_bounds(box: _BoxMap, phys: PhysicalParams, bounds: PhysicalBounds) -> list[str]:
    labels = []
    k = phys.n_materials
    for g in box.ordered():
        if g == "attitude":
            labels += ["rotvec"] * 3
        elif g == "m":
            labels += [f"m[{i}]" for i in range(k)]
        elif g == "n":
            labels += [f"n_re[{i}]" for i in range(k)] + [f"n_im[{i}]" for i in range(k)]
        elif g == "corr_length":
            labels += [f"corr_length[{i}]" for i in range(k)]
        elif g == "thickness":
            labels += [f"thickness[{i}]" for i in phys.thickness_slots]
        else:
            labels.append(g)
    z = np.asarray(box.from_physical(phys))
    lo, hi = box.bounds(bounds)
    tol = 1e-9 * np.maximum(1.0, np.abs(z))
    hit = (np.abs(z - lo) <= tol) | (np.abs(z - hi) <= tol)
    return [lab for lab, h in zip(labels, hit, strict=True) if h and lab != "rotvec"]


# --------------------------------------------------------------------------- ppr simulator
class SimulatorKernel(eqx.Module):
    """The pure, jittable part of :class:`SimulatorModel` (arrays + static sizes only, so
    meshes padded to the same capacity share one compilation)."""

    arrays: Any
    sensor: Any
    sigma_r: Array
    start: Array
    width: Array
    projection: Array
    background: Array
    position: Array
    n_bins: int = eqx.field(static=True)
    window: int = eqx.field(static=True)
    brdf: Any = eqx.field(static=True)
    terms: Any = eqx.field(static=True)
    # the scene's film stacks, stacked per slot (ppr.stack_materials), or None; film_fit marks
    # per layer the slots whose layer thickness is PhysicalParams.thickness
    films: Any = None
    film_wavelength: Any = None
    film_fit: Any = None
    film_mode: str = eqx.field(static=True, default="coherent")
    thick_layer: int = eqx.field(static=True, default=-1)

    def prepare(self, phys):  # pragma: no cover - the host part lives in SimulatorModel
        raise TypeError("SimulatorKernel has no visibility caster; use SimulatorModel")

    def expected(self, phys: PhysicalParams, vis):
        import ppr

        macro = None
        if isinstance(vis, tuple):  # (visibility, ppr.MacroPairs): SimulatorModel.prepare
            vis, macro = vis
        dt = self.arrays.tri.dtype
        pose = ppr.Pose(phys.unit_quaternion().astype(dt), self.position)
        mats = ppr.Material(phys.n, phys.m.astype(dt), phys.corr_length.astype(dt))
        if self.films is not None:
            # the slots phys names (thickness_slots, static) take its thickness at their
            # fitted layer; every other layer keeps the scene's
            t = phys.thickness.astype(dt)
            named = np.zeros(t.shape, bool)
            named[list(phys.thickness_slots)] = True
            films = tuple(
                (n, jnp.where(fit & named, t, tj))
                for (n, tj), fit in zip(self.films, self.film_fit, strict=True)
            )
            mats = ppr.Material(
                phys.n,
                phys.m.astype(dt),
                phys.corr_length.astype(dt),
                films=films,
                wavelength=self.film_wavelength,
                film_mode=self.film_mode,
                thick_layer=self.thick_layer,
            )
        arrays = self.arrays
        if isinstance(vis, ppr.FaceSubset):
            # only the facets lit and visible at the round's pose (SimulatorModel(prune=True))
            arrays, vis = vis.apply(arrays), vis.vis
        out = ppr.render(
            arrays,
            vis,
            pose,
            mats,
            self.sensor,
            self.sigma_r,
            self.start - phys.range_offset.astype(dt),
            self.width,
            n_bins=self.n_bins,
            window=self.window,
            projection=self.projection,
            brdf=self.brdf,
            terms=self.terms,
            macro=macro,
        )
        return phys.gain.astype(dt) * out + self.background


class SimulatorModel:
    """Forward model backed by ppr's pulse synthesis (:func:`ppr.render`) and a PSG/PSA
    measurement model: expected counts ``gain * P . M(b) + background`` per channel and bin.

    ``prepare`` ray-casts the per-face lit-and-visible fractions at the given attitude on the
    host (embree, :class:`ppr.VisibilityCaster`); ``expected`` is pure and differentiable in
    the attitude, ``m``, ``n``, correlation length, range offset (moves the range gate) and
    gain. Material slot ``k`` of :class:`PhysicalParams` is mesh part ``k``. The jitted
    solvers see only :attr:`pure_model` (a :class:`SimulatorKernel`).

    **Arguments:**

    - `scene`: :class:`ppr.Scene` (mesh, sensor, pulse, bins, position; its attitude and
      materials are ignored).
    - `channel_matrix`: ``(C, 4, 4)``, ``I_c = sum_ij P[c, i, j] M[i, j]``
      (:meth:`inversion.MeasurementModel.channel_matrix`).
    - `brdf`, `terms`: Mueller BRDF (default :func:`ppr.mueller_brdf`) and its terms.
    - `background`: expected background counts per (channel, bin).
    - `dense`: evaluate every facet on every bin (window = n_bins): slower per call for large
      meshes, but every mesh of the same padded capacity shares one compilation.
    - `capacity`: padded face capacity (default :func:`ppr.mesh_arrays`'s).
    - `multibounce`, `macro_options`: the macro double bounce between the mesh's surfaces
      (``ppr.simulate``'s switch; ``"auto"``: included when some surfaces face each other).
      :meth:`prepare` then returns ``(visibility, ppr.MacroPairs)``: the pairs, their
      visibility and glossy/broad kinds are held fixed over a round like the visibility,
      each kind padded to the capacity of the pose's own count (0 when it has none, else
      8, 16, ...): a pose pays only for the paths it has (a dead slot costs as much as a
      live one), at the price of one program per combination met (glossy pairs only,
      broad pairs only, both).
    - `prune`: :meth:`prepare` returns a :class:`ppr.FaceSubset` of the facets lit and
      visible at the given pose instead of the whole mesh's fractions: the facets it leaves
      out contribute exactly zero at that visibility, so every result is the same (to the
      summation order), and each solver round and MCMC chain renders only the subset (2-3x
      faster on the bench's CubeSats and cylinder, `bench/bench_prune.py`). The subsets'
      capacities are fixed per model (:meth:`subset_capacities`: the largest lit count over
      random attitudes, padded), so the solvers compile once per model, not once per padded
      mesh capacity; a pose beyond it gets the next capacity (8, 16, 32, 64, ...) and one
      more compilation. :meth:`visibility` gives the full fractions either way.
    """

    def __init__(
        self,
        scene,
        channel_matrix,
        *,
        brdf=None,
        terms=None,
        background=0.0,
        dtype=None,
        dense=False,
        capacity=None,
        prune=True,
        multibounce="auto",
        macro_options=None,
    ):
        import ppr
        from ppr.optics.conventions import C_LIGHT

        dt = jnp.result_type(float) if dtype is None else dtype
        mesh, sensor, pulse, bins = scene.mesh, scene.sensor, scene.pulse, scene.bins
        P = np.asarray(channel_matrix, np.float64)
        if P.ndim != 3 or P.shape[1:] != (4, 4):
            raise ValueError(f"channel_matrix must have shape (C, 4, 4), got {P.shape}")
        arrays = ppr.mesh_arrays(mesh, capacity, dtype=dt)
        sigma_r = 0.5 * C_LIGHT * float(pulse.sigma_t)
        shift = 0.5 * C_LIGHT * float(pulse.t0)
        tri = mesh.triangles()
        w = np.asarray(sensor.bisector, np.float64)
        max_edge = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max())
        if dense:
            window = int(bins.n_bins)
        else:
            window = ppr.window_size(
                max_edge * float(np.linalg.norm(w)), sigma_r, float(bins.width), bins.n_bins
            )
        cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dt), t)  # noqa: E731
        brdf = ppr.mueller_brdf if brdf is None else brdf
        if brdf is ppr.mueller_brdf:
            # the kernel's traced inputs are valid by construction (attitude normalized,
            # m = e^x, n'' = softplus): without the traced checks' host callback the solver
            # and sampler programs can go to JAX's persistent compilation cache
            from ppr.brdf import mueller_brdf_unchecked  # noqa: PLC0415

            brdf = mueller_brdf_unchecked
        self.scene = scene
        self.prune = bool(prune)
        self._subset_caps: tuple[int, int] | None = None
        self.caster = ppr.VisibilityCaster(mesh, scene.vis_samples)
        self.n_faces = mesh.n_faces
        if multibounce not in (True, False, "auto"):
            raise ValueError(f"multibounce must be True, False or 'auto', got {multibounce!r}")
        self.macro_options = macro_options or ppr.MacroOptions()
        geom = ppr.macro_geometry(mesh, plates=self.macro_options.plates)
        self.multibounce = multibounce is True or (multibounce == "auto" and not geom.convex)
        # macro triangles padded once; the glossy and broad pair capacities start at 8 each
        # and only grow (macro_pairs), so that every pose and roughness (a part is glossy or
        # broad by its m) shares one compiled program; dead broad slots are skipped at run
        # time (ppr.pulse macro_profile's cond), dead glossy ones are cheap
        from ppr.pulse import glossy_parts  # noqa: PLC0415

        glossy_ok = self.multibounce and bool(glossy_parts([np.inf], brdf).any())
        self._macro_caps = (geom.n_macro, 8 * glossy_ok, 8 * self.multibounce)
        self.pure_model = SimulatorKernel(
            arrays=arrays,
            sensor=cast(sensor),
            sigma_r=jnp.asarray(sigma_r, dt),
            start=jnp.asarray(float(bins.start) - shift, dt),
            width=jnp.asarray(float(bins.width), dt),
            projection=jnp.asarray(P.reshape(P.shape[0], 16).T, dt),
            background=jnp.asarray(background, dt),
            position=jnp.asarray(np.asarray(scene.pose.position, np.float64), dt),
            n_bins=int(bins.n_bins),
            window=int(window),
            brdf=brdf,
            # monostatic: the double term's backscatter table, not its quadrature, in the
            # compiled residual and gradient programs
            terms=ppr.sensor_terms(brdf, terms, sensor),
            **self._film_template(scene.materials, dt),
        )

    def _film_template(self, materials, dt) -> dict:
        """The scene's film stacks for :class:`SimulatorKernel` (slots = mesh parts) and, on
        the model, ``film_slots`` (the coated slots, in order: ``PhysicalParams.
        thickness_slots``) and ``film_thickness`` ``(K,)`` (each slot's fitted layer: the thick
        layer of a stack that has one, else its outermost; 0 for bare slots)."""
        import ppr
        from ppr.materials import film_fit_layers

        mats = list(materials)
        fit = film_fit_layers(mats)
        self.film_slots = tuple(i for i, j in enumerate(fit) if j is not None)
        self.film_thickness = np.zeros(len(mats))
        if not self.film_slots:
            return {}
        st = ppr.stack_materials(mats)
        cdt = jnp.result_type(dt, jnp.complex64)
        films = tuple((jnp.asarray(n, cdt), jnp.asarray(t, dt)) for n, t in st.films)
        mask = np.zeros((len(films), len(mats)), bool)
        for i, j in enumerate(fit):
            if j is not None:
                mask[j, i] = True
                self.film_thickness[i] = float(np.asarray(st.films[j][1])[i])
        return dict(
            films=films,
            film_wavelength=jnp.asarray(st.wavelength, dt),
            film_fit=tuple(jnp.asarray(row) for row in mask),
            film_mode=st.film_mode,
            thick_layer=st.thick_layer,
        )

    def physical_params(self, quaternion, m, n, **kw) -> PhysicalParams:
        """:class:`PhysicalParams` for this model's scene: ``thickness`` and
        ``thickness_slots`` default to the scene's coated slots and their fitted layers."""
        kw.setdefault("thickness", self.film_thickness)
        kw.setdefault("thickness_slots", self.film_slots)
        return PhysicalParams(quaternion, m, n, **kw)

    @property
    def n_channels(self) -> int:
        return int(self.pure_model.projection.shape[1])

    @property
    def n_bins(self) -> int:
        return self.pure_model.n_bins

    def prepare(self, phys: PhysicalParams):
        """Host: the per-face lit-and-visible fractions at ``phys``'s attitude
        (:meth:`visibility`), as a :class:`ppr.FaceSubset` of the contributing facets when
        the model prunes."""
        import ppr

        n_parts = len(self.scene.mesh.parts)
        if phys.n_materials != n_parts:
            raise ValueError(
                f"PhysicalParams has {phys.n_materials} material slots (m, n) but the model's "
                f"mesh has {n_parts} part{'s' if n_parts != 1 else ''} "
                f"({', '.join(self.scene.mesh.parts)}): one material per part"
            )
        vis = self.visibility(phys)
        macro = self.macro_pairs(phys)
        if not self.prune:
            return vis if macro is None else (vis, macro)
        cap, g_cap = self.subset_capacities()
        arrays = self.pure_model.arrays
        lit = (np.asarray(vis) > 0) & np.asarray(arrays.valid)
        n_groups = len(np.unique(np.asarray(arrays.normal_group)[lit]))
        # a pose beyond the sampled counts gets the next capacity (one more compilation)
        subset = ppr.FaceSubset.of(
            arrays,
            vis,
            capacity=max(cap, ppr.geometry.subset_capacity(int(lit.sum()))),
            group_capacity=max(g_cap, ppr.geometry.subset_capacity(n_groups)),
        )
        return subset if macro is None else (subset, macro)

    def macro_pairs(self, phys: PhysicalParams):
        """Host: the ``ppr.MacroPairs`` at ``phys``'s attitude and exponents (None without the
        double bounce)."""
        if not self.multibounce:
            return None
        import ppr
        from ppr.pulse import batch_pairs

        q = np.asarray(phys.unit_quaternion(), np.float64)
        rot = np.asarray(ppr.quat_to_matrix(q))
        sensor = self.pure_model.sensor
        u_in = rot.T @ np.asarray(sensor.laser_dir, np.float64)
        u_out = rot.T @ np.asarray(sensor.receiver_dir, np.float64)
        pm = self.pure_model
        pairs = batch_pairs(
            [self.scene.mesh],
            [self.caster],
            [0],
            [u_in],
            [u_out],
            [np.asarray(phys.m, np.float64)],
            pm.brdf,
            self.macro_options,
            capacities=self._macro_caps,
            bins=(float(pm.sigma_r), float(pm.width), pm.n_bins),
            window=pm.n_bins,
            mixed=True,
            dtype=pm.arrays.tri.dtype,
        )
        new = (pairs.tri.shape[1], pairs.g_i.shape[1], pairs.r_i.shape[1])
        # capacities only grow (inversion.invert prepares from a background thread too: a
        # smaller result written last must not shrink them and recompile the solver)
        self._macro_caps = tuple(max(a, b) for a, b in zip(self._macro_caps, new, strict=True))
        return jax.tree_util.tree_map(lambda a: a[0], pairs)  # the one row

    def subset_capacities(self, n_poses: int = 256) -> tuple[int, int]:
        """Host: the facet and group capacities of the pruned subsets (:meth:`prepare`): the
        padded largest lit-and-visible counts over ``n_poses`` random attitudes (seeded), so
        that every subset has the same shapes and the solvers compile once per model. Cached
        after the first call (~40 ms for 50 facets, ~130 ms for 500)."""
        if self._subset_caps is None:
            from ppr.geometry import quat_to_matrix_host, subset_capacity

            arrays = self.pure_model.arrays
            valid, grp = np.asarray(arrays.valid), np.asarray(arrays.normal_group)
            n_max, g_max = 1, 1
            for q in np.random.default_rng(0).normal(size=(n_poses, 4)):
                lit = (self._fractions(quat_to_matrix_host(q)) > 0) & valid
                n_max = max(n_max, int(lit.sum()))
                g_max = max(g_max, len(np.unique(grp[lit])))
            self._subset_caps = (subset_capacity(n_max), subset_capacity(g_max))
        return self._subset_caps

    def visibility(self, phys: PhysicalParams):
        """Host: ``(F,)`` lit-and-visible fraction of every padded facet at ``phys``'s attitude
        (embree ray casts, :class:`ppr.VisibilityCaster`)."""
        import ppr

        q = np.asarray(phys.unit_quaternion(), np.float64)
        rot = np.asarray(ppr.quat_to_matrix(q))
        return jnp.asarray(self._fractions(rot), self.pure_model.arrays.tri.dtype)

    def _fractions(self, rot):
        """Host: ``(F,)`` fractions (NumPy, padded) at the body-to-world rotation ``rot``."""
        u_in = np.asarray(self.pure_model.sensor.laser_dir, np.float64)
        u_out = np.asarray(self.pure_model.sensor.receiver_dir, np.float64)
        vis = self.caster.fractions(rot.T @ u_in, rot.T @ u_out)
        full = np.zeros(self.pure_model.arrays.valid.shape[0])
        full[: vis.shape[0]] = vis
        return full

    def expected(self, phys: PhysicalParams, vis):
        return _expected_jit(self.pure_model, phys, vis)


@eqx.filter_jit(compiler_options=MODEL_PROGRAM)
def _expected_jit(kernel, phys, vis):
    return kernel.expected(phys, vis)


def _pure(model):
    """What the jitted functions see: ``model.pure_model`` if present, else the model."""
    return getattr(model, "pure_model", model)
