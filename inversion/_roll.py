"""Roll about the line of sight: the attitude direction a monostatic return sees only through
its polarization.

Turning the target by ``phi`` about the world line of sight ``k`` (``q -> C(k, phi) q``)
keeps every depth along the line of sight and, for a monostatic sensor, every visible and
illuminated facet: the range profile of the total intensity does not change. What changes is
the polarization: the turn is the sensor's polarization frame turned by ``-phi``, so the
scene's Mueller matrix becomes ``R(-2 phi) M R(2 phi)`` and every channel ``a^T M g`` is a
trigonometric polynomial in ``2 phi`` of degree 2:

    y(phi) = c0 + c1 cos 2phi + s1 sin 2phi + c2 cos 4phi + s2 sin 4phi

(period 180 deg: the half turn is exact, :func:`inversion.los_half_turn`). Five evaluations at
``phi = 0, 36, ..., 144`` deg determine it exactly (a five-point discrete Fourier transform),
so :func:`roll_scan` gives the deviance at every roll for the price of five forward-model
calls. The deviance is often multimodal in the roll (a body with panels, copolarized
channels that cannot tell a 90 deg turn from a swap of the panels' lobes), and a local
refiner started in the wrong basin stays there; :func:`inversion.invert` therefore starts its
refinement at the best roll of each start and refits the other roll minima as modes.

For a bistatic sensor the turn about the bisector is no symmetry of the geometry (depths and
visibility change): the scan then evaluates the model at each of ``n_direct`` rolls over the
full turn.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ppr.geometry._rotation import quat_multiply_host

from ._gof import deviance_function
from ._params import PhysicalParams
from ._refine import PoissonCounts, _expected_jit, _pure

__all__ = ["RollScan", "roll_scan", "rolled_about"]

_N_HARMONIC = 5  # samples over 180 deg: a degree-2 trigonometric polynomial in 2 phi


def rolled_about(phys: PhysicalParams, angle_deg: float, los=(0.0, 0.0, 1.0)) -> PhysicalParams:
    """``phys`` with its attitude turned by ``angle_deg`` (right-handed) about the world line
    of sight ``los``: ``q -> C(los, angle) q``; every other parameter unchanged."""
    k = np.asarray(los, np.float64)
    if k.shape != (3,) or not np.all(np.isfinite(k)) or abs(np.linalg.norm(k) - 1) > 1e-6:
        raise ValueError(f"rolled_about: los must be a unit 3-vector, got {k.tolist()}")
    a = np.deg2rad(float(angle_deg))
    c = np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * k / np.linalg.norm(k)])
    q = quat_multiply_host(c, np.asarray(phys.quaternion, np.float64))
    q = q / np.linalg.norm(q)
    return eqx.tree_at(
        lambda p: p.quaternion, phys, jnp.asarray(q, jnp.asarray(phys.quaternion).dtype)
    )


@dataclasses.dataclass(frozen=True)
class RollScan:
    """The deviance of a fit's parameters turned about the line of sight (:func:`roll_scan`).

    - `angles_deg`: ``(G,)`` rolls from the given attitude, ``[0, 180)`` for a monostatic
      sensor (period 180 deg), ``[0, 360)`` otherwise.
    - `deviance`: ``(G,)`` the deviance at each roll with the gain re-scaled so that the
      expected total equals the data's (``gain_factor``); every other parameter as given.
    - `gain_factor`: ``(G,)`` the factor on the gain at each roll.
    - `minima`: indices of the local minima of ``deviance`` (cyclic), lowest first.
    - `exact`: True when the deviance at every roll comes from the exact five-sample
      harmonic reconstruction (monostatic), False when from direct evaluations.
    - `los`: the world line of sight turned about.
    """

    angles_deg: np.ndarray
    deviance: np.ndarray
    gain_factor: np.ndarray
    minima: np.ndarray
    exact: bool
    los: np.ndarray

    @property
    def best_deg(self) -> float:
        """The roll of the lowest deviance."""
        return float(self.angles_deg[self.minima[0]])

    def params(self, phys: PhysicalParams, i: int) -> PhysicalParams:
        """``phys`` turned to the scan's ``i``-th roll, its gain re-scaled."""
        p = rolled_about(phys, float(self.angles_deg[i]), self.los)
        g = jnp.asarray(np.asarray(phys.gain) * self.gain_factor[i], jnp.asarray(phys.gain).dtype)
        return eqx.tree_at(lambda x: x.gain, p, g)


def _expect(model, phys, aux) -> np.ndarray:
    pure = _pure(model)
    try:
        return np.asarray(_expected_jit(pure, phys, aux), np.float64)
    except TypeError:  # pragma: no cover - a model that is not an equinox module
        return np.asarray(model.expected(phys, aux), np.float64)


def _cyclic_minima(d: np.ndarray) -> np.ndarray:
    left, right = np.roll(d, 1), np.roll(d, -1)
    idx = np.flatnonzero((d <= left) & (d < right))
    if idx.size == 0:  # a flat scan: its first point
        idx = np.array([int(np.argmin(d))])
    return idx[np.argsort(d[idx], kind="stable")]


def roll_scan(
    model,
    data,
    phys: PhysicalParams,
    *,
    noise=None,
    los=None,
    monostatic: bool | None = None,
    n_grid: int = 180,
    n_direct: int = 24,
    aux=None,
) -> RollScan:
    """The deviance of ``phys`` at every roll about the line of sight (module docstring).

    **Arguments:**

    - `model`: forward model (``prepare``/``expected``); `data`: counts ``(C, B)``.
    - `phys`: the parameters turned; its attitude is roll 0.
    - `noise`: the noise model whose deviance is scanned (default
      :class:`~inversion.PoissonCounts`).
    - `los`: world line of sight (default: the model's sensor's, else ``+z``).
    - `monostatic`: default from the model's sensor (True without one). True: five
      evaluations and the exact harmonic reconstruction on ``n_grid`` rolls over 180 deg;
      False: ``n_direct`` evaluations over 360 deg, each with its own visibility.
    - `aux`: the model's prepared visibility at ``phys`` (monostatic: shared by every roll).

    **Returns:** :class:`RollScan`.
    """
    from ._observability import line_of_sight_of

    if n_grid < _N_HARMONIC or n_direct < 4:
        raise ValueError(f"roll_scan: n_grid >= 5 and n_direct >= 4, got {n_grid}, {n_direct}")
    noise = PoissonCounts() if noise is None else noise
    sensor = getattr(_pure(model), "sensor", None)
    if los is None:
        los = line_of_sight_of(model)
        los = np.array([0.0, 0.0, 1.0]) if los is None else los
    los = np.asarray(los, np.float64)
    if monostatic is None:
        monostatic = bool(getattr(sensor, "monostatic", True)) if sensor is not None else True
    y = np.asarray(data, np.float64)
    if monostatic:
        aux = model.prepare(phys) if aux is None else aux
        base = np.arange(_N_HARMONIC) * (180.0 / _N_HARMONIC)
        samples = np.stack([_expect(model, rolled_about(phys, a, los), aux) for a in base])
        # exact: a degree-2 trigonometric polynomial in theta = 2 phi from 5 equispaced samples
        f = np.fft.rfft(samples, axis=0) / _N_HARMONIC  # (3, C, B)
        angles = np.arange(n_grid) * (180.0 / n_grid)
        theta = np.deg2rad(2.0 * angles)
        e1 = np.exp(1j * theta)[:, None, None]
        mu = f[0].real[None] + 2.0 * np.real(f[1][None] * e1) + 2.0 * np.real(f[2][None] * e1**2)
    else:
        angles = np.arange(n_direct) * (360.0 / n_direct)
        mu = []
        for a in angles:
            p = rolled_about(phys, a, los)
            mu.append(_expect(model, p, model.prepare(p)))
        mu = np.stack(mu)
    # the gain profiled in closed form: each roll's expected total equals the data's (the
    # Poisson maximum-likelihood gain without background; a converged fit already has it)
    tot = mu.sum(axis=(1, 2))
    ok = np.isfinite(tot) & (tot > 0) & (y.sum() > 0)
    scale = np.where(ok, y.sum() / np.where(ok, tot, 1.0), 1.0)
    mu = mu * scale[:, None, None]
    dev_of = deviance_function(noise, phys)
    dev = np.array([dev_of(y, m) for m in mu])
    dev = np.where(np.isfinite(dev), dev, np.inf)
    return RollScan(
        angles_deg=angles,
        deviance=dev,
        gain_factor=scale,
        minima=_cyclic_minima(dev),
        exact=bool(monostatic),
        los=los,
    )
