"""Parametric shapes (metres, body frame, outward normals), each with named parts.

Every function returns a validated :class:`ppr.Mesh` whose ``parts`` name the material slots
(``"body"``, ``"solar_panel"``, ``"panel_back"``, ...); a scene maps part names to materials.

- :func:`plate`: square/rectangular plate in the z = 0 plane, normal +z (one-sided).
- :func:`box`, :func:`cubesat`: boxes (1U = 0.1 m cube, 3U = 0.1 x 0.1 x 0.34 m).
- :func:`cylinder`, :func:`cone`, :func:`sphere` (icosphere).
- :func:`cubesat_with_panels`: a CubeSat body with two deployed solar panels sticking out of
  its +y and -y faces in the x = 0 plane: non-convex, self-shadowing, with 90 deg
  panel-body dihedrals.
"""

from __future__ import annotations

import numpy as np

from ._mesh import Mesh, check_mesh, concatenate, subdivide

__all__ = [
    "plate",
    "box",
    "cubesat",
    "cylinder",
    "cone",
    "sphere",
    "cubesat_with_panels",
    "by_name",
]


def _positive(name: str, value) -> float:
    if isinstance(value, str | bool) or not np.isscalar(value) and np.ndim(value) != 0:
        raise ValueError(f"{name} must be a positive finite length in metres, got {value!r}")
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite length in metres, got {value!r}")
    return v


def _count(name: str, value, minimum: int) -> int:
    """An integer parameter (a number of sections, subdivisions): ``1.9`` or ``"3"`` are
    refused, not truncated or parsed."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


MAX_FACES = 2_000_000
"""Most faces a generated shape may have (a count parameter past it is refused before any
memory is allocated: an icosphere of 12 subdivisions has 3.4e8 faces and exhausts memory)."""


def _budget(name: str, value, faces: float) -> None:
    """``faces``: the count as a float, its count parameter clamped first (a huge integer
    would overflow the conversion: the clamp is far above any budget)."""
    if faces > MAX_FACES:
        raise ValueError(
            f"{name} = {value!r} would make {faces:.3g} faces, more than the {MAX_FACES:.3g} a "
            "generated shape may have (ppr.shapes.MAX_FACES)"
        )


def _from_trimesh(tm, part: str) -> Mesh:
    return Mesh(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces), None, (part,))


def plate(
    width: float = 1.0, height: float | None = None, *, subdivisions: int = 1, part: str = "body"
) -> Mesh:
    """Rectangular plate ``width x height`` (x by y) centred at the origin in z = 0, normal +z,
    split into ``subdivisions^2`` squares of two triangles each."""
    w = _positive("width", width)
    h = w if height is None else _positive("height", height)
    n = _count("subdivisions", subdivisions, 1)
    _budget("subdivisions", subdivisions, 2.0 * float(min(n, 10**9)) ** 2)
    xs = np.linspace(-w / 2, w / 2, n + 1)
    ys = np.linspace(-h / 2, h / 2, n + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    verts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return check_mesh(Mesh(verts, faces, None, (part,)), name="plate")


def box(extents=(0.1, 0.1, 0.1), *, max_edge: float | None = None, part: str = "body") -> Mesh:
    """Axis-aligned box centred at the origin (12 triangles, optionally subdivided to
    ``max_edge``)."""
    import trimesh

    ext = [_positive(f"extents[{i}]", e) for i, e in enumerate(np.broadcast_to(extents, (3,)))]
    m = _from_trimesh(trimesh.creation.box(extents=ext), part)
    if max_edge is not None:
        m = subdivide(m, max_edge)
    return check_mesh(m, name="box")


def cubesat(units: int = 1, *, max_edge: float | None = None, part: str = "body") -> Mesh:
    """CubeSat body: 1U is a 0.1 m cube, 3U is 0.1 x 0.1 x 0.34 m (long axis z)."""
    lengths = {1: 0.1, 2: 0.227, 3: 0.34, 6: 0.34}
    if isinstance(units, bool) or units not in lengths:
        raise ValueError(f"units must be one of {sorted(lengths)}, got {units!r}")
    ext = (0.2 if units == 6 else 0.1, 0.1, lengths[units])
    return box(ext, max_edge=max_edge, part=part)


def cylinder(
    radius: float = 0.5, height: float = 1.0, *, sections: int = 32, part: str = "body"
) -> Mesh:
    """Closed cylinder along z, centred at the origin."""
    import trimesh

    n = _count("sections", sections, 3)
    _budget("sections", sections, 4.0 * min(n, 10**12))
    tm = trimesh.creation.cylinder(
        radius=_positive("radius", radius), height=_positive("height", height), sections=n
    )
    return check_mesh(_from_trimesh(tm, part), name="cylinder")


def cone(
    radius: float = 0.5, height: float = 1.0, *, sections: int = 32, part: str = "body"
) -> Mesh:
    """Closed cone along z, base at z = 0, apex at z = height."""
    import trimesh

    n = _count("sections", sections, 3)
    _budget("sections", sections, 2.0 * min(n, 10**12))
    tm = trimesh.creation.cone(
        radius=_positive("radius", radius), height=_positive("height", height), sections=n
    )
    return check_mesh(_from_trimesh(tm, part), name="cone")


def sphere(radius: float = 0.5, *, subdivisions: int = 3, part: str = "body") -> Mesh:
    """Icosphere (20 * 4^subdivisions faces) of circumradius ``radius``."""
    import trimesh

    n = _count("subdivisions", subdivisions, 0)
    _budget("subdivisions", subdivisions, 20.0 * 4.0 ** min(n, 100))
    tm = trimesh.creation.icosphere(subdivisions=n, radius=_positive("radius", radius))
    return check_mesh(_from_trimesh(tm, part), name="sphere")


def cubesat_with_panels(
    units: int = 3,
    *,
    panel_span: float = 0.3,
    panel_thickness: float = 0.002,
    max_edge: float | None = None,
) -> Mesh:
    """CubeSat body plus two deployed solar panels (parts ``"body"``, ``"solar_panel"``,
    ``"panel_back"``).

    The panels are thin boxes ``panel_thickness`` thick (x), ``panel_span`` long (y) and as
    long as the body (z), attached to the body's +y and -y faces in the x = 0 plane. Their +x
    faces are solar cells (``"solar_panel"``), every other panel face is ``"panel_back"``.
    Panel front and body side faces meet in 90 deg concave dihedrals.
    """
    body = cubesat(units)
    _, by, bz = np.ptp(np.asarray(body.vertices), axis=0)
    span = _positive("panel_span", panel_span)
    t = _positive("panel_thickness", panel_thickness)
    panels = []
    for sign in (+1.0, -1.0):
        pm = box((t, span, bz))
        v = np.asarray(pm.vertices) + np.array([0.0, sign * (by / 2 + span / 2), 0.0])
        tri = v[np.asarray(pm.faces)]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        front = nrm[:, 0] > 0.5 * np.linalg.norm(nrm, axis=1)
        panels.append(
            Mesh(v, pm.faces, np.where(front, 0, 1).astype(np.int32), ("solar_panel", "panel_back"))
        )
    m = concatenate([body, *panels])
    if max_edge is not None:
        m = subdivide(m, max_edge)
    return check_mesh(m, name="cubesat_with_panels")


_SHAPES = {
    "plate": plate,
    "box": box,
    "cubesat": cubesat,
    "cylinder": cylinder,
    "cone": cone,
    "sphere": sphere,
    "cubesat_with_panels": cubesat_with_panels,
}


def by_name(name: str, **params) -> Mesh:
    """Build a parametric shape by name (used by scene configs)."""
    if name not in _SHAPES:
        raise ValueError(f"unknown shape {name!r}; known shapes: {sorted(_SHAPES)}")
    try:
        return _SHAPES[name](**params)
    except TypeError as exc:
        raise ValueError(f"bad parameters for shape {name!r}: {params!r} ({exc})") from exc
