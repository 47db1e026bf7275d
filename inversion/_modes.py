r"""Equivalent and near-equivalent attitudes of a fit: the modes a posterior can have.

A monostatic measurement of a body at attitude ``R`` (body -> world) cannot tell ``R`` from

- ``R B`` for a proper rotation ``B`` of the body's symmetry group (about its centre ``c``):
  the same scene, so the same data in every channel and bin;
- ``C2(k) R B``, the half turn about the line of sight ``k`` (world, object -> sensor): it
  keeps every depth and turns the polarization frame by 180 deg, the identity on Stokes
  vectors (:func:`inversion.los_half_turn`); exact for a monostatic sensor only;
- ``P R B`` and ``C2(k) P R B`` for an improper element ``B`` (mirror plane,
  rotoreflection, inversion) and ``P = I - 2 w w^T`` the world mirror through the plane
  that holds the line of sight and the sensor's x polarization reference (``w = +y`` for
  the canonical sensor): the mirror image of the scene, with the same range profiles and
  Mueller profiles ``D M D``, ``D = diag(1, 1, -1, -1)`` (:func:`inversion.mirror_attitude`).
  Only the off-block Mueller elements tell it apart, and glossy returns have none: a second
  mode, exactly as likely when those elements are below the noise;
- any of these with an element ``B`` that the mesh has only approximately
  (:func:`ppr.mesh_symmetries` at a loose tolerance): a near-degenerate mode, which a local
  fit and its Cramer-Rao bound do not see.

The body symmetry acts about the centre ``c``: the scene at ``W R B`` is the scene at ``R``
(or its mirror image) moved by ``W R (B c - c)``, so its range profiles are shifted by
``-k . R (B c - c)``; a refit from that attitude starts at the range offset plus
:attr:`Mode.range_shift` ``= k . R (B c - c)`` (zero for a body centred on its origin).

:func:`equivalent_attitudes` lists the exactly equivalent attitudes (same data);
:func:`candidate_modes` lists the distinct modes to refit: attitudes that are not exactly
equivalent to the fit or to each other, within ``min_separation_deg`` modulo the exact
equivalences. :func:`inversion.mode_check` refits them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import ppr
from ppr.geometry import quat_angle_deg, quat_multiply_host, quat_to_matrix_host

from ._grid import as_symmetry, canonical_sign

__all__ = ["Mode", "candidate_modes", "equivalent_attitudes"]

_WORLD_LABELS = {
    "identity": "",
    "half turn": "half turn about the line of sight",
    "mirror": "mirror image",
    "mirror, half turn": "mirror image turned about the line of sight",
}


@dataclasses.dataclass(frozen=True, eq=False)
class Mode:
    """One attitude equivalent or nearly equivalent to a fit's (:func:`candidate_modes`).

    - `quaternion`: ``(4,)`` the attitude ``W R B`` (body -> world, scalar first).
    - `label`: what it is: ``"fit"``, ``"symmetry: C4 about body +z"``, ``"half turn about
      the line of sight"``, ``"mirror image"``, ``"near symmetry: C2 about body x (residual
      3.1e-03)"``, ...
    - `kind`: ``"fit"``, ``"symmetry"``, ``"half turn"``, ``"mirror"``,
      ``"near symmetry"``, ``"near mirror"``, ``"roll"`` (another minimum of the roll about
      the line of sight) or ``"other optimum"`` (another line of sight that explains the data
      at the fit's materials; ``inversion.invert``).
    - `exact`: the data at this attitude are those at the fit's, in every channel and bin
      (an exact proper symmetry, with or without the half turn of a monostatic sensor).
    - `range_shift`: metres to add to the fit's range offset (the body centre's move along
      the line of sight; module docstring).
    - `body`: ``(3, 3)`` the body element ``B``; `world`: the world operation ``W``
      (``"identity"``, ``"half turn"``, ``"mirror"``, ``"mirror, half turn"``);
      `residual`: ``B``'s residual relative to the mesh size (:func:`ppr.mesh_symmetries`).
    - `start`: the parameters to refit from (an optimum found by its own search, with its own
      roughness, gain and range offset), or None: the fit's with this attitude and the range
      offset moved by `range_shift`.
    """

    quaternion: np.ndarray
    label: str
    kind: str
    exact: bool
    range_shift: float
    body: np.ndarray
    world: str
    residual: float
    start: object = None

    def to_dict(self) -> dict:
        return {
            "quaternion": [float(x) for x in self.quaternion],
            "label": self.label,
            "kind": self.kind,
            "exact": bool(self.exact),
            "range_shift_m": float(self.range_shift),
            "world": self.world,
            "body_residual": float(self.residual),
        }


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or abs(np.linalg.norm(a) - 1) > 1e-6:
        raise ValueError(f"{name} must be a unit 3-vector, got {a.tolist()}")
    return a / np.linalg.norm(a)


def _world_ops(los, world_normal, mirror: bool) -> dict[str, np.ndarray]:
    k = _unit(los, "los")
    c2 = 2.0 * np.outer(k, k) - np.eye(3)
    ops = {"identity": np.eye(3), "half turn": c2}
    if mirror:
        w = _unit(world_normal, "world_normal")
        if abs(np.dot(k, w)) > 1e-6:
            raise ValueError(
                f"world_normal {w.tolist()} must be perpendicular to the line of sight "
                f"{k.tolist()} (the world mirror plane holds the line of sight)"
            )
        p = np.eye(3) - 2.0 * np.outer(w, w)
        ops["mirror"] = p
        ops["mirror, half turn"] = c2 @ p
    return ops


def _check_quat(q) -> np.ndarray:
    q = np.asarray(q, np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0:
        raise ValueError(f"attitude must be a finite quaternion (w, x, y, z), got {q.tolist()}")
    return q / np.linalg.norm(q)


def _all_candidates(q, sym: ppr.MeshSymmetry, ops, los, exact_tol: float, half_turn_exact: bool):
    """Every (W, B) combination as a Mode, in priority order for the labels."""
    r = quat_to_matrix_host(q)
    labels = sym.labels
    out, plain = [], []  # plain: the body element is a plain mirror plane
    for b, lab, res, det in zip(sym.matrices, labels, sym.residuals, sym.determinants, strict=True):
        exact_b = res <= exact_tol
        for world, wm in ops.items():
            if (det < 0) != world.startswith("mirror"):
                continue
            rp = wm @ r @ b
            shift = float(los @ (r @ (b @ sym.centre - sym.centre)))
            is_identity = lab == "identity"
            if det > 0:
                if not exact_b:
                    kind = "near symmetry"
                elif world == "identity":
                    kind = "fit" if is_identity else "symmetry"
                else:
                    kind = "half turn"
            else:
                kind = "mirror" if exact_b else "near mirror"
            exact = exact_b and det > 0 and (world == "identity" or half_turn_exact)
            parts = [_WORLD_LABELS[world]] if _WORLD_LABELS[world] else []
            if det > 0 and not is_identity:  # every exact improper element: one mirror image
                parts.append(f"{'symmetry' if exact_b else 'near symmetry'}: {lab}")
            if not exact_b:
                if det < 0:
                    parts.append(f"near {lab}")
                parts[-1] += f" (residual {res:.2g})"
            label = ", ".join(parts) if parts else "fit"
            plain.append(lab.startswith("mirror"))
            out.append(
                Mode(
                    quaternion=canonical_sign(ppr.matrix_to_quat(rp)),
                    label=label,
                    kind=kind,
                    exact=bool(exact),
                    range_shift=shift,
                    body=b,
                    world=world,
                    residual=float(res),
                )
            )
    rank = {"fit": 0, "symmetry": 1, "half turn": 2, "mirror": 3, "near symmetry": 4}
    rank["near mirror"] = 5
    # within a kind: smaller residual first, a plain mirror plane before other improper
    # elements (the mirror image's start), then the symmetry's own element order
    order = sorted(
        range(len(out)),
        key=lambda i: (
            rank[out[i].kind],
            out[i].residual,
            not plain[i],
            i,
        ),
    )
    return [out[i] for i in order]


def _exact_group(sym: ppr.MeshSymmetry, ops, exact_tol: float, half_turn_exact: bool):
    """(world quaternions, body quaternions) of the exact equivalences."""
    rot = sym.matrices[(sym.determinants > 0) & (sym.residuals <= exact_tol)]
    body = np.stack([ppr.matrix_to_quat(b) for b in rot])
    worlds = [np.array([1.0, 0, 0, 0])]
    if half_turn_exact:
        worlds.append(ppr.matrix_to_quat(ops["half turn"]))
    return np.stack(worlds), body


def _orbit(q, worlds, body) -> np.ndarray:
    """``(|W| |B|, 4)``: ``w q b`` for every exact equivalence."""
    qb = quat_multiply_host(np.asarray(q)[None, :], body)  # (B, 4)
    return quat_multiply_host(worlds[:, None, :], qb[None, :, :]).reshape(-1, 4)


def _prepare(q, symmetry, los, world_normal, mirror, exact_tol, tol):
    q = _check_quat(q)
    sym = as_symmetry(symmetry, tol=tol)
    ops = _world_ops(los, world_normal, mirror)
    if not (np.isfinite(exact_tol) and exact_tol >= 0):
        raise ValueError(f"exact_tol must be a finite number >= 0, got {exact_tol!r}")
    return q, sym, ops, _unit(los, "los")


def equivalent_attitudes(
    q,
    symmetry,
    *,
    half_turn: bool = True,
    los=(0.0, 0.0, 1.0),
    exact_tol: float = 1e-6,
    tol: float = 1e-6,
) -> list[Mode]:
    """Every attitude that gives exactly the data of attitude ``q``: ``R B`` for the exact
    proper elements ``B`` of the body's symmetry and, with ``half_turn`` (a monostatic
    sensor), their half turns ``C2(k) R B`` about the line of sight ``los``. The first is
    ``q`` itself (label ``"fit"``); duplicates (attitudes a symmetry fixes) are dropped.

    ``symmetry``: a named class, a :class:`ppr.MeshSymmetry` or a :class:`ppr.Mesh` (its own
    group at ``tol``, :func:`inversion.as_symmetry`). ``exact_tol``: elements with a relative
    residual above it are only near symmetries (:func:`candidate_modes`), not listed here.
    """
    q, sym, ops, k = _prepare(q, symmetry, los, None, False, exact_tol, tol)
    modes = [
        m
        for m in _all_candidates(q, sym, ops, k, exact_tol, half_turn)
        if m.exact and (half_turn or m.world == "identity")
    ]
    kept: list[Mode] = []
    for m in modes:
        if all(quat_angle_deg(m.quaternion, k.quaternion) > 1e-3 for k in kept):
            kept.append(m)
    return kept


def candidate_modes(
    q,
    symmetry,
    *,
    mirror: bool = True,
    near: bool = True,
    half_turn_exact: bool = True,
    los=(0.0, 0.0, 1.0),
    world_normal=(0.0, 1.0, 0.0),
    exact_tol: float = 1e-6,
    min_separation_deg: float = 1.0,
    tol: float = 1e-6,
) -> list[Mode]:
    """The distinct modes to refit for a fit at attitude ``q`` (module docstring).

    The first mode is the fit itself (label ``"fit"``). The others are, in this order, the
    mirror image (with ``mirror``, when the body has an exact improper element), the near
    symmetries and near mirror images (with ``near``, elements with a relative residual
    above ``exact_tol``), and, when ``half_turn_exact`` is False (a bistatic sensor), the
    half turn about the line of sight. A candidate within ``min_separation_deg`` (geodesic)
    of an earlier mode, modulo the exact equivalences (:func:`equivalent_attitudes`), is
    the same mode and is dropped: when the line of sight lies in a mirror plane, for
    instance, the mirror image can coincide with the fit.

    ``symmetry``: a named class, a :class:`ppr.MeshSymmetry` or a :class:`ppr.Mesh` (its own
    group at ``tol``; pass ``ppr.mesh_symmetries(mesh, tol=1e-2)`` to see near symmetries).
    ``los``: world line of sight (object -> sensor; ``+z`` for the canonical sensor);
    ``world_normal``: normal of the world mirror plane (holds the line of sight and the
    sensor's x polarization reference; ``+y`` for the canonical sensor).
    """
    if not (np.isfinite(min_separation_deg) and min_separation_deg >= 0):
        raise ValueError(f"min_separation_deg must be >= 0, got {min_separation_deg!r}")
    q, sym, ops, k = _prepare(q, symmetry, los, world_normal, mirror, exact_tol, tol)
    worlds, body = _exact_group(sym, ops, exact_tol, half_turn_exact)
    kept: list[Mode] = []
    orbits: list[np.ndarray] = []
    for m in _all_candidates(q, sym, ops, k, exact_tol, half_turn_exact):
        if m.exact and m.kind != "fit":
            continue
        if not near and m.kind.startswith("near"):
            continue
        d = [quat_angle_deg(o, m.quaternion).min() for o in orbits]
        if d and min(d) <= min_separation_deg:
            continue
        kept.append(m)
        orbits.append(_orbit(m.quaternion, worlds, body))
    return kept


def mode_separation_deg(
    q_a, q_b, symmetry, *, half_turn_exact: bool = True, los=(0.0, 0.0, 1.0), exact_tol=1e-6
) -> float:
    """Geodesic angle (deg) between two attitudes modulo the exact equivalences (the exact
    proper elements of ``symmetry`` and, when ``half_turn_exact``, the half turn about
    ``los``)."""
    sym = as_symmetry(symmetry)
    ops = _world_ops(los, None, False)
    worlds, body = _exact_group(sym, ops, exact_tol, half_turn_exact)
    return float(quat_angle_deg(_orbit(_check_quat(q_a), worlds, body), _check_quat(q_b)).min())
