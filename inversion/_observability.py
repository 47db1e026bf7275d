r"""Observability: which parameter directions the data constrain, named, with finite errors.

A Fisher matrix ``F`` (the refiner's Gauss-Newton ``J^T J`` at a fit, or the Cramer-Rao
information at a truth; solver coordinates ``theta`` of :mod:`inversion._params`) that is
singular makes every marginal variance with weight in its null space infinite. One exact
symmetry (the roll about the line of sight of a target whose returns are normal-incidence
reflections, or the reflectance of the index against the gain) then turns every reported
uncertainty into ``inf``. Here:

1. A parameter whose own axis carries no information (``F_ii <= 1e-12 max_j F_jj``: the data
   do not depend on it at all) is **unobservable on its own**. Its uncertainty is infinite
   and it is named.
2. The rest of ``F`` is put in correlation form, ``C = D^-1/2 F D^-1/2`` with
   ``D = diag(F)``, which does not depend on the units of the parameters. An eigenvalue
   ``w <= rtol`` (default 1e-8) of ``C`` is an **unobservable direction**: along it the data
   determine the parameters ``1/sqrt(w)`` (>= 1e4) times worse than each one alone, with
   the others known. Each is named in physical terms: "roll about the line of sight" (a
   rotation whose axis is within 5 deg of the line of sight), "rotation about ..." (another
   axis, in the sensor and the body frame), a single parameter, or a trade-off such as
   "gain vs m[0]" with the product the data do fix (``gain x m[0]^1.0``) when two log
   coordinates trade.
3. Uncertainties are reported **in the observable subspace**: the covariance
   ``D^-1/2 U_o diag(1/w_o) U_o^T D^-1/2`` over the observable eigenvectors ``U_o`` of
   ``C`` (the pseudo-inverse in correlation form), propagated to physical units. It is the
   spread of each parameter with the position along every unobservable direction held at
   its fitted value. Per parameter, ``determined`` says whether it has weight in no
   unobservable direction (then this is also its marginal uncertainty).

Nothing here is infinite except the uncertainty of a parameter unobservable on its own,
which :meth:`Observability.to_dict` writes as JSON ``null`` next to its name.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import numpy as np

from ppr import quat_to_matrix

__all__ = [
    "Observability",
    "UnobservableDirection",
    "observability",
    "observability_from_fisher",
    "observable_inverse",
    "line_of_sight_of",
    "DEFAULT_RTOL",
]

DEFAULT_RTOL = 1e-8
# a parameter whose own axis carries less than this fraction of the largest diagonal entry
# of the Fisher matrix has no information at all (round-off of an exact zero)
OWN_AXIS_RTOL = 1e-12
ROLL_TOLERANCE_DEG = 5.0


@dataclasses.dataclass(frozen=True)
class UnobservableDirection:
    """One direction of parameter space the data do not constrain.

    - `name`: what it is, e.g. ``"roll about the line of sight"``, ``"n_re[0]"``,
      ``"gain vs m[0] (the data fix gain x m[0]^1.0)"``.
    - `loadings`: the unit direction in solver coordinates (``theta`` labels: radians of
      rotation, natural logs of ``m``, ``n'`` and the gain, ...), components above 1 %.
    - `physical`: the change of each physical parameter (its labels and units) per unit
      step along the direction, components above 1 % of the largest.
    - `information`: eigenvalue of the correlation-form Fisher matrix (0 for a parameter
      unobservable on its own); ``1 / sqrt(information)`` is how many times worse than
      individually the data determine the combination.
    - `axis_sensor`, `axis_body`: unit rotation axis of an attitude direction, in the sensor
      and the body frame (None otherwise).
    """

    name: str
    loadings: dict[str, float]
    physical: dict[str, float]
    information: float
    axis_sensor: tuple[float, float, float] | None = None
    axis_body: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Observability:
    """What the data constrain at a parameter point (:func:`observability`).

    - `labels`: physical parameters (with units, as :attr:`RefineResult.labels`); `values`
      their values at the point.
    - `sigma`: 1-sigma uncertainty in the observable subspace, finite; ``inf`` only for a
      parameter unobservable on its own (`observable` False).
    - `covariance`: the observable-subspace covariance in physical units (rows and columns
      of a parameter unobservable on its own: ``inf`` on the diagonal, 0 elsewhere).
    - `observable`: the parameter's own axis carries information (the data change when it
      alone changes).
    - `determined`: the parameter has no weight in an unobservable direction (its `sigma` is
      then its marginal uncertainty too).
    - `unobservable`: the unobservable directions, named (:class:`UnobservableDirection`).
    - `rank`: number of observable directions (fitted degrees of freedom the data absorb).
    - `rtol`: the eigenvalue threshold used; `condition`: condition number of the observable
      part of the correlation-form Fisher matrix.
    """

    labels: list[str]
    values: np.ndarray
    sigma: np.ndarray
    covariance: np.ndarray
    observable: np.ndarray
    determined: np.ndarray
    unobservable: tuple[UnobservableDirection, ...]
    rank: int
    rtol: float
    condition: float

    @property
    def names(self) -> list[str]:
        """Names of the unobservable directions."""
        return [d.name for d in self.unobservable]

    @property
    def attitude_sigma_deg(self) -> float | None:
        """Root-sum-square 1-sigma of the attitude components observable on their own
        (degrees, observable subspace; the unobservable ones are named instead); ``None``
        when the attitude is not fitted."""
        idx = [i for i, lab in enumerate(self.labels) if lab.startswith("rot_")]
        if not idx:
            return None
        return float(np.sqrt(sum(self.sigma[i] ** 2 for i in idx if self.observable[i])))

    def sigma_of(self, label: str) -> float:
        """Uncertainty of one parameter by label (with or without its unit)."""
        return float(self.sigma[_index(self.labels, label)])

    def summary(self) -> str:
        lines = [
            f"observability: {self.rank} of {len(self.labels)} directions constrained"
            + (
                "; unobservable: " + "; ".join(self.names)
                if self.unobservable
                else " (all parameters observable)"
            )
        ]
        edges = self.at_bounds()
        for lab, v, s, obs, det in zip(
            self.labels, self.values, self.sigma, self.observable, self.determined, strict=True
        ):
            if lab in edges:
                lines.append(f"  {lab:>22s} = {v: .6g}  ({edges[lab]}: no Gaussian sigma)")
                continue
            if not obs:
                note = "unobservable on its own"
                lines.append(f"  {lab:>22s} = {v: .6g}  ({note})")
                continue
            note = "" if det else "  (in the observable subspace: see the unobservable directions)"
            lines.append(f"  {lab:>22s} = {v: .6g} +- {s:.3g}{note}")
        return "\n".join(lines)

    def at_bounds(self, bounds=None) -> dict[str, str]:
        """:func:`box_edges` of these parameters."""
        return box_edges(self.labels, self.values, bounds)

    def to_dict(self) -> dict:
        """JSON-ready: ``sigma`` is ``None`` (JSON ``null``) exactly for the parameters
        unobservable on their own, which are listed by name; ``at_bounds`` names the
        parameters on an edge of the physical box (:meth:`at_bounds`)."""
        return {
            "labels": list(self.labels),
            "values": [float(v) for v in self.values],
            "sigma": [float(s) if math.isfinite(s) else None for s in self.sigma],
            "observable": [bool(b) for b in self.observable],
            "determined": [bool(b) for b in self.determined],
            "at_bounds": self.at_bounds(),
            "unobservable_on_own": [
                lab for lab, b in zip(self.labels, self.observable, strict=True) if not b
            ],
            "unobservable": [
                {
                    "name": d.name,
                    "loadings": d.loadings,
                    "physical": d.physical,
                    "information": d.information,
                    "axis_sensor": d.axis_sensor,
                    "axis_body": d.axis_body,
                }
                for d in self.unobservable
            ],
            "rank": int(self.rank),
            "rtol": float(self.rtol),
            "condition": float(self.condition) if math.isfinite(self.condition) else None,
        }


def line_of_sight_of(model) -> np.ndarray | None:
    """Unit vector toward the sensor in the sensor frame of a model built on a
    :class:`ppr.Sensor` (its bisector, e.g. :class:`~inversion.SimulatorModel`); ``None`` for
    a model without one (:func:`observability` then uses ``+z``)."""
    sensor = getattr(getattr(model, "pure_model", model), "sensor", None)
    w = getattr(sensor, "bisector", None)
    if w is None:
        return None
    w = np.asarray(w, np.float64)
    return w / np.linalg.norm(w)


def _index(labels, label):
    for i, lab in enumerate(labels):
        if lab == label or lab.split(" [")[0] == label:
            return i
    raise KeyError(f"no parameter {label!r}; labels: {labels}")


def _short(label: str) -> str:
    return label.split(" [")[0]


def box_edges(labels, values, bounds=None) -> dict[str, str]:
    """Parameters on an edge of the physical box (default :class:`~inversion.PhysicalBounds`,
    the box of :func:`inversion.invert`), by label, e.g. ``{"m[0]": "at the upper bound
    1e+06"}``: the optimum lies at or beyond the edge (a mirror-smooth part, a dielectric's
    ``n'' = 0``), where the likelihood is cut by the box, not curved, and a local Gaussian
    sigma says nothing."""
    from ._refine import PhysicalBounds

    b = PhysicalBounds() if bounds is None else bounds
    edges = {"m": b.m, "n_re": b.n_re, "n_im": b.n_im, "corr_length": b.corr_length}
    edges |= {"gain": b.gain, "range_offset": b.range_offset, "thickness": b.thickness}
    out = {}
    for lab, v in zip(labels, np.asarray(values, np.float64), strict=True):
        key = lab.split("[")[0].split(" ")[0]
        if key not in edges or not math.isfinite(v):
            continue
        lo, hi = edges[key]
        # m and n'' have floors of 1e-9 (a start lifted to 1e-6): physically zero; other
        # bounds to 1e-9 of their size (a 1.5 nm film is not on the 1 nm bound)
        floor = 1.001e-6 if key in ("m", "n_im") and lo == 0.0 else lo + 1e-9 * abs(lo)
        if v <= floor:
            out[lab] = f"at the lower bound {lo:g}"
        elif v >= hi - 1e-9 * abs(hi):
            out[lab] = f"at the upper bound {hi:g}"
    return out


def observability(
    result,
    *,
    line_of_sight=None,
    rtol: float | None = None,
) -> Observability:
    """Name the directions the data do not constrain; uncertainties in the observable subspace.

    **Arguments:**

    - `result`: a :class:`~inversion.RefineResult` (its Gauss-Newton information at the fit)
      or a :class:`~inversion.CramerRao` (the expected information at a truth).
    - `line_of_sight`: unit vector from the target toward the sensor in the sensor frame (the
      frame the attitude's rotation vector is expressed in); default ``+z``, the canonical
      sensor's (``line_of_sight = [0, 0, -1]`` in sensor configs is the laser's propagation
      direction). For a :class:`~inversion.SimulatorModel` pass
      ``model.pure_model.sensor.bisector``.
    - `rtol`: eigenvalue threshold of the correlation-form Fisher matrix (default 1e-8).

    **Returns:** :class:`Observability` (module docstring).
    """
    fisher = getattr(result, "fisher_theta", None)
    param = getattr(result, "parametrisation", None)
    if fisher is None or param is None:
        raise ValueError(
            f"observability: {type(result).__name__} carries no Fisher matrix; pass a "
            "RefineResult from inversion.refine/refine_bounded or a CramerRao from "
            "inversion.cramer_rao"
        )
    return observability_from_fisher(
        fisher,
        param,
        line_of_sight=line_of_sight,
        rtol=rtol,
        physical_jacobian=getattr(result, "physical_jacobian", None),
    )


def observability_from_fisher(
    fisher,
    parametrisation,
    *,
    line_of_sight=None,
    rtol: float | None = None,
    physical_jacobian=None,
) -> Observability:
    """:func:`observability` of a Fisher matrix in the solver coordinates of
    ``parametrisation`` (whose reference is the parameter point); ``physical_jacobian``
    ``d physical_vector / d theta`` there if known (else computed)."""
    from ._refine import _from_physical

    rtol = DEFAULT_RTOL if rtol is None else float(rtol)
    if not 0 < rtol < 1:
        raise ValueError(f"observability: rtol must lie in (0, 1), got {rtol!r}")
    los = np.array([0.0, 0.0, 1.0]) if line_of_sight is None else np.asarray(line_of_sight, float)
    if los.shape != (3,) or not np.all(np.isfinite(los)) or np.linalg.norm(los) == 0:
        raise ValueError(f"observability: line_of_sight must be a non-zero 3-vector, got {los!r}")
    los = los / np.linalg.norm(los)
    F = np.asarray(fisher, np.float64)
    param = parametrisation
    P = param.size
    if F.shape != (P, P):
        raise ValueError(f"observability: Fisher matrix {F.shape} does not match {P} parameters")
    if not np.all(np.isfinite(F)):
        raise ValueError("observability: the Fisher matrix has non-finite entries (failed fit?)")
    F = 0.5 * (F + F.T)
    theta = _from_physical(param, param.reference)
    if physical_jacobian is None:
        G, values = _physical_jacobian(param, theta)
    else:
        G = np.asarray(physical_jacobian, np.float64)
        values = np.asarray(_physical_vector(param, theta))
    G, values = np.asarray(G, np.float64), np.asarray(values, np.float64)
    labels, tlabels = param.labels, param.theta_labels

    own, keep, s, w, U, null, cov_theta = _decompose(F, rtol)
    obs = ~null
    cov = G @ cov_theta @ G.T
    # null directions in theta: the own-axis ones, then those of the correlation form
    dirs = [(np.eye(P)[i], 0.0) for i in np.flatnonzero(own)]
    for k in np.flatnonzero(null):
        v = np.zeros(P)
        v[keep] = s * U[:, k]
        dirs.append((v / np.linalg.norm(v), float(max(w[k], 0.0))))
    determined = ~own.copy()
    for v, _ in dirs:
        moved = np.abs(G @ v)
        # a parameter pinned on its reparametrisation floor (n'' or m at 1e-9) hardly moves
        determined &= moved <= 1e-6 * (1.0 + np.abs(values))
    observable_phys = np.abs(G) @ (~own).astype(float) > 0  # G is diagonal for theta
    cov = cov.copy()
    idx = np.flatnonzero(~observable_phys)
    cov[idx, :] = 0.0
    cov[:, idx] = 0.0
    cov[idx, idx] = np.inf
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    q_ref = np.asarray(param.reference.unit_quaternion(), np.float64)
    named = _distinct_names(
        [_describe(v, info, G, labels, tlabels, values, los, q_ref) for v, info in dirs]
    )
    wo = w[obs]
    cond = float(wo.max() / wo.min()) if wo.size else math.inf
    return Observability(
        labels=list(labels),
        values=values,
        sigma=sigma,
        covariance=cov,
        observable=observable_phys,
        determined=determined,
        unobservable=named,
        rank=int(obs.sum()),
        rtol=rtol,
        condition=cond,
    )


@eqx.filter_jit
def _physical_jacobian(param, theta):
    return jax.jacfwd(param.physical_vector)(theta), param.physical_vector(theta)


@eqx.filter_jit
def _physical_vector(param, theta):
    return param.physical_vector(theta)


def _decompose(F, rtol):
    """Own-axis nulls, the correlation form's eigen-decomposition and the observable-subspace
    inverse of a symmetric Fisher matrix (module docstring)."""
    P = F.shape[0]
    d = np.clip(np.diag(F), 0.0, None)
    own = d <= OWN_AXIS_RTOL * max(float(d.max()) if P else 0.0, 1e-300)
    keep = np.flatnonzero(~own)
    s = 1.0 / np.sqrt(d[keep])
    C = s[:, None] * F[np.ix_(keep, keep)] * s[None, :]
    w, U = np.linalg.eigh(C) if keep.size else (np.zeros(0), np.zeros((0, 0)))
    null = w <= rtol
    cov_theta = np.zeros((P, P))
    if (~null).any():
        Us = s[:, None] * U[:, ~null]
        cov_theta[np.ix_(keep, keep)] = (Us / w[~null]) @ Us.T
    return own, keep, s, w, U, null, cov_theta


def observable_inverse(fisher, rtol: float | None = None) -> tuple[np.ndarray, int]:
    """Inverse of a Fisher matrix in its observable subspace and that subspace's dimension
    (the number of parameter directions the data constrain), as in :func:`observability`."""
    F = np.asarray(fisher, np.float64)
    F = 0.5 * (F + F.T)
    *_, null, cov = _decompose(F, DEFAULT_RTOL if rtol is None else float(rtol))
    return cov, int((~null).sum())


def _fmt_vec(v) -> str:
    return "(" + ", ".join(f"{c:+.3f}" for c in v) + ")"


def _distinct_names(named: list[UnobservableDirection]) -> tuple[UnobservableDirection, ...]:
    """Two directions led by the same parameter (e.g. ``m[0]`` alone and ``m[0]`` with 5 %
    of the gain) would read as the same name twice: the later ones list every physical
    component above 1 % by size, and a number where that still repeats."""
    used: set[str] = set()
    out = []
    for d in named:
        if d.name in used:
            comps = sorted(d.physical, key=lambda k: -abs(d.physical[k]))
            alt = " vs ".join(_short(k) for k in comps[:4])
            k = 2
            while alt in used:
                alt, k = f"{d.name} (direction {k})", k + 1
            d = dataclasses.replace(d, name=alt)
        used.add(d.name)
        out.append(d)
    return tuple(out)


def _describe(v, info, G, labels, tlabels, values, los, q_ref) -> UnobservableDirection:
    big = np.abs(v) >= 0.01 * np.abs(v).max()
    loadings = {tlabels[i]: float(v[i]) for i in np.flatnonzero(big)}
    dphys = G @ v
    bigp = np.abs(dphys) >= 0.01 * np.abs(dphys).max() if np.any(dphys) else big
    physical = {labels[i]: float(dphys[i]) for i in np.flatnonzero(bigp)}
    att = [i for i, t in enumerate(tlabels) if t.startswith("rotvec_")]
    a = v[att] if att else np.zeros(3)
    frac_att = float(a @ a)
    if att and frac_att >= 0.99:
        axis = a / np.linalg.norm(a)
        if axis @ los < 0:
            axis = -axis
        body = np.asarray(quat_to_matrix(q_ref), np.float64).T @ axis
        angle = math.degrees(math.acos(min(1.0, abs(float(axis @ los)))))
        if angle <= ROLL_TOLERANCE_DEG:
            name = "roll about the line of sight"
        else:
            name = (
                f"rotation about the sensor-frame axis {_fmt_vec(axis)}, {angle:.1f} deg from "
                f"the line of sight"
            )
        name += f" (body axis {_fmt_vec(body)})"
        return UnobservableDirection(
            name, loadings, physical, info, tuple(map(float, axis)), tuple(map(float, body))
        )
    comps = [i for i in np.argsort(-np.abs(v)) if big[i]]
    if len(comps) == 1:
        i = comps[0]
        name = _short(labels[i])
        if labels[i].startswith(("m[", "n_im[")) and values[i] <= 1.001e-9:
            # the reparametrisation's floor (physically 0): flat, so no local information
            name += " (at its lower bound 0: no local information)"
        return UnobservableDirection(name, loadings, physical, info)
    main = [i for i in comps if abs(v[i]) >= 0.1 * abs(v[comps[0]])]
    name = " vs ".join(_short(labels[i]) for i in main)
    logs = [tlabels[i].startswith("log_") for i in main]
    if len(main) == 2 and all(logs):
        # along v, log x_i moves by v_i t: x_0 x_1^(-v_0 / v_1) stays fixed
        i, j = main
        c = -v[i] / v[j]
        name += (
            f" (the data fix {_short(labels[i])} x {_short(labels[j])}^{c:.2g}; each alone is free)"
        )
    if att and frac_att > 0.01:
        name += " (with a rotation)"
    return UnobservableDirection(name, loadings, physical, info)
