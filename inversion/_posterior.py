r"""Posterior files a researcher can open: ArviZ ``InferenceData`` in physical units.

:func:`to_inference_data` turns an :class:`~inversion.MCMCResult` into an
``arviz.InferenceData`` whose ``posterior`` group holds every fitted parameter in the unit its
``units`` attribute states, with ArviZ's dimensions ``chain`` (the ensemble sampler's
*walkers*: they are not independent chains, but R-hat across them is what shows a walker
stuck in its own region) and ``draw`` (steps after the burn-in, thinned):

=====================  ===============================  ===================================
variable               unit                             meaning
=====================  ===============================  ===================================
``rot_x/y/z``          deg                              rotation vector about the reference
                                                        attitude (the refined optimum),
                                                        sensor-frame components
``quaternion``         1                                absolute attitude, scalar first,
                                                        body -> sensor (dim ``component``)
``los_polar``,         deg                              the line of sight (toward the sensor)
``los_azimuth``                                         in the body frame: angle from body
                                                        +z, azimuth from +x toward +y
``m``                  1                                Blinn-Phong exponent (dim
                                                        ``material``)
``n_re``, ``n_im``     1                                complex index ``n' + i n''``
``corr_length``        m                                surface correlation length
``range_offset``       m                                one-way range offset
``gain``               counts per (m^2 sr^-1)           expected counts per unit of the
                                                        simulator's profile (``gain_unit``)
=====================  ===============================  ===================================

``sample_stats.lp`` is the log posterior (solver coordinates, up to a constant); the burn-in
draws are in ``warmup_posterior`` / ``warmup_sample_stats`` and the attributes record
``burn_in``, ``thin``, the reference attitude, the free groups and the walkers' acceptance
fractions. :func:`posterior_diagnostics` gives R-hat, bulk and tail ESS and the Monte Carlo
standard errors of the mean and the sd, all from ArviZ (:func:`arviz.rhat`, :func:`arviz.ess`,
:func:`arviz.mcse`), per physical label; :func:`write_posterior` writes the netCDF file
(h5netcdf), atomically.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

__all__ = [
    "GAIN_UNIT",
    "to_inference_data",
    "posterior_diagnostics",
    "write_posterior",
    "posterior_variables",
]

# the gain of SimulatorModel: expected counts = gain x profile (ppr.render: m^2 sr^-1 per bin)
GAIN_UNIT = "counts per (m^2 sr^-1)"


def _arviz():
    with warnings.catch_warnings():
        # arviz 0.2x announces its 1.0 API on import (FutureWarning): nothing to act on here
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


def posterior_variables(labels, gain_unit: str = GAIN_UNIT) -> list[tuple[str, int | None, str]]:
    """``(variable, material index or None, unit)`` of each physical label (in order)."""
    out = []
    for lab in labels:
        name, _, unit = lab.partition(" [")
        unit = unit.rstrip("]") if unit else "1"
        idx = None
        if name.endswith("]"):
            name, _, rest = name.partition("[")
            idx = int(rest.rstrip("]"))
        if name == "gain":
            unit = gain_unit
        out.append((name, idx, unit))
    return out


def _body_los(q, los):
    """The sensor-frame direction ``los`` in the body frame, ``R(q)^T los`` (``q`` body ->
    sensor, scalar first; batched)."""
    from ppr import quat_to_matrix

    return np.einsum("...ij,i->...j", np.asarray(quat_to_matrix(q), np.float64), los)


def _groups(result, chain, lp, gain_unit, line_of_sight):
    """Posterior variables ``(walker, draw, ...)`` and dims of physical ``chain``
    ``(steps, walkers, P)``."""
    from ppr.geometry import quat_from_rotvec_host, quat_multiply_host

    labels = result.labels
    cube = np.swapaxes(chain, 0, 1)  # (walker, draw, P)
    data: dict[str, np.ndarray] = {}
    units: dict[str, str] = {}
    slots: dict[str, list[tuple[int, int]]] = {}
    for col, (name, idx, unit) in enumerate(posterior_variables(labels, gain_unit)):
        units[name] = unit
        if idx is None:
            data[name] = cube[..., col]
        else:
            slots.setdefault(name, []).append((idx, col))
    for name, pairs in slots.items():
        cols = [c for _, c in sorted(pairs)]
        data[name] = cube[..., cols]
    dims = {name: ["material"] for name in slots}
    q_ref = np.asarray(result.parametrisation.reference.unit_quaternion(), np.float64)
    if "rot_x" in data:
        rv = np.radians(np.stack([data["rot_x"], data["rot_y"], data["rot_z"]], -1))
        q_ref = np.broadcast_to(q_ref, rv.shape[:-1] + (4,))
        q = quat_multiply_host(quat_from_rotvec_host(rv), q_ref)
    else:
        q = np.broadcast_to(q_ref, cube.shape[:2] + (4,)).copy()
    q = np.where(q[..., :1] < 0, -q, q)
    data["quaternion"] = q
    units["quaternion"] = "1"
    dims["quaternion"] = ["component"]
    v = _body_los(q, line_of_sight)
    data["los_polar"] = np.degrees(np.arccos(np.clip(v[..., 2], -1.0, 1.0)))
    data["los_azimuth"] = np.degrees(np.arctan2(v[..., 1], v[..., 0]))
    units["los_polar"] = units["los_azimuth"] = "deg"
    stats = {"lp": np.swapaxes(lp, 0, 1)}
    # contiguous, as read back from a file: ArviZ's sums then run in the same order in memory
    # and on disk (the diagnostics agree to the last bit)
    data = {k: np.ascontiguousarray(v) for k, v in data.items()}
    stats = {k: np.ascontiguousarray(v) for k, v in stats.items()}
    return data, stats, dims, units


_LONG_NAMES = {
    "rot_x": "rotation vector about the reference attitude, sensor-frame x",
    "rot_y": "rotation vector about the reference attitude, sensor-frame y",
    "rot_z": "rotation vector about the reference attitude, sensor-frame z",
    "quaternion": "attitude quaternion (w, x, y, z), body to sensor frame",
    "los_polar": "line of sight (toward the sensor) in the body frame: angle from body +z",
    "los_azimuth": "line of sight in the body frame: azimuth from body +x toward +y",
    "m": "Blinn-Phong exponent",
    "n_re": "refractive index, real part n'",
    "n_im": "refractive index, imaginary part n''",
    "corr_length": "surface correlation length",
    "range_offset": "one-way range offset",
    "gain": "expected counts per unit of the simulated profile",
}


def to_inference_data(
    result,
    *,
    gain_unit: str = GAIN_UNIT,
    line_of_sight=(0.0, 0.0, 1.0),
    observed=None,
):
    """``arviz.InferenceData`` of an :class:`~inversion.MCMCResult` in physical units.

    **Arguments:**

    - `result`: the :class:`~inversion.MCMCResult` (:func:`inversion.sample_posterior`).
    - `gain_unit`: unit of the gain (default :data:`GAIN_UNIT`, that of
      :class:`~inversion.SimulatorModel`; a toy model's gain has its own).
    - `line_of_sight`: sensor-frame unit vector toward the sensor (default ``+z``, the
      canonical sensor's), for the body-frame line of sight ``los_polar``/``los_azimuth``.
    - `observed`: the data ``(C, B)``, stored as ``observed_data.counts`` (optional).

    **Returns:** ``InferenceData`` with groups ``posterior``, ``sample_stats`` (``lp``), the
    burn-in in ``warmup_posterior`` and ``warmup_sample_stats`` (when ``burn_in > 0``) and
    ``observed_data`` (when given); see the module docstring for the variables and units.
    """
    az = _arviz()
    los = np.asarray(line_of_sight, np.float64)
    if los.shape != (3,) or not np.all(np.isfinite(los)) or np.linalg.norm(los) == 0:
        raise ValueError(f"to_inference_data: line_of_sight must be a non-zero 3-vector, got {los}")
    los = los / np.linalg.norm(los)
    chain = result.physical_chain
    if chain is None:
        raise ValueError(
            "to_inference_data: the MCMCResult has no physical_chain (made by an older "
            "sample_posterior); sample again"
        )
    b, t = int(result.burn_in), int(result.thin)
    post, stats, dims, units = _groups(result, chain[b::t], result.log_prob[b::t], gain_unit, los)
    kwargs = {}
    if b > 0:
        warm, warm_stats, _, _ = _groups(result, chain[:b:t], result.log_prob[:b:t], gain_unit, los)
        kwargs = {"warmup_posterior": warm, "warmup_sample_stats": warm_stats, "save_warmup": True}
    if observed is not None:
        kwargs["observed_data"] = {"counts": np.asarray(observed, np.float64)}
        dims["counts"] = ["channel", "bin"]
    par = result.parametrisation
    attrs = {
        "sampler": "emcee.EnsembleSampler",
        "chain_dimension": "walkers of one ensemble (not independent chains)",
        "n_walkers": int(chain.shape[1]),
        "n_steps": int(chain.shape[0]),
        "burn_in": b,
        "thin": t,
        "reference_quaternion": np.asarray(par.reference.unit_quaternion(), np.float64),
        "free": " ".join(par.free),
        "line_of_sight": los,
        "acceptance_fraction": np.asarray(result.acceptance_fraction, np.float64),
        "labels": " | ".join(result.labels),
    }
    k = par.reference.n_materials
    with warnings.catch_warnings():
        # an ensemble often has more walkers than kept steps: the layout is (chain, draw)
        warnings.filterwarnings("ignore", "More chains", UserWarning)
        idata = az.from_dict(
            posterior=post,
            sample_stats=stats,
            dims=dims,
            coords={"material": np.arange(k), "component": ["w", "x", "y", "z"]},
            **kwargs,
        )
    for group in ("posterior", "warmup_posterior"):
        if group in idata.groups():
            ds = idata[group]
            ds.attrs.update(attrs)
            for name, unit in units.items():
                ds[name].attrs["units"] = unit
                ds[name].attrs["long_name"] = _LONG_NAMES.get(name, name)
    idata.sample_stats["lp"].attrs["long_name"] = "log posterior (solver coordinates)"
    return idata


def posterior_diagnostics(idata, labels=None) -> dict[str, dict[str, float]]:
    """ArviZ's convergence diagnostics per physical label: ``r_hat`` (rank-normalized split
    R-hat), ``ess_bulk``, ``ess_tail``, ``mcse_mean``, ``mcse_sd`` (the last two in the
    parameter's unit). ``labels``: the physical labels of the posterior's fitted variables
    (default: those recorded in its attributes)."""
    az = _arviz()
    post = idata.posterior
    if labels is None:
        labels = str(post.attrs.get("labels", "")).split(" | ")
    with warnings.catch_warnings():
        # a parameter constant over the draws (e.g. an index held at a library value) has no
        # defined R-hat or ESS: ArviZ warns and returns NaN, reported here as None
        warnings.simplefilter("ignore", RuntimeWarning)
        results = {
            "r_hat": az.rhat(post),
            "ess_bulk": az.ess(post, method="bulk"),
            "ess_tail": az.ess(post, method="tail"),
            "mcse_mean": az.mcse(post, method="mean"),
            "mcse_sd": az.mcse(post, method="sd"),
        }
    out = {}
    for lab, (name, idx, _) in zip(labels, posterior_variables(labels), strict=True):
        entry = {}
        for key, ds in results.items():
            val = ds[name].values
            v = float(val if idx is None else val[idx])
            entry[key] = v if math.isfinite(v) else None
        out[lab] = entry
    return out


def attitude_rhat(result, line_of_sight=(0.0, 0.0, 1.0)) -> dict[str, float | None]:
    """ArviZ's R-hat (walkers as chains, kept draws) of the attitude modulo the half turn
    about the line of sight, for an :class:`~inversion.MCMCResult` with the attitude free
    (empty dict otherwise): the body-frame line of sight's unit-vector components
    ``los_x``, ``los_y``, ``los_z`` and the doubled roll about it, ``roll_cos2``,
    ``roll_sin2`` (``cos 2 phi``, ``sin 2 phi``; ``phi`` the twist about the sensor-frame
    line of sight of the rotation from the reference attitude).

    A monostatic measurement is unchanged by the half turn about the line of sight (its
    Mueller matrices are), and :func:`inversion.invert` samples the half turn as a mode of
    its own; the sampler keeps each walker in its half-circle of roll. The rotation-vector
    components ``rot_x/y/z`` jump by the half turn between walkers in the two halves, and
    their R-hat then says how the walkers share the halves, not whether the answer has
    converged. These five quantities do not see the half turn (``R -> C2(k) R`` leaves
    ``R^T k`` and ``2 phi mod 2 pi`` unchanged) and see everything else of the attitude:
    walkers that do not share the roll show in ``roll_cos2``/``roll_sin2``."""
    if "rot_x [deg]" not in result.labels or result.physical_chain is None:
        return {}
    from ppr.geometry import quat_from_rotvec_host, quat_multiply_host

    az = _arviz()
    i = result.labels.index("rot_x [deg]")
    kept = result.physical_chain[result.burn_in :: result.thin]  # (draw, walker, P)
    rv = np.radians(kept[..., i : i + 3])
    dq = quat_from_rotvec_host(rv)
    q_ref = np.asarray(result.parametrisation.reference.unit_quaternion(), np.float64)
    q = quat_multiply_host(dq, np.broadcast_to(q_ref, rv.shape[:-1] + (4,)))
    los = np.asarray(line_of_sight, np.float64)
    los = los / np.linalg.norm(los)
    v = _body_los(q, los)
    dq = np.where(dq[..., :1] < 0, -dq, dq)
    phi = 2.0 * np.arctan2(dq[..., 1:] @ los, dq[..., 0])  # swing-twist: twist about los
    parts = {
        "los_x": v[..., 0],
        "los_y": v[..., 1],
        "los_z": v[..., 2],
        "roll_cos2": np.cos(2.0 * phi),
        "roll_sin2": np.sin(2.0 * phi),
    }
    out = {}
    for name, x in parts.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a constant quantity: NaN (None below)
            r = float(az.rhat(np.ascontiguousarray(np.swapaxes(x, 0, 1))))
        out[name] = r if math.isfinite(r) else None
    return out


def write_posterior(path, result, **kwargs) -> Path:
    """Write :func:`to_inference_data` of ``result`` to a netCDF file (h5netcdf) at ``path``,
    atomically: a failed write leaves any previous file in place. ``kwargs`` go to
    :func:`to_inference_data`. Read it back with ``arviz.from_netcdf(path)``."""
    path = Path(path)
    idata = to_inference_data(result, **kwargs)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        idata.to_netcdf(str(tmp), engine="h5netcdf")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
