"""Random scattering geometries, shared by the tests and the benchmarks (one sampler, so a
benchmark's error figures and the tests' tolerances refer to the same distribution).

Not part of the public API; NumPy only (geometries are inputs, not traced).
"""

from __future__ import annotations

import numpy as np


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bistatic_geometry(rng: np.random.Generator, theta_deg: np.ndarray, psi: float):
    """Random facet geometries at given incidence angles and bistatic angle ``psi`` (rad).

    For each incidence ``theta_deg[i]``: a random unit normal, an illumination direction
    ``k_in`` at that angle from it in a random azimuth, a receiver direction at angle ``psi``
    from ``k_in`` in a random azimuth (``k_in`` itself where that would fall below the
    facet's horizon), and random beam frame vectors perpendicular to each beam.

    **Returns:** ``(normal, k_in, k_out, frame_in, frame_out)``, each ``(n, 3)``.
    """
    th = np.radians(np.asarray(theta_deg, np.float64))[:, None]
    n = th.shape[0]
    nrm = _unit(rng.normal(size=(n, 3)))
    t1 = _unit(np.cross(nrm, rng.normal(size=(n, 3))))
    k = np.cos(th) * nrm + np.sin(th) * t1
    ax = _unit(np.cross(k, rng.normal(size=(n, 3))))
    kp = _unit(np.cos(psi) * k + np.sin(psi) * ax)
    kp = np.where(np.sum(kp * nrm, -1, keepdims=True) > 0, kp, k)
    fi = _unit(np.cross(k, rng.normal(size=(n, 3))))
    fo = _unit(np.cross(kp, rng.normal(size=(n, 3))))
    return nrm, k, kp, fi, fo
