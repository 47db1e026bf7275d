r"""One call from an observation to an answer and how far to believe it: :func:`invert`.

Stages (each logged with its wall time on the ``inversion.invert`` logger):

1. **validate**: the config (:class:`InvertConfig`, MCMC settings included), the observation
   against every candidate model, the candidate names against the bank, the materials and
   the symmetry names, all before any computation. Errors name the field as written
   (``mcmc.sampler.n_walkers = 2: ...``) and the value.
2. **classify**: the observation against a template bank (a :class:`~inversion.TemplateBank`
   or :class:`~inversion.PreparedBank` given as ``bank=``, or one built from the candidate
   models over an attitude grid x materials x finishes, :func:`screening_bank`). Starts: the
   top-k rows and the best rows of every shape (:meth:`~inversion.Classification.candidates`),
   with the row's attitude, material, finish, the fitted range shift and the gain that
   matches the total counts, turned to its best roll about the line of sight (a monostatic
   sensor: :func:`inversion.roll_scan`, exact from five model calls; the template grid is
   coarse in the roll and the deviance multimodal in it).
3. **refine**: screened multi-start refinement per shape: every start one loose round (the
   solver's tolerances are traced, so the same compiled program), the best screened start of
   each competitive shape polished to full tolerance (after more screened starts from its
   best roll, when that is lower, and from turns of 45, 90 and 135 deg about the line of
   sight); shapes weighted by their evidence.
   The index ``n`` is held at the start's material here (see 4).
4. **materials**: the chosen shape refit with the index of every library material, part by
   part (the other parts at their best), swept again while any part's best changed (at
   most ``MATERIAL_SWEEPS``); each fit weighted by its evidence (Laplace
   approximation, :func:`log_evidence`, ``docs/physics/model_evidence.md``): posterior
   probabilities over the materials. A material whose reflectance the gain absorbs gives
   (nearly) equal deviances and volumes, hence spread probabilities. When another
   single-slot shape keeps a probability >= ``ambiguity``, its own table is computed too and
   the probabilities are averaged over the shapes (weighted by theirs).
5. **modes**: every equivalent and near-equivalent attitude of the best fit refit and
   weighted (:func:`inversion.mode_check` with the candidate mesh's own symmetry at the
   config's near tolerance: mirror images, near symmetries, the half turn of a bistatic
   sensor; and the other minima of the deviance in the roll about the line of sight,
   ``"roll X deg about the line of sight"``; and other lines of sight that explain the data
   at the fit's materials, found by a roll-scanned search over the sphere, ``"other
   optimum"``, ``_other_optima``), weights from the same evidence.
6. **index**: with ``"n"`` among the free groups, Fisher scoring from the best
   library-material fit with the index free (the refiner's Jacobian program, the step in the
   observable subspace only): the continuous index, reported only where the data determine
   it (:func:`inversion.observability`).
7. **check**: goodness of fit of the final fit against its exact null distribution
   (:func:`inversion.fit_goodness_of_fit`; ``model_mismatch``) and its observability.
8. **sample** (optional, ``config.mcmc``): one emcee chain per mode with posterior weight
   above ``mcmc_min_weight`` (:func:`inversion.sample_posterior`), ArviZ diagnostics.

The result, :class:`Inversion`, separates ``converged`` (the solver of the final fit) from
``reliable``: the fit is acceptable, the modes and shapes are resolved and, when sampled, the
chains converged; ``reasons`` lists what failed. :meth:`Inversion.write` writes
``invert.json`` (no inf/NaN), the posterior netCDF files and the fit arrays atomically
(:mod:`ppr.outputs`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import math
import numbers
import os
import threading
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pydantic
from scipy.spatial.transform import Rotation

import ppr
from ppr.config import ConfigError, StrictModel, first_nonfinite, validate_data
from ppr.geometry import quat_from_axis_angle, quat_multiply_host

from ._classifier import (
    Classification,
    PreparedBank,
    _body_los,
    attitude_error_deg,
    classify,
    line_of_sight_error_deg,
    prepare,
)
from ._database import TemplateBank
from ._gof import GoodnessOfFit, fit_goodness_of_fit, goodness_of_fit
from ._grid import (
    AttitudeGrid,
    as_symmetry,
    face_on_attitudes,
    fibonacci_sphere,
    symmetry_group,
)
from ._mcmc import (
    ChainTooShortWarning,
    MCMCConfig,
    MCMCResult,
    ModeMixture,
    PriorConfig,
    _ReflectanceShear,
    sample_posterior,
)
from ._noise import Observation
from ._observability import Observability, line_of_sight_of, observability, observable_inverse
from ._params import GROUPS, Parametrisation, PhysicalParams, lift_start
from ._posterior import _arviz, attitude_rhat
from ._refine import (
    PhysicalBounds,
    PoissonCounts,
    PoissonNoise,
    RefineResult,
    StartSummary,
    _expected_jit,
    _finish,
    _from_physical,
    _make_solver,
    _pure,
    _refine_start,
    _to_physical,
    check_observation,
    fisher_at,
    mode_check,
    refine_bounded,
    weighted_jacobian,
)
from ._roll import roll_scan

__all__ = [
    "InvertConfig",
    "Candidate",
    "Inversion",
    "invert",
    "screening_bank",
    "log_evidence",
    "prior_scales",
    "load_invert_config",
]

log = logging.getLogger("inversion.invert")

DEFAULT_FINISHES = {"rough": 10.0, "brushed": 300.0}
# the physical box (the default priors' supports): the refiner's solvers are kept inside it
BOUNDS = PhysicalBounds()
N_RE_BOX = BOUNDS.n_re
N_IM_BOX = BOUNDS.n_im
MAX_MODES_SAMPLED = 8  # posterior files: invert_posterior.nc + invert_posterior_mode{1..7}.nc
# per-axis prior sd of the attitude rotation vector (rad): the Haar volume of SO(3) in
# rotation-vector coordinates is 8 pi^2, a box of that volume has sides (8 pi^2)^(1/3) =
# 4.29 rad, and a uniform law of that width has sd 4.29 / sqrt(12)
ATTITUDE_PRIOR_SD = (8.0 * math.pi**2) ** (1.0 / 3.0) / math.sqrt(12.0)


def _distinct(v: list) -> list:
    dup = sorted({str(x) for x in v if v.count(x) > 1})
    if dup:
        raise ValueError(f"{dup[0]!r} is listed twice")
    # materials: an inline index may not take a library name listed too (one would replace
    # the other)
    names = [getattr(x, "name", x) for x in v]
    dup = sorted({str(x) for x in names if names.count(x) > 1})
    if dup:
        raise ValueError(f"the name {dup[0]!r} is given twice")
    return v


# ============================================================================ config
class GridConfig(StrictModel):
    """Attitude grid of the screening bank built from candidate models (no ``bank=``)."""

    kind: Literal["hopf", "fibonacci"] = pydantic.Field("hopf", description="grid kind")
    size: int = pydantic.Field(
        1,
        ge=1,
        le=4096,
        description="Hopf nside (72 nside^3 attitudes, ~55/nside deg apart) or Fibonacci points",
    )


def _in_box(box: tuple[float, float]):
    def check(v: float) -> float:
        if not box[0] <= v <= box[1]:
            raise ValueError(
                f"outside [{box[0]:g}, {box[1]:g}], the box the fits and the default priors "
                "cover (inversion.PhysicalBounds)"
            )
        return v

    return pydantic.AfterValidator(check)


class InlineIndex(StrictModel):
    """A material given by its index ``n_real + i n_imag`` (not in the library), inside the
    box the refiner keeps its fits in (:data:`N_RE_BOX`, :data:`N_IM_BOX`): a start outside
    it would be moved into it."""

    name: str = pydantic.Field(min_length=1)
    n_real: Annotated[float, _in_box(N_RE_BOX)]
    n_imag: Annotated[float, _in_box(N_IM_BOX)]


Group = Literal["attitude", "m", "n", "corr_length", "range_offset", "gain"]


class InvertConfig(StrictModel):
    """Settings of :func:`invert` (validated whole before any computation).

    - `free`: parameter groups fitted (``attitude``, ``m``, ``n``, ``corr_length``,
      ``range_offset``, ``gain``); ``n`` free adds the continuous-index stage.
    - `likelihood`: ``"poisson"`` (photo-counts >= 0, non-integer ones included,
      :class:`~inversion.PoissonCounts` with `background` counts per bin) or ``"gaussian"``
      (``mu + 1`` variance, :class:`~inversion.PoissonNoise`, for scaled data).
    - `solver`: ``lm`` | ``dogleg`` | ``gauss_newton``; `max_steps` per round, `rounds` of
      visibility/weights when polishing; `screen_tol` the screening round's tolerance;
      `index_steps` the trial steps of the continuous-index stage's Fisher scoring (it creeps
      along the ridge on which the gain absorbs the reflectance: on the shipped example 35
      steps to stationarity, lowering the deviance by 2.7 after the 12th).
    - `materials`: library names (``ppr.load_material``) or ``{name, n_real, n_imag}``
      tables; default: the bank's materials, or every library material at the sensor's
      wavelength. `finishes`: ``name = m`` of the screening bank (default rough 10,
      brushed 300). `grid`: the screening bank's attitude grid.
    - `top_k`, `per_shape`: template attitudes refined: the best `top_k` distinct
      (shape, attitude) rows of the classification and the best `per_shape` of every shape,
      each started at every finish of the bank; `escalate`: while the best screened start's
      goodness of fit is a model mismatch, the next `top_k` templates in rank order are
      screened too, at most `escalate` times (a search that missed the optimum is otherwise
      indistinguishable from a target outside the candidates); `polish_factor`,
      `polish_abs`: shapes whose screened deviance is within ``factor x best + abs`` are
      polished.
    - `symmetry`: ``"auto"`` (each candidate mesh's own group), a named class
      (``dihedral:4``) or ``"none"``; `near_tol`: tolerance (fraction of the mesh size) of
      the near symmetries refit as modes (0: exact ones only); `mirror`: refit mirror
      images; `min_separation_deg`: optima closer than this are one mode;
      `other_directions`, `other_starts`: the search for other optima at the fit's materials
      (``_other_optima``): the roll-scanned deviance at `other_directions` lines of sight,
      the best `other_starts` screened, those that end near the fit's deviance refit as
      modes (a template screening finds one basin; the data can have two).
    - `ambiguity`: a second shape or mode above this posterior weight is unresolved.
    - `mismatch_p`: p-value below which the goodness of fit reports a model mismatch.
    - `mcmc`: priors and sampler (:class:`~inversion.MCMCConfig`) or None (no sampling);
      `mcmc_min_weight`: modes sampled above this weight (at most `max_sampled_modes`);
      `rhat_max`: largest ArviZ R-hat of a converged chain (of the parameters the answer
      reports: the library-index columns and the rotation-vector components are judged by
      each material's indicator and by the attitude modulo the half turn about the line of
      sight instead; ``_judged_rhat``).
    - `progress`: tqdm bars (they start after the first, compiling, item).
    """

    free: Annotated[
        list[Group], pydantic.Field(min_length=1), pydantic.AfterValidator(_distinct)
    ] = pydantic.Field(
        ["attitude", "m", "n", "range_offset", "gain"],
        description="parameter groups fitted; n free adds the continuous-index fit",
    )
    likelihood: Literal["poisson", "gaussian"] = pydantic.Field(
        "poisson",
        description='"poisson": photo-counts (inversion.PoissonCounts); "gaussian": variance '
        "mu + 1 (inversion.PoissonNoise) for scaled data",
    )
    background: float = pydantic.Field(
        1e-3, gt=0.0, description="expected background counts per channel and bin (poisson)"
    )
    solver: Literal["lm", "dogleg", "gauss_newton"] = pydantic.Field(
        "lm", description="least-squares solver (optimistix)"
    )
    max_steps: int = pydantic.Field(
        100, ge=1, le=100_000, description="solver steps per round (one value: one program)"
    )
    rounds: int = pydantic.Field(
        3, ge=1, le=50, description="visibility/weight rounds when polishing a start"
    )
    screen_tol: float = pydantic.Field(
        1e-3, gt=0.0, lt=1.0, description="solver tolerance of the one screening round per start"
    )
    index_steps: int = pydantic.Field(
        50,
        ge=1,
        le=10_000,
        description="trial steps of the continuous-index Fisher scoring (each one Jacobian)",
    )
    materials: (
        Annotated[
            list[str | InlineIndex],
            pydantic.Field(min_length=1),
            pydantic.AfterValidator(_distinct),
        ]
        | None
    ) = pydantic.Field(
        None,
        description="library materials weighed per mesh part (names, or {name, n_real, "
        "n_imag}); unset: the bank's, or every library material at the sensor's wavelength",
    )
    # m > 0: the refiner moves log m, whose derivative vanishes as m -> 0 (a start at 0 stays)
    finishes: dict[str, Annotated[float, pydantic.Field(gt=0.0, le=1e6)]] | None = pydantic.Field(
        None,
        description="{name = Blinn-Phong m > 0} of the templates built from the candidate "
        "models (unset: rough = 10, brushed = 300)",
    )
    grid: GridConfig = pydantic.Field(
        GridConfig(), description="attitudes of the templates built from the candidate models"
    )
    top_k: int = pydantic.Field(
        4, ge=1, le=10_000, description="distinct template attitudes refined (best first)"
    )
    per_shape: int = pydantic.Field(
        1, ge=0, le=10_000, description="... plus the best of every candidate shape"
    )
    escalate: int = pydantic.Field(
        3,
        ge=0,
        le=1000,
        description="while the best screened fit is a model mismatch (p < mismatch_p), screen "
        "the next top_k templates, at most this many times (a missed optimum looks like a "
        "mismatch)",
    )
    face_on: int = pydantic.Field(
        3,
        ge=0,
        le=1000,
        description="each candidate's largest flat sides (classes under its symmetry) turned "
        "to face the sensor as extra screening starts, at the glossiest finish: a glint is "
        "narrower than the template grid's spacing (0: none)",
    )
    polish_factor: float = pydantic.Field(
        1.25, ge=1.0, description="shapes polished: screened deviance <= factor x best + abs"
    )
    polish_abs: float = pydantic.Field(25.0, ge=0.0, description="(see polish_factor)")
    symmetry: str = pydantic.Field(
        "auto",
        description='"auto": each candidate mesh\'s own group; a class (dihedral:n, '
        'octahedral, cyclic:n); "none"',
    )
    near_tol: float = pydantic.Field(
        1e-2,
        ge=0.0,
        lt=0.5,
        description="near symmetries to this fraction of the mesh size are refit as modes "
        "(0: exact ones only)",
    )
    mirror: bool = pydantic.Field(True, description="refit the mirror images as modes")
    other_directions: int = pydantic.Field(
        24,
        ge=0,
        le=10_000,
        description="lines of sight (a Fibonacci sphere in the body) scanned for other optima "
        "at the fit's materials (0: none)",
    )
    other_starts: int = pydantic.Field(
        12, ge=1, le=1000, description="... of which the best-scanning ones are screened"
    )
    min_separation_deg: float = pydantic.Field(
        1.0, ge=0.0, le=180.0, description="optima closer than this are one mode"
    )
    ambiguity: float = pydantic.Field(
        0.05,
        gt=0.0,
        lt=0.5,
        description="a second shape or mode above this posterior weight is unresolved",
    )
    mismatch_p: float = pydantic.Field(
        1e-3, gt=0.0, lt=1.0, description="goodness-of-fit p-value of a model mismatch"
    )
    mcmc: MCMCConfig | None = pydantic.Field(
        None, description="priors and sampler (inversion.MCMCConfig); unset: no sampling"
    )
    mcmc_min_weight: float = pydantic.Field(
        0.01, ge=0.0, le=1.0, description="modes above this weight are sampled"
    )
    max_sampled_modes: int = pydantic.Field(
        4, ge=1, le=MAX_MODES_SAMPLED, description="at most this many modes sampled"
    )
    rhat_max: float = pydantic.Field(
        1.1, gt=1.0, description="largest ArviZ R-hat of a converged chain"
    )
    progress: bool = pydantic.Field(False, description="progress bars (after compilation)")

    @pydantic.field_validator("symmetry")
    @classmethod
    def _symmetry(cls, v):
        if v not in ("auto", "none"):
            symmetry_group(v)  # raises ValueError naming the class
        return v

    @pydantic.field_validator("finishes")
    @classmethod
    def _finishes(cls, v):
        if v is not None and len(v) == 0:
            raise ValueError("must not be empty")
        return v

    @pydantic.model_validator(mode="after")
    def _finishes_in_prior(self):
        # the refined fits start at the finishes' m, and log m barely moves from a very small
        # one; the sampler then starts from a fit outside its prior and refuses to run,
        # after the whole refinement: refused here instead
        if isinstance(self.mcmc, MCMCConfig) and self.finishes:
            lo, hi = self.mcmc.priors.m.support()
            for name, m in self.finishes.items():
                if not lo <= m <= hi:
                    raise ValueError(
                        f"finishes.{name} = {m!r}: outside the support [{lo:g}, {hi:g}] of "
                        "mcmc.priors.m, where the refined fits that start from it are sampled"
                    )
        return self


def load_invert_config(path, overrides: dict | None = None) -> InvertConfig:
    """An :class:`InvertConfig` from a TOML file (errors name the file, field and value)."""
    from ppr.config import load_toml_model

    return load_toml_model(InvertConfig, path, overrides)


def _as_config(config) -> InvertConfig:
    if config is None:
        return InvertConfig()
    if isinstance(config, InvertConfig):
        return config
    if isinstance(config, Mapping):
        return validate_data(InvertConfig, dict(config), "invert config")
    hint = ""
    if isinstance(config, str | Path):
        hint = f" ({str(config)!r}: read a TOML file with inversion.load_invert_config(path))"
    raise ConfigError(
        f"invert config: expected an InvertConfig or a mapping, got {type(config).__name__}" + hint
    )


# ============================================================================ candidates
@dataclasses.dataclass(frozen=True)
class Candidate:
    """One candidate shape: its forward model (``prepare``/``expected``, e.g. an
    :class:`~inversion.SimulatorModel`), its name (as in a bank's ``names["shapes"]``), and
    optionally its symmetry (a named class, :class:`ppr.MeshSymmetry` or :class:`ppr.Mesh`;
    default: the model's mesh, ``model.scene.mesh``) and its range bin width in metres
    (default: a :class:`~inversion.SimulatorModel`'s; it turns the classifier's shift into
    a range-offset start)."""

    name: str
    model: Any
    symmetry: Any = None
    bin_width_m: float | None = None  # range bin width (default: the model's)

    def __post_init__(self):
        # checked here, not where the screening bank first uses them
        where = f"Candidate {self.name!r}"
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"{where}: name must be a non-empty string")
        if not (hasattr(self.model, "prepare") and hasattr(self.model, "expected")):
            raise ValueError(
                f"{where}: model is {type(self.model).__name__}, expected a forward model "
                "(prepare/expected, e.g. inversion.SimulatorModel)"
            )
        if isinstance(self.symmetry, str):
            try:
                symmetry_group(self.symmetry)
            except ValueError as err:
                raise ValueError(f"{where}: symmetry = {self.symmetry!r}: {err}") from None
        if self.bin_width_m is not None:
            w = self.bin_width_m
            if isinstance(w, bool) or not isinstance(w, numbers.Real) or not 0 < w < math.inf:
                raise ValueError(f"{where}: bin_width_m = {w!r}: expected metres, finite and > 0")

    @property
    def mesh(self):
        scene = getattr(self.model, "scene", None)
        return getattr(scene, "mesh", None)

    @property
    def n_materials(self) -> int:
        mesh = self.mesh
        if mesh is not None:
            return len(mesh.parts)
        return int(getattr(self.model, "n_materials", 1))

    @property
    def wavelength(self) -> float:
        scene = getattr(self.model, "scene", None)
        sensor = getattr(scene, "sensor", None)
        wl = getattr(sensor, "wavelength", None)
        return 532e-9 if wl is None else float(np.asarray(wl))

    @property
    def bin_width(self) -> float | None:
        if self.bin_width_m is not None:
            return float(self.bin_width_m)
        pure = getattr(self.model, "pure_model", None)
        w = getattr(pure, "width", None)
        if w is None:
            w = getattr(self.model, "bin_width_m", None)
        return None if w is None else float(np.asarray(w))

    def exact_symmetry(self, setting: str):
        """The exact group (attitude grid, errors): a named class or the mesh's own."""
        if setting != "auto":
            return setting
        if self.symmetry is not None:
            return self.symmetry if isinstance(self.symmetry, str) else as_symmetry(self.symmetry)
        return "none" if self.mesh is None else as_symmetry(self.mesh)

    def mode_symmetry(self, setting: str, near_tol: float):
        """The group whose elements are refit as modes (near ones at ``near_tol``)."""
        if setting != "auto":
            return setting
        mesh = self.symmetry if self.symmetry is not None else self.mesh
        if mesh is None:
            return "none"
        if not isinstance(mesh, ppr.Mesh):
            return mesh  # a named class or a ready MeshSymmetry
        return as_symmetry(mesh, tol=near_tol) if near_tol > 0 else as_symmetry(mesh)


def _as_candidates(candidates) -> list[Candidate]:
    if isinstance(candidates, Candidate):
        return [candidates]
    if isinstance(candidates, Mapping):
        out = []
        for k, v in candidates.items():
            if isinstance(v, Candidate) or not (hasattr(v, "expected") and hasattr(v, "prepare")):
                raise ValueError(
                    f"candidates[{k!r}] is {type(v).__name__}: expected a forward model "
                    "(prepare/expected)"
                )
            out.append(Candidate(str(k), v))
    elif isinstance(candidates, list | tuple):
        out = []
        for i, c in enumerate(candidates):
            if isinstance(c, Candidate):
                out.append(c)
            elif hasattr(c, "expected") and hasattr(c, "prepare"):
                out.append(Candidate(f"shape{i}", c))
            else:
                raise ValueError(
                    f"candidates[{i}] is {type(c).__name__}: expected an inversion.Candidate "
                    "or a forward model (prepare/expected)"
                )
    elif hasattr(candidates, "expected") and hasattr(candidates, "prepare"):
        out = [Candidate("shape", candidates)]
    else:
        raise ValueError(
            f"candidates: expected a forward model, an inversion.Candidate, a list of them or "
            f"a mapping name -> model, got {type(candidates).__name__}"
        )
    if not out:
        raise ValueError("candidates: empty (give at least one forward model)")
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"candidates: the name {dup[0]!r} is given twice")
    return out


# ============================================================================ evidence
def prior_scales(parametrisation, priors: PriorConfig | None = None) -> np.ndarray:
    """Prior standard deviation of every solver coordinate ``theta`` of ``parametrisation``
    (its ``theta_labels``), from the priors of the MCMC config (default
    :class:`~inversion.PriorConfig`): a uniform law over the prior's support mapped to the
    coordinate (log for ``m``, the gain, the correlation length and ``n'``; metres over the
    range scale for the offset) has sd ``width / sqrt(12)``; normal priors their sigma
    (through the coordinate's derivative at the reference); the attitude's Haar measure
    :data:`ATTITUDE_PRIOR_SD` rad per axis (or a Gaussian attitude prior's ``sigma_deg``).
    ``docs/physics/model_evidence.md``."""
    pri = PriorConfig() if priors is None else priors
    ref = parametrisation.reference
    out = []

    def one(prior, to_theta, value, deriv):
        lo, hi = prior.support()
        if prior.kind in ("uniform", "loguniform"):
            return abs(to_theta(hi) - to_theta(lo)) / math.sqrt(12.0)
        sd = prior.sigma if prior.kind != "lognormal" else prior.sigma * float(value)
        return abs(sd * deriv(value))

    for lab in parametrisation.theta_labels:
        if lab.startswith("rotvec"):
            if pri.attitude.kind == "gaussian":
                out.append(math.radians(pri.attitude.sigma_deg))
            else:
                out.append(ATTITUDE_PRIOR_SD)
            continue
        k = int(lab.split("[")[1].rstrip("]")) if "[" in lab else 0
        if lab.startswith("log_m"):
            v = max(float(np.asarray(ref.m)[k]), 1e-9)
            out.append(one(pri.m, lambda x: math.log(max(x, 1e-9)), v, lambda x: 1.0 / x))
        elif lab.startswith("log_n_re"):
            v = float(np.real(np.asarray(ref.n)[k]))
            out.append(one(pri.n_re, lambda x: math.log(max(x, 1e-9)), v, lambda x: 1.0 / x))
        elif lab.startswith("softplus_inv_n_im"):
            v = max(float(np.imag(np.asarray(ref.n)[k])), 1e-9)

            def sp_inv(x):
                x = max(x, 1e-9)
                return x + math.log(-math.expm1(-x))

            out.append(one(pri.n_im, sp_inv, v, lambda x: 1.0 / -math.expm1(-max(x, 1e-9))))
        elif lab.startswith("log_corr"):
            v = float(np.asarray(ref.corr_length)[k])
            out.append(one(pri.corr_length, lambda x: math.log(max(x, 1e-300)), v, lambda x: 1 / x))
        elif lab.startswith("range_offset"):
            s = parametrisation.range_scale
            v = float(ref.range_offset)
            out.append(one(pri.range_offset, lambda x, s=s: x / s, v, lambda x, s=s: 1.0 / s))
        elif lab == "log_gain":
            v = float(ref.gain)
            out.append(one(pri.gain, lambda x: math.log(max(x, 1e-300)), v, lambda x: 1.0 / x))
        else:  # pragma: no cover - a new group
            raise ValueError(f"prior_scales: unknown coordinate {lab!r}")
    return np.asarray(out, np.float64)


def log_evidence(fit: RefineResult, priors: PriorConfig | None = None) -> float:
    r"""Laplace approximation of the log evidence of a fit, up to a constant common to every
    fit of the same data with the same free groups:

        log Z = -D / 2 - 1/2 log det(I + S F S),   S = diag(prior sd of each coordinate)

    with ``D`` the fit's deviance (``-2 log L`` + a constant of the data) and ``F`` its Fisher
    (Gauss-Newton) matrix in the solver coordinates. ``S F S`` is the information in units of
    the prior's width: ``log det(I + S F S)`` is the Occam factor (how much the data shrink the
    prior volume) and stays finite along unobservable directions, which keep their prior
    width (``docs/physics/model_evidence.md``). ``-inf`` for a failed fit."""
    F = fit.fisher_theta
    if F is None or not np.isfinite(fit.cost) or not np.all(np.isfinite(F)):
        return -math.inf
    s = prior_scales(fit.parametrisation, priors)
    if not np.all(np.isfinite(s)):
        return -math.inf
    # A glint's Fisher matrix can have condition ~1e23 (a tilt pinned to 1e-11 rad beside an
    # unobservable roll): formed as J^T J, its small eigenvalues are round-off of either sign
    # ~1e-16 x the largest (a determinant of sign -1; clamped, errors of several units in
    # log Z). From J's R factor, det(I + S F S) = prod(1 + sigma_i^2) over the singular
    # values of R S, whose condition is the square root of F's.
    R = getattr(fit, "jacobian_r", None)
    if R is not None and R.shape[1] == len(s) and np.all(np.isfinite(R)):
        sv = np.linalg.svd(R * s[None, :], compute_uv=False)
        logdet = float(np.sum(np.log1p(sv * sv)))
        return float(-0.5 * fit.cost - 0.5 * logdet)
    A = np.eye(len(s)) + s[:, None] * (0.5 * (F + F.T)) * s[None, :]
    if not np.all(np.isfinite(A)):
        return -math.inf
    # otherwise (a Fisher matrix without its Jacobian): A's eigenvalues are >= 1 exactly
    ev = np.linalg.eigvalsh(0.5 * (A + A.T))
    logdet = float(np.sum(np.log(np.maximum(ev, 1.0))))
    return float(-0.5 * fit.cost - 0.5 * logdet)


def _probabilities(logz: Sequence[float]) -> np.ndarray:
    lz = np.asarray(logz, np.float64)
    ok = np.isfinite(lz)
    p = np.zeros(len(lz))
    if ok.any():
        w = np.exp(lz[ok] - lz[ok].max())
        p[ok] = w / w.sum()
    return p


# ============================================================================ results
@dataclasses.dataclass(frozen=True)
class ShapeFit:
    """One candidate shape refined: screened and (if competitive) polished."""

    name: str
    n_starts: int
    screened_deviance: float
    fit: RefineResult | None  # polished, or None when not competitive
    log_evidence: float
    probability: float

    def to_dict(self) -> dict:
        f = self.fit
        return {
            "name": self.name,
            "n_starts": self.n_starts,
            "screened_deviance": _num(self.screened_deviance),
            "polished": f is not None,
            "deviance": None if f is None else _num(f.cost),
            "converged": None if f is None else bool(f.success),
            "log_evidence": _num(self.log_evidence),
            "probability": float(self.probability),
        }


@dataclasses.dataclass(frozen=True)
class MaterialFit:
    """One library material in one material slot (mesh part) of the chosen shape: its fit
    and Laplace log evidence on that shape, and its posterior probability. With single-slot
    shapes that the data do not rule out (probability >= ``ambiguity``), the probability is
    averaged over them, each shape's own material table weighted by the shape's probability
    (a wrong shape's table alone gave confident wrong materials); otherwise it is the chosen
    shape's."""

    part: int
    name: str
    n: complex
    fit: RefineResult
    log_evidence: float
    probability: float
    evidence_at: str | None = None  # another material's optimum the evidence was taken at

    def to_dict(self) -> dict:
        return {
            "part": self.part,
            "name": self.name,
            "n": [float(self.n.real), float(self.n.imag)],
            "deviance": _num(self.fit.cost),
            "converged": bool(self.fit.success),
            "n_steps": int(self.fit.n_steps),
            "log_evidence": _num(self.log_evidence),
            "evidence_at": self.evidence_at,
            "probability": float(self.probability),
        }


@dataclasses.dataclass(frozen=True)
class IndexEstimate:
    """The continuous index of one material slot where the data determine it."""

    part: int
    n: complex
    sigma: tuple[float, float] | None  # (n', n'') 1-sigma, observable subspace; None: not
    constrained: bool
    note: str

    def to_dict(self) -> dict:
        return {
            "part": self.part,
            "n": [float(self.n.real), float(self.n.imag)],
            "sigma": None if self.sigma is None else [_num(s) for s in self.sigma],
            "constrained": bool(self.constrained),
            "note": self.note,
        }


@dataclasses.dataclass(frozen=True)
class ModeResult:
    """One distinct mode of the posterior (an equivalent or near-equivalent attitude)."""

    label: str
    kind: str
    fit: RefineResult
    delta_deviance: float
    separation_deg: float
    los_separation_deg: float
    log_evidence: float
    weight: float
    posterior: MCMCResult | None = None
    posterior_converged: bool | None = None
    posterior_warnings: tuple[str, ...] = ()
    diagnostics: dict | None = None

    def to_dict(self, los_world=None) -> dict:
        q = np.asarray(self.fit.params.unit_quaternion(), np.float64)
        out = {
            "label": self.label,
            "kind": self.kind,
            "quaternion": q.tolist(),
            "line_of_sight_body": _body_los(q, los_world).tolist(),
            "deviance": _num(self.fit.cost),
            "delta_deviance": _num(self.delta_deviance),
            "separation_deg": _num(self.separation_deg),
            "los_separation_deg": _num(self.los_separation_deg),
            "converged": bool(self.fit.success),
            "log_evidence": _num(self.log_evidence),
            "weight": float(self.weight),
            "sampled": self.posterior is not None,
        }
        if self.posterior is not None:
            post = self.posterior
            iv68, iv95 = post.interval(0.68), post.interval(0.95)
            out["posterior"] = {
                "labels": list(post.labels),
                "median": post.median(),
                "interval68": iv68,
                "interval95": iv95,
                "acceptance_fraction": float(np.mean(post.acceptance_fraction)),
                "tau": post.tau,
                "burn_in": int(post.burn_in),
                "thin": int(post.thin),
                "converged": bool(self.posterior_converged),
                "warnings": list(self.posterior_warnings),
                "diagnostics": self.diagnostics,
            }
        return out


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _jsonable(obj: Any) -> Any:
    """Plain JSON values; non-finite floats become ``None``."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, np.ndarray | jax.Array):
        return _jsonable(np.asarray(obj).tolist())
    if isinstance(obj, complex):
        return [_num(obj.real), _num(obj.imag)]
    if isinstance(obj, float):
        return _num(obj)
    if isinstance(obj, pydantic.BaseModel):
        return _jsonable(obj.model_dump(mode="json"))
    return obj


def _polar_azimuth(v) -> tuple[float, float]:
    v = np.asarray(v, np.float64) / np.linalg.norm(v)
    return (
        float(np.degrees(np.arccos(np.clip(v[2], -1.0, 1.0)))),
        float(np.degrees(np.arctan2(v[1], v[0]))),
    )


INVERT_FILES = (
    "invert.json",
    "invert_fit.npz",
    "invert_posterior.nc",
    *[f"invert_posterior_mode{j}.nc" for j in range(1, MAX_MODES_SAMPLED)],
    "invert_fit.png",
    "invert_corner.png",
)


@dataclasses.dataclass(frozen=True)
class Inversion:
    """The result of :func:`invert` (module docstring).

    - `shape`: the chosen candidate's name; `shapes`: every candidate refined
      (:class:`ShapeFit`: deviances, evidence, probability).
    - `fit`: the final fit (:class:`~inversion.RefineResult`; with ``n`` free, the
      continuous-index fit); `params` its :class:`~inversion.PhysicalParams`.
    - `materials`: per material slot, the library materials' fits and probabilities
      (:class:`MaterialFit`); `material`: the most probable per slot; `index`: the
      continuous index where the data determine it (:class:`IndexEstimate`).
    - `modes`: the distinct modes (:class:`ModeResult`: label, weight, optional posterior),
      best first.
    - `goodness_of_fit`, `observability`: of the final fit.
    - `converged`: the final fit's solver converged. `reliable`: the fit is acceptable (no
      model mismatch), shapes and modes are resolved and the sampled chains converged;
      `reasons`: what is not, in words.
    - `timings`: seconds per stage; `provenance`: versions and the resolved config;
      `classification`: the classifier's answer; `data`: the observation; `expected`: the
      final fit's expected counts.
    """

    shape: str
    shapes: tuple[ShapeFit, ...]
    fit: RefineResult
    materials: tuple[tuple[MaterialFit, ...], ...]
    index: tuple[IndexEstimate, ...]
    modes: tuple[ModeResult, ...]
    goodness_of_fit: GoodnessOfFit
    observability: Observability
    converged: bool
    reliable: bool
    reasons: tuple[str, ...]
    timings: dict
    provenance: dict
    classification: Classification | None
    data: np.ndarray
    expected: np.ndarray
    line_of_sight_world: np.ndarray
    sampled: bool = False

    # ------------------------------------------------------------------ views
    @property
    def params(self) -> PhysicalParams:
        return self.fit.params

    @property
    def quaternion(self) -> np.ndarray:
        return np.asarray(self.fit.params.unit_quaternion(), np.float64)

    @property
    def line_of_sight(self) -> np.ndarray:
        """Unit line of sight (toward the sensor) in the body frame."""
        return _body_los(self.quaternion, self.line_of_sight_world)

    @property
    def material(self) -> tuple[str, ...]:
        """The most probable library material of each slot."""
        return tuple(max(ms, key=lambda m: m.probability).name for ms in self.materials)

    @property
    def material_probabilities(self) -> tuple[dict[str, float], ...]:
        return tuple({m.name: float(m.probability) for m in ms} for ms in self.materials)

    @property
    def shape_probabilities(self) -> dict[str, float]:
        return {s.name: float(s.probability) for s in self.shapes}

    @property
    def mode_weights(self) -> np.ndarray:
        return np.array([m.weight for m in self.modes])

    @property
    def posteriors(self) -> tuple[MCMCResult, ...]:
        return tuple(m.posterior for m in self.modes if m.posterior is not None)

    @property
    def mixture(self) -> ModeMixture | None:
        """The posterior over every sampled mode (:class:`~inversion.ModeMixture`: each mode's
        chain weighted by its posterior weight, renormalised over the sampled modes), or None
        without sampling. Its ``interval(label, level)`` is the interval a parameter has
        when the modes are not resolved (two modes of weight 0.5 whose range offsets differ
        by more than either's width: one mode's interval covers the truth half the time)."""
        kept = [m for m in self.modes if m.posterior is not None]
        if not kept:
            return None
        w = np.array([m.weight for m in kept], np.float64)
        w = w / w.sum() if w.sum() > 0 else np.full(len(kept), 1.0 / len(kept))
        return ModeMixture(
            modes=tuple(m.posterior for m in kept),
            weights=w,
            costs=np.array([m.fit.cost for m in kept], np.float64),
        )

    @functools.cached_property
    def posterior(self):
        """ArviZ ``InferenceData`` of the most probable sampled mode (physical units), or
        None without sampling."""
        posts = self.posteriors
        if not posts:
            return None
        return posts[0].to_inference_data(
            line_of_sight=self.line_of_sight_world, observed=self.data
        )

    # ------------------------------------------------------------------ checks
    def compare(self, truth: PhysicalParams, shape: str | None = None) -> dict:
        """Errors against a known truth (simulation studies): attitude error modulo the
        chosen shape's exact symmetry, line-of-sight error (also modulo the mirror images and
        the half turn, which the data may not tell apart), parameter errors in units of the
        reported uncertainty, and whether the truth lies in the sampled intervals."""
        q_t = np.asarray(truth.unit_quaternion(), np.float64)
        q_f = self.quaternion
        sym = self.provenance.get("_exact_symmetry")
        out: dict[str, Any] = {"shape_ok": None if shape is None else shape == self.shape}
        if shape is not None and shape != self.shape:
            return out
        if sym is None:
            sym = "none"
        mirror = len(as_symmetry(sym).improper) > 0
        out["attitude_error_deg"] = float(attitude_error_deg(q_t, q_f, sym)[0])
        out["attitude_error_mod_half_turn_deg"] = float(
            attitude_error_deg(q_t, q_f, sym, mirror=mirror, half_turn=True)[0]
        )
        k = self.line_of_sight_world
        out["los_error_deg"] = float(line_of_sight_error_deg(q_t, q_f, sym, los=k)[0])
        out["los_error_mod_mirror_deg"] = (
            float(line_of_sight_error_deg(q_t, q_f, sym, mirror=True, los=k)[0]) if mirror else None
        )
        ob = self.observability
        labels = ob.labels
        par = self.fit.parametrisation
        tv = np.asarray(
            par.physical_vector(par.from_physical(_nearest_equivalent(truth, q_f, sym)))
        )
        # (truth - fit) / sigma for the parameters the data determine (None for the others:
        # along an unobservable direction the fit's value is arbitrary)
        z = {}
        for i, lab in enumerate(labels):
            s = ob.sigma[i]
            ok = np.isfinite(s) and s > 0 and bool(ob.determined[i])
            z[lab] = _num((tv[i] - ob.values[i]) / s) if ok else None
        out["z"] = z
        return out

    # ------------------------------------------------------------------ text and files
    def to_dict(self) -> dict:
        los = self.line_of_sight
        polar, azim = _polar_azimuth(los)
        ob = self.observability
        fit = self.fit
        cls = self.classification
        cls_d = None
        if cls is not None:
            cls_d = {
                "seconds": float(cls.seconds),
                "no_template_fits": None
                if cls.no_template_fits is None
                else bool(cls.no_template_fits[0]),
                "template_p_value": None if cls.fit is None else _num(cls.fit[0].p_value),
            }
        return _jsonable(
            {
                "converged": self.converged,
                "reliable": self.reliable,
                "reasons": list(self.reasons),
                "shape": self.shape,
                "material": list(self.material),
                "attitude": {
                    "quaternion": self.quaternion,
                    "line_of_sight_body": los,
                    "los_polar_deg": polar,
                    "los_azimuth_deg": azim,
                    "line_of_sight_world": self.line_of_sight_world,
                },
                "parameters": {
                    "labels": list(ob.labels),
                    "values": ob.values,
                    "sigma": [_num(s) for s in ob.sigma],
                    "note": "sigma in the observable subspace (null: unobservable on its own); "
                    "attitude as a rotation vector (deg) about the quaternion above",
                    "range_offset_m": float(fit.params.range_offset),
                    "gain": float(fit.params.gain),
                    "gain_unit": "counts per (m^2 sr^-1) for SimulatorModel",
                    "m": np.asarray(fit.params.m),
                    "n": [[float(z.real), float(z.imag)] for z in np.asarray(fit.params.n)],
                },
                "fit": {
                    "method": fit.method,
                    "result": fit.result,
                    "message": fit.message,
                    "deviance": fit.cost,
                    "dof": fit.dof,
                    "n_steps": fit.n_steps,
                    "free": list(fit.parametrisation.free),
                },
                "goodness_of_fit": self.goodness_of_fit.to_dict(),
                "observability": ob.to_dict(),
                "shapes": [s.to_dict() for s in self.shapes],
                "material_probabilities": [
                    {"part": k, "probabilities": p}
                    for k, p in enumerate(self.material_probabilities)
                ],
                "materials": [[m.to_dict() for m in ms] for ms in self.materials],
                "index": [e.to_dict() for e in self.index],
                "modes": [m.to_dict(self.line_of_sight_world) for m in self.modes],
                "posterior_over_modes": self._mixture_intervals(),
                "classification": cls_d,
                "timings_s": self.timings,
                "provenance": {k: v for k, v in self.provenance.items() if not k.startswith("_")},
            }
        )

    def summary(self) -> str:
        """Human-readable verdict first, then the answer and its uncertainties."""
        lines = []
        if self.reliable:
            lines.append(
                "RELIABLE: fit acceptable, shape and modes resolved"
                + (", chains converged" if self.sampled else "")
            )
        else:
            lines.append("NOT RELIABLE: " + "; ".join(self.reasons))
        lines.append(f"solver converged: {self.converged} ({self.fit.result})")
        lines.append(self.goodness_of_fit.summary())
        shp = ", ".join(f"{s.name} {s.probability:.3g}" for s in self.shapes)
        lines.append(f"shape: {self.shape} (probabilities: {shp})")
        polar, azim = _polar_azimuth(self.line_of_sight)
        q = self.quaternion
        lines.append(
            f"attitude: quaternion [{', '.join(f'{x:.5f}' for x in q)}]; line of sight in the "
            f"body frame: polar {polar:.2f} deg, azimuth {azim:.2f} deg"
        )
        for k, probs in enumerate(self.material_probabilities):
            items = sorted(probs.items(), key=lambda kv: -kv[1])
            lines.append(f"material (part {k}): " + ", ".join(f"{n} {p:.2f}" for n, p in items))
        for e in self.index:
            if e.constrained:
                lines.append(
                    f"index (part {e.part}): n = {e.n.real:.4g} + {e.n.imag:.4g}i "
                    f"+- ({e.sigma[0]:.2g}, {e.sigma[1]:.2g})"
                )
            else:
                lines.append(f"index (part {e.part}): not determined by the data ({e.note})")
        lines.append(f"modes: {len(self.modes)} distinct")
        for j, m in enumerate(self.modes):
            lines.append(
                f"  {j}: {m.label}: weight {m.weight:.3g}, delta deviance "
                f"{m.delta_deviance:+.4g}, line of sight {m.los_separation_deg:.3g} deg from "
                "the best" + (" (sampled)" if m.posterior is not None else "")
            )
        lines.append(self.observability.summary())
        for j, m in enumerate(self.modes):
            if m.posterior is None:
                continue
            post = m.posterior
            iv = post.interval(0.95)
            lines.append(
                f"posterior, mode {j} ({m.label}): converged {m.posterior_converged}, "
                f"acceptance {np.mean(post.acceptance_fraction):.2f}"
            )
            med = post.median()
            for i, lab in enumerate(post.labels):
                lines.append(
                    f"  {lab:>22s} median {med[i]: .6g}  95% [{iv[i, 0]:.6g}, {iv[i, 1]:.6g}]"
                )
        mix = self._mixture_intervals()
        if mix is not None and len(mix["weights"]) > 1:
            w = ", ".join(f"{x:.3g}" for x in mix["weights"])
            lines.append(f"posterior over the {len(mix['weights'])} sampled modes (weights {w}):")
            for lab, v in mix["intervals"].items():
                lo, hi = v["95"]
                lines.append(f"  {lab:>22s} median {v['median']: .6g}  95% [{lo:.6g}, {hi:.6g}]")
        t = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items())
        lines.append(f"timings: {t}")
        return "\n".join(lines)

    def _mixture_intervals(self) -> dict | None:
        """Median and 68 / 95 % equal-tailed intervals of every parameter but the attitude
        over :attr:`mixture` (physical units, the posterior labels), or None unsampled."""
        mix = self.mixture
        if mix is None:
            return None
        out = {}
        for lab in mix.modes[0].labels:
            if lab.startswith("rot_"):
                continue
            lo68, hi68 = mix.interval(lab, 0.68)
            lo95, hi95 = mix.interval(lab, 0.95)
            med = float(mix.interval(lab, 0.0)[0])  # the 0 % interval: the median
            out[lab] = {
                "median": med,
                "68": [float(lo68), float(hi68)],
                "95": [float(lo95), float(hi95)],
            }
        return {
            "weights": [float(x) for x in mix.weights],
            "intervals": out,
            "note": "every sampled mode's samples weighted by its weight (the attitude is "
            "per mode: see modes)",
        }

    def output_names(self) -> list[str]:
        return list(INVERT_FILES)

    def write(
        self,
        out_dir,
        *,
        overwrite: bool = False,
        extra: Mapping | None = None,
        plots: bool = True,
    ) -> list[Path]:
        """Write ``invert.json`` (:meth:`to_dict` plus `extra`), ``invert_fit.npz`` (data,
        expected counts of the final fit), one posterior netCDF per sampled mode
        (``invert_posterior.nc`` for the most probable, ``invert_posterior_mode{j}.nc``) and,
        with `plots`, ``invert_fit.png`` and ``invert_corner.png``, as one atomic commit into
        ``out_dir`` (:mod:`ppr.outputs`: a failed write leaves the previous result as it
        was; files of a previous run that this one does not produce are removed with it).
        JSON has no NaN or inf: non-finite numbers, the result's own (a sigma of an
        unobservable parameter) and those in `extra`, are written as ``null``. Returns the
        paths written."""
        from ppr import outputs as _outputs

        optional = [n for n in INVERT_FILES if n not in ("invert.json", "invert_fit.npz")]
        with _outputs.outputs(out_dir, INVERT_FILES, overwrite, optional=optional) as out:
            self.write_into(out.folder, extra=extra, plots=plots)
        return out.written

    def write_into(self, folder, *, extra: Mapping | None = None, plots: bool = True) -> None:
        """Write the files of :meth:`write` into an existing (staging) folder."""
        folder = Path(folder)
        d = self.to_dict()
        post_files = []
        k = 0
        for j, m in enumerate(self.modes):
            if m.posterior is None:
                continue
            name = "invert_posterior.nc" if k == 0 else f"invert_posterior_mode{k}.nc"
            m.posterior.write(
                folder / name, line_of_sight=self.line_of_sight_world, observed=self.data
            )
            d["modes"][j]["posterior"]["file"] = name
            post_files.append(name)
            k += 1
        d["posterior_files"] = post_files
        if extra:
            clash = sorted(set(extra) & set(d))
            if clash:
                raise ValueError(f"Inversion.write: extra keys {clash} clash with the result's")
            d.update(_jsonable(dict(extra)))
        (folder / "invert.json").write_text(json.dumps(d, indent=2, allow_nan=False) + "\n")
        np.savez_compressed(
            folder / "invert_fit.npz",
            data=self.data,
            expected=self.expected,
            quaternion=self.quaternion,
        )
        if plots:
            _plot_fit(folder / "invert_fit.png", self.data, self.expected)
            posts = self.posteriors
            if posts:
                posts[0].corner_plot(folder / "invert_corner.png")


def _nearest_equivalent(truth: PhysicalParams, q_fit, sym) -> PhysicalParams:
    """The truth at the exactly equivalent attitude (its images under the shape's rotations
    and the half turn about the line of sight) nearest the fit."""
    from ._classifier import _equivalents

    cands = _equivalents(np.asarray(truth.unit_quaternion(), np.float64), sym, False, True)[0]
    d = np.abs(cands @ np.asarray(q_fit, np.float64))
    q = cands[int(np.argmax(d))]
    return PhysicalParams(q, truth.m, truth.n, truth.corr_length, truth.range_offset, truth.gain)


def _plot_fit(path, data, fitted) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for c in range(data.shape[0]):
        ax.plot(data[c], ".", ms=3, label=f"channel {c} data")
        ax.plot(fitted[c], "-", lw=1)
    ax.set_xlabel("range bin")
    ax.set_ylabel("counts")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("inversion: data (dots) and best fit (lines)")
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ============================================================================ helpers
class _Stages:
    """Wall time per stage, logged as each ends."""

    def __init__(self):
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    @contextlib.contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        log.info("stage %s ...", name)
        try:
            yield
        finally:
            dt = time.perf_counter() - t
            self.timings[name] = self.timings.get(name, 0.0) + dt
            log.info("stage %s done in %.2f s", name, dt)


class _Bar:
    """A labelled tqdm bar that appears after the first item (which compiles)."""

    def __init__(self, enabled: bool, total: int, desc: str):
        self.enabled, self.total, self.desc = enabled and total > 1, total, desc
        self.done, self.bar = 0, None

    def step(self):
        self.done += 1
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, initial=self.done, desc=self.desc, leave=False)
        else:
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _physical_memory() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):  # not a POSIX system
        return None


def _check_bank_fits(cfg: InvertConfig, cands: list[Candidate], n_mat: int, n_fin: int) -> None:
    """Refuse a screening grid whose attitudes (before the symmetry reduction, 4 float64 each)
    and templates (after it, one float32 per channel and bin) cannot be held in this
    machine's memory: ``grid.size`` is bounded by the grid's schema, but a Hopf grid grows as
    72 size^3 and one of size 4096 would need petabytes, found only when it is built."""
    g = cfg.grid
    n_att = 72 * g.size**3 if g.kind == "hopf" else g.size
    need = 32 * n_att
    n_templates = 0
    for c in cands:
        order = len(symmetry_group(c.exact_symmetry(cfg.symmetry)))
        n_c = -(-n_att // order) * n_mat * n_fin
        n_templates += n_c
        shape = _expected_shape(c.model)
        need += 4 * n_c * (shape[0] * shape[1] if shape is not None else 1)
    have = _physical_memory()
    if have is not None and need > have:
        raise ConfigError(
            f"grid.size = {g.size}: a {g.kind} grid of {n_att:.3g} attitudes gives "
            f"{n_templates:.3g} screening templates (x {n_mat} materials x {n_fin} finishes, "
            f"after the symmetry reduction), {need / 2**30:.3g} GiB, more than this machine's "
            f"{have / 2**30:.3g} GiB of memory; lower grid.size"
        )


def _resolve_materials(cfg: InvertConfig, bank: TemplateBank | None, wavelength: float):
    """``{name: n}`` of the materials the material stage weighs (and, without a bank, the
    screening bank's)."""
    out: dict[str, complex] = {}

    def lib(name: str, where: str) -> complex:
        try:
            return complex(np.asarray(ppr.load_material(name, wavelength).n))
        except (KeyError, ValueError) as err:
            raise ConfigError(f"{where} = {name!r}: {str(err).strip(chr(39))}") from None

    if cfg.materials is not None:
        for i, m in enumerate(cfg.materials):
            if isinstance(m, InlineIndex):
                out[m.name] = complex(m.n_real, m.n_imag)
            else:
                out[m] = lib(m, f"invert config: materials[{i}]")
        return out
    if bank is not None:
        for i, name in enumerate(bank.names["materials"]):
            out[name] = lib(name, f"bank: names.materials[{i}]")
        return out
    for name in ppr.material_names():
        with contextlib.suppress(KeyError, ValueError):
            out[name] = complex(np.asarray(ppr.load_material(name, wavelength).n))
    return out


def screening_bank(
    candidates,
    materials: Mapping[str, complex],
    finishes: Mapping[str, float],
    *,
    grid: GridConfig | Mapping | None = None,
    symmetry: str = "auto",
    attitudes=None,
    progress: bool = False,
) -> TemplateBank:
    """A template bank from the candidate models themselves: every shape at the attitudes of
    a grid (reduced by its exact symmetry) x `materials` (every part the same) x `finishes`
    (Blinn-Phong ``m``), energy-normalized, for :func:`inversion.classify`. Each attitude's
    visibility is ray cast once (per finish for a model with the macro double bounce).
    `attitudes`: ``(A, 4)`` quaternions used for every shape instead of the grid (its stated
    resolution is then unknown: NaN). `progress`: a tqdm bar per shape (after its first,
    compiling, attitude)."""
    if grid is None:
        grid = GridConfig()
    elif isinstance(grid, Mapping):
        grid = validate_data(GridConfig, dict(grid), "screening_bank: grid")
    cands = _as_candidates(candidates)
    mats, fins = list(materials.items()), list(finishes.items())
    sigs, sid, aid, mid, fid, quats, res, syms = [], [], [], [], [], [], [], []
    for s, c in enumerate(cands):
        sym = c.exact_symmetry(symmetry)
        if attitudes is None:
            g = AttitudeGrid(grid.kind, grid.size, sym)
            res.append(g.resolution_deg)
            grid_quats = g.quats
        else:
            grid_quats = np.asarray(attitudes, np.float64).reshape(-1, 4)
            grid_quats = grid_quats / np.linalg.norm(grid_quats, axis=1, keepdims=True)
            res.append(math.nan)
        syms.append(symmetry_group(sym).tolist() if not isinstance(sym, str) else sym)
        k = c.n_materials
        per_finish = bool(getattr(c.model, "multibounce", False))
        bar = _Bar(progress, len(grid_quats), f"templates {c.name}")
        for a, q in enumerate(grid_quats):
            aux = None
            for fi, (_, m) in enumerate(fins):
                for mi, (_, n) in enumerate(mats):
                    phys = PhysicalParams(q, [m] * k, [n] * k, range_offset=0.0, gain=1.0)
                    if aux is None or (per_finish and mi == 0):
                        aux = c.model.prepare(phys)
                    mu = np.maximum(_expect(c.model, phys, aux), 0.0)
                    sigs.append((mu / max(mu.sum(), 1e-300)).astype(np.float32))
                    sid.append(s)
                    aid.append(a)
                    mid.append(mi)
                    fid.append(fi)
                    quats.append(q)
            bar.step()
        bar.close()
    return TemplateBank(
        signatures=np.stack(sigs),
        shape_id=np.asarray(sid, np.int32),
        attitude_id=np.asarray(aid, np.int32),
        material_id=np.asarray(mid, np.int32),
        finish_id=np.asarray(fid, np.int32),
        quat=np.asarray(quats, np.float64),
        names={
            "shapes": [c.name for c in cands],
            "materials": [n for n, _ in mats],
            "finishes": [n for n, _ in fins],
            "finish_m": [float(m) for _, m in fins],
            "symmetry": syms,
            # the models' range bins, pulse, sensor and channels (invert checks candidates
            # against it: a bank of other sensor settings ranks the wrong templates)
            "model_sensor": _sensor_fingerprint(cands[0].model) if cands else None,
        },
        sensor="",
        resolution_deg=res,
    )


def _sensor_fingerprint(model) -> dict | None:
    """The settings a model's counts depend on besides the target: range bins, pulse, sensor
    directions, wavelength and channel matrix (JSON values), or None for a model without a
    ppr scene (a user's own forward model)."""
    scene = getattr(model, "scene", None)
    if scene is None:
        return None
    pure = getattr(model, "pure_model", None)
    proj = getattr(pure, "projection", None)

    def r(a):  # 12 significant digits (a pulse sigma is 4e-11 s)
        return [float(f"{float(x):.12g}") for x in np.asarray(a, np.float64).reshape(-1)]

    b, p, s = scene.bins, scene.pulse, scene.sensor
    return {
        "bins.n_bins": int(b.n_bins),
        "bins.width_m": r(b.width),
        "bins.start_m": r(b.start),
        "pulse.sigma_t_s": r(p.sigma_t),
        "pulse.t0_s": r(getattr(p, "t0", 0.0)),
        "sensor.laser_dir": r(s.laser_dir),
        "sensor.receiver_dir": r(s.receiver_dir),
        "sensor.frame_tx": r(s.frame_tx),
        "sensor.wavelength_m": r(s.wavelength),
        "channels": None if proj is None else r(proj),
    }


def _check_same_sensor(cands, bank) -> None:
    """Candidates of one observation share its sensor settings, and a screening bank's are
    theirs: a ValueError naming the first setting that differs (the invert docstring's "the
    same sensor settings" was not checked: a bank of 5 cm bins screened 1 cm data)."""
    prints = [(c.name, _sensor_fingerprint(c.model)) for c in cands]
    prints = [(n, f) for n, f in prints if f is not None]
    ref = None
    if bank is not None and bank.names.get("model_sensor"):
        ref = ("the bank", bank.names["model_sensor"])
    elif prints:
        ref = (f"candidate {prints[0][0]!r}", prints[0][1])
    if ref is None:
        return

    def show(x):
        x = np.atleast_1d(np.asarray(x, np.float64))
        return f"{x[0]:.6g}" if x.size == 1 else (str(x.tolist()) if x.size <= 4 else "(other)")

    for name, f in prints:
        for key, v in f.items():
            w = ref[1].get(key)
            if v is None or w is None:
                continue
            va = np.atleast_1d(np.asarray(v, np.float64))
            wa = np.atleast_1d(np.asarray(w, np.float64))
            if va.shape != wa.shape or not np.allclose(va, wa, rtol=1e-9, atol=1e-15):
                raise ValueError(
                    f"candidate {name!r}: {key} = {show(v)} differs from {ref[0]}'s {show(w)}: "
                    "the candidates (and a bank) must share the observation's sensor settings"
                )


def _expect(model, phys, aux) -> np.ndarray:
    """Expected counts, jitted: the refiner's program for an equinox model (a
    SimulatorModel's kernel or a toy), the model's own ``expected`` otherwise."""
    pure = _pure(model)
    if isinstance(pure, eqx.Module):
        return np.asarray(_expected_jit(pure, phys, aux), np.float64)
    return np.asarray(model.expected(phys, aux), np.float64)


def _noise_of(cfg: InvertConfig):
    if cfg.likelihood == "poisson":
        return PoissonCounts(background=cfg.background)
    return PoissonNoise()


def _with(phys: PhysicalParams, **kw) -> PhysicalParams:
    d = {
        "quaternion": phys.quaternion,
        "m": phys.m,
        "n": phys.n,
        "corr_length": phys.corr_length,
        "range_offset": phys.range_offset,
        "gain": phys.gain,
    }
    d.update(kw)
    return PhysicalParams(**d)


def _mode_material_optima(refiner, params: PhysicalParams, fits, lib_n, max_deg: float = 1.0):
    """Per part and library material, the optimum next to ``params`` (a sampled mode): the
    material stage's fit where its attitude is within ``max_deg`` of the mode's, else a
    local refit from the mode with that material (the material stage ran at the first fit,
    and the best mode can be another one, e.g. its mirror image: the sampler's material jumps
    translate between these optima, and a translation taken from another mode is off by
    more than the posterior's width at high SNR)."""
    q = np.asarray(params.unit_quaternion(), np.float64)
    out = []
    for part, row in enumerate(fits):
        new_row = []
        for n, ph in zip(lib_n, row, strict=True):
            if ph is not None:
                qm = np.asarray(ph.unit_quaternion(), np.float64)
                dot = min(abs(float(q @ qm)), 1.0)
                if np.degrees(2.0 * np.arccos(dot)) <= max_deg:
                    new_row.append(ph)
                    continue
            f = refiner.polish(
                _gain_profiled(refiner, _with(params, n=_set_part(params.n, part, n))), local=True
            )
            new_row.append(f.params if np.isfinite(f.cost) else ph)
        out.append(new_row)
    return out


def _gain_profiled(refiner, phys: PhysicalParams) -> PhysicalParams:
    """``phys`` with the gain at its closed-form optimum for the data: the expected total
    equal to the observed one (the Poisson maximum-likelihood gain without background). A
    start with another material's index keeps the previous material's gain otherwise, off by
    the ratio of their reflectances (aluminium to fused silica: ~25x), and a refit from
    there can settle in another basin (a fused-silica cylinder at SNR 1000: deviance 441.7
    against 428.0 from the truth). Unchanged when the gain is not free or a total is not
    positive."""
    if "gain" not in refiner.free:
        return phys
    mu = _expect(refiner.model, phys, refiner.model.prepare(phys))
    tot, y = float(np.sum(mu)), float(np.sum(np.asarray(refiner.data_j)))
    if not (np.isfinite(tot) and tot > 0 and y > 0):
        return phys
    return _with(phys, gain=phys.gain * (y / tot))


def _material_tables(refiner, fit, k_parts: int, materials: dict, priors, progress):
    """The material stage on one shape: every library material in every slot refit from
    ``fit`` (the other slots at their best), swept again while a slot's best changed (at most
    ``MATERIAL_SWEEPS``; the tables are the last sweep's, each slot's conditional on the
    others' best). Returns ``(tables, fit)``: per slot the :class:`MaterialFit` rows, and the
    fit with every slot at its most probable material."""
    mat_names = list(materials)
    n_best = np.asarray(fit.params.n).copy()
    tables: list[list[MaterialFit]] = []
    for sweep in range(MATERIAL_SWEEPS):
        tables = []
        changed = False
        bar = _Bar(progress, k_parts * len(mat_names), f"material fits (sweep {sweep + 1})")
        for part in range(k_parts):
            fits, local = [], []
            for name in mat_names:
                n = materials[name]
                if abs(complex(np.asarray(fit.params.n)[part]) - n) < 1e-5:
                    f = fit  # the current fit already holds this material (n'' lifted)
                else:
                    f = refiner.polish(
                        _gain_profiled(refiner, _with(fit.params, n=_set_part(n_best, part, n))),
                        local=True,
                    )
                fits.append(f)
                local.append(f is not fit)
                bar.step()
            lz = [log_evidence(f, priors) for f in fits]
            _polish_material_fits(refiner, fits, lz, local, priors)
            at = _carry_best_optimum(refiner, fits, lz, mat_names, materials, part, priors)
            p = _probabilities(lz)
            table = [
                MaterialFit(part, nm, materials[nm], f, z, float(pp), a)
                for nm, f, z, pp, a in zip(mat_names, fits, lz, p, at, strict=True)
            ]
            tables.append(table)
            best_m = max(table, key=lambda m: (m.probability, -m.fit.cost))
            changed |= abs(complex(n_best[part]) - best_m.n) > 1e-5
            n_best[part] = best_m.n
            fit = best_m.fit
        bar.close()
        if not changed or k_parts == 1:
            break
    return tables, fit


def _shape_averaged(tables, p_best: float, others) -> list[list]:
    """The best shape's single-slot table with each row's probability averaged over the
    shapes: ``sum_s P(s) P(material | s) / sum_s P(s)`` over the best shape (``p_best``) and
    ``others`` (``(P(s), tables of s)``); fits and log evidences stay the best shape's."""
    (rows,) = tables
    tot = p_best + sum(p for p, _ in others)
    mix = {r.name: p_best * r.probability for r in rows}
    for p, (other_rows,) in others:
        for r in other_rows:
            mix[r.name] = mix.get(r.name, 0.0) + p * r.probability
    return [[dataclasses.replace(r, probability=mix[r.name] / tot) for r in rows]]


def _polish_material_fits(refiner, fits: list, lz: list, local: list, priors) -> None:
    """Polish to convergence, in place, the material stage's local refits that can matter.

    A local refit (one round at tolerance 1e-6 from another material's optimum) can stop
    early on a ridge the data barely constrain (a glossy target's roughness, the index
    against the gain), where the Laplace Occam factor differs by ~1 in log evidence at equal
    deviance (a fused-silica 3U at SNR 1000: probability 0.09 as a local refit, 0.28
    converged). Polished: every local refit whose log evidence is within
    ``MATERIAL_POLISH_WINDOW`` of the best, and every one whose solver did not converge
    (its deviance can be far above its optimum) unless even the generous estimate of
    :func:`_polish_gain` (its Fisher-scoring decrement plus ``MATERIAL_OCCAM_SLACK``) leaves it
    outside the window, repeated while a polish moves the best.
    A converged local refit further behind is kept: a polish lowers its deviance only by
    what the 1e-6 tolerance left and moves its Occam factor by O(1), so its probability stays
    below ~e^-8 of the best's. A polish is kept only if it is finite and no worse than the
    refit it started from (a visibility round or the box-bounded fallback can end higher)."""
    polished = [not x for x in local]
    while True:
        top = max(lz)
        todo = [
            i
            for i, f in enumerate(fits)
            if not polished[i]
            and (
                lz[i] >= top - MATERIAL_POLISH_WINDOW
                or (
                    not f.success
                    and (
                        not math.isfinite(lz[i])
                        or lz[i] + _polish_gain(f) >= top - MATERIAL_POLISH_WINDOW
                    )
                )
            )
        ]
        if not todo:
            return
        for i in todo:
            polished[i] = True
            g = refiner.polish(fits[i].params)
            if np.isfinite(g.cost) and g.cost <= fits[i].cost + 1e-9 * max(1.0, abs(fits[i].cost)):
                fits[i], lz[i] = g, log_evidence(g, priors)
            else:
                log.info(
                    "material refit: the polish ended at deviance %.6g above the local refit's "
                    "%.6g; the local refit is kept",
                    g.cost,
                    fits[i].cost,
                )


def _polish_gain(fit) -> float:
    """A generous estimate (a heuristic, not a bound: the decrement is second order and
    local) of what polishing ``fit`` can add to its log evidence: the whole Fisher-scoring
    decrement of its deviance (twice the half that enters ``log Z``) plus
    ``MATERIAL_OCCAM_SLACK`` for the Occam factor moving along a ridge; ``inf`` (always
    polish) when the decrement is unknown."""
    dec = getattr(fit, "decrement", None)
    if dec is None or not math.isfinite(dec):
        return math.inf
    return float(dec) + MATERIAL_OCCAM_SLACK


def _carry_best_optimum(
    refiner, fits: list, lz: list, names: list, materials: dict, part: int, priors
) -> list:
    """Each material's evidence also taken at the best material's optimum, carried over.

    Where the data do not tell the materials apart (a glint whose area and reflectance the
    gain absorbs), each material's likelihood is the others' up to a shift of the gain, and
    the optima form a flat ridge (roughness against the tilt and the gain) on which each
    material's refit stops somewhere of its own. The point Laplace estimate varies along
    that ridge by several units of log evidence at equal deviance: a fused-silica 3U at SNR
    30 came out aluminium 0.94 from four fits within 0.02 in deviance, the other three
    stopped where the gain trades against the roughness (log evidence 3.8 lower). Here, for
    every other material, the Laplace estimate is also evaluated at the best fit's point
    with that material's index and its closed-form Poisson gain (:func:`_gain_profiled`; no
    refit, so it stays on the same stretch of the ridge), and the larger of the two is its
    log evidence: a material the data cannot tell from the best gets the best's estimate,
    one they rule out keeps its own (its carried point has the higher deviance). Returns
    per material ``None`` (its own optimum) or the name of the material whose optimum gave
    the estimate; ``lz`` and ``fits`` are updated in place (a carried estimate's row holds
    the carried point, evaluated without refitting). ``docs/physics/model_evidence.md``."""
    at: list = [None] * len(fits)
    src = int(np.argmax(lz))
    if not np.isfinite(lz[src]):
        return at
    base = fits[src].params
    for k, name in enumerate(names):
        if k == src:
            continue
        p = _gain_profiled(
            refiner, _with(base, n=_set_part(np.asarray(base.n), part, materials[name]))
        )
        try:
            g = refiner.at(p)
        except FloatingPointError:  # a non-finite Jacobian there: no estimate
            continue
        z = log_evidence(g, priors)
        if np.isfinite(z) and z > lz[k]:
            # the row's fit is the point its evidence was taken at (its own refit stopped
            # elsewhere on the ridge, with less evidence): the stages after take it from here
            fits[k], lz[k], at[k] = g, z, names[src]
    return at


def _centred(c: Candidate, p: PhysicalParams, data) -> PhysicalParams:
    """``p`` with the range offset that puts the model's range centroid (summed over channels)
    on the data's: of the offsets ``0`` and ``+-`` the centroids' difference in bin widths,
    the one whose centroid lands nearest (the sign convention is the model's). Both profiles
    lose their floor first (the data's median bin, the model's smallest: a background would
    pull a centroid to the middle of the window) and are clipped at 0. Unchanged without a
    bin width or a positive total."""
    w = c.bin_width
    d = np.asarray(data, np.float64).reshape(-1, np.shape(data)[-1]).sum(0)
    d = np.maximum(d - np.median(d), 0.0)
    if w is None or not d.sum() > 0:
        return p

    def centroid(q: PhysicalParams) -> float:
        mu = np.asarray(_expect(c.model, q, c.model.prepare(q)), np.float64)
        prof = mu.reshape(-1, mu.shape[-1]).sum(0)
        prof = np.maximum(prof - prof.min(), 0.0)
        tot = prof.sum()
        return float(prof @ np.arange(len(prof)) / tot) if tot > 0 else math.nan

    target = float(d @ np.arange(len(d)) / d.sum())
    c0 = centroid(p)
    if not np.isfinite(c0):
        return p
    shift = (target - c0) * w
    best, err = p, abs(c0 - target)
    for sgn in (1.0, -1.0):
        q = _with(p, range_offset=jnp.asarray(float(np.asarray(p.range_offset)) + sgn * shift))
        e = abs(centroid(q) - target)
        if e < err:
            best, err = q, e
    return best


def _set_part(a, k: int, v):
    a = np.array(np.asarray(a))
    a[k] = v
    return a


def _warm_jacobian(refiner: _Refiner, phys: PhysicalParams) -> threading.Thread:
    """Compile ``refiner``'s Jacobian program (the covariance at the end of the refinement)
    in a background thread, started with the screening, whose solver program compiles at the
    same time: XLA compiles the two concurrently (the shipped ``ppr invert`` example's first
    refinement, cache off: 74.7 s serial, 55.8 s with the Jacobian compiled alongside, the
    same CPU seconds; ``bench/bench_background_compile.py``). Best effort: a failure is logged
    and the program compiles when first needed. Join the thread before the program's first
    use (a second compilation of it would start otherwise)."""

    def run() -> None:
        try:
            fisher_at(
                refiner.model,
                refiner.noise,
                refiner.data_j,
                phys,
                refiner.free,
                None,
                refiner.range_scale,
            )
        except Exception as err:  # noqa: BLE001 - a warm-up must not fail the inversion
            log.debug("background compilation of the Jacobian program: %s", err)

    # not a daemon: an interpreter shutting down under a running XLA compilation crashes
    # (exit 139 instead of the error's status); the caller joins it on every path
    thread = threading.Thread(target=run, name="ppr-warm-jacobian", daemon=False)
    thread.start()
    return thread


class _Refiner:
    """The refiner's per-start loop (:func:`inversion.refine`'s programs) for one model."""

    def __init__(self, model, noise, data, free, cfg: InvertConfig, range_scale=0.01):
        self.model, self.noise, self.free, self.cfg = model, noise, tuple(free), cfg
        self.data_j = jnp.asarray(data, jnp.result_type(float))
        self.range_scale = range_scale
        # tolerances are traced: the three solvers share one compiled program
        self.full = _make_solver(cfg.solver, 1e-8, 1e-8)
        self.loose = _make_solver(cfg.solver, cfg.screen_tol, cfg.screen_tol)
        self.local = _make_solver(cfg.solver, 1e-6, 1e-6)

    def start(self, idx, start: PhysicalParams, phys, loose, rounds: int) -> StartSummary:
        """One start: ``loose`` True (screening tolerance), False (full) or ``"local"``
        (1e-6: a refit near an optimum, e.g. with another material's index). The step limit
        is static in the compiled solver: one value (``max_steps``) for every call."""
        solver = self.local if loose == "local" else self.loose if loose else self.full
        return _refine_start(
            self.model,
            self.noise,
            self.data_j,
            self.free,
            self.range_scale,
            idx,
            start,
            phys,
            solver,
            rounds,
            None,
            max_steps=self.cfg.max_steps,
            bounds=BOUNDS,
        )

    def finish(self, best: StartSummary, ordered, t0, method="levenberg_marquardt"):
        return _finish(
            self.model,
            self.noise,
            self.data_j,
            best,
            tuple(ordered),
            self.free,
            self.range_scale,
            t0,
            method if self.cfg.solver == "lm" else self.cfg.solver,
        )

    def polish(self, start: PhysicalParams, rounds: int | None = None, local: bool = False):
        """Refine one start to convergence (``local``: one round at tolerance 1e-6, for a
        start next to an optimum), refit inside the box if needed."""
        t0 = time.perf_counter()
        if local:
            s = self.start(0, start, lift_start(start), "local", 1)
        else:
            s = self.start(0, start, lift_start(start), False, rounds or self.cfg.rounds)
        return self.bounded(self.finish(s, [s], t0), start)

    def bounded(self, fit: RefineResult, start: PhysicalParams) -> RefineResult:
        """``fit``, or should it lie outside the physical box, the box-bounded L-BFGS-B refit
        from ``start`` (:func:`inversion.refine_bounded`; compiled only when needed). The
        solver runs with the box clamped into its parametrisation (``refine(bounds=)``: a
        roughness running off towards the mirror limit, or the index trading against the
        gain along a ridge, stops on the bound), so this is a guard, not a step."""
        if not fit.outside_bounds(BOUNDS):
            return fit
        log.info("refit inside the physical box: %s", "; ".join(fit.outside_bounds(BOUNDS)))
        return refine_bounded(
            self.model,
            np.asarray(self.data_j),
            [_clip_box(start)],
            noise=self.noise,
            bounds=BOUNDS,
            free=self.free,
            rounds=self.cfg.rounds,
            range_scale=self.range_scale,
        )

    def at(self, phys: PhysicalParams, free=None) -> RefineResult:
        """A RefineResult at ``phys`` without refining (Fisher and covariance there)."""
        t0 = time.perf_counter()
        data = self.data_j
        free = self.free if free is None else tuple(free)
        # _finish evaluates the deviance and the Fisher matrix at phys (cost 0: a placeholder)
        s = StartSummary(0, phys, phys, 0.0, True, "successful", "evaluated", 0, 0)
        return _finish(self.model, self.noise, data, s, (s,), free, self.range_scale, t0, "laplace")


# ============================================================================ the workflow
def invert(
    observation,
    candidates,
    *,
    config: InvertConfig | Mapping | None = None,
    bank: TemplateBank | PreparedBank | None = None,
    noise=None,
) -> Inversion:
    """From one observation to shape, attitude, materials and how far to believe them.

    **Arguments:**

    - `observation`: counts ``(channels, bins)`` (an array or an
      :class:`~inversion.Observation`).
    - `candidates`: the candidate shapes' forward models: one model, an
      :class:`Candidate`, a list of them, or a mapping ``name -> model`` (names as in the
      bank's ``names["shapes"]`` when a bank is given).
    - `config`: :class:`InvertConfig` or a mapping validated into one (errors name the
      field and value, before any computation).
    - `bank`: a :class:`~inversion.TemplateBank` or :class:`~inversion.PreparedBank` made
      with the same sensor settings as the models; default: :func:`screening_bank` of the
      candidates over ``config.grid`` x materials x finishes.
    - `noise`: a noise model overriding ``config.likelihood`` (e.g.
      :class:`~inversion.GaussianNoise`).

    **Returns:** :class:`Inversion` (see the module docstring for the stages).

    Raises :class:`ppr.config.ConfigError` (a ``ValueError``) for a bad config and
    ``ValueError`` for data or candidates that do not fit together, all before computing.
    """
    stages = _Stages()
    with stages("validate"):
        if not jax.config.read("jax_enable_x64"):
            # the Fisher matrix, the observability's rank decisions, the goodness of fit and
            # the evidence need float64 (in float32 a glint's Fisher matrix is noise)
            raise ValueError(
                "inversion.invert needs float64: enable x64 before building the models "
                "(jax.config.update('jax_enable_x64', True)); the library never sets it"
            )
        cfg = _as_config(config)
        cands = _as_candidates(candidates)
        data, sensor = _observation_data(observation)
        from_config = noise is None
        noise = _noise_of(cfg) if noise is None else noise
        if not callable(getattr(noise, "variance", None)):
            raise ValueError(
                "noise: expected a noise model (inversion.PoissonCounts, PoissonNoise or "
                f"GaussianNoise), got {type(noise).__name__}"
            )
        prep = bank if isinstance(bank, PreparedBank) else None
        bank_ = prep.bank if prep is not None else bank
        if bank_ is not None and not isinstance(bank_, TemplateBank):
            raise ValueError(
                f"bank: expected an inversion.TemplateBank or PreparedBank, got "
                f"{type(bank).__name__}"
            )
        by_name = {c.name: c for c in cands}
        if bank_ is not None:
            missing = [s for s in bank_.names["shapes"] if s not in by_name]
            if missing:
                raise ValueError(
                    f"bank shape {missing[0]!r} has no candidate model (candidates: "
                    f"{', '.join(by_name)}); pass a mapping name -> model with the bank's names"
                )
            extra = [c for c in by_name if c not in bank_.names["shapes"]]
            if extra:
                raise ValueError(
                    f"candidate {extra[0]!r} is not a shape of the bank (its shapes: "
                    f"{', '.join(bank_.names['shapes'])})"
                )
            if bank_.n_channels != data.shape[0] or bank_.n_bins != data.shape[1]:
                raise ValueError(
                    f"observation: shape {data.shape} (channels, bins) does not match the "
                    f"bank's ({bank_.n_channels}, {bank_.n_bins})"
                )
        for c in cands:
            shape = _expected_shape(c.model)
            if shape is not None:
                check_observation(data, shape, f"observation (candidate {c.name!r})")
        _check_same_sensor(cands, bank_)
        for c in cands:
            proj = getattr(getattr(c.model, "pure_model", None), "projection", None)
            if proj is not None and np.asarray(proj).dtype != np.float64:
                raise ValueError(
                    f"candidate {c.name!r} holds {np.asarray(proj).dtype} arrays (built before "
                    "x64 was enabled?): build the models after "
                    "jax.config.update('jax_enable_x64', True)"
                )
        if hasattr(noise, "check_data"):
            try:
                noise.check_data(data, "observation")
            except ValueError as err:
                if not from_config:
                    raise
                # the noise came from the config: name its field, not the library's classes
                msg = str(err).split("; use ")[0]
                raise ValueError(
                    f"{msg}; likelihood = {cfg.likelihood!r} takes photo-counts: set "
                    'likelihood = "gaussian" (variance mu + 1) for background-subtracted or '
                    "scaled data"
                ) from None
        wavelength = cands[0].wavelength
        materials = _resolve_materials(cfg, bank_, wavelength)
        if not materials:
            raise ValueError(
                f"materials: the library has no material at wavelength {wavelength:g} m; give "
                "materials = [{name, n_real, n_imag}, ...]"
            )
        finishes = dict(DEFAULT_FINISHES if cfg.finishes is None else cfg.finishes)
        if bank_ is None:
            _check_bank_fits(cfg, cands, len(materials), len(finishes))
        free_all = tuple(g for g in GROUPS if g in cfg.free)
        free_fixed = tuple(g for g in free_all if g != "n")
        if not free_fixed:
            raise ValueError(
                "free: at least one group besides n (the index is weighed per material)"
            )
        priors = cfg.mcmc.priors if cfg.mcmc is not None else PriorConfig()

    # ---------------------------------------------------------------- classification
    with stages("classify"):
        if bank_ is None:
            bank_ = screening_bank(
                cands,
                materials,
                finishes,
                grid=cfg.grid,
                symmetry=cfg.symmetry,
                progress=cfg.progress,
            )
        if prep is None:
            prep = prepare(bank_)
        obs = Observation(data=data, sensor=sensor) if sensor else data
        cls = classify(prep, obs, k=len(bank_), noise=noise, threshold=cfg.mismatch_p)
        cols = _pick_rows(cls, bank_, cfg.top_k, cfg.per_shape)
        used_cols = set(cols)
        bank_mats = [materials.get(n) for n in bank_.names["materials"]]
        for i, n in enumerate(bank_mats):
            if n is None:
                nm = bank_.names["materials"][i]
                bank_mats[i] = complex(np.asarray(ppr.load_material(nm, wavelength).n))

        # starts: each picked attitude with every finish of the bank (the cosine score
        # cannot tell a broad lobe from a narrow glint of the same face, the deviance can),
        # the gain matching the total counts; a start whose gain lies outside the physical
        # range (a glint too faint for any real sensor) is dropped unless it is all there is
        def seed_start(c, p: PhysicalParams, aux=None) -> PhysicalParams:
            """``p`` with the gain matching the total counts and, for a monostatic sensor,
            the best roll about the line of sight: the template grid's roll is coarse, and
            the deviance is multimodal in it (five model calls: inversion._roll; the turn
            keeps the visibility)."""
            aux = c.model.prepare(p) if aux is None else aux
            total = float(_expect(c.model, p, aux).sum())
            gain = float(max(data.sum(), 1.0) / max(total, 1e-300))
            p = _with(p, gain=jnp.asarray(min(max(gain, 1e-300), 1e300), p.m.dtype))
            los_c = _roll_los(c.model)
            if los_c is not None:
                sc = roll_scan(
                    c.model,
                    data,
                    p,
                    noise=noise,
                    los=los_c,
                    monostatic=True,
                    aux=aux,
                    n_grid=ROLL_GRID,
                )
                if sc.minima[0] != 0:
                    p = sc.params(p, int(sc.minima[0]))
            return p

        def make_starts(cols, have=()) -> dict[str, list[PhysicalParams]]:
            starts: dict[str, list[PhysicalParams]] = {}
            spare: dict[str, list[tuple[float, PhysicalParams]]] = {}
            for col in cols:
                row = int(cls.index[0, col])
                c = by_name[bank_.names["shapes"][bank_.shape_id[row]]]
                k = c.n_materials
                n = bank_mats[bank_.material_id[row]]
                w = c.bin_width
                off = 0.0 if w is None else float(cls.shift_refined[0, col]) * w
                aux = None
                for m in bank_.names["finish_m"]:
                    p = PhysicalParams(
                        bank_.quat[row], [m] * k, [n] * k, range_offset=off, gain=1.0
                    )
                    if aux is None or getattr(c.model, "multibounce", False):
                        aux = c.model.prepare(p)
                    p = seed_start(c, p, aux)
                    gain = float(np.asarray(p.gain))
                    if BOUNDS.gain[0] <= gain <= BOUNDS.gain[1]:
                        starts.setdefault(c.name, []).append(p)
                    else:
                        spare.setdefault(c.name, []).append((abs(math.log(gain / 1e6)), p))
            for name, sp in spare.items():
                if name not in starts and name not in have:
                    starts[name] = [_clip_box(min(sp, key=lambda x: x[0])[1])]
            return starts

        starts = make_starts(cols)

        def face_on_starts() -> dict[str, list[PhysicalParams]]:
            """Each candidate's largest sides face-on (:func:`face_on_attitudes`), at the
            glossiest finish and the material of the shape's best template, the range offset
            matching the data's range centroid, the gain their total, the roll scanned."""
            out: dict[str, list[PhysicalParams]] = {}
            if cfg.face_on == 0:
                return out
            m = max(bank_.names["finish_m"])
            for c in cands:
                mesh = c.mesh if c.mesh is not None else c.symmetry
                if not isinstance(mesh, ppr.Mesh):
                    continue
                sym = c.exact_symmetry(cfg.symmetry)
                los_c = line_of_sight_of(c.model)
                los_c = np.array([0.0, 0.0, 1.0]) if los_c is None else los_c
                rows = [int(cls.index[0, j]) for j in _ranked_rows(cls, bank_)]
                rows = [r for r in rows if bank_.names["shapes"][bank_.shape_id[r]] == c.name]
                n = bank_mats[bank_.material_id[rows[0]]] if rows else bank_mats[0]
                k = c.n_materials
                for q in face_on_attitudes(
                    mesh,
                    los_c,
                    symmetry=sym,
                    max_classes=cfg.face_on,
                ):
                    # the roll about the line of sight: scanned by seed_start for a monostatic
                    # sensor, else ROLL_STARTS turns over the half circle
                    turns = (
                        [0.0]
                        if _roll_los(c.model) is not None
                        else [j * math.pi / ROLL_STARTS for j in range(ROLL_STARTS)]
                    )
                    for a in turns:
                        qa = quat_multiply_host(quat_from_axis_angle(los_c, a), q)
                        p = PhysicalParams(qa, [m] * k, [n] * k, range_offset=0.0, gain=1.0)
                        p = seed_start(c, _centred(c, p, data))
                        if BOUNDS.gain[0] <= float(np.asarray(p.gain)) <= BOUNDS.gain[1]:
                            out.setdefault(c.name, []).append(p)
            return out

    # ---------------------------------------------------------------- screened refinement
    with stages("refine"):
        screened: dict[str, list[StartSummary]] = {}
        refiners = {}
        rolled: set[str] = set()

        def screen(starts: dict[str, list[PhysicalParams]], desc: str) -> None:
            bar = _Bar(cfg.progress, sum(len(v) for v in starts.values()), desc)
            for name, sts in starts.items():
                if name not in refiners:
                    refiners[name] = _Refiner(by_name[name].model, noise, data, free_fixed, cfg)
                r = refiners[name]
                out = screened.setdefault(name, [])
                for s_ in sts:
                    out.append(r.start(len(out), s_, lift_start(s_), True, 1))
                    bar.step()
                out.sort(key=lambda x: x.cost)
                roll_rescreen(name)
            bar.close()

        def roll_rescreen(name: str) -> None:
            r = refiners[name]
            out = screened[name]
            los_c = _roll_los(r.model)
            best = out[0]
            key = (name, best.index)
            if los_c is None or not np.isfinite(best.cost) or key in rolled:
                return
            rolled.add(key)
            # the screened optimum may sit in a side basin of the roll about the line of
            # sight (a basin is about +-45 deg wide; the roll is coupled to m and n, so a
            # scan at the screened parameters can miss the right one): rescreen from its
            # best roll when that is lower and from ROLL_STARTS evenly spaced turns
            sc = roll_scan(
                r.model,
                data,
                best.params,
                noise=noise,
                los=los_c,
                monostatic=True,
                n_grid=ROLL_GRID,
            )
            i = int(sc.minima[0])
            turns = [k * 180.0 / ROLL_STARTS for k in range(1, ROLL_STARTS)]
            if i != 0 and sc.deviance[i] < sc.deviance[0] - 1.0:
                turns.insert(0, float(sc.angles_deg[i]))
            for a in turns:
                j = int(round(a / 180.0 * ROLL_GRID)) % ROLL_GRID
                p = sc.params(best.params, j)
                out.append(r.start(len(out), p, lift_start(p), True, 1))
            out.sort(key=lambda x: x.cost)
            rolled.add((name, out[0].index))  # a rolled start is not rolled again

        def screened_mismatch() -> bool:
            """The best screened start's goodness of fit (not yet polished: the test counts
            the fitted parameters, a conservative variance) is a model mismatch."""
            name = min(screened, key=lambda n: screened[n][0].cost)
            best = screened[name][0]
            if not np.isfinite(best.cost):
                return True
            model_b = by_name[name].model
            mu = _expect(model_b, best.params, model_b.prepare(best.params))
            n_par = Parametrisation(best.params, free_fixed).size
            g = goodness_of_fit(
                data, mu, noise, n_params=n_par, phys=best.params, threshold=cfg.mismatch_p
            )
            return bool(g.model_mismatch)

        # the best classified shape's covariance program compiles while the screening runs
        first = next(iter(starts))
        refiners[first] = _Refiner(by_name[first].model, noise, data, free_fixed, cfg)
        warm = _warm_jacobian(refiners[first], starts[first][0])
        try:
            screen(starts, "screening starts")
            face = face_on_starts()
            if face:
                screen(face, "face-on starts")
            n_batches = 1
            ranked = _ranked_rows(cls, bank_)
            while n_batches <= cfg.escalate and screened_mismatch():
                more = [c for c in ranked if c not in used_cols][: cfg.top_k]
                if not more:
                    break
                used_cols.update(more)
                log.info(
                    "best screened fit is a model mismatch: screening %d more templates",
                    len(more),
                )
                screen(make_starts(more, have=set(screened)), f"more starts ({n_batches})")
                n_batches += 1
        finally:
            warm.join()  # before the polish's covariance uses the program, and on any error
        n_templates = len(used_cols)
        best_screen = min(v[0].cost for v in screened.values())
        if not np.isfinite(best_screen):
            raise RuntimeError(
                "invert: every start failed in screening (non-finite deviance); "
                + "; ".join(f"{n}: {v[0].message}" for n, v in screened.items())
            )
        shape_fits = []
        for c in cands:
            if c.name not in screened:
                continue
            sc = screened[c.name]
            fit = None
            if sc[0].cost <= cfg.polish_factor * best_screen + cfg.polish_abs:
                t0 = time.perf_counter()
                s = refiners[c.name].start(0, sc[0].start, sc[0].params, False, cfg.rounds)
                s = dataclasses.replace(
                    s, n_steps=s.n_steps + sc[0].n_steps, n_rounds=s.n_rounds + sc[0].n_rounds
                )
                fit = refiners[c.name].finish(s, [s, *sc[1:]], t0)
                fit = refiners[c.name].bounded(fit, sc[0].start)
            shape_fits.append((c.name, len(sc), sc[0].cost, fit))
        lz = [log_evidence(f, priors) if f is not None else -math.inf for *_, f in shape_fits]
        p_shape = _probabilities(lz)
        shapes = tuple(
            ShapeFit(n, ns, d, f, z, float(p))
            for (n, ns, d, f), z, p in zip(shape_fits, lz, p_shape, strict=True)
        )
        best_shape = max(shapes, key=lambda s: (s.probability, -(s.fit.cost if s.fit else np.inf)))
        cand = by_name[best_shape.name]
        model = cand.model
        refiner = refiners[cand.name]
        fit = best_shape.fit

    # ---------------------------------------------------------------- materials
    with stages("materials"):
        k_parts = cand.n_materials
        tables, fit = _material_tables(refiner, fit, k_parts, materials, priors, cfg.progress)
        # a shape the data do not rule out weighs in its own table (single-slot shapes,
        # whose one slot is the same thing on both): P(material) = sum over shapes of
        # P(shape) P(material | shape), the best shape's table otherwise
        others = [
            s
            for s in shapes
            if s.name != cand.name
            and s.fit is not None
            and s.probability >= cfg.ambiguity
            and by_name[s.name].n_materials == 1
        ]
        if others and k_parts == 1:
            tables = _shape_averaged(
                tables,
                best_shape.probability,
                [
                    (
                        s.probability,
                        _material_tables(
                            refiners[s.name], s.fit, 1, materials, priors, cfg.progress
                        )[0],
                    )
                    for s in others
                ],
            )

    # ---------------------------------------------------------------- modes
    with stages("modes"):
        los_world = line_of_sight_of(model)
        los_world = np.array([0.0, 0.0, 1.0]) if los_world is None else los_world
        half_turn_exact, world_normal = _sensor_geometry(model, los_world)
        sym = cand.mode_symmetry(cfg.symmetry, cfg.near_tol)
        from ._modes import candidate_modes

        geometry = dict(
            mirror=cfg.mirror,
            near=cfg.near_tol > 0,
            half_turn_exact=half_turn_exact,
            los=tuple(los_world),
            world_normal=tuple(world_normal),
            min_separation_deg=cfg.min_separation_deg,
        )
        cands_m = candidate_modes(np.asarray(fit.params.quaternion, np.float64), sym, **geometry)
        cands_m += _roll_modes(model, data, fit, noise, sym, cands_m, half_turn_exact, cfg)
        cands_m += _other_optima(refiner, data, fit, sym, cands_m, half_turn_exact, cfg)
        chk = mode_check(
            model,
            data,
            fit,
            sym,
            noise=noise,
            **geometry,
            max_steps=cfg.max_steps,
            rounds=2,
            solver=cfg.solver,
            bounds=BOUNDS,
            modes=cands_m,
        )
        distinct = [m for m in chk.modes if m.duplicate_of is None and np.isfinite(m.fit.cost)]
        lz = [log_evidence(m.fit, priors) for m in distinct]
        w = _probabilities(lz)
        order = np.argsort(-w, kind="stable")
        distinct = [distinct[i] for i in order]
        lz = [lz[i] for i in order]
        w = w[order]
        distinct, lz, w = _merge_roll_ridge(distinct, lz, w, cand, cfg, los_world, data, noise)
        best_mode_fit = distinct[0].fit
        base_cost = best_mode_fit.cost
        q_best = np.asarray(best_mode_fit.params.unit_quaternion(), np.float64)
        from ._modes import mode_separation_deg

        mode_rows = []
        for m, z, wt in zip(distinct, lz, w, strict=True):
            q = np.asarray(m.fit.params.unit_quaternion(), np.float64)
            mode_rows.append(
                dict(
                    label=m.label if m.label != "fit" else "refined fit",
                    kind=m.kind,
                    fit=m.fit,
                    delta_deviance=float(m.fit.cost - base_cost),
                    separation_deg=mode_separation_deg(
                        q_best, q, sym, half_turn_exact=half_turn_exact, los=tuple(los_world)
                    ),
                    los_separation_deg=float(
                        line_of_sight_error_deg(
                            q_best, q, cand.exact_symmetry(cfg.symmetry), los=los_world
                        )[0]
                    ),
                    log_evidence=z,
                    weight=float(wt),
                )
            )
        fit = best_mode_fit

    # ---------------------------------------------------------------- continuous index
    index_fit = None
    with stages("index"):
        if "n" in free_all:
            index_fit = _index_fit(refiner, fit, free_all, cfg, cfg.index_steps)
        final = fit
        if index_fit is not None and np.isfinite(index_fit.cost) and index_fit.cost <= fit.cost:
            final = index_fit
        # the index per part: determined by the data, inside the physical box
        index = _index_estimates(index_fit, k_parts, los_world)

    # ---------------------------------------------------------------- checks
    with stages("check"):
        gof = fit_goodness_of_fit(model, data, final, noise, threshold=cfg.mismatch_p)
        ob = observability(final, line_of_sight=los_world)
        expected = _expect(model, final.params, model.prepare(final.params))

    # ---------------------------------------------------------------- posterior sampling
    mode_results = []
    mcmc_reasons = []
    with stages("sample"):
        # with the index free, the chains sample it over the library materials, jumping
        # between the per-material optima of the material stage (inversion._mcmc._LibraryIndex)
        lib_n = lib_fits = None
        if "n" in free_all:
            names = list(materials)
            lib_n = [materials[nm] for nm in names]
            lib_fits = [
                [next((mf.fit.params for mf in t if mf.name == nm), None) for nm in names]
                for t in tables
            ]
        n_sampled = 0
        for j, row in enumerate(mode_rows):
            post = diag = None
            conv = None
            warns: tuple[str, ...] = ()
            want = (
                cfg.mcmc is not None
                and row["weight"] >= cfg.mcmc_min_weight
                and n_sampled < cfg.max_sampled_modes
            )
            if want:
                start = final if j == 0 else row["fit"]
                if start.parametrisation.free != free_all:
                    start = refiner.at(start.params, free_all)
                mode_fits = lib_fits
                if lib_fits is not None:
                    mode_fits = _mode_material_optima(refiner, start.params, lib_fits, lib_n)
                try:
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always", ChainTooShortWarning)
                        post = sample_posterior(
                            model,
                            data,
                            start,
                            config=_sampler_progress(cfg),
                            noise=noise,
                            free=free_all,
                            progress_desc=f"MCMC mode {j} ({row['label']})",
                            materials=lib_n,
                            material_fits=mode_fits,
                        )
                    warns = tuple(str(x.message) for x in caught)
                    diag = post.diagnostics()
                    library = None
                    if lib_n is not None and cfg.mcmc.sampler.index == "library":
                        library = dict(zip(names, lib_n, strict=True))
                    judged = _judged_rhat(post, diag, los_world, library)
                    rh = {k: v for k, v in judged.items() if v is not None}
                    worst = max(rh, key=rh.get, default=None)
                    max_rhat = math.inf if worst is None else rh[worst]
                    conv = bool(post.converged and max_rhat <= cfg.rhat_max)
                    if not conv:
                        why = []
                        if not post.converged:
                            why.append("chain shorter than autocorr_tol x tau")
                        if not max_rhat <= cfg.rhat_max:
                            if worst is None:
                                why.append("no R-hat could be computed")
                            else:
                                txt = (
                                    f"{max_rhat:.3g}"
                                    if max_rhat < 1e3
                                    else "> 1000: the walkers never mix"
                                )
                                why.append(f"max R-hat {txt} ({worst}) > {cfg.rhat_max:g}")
                        mcmc_reasons.append(
                            f"posterior of mode {j} ({row['label']}) not converged: "
                            + ", ".join(why)
                        )
                    n_sampled += 1
                except ValueError as err:
                    mcmc_reasons.append(f"posterior of mode {j} not sampled: {err}")
                    post = None
            mode_results.append(
                ModeResult(
                    **row,
                    posterior=post,
                    posterior_converged=conv,
                    posterior_warnings=warns,
                    diagnostics=diag,
                )
            )
        if final is not fit and mode_results:
            # the best mode's fit is reported with the index free when that fits better
            mode_results[0] = dataclasses.replace(mode_results[0], fit=final)

    # ---------------------------------------------------------------- status
    reasons = []
    if gof.model_mismatch:
        n_starts = len(screened.get(cand.name, ()))
        reasons.append(
            f"model mismatch: p = {gof.p_value:.3g} < {gof.threshold:g} ({gof.strongest.name}: "
            f"z = {gof.strongest.z:+.1f}): no "
            f"fit of shape {cand.name!r} from {n_starts} starts ({n_templates} template "
            "attitudes) explains the data: a target unlike the candidates, or an optimum the "
            "search missed (more templates: top_k, escalate, grid.size)"
        )
    if gof.underdispersed:
        reasons.append(
            f"noise model: the data scatter less than the likelihood allows (z = {gof.z:+.1f}, "
            f"lower tail p = {gof.lower_p_value:.3g}): counts averaged, scaled or "
            "background-subtracted? the uncertainties rest on the likelihood (likelihood, "
            "background, or GaussianNoise with the data's own variance)"
        )
    converged = bool(final.success)
    if not converged:
        reasons.append(f"solver did not converge ({final.result}: {final.message})")
    other_shapes = [s for s in shapes if s.name != cand.name and s.probability > cfg.ambiguity]
    if other_shapes:
        reasons.append(
            "shape not resolved: "
            + ", ".join(f"{s.name} probability {s.probability:.2g}" for s in other_shapes)
        )
    amb = [m for m in mode_results[1:] if m.weight > cfg.ambiguity]
    if amb:
        reasons.append(
            "attitude modes not resolved: "
            + ", ".join(
                f"{m.label} weight {m.weight:.2g} (line of sight {m.los_separation_deg:.2g} deg "
                "away)"
                for m in amb
            )
        )
    reasons += mcmc_reasons
    from ppr.outputs import provenance

    prov = {
        **provenance(cfg.model_dump(mode="json")),  # versions, command line, time, config
        "noise": repr(noise),
        "candidates": [c.name for c in cands],
        "materials": {k: [v.real, v.imag] for k, v in materials.items()},
        "finishes": finishes,
        "bank": {"n_templates": len(bank_), "resolution_deg": list(bank_.resolution_deg)},
        "_exact_symmetry": cand.exact_symmetry(cfg.symmetry),
    }
    stages.timings["total"] = time.perf_counter() - stages.t0
    result = Inversion(
        shape=cand.name,
        shapes=shapes,
        fit=final,
        materials=tuple(tuple(t) for t in tables),
        index=index,
        modes=tuple(mode_results),
        goodness_of_fit=gof,
        observability=ob,
        converged=converged,
        reliable=not reasons,
        reasons=tuple(reasons),
        timings=dict(stages.timings),
        provenance=prov,
        classification=cls,
        data=data,
        expected=expected,
        line_of_sight_world=np.asarray(los_world, np.float64),
        sampled=cfg.mcmc is not None,
    )
    log.info("invert: %s", "reliable" if result.reliable else "NOT reliable: " + "; ".join(reasons))
    return result


def _pick_rows(cls: Classification, bank: TemplateBank, top_k: int, per_shape: int) -> list[int]:
    """Columns of the classification to start from: the best `top_k` *distinct* templates
    (one per shape and attitude: the materials and finishes of one attitude are one start,
    the material stage weighs the materials) and the best `per_shape` distinct attitudes of
    every shape (the cosine rank is not a likelihood: a shape whose signature changes fast
    with attitude ranks low at the grid's resolution and can still fit best)."""
    idx = cls.index[0]
    key = (
        np.asarray(bank.shape_id)[idx].astype(np.int64) * (int(np.max(bank.attitude_id)) + 1)
        + np.asarray(bank.attitude_id)[idx]
    )
    _, first = np.unique(key, return_index=True)
    first = np.sort(first)  # rank order, one column per (shape, attitude)
    cols = list(first[:top_k])
    sid = np.asarray(bank.shape_id)[idx[first]]
    for s in np.unique(bank.shape_id):
        cols += [int(c) for c in first[sid == s][:per_shape] if c not in cols]
    return sorted(int(c) for c in cols)


def _ranked_rows(cls: Classification, bank: TemplateBank) -> list[int]:
    """Every distinct (shape, attitude) column of the classification, best rank first (the
    order :func:`_pick_rows` takes its `top_k` from)."""
    idx = cls.index[0]
    key = (
        np.asarray(bank.shape_id)[idx].astype(np.int64) * (int(np.max(bank.attitude_id)) + 1)
        + np.asarray(bank.attitude_id)[idx]
    )
    _, first = np.unique(key, return_index=True)
    return [int(c) for c in np.sort(first)]


def _judged_rhat(post, diag, los_world, library=None) -> dict[str, float | None]:
    """The R-hat values the ``rhat_max`` verdict judges, by label: every sampled parameter,
    except
    - with the index sampled over the library materials (``library``: name -> index), the
      ``n_re``/``n_im`` columns (discrete values), replaced by the R-hat of each material's
      indicator per part (``material[k] = name``, for the materials holding at least 5 % of
      the draws): walkers that do not share the materials show there;
    - with the attitude free, ``rot_x/y/z``, replaced by the attitude modulo the half turn
      about the line of sight (:func:`inversion.attitude_rhat`: the body-frame line of
      sight and the doubled roll): the half turn is a mode of its own, each walker samples
      its half-circle of roll, and the rotation-vector components jump by the half turn
      between walkers in the two halves (measured on the held-out bench: ``rot_z`` was the
      worst R-hat of 36 of 62 chains above 1.1).
    """
    out = {}
    for lab, d in diag.items():
        name = lab.split(" [")[0].split("[")[0]
        if library is not None and name in ("n_re", "n_im"):
            continue
        if name in ("rot_x", "rot_y", "rot_z"):
            continue
        out[lab] = d["r_hat"]
    out.update(attitude_rhat(post, los_world))
    if library is not None:
        out.update(_material_rhat(post, library))
    return out


def _material_rhat(post, library: dict) -> dict[str, float | None]:
    """ArviZ R-hat (walkers as chains, kept draws) of the indicator of each library material
    holding >= 5 % of a part's draws."""
    az = _arviz()
    names = list(library)
    n_lib = np.asarray([library[nm] for nm in names], np.complex128)
    kept = post.physical_chain[post.burn_in :: post.thin]  # (draw, walker, P)
    out = {}
    for k, lab in enumerate(post.labels):
        if not lab.startswith("n_re["):
            continue
        slot = lab[len("n_re[") : lab.index("]")]
        j_im = post.labels.index(f"n_im[{slot}]")
        n = kept[..., k] + 1j * kept[..., j_im]
        which = np.argmin(np.abs(n[..., None] - n_lib), axis=-1)  # (draw, walker)
        for m, nm in enumerate(names):
            ind = (which == m).astype(np.float64)
            if ind.mean() < 0.05:
                continue
            if np.all(ind.min(axis=0) == ind.max(axis=0)):
                # no walker ever changes material: they agree (1) or never mix (inf; ArviZ
                # gives NaN or a rounding-level 1e15 here)
                r = 1.0 if ind.min() == ind.max() else math.inf
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    r = float(az.rhat(np.ascontiguousarray(ind.T)))
                r = r if math.isfinite(r) else math.inf
            out[f"material[{slot}] = {nm}"] = r
    return out


def _sampler_progress(cfg: InvertConfig) -> MCMCConfig:
    mc = cfg.mcmc
    if mc.sampler.progress == cfg.progress:
        return mc
    return mc.model_copy(
        update={"sampler": mc.sampler.model_copy(update={"progress": cfg.progress})}
    )


# photo-counts above 2^53 per bin are not integers in float64, and no detector records them:
# such data are in other units (rescale them) and overflow the deviance's Jacobian products
MAX_COUNTS = 2.0**53


def _observation_data(observation) -> tuple[np.ndarray, str]:
    """The observation as float64 ``(channels, bins)`` and its sensor tag, validated: real
    numbers (no strings, booleans or complex numbers, whose imaginary part would be lost),
    finite, at most :data:`MAX_COUNTS` in magnitude and not all zero (no signal: nothing to
    fit). The same checks for an :class:`~inversion.Observation`'s data."""
    sensor = ""
    if isinstance(observation, Observation):
        observation, sensor = observation.data, observation.sensor
    try:
        arr = np.asarray(observation)
    except ValueError as err:  # ragged nested lists
        raise ValueError(f"observation: not a (channels, bins) array ({err})") from None
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"observation: expected a numeric array, got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise ValueError(
            f"observation: got complex dtype {arr.dtype}; expected real counts (the imaginary "
            "part would be lost)"
        )
    if arr.ndim != 2:
        raise ValueError(f"observation: expected (channels, bins), got shape {arr.shape}")
    arr = arr.astype(np.float64)
    bad = first_nonfinite(arr)
    if bad is not None:
        count, first, value = bad
        raise ValueError(
            f"observation: {count} non-finite value(s) (NaN/inf), first at index "
            f"{first} (channel, bin) = {value}"
        )
    big = np.abs(arr) > MAX_COUNTS
    if big.any():
        first = tuple(int(i) for i in np.argwhere(big)[0])
        raise ValueError(
            f"observation: value {float(arr[first]):g} at index {first} (channel, bin) is above "
            f"{MAX_COUNTS:g} (2^53) counts in magnitude; photo-counts that large are not exact "
            "in float64 (rescale the data)"
        )
    if arr.size and not np.any(arr):
        raise ValueError(
            f"observation: all {arr.size} values are 0 (no signal): the data constrain no "
            "shape, attitude or material"
        )
    return arr, sensor


def _expected_shape(model) -> tuple[int, int] | None:
    c, b = getattr(model, "n_channels", None), getattr(model, "n_bins", None)
    if c is None or b is None:
        return None
    return (int(c), int(b))


# the roll about the line of sight (inversion._roll): grid of the scans (0.5 deg over the
# 180 deg period), how many of its other minima are refit as modes and how far above the
# fit's deviance a minimum may lie (before the refit, which only lowers it) to be one
ROLL_GRID = 360
# turns about the line of sight rescreened from the best screened start of each shape
# (0, 45, 90, 135 deg: one within 22.5 deg of any roll, modulo the half turn)
ROLL_STARTS = 4
# sweeps of the material stage over the parts (stops early when no part changed)
MATERIAL_SWEEPS = 2
# log-evidence window of the material stage (_polish_material_fits): a library material's
# converged local refit within it of the best is polished to convergence, one further behind
# is not
MATERIAL_POLISH_WINDOW = 10.0
# what the Occam factor of an unconverged material refit may move by when polished (a ridge:
# up to ~4 units measured); with its deviance decrement, the bound of _polish_gain
MATERIAL_OCCAM_SLACK = 5.0
ROLL_MODES = 3
ROLL_MODE_DELTA = 50.0
# the rise of the deviance between the fit's roll and another minimum that makes it a mode
ROLL_BARRIER = 2.0


def _roll_los(model) -> np.ndarray | None:
    """The world line of sight when the roll scan is exact (a monostatic ppr sensor: the turn
    about it changes only the polarization), else None (no scan)."""
    sensor = getattr(getattr(model, "pure_model", model), "sensor", None)
    if sensor is None or not bool(getattr(sensor, "monostatic", False)):
        return None
    los = line_of_sight_of(model)
    return None if los is None else np.asarray(los, np.float64)


def _roll_modes(model, data, fit, noise, sym, kept, half_turn_exact, cfg) -> list:
    """The other minima of the deviance in the roll about the line of sight at ``fit``
    (:func:`inversion.roll_scan`), as modes to refit: at most ``ROLL_MODES``, each within
    ``ROLL_MODE_DELTA`` (or a quarter of the deviance) of the fit's, behind a barrier of at
    least ``ROLL_BARRIER`` on both ways round, and farther than the mode separation from
    every candidate already kept (modulo the exact equivalences)."""
    from ._modes import Mode, mode_separation_deg

    los = _roll_los(model)
    if los is None or not np.isfinite(fit.cost):
        return []
    sc = roll_scan(model, data, fit.params, noise=noise, los=los, monostatic=True, n_grid=ROLL_GRID)
    limit = sc.deviance[0] + max(ROLL_MODE_DELTA, 0.25 * sc.deviance[0])
    quats = [np.asarray(m.quaternion, np.float64) for m in kept]
    out = []
    sep_kw = {"half_turn_exact": half_turn_exact, "los": tuple(los)}
    d = sc.deviance
    for i in sc.minima:
        if len(out) >= ROLL_MODES or d[i] > limit:
            break
        # a separate basin only: the scan must rise by ROLL_BARRIER above both ends on
        # either way round (a flat or nearly flat scan is an unobservable roll, a continuous
        # direction that observability() names, not a set of discrete modes)
        i = int(i)
        if i == 0:
            continue
        barrier = min(d[: i + 1].max(), np.concatenate([d[i:], d[:1]]).max())
        if barrier - max(d[0], d[i]) < ROLL_BARRIER:
            continue
        a = float(sc.angles_deg[i])
        q = np.asarray(sc.params(fit.params, int(i)).quaternion, np.float64)
        sep = min(mode_separation_deg(qk, q, sym, **sep_kw) for qk in quats)
        if sep <= max(cfg.min_separation_deg, 2.0):
            continue
        out.append(
            Mode(
                quaternion=q,
                label=f"roll {a:.1f} deg about the line of sight",
                kind="roll",
                exact=False,
                range_shift=0.0,
                body=np.eye(3),
                world=f"roll {a:.1f} deg",
                residual=0.0,
            )
        )
        quats.append(q)
    return out


# other optima (_other_optima): at most this many refit as modes, those whose screened
# deviance is within OTHER_DELTA of the fit's
OTHER_MODES = 2
OTHER_DELTA = 25.0
# ... and whose line of sight is farther than this from every kept mode's (modulo the mesh's
# exact rotations), unless they fit better than the fit by more than OTHER_DELTA
OTHER_LOS_DEG = 5.0


def _other_optima(refiner, data, fit, sym, kept, half_turn_exact, cfg) -> list:
    """Other optima of the deviance far from the fit's attitude, as modes to refit.

    The template screening ends in one basin per start; data that two attitudes explain
    (with other materials per part, say: two copolarized channels of a body with three
    materials) have a second basin that a coarse template grid can miss entirely, and the
    fit's Cramer-Rao bound then states a confident answer. This search looks for it at the
    fit's materials and roughness: for each of ``cfg.other_directions`` body directions (a
    Fibonacci sphere) the attitude that points it along the line of sight, its best roll and
    gain (:func:`inversion.roll_scan`: exact on a fine grid for a monostatic sensor, 8 rolls
    otherwise); the ``cfg.other_starts`` lowest deviances are screened (one loose round of
    the refiner's solver). An optimum is kept when its screened deviance is within
    ``OTHER_DELTA`` of the fit's, its attitude is farther than the mode separation from every
    kept candidate (modulo the exact equivalences), and either its line of sight is farther
    than ``OTHER_LOS_DEG`` from every kept candidate's (modulo the mesh's exact rotations) or
    it fits better than the fit by more than ``OTHER_DELTA`` (a kept line of sight with
    another roll and an equal deviance is the unobservable roll, or a roll mode, not another
    optimum; a much better one is the optimum the fit missed). At most ``OTHER_MODES``,
    lowest first, are returned as modes ``"other optimum"`` that start from their own
    screened parameters; the mode check refits them and their evidence weighs them."""
    from ._modes import Mode, mode_separation_deg

    if cfg.other_directions == 0 or not np.isfinite(fit.cost):
        return []
    model = refiner.model
    sym = as_symmetry(sym)
    los = line_of_sight_of(model)
    los = np.array([0.0, 0.0, 1.0]) if los is None else np.asarray(los, np.float64)
    p0 = fit.params
    scanned = []
    for d in fibonacci_sphere(cfg.other_directions):
        # the attitude (body -> world) taking the body direction d onto the line of sight
        rot, _ = Rotation.align_vectors(los[None], d[None])
        x, y, z, w = rot.as_quat()  # scipy: scalar last
        p = _with(p0, quaternion=jnp.asarray([w, x, y, z], p0.m.dtype))
        sc = roll_scan(model, data, p, noise=refiner.noise, los=los, n_direct=8)
        i = int(sc.minima[0])
        if np.isfinite(sc.deviance[i]):
            scanned.append((float(sc.deviance[i]), sc.params(p, i)))
    scanned.sort(key=lambda t: t[0])
    # the proper rotations the mesh has exactly: their lines of sight are one
    exact = sym.quaternions()[sym.residuals[sym.determinants > 0] <= 1e-6]
    sep_kw = {"half_turn_exact": half_turn_exact, "los": tuple(los)}
    quats = [np.asarray(m.quaternion, np.float64) for m in kept]
    found = []
    for _, p in scanned[: cfg.other_starts]:
        s = refiner.start(0, p, lift_start(p), True, 1)
        if not np.isfinite(s.cost) or s.cost > fit.cost + OTHER_DELTA:
            continue
        q = np.asarray(s.params.quaternion, np.float64)
        sep = min((mode_separation_deg(qk, q, sym, **sep_kw) for qk in quats), default=np.inf)
        if sep <= max(cfg.min_separation_deg, 2.0):
            continue
        los_sep = min(
            (line_of_sight_error_deg(qk, q, exact, los=los)[0] for qk in quats), default=np.inf
        )
        if los_sep <= OTHER_LOS_DEG and s.cost >= fit.cost - OTHER_DELTA:
            continue
        found.append((s.cost, q, s.params))
        quats.append(q)
    found.sort(key=lambda t: t[0])
    return [
        Mode(
            quaternion=q,
            label="other optimum",
            kind="other optimum",
            exact=False,
            range_shift=float(np.asarray(p.range_offset) - np.asarray(p0.range_offset)),
            body=np.eye(3),
            world="other optimum",
            residual=0.0,
            start=p,
        )
        for _, q, p in found[:OTHER_MODES]
    ]


ROLL_RIDGE_DEG = 0.5
"""Modes whose lines of sight are this close may be one mode when the roll about the line
of sight is unobservable at the best of them (:func:`_merge_roll_ridge`)."""
ROLL_RIDGE_RISE = 2.0
"""... and when the deviance along the roll between them rises by no more than this."""


def _roll_between_deg(q_from, q_to, los) -> float:
    """Signed turn (deg) about the world line of sight taking attitude ``q_from`` to
    ``q_to`` (their relative rotation's component along it)."""
    from scipy.spatial.transform import Rotation

    def rot(q):
        return Rotation.from_quat(np.roll(np.asarray(q, np.float64), -1))  # scalar-last

    rv = (rot(q_to) * rot(q_from).inv()).as_rotvec()
    return float(np.degrees(rv @ np.asarray(los, np.float64)))


def _merge_roll_ridge(distinct, lz, w, cand, cfg, los_world, data, noise):
    """Modes that differ only by a roll the data do not determine are one mode: when the
    best mode's observability names the roll about the line of sight unobservable, a mode
    whose line of sight is within ``ROLL_RIDGE_DEG`` of a more probable one, and between
    which and that one the deviance along the roll (:func:`inversion.roll_scan`, gain
    profiled) rises by at most ``ROLL_RIDGE_RISE``, is dropped (its evidence is the ridge's,
    which the kept point already carries) and the weights renormalised: the chain samples
    the roll along the ridge (two points of one ridge
    were reported as two modes of weight 1/3 each, "line of sight 0 deg away"). Modes
    separated by a barrier in the roll (a bistatic half turn, another roll minimum) stay."""
    if len(distinct) < 2:
        return distinct, lz, w
    ob = observability(distinct[0].fit, line_of_sight=los_world)
    if not any(n.startswith("roll about the line of sight") for n in ob.names):
        return distinct, lz, w
    exact = cand.exact_symmetry(cfg.symmetry)
    model = cand.model
    scans: dict[int, Any] = {}

    def quat(k):
        return np.asarray(distinct[k].fit.params.unit_quaternion(), np.float64)

    def one_ridge(k, j) -> bool:
        if line_of_sight_error_deg(quat(k), quat(j), exact, los=los_world)[0] > ROLL_RIDGE_DEG:
            return False
        if k not in scans:
            scans[k] = roll_scan(model, data, distinct[k].fit.params, noise=noise, los=los_world)
        sc = scans[k]
        period = 180.0 if sc.exact else 360.0
        turn = _roll_between_deg(quat(k), quat(j), los_world) % period
        ang = np.asarray(sc.angles_deg, np.float64)
        # the shorter arc from roll 0 to the turn, both ends included
        if turn <= period / 2:
            arc = ang <= turn + 1e-9
        else:
            arc = ang >= turn - 1e-9
        arc[0] = True
        dev = np.asarray(sc.deviance, np.float64)
        return bool(np.max(dev[arc]) - dev[0] <= ROLL_RIDGE_RISE)

    keep: list[int] = []
    for j in range(len(distinct)):
        home = next((k for k in keep if one_ridge(k, j)), None)
        if home is None:
            keep.append(j)
    # each point of a flat roll ridge already carries the whole ridge's evidence (the Laplace
    # Occam factor of an unobservable roll is its full prior width): the kept point's own
    # evidence is the ridge's, not a sum over the points found on it
    lz = [lz[k] for k in keep]
    return [distinct[k] for k in keep], lz, _probabilities(lz)


def _sensor_geometry(model, los_world) -> tuple[bool, np.ndarray]:
    """(half turn exact: monostatic sensor, world mirror normal: perpendicular to the line of
    sight and the transmitter's x polarization reference)."""
    sensor = getattr(getattr(model, "pure_model", model), "sensor", None)
    if sensor is None:
        return True, np.array([0.0, 1.0, 0.0])
    mono = bool(getattr(sensor, "monostatic", True))
    x = np.asarray(sensor.frame_tx, np.float64).reshape(-1, 3)[0]
    w = np.cross(np.asarray(los_world, np.float64), x)
    nrm = np.linalg.norm(w)
    if nrm < 1e-9:  # pragma: no cover - a reference along the line of sight
        return mono, np.array([0.0, 1.0, 0.0])
    return mono, w / nrm


def _shear_matrix(sh: _ReflectanceShear | None, theta: np.ndarray) -> np.ndarray:
    """``d theta / d theta'`` of the reflectance shear at ``theta`` (identity without one):
    ``log_gain = log_gain' - s(n)``, so the gain row holds ``-ds/d theta_n``."""
    a = np.eye(theta.size)
    if sh is None:
        return a
    for i in (*sh.i_nre, *sh.i_nim):
        h = 1e-6 * max(1.0, abs(theta[i]))
        up, dn = theta.copy(), theta.copy()
        up[i] += h
        dn[i] -= h
        a[sh.i_gain, i] = -(float(sh.shift(up)) - float(sh.shift(dn))) / (2 * h)
    return a


def _index_fit(refiner: _Refiner, fit: RefineResult, free, cfg: InvertConfig, max_iter: int = 50):
    """Fisher scoring with the index free, from a fit with the index fixed: damped steps
    ``-(F + lambda diag F)^+ J^T r`` (Pearson residuals ``r``, ``F = J^T J`` inverted in
    its observable subspace, so no step along a direction the data do not fix; ``lambda``
    raised tenfold after a step that does not lower the deviance; after one that does,
    lowered threefold when the gain exceeds 3/4 of the quadratic model's prediction and
    doubled when it is below 1/4, the trust-region rule of Levenberg-Marquardt), every
    trial kept inside the physical box. Uses the
    refiner's Jacobian program only (no second solver to compile).

    The steps are taken in the sampler's sheared coordinates (:class:`_ReflectanceShear`:
    the log gain shifted by the log normal-incidence reflectance of the index), where the
    curved ridge along which the gain absorbs the reflectance is nearly straight, so a
    Gauss-Newton step follows it instead of zig-zagging across it.

    Stationary (converged) when the undamped step's predicted decrease of the deviance,
    ``g^T F^+ g`` with the score ``g = J^T r``, or the last accepted step's actual decrease
    is below ``max(1e-3, 1e-9 D)`` (a likelihood ratio of 1.0005: no change at all), or when
    no damping up to ``lambda = 1e8`` lowers the deviance; at most ``max_iter`` trial steps.
    Returns a RefineResult (method ``fisher_scoring``)."""
    model, noise, data = refiner.model, refiner.noise, refiner.data_j
    t0 = time.perf_counter()
    phys = _clip_box(fit.params)
    bg = float(getattr(noise, "background", 0.0)) if isinstance(noise, PoissonCounts) else 0.0
    try:
        J, inv_sigma, mu, _, param, dev = weighted_jacobian(
            model, noise, data, phys, free, None, refiner.range_scale
        )
    except FloatingPointError:
        return None
    # the shear where the start is metallic (n'' > 1 in every part): there the gain absorbs
    # the reflectance along a curved ridge; from a dielectric start (n'' on its floor) the
    # sheared steps overshoot to the box's edge
    metal = bool(np.all(np.imag(np.asarray(phys.n)) > 1.0))
    sh = _ReflectanceShear(param) if metal and _ReflectanceShear.applies(param) else None
    data_np = np.asarray(data, np.float64)
    steps, ok, lam = 0, False, 1e-3
    while True:
        theta0 = np.asarray(_from_physical(param, phys), np.float64)
        A = _shear_matrix(sh, theta0)
        Js = J @ A  # Jacobian in the sheared coordinates
        r = ((data_np - mu - bg) * inv_sigma).ravel()
        g = Js.T @ r
        F = Js.T @ Js
        C0, _ = observable_inverse(F)
        # a deviance change of 1e-3 (a likelihood ratio of 1.0005) is no change at all
        tol = max(1e-3, 1e-9 * dev)
        if float(g @ C0 @ g) <= tol:  # the undamped step would gain nothing: stationary
            ok = True
            break
        if steps >= max_iter:
            break
        steps += 1
        C, _ = observable_inverse(F + lam * np.diag(np.diag(F)))
        delta = -C @ g
        with np.errstate(over="ignore", invalid="ignore"):
            theta_t = theta0 + delta if sh is None else sh.inverse(sh.forward(theta0) + delta)
        dev_t = math.inf
        if np.all(np.isfinite(theta_t)):  # a step so long that the index overflows: rejected
            trial = _clip_box(_to_physical(param, jnp.asarray(theta_t)))
            try:
                Jt, inv_t, mu_t, _, par_t, dev_t = weighted_jacobian(
                    model, noise, data, trial, free, None, refiner.range_scale
                )
            except FloatingPointError:
                dev_t = math.inf
        if not (np.isfinite(dev_t) and dev_t < dev):
            lam *= 10.0
            if lam > 1e8:  # no descent left along the observable directions: stationary
                ok = True
                break
            continue
        gain = dev - dev_t
        # the quadratic model's decrease for this step: 2 g^T C g - g^T C F C g
        pred = float(-2.0 * (g @ delta) - delta @ F @ delta)
        rho = gain / pred if pred > 0 else 1.0
        phys, J, inv_sigma, mu, param, dev = trial, Jt, inv_t, mu_t, par_t, dev_t
        # trust-region rule: relax the damping only where the model predicted the gain
        if rho > 0.75:
            lam = max(lam / 3.0, 1e-9)
        elif rho < 0.25:
            lam *= 2.0
        if gain <= tol:
            ok = True
            break
    s = StartSummary(
        0,
        fit.params,
        phys,
        float(dev),
        ok,
        "successful" if ok else "max_steps_reached",
        "converged" if ok else f"Fisher scoring still descending after {max_iter} steps",
        steps,
        steps,
    )
    return _finish(
        model, noise, data, s, (s,), tuple(free), refiner.range_scale, t0, "fisher_scoring"
    )


def _clip_box(phys: PhysicalParams) -> PhysicalParams:
    """``phys`` with ``n``, ``m``, the gain and the offset inside :data:`BOUNDS`."""
    b = BOUNDS
    n = np.asarray(phys.n)
    re = np.clip(n.real, *b.n_re)
    im = np.clip(n.imag, *b.n_im)
    return _with(
        phys,
        n=jnp.asarray(re + 1j * im, phys.n.dtype),
        m=jnp.clip(phys.m, *b.m),
        gain=jnp.clip(phys.gain, *b.gain),
        range_offset=jnp.clip(phys.range_offset, *b.range_offset),
    )


def _index_estimates(index_fit, k_parts: int, los_world) -> tuple[IndexEstimate, ...]:
    if index_fit is None:
        return ()
    ob = observability(index_fit, line_of_sight=los_world)
    n = np.asarray(index_fit.params.n)
    out = []
    for k in range(k_parts):
        i_re, i_im = ob.labels.index(f"n_re[{k}]"), ob.labels.index(f"n_im[{k}]")
        s_re, s_im = float(ob.sigma[i_re]), float(ob.sigma[i_im])
        det = bool(ob.determined[i_re] and ob.determined[i_im])
        at_box = not (N_RE_BOX[0] < n[k].real < N_RE_BOX[1] and n[k].imag < N_IM_BOX[1])
        # determined, and the 2-sigma box smaller than half the prior box
        small = (
            np.isfinite(s_re)
            and np.isfinite(s_im)
            and (
                4 * s_re < 0.5 * (N_RE_BOX[1] - N_RE_BOX[0])
                and 4 * s_im < 0.5 * (N_IM_BOX[1] - N_IM_BOX[0])
            )
        )
        if det and small and not at_box and index_fit.success:
            out.append(IndexEstimate(k, complex(n[k]), (s_re, s_im), True, "determined"))
            continue
        why = []
        if not det:
            names = [
                d.name
                for d in ob.unobservable
                if any(lab.startswith((f"n_re[{k}]", f"n_im[{k}]")) for lab in d.physical)
            ]
            why.append("on an unobservable direction" + (f": {'; '.join(names)}" if names else ""))
        if det and not small:
            why.append(f"uncertainty +-({s_re:.2g}, {s_im:.2g}) spans the physical range")
        if at_box:
            why.append("at the physical bound")
        if not index_fit.success:
            why.append("the index fit did not converge")
        out.append(IndexEstimate(k, complex(n[k]), None, False, "; ".join(why)))
    return tuple(out)
