"""Triangle meshes: validated container, trimesh loading, fixed-capacity kernel arrays.

Units are metres. Each face carries a *part* index (``material_ids``) into the mesh's
``parts`` names (e.g. ``("body", "solar_panel")``); a scene maps part names to materials.

Validation (host side, concrete arrays only):

- :class:`Mesh` construction rejects empty meshes, non-finite vertices, wrong shapes and
  out-of-range face or part indices (``ValueError`` naming the field and value).
- :func:`check_mesh` additionally rejects zero-area (degenerate) faces and duplicate faces
  (same three vertex positions with the same orientation) unless ``on_degenerate="drop"``,
  in which case they are removed. Back-to-back faces (same vertices, opposite winding) form
  a legitimate two-sided sheet and are kept. The pulse kernel itself stays finite (values and
  gradients) if it is handed zero-area or duplicate faces anyway: a zero-area face has zero
  weight and a fallback normal.

:func:`mesh_arrays` turns a mesh into the structure-of-arrays the jitted kernel consumes,
padded to a fixed capacity with a validity mask, so that meshes of similar size reuse one
compilation.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, Bool, Float, Int

AREA_RTOL = 1e-12
"""Faces with area below ``AREA_RTOL * (longest edge)^2`` (collinear vertices: float64
rounding leaves ~1e-16 of it), a height within 8 rounding steps of their coordinates' size
(collinear in the stored precision), or every edge below ``AREA_RTOL`` of the bounding-box
diagonal (collapsed to a point) count as degenerate. The test is the face's own shape, not its
size against the mesh: a real 0.1 mm facet on a 100 m structure is kept."""


def _as_vertices(x) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _as_int(x) -> Array:
    if _concrete(x) and not isinstance(x, jax.Array):
        a = np.asarray(x)
        if a.dtype.kind == "f" and a.size and not np.all(a == np.round(a)):
            # 2.5 would silently be vertex 2
            bad = tuple(int(i) for i in np.argwhere(a != np.round(a))[0])
            raise ValueError(
                f"Mesh face and material indices must be integers, got {float(a[bad])} at {bad}"
            )
        if a.dtype.kind not in "iuf" and a.size:
            raise ValueError(f"Mesh face and material indices must be integers, got {a.dtype}")
    return jnp.asarray(x, dtype=jnp.int32)


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


class Mesh(eqx.Module):
    """A triangle mesh with a part (material slot) per face.

    **Arguments:**

    - `vertices`: ``(V, 3)`` positions in metres, body frame.
    - `faces`: ``(F, 3)`` vertex indices, counter-clockwise seen from outside (the outward
      normal is ``(v1 - v0) x (v2 - v0)``).
    - `material_ids`: ``(F,)`` index into ``parts`` (default all 0).
    - `parts`: names of the material slots (static), default ``("default",)``.
    """

    vertices: Array = eqx.field(converter=_as_vertices)
    faces: Array = eqx.field(converter=_as_int)
    material_ids: Array = eqx.field(converter=_as_int)
    parts: tuple[str, ...] = eqx.field(static=True, default=("default",))

    def __init__(self, vertices, faces, material_ids=None, parts=("default",)):
        self.vertices = vertices
        self.faces = faces
        if material_ids is None:
            material_ids = np.zeros(np.shape(faces)[0] if np.ndim(faces) else 0, np.int32)
        self.material_ids = material_ids
        self.parts = tuple(str(p) for p in parts)

    def __check_init__(self):
        v, f, mid = self.vertices, self.faces, self.material_ids
        if v.ndim != 2 or v.shape[-1] != 3:
            raise ValueError(f"Mesh.vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[-1] != 3:
            raise ValueError(f"Mesh.faces must have shape (F, 3), got {f.shape}")
        if v.shape[0] == 0 or f.shape[0] == 0:
            raise ValueError(
                f"Mesh is empty: {v.shape[0]} vertices and {f.shape[0]} faces (need at least one "
                "triangle)"
            )
        if mid.shape != (f.shape[0],):
            raise ValueError(f"Mesh.material_ids must have shape ({f.shape[0]},), got {mid.shape}")
        if len(self.parts) == 0:
            raise ValueError("Mesh.parts must name at least one part")
        if len(set(self.parts)) != len(self.parts):
            dup = next(p for p in self.parts if self.parts.count(p) > 1)
            raise ValueError(
                f"Mesh.parts names {dup!r} twice: each part is a material slot of its own "
                f"name, got {self.parts}"
            )
        if _concrete(v):
            a = np.asarray(v)
            bad = ~np.isfinite(a).all(axis=1)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"Mesh.vertices must be finite: {int(bad.sum())} non-finite vertices, "
                    f"first is vertex {i} = {a[i].tolist()}"
                )
        if _concrete(f):
            fa = np.asarray(f)
            if fa.min() < 0 or fa.max() >= v.shape[0]:
                raise ValueError(
                    f"Mesh.faces index out of range [0, {v.shape[0]}): "
                    f"min {fa.min()}, max {fa.max()}"
                )
        if _concrete(mid):
            ma = np.asarray(mid)
            if ma.min() < 0 or ma.max() >= len(self.parts):
                raise ValueError(
                    f"Mesh.material_ids out of range [0, {len(self.parts)}) for parts "
                    f"{self.parts}: min {ma.min()}, max {ma.max()}"
                )

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def triangles(self) -> np.ndarray:
        """``(F, 3, 3)`` float64 vertex positions per face (host)."""
        return np.asarray(self.vertices, dtype=np.float64)[np.asarray(self.faces)]

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(
            vertices=np.asarray(self.vertices, np.float64),
            faces=np.asarray(self.faces),
            process=False,
        )

    def max_edge(self) -> float:
        """Longest edge in metres (bounds every face's depth extent along any direction)."""
        t = self.triangles()
        e = np.linalg.norm(t - np.roll(t, 1, axis=1), axis=-1)
        return float(e.max())

    def bounding_radius(self) -> float:
        """Radius of the sphere about the body origin that contains every vertex."""
        return float(np.linalg.norm(np.asarray(self.vertices, np.float64), axis=1).max())


def face_areas_normals(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas ``(F,)`` and unit outward normals ``(F, 3)`` of ``(F, 3, 3)`` triangles (host,
    float64). Zero-area faces get area 0 and the fallback normal +z."""
    tri = np.asarray(tri, np.float64)
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm = np.linalg.norm(cr, axis=1)
    area = 0.5 * nrm
    ok = nrm > 0
    n = np.zeros_like(cr)
    n[:, 2] = 1.0
    n[ok] = cr[ok] / nrm[ok, None]
    return area, n


def _degenerate_and_duplicate(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    tri = mesh.triangles()
    v = np.asarray(mesh.vertices, np.float64)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    area, _ = face_areas_normals(tri)
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(-1)
    # collinear up to the rounding of the stored coordinates: a float32 mesh 6 m from its
    # origin rounds a collinear triple to heights of ~1e-6 m, far above AREA_RTOL of a short
    # edge
    eps = float(np.finfo(np.asarray(mesh.vertices).dtype).eps)
    height = 2.0 * area / np.maximum(edge, 1e-300)
    size = np.abs(tri).max(axis=(1, 2))
    degenerate = (
        (area <= AREA_RTOL * edge**2)
        | (edge <= AREA_RTOL * max(diag, 1e-300))
        | (height <= 8.0 * eps * size)
    )
    # duplicates: same positions, same orientation (cyclic rotations of one ordered triple)
    scale = max(diag, 1e-300) * 1e-9
    key = np.round(tri / scale).astype(np.int64)  # (F, 3, 3)
    # canonical cyclic rotation: start at the lexicographically smallest vertex
    flat_v = key.reshape(-1, 3)
    rank = np.empty(len(flat_v), np.int64)
    rank[np.lexsort(flat_v.T[::-1])] = np.arange(len(flat_v))
    start = np.argmin(rank.reshape(-1, 3), axis=1)
    idx = (start[:, None] + np.arange(3)[None, :]) % 3
    canon = np.take_along_axis(key, idx[:, :, None], axis=1).reshape(len(key), 9)
    _, first = np.unique(canon, axis=0, return_index=True)
    duplicate = np.ones(len(canon), bool)
    duplicate[first] = False
    duplicate &= ~degenerate
    return degenerate, duplicate


_DROP_HINT = (
    'on_degenerate = "drop" removes them (load_mesh\'s argument; in a config, the mesh '
    'table\'s key: mesh = {path = "...", on_degenerate = "drop"})'
)


def check_mesh(mesh: Mesh, on_degenerate: str = "error", name: str = "mesh") -> Mesh:
    """Reject (``"error"``) or remove (``"drop"``) zero-area and duplicate faces.

    Raises ``ValueError`` naming ``name``, the count and the first offending face.
    """
    if on_degenerate not in ("error", "drop"):
        raise ValueError(f"on_degenerate must be 'error' or 'drop', got {on_degenerate!r}")
    deg, dup = _degenerate_and_duplicate(mesh)
    if not (deg.any() or dup.any()):
        return mesh
    if on_degenerate == "error":
        tri = mesh.triangles()
        if deg.any():
            i = int(np.flatnonzero(deg)[0])
            raise ValueError(
                f"{name}: {int(deg.sum())} degenerate (zero-area) faces, first is face {i} with "
                f"vertices {tri[i].tolist()}; {_DROP_HINT}"
            )
        i = int(np.flatnonzero(dup)[0])
        raise ValueError(
            f"{name}: {int(dup.sum())} duplicate faces, first is face {i} with vertices "
            f"{tri[i].tolist()}; {_DROP_HINT}"
        )
    keep = ~(deg | dup)
    if not keep.any():
        raise ValueError(f"{name}: every face is degenerate or duplicate; nothing left")
    return Mesh(
        mesh.vertices, np.asarray(mesh.faces)[keep], np.asarray(mesh.material_ids)[keep], mesh.parts
    )


def concatenate(meshes: Sequence[Mesh]) -> Mesh:
    """Concatenate meshes, merging their part lists by name."""
    parts: list[str] = []
    vs, fs, ms = [], [], []
    off = 0
    for m in meshes:
        remap = []
        for p in m.parts:
            if p not in parts:
                parts.append(p)
            remap.append(parts.index(p))
        vs.append(np.asarray(m.vertices, np.float64))
        fs.append(np.asarray(m.faces) + off)
        ms.append(np.asarray(remap, np.int32)[np.asarray(m.material_ids)])
        off += vs[-1].shape[0]
    return Mesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(ms), tuple(parts))


def subdivide(mesh: Mesh, max_edge: float) -> Mesh:
    """Split faces until no edge is longer than ``max_edge`` metres (parts are kept)."""
    import trimesh

    if not (max_edge > 0 and np.isfinite(max_edge)):
        raise ValueError(f"max_edge must be a positive finite length in metres, got {max_edge!r}")
    from .shapes import MAX_FACES  # noqa: PLC0415

    # each split quarters a face and halves its edges: faces * 4^(splits its longest edge needs)
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1), axis=-1)
    splits = np.ceil(np.log2(np.maximum(longest / max_edge, 1.0)))
    faces = float(np.sum(4.0 ** np.minimum(splits, 200.0)))
    if faces > max(MAX_FACES, mesh.n_faces):  # the growth is budgeted, not the input
        raise ValueError(
            f"max_edge = {max_edge!r} m would make ~{faces:.3g} faces, more than the "
            f"{MAX_FACES:.3g} a subdivided mesh may have (ppr.shapes.MAX_FACES)"
        )
    v, f, idx = trimesh.remesh.subdivide_to_size(
        np.asarray(mesh.vertices, np.float64),
        np.asarray(mesh.faces),
        max_edge,
        max_iter=30,
        return_index=True,
    )
    return Mesh(v, f, np.asarray(mesh.material_ids)[idx], mesh.parts)


def from_trimesh(tm, part: str = "default") -> Mesh:
    return Mesh(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces), None, (part,))


MESH_FORMATS = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")
"""File formats :func:`load_mesh` reads (through trimesh)."""


def part_key(name: str) -> str:
    """A part name usable as a config key: letters, digits, ``_`` and ``-`` only (dots
    would split ``--set materials.<part>=...`` into nested keys)."""
    key = re.sub(r"[^A-Za-z0-9_-]+", "_", str(name)).strip("_")
    return key or "part"


def _read_scene(path: str):
    import trimesh

    ext = os.path.splitext(path)[1].lower()
    if ext not in MESH_FORMATS:
        raise ValueError(
            f"mesh file {path!r}: unsupported format {ext or '(no extension)'!r}; "
            f"supported: {', '.join(MESH_FORMATS)}"
        )
    kind = ext[1:].upper()
    try:
        # process=False: trimesh's processing silently removes non-finite vertices with their
        # faces and merges vertices; split_*: every OBJ object and group is its own geometry
        return trimesh.load(
            path, force="scene", process=False, split_objects=True, split_groups=True
        )
    except ImportError:  # trimesh guesses text encodings with optional modules
        raise ValueError(
            f"mesh file {path!r} is not a valid {kind} file (neither binary nor text {kind} "
            "that trimesh can parse)"
        ) from None
    except Exception as exc:  # noqa: BLE001 - re-raised with the file name
        raise ValueError(f"mesh file {path!r} is not a valid {kind} file: {exc}") from None


def _check_outward(v: np.ndarray, f: np.ndarray, path: str, obj: str) -> None:
    """A closed body whose faces all point inward (negative signed volume) reflects nothing
    in the pulse model, whose facets scatter from their front side (counter-clockwise
    winding seen from outside) only. Refused, naming the object, rather than rendered as an
    all-zero return. Checked per connected body, on a copy whose coincident vertices are
    merged (an STL stores three per face); open bodies, bodies with inconsistent winding and
    cavities (an inward body inside an outward shell) are left alone."""
    import trimesh

    if len(f) < 4:
        return
    tm = trimesh.Trimesh(v, f, process=False)
    tm.merge_vertices()
    bodies = tm.split(only_watertight=False, repair=False, engine="scipy")  # no networkx
    bodies = [b for b in bodies if len(b.faces) >= 4]
    closed = [b for b in bodies if b.is_watertight and b.is_winding_consistent]
    if not closed:
        return
    vols = np.array([float(b.volume) for b in closed])
    shells = [b for b, x in zip(closed, vols, strict=True) if x > 0]

    def enclosed(body, vol) -> bool:  # a cavity: inside an outward shell larger than it
        pt = np.asarray(body.vertices[:1], np.float64)
        try:
            return any(bool(s.contains(pt)[0]) for s in shells if float(s.volume) > -vol)
        except Exception:  # noqa: BLE001 - no ray backend: the volume alone decides
            return any(float(s.volume) > -vol for s in shells)

    bad = [i for i, x in enumerate(vols) if x < 0 and not enclosed(closed[i], x)]
    if not bad:
        return
    i = min(bad, key=lambda j: vols[j])
    raise ValueError(
        f"mesh file {path!r}: object {obj!r} has a closed body whose faces point inward "
        f"({len(closed[i].faces)} faces, signed volume {vols[i]:.3g} in the file's units^3): "
        "the pulse model's facets (ppr.simulate, inversion) reflect from their front side only "
        "(counter-clockwise seen from outside); reverse that body's face winding (e.g. "
        "trimesh's mesh.invert())"
    )


def load_mesh(
    path: str | os.PathLike,
    *,
    scale: float = 1.0,
    on_degenerate: str = "error",
    part_names: Mapping[str, str] | None = None,
) -> Mesh:
    """Load a mesh file (OBJ, STL, PLY, OFF, GLB, glTF; :data:`MESH_FORMATS`) as a
    :class:`Mesh`.

    Every object of the file becomes a part: OBJ objects (``o``) and groups (``g``, split
    further by material when an object uses several), GLB/glTF scene nodes (two nodes
    instancing one geometry are two parts). Parts are named after the object, made usable
    as config keys by :func:`part_key` (a single-object file such as an STL is named after
    the file, without extension: ``box.stl`` -> ``box``); clashing names get ``_2``,
    ``_3``, ... ``part_names`` renames parts (``{"name in the file or its key": "part"}``;
    naming an object the file does not have is an error; mapping two objects to one part
    merges them on purpose). ``scale`` converts file units to metres.

    Nothing is dropped or merged silently: the file is read without trimesh's processing;
    non-finite vertices are an error naming the file, the object and the count; objects
    that hold no triangles (lines, points) are an error; degenerate and duplicate faces are
    handled per :func:`check_mesh`.
    """
    import trimesh

    path = os.fspath(path)
    if isinstance(scale, bool) or not isinstance(scale, numbers.Real):
        raise ValueError(f"load_mesh: scale must be a number (file units -> metres), got {scale!r}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(
            f"load_mesh: scale must be finite and > 0 (file units -> metres), got {scale!r}"
        )
    if not os.path.exists(path):
        raise ValueError(f"mesh file not found: {path!r}")
    scene = _read_scene(path)
    base = os.path.basename(path)
    stem = os.path.splitext(base)[0]
    pieces: list[tuple[str, str, np.ndarray, np.ndarray]] = []  # (raw, key, vertices, faces)
    used: set[str] = set()
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        raw = str(node)
        if not isinstance(geom, trimesh.Trimesh):
            raise ValueError(
                f"mesh file {path!r}: object {raw!r} holds a {type(geom).__name__}, not "
                "triangles; remove it from the file"
            )
        if len(geom.faces) == 0:
            continue
        v = np.asarray(geom.vertices, np.float64)
        f = np.asarray(geom.faces, np.int64)
        bad = ~np.isfinite(v).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            n_faces = int(bad[f].any(axis=1).sum())
            raise ValueError(
                f"mesh file {path!r}: {int(bad.sum())} non-finite (NaN/inf) vertices in object "
                f"{raw!r}, used by {n_faces} of its {len(f)} faces (first: vertex {i} = "
                f"{v[i].tolist()}); fix the file"
            )
        t = np.asarray(transform, np.float64)
        v = v @ t[:3, :3].T + t[:3, 3]
        if np.linalg.det(t[:3, :3]) < 0:
            # a mirroring node transform turns the front side to the back (glTF: the winding
            # is reversed with it; trimesh's apply_transform does the same)
            f = f[:, ::-1]
        _check_outward(v, f, path, stem if raw == base else raw)
        key = part_key(stem if raw == base else raw)  # trimesh names lone objects by file
        k, n = key, 1
        while k in used:
            n += 1
            k = f"{key}_{n}"
        used.add(k)
        pieces.append((raw, k, v * scale, f))
    if not pieces:
        raise ValueError(f"mesh file {path!r} contains no triangles")
    if part_names:
        known = {raw for raw, _, _, _ in pieces} | {k for _, k, _, _ in pieces}
        unknown = sorted(set(part_names) - known)
        if unknown:
            raise ValueError(
                f"part_names.{unknown[0]}: mesh file {path!r} has no object {unknown[0]!r} "
                f"(objects: {', '.join(k for _, k, _, _ in pieces)})"
            )
        for k, name in part_names.items():
            if part_key(name) != name:
                raise ValueError(
                    f"part_names.{k} = {name!r}: a part name may hold letters, digits, '_' "
                    f"and '-' only (it is a config key), e.g. {part_key(name)!r}"
                )
    meshes = []
    for raw, key, v, f in pieces:
        name = (part_names or {}).get(raw, (part_names or {}).get(key, key))
        meshes.append(Mesh(v, f, None, (name,)))
    return check_mesh(concatenate(meshes), on_degenerate, name=f"mesh file {path!r}")


class MeshArrays(eqx.Module):
    """Kernel-side structure-of-arrays of a mesh padded to a fixed capacity (a pytree of arrays
    only, so a new mesh of the same capacities does not recompile).

    - `tri`: ``(F, 3, 3)`` body-frame vertex positions per face (padding: zeros).
    - `normals`: ``(F, 3)`` unit outward normals (padding and zero-area faces: +z).
    - `areas`: ``(F,)`` face areas in m^2 (padding: 0).
    - `material_ids`: ``(F,)`` part index (padding: 0).
    - `valid`: ``(F,)`` True for real faces.
    - `normal_group`: ``(F,)`` index of the face's (normal, part) group (padding: 0).
    - `group_normals`: ``(G, 3)`` normal of each group, bit-identical to its faces' normals
      (padding: +z).
    - `group_material_ids`: ``(G,)`` part index of each group (padding: 0).

    Faces with the same normal and part have the same Mueller BRDF at any pose, so the pulse
    kernel evaluates the BRDF once per group when there are fewer groups than facets to
    render (:func:`ppr.pulse._pulse.facet_weights`): a subdivided flat-panelled satellite of 13600
    faces has 12 groups. Grouping is by exact equality of the float64 normals' bits, so it
    changes no result (tests/test_pulse.py).
    """

    tri: Float[Array, "F 3 3"]
    normals: Float[Array, "F 3"]
    areas: Float[Array, " F"]
    material_ids: Int[Array, " F"]
    valid: Bool[Array, " F"]
    normal_group: Int[Array, " F"]
    group_normals: Float[Array, "G 3"]
    group_material_ids: Int[Array, " G"]

    def take_faces(self, faces: Int[Array, " Fc"]) -> MeshArrays:
        """The per-face fields at ``faces`` (the group tables are kept whole)."""
        return MeshArrays(
            tri=self.tri[faces],
            normals=self.normals[faces],
            areas=self.areas[faces],
            material_ids=self.material_ids[faces],
            valid=self.valid[faces],
            normal_group=self.normal_group[faces],
            group_normals=self.group_normals,
            group_material_ids=self.group_material_ids,
        )


class FaceSubset(eqx.Module):
    """The facets of a :class:`MeshArrays` that can contribute at one pose, and their
    (normal, part) groups, padded to a small capacity: what pose-local work (a solver round,
    an MCMC chain: the visibility is held fixed) needs instead of the whole mesh.

    A facet with zero lit-and-visible fraction contributes exactly zero to a render at that
    visibility, so rendering :meth:`apply`'s arrays with :attr:`vis` gives the full render's
    result (same values up to the summation order; tests/test_pulse.py) at a cost that
    scales with the subset: the facets behind the body are about half of a convex mesh, and
    a padded capacity can be most of a small one (a CubeSat's 12 faces padded to 64, of
    which at most 6 face the sensor).

    - `faces`: ``(Fc,)`` indices of the kept facets; padding entries repeat a kept facet
      and carry ``vis == 0``.
    - `vis`: ``(Fc,)`` their lit-and-visible fractions.
    - `groups`: ``(Gc,)`` indices of the kept facets' groups in the full group table.
    - `face_group`: ``(Fc,)`` each kept facet's group as an index into `groups`.

    Build it on the host with :meth:`of`; :meth:`apply` is traceable (gathers only), so a
    new subset of the same capacities does not recompile.
    """

    faces: Int[Array, " Fc"]
    vis: Float[Array, " Fc"]
    groups: Int[Array, " Gc"]
    face_group: Int[Array, " Fc"]

    @classmethod
    def of(
        cls,
        arrays: MeshArrays,
        vis,
        capacity: int | None = None,
        group_capacity: int | None = None,
    ) -> FaceSubset:
        """Host: the facets of ``arrays`` with ``vis > 0``, padded to ``capacity`` (default
        :func:`subset_capacity` of their count: a few distinct compiled shapes), and their
        groups, padded to ``group_capacity`` (default :func:`subset_capacity` of their
        count). Groups are kept when their capacity is below the facets'; otherwise each
        facet is its own group, as in :func:`mesh_arrays`. Fixed capacities (at least the
        largest counts over the poses of a batch) give every subset the same shapes."""
        v = np.asarray(vis)
        valid = np.asarray(arrays.valid)
        if v.shape != valid.shape or not np.all(np.isfinite(v)):
            raise ValueError(
                f"FaceSubset.of: vis must be finite with shape {valid.shape} (one value per "
                f"padded facet), got shape {v.shape}"
            )
        idx = np.flatnonzero((v > 0) & valid)
        cap = subset_capacity(len(idx)) if capacity is None else int(capacity)
        if cap < max(len(idx), 1):
            raise ValueError(
                f"FaceSubset.of: capacity {cap} is smaller than the {len(idx)} visible facets"
            )
        pad_face = int(idx[0]) if len(idx) else 0
        faces = np.concatenate([idx, np.full(cap - len(idx), pad_face)]).astype(np.int32)
        fvis = np.concatenate([v[idx], np.zeros(cap - len(idx))])
        grp = np.asarray(arrays.normal_group)[idx]
        uniq, inv = np.unique(grp, return_inverse=True)
        g_cap = subset_capacity(len(uniq)) if group_capacity is None else int(group_capacity)
        if g_cap < len(uniq):
            raise ValueError(
                f"FaceSubset.of: group_capacity {g_cap} is smaller than the {len(uniq)} "
                "groups of the visible facets"
            )
        if g_cap < cap:
            groups = np.concatenate([uniq, np.full(g_cap - len(uniq), uniq[0] if len(uniq) else 0)])
            face_group = np.concatenate([inv, np.zeros(cap - len(idx), np.int64)])
        else:
            # no fewer groups than facets: one group per facet (the kernel then skips the
            # per-group evaluation, as for an ungrouped mesh_arrays)
            groups = np.asarray(arrays.normal_group)[faces]
            face_group = np.arange(cap)
        return cls(
            faces=jnp.asarray(faces, jnp.int32),
            vis=jnp.asarray(fvis, jnp.asarray(vis).dtype),
            groups=jnp.asarray(groups, jnp.int32),
            face_group=jnp.asarray(face_group, jnp.int32),
        )

    @property
    def n_faces(self) -> int:
        """Padded facet capacity of the subset."""
        return int(self.faces.shape[0])

    def apply(self, arrays: MeshArrays) -> MeshArrays:
        """The subset's :class:`MeshArrays` (traceable): per-face fields at :attr:`faces`,
        group tables at :attr:`groups`; render it with :attr:`vis`."""
        return MeshArrays(
            tri=arrays.tri[self.faces],
            normals=arrays.normals[self.faces],
            areas=arrays.areas[self.faces],
            material_ids=arrays.material_ids[self.faces],
            valid=arrays.valid[self.faces],
            normal_group=self.face_group,
            group_normals=arrays.group_normals[self.groups],
            group_material_ids=arrays.group_material_ids[self.groups],
        )


def subset_capacity(n: int) -> int:
    """Padded capacity of a :class:`FaceSubset` of ``n`` facets or groups: the next power of
    two from 8 up to 64, then :func:`capacity_for`."""
    n = max(int(n), 1)
    if n <= 64:
        return max(8, 1 << (n - 1).bit_length())
    return capacity_for(n)


def capacity_for(n_faces: int) -> int:
    """Padded capacity: the next of 2^k * {1, 1.25, 1.5, 1.75} (at least 64) - at most 25 %
    waste and few distinct compiled shapes."""
    if n_faces <= 64:
        return 64
    k = int(np.floor(np.log2(n_faces)))
    for frac in (1.0, 1.25, 1.5, 1.75, 2.0):
        c = int(round(2**k * frac))
        if c >= n_faces:
            return c
    return 2 ** (k + 1)


def normal_groups(normals: np.ndarray, material_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Host helper: ``(first, inverse)`` of the distinct (normal, part) pairs, compared by the
    exact bits of the float64 normals: ``first[g]`` is a face of group ``g`` and
    ``inverse[f]`` the group of face ``f``."""
    nrm = np.ascontiguousarray(np.asarray(normals, np.float64))
    key = np.concatenate(
        [nrm.view(np.uint64).reshape(-1, 3), np.asarray(material_ids, np.uint64)[:, None]], axis=1
    )
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def n_normal_groups(mesh: Mesh) -> int:
    """Number of distinct (normal, part) groups of ``mesh`` (:func:`normal_groups`)."""
    _, nrm = face_areas_normals(mesh.triangles())
    return len(normal_groups(nrm + 0.0, np.asarray(mesh.material_ids))[0])


def mesh_arrays(
    mesh: Mesh,
    capacity: int | None = None,
    dtype=None,
    *,
    group_capacity: int | None = None,
    group: bool = True,
) -> MeshArrays:
    """Pad ``mesh`` to ``capacity`` faces (default :func:`capacity_for`) for the kernel.

    ``group_capacity``: padded number of (normal, part) groups (default
    :func:`capacity_for` of the count; meshes stacked together need one common value).
    ``group=False`` makes every face its own group (``G = capacity``), which turns the
    per-group BRDF evaluation off; the results are the same.
    """
    tri = mesh.triangles()
    f = tri.shape[0]
    cap = capacity_for(f) if capacity is None else int(capacity)
    if cap < f:
        raise ValueError(f"capacity {cap} is smaller than the mesh's {f} faces (overflow)")
    area, nrm = face_areas_normals(tri)
    nrm = nrm + 0.0  # -0.0 -> +0.0: signed zeros would split groups of equal normals
    mid = np.asarray(mesh.material_ids, np.int32)
    if dtype is None:
        dtype = jnp.result_type(float)
    pad = cap - f
    tri_p = np.concatenate([tri, np.zeros((pad, 3, 3))])
    nrm_p = np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (pad, 1))])
    area_p = np.concatenate([area, np.zeros(pad)])
    mid_p = np.concatenate([mid, np.zeros(pad, np.int32)])
    valid = np.concatenate([np.ones(f, bool), np.zeros(pad, bool)])
    if group:
        first, inverse = normal_groups(nrm, mid)
        n_groups = len(first)
        g_cap = min(capacity_for(n_groups), cap) if group_capacity is None else int(group_capacity)
        if g_cap < n_groups:
            raise ValueError(
                f"group_capacity {g_cap} is smaller than the mesh's {n_groups} (normal, part) "
                "groups (overflow)"
            )
        g_pad = g_cap - n_groups
        gn = np.concatenate([nrm[first], np.tile([0.0, 0.0, 1.0], (g_pad, 1))])
        gm = np.concatenate([mid[first], np.zeros(g_pad, np.int32)])
        grp = np.concatenate([inverse, np.zeros(pad, np.int64)])
    else:
        gn, gm, grp = nrm_p, mid_p, np.arange(cap)
    return MeshArrays(
        tri=jnp.asarray(tri_p, dtype),
        normals=jnp.asarray(nrm_p, dtype),
        areas=jnp.asarray(area_p, dtype),
        material_ids=jnp.asarray(mid_p, jnp.int32),
        valid=jnp.asarray(valid),
        normal_group=jnp.asarray(grp, jnp.int32),
        group_normals=jnp.asarray(gn, dtype),
        group_material_ids=jnp.asarray(gm, jnp.int32),
    )
