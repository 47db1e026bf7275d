r"""Posterior sampling with emcee: jitted, walker-vectorised log-probability; diagnostics.

The sampler moves the refiner's unconstrained vector ``theta`` (:mod:`inversion._params`,
reference = the refined optimum, so the attitude entries are small rotations about it). The
log-posterior in ``theta`` is

    log p(theta | d) = log L(d | phys(theta)) + sum_g log pi_g(phys_g) + log |d phys / d theta|

with the noise model's likelihood: exact Poisson for :class:`~inversion._refine.PoissonCounts`,
otherwise Gaussian with the noise model's ``variance(expected, phys)`` (including the
``-1/2 log(2 pi var)`` term, since the variance depends on the parameters),
priors ``pi_g`` on *physical* values (from a TOML config, :class:`MCMCConfig`) and the
Jacobian of the reparametrisation (``m = e^x`` -> ``x``; ``n'' = softplus(u)`` ->
``log sigmoid(u)``; rotation vector -> Haar measure ``4 sin^2(|w|/2) / |w|^2`` for a uniform
attitude prior). Visibility (``aux``) is fixed at the refined optimum during sampling (it is
piecewise constant; the chain explores a small neighbourhood).

The walkers move in sampler coordinates, bijections of ``theta`` whose log Jacobians enter
the target, so the posterior is unchanged (``SamplerConfig``): the attitude as
``exp(phi k) exp(t) q_ref`` with ``k`` the line of sight (:class:`_RollSeparation`), the
gain as the log of the total expected signal (:class:`_CountsLogProb`), and, given a
material library (``materials``, as :func:`inversion.invert` does), the index as a
coordinate over the library's materials (:class:`_LibraryIndex`: the posterior over them
with a uniform prior on the library). Besides emcee's moves, independence moves redraw the
roll (:class:`_RollMove`) and jump between materials, translated between the per-material
optima (:class:`_MaterialMove`); each satisfies detailed balance on its own. These make the
directions a glossy target leaves flat (the roll, the index the gain absorbs) mix in a few
steps instead of diffusing across the prior (``bench/results/mcmc_flat.md``). From the
second quarter of the burn-in on, independence moves redraw the continuous coordinates from a
Student-t fitted to the walkers' positions over the quarter before (:class:`_IndependenceMove`;
the last fit, from the burn-in's last quarter, is fixed for the kept draws), so that the
walkers decorrelate in a few steps instead of the stretch move's tens.

The log-probability is one ``jax.jit(jax.vmap(...))`` over walkers, called by
``emcee.EnsembleSampler(..., vectorize=True)``; float64 is required (x64 on). Chains can be
stored in HDF5 (emcee's ``HDFBackend``). Diagnostics: integrated autocorrelation time per
parameter (emcee's estimator, ``tol`` = chain length in units of tau), acceptance fraction,
effective sample size ``n_walkers * n_kept / tau``; a :class:`ChainTooShortWarning` is issued
when the chain is shorter than ``tol * tau`` (emcee's ``AutocorrError``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pydantic

from ppr.config import ConfigError, StrictModel, load_toml_model, validate_data
from ppr.geometry import quat_from_rotvec_host, quat_multiply_host

from ._observability import line_of_sight_of
from ._params import (
    DEFAULT_FREE,
    GAIN_RANGE,
    LOG_M_MIN,
    U_N_IMAG_MIN,
    Parametrisation,
    PhysicalParams,
    quat_from_rotvec,
    quat_multiply,
)
from ._refine import (
    PoissonNoise,
    RefineResult,
    _from_physical,
    _model_shape,
    _pure,
    _to_physical,
    check_observation,
    noise_log_likelihood,
)

__all__ = [
    "ChainTooShortWarning",
    "MCMCConfig",
    "MCMCResult",
    "ModeMixture",
    "sample_modes",
    "PriorConfig",
    "SamplerConfig",
    "load_mcmc_config",
    "make_log_prob",
    "sample_posterior",
]


class ChainTooShortWarning(UserWarning):
    """The chain is too short for a reliable autocorrelation time (emcee's AutocorrError)."""


class WalkersRaisedWarning(UserWarning):
    """``sampler.n_walkers`` was below twice the number of sampled parameters (what emcee's
    ensemble moves need); the chain ran with that many walkers instead."""


# --------------------------------------------------------------------------- config schema
class Prior1D(StrictModel):
    """A prior on one physical scalar (applied to every material slot of its group).

    ``kind``: ``uniform`` (``low``, ``high``), ``loguniform`` (``low > 0``, ``high``),
    ``normal`` (``mean``, ``sigma``), ``lognormal`` (``mean`` = median, ``sigma`` in ln units),
    ``halfnormal`` (``sigma``; support ``>= 0``).
    """

    kind: Literal["uniform", "loguniform", "normal", "lognormal", "halfnormal"]
    low: float | None = None
    high: float | None = None
    mean: float | None = None
    sigma: float | None = None

    @pydantic.model_validator(mode="after")
    def _check(self):
        k = self.kind
        takes = {
            "uniform": ("low", "high"),
            "loguniform": ("low", "high"),
            "normal": ("mean", "sigma"),
            "lognormal": ("mean", "sigma"),
            "halfnormal": ("sigma",),
        }[k]
        extra = [f for f in ("low", "high", "mean", "sigma") if f not in takes]
        given = [f"{f} = {getattr(self, f)}" for f in extra if getattr(self, f) is not None]
        if given:
            # a normal prior with low/high would silently be an untruncated normal
            raise ValueError(
                f"a {k} prior takes {' and '.join(takes)}, not {', '.join(given)} (there are "
                "no truncated priors)"
            )
        if k in ("uniform", "loguniform"):
            if self.low is None or self.high is None:
                raise ValueError(f"{k} prior needs low and high")
            if not self.low < self.high:
                raise ValueError(
                    f"{k} prior needs low < high, got low={self.low}, high={self.high}"
                )
            if k == "loguniform" and self.low <= 0:
                raise ValueError(f"loguniform prior needs low > 0, got low={self.low}")
        else:
            if self.sigma is None or not self.sigma > 0:
                raise ValueError(f"{k} prior needs sigma > 0, got sigma={self.sigma}")
            if k in ("normal", "lognormal") and self.mean is None:
                raise ValueError(f"{k} prior needs mean")
            if k == "lognormal" and not self.mean > 0:
                raise ValueError(f"lognormal prior needs mean (median) > 0, got {self.mean}")
        return self

    def support(self) -> tuple[float, float]:
        if self.kind in ("uniform", "loguniform"):
            return (self.low, self.high)
        if self.kind == "normal":
            return (-math.inf, math.inf)
        return (0.0, math.inf)

    def logpdf(self, x):
        """Log density (up to a constant) on physical ``x``; ``-inf`` outside the support."""
        k = self.kind
        if k == "uniform":
            ok = (x >= self.low) & (x <= self.high)
            return jnp.where(ok, 0.0, -jnp.inf)
        if k == "loguniform":
            ok = (x >= self.low) & (x <= self.high)
            return jnp.where(ok, -jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)
        if k == "normal":
            return -0.5 * ((x - self.mean) / self.sigma) ** 2
        if k == "halfnormal":
            return jnp.where(x >= 0, -0.5 * (x / self.sigma) ** 2, -jnp.inf)
        ok = x > 0
        lx = jnp.log(jnp.where(ok, x, 1.0))
        return jnp.where(ok, -lx - 0.5 * ((lx - math.log(self.mean)) / self.sigma) ** 2, -jnp.inf)


class AttitudePrior(StrictModel):
    """``uniform`` on SO(3) (Haar) or ``gaussian``: isotropic, ``sigma_deg`` about the refined
    optimum (use it to encode a classifier's grid resolution)."""

    kind: Literal["uniform", "gaussian"] = "uniform"
    sigma_deg: float | None = None

    @pydantic.model_validator(mode="after")
    def _check(self):
        if self.kind == "uniform" and self.sigma_deg is not None:
            raise ValueError(
                f"a uniform attitude prior takes no sigma_deg (got {self.sigma_deg}); "
                'kind = "gaussian" uses it'
            )
        if self.kind == "gaussian" and (self.sigma_deg is None or not self.sigma_deg > 0):
            raise ValueError(f"gaussian attitude prior needs sigma_deg > 0, got {self.sigma_deg}")
        return self


class PriorConfig(StrictModel):
    attitude: AttitudePrior = AttitudePrior()
    m: Prior1D = Prior1D(kind="loguniform", low=1e-3, high=1e6)
    n_re: Prior1D = Prior1D(kind="uniform", low=0.05, high=5.0)
    n_im: Prior1D = Prior1D(kind="uniform", low=0.0, high=15.0)
    corr_length: Prior1D = Prior1D(kind="loguniform", low=1e-8, high=1e-2)
    range_offset: Prior1D = Prior1D(kind="uniform", low=-1.0, high=1.0)
    # counts per (m^2 sr^-1) for SimulatorModel (PhysicalParams.gain): the single-photon
    # regime of ranging to small debris (~1-100) up to laboratory scales (~1e12), with margin
    gain: Prior1D = Prior1D(kind="loguniform", low=GAIN_RANGE[0], high=GAIN_RANGE[1])
    # film thickness (metres) of the coated slots (PhysicalParams.thickness_slots)
    thickness: Prior1D = Prior1D(kind="loguniform", low=1e-9, high=1e-3)


class SamplerConfig(StrictModel):
    n_walkers: int = pydantic.Field(32, ge=4)
    n_steps: int = pydantic.Field(2000, ge=10)
    burn_in: int = pydantic.Field(500, ge=0)
    thin: int = pydantic.Field(1, ge=1)
    init_scale: float = pydantic.Field(0.1, gt=0)
    autocorr_tol: float = pydantic.Field(50.0, gt=0)
    seed: int = 0
    progress: bool = False
    # emcee proposal: "stretch" (Goodman-Weare, emcee's default) or "de_snooker" (differential
    # evolution 0.8 + DE snooker 0.2, ter Braak & Vrugt 2008; bench/bench_mcmc_moves.py)
    moves: Literal["stretch", "de_snooker"] = "stretch"
    # the attitude moves in roll-separated coordinates exp(phi k) exp(t) (k the line of
    # sight; _RollSeparation), so the roll the data do not fix is one straight axis
    roll_separation: bool = True
    # with `materials` given to sample_posterior (inversion.invert gives its library), the
    # index is sampled over those materials (_LibraryIndex), and this fraction of the steps
    # redraws each walker's material uniformly (_MaterialMove); "continuous": the index
    # moves in its continuous prior box like the other parameters
    index: Literal["library", "continuous"] = "library"
    material_move: float = pydantic.Field(0.2, ge=0.0, lt=1.0)
    # fraction of the steps that redraw the roll about the line of sight uniformly within
    # the walker's half-circle (needs roll_separation; _RollMove): a roll the data do not fix
    # mixes in a few steps
    roll_move: float = pydantic.Field(0.1, ge=0.0, lt=1.0)
    # fraction of the steps, from the burn-in's second quarter on, that redraw each walker's
    # continuous coordinates from a multivariate Student-t fitted to the walkers' positions
    # over the quarter before (per library material; _IndependenceMove; the kept draws use
    # the fit to the burn-in's last quarter): a posterior close to that t mixes in a few
    # steps instead of the stretch move's tens. A fraction of emcee's moves' share (the steps
    # neither material nor roll moves take; default: 0.6 x 0.7 = 0.42 of the steps); needs
    # burn_in >= 20; 0 turns it off
    independence_move: float = pydantic.Field(0.6, ge=0.0, lt=1.0)
    # with the index sampled over a library and material_move > 0: the fraction of the
    # independence moves that also jump to a uniformly drawn material, into that material's
    # fitted component (_IndependenceMove.jumping). Measured on the held-out bench (62
    # chains; bench/results/inversion_heldout_jump.md against _nojump.md): 0.5 mixes the
    # materials better (the worst judged R-hat a material indicator in 11 chains instead of
    # 18, median worst R-hat 1.26 instead of 1.31) but fewer chains reach 1.1 (1 against 8)
    # and the line of sight and gain cover 0.90 at 68 %; off by default
    independence_jump: float = pydantic.Field(0.0, ge=0.0, le=1.0)
    # the sampler's gain coordinate: "total_counts" (log of the total expected signal,
    # _CountsLogProb), "reflectance" (log gain + log normal-incidence reflectance,
    # _ReflectanceShear) or "log_gain"; all have unit Jacobian (same posterior)
    gain_coordinate: Literal["total_counts", "reflectance", "log_gain"] = "total_counts"

    @pydantic.model_validator(mode="after")
    def _moves_sum(self):
        if self.material_move + self.roll_move >= 1.0:
            raise ValueError(
                f"material_move + roll_move must be < 1 (the rest are emcee's moves), got "
                f"{self.material_move} + {self.roll_move}"
            )
        return self

    @pydantic.model_validator(mode="after")
    def _check(self):
        if self.burn_in >= self.n_steps:
            raise ValueError(f"burn_in ({self.burn_in}) must be < n_steps ({self.n_steps})")
        return self


class MCMCConfig(StrictModel):
    """Schema of ``configs/inversion/*.toml``: ``[priors.*]`` tables and ``[sampler]``."""

    priors: PriorConfig = PriorConfig()
    sampler: SamplerConfig = SamplerConfig()


def load_mcmc_config(path: str | Path, overrides: dict | None = None) -> MCMCConfig:
    """Load and validate an MCMC config (errors name file, field and value: ConfigError)."""
    return load_toml_model(MCMCConfig, path, overrides)


def mcmc_config_from_dict(data: dict, source: str = "<dict>") -> MCMCConfig:
    return validate_data(MCMCConfig, data, source)


# --------------------------------------------------------------------------- log probability
def _log_prior_and_jacobian(param: Parametrisation, theta, priors: PriorConfig):
    """Sum of log priors on physical values plus log |d phys/d theta| (per free group)."""
    parts = param._split(theta)
    phys = param.to_physical(theta)
    lp = jnp.zeros((), theta.dtype)
    k = param.reference.n_materials
    if "attitude" in parts:
        w = parts["attitude"]
        a2 = jnp.sum(w * w)
        small = a2 < 1e-12
        a = jnp.sqrt(jnp.where(small, 1.0, a2))
        # Haar density in rotation-vector coordinates, 4 sin^2(a/2)/a^2 (-> 1 at a = 0)
        haar = jnp.where(small, 1.0 - a2 / 12.0, 4.0 * jnp.sin(0.5 * a) ** 2 / (a * a))
        lp = lp + jnp.log(haar)
        lp = lp + jnp.where(a2 <= math.pi**2, 0.0, -jnp.inf)
        if priors.attitude.kind == "gaussian":
            s = math.radians(priors.attitude.sigma_deg)
            lp = lp - 0.5 * a2 / s**2
    if "m" in parts:
        x = parts["m"]
        lp = lp + jnp.sum(priors.m.logpdf(phys.m)) + jnp.sum(jnp.where(x >= LOG_M_MIN, x, -jnp.inf))
    if "n" in parts:
        u = parts["n"][k:]
        lp = lp + jnp.sum(priors.n_re.logpdf(jnp.real(phys.n))) + jnp.sum(parts["n"][:k])
        # below the clamp the map is flat (zero Jacobian): no posterior mass there
        jac_u = jnp.where(u >= U_N_IMAG_MIN, jax.nn.log_sigmoid(u), -jnp.inf)
        lp = lp + jnp.sum(priors.n_im.logpdf(jnp.imag(phys.n))) + jnp.sum(jac_u)
    if "corr_length" in parts:
        lp = (
            lp
            + jnp.sum(priors.corr_length.logpdf(phys.corr_length))
            + jnp.sum(parts["corr_length"])
        )
    if "range_offset" in parts:
        lp = lp + priors.range_offset.logpdf(phys.range_offset)
    if "gain" in parts:
        lp = lp + priors.gain.logpdf(phys.gain) + parts["gain"][0]
    if "thickness" in parts and param.reference.thickness_slots:
        t = phys.thickness[jnp.asarray(param.reference.thickness_slots, jnp.int32)]
        # theta = log t: log |dt / dtheta| = theta
        lp = lp + jnp.sum(priors.thickness.logpdf(t)) + jnp.sum(parts["thickness"])
    return lp


def _log_likelihood(model, noise, param, aux, data, theta):
    phys = param.to_physical(theta)
    return noise_log_likelihood(noise, data, model.expected(phys, aux), phys)


class _LogProb(eqx.Module):
    model: object
    noise: object
    param: Parametrisation
    aux: object
    data: jax.Array
    priors: PriorConfig = eqx.field(static=True)

    def single(self, theta):
        lp = _log_prior_and_jacobian(self.param, theta, self.priors)
        ll = _log_likelihood(self.model, self.noise, self.param, self.aux, self.data, theta)
        out = jnp.where(jnp.isfinite(lp), lp + ll, -jnp.inf)
        return jnp.where(jnp.isnan(out), -jnp.inf, out)


class _CountsLogProb(_LogProb):
    """The log-posterior in coordinates whose gain entry is ``c = log_gain + h(rest)``,
    ``h = log sum_ij (E_ij(gain 1) - b_ij)`` (``E`` the expected counts, ``b`` the model's
    counts at gain 0 at the reference): ``c`` is the log of the total expected signal, which
    the data fix to ``1/sqrt(counts)`` whatever the index, roughness or attitude. ``h`` does
    not depend on the gain, so the map is a shear with unit Jacobian (the density needs no
    correction); in these coordinates the reflectance, roughness or tilt the gain would
    otherwise have to follow move freely. :meth:`pair` returns the log-posterior and the
    log gain (``theta``'s entry) of each point.

    ``affine``: the model is ``gain * E(gain 1) - (gain - 1) b`` (checked on the host), so
    one model evaluation serves both ``h`` and the likelihood; otherwise the likelihood
    evaluates the model again at the actual gain."""

    i_gain: int = eqx.field(static=True, default=-1)
    background: jax.Array | None = None
    affine: bool = eqx.field(static=True, default=False)

    def pair(self, s):
        th1 = s.at[self.i_gain].set(0.0)
        e1 = self.model.expected(self.param.to_physical(th1), self.aux) - self.background
        tot = jnp.sum(e1)
        ok = tot > 0
        lg = s[self.i_gain] - jnp.log(jnp.where(ok, tot, 1.0))
        theta = s.at[self.i_gain].set(lg)
        lp = _log_prior_and_jacobian(self.param, theta, self.priors)
        phys = self.param.to_physical(theta)
        if self.affine:
            expected = jnp.exp(lg) * e1 + self.background
        else:
            expected = self.model.expected(phys, self.aux)
        ll = noise_log_likelihood(self.noise, self.data, expected, phys)
        out = jnp.where(jnp.isfinite(lp) & ok, lp + ll, -jnp.inf)
        return jnp.where(jnp.isnan(out), -jnp.inf, out), lg


_JIT_CACHE: dict = {}


def _jitted_vmap(static, method: str = "single"):
    """One ``jax.jit(vmap(<log_prob>.<method>))`` per static structure (model sizes, priors,
    layout) and method (``"single"``: a walker's log-posterior; ``"pair"``: with its blob)."""
    try:
        key = (method, hash(static))
    except TypeError:
        key = (method, id(static))
    fn = _JIT_CACHE.get(key)
    if fn is None:

        def batched(dyn, x):
            lp = eqx.combine(dyn, static)
            return jax.vmap(getattr(lp, method))(x)

        # XLA's default (fusion) kernel emitters, unlike the refiner's programs
        # (inversion._xla): the walkers' batch runs 1.6x faster with them
        # (bench/results/xla_emitters.md)
        fn = _JIT_CACHE[key] = jax.jit(batched)
    return fn


def _make_counts_log_prob(
    model, data, param: Parametrisation, priors: PriorConfig, noise, probe, batch: int
):
    """``f(s (W, P)) -> (W, 2)``: log-posterior and log gain in the total-signal gain
    coordinate of :class:`_CountsLogProb` (the log gain is emcee's blob). ``probe``: a few
    ``theta`` rows at which the model is checked for being affine in the gain; ``batch``:
    smaller batches are padded to it."""
    aux = model.prepare(param.reference)
    shape = _model_shape(model, param.reference, aux)
    data_j = jnp.asarray(check_observation(data, shape))
    i = param.theta_labels.index("log_gain")

    def at_gain(theta, g):
        return np.asarray(model.expected(param.to_physical(jnp.asarray(theta).at[i].set(g)), aux))

    th0 = np.asarray(probe[0], np.float64)
    # counts at gain 0 (log gain -> -inf): from two gains, assuming the model is affine
    e_a, e_b = at_gain(th0, 0.0), at_gain(th0, math.log(2.0))
    b = 2.0 * e_a - e_b
    affine = True
    for th in probe:
        th = np.asarray(th, np.float64)
        e1, e3 = at_gain(th, 0.0), at_gain(th, math.log(3.0))
        want = 3.0 * e1 - 2.0 * b
        scale = np.max(np.abs(e3)) + 1e-300
        if not np.all(np.isfinite(e3)) or np.max(np.abs(e3 - want)) > 1e-9 * scale:
            affine = False
            break
    lp = _CountsLogProb(
        _pure(model),
        noise,
        param,
        aux,
        data_j,
        priors,
        i_gain=i,
        background=jnp.asarray(b),
        affine=affine,
    )
    dyn, static = eqx.partition(lp, eqx.is_array)
    batched = _jitted_vmap(static, "pair")

    def f(s):
        s = np.asarray(s, np.float64)
        rows = s.shape[0]
        if rows < batch:  # pad small batches to the walkers' (one compilation fewer)
            s = np.concatenate([s, np.broadcast_to(s[:1], (batch - rows, s.shape[1]))])
        lp_, lg = batched(dyn, jnp.asarray(s))
        out = np.stack([np.asarray(lp_, np.float64), np.asarray(lg, np.float64)], axis=-1)
        return out[:rows]

    f.i_gain = i  # type: ignore[attr-defined]
    f.affine = affine  # type: ignore[attr-defined]
    return f


def _require_x64() -> None:
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "MCMC needs float64: enable x64 before sampling "
            "(jax.config.update('jax_enable_x64', True)); the library never sets it"
        )


def make_log_prob(model, data, param: Parametrisation, priors: PriorConfig, noise=None, aux=None):
    """``f(thetas (W, P) numpy) -> (W,) numpy float64``: jitted, vmapped over walkers."""
    _require_x64()
    noise = PoissonNoise() if noise is None else noise
    aux = model.prepare(param.reference) if aux is None else aux
    shape = _model_shape(model, param.reference, aux)
    data_np = check_observation(data, shape)
    if hasattr(noise, "check_data"):
        noise.check_data(data_np)
    data = jnp.asarray(data_np)
    lp = _LogProb(_pure(model), noise, param, aux, data, priors)
    # Partition once and call a plain jax.jit: emcee calls this thousands of times, and
    # filter_jit's per-call pytree handling costs more than the toy-sized model itself.
    dyn, static = eqx.partition(lp, eqx.is_array)
    batched = _jitted_vmap(static)

    def f(thetas):
        return np.asarray(batched(dyn, jnp.asarray(thetas, jnp.float64)), np.float64)

    f.single = lp.single  # type: ignore[attr-defined]
    return f


def _check_prior_support(param: Parametrisation, theta0: np.ndarray, priors: PriorConfig):
    """Raise a ValueError naming every parameter whose prior has no support at ``theta0``."""
    phys = _to_physical(param, jnp.asarray(theta0))
    k = param.reference.n_materials
    problems = []

    def chk(name, prior: Prior1D, values):
        for i, v in enumerate(np.atleast_1d(np.asarray(values, float))):
            if not np.isfinite(float(prior.logpdf(jnp.asarray(v)))):
                lo, hi = prior.support()
                tag = f"{name}[{i}]" if np.ndim(values) else name
                problems.append(
                    f"{tag} = {v:.6g} outside the {prior.kind} prior's support [{lo:g}, {hi:g}]"
                )

    free = param.free
    if "m" in free:
        chk("m", priors.m, phys.m)
    if "n" in free:
        chk("n_re", priors.n_re, np.real(phys.n)[:k])
        chk("n_im", priors.n_im, np.imag(phys.n)[:k])
    if "corr_length" in free:
        chk("corr_length", priors.corr_length, phys.corr_length)
    if "range_offset" in free:
        chk("range_offset", priors.range_offset, phys.range_offset)
    if "gain" in free:
        chk("gain", priors.gain, phys.gain)
    if "thickness" in free and param.reference.thickness_slots:
        slots = list(param.reference.thickness_slots)
        chk("thickness", priors.thickness, np.asarray(phys.thickness)[slots])
    if problems:
        raise ValueError(
            "prior has no support at the starting point (the refined optimum): "
            + "; ".join(problems)
            + ". Widen the prior in the config or check the refinement."
        )


# --------------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True)
class MCMCResult:
    """Posterior samples and diagnostics.

    - `chain`: ``(n_steps, n_walkers, P)`` in solver coordinates ``theta`` (all steps);
      `log_prob`: ``(n_steps, n_walkers)``; `samples`: kept, flattened samples in *physical*
      units (:attr:`labels`), ``(n_kept * n_walkers / thin, P)``; `physical_chain`: every
      step in physical units, ``(n_steps, n_walkers, P)`` (`samples` is its rows after
      ``burn_in``, thinned, flattened step-major).
    - `acceptance_fraction` per walker; `tau` integrated autocorrelation time per parameter
      (steps, emcee's estimator); `ess` emcee's effective sample size per parameter
      (``n_walkers n_kept / tau``); `converged`: chain longer than
      ``autocorr_tol * max(tau)``; `path`: HDF5 file of the chain (or None).
    - :meth:`to_inference_data`, :meth:`write` (ArviZ netCDF in physical units, walkers as
      chains) and :meth:`diagnostics` (ArviZ's R-hat, bulk/tail ESS, MCSE): what reports
      should quote (:mod:`inversion._posterior`).
    """

    chain: np.ndarray
    log_prob: np.ndarray
    samples: np.ndarray
    labels: list[str]
    parametrisation: Parametrisation
    acceptance_fraction: np.ndarray
    tau: np.ndarray
    ess: np.ndarray
    converged: bool
    burn_in: int
    thin: int
    elapsed_s: float
    path: Path | None = None
    physical_chain: np.ndarray | None = None

    def to_inference_data(self, **kwargs):
        """:func:`inversion.to_inference_data` of this result (ArviZ, physical units)."""
        from ._posterior import to_inference_data

        return to_inference_data(self, **kwargs)

    def write(self, path: str | Path, **kwargs) -> Path:
        """Write the posterior as ArviZ netCDF (:func:`inversion.write_posterior`)."""
        from ._posterior import write_posterior

        return write_posterior(path, self, **kwargs)

    def diagnostics(self) -> dict[str, dict[str, float]]:
        """ArviZ's ``r_hat``, ``ess_bulk``, ``ess_tail``, ``mcse_mean``, ``mcse_sd`` per label
        (walkers as chains; :func:`inversion.posterior_diagnostics`)."""
        from ._posterior import posterior_diagnostics

        return posterior_diagnostics(self.to_inference_data(), self.labels)

    def interval(self, level: float = 0.68) -> np.ndarray:
        """Equal-tailed credible interval ``(P, 2)`` in physical units at ``level``."""
        if not 0 < level < 1:
            raise ValueError(f"interval: level must be in (0, 1), got {level}")
        q = 50 * (1 - level)
        return np.percentile(self.samples, [q, 100 - q], axis=0).T

    def median(self) -> np.ndarray:
        return np.median(self.samples, axis=0)

    def contains(self, truth_vector, level: float) -> np.ndarray:
        iv = self.interval(level)
        t = np.asarray(truth_vector)
        return (t >= iv[:, 0]) & (t <= iv[:, 1])

    def quaternions(self) -> np.ndarray:
        """Absolute attitude of every sample, ``(n, 4)`` scalar-first quaternions: the
        rotation-vector samples (deg, about the reference) composed with the reference."""
        par = self.parametrisation
        q_ref = np.asarray(par.reference.unit_quaternion(), np.float64)
        if "rot_x [deg]" not in self.labels:
            return np.broadcast_to(q_ref, (len(self.samples), 4)).copy()
        i = self.labels.index("rot_x [deg]")
        rv = jnp.asarray(np.radians(self.samples[:, i : i + 3]))
        dq = jax.vmap(quat_from_rotvec)(rv)
        return np.asarray(quat_multiply(dq, jnp.broadcast_to(jnp.asarray(q_ref), dq.shape)))

    def truth_vector(self, truth: PhysicalParams) -> np.ndarray:
        """``truth`` in the coordinates of :attr:`samples` (attitude relative to the reference)."""
        par = self.parametrisation
        return np.asarray(par.physical_vector(par.from_physical(truth)))

    def summary(self) -> str:
        iv68, iv95 = self.interval(0.68), self.interval(0.95)
        med = self.median()
        diag = self.diagnostics() if self.physical_chain is not None else None
        lines = [
            f"mcmc: walkers={self.chain.shape[1]} steps={self.chain.shape[0]} "
            f"burn_in={self.burn_in} "
            f"acceptance={np.mean(self.acceptance_fraction):.2f} max_tau={np.max(self.tau):.1f} "
            f"converged={self.converged} time={self.elapsed_s:.1f}s"
        ]
        if diag is not None:
            rhat = [d["r_hat"] for d in diag.values() if d["r_hat"] is not None]
            ess = [d["ess_bulk"] for d in diag.values() if d["ess_bulk"] is not None]
            lines[0] += (
                f" max_rhat={max(rhat, default=float('nan')):.3f} "
                f"min_ess_bulk={min(ess, default=float('nan')):.0f} (ArviZ, walkers as chains)"
            )
        for i, lab in enumerate(self.labels):
            tail = f"  tau {self.tau[i]:.1f}"
            if diag is not None and diag[lab]["r_hat"] is not None:
                tail = f"  r_hat {diag[lab]['r_hat']:.3f}  ess_bulk {diag[lab]['ess_bulk']:.0f}"
            lines.append(
                f"  {lab:>22s} median {med[i]: .6g}  68% [{iv68[i, 0]:.6g}, {iv68[i, 1]:.6g}]"
                f"  95% [{iv95[i, 0]:.6g}, {iv95[i, 1]:.6g}]{tail}"
            )
        return "\n".join(lines)

    def corner_plot(self, path: str | Path, truth: PhysicalParams | None = None):
        """Write a corner plot (``corner`` package) of the physical samples to ``path``."""
        import corner
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        truths = None if truth is None else self.truth_vector(truth)
        keep = np.ptp(self.samples, axis=0) > 0
        fig = corner.corner(
            self.samples[:, keep],
            labels=[lab for lab, k in zip(self.labels, keep, strict=True) if k],
            truths=None if truths is None else truths[keep],
            quantiles=[0.16, 0.5, 0.84],
            show_titles=True,
            title_fmt=".3g",
            # corner logs "Too few points to create valid contours" for every panel of a
            # discrete column (a library index sampled over its materials) and draws the
            # same panel either way: silenced, so the command's output stays readable
            quiet=True,
        )
        fig.savefig(path, dpi=80)
        plt.close(fig)
        return Path(path)


# --------------------------------------------------------------------------- driver
def sample_posterior(
    model,
    data,
    start: RefineResult | PhysicalParams,
    *,
    config: MCMCConfig | None = None,
    noise=None,
    free=None,
    path: str | Path | None = None,
    range_scale: float = 0.01,
    shear: bool = True,
    progress_desc: str | None = None,
    materials=None,
    material_fits=None,
) -> MCMCResult:
    """Sample the posterior with emcee, started in a small ball around ``start``.

    **Arguments:**

    - `model`, `data`, `noise`: as for :func:`inversion.refine`.
    - `start`: a :class:`RefineResult` (its optimum and covariance set the ball: walkers start
      at ``theta* + init_scale * N(0, cov_theta)``, the block of the free groups) or
      :class:`PhysicalParams` (ball of ``init_scale * 1e-2`` in every coordinate).
    - `config`: :class:`MCMCConfig` (priors and sampler settings), e.g. from
      :func:`load_mcmc_config`.
    - `free`: parameter groups (default: those of the RefineResult, else the default set).
    - `path`: HDF5 file to store the chain in (emcee ``HDFBackend``; overwritten), in the
      solver coordinates ``theta`` like :attr:`MCMCResult.chain`.
    - `shear`: when the index and the gain are both free, the walkers move in coordinates
      whose log gain is shifted by the log normal-incidence reflectance
      (:class:`_ReflectanceShear`: unit Jacobian, same posterior), which straightens the
      index-gain ridge.
    - `progress_desc`: label of the progress bar (``config.sampler.progress``), which
      starts after the log-probability has compiled.
    - `materials`: library indices (complex); with ``"n"`` free and ``sampler.index =
      "library"`` the index is sampled over them (uniform prior on the library, every
      material slot independently; the chain's ``n_re``/``n_im`` are library values).
    - `material_fits`: ``[slot][material]`` optima (:class:`PhysicalParams` or None) that
      the material jumps translate between (none: jumps at fixed other coordinates).

    Raises ``ValueError`` when the data do not match the model, contain NaN, or a prior has
    no support at the start. Warns :class:`ChainTooShortWarning` when the chain is too short
    for the autocorrelation estimate.
    """
    t0 = time.perf_counter()
    config = MCMCConfig() if config is None else config
    sc = config.sampler
    if isinstance(start, RefineResult):
        phys = start.params
        free = tuple(start.parametrisation.free) if free is None else tuple(free)
        cov = _sub_covariance(start, Parametrisation(phys, free, range_scale))
    elif isinstance(start, PhysicalParams):
        phys, cov = start, None
        free = DEFAULT_FREE if free is None else tuple(free)
    else:
        raise ValueError(
            "sample_posterior: start must be a RefineResult or PhysicalParams, "
            f"got {type(start).__name__}"
        )
    param = Parametrisation(phys, free, range_scale)
    theta0 = np.asarray(_from_physical(param, phys), np.float64)
    _check_prior_support(param, theta0, config.priors)
    if sc.n_walkers < 2 * theta0.size:
        # how many parameters are free is known only now (the index stage may free n); the
        # refinement before this point is not thrown away for a setting that is too small
        warnings.warn(
            f"sampler.n_walkers = {sc.n_walkers} is below twice the {theta0.size} sampled "
            f"parameters ({', '.join(param.labels)}) that emcee's ensemble moves need: "
            f"running {2 * theta0.size} walkers",
            WalkersRaisedWarning,
            stacklevel=2,
        )
        sc = sc.model_copy(update={"n_walkers": 2 * theta0.size})
    nw = sc.n_walkers
    ndim = theta0.size
    root = _ball_root(cov, ndim)
    gc = sc.gain_coordinate if shear and "gain" in param.free else "log_gain"
    counts = None
    if gc == "total_counts":
        _require_x64()
        # the sampler's program (log-posterior in the total-signal gain coordinate) also
        # gives the log-posterior at theta rows: one compiled program instead of two
        noise_c = PoissonNoise() if noise is None else noise
        near = np.random.default_rng(sc.seed + 2).normal(size=(3, ndim)) @ root.T
        counts = _make_counts_log_prob(
            model,
            data,
            param,
            config.priors,
            noise_c,
            np.vstack([theta0[None], theta0 + 0.1 * sc.init_scale * near]),
            nw,
        )
        if hasattr(noise_c, "check_data"):  # (the shape was checked above)
            noise_c.check_data(np.asarray(data, np.float64))

        def log_prob(theta):
            x = np.array(theta, np.float64, copy=True)
            lg = x[:, counts.i_gain].copy()
            x[:, counts.i_gain] = 0.0
            x[:, counts.i_gain] = lg - counts(x)[:, 1]  # c = log_gain + h
            return counts(x)[:, 0]

    else:
        log_prob = make_log_prob(model, data, param, config.priors, noise=noise)
    # every call has the walkers' batch shape (one compilation)
    lp0 = log_prob(np.tile(theta0, (nw, 1)))[0]
    if not np.isfinite(lp0):
        raise ValueError(
            f"log-posterior is not finite at the start (value {lp0}); the model or noise "
            f"variance may be invalid there"
        )
    rng = np.random.default_rng(sc.seed)
    p0 = theta0 + sc.init_scale * rng.normal(size=(nw, ndim)) @ root.T
    for _ in range(50):
        bad = ~np.isfinite(log_prob(p0))
        if not bad.any():
            break
        # pull walkers outside the support halfway back toward the optimum
        p0[bad] = theta0 + 0.5 * (p0[bad] - theta0)
    else:
        p0[bad] = theta0 + 1e-8 * rng.normal(size=(int(bad.sum()), ndim))

    backend = None
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        backend = emcee.backends.HDFBackend(str(path))
        backend.reset(sc.n_walkers, ndim)
    # sampler coordinates y: theta with the attitude roll-separated (rs), the gain as the
    # log total signal (counts) or reflectance-sheared (sh), the index as a library
    # coordinate (lib); every map is a bijection whose log Jacobian enters the target
    los = line_of_sight_of(model)
    rs = (
        _RollSeparation(param, (0.0, 0.0, 1.0) if los is None else los)
        if shear and sc.roll_separation and _RollSeparation.applies(param)
        else None
    )
    lib = (
        _LibraryIndex(param, materials, config.priors)
        if materials is not None and sc.index == "library" and _LibraryIndex.applies(param)
        else None
    )
    sh = (
        _ReflectanceShear(param)
        if gc == "reflectance" and lib is None and _ReflectanceShear.applies(param)
        else None
    )

    def target(y):
        if lib is not None:
            s, inside = lib.expand(y)
        else:
            s, inside = np.asarray(y, np.float64), True
        x = s if rs is None else rs.inverse(s)
        if counts is not None:
            out = counts(x)
            lp = out[:, 0]
        else:
            lp = log_prob(x if sh is None else sh.inverse(x))
        if rs is not None:
            lp = lp + rs.log_jacobian(s)
        if lib is not None:
            lp = np.where(inside, lp + lib.log_correction(x), -np.inf)
        if counts is not None:
            return np.stack([lp, out[:, 1]], axis=-1)
        return lp

    def to_theta(y, log_gain=None):
        x = y if lib is None else lib.expand(y)[0]
        x = x if rs is None else rs.inverse(x)
        if counts is not None:
            x = np.array(x, np.float64, copy=True)
            x[..., counts.i_gain] = log_gain
        return x if sh is None else sh.inverse(x)

    def forward(theta):
        """``theta`` rows -> sampler rows (before the library coordinate)."""
        x = theta if sh is None else sh.forward(theta)
        if counts is not None:
            x = np.array(x, np.float64, copy=True)
            lg = x[:, counts.i_gain].copy()
            x[:, counts.i_gain] = 0.0
            x[:, counts.i_gain] = lg - counts(x)[:, 1]  # c = log_gain + h
        return x if rs is None else rs.forward(x)

    x = forward(p0)
    shifts = None
    if lib is not None and material_fits is not None:
        # y*_{jk}: sampler coordinates of each slot's per-material optimum (the material
        # jumps translate by their differences; phi and z are not translated)
        k_slots, n_lib = lib.i_re.size, lib.n.size
        shifts = np.zeros((k_slots, n_lib, len(lib.keep)))
        base = forward(theta0[None])[0][lib.keep]
        for j in range(k_slots):
            for m in range(n_lib):
                ph = material_fits[j][m] if j < len(material_fits) else None
                th = None if ph is None else np.asarray(_from_physical(param, ph), np.float64)
                if th is None or not np.all(np.isfinite(th)):
                    shifts[j, m] = base
                    continue
                y = forward(th[None])[0][lib.keep]
                shifts[j, m] = np.where(np.isfinite(y), y, base)
        fixed = list(lib.z_columns()) + ([lib.position(rs.i[2])] if rs is not None else [])
        shifts[:, :, fixed] = 0.0
        base[fixed] = 0.0
    if lib is not None:
        # each walker starts in a material drawn with its likelihood at the walker's other
        # coordinates moved to that material's optimum (a starting point only: the chain's
        # material jumps do the sampling)
        rng_m = np.random.default_rng(sc.seed + 1)
        k_slots, n_lib = lib.i_re.size, lib.n.size
        which = np.zeros((nw, k_slots), int)
        y = lib.compress(x, which, rng_m)
        # the walkers move by the differences between the per-material optima, from the
        # library material nearest the start's index, not to the optima themselves: those may
        # lie in another mode than the one sampled here (the material stage runs at the first
        # fit, and a mirror image can be the best mode), far from this reference, where the
        # visibility held fixed at this reference is wrong (measured: walkers started 100 deg
        # away, at log-posterior -1.4e6 against -1.3e3 here, and climbed back for the whole
        # chain)
        n_ref = np.asarray(param.reference.n, np.complex128).reshape(-1)
        anchor = [
            int(np.argmin(np.abs(np.log(lib.n) - np.log(n_ref[min(j, n_ref.size - 1)]))))
            for j in range(k_slots)
        ]
        for j in range(k_slots):
            cands = []
            for m in range(n_lib):
                c = y.copy()
                if shifts is not None:
                    c += shifts[j, m] - shifts[j, anchor[j]]
                c[:, lib.z_columns()[j]] = m + 0.5
                cands.append(c)
            lk = np.stack([np.atleast_2d(target(c).T)[0] for c in cands], axis=1)
            lk = np.where(np.isfinite(lk), lk, -np.inf)
            best = np.max(lk, axis=1, keepdims=True)
            pk = np.where(np.isfinite(best), np.exp(lk - best), 1.0)
            pk /= pk.sum(axis=1, keepdims=True)
            pick = np.array([rng_m.choice(n_lib, p=row) for row in pk])
            y = np.stack([cands[m][i] for i, m in enumerate(pick)])
            y[:, lib.z_columns()[j]] = pick + rng_m.uniform(0.05, 0.95, size=nw)
        x = y
    p_start = x
    ndim_s = p_start.shape[1]
    if backend is not None and ndim_s != ndim:
        backend.reset(sc.n_walkers, ndim_s)
    moves = _moves(sc.moves)
    extra = []
    if lib is not None and sc.material_move > 0:
        extra.append((_MaterialMove(lib.z_columns(), lib.n.size, shifts), sc.material_move))
    if sc.roll_move > 0 and rs is not None:
        col = rs.i[2] if lib is None else lib.position(rs.i[2])
        extra.append((_RollMove(col), sc.roll_move))
    base = moves if isinstance(moves, list) else [(moves, 1.0)]  # emcee's own moves
    if extra:
        rest = 1.0 - sum(w for _, w in extra)
        moves = [(mv, w * rest) for mv, w in base] + extra
    adapt = sc.independence_move > 0 and sc.burn_in >= _MIN_ADAPT_STEPS
    if adapt and backend is None:
        backend = emcee.backends.Backend()  # the production run continues in it
    sampler = emcee.EnsembleSampler(
        sc.n_walkers, ndim_s, target, vectorize=True, backend=backend, moves=moves
    )
    sampler.random_state = np.random.RandomState(sc.seed).get_state()
    pkw = None if progress_desc is None else {"desc": progress_desc}
    if adapt:
        # the burn-in in quarters: the first with the moves above, each later one (and the
        # production run) with an independence move fitted to the quarter before it (each
        # proposal fixed while it runs: detailed balance holds; the walkers mix faster with
        # every refit, so the next fit is closer to the posterior)
        roll = None
        if rs is not None:  # each walker keeps its half-circle of roll, as in the roll move
            roll = rs.i[2] if lib is None else lib.position(rs.i[2])
        fixed = [] if lib is None else list(lib.z_columns())
        # the independence move takes its fraction of emcee's moves' share (the material and
        # roll moves keep theirs)
        rest = (1.0 - sum(w for _, w in extra)) * (1.0 - sc.independence_move)
        ind_w = (1.0 - sum(w for _, w in extra)) * sc.independence_move
        with_ind = [(m, w * rest) for m, w in base] + extra
        ends = [sc.burn_in * k // _ADAPT_STAGES for k in range(1, _ADAPT_STAGES + 1)]
        sampler.run_mcmc(p_start, ends[0], progress=sc.progress, progress_kwargs=pkw)
        for k in range(1, _ADAPT_STAGES + 1):
            start = ends[k - 2] if k >= 2 else ends[0] // 2
            steps = (ends[k] - ends[k - 1]) if k < _ADAPT_STAGES else sc.n_steps - sc.burn_in
            ind = _IndependenceMove.fit(sampler.get_chain()[start:], fixed=fixed, roll=roll)
            mv = moves
            fj = sc.independence_jump if lib is not None and sc.material_move > 0 else 0.0
            if ind is not None:
                # a fraction jumps between materials too (into each one's fitted bulk)
                mv = with_ind + [(ind, (1.0 - fj) * ind_w)]
                if fj > 0:
                    mv.append((ind.jumping(lib.n.size), fj * ind_w))
            sampler = emcee.EnsembleSampler(
                sc.n_walkers, ndim_s, target, vectorize=True, backend=backend, moves=mv
            )
            # the walkers' independence was checked at the start; a stage's start is the last
            # one's end, which the check may refuse for an ensemble contracted in a stiff
            # direction, where one run would carry on
            sampler.run_mcmc(
                None,
                steps,
                progress=sc.progress,
                progress_kwargs=pkw,
                skip_initial_state_check=True,
            )
    else:
        sampler.run_mcmc(p_start, sc.n_steps, progress=sc.progress, progress_kwargs=pkw)

    chain = sampler.get_chain()
    if counts is not None or sh is not None or rs is not None or lib is not None:
        chain = to_theta(chain, None if counts is None else sampler.get_blobs())
        if path is not None:  # the file holds theta too, like the returned chain
            import h5py

            with h5py.File(path, "r+") as f:
                if ndim_s != ndim:
                    del f[backend.name]["chain"]
                    f[backend.name].create_dataset("chain", data=chain)
                else:
                    f[backend.name]["chain"][...] = chain
    lps = sampler.get_log_prob()
    kept = chain[sc.burn_in :: sc.thin]
    tau, converged = _autocorr(kept, sc.autocorr_tol)
    n_kept = kept.shape[0]
    ess = n_kept * sc.thin * sc.n_walkers / np.maximum(tau, 1.0)
    phys_chain = np.asarray(
        _physical_vectors(param, jnp.asarray(chain.reshape(-1, ndim))), np.float64
    ).reshape(chain.shape)
    samples = phys_chain[sc.burn_in :: sc.thin].reshape(-1, ndim)
    return MCMCResult(
        chain=chain,
        log_prob=lps,
        samples=samples,
        labels=param.labels,
        parametrisation=param,
        acceptance_fraction=np.asarray(sampler.acceptance_fraction),
        tau=tau,
        ess=ess,
        converged=converged,
        burn_in=sc.burn_in,
        thin=sc.thin,
        elapsed_s=time.perf_counter() - t0,
        path=path,
        physical_chain=phys_chain,
    )


# --------------------------------------------------------------------------- modes
@dataclasses.dataclass(frozen=True)
class ModeMixture:
    """A posterior with separated modes, one chain per mode (:func:`sample_modes`).

    - `modes`: one :class:`MCMCResult` per mode (samples in that mode's coordinates: the
      attitude as a rotation vector about the mode's own optimum).
    - `weights`: posterior probability of each mode, ``exp(-cost_k / 2)`` normalised (equal
      prior mass and posterior volume: exact for the two modes of a parity symmetry,
      :func:`inversion.mirror_check`); `costs` the modes' refined deviances.
    """

    modes: tuple[MCMCResult, ...]
    weights: np.ndarray
    costs: np.ndarray

    def draw(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` draws from the mixture: (mode index, row of that mode's ``samples``)."""
        sizes = np.array([len(m.samples) for m in self.modes], dtype=np.int64)
        empty = [
            j for j, (z, w) in enumerate(zip(sizes, self.weights, strict=True)) if z == 0 and w > 0
        ]
        if empty:
            raise ValueError(
                f"ModeMixture.draw: mode {empty[0]} has weight {self.weights[empty[0]]:.3g} but "
                "no samples (a chain shorter than its burn-in?)"
            )
        rng = np.random.default_rng(seed)
        k = rng.choice(len(self.modes), size=n, p=self.weights)
        rows = np.minimum((rng.random(n) * sizes[k]).astype(np.int64), sizes[k] - 1)
        return k, rows

    def quaternions(self, n: int = 4000, seed: int = 0) -> np.ndarray:
        """``(n, 4)`` attitude draws from the mixture (absolute, scalar-first quaternions)."""
        k, rows = self.draw(n, seed)
        out = np.empty((n, 4))
        for j, mode in enumerate(self.modes):
            sel = k == j
            if np.any(sel):
                out[sel] = mode.quaternions()[rows[sel]]
        return out

    def interval(self, label: str, level: float = 0.68, n: int = 20000, seed: int = 0):
        """Equal-tailed interval of a parameter that is not an attitude component (those are
        relative to each mode's own optimum: use :meth:`quaternions`), over the mixture."""
        if label.startswith("rot_"):
            raise ValueError(
                f"interval: {label!r} is relative to each mode's optimum; use quaternions()"
            )
        i = self.modes[0].labels.index(label)
        k, rows = self.draw(n, seed)
        x = np.empty(n)
        for j, mode in enumerate(self.modes):
            sel = k == j
            x[sel] = mode.samples[rows[sel], i]
        q = 50 * (1 - level)
        return np.percentile(x, [q, 100 - q])

    def summary(self) -> str:
        lines = [f"mode mixture: {len(self.modes)} modes"]
        for j, (m, w, c) in enumerate(zip(self.modes, self.weights, self.costs, strict=True)):
            lines.append(
                f"  mode {j}: probability {w:.3g}, deviance {c:.6g}, "
                f"acceptance {np.mean(m.acceptance_fraction):.2f}, max tau {np.max(m.tau):.1f}"
            )
        return "\n".join(lines)


def sample_modes(
    model,
    data,
    fits: Sequence[RefineResult],
    *,
    config: MCMCConfig | None = None,
    noise=None,
    **kwargs,
) -> ModeMixture:
    """Sample a posterior with several separated modes: one :func:`sample_posterior` chain
    per refined optimum in `fits` (e.g. ``[chk.fit, chk.mirror]`` of an ambiguous
    :func:`inversion.mirror_check`), weighted by ``exp(-cost / 2)``.

    An ensemble sampler started in one mode stays there: its walkers cannot cross the
    degrees-wide low-probability gap between the two attitudes of a parity ambiguity. Each mode
    is sampled locally instead, and the modes are combined with their posterior
    probabilities, which for the two mirror images (equal volumes) is the likelihood ratio.
    `kwargs` go to :func:`sample_posterior` (``free``, ``range_scale``, ``shear``; ``path``
    gets the mode index appended before its suffix).
    """
    if len(fits) < 1:
        raise ValueError("sample_modes: fits is empty")
    for j, f in enumerate(fits):
        if not isinstance(f, RefineResult):
            raise ValueError(f"sample_modes: fits[{j}] is {type(f).__name__}, not a RefineResult")
        if not np.isfinite(f.cost):
            raise ValueError(f"sample_modes: fits[{j}] has a non-finite cost ({f.cost})")
    path = kwargs.pop("path", None)
    modes = []
    for j, f in enumerate(fits):
        pj = None if path is None else Path(path).with_stem(f"{Path(path).stem}_mode{j}")
        modes.append(
            sample_posterior(model, data, f, config=config, noise=noise, path=pj, **kwargs)
        )
    costs = np.array([f.cost for f in fits], float)
    logw = -0.5 * (costs - costs.min())
    w = np.exp(logw)
    return ModeMixture(modes=tuple(modes), weights=w / w.sum(), costs=costs)


def _moves(name: str):
    """emcee proposal moves of ``SamplerConfig.moves``."""
    if name == "stretch":
        return emcee.moves.StretchMove()
    if name == "de_snooker":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    raise ValueError(f"sampler.moves = {name!r}: use 'stretch' or 'de_snooker'")


class _ReflectanceShear:
    """Sampler coordinates ``theta'``: ``theta`` with the log gain shifted by the log
    normal-incidence reflectance of the index, ``log_gain' = log_gain + log(mean_k R0(n_k) +
    1e-4)``, ``R0 = |(n - 1)/(n + 1)|^2``. At normal incidence the data fix mostly
    reflectance x gain, so in ``theta`` the posterior is a curved ridge in (n', n'', gain)
    that the stretch move crosses slowly; in ``theta'`` the ridge is nearly parallel to the
    index axes. The shift depends only on the index coordinates, so the map is a bijection
    with unit Jacobian: the log-posterior needs no correction."""

    def __init__(self, param: Parametrisation):
        labels = param.theta_labels
        self.k = param.reference.n_materials
        self.i_gain = labels.index("log_gain")
        self.i_nre = [labels.index(f"log_n_re[{i}]") for i in range(self.k)]
        self.i_nim = [labels.index(f"softplus_inv_n_im[{i}]") for i in range(self.k)]

    @staticmethod
    def applies(param: Parametrisation) -> bool:
        return "n" in param.free and "gain" in param.free

    def shift(self, theta: np.ndarray) -> np.ndarray | float:
        n_re = np.exp(theta[..., self.i_nre])
        n_im = np.logaddexp(np.maximum(theta[..., self.i_nim], U_N_IMAG_MIN), 0.0)
        r0 = ((n_re - 1) ** 2 + n_im**2) / ((n_re + 1) ** 2 + n_im**2)
        return np.log(np.mean(r0, axis=-1) + 1e-4)

    def forward(self, theta: np.ndarray) -> np.ndarray:
        out = np.array(theta, np.float64, copy=True)
        out[..., self.i_gain] += self.shift(theta)
        return out

    def inverse(self, theta_s: np.ndarray) -> np.ndarray:
        out = np.array(theta_s, np.float64, copy=True)
        out[..., self.i_gain] -= self.shift(theta_s)  # the index entries are unchanged
        return out


class _LibraryIndex:
    """The index sampled over a library of materials: per material slot ``j`` one sampler
    coordinate ``z_j`` in ``[0, K)`` replaces ``(log n'_j, softplus^-1 n''_j)``, and the slot
    holds library index ``floor(z_j)``. The density in ``z`` is piecewise constant, so
    sampling it is exactly sampling the discrete posterior over the library materials with a
    uniform prior on them (each slot independently); the continuous prior's terms on the
    index (``priors.n_re``, ``priors.n_im`` and the Jacobian of ``log``/``softplus``, which
    the log-posterior in ``theta`` adds) are removed by :meth:`log_correction`; a library
    index outside the continuous prior's support gets no mass.

    Why: a glossy target's data leave a curved ridge of indices (the gain absorbing the
    reflectance) across the whole prior box; its posterior mass then follows the prior
    volume along the ridge, not the materials targets are made of, and the stretch move
    cannot cross it in a few hundred steps. With a library, :class:`_MaterialMove` jumps
    between materials (accepted when the data cannot tell them apart) and the posterior of
    the gain, roughness and attitude is the evidence-weighted mixture over materials."""

    def __init__(self, param: Parametrisation, materials, priors: PriorConfig):
        labels = param.theta_labels
        k = param.reference.n_materials
        self.size = len(labels)
        self.i_re = np.array([labels.index(f"log_n_re[{i}]") for i in range(k)])
        self.i_im = np.array([labels.index(f"softplus_inv_n_im[{i}]") for i in range(k)])
        self.keep = np.array([i for i in range(self.size) if i not in set(self.i_im)])
        n = np.asarray(list(materials), np.complex128)
        if n.ndim != 1 or n.size < 1 or not np.all(np.isfinite(n)) or np.any(n.real <= 0):
            raise ValueError(f"materials: need indices with n' > 0, got {list(materials)}")
        self.n = n
        self.x = np.log(n.real)
        self.u = np.maximum(np.log(np.expm1(np.maximum(n.imag, 1e-9))), U_N_IMAG_MIN)
        self.p_re, self.p_im = priors.n_re, priors.n_im

    @staticmethod
    def applies(param: Parametrisation) -> bool:
        return "n" in param.free

    def z_columns(self) -> np.ndarray:
        """Sampler columns of the ``z_j``."""
        return np.searchsorted(self.keep, self.i_re)

    def position(self, theta_col: int) -> int:
        """Sampler column of ``theta`` column ``theta_col`` (not an index column)."""
        return int(np.searchsorted(self.keep, theta_col))

    def expand(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sampler rows -> ``theta``-sized rows with the library index; and whether every
        ``z_j`` is inside ``[0, K)``."""
        y = np.asarray(y, np.float64)
        out = np.zeros(y.shape[:-1] + (self.size,))
        out[..., self.keep] = y
        z = out[..., self.i_re]
        inside = np.all((z >= 0) & (z < self.n.size), axis=-1)
        kk = np.clip(np.floor(np.where(np.isfinite(z), z, 0.0)), 0, self.n.size - 1).astype(int)
        out[..., self.i_re] = self.x[kk]
        out[..., self.i_im] = self.u[kk]
        return out, inside

    def compress(self, theta: np.ndarray, which: np.ndarray, rng) -> np.ndarray:
        """``theta`` rows -> sampler rows with material ``which`` ``(rows, k)`` (``z``
        uniform within the material's unit interval)."""
        y = np.array(np.asarray(theta, np.float64)[..., self.keep], copy=True)
        y[..., self.z_columns()] = which + rng.uniform(0.05, 0.95, size=which.shape)
        return y

    def log_correction(self, theta: np.ndarray) -> np.ndarray:
        """Minus the continuous prior's index terms of the log-posterior in ``theta`` (0 where
        those are not finite: the log-posterior is then ``-inf`` already)."""
        x, u = theta[..., self.i_re], theta[..., self.i_im]
        n_re, n_im = np.exp(x), np.logaddexp(u, 0.0)
        lp = np.asarray(self.p_re.logpdf(n_re)) + x
        lp = lp + np.asarray(self.p_im.logpdf(n_im)) - np.logaddexp(0.0, -u)
        lp = np.sum(lp, axis=-1)
        return np.where(np.isfinite(lp), -lp, 0.0)


class _MaterialMove(emcee.moves.MHMove):
    """Jump between library materials (:class:`_LibraryIndex`): every walker picks one slot
    ``j`` and a material ``k'`` uniformly, sets ``z_j`` to ``k'`` plus its fractional part,
    and translates its other coordinates by ``y*_{j k'} - y*_{j k}`` (``y*_{jk}``: the
    optimum with material ``k`` in slot ``j``, from ``shifts``; none: no translation). The
    reverse jump is proposed with the same probability and the map is a translation (unit
    Jacobian), so the Hastings factor is 0 and the move is exact for any target; the
    translation carries a walker from one material's optimum to the other's (the gain,
    roughness and attitude that material needs), so the jump is accepted about as often as
    the two materials' evidences allow."""

    def __init__(self, columns, n_materials: int, shifts: np.ndarray | None = None):
        self.columns = np.asarray(columns, int)
        self.k = int(n_materials)
        self.shifts = shifts
        super().__init__(self._propose)

    def _propose(self, coords: np.ndarray, random):
        w = coords.shape[0]
        rows = np.arange(w)
        new = np.array(coords, np.float64, copy=True)
        j = random.randint(self.columns.size, size=w)
        col = self.columns[j]
        z = coords[rows, col]
        k_old = np.clip(np.floor(z), 0, self.k - 1).astype(int)
        k_new = random.randint(self.k, size=w)
        if self.shifts is not None:
            new += self.shifts[j, k_new] - self.shifts[j, k_old]
        new[rows, col] = k_new + (z - np.floor(z))
        return new, np.zeros(w)


# burn-in steps below which no independence proposal is fitted (too few, too correlated),
# and the burn-in's stages, each with a proposal fitted to the stage before
_MIN_ADAPT_STEPS = 20
_ADAPT_STAGES = 4


class _IndependenceMove(emcee.moves.MHMove):
    r"""Independence Metropolis move from a multivariate Student-t fitted to the burn-in.

    Each walker redraws its continuous sampler coordinates ``A`` (all but the library
    coordinates ``z``, which :class:`_MaterialMove` samples) from ``t_nu(mu_k, c^2 Sigma_k)``,
    ``k`` the walker's library material (``floor(z)``; one component without a library); ``mu_k,
    Sigma_k`` are the mean and covariance of the walkers' positions over the preceding burn-in
    stage (:func:`sample_posterior` refits it at each quarter of the burn-in and keeps the last
    fit for the kept draws) among the samples with material ``k`` (all samples when there are
    fewer than ``4 dim + 10``), ``c = 1.25``, ``nu = 5``. The proposal does not depend on the
    current ``y_A``, so the Hastings factor is ``log q_k(y_A) - log q_k(y'_A)`` (the
    normalization, the same for both, cancels) and the move is exact for any target. With
    ``roll`` (the column of the roll ``phi`` about the line of sight) the move keeps each walker
    in its half-circle, as :class:`_RollMove` does (the half turn of monostatic data is a mode
    of its own when the roll is observable): the fit and ``q`` see the roll folded into
    ``[-pi/2, pi/2]`` by the half turn (:func:`_fold_roll`), a draw with ``|phi'| >= pi/2`` is
    rejected and the proposal is unfolded into the walker's half; within either half the move is
    the same exact independence sampler.

    Where the posterior is close to the fitted t (the Laplace picture with heavier tails),
    a proposal is accepted with probability of order one wherever the walker is: the chain
    forgets its state in a few steps, against tens for the stretch move in 8-10 dimensions,
    whose ensemble drifts collectively (which inflates R-hat across walkers). emcee's moves
    keep running alongside for what the t does not describe (measured on a glossy cubesat
    at SNR 1000: 30-37 % of these proposals accepted, the worst R-hat 1.56-1.64 -> 1.16-1.24
    at 300 steps; ``bench/results/mcmc_flat.md``).
    """

    def __init__(self, cols_a, z_cols, comps: dict, pooled, nu: float, roll=None):
        self.a = np.asarray(cols_a, int)
        self.z = np.asarray(z_cols, int)
        self.comps = comps
        self.pooled = pooled
        self.nu = float(nu)
        self.roll = roll
        self.n_materials: int | None = None  # set by jumping()
        super().__init__(self._propose)

    @classmethod
    def fit(cls, chain, fixed=(), roll=None, nu: float = 5.0, scale: float = 1.25):
        """From burn-in samples ``(steps, walkers, dim)``; None when no component can be
        fitted (too few samples or a singular covariance)."""
        x = np.array(chain, np.float64).reshape(-1, chain.shape[-1])
        x = x[np.all(np.isfinite(x), axis=1)]
        if roll is not None:
            x[:, roll] = _fold_roll(x[:, roll])[0]
        z = np.asarray(list(fixed), int)
        a = np.array([i for i in range(x.shape[1]) if i not in set(z.tolist())], int)
        if a.size == 0:
            return None

        def component(rows):
            if rows.shape[0] < 4 * a.size + 10:
                return None
            y = rows[:, a]
            cov = np.atleast_2d(np.cov(y, rowvar=False)) * scale**2
            try:
                chol = np.linalg.cholesky(0.5 * (cov + cov.T))
            except np.linalg.LinAlgError:
                return None
            return y.mean(axis=0), chol

        pooled = component(x)
        if pooled is None:
            return None
        comps = {}
        if z.size:
            keys = np.floor(x[:, z]).astype(int)
            for key in {tuple(k) for k in keys.tolist()}:
                comp = component(x[np.all(keys == np.asarray(key), axis=1)])
                if comp is not None:
                    comps[key] = comp
        return cls(a, z, comps, pooled, nu, roll)

    def _log_q(self, y, mu, chol):
        """Log density of the fitted t at rows ``y``, normalized up to a constant shared by
        every component (same ``nu`` and dimension): ``- log det chol`` included, so that
        densities of different materials' components compare (the jumping variant)."""
        u = np.linalg.solve(chol, (y - mu).T).T
        kern = -0.5 * (self.nu + self.a.size) * np.log1p(np.sum(u * u, axis=-1) / self.nu)
        return kern - np.sum(np.log(np.diag(chol)))

    def jumping(self, n_materials: int) -> _IndependenceMove:
        """The same proposal with a material jump: each walker also draws one library
        slot ``j`` and a material ``k'`` uniformly (``z_j -> k' + frac(z_j)``, like
        :class:`_MaterialMove`) and its continuous coordinates from ``k'``'s component. The
        reverse jump has the same probability, so the Hastings factor is ``log q_k(y_A) -
        log q_k'(y'_A)`` with the components' normalizations: exact. Unlike the translation
        of :class:`_MaterialMove`, the walker lands in the bulk that the burn-in found for
        the new material (measured on the held-out bench: the dielectric's indicator was
        the worst R-hat of 10 of 60 chains with translated jumps only)."""
        out = _IndependenceMove(self.a, self.z, self.comps, self.pooled, self.nu, self.roll)
        out.n_materials = int(n_materials)
        return out

    def _propose(self, coords: np.ndarray, random):
        w = coords.shape[0]
        keys = np.floor(coords[:, self.z]).astype(int) if self.z.size else np.zeros((w, 0), int)
        coords = np.array(coords, np.float64, copy=True)
        if self.roll is not None:
            coords[:, self.roll], half = _fold_roll(coords[:, self.roll])
        new = coords.copy()
        new_keys = keys.copy()
        if self.n_materials is not None and self.z.size:
            rows = np.arange(w)
            j = random.randint(self.z.size, size=w)
            k_new = random.randint(self.n_materials, size=w)
            z = coords[rows, self.z[j]]
            new[rows, self.z[j]] = k_new + (z - np.floor(z))
            new_keys[rows, j] = k_new
        g = random.standard_normal((w, self.a.size))
        r = np.sqrt(self.nu / random.chisquare(self.nu, size=w))
        factors = np.zeros(w)
        for key in {tuple(k) for k in keys.tolist()}:
            rows = np.flatnonzero(np.all(keys == np.asarray(key, int), axis=1))
            mu, chol = self.comps.get(key, self.pooled)
            factors[rows] += self._log_q(coords[np.ix_(rows, self.a)], mu, chol)
        for key in {tuple(k) for k in new_keys.tolist()}:
            rows = np.flatnonzero(np.all(new_keys == np.asarray(key, int), axis=1))
            mu, chol = self.comps.get(key, self.pooled)
            y_new = mu + r[rows, None] * (g[rows] @ chol.T)
            new[np.ix_(rows, self.a)] = y_new
            factors[rows] -= self._log_q(y_new, mu, chol)
        if self.roll is not None:
            u = new[:, self.roll]
            factors = np.where(np.abs(u) < 0.5 * math.pi, factors, -np.inf)
            new[:, self.roll] = _unfold_roll(u, half)
        return new, factors


def _fold_roll(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll ``phi`` in ``[-pi, pi]`` -> its image in ``[-pi/2, pi/2]`` under the half turn
    about the line of sight, and whether it was in the outer half (``|phi| >= pi/2``)."""
    phi = np.asarray(phi, np.float64)
    half = np.abs(phi) >= 0.5 * math.pi
    return np.where(half, phi - np.copysign(math.pi, phi), phi), half


def _unfold_roll(u: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_fold_roll` for ``|u| < pi/2``: ``u`` carried into the outer half
    by the half turn where ``half``."""
    u = np.asarray(u, np.float64)
    return np.where(half, np.where(u <= 0.0, u + math.pi, u - math.pi), u)


class _RollMove(emcee.moves.MHMove):
    """Independence move of the roll ``phi`` about the line of sight (the roll-separated
    coordinate of :class:`_RollSeparation`) within the walker's half-circle: a walker with
    ``|phi| < pi/2`` proposes ``phi' ~ U(-pi/2, pi/2)``, one with ``|phi| >= pi/2`` the
    half turn's image of such a draw (:func:`_unfold_roll`), and keeps its other
    coordinates. Within either half the proposal density is constant, so the factor is 0 and
    the move is exact for any target; for the uniform (Haar) attitude prior, whose density
    in ``(t, phi)`` does not depend on ``phi`` (left invariance), the acceptance is the
    likelihood ratio: ~1 for a roll the data do not fix. No walker is carried across the
    half-circles: the half turn about the line of sight is an exact mode of monostatic data
    that :func:`inversion.invert` samples as a mode of its own, and a walker carried there
    alone could not come back (the stretch move needs company). A roll the data do not fix
    at all spreads over both halves through the stretch move, and walkers in the outer half
    are redrawn there too (measured: on a glossy cubesat with a free roll half the walkers
    sat in the outer half, where the earlier rule, proposals only from the inner half, never
    moved them)."""

    def __init__(self, i_phi: int):
        self.i_phi = int(i_phi)
        super().__init__(self._propose)

    def _propose(self, coords: np.ndarray, random):
        w = coords.shape[0]
        new = np.array(coords, np.float64, copy=True)
        half = _fold_roll(coords[:, self.i_phi])[1]
        u = random.uniform(-0.5 * math.pi, 0.5 * math.pi, size=w)
        new[:, self.i_phi] = _unfold_roll(u, half)
        return new, np.zeros(w)


def _rotvec_host(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (rad, angle in [0, pi]) of quaternions ``(..., 4)``, host."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    sv = np.linalg.norm(v, axis=-1)
    small = sv < 1e-12
    angle = 2.0 * np.arctan2(sv, q[..., 0])
    factor = np.where(small, 2.0 / q[..., 0], angle / np.where(small, 1.0, sv))
    return factor[..., None] * v


class _RollSeparation:
    """Sampler coordinates in which the roll about the line of sight ``k`` is one axis: the
    attitude's rotation vector ``w`` (``exp(w) q_ref``, sensor frame) replaced by
    ``(t_1, t_2, phi)`` with ``exp(w) = exp(phi k) exp(t_1 e_1 + t_2 e_2)`` (``e_1, e_2``
    perpendicular to ``k``; the swing-twist decomposition). A monostatic measurement sees the
    line of sight through the tilt ``t`` only plus, through the polarization, the roll
    ``phi``; in ``w`` a roll the data do not fix turns and rescales the thin tilt
    cross-section as it goes (``exp(w)`` mixes them), a twisted tube the stretch move cannot
    cross; in ``(t, phi)`` the tube is straight and axis-aligned. ``phi`` is kept in
    ``(-pi, pi]`` and ``|t| < pi`` (each rotation once); the density is corrected by
    ``log |det dw / d(t, phi)|`` (:meth:`log_jacobian`)."""

    def __init__(self, param: Parametrisation, los=(0.0, 0.0, 1.0)):
        labels = param.theta_labels
        self.i = [labels.index(x) for x in ("rotvec_x", "rotvec_y", "rotvec_z")]
        k = np.asarray(los, np.float64)
        k = k / np.linalg.norm(k)
        a = np.eye(3)[int(np.argmin(np.abs(k)))]
        e1 = np.cross(k, a)
        e1 /= np.linalg.norm(e1)
        self.k, self.e1, self.e2 = k, e1, np.cross(k, e1)

    @staticmethod
    def applies(param: Parametrisation) -> bool:
        return "attitude" in param.free

    def _w(self, s: np.ndarray) -> np.ndarray:
        t = s[..., 0:1] * self.e1 + s[..., 1:2] * self.e2
        q = quat_multiply_host(
            quat_from_rotvec_host(s[..., 2:3] * self.k), quat_from_rotvec_host(t)
        )
        return _rotvec_host(q)

    def _s(self, w: np.ndarray) -> np.ndarray:
        q = quat_from_rotvec_host(w)
        q = np.where(q[..., :1] < 0, -q, q)
        vk = q[..., 1:] @ self.k
        phi = 2.0 * np.arctan2(vk, q[..., 0])  # in (-pi, pi] for q_w >= 0
        half = 0.5 * phi
        twist_conj = np.concatenate(
            [np.cos(half)[..., None], -np.sin(half)[..., None] * self.k], axis=-1
        )
        t = _rotvec_host(quat_multiply_host(twist_conj, q))
        return np.stack([t @ self.e1, t @ self.e2, phi], axis=-1)

    def forward(self, theta: np.ndarray) -> np.ndarray:
        out = np.array(theta, np.float64, copy=True)
        out[..., self.i] = self._s(out[..., self.i])
        return out

    def inverse(self, theta_s: np.ndarray) -> np.ndarray:
        out = np.array(theta_s, np.float64, copy=True)
        out[..., self.i] = self._w(out[..., self.i])
        return out

    def log_jacobian(self, theta_s: np.ndarray) -> np.ndarray:
        """``log |det dw / d(t, phi)|`` per row (central differences); ``-inf`` outside
        ``|phi| <= pi``, ``|t| < pi``."""
        s = np.asarray(theta_s, np.float64)[..., self.i]
        h = 1e-6
        cols = []
        for j in range(3):
            d = np.zeros(3)
            d[j] = h
            cols.append((self._w(s + d) - self._w(s - d)) / (2 * h))
        jac = np.stack(cols, axis=-1)
        with np.errstate(divide="ignore"):
            out = np.log(np.abs(np.linalg.det(jac)))
        inside = (np.abs(s[..., 2]) <= math.pi) & (np.hypot(s[..., 0], s[..., 1]) < math.pi)
        return np.where(inside & np.isfinite(out), out, -np.inf)


@eqx.filter_jit
def _physical_vectors(param, thetas):
    return jax.vmap(param.physical_vector)(thetas)


# prior-scale spread (theta units: rad of rotation, log m, log n', the n'' softplus argument,
# range_scale units, log gain) that the starting ball gets in directions the data do not fix
BALL_PRIOR_SCALE = 0.5


def _ball_root(cov, ndim, prior_scale: float = BALL_PRIOR_SCALE):
    """Matrix square root of the starting-ball covariance; identity * 1e-2 without one.

    The ball is the Laplace covariance regularized by a Gaussian of sd `prior_scale` per
    coordinate, ``(pinv(cov) + I / s^2)^-1``: the data's spread where they constrain the
    parameters, `prior_scale` where they do not. The refined ``cov_theta`` is a
    pseudo-inverse, so an exactly unconstrained direction (the roll of a glossy target, the
    index against the gain) has variance 0 in it. A ball that thin in a flat direction
    left the stretch-move ensemble collapsed there: the 68% interval of the (flat) roll of a
    glossy gold cylinder was 0.03 deg wide after 300 steps and 8 deg after 1500, against 88
    and 218 deg with this ball
    (``bench/results/mcmc_start_ball.md``). Each direction's sd is floored at 1e-5 so no
    direction is empty (emcee rejects linearly dependent walkers).
    """
    if cov is None or not np.all(np.isfinite(cov)):
        return np.eye(ndim) * 1e-2
    sym = 0.5 * (cov + cov.T)
    precision = np.linalg.pinv(sym, rcond=1e-15, hermitian=True) + np.eye(ndim) / prior_scale**2
    w, v = np.linalg.eigh(np.linalg.inv(precision))
    return v * np.maximum(np.sqrt(np.clip(w, 0.0, None)), 1e-5)


def _sub_covariance(ref: RefineResult, param: Parametrisation):
    """Block of the refined covariance (solver coordinates) for the groups of ``param``."""
    labels = ref.parametrisation.theta_labels
    try:
        idx = [labels.index(lab) for lab in param.theta_labels]
    except ValueError:
        return None
    return ref.covariance_theta[np.ix_(idx, idx)]


def _autocorr(kept: np.ndarray, tol: float) -> tuple[np.ndarray, bool]:
    """Integrated autocorrelation time (in steps of ``kept``) and whether it is reliable."""
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            tau = emcee.autocorr.integrated_time(kept, tol=tol, quiet=False)
        if np.all(np.isfinite(tau)):
            return np.asarray(tau), True
        raise emcee.autocorr.AutocorrError(tau, "a parameter never changed")
    except emcee.autocorr.AutocorrError:
        import logging

        logger = logging.getLogger("emcee.autocorr")
        level = logger.level
        logger.setLevel(logging.ERROR)
        try:
            with np.errstate(invalid="ignore", divide="ignore"):
                tau = np.asarray(emcee.autocorr.integrated_time(kept, tol=tol, quiet=True))
        finally:
            logger.setLevel(level)
        # a parameter whose every walker kept one value (zero variance: no accepted move
        # changed it) has an undefined (NaN) estimate: it did not mix at all, tau = inf
        stuck = ~np.isfinite(tau)
        tau = np.where(stuck, np.inf, tau)
        finite = tau[np.isfinite(tau)]
        need = int(np.ceil(tol * finite.max())) if finite.size else None
        msg = (
            f"chain too short for a reliable autocorrelation time: {kept.shape[0]} kept steps "
            f"< {tol:g} x tau_max = {need} (tau estimates {np.round(tau, 1).tolist()})"
        )
        if stuck.any():
            msg += (
                f"; parameters {np.flatnonzero(stuck).tolist()} (theta order) never changed "
                "within any walker (acceptance too low, or a start outside the posterior's bulk)"
            )
        warnings.warn(
            ChainTooShortWarning(
                msg + "; run longer (n_steps) or lower sampler.autocorr_tol; ESS and intervals "
                "are approximate"
            ),
            stacklevel=3,
        )
        return tau, False


__all__ += ["ConfigError", "mcmc_config_from_dict"]
