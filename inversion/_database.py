r"""Signature databases: shapes x attitudes x materials x finishes, on disk in zarr v3.

Layout of a database directory ``path`` (a zarr v3 group):

- ``signatures`` (N, n_channels, n_bins) float32, chunked ``(chunk_rows, C, B)``: energy-
  normalized signatures (each row sums to 1: the gain drops out,
  docs/physics/pulse_and_measurement.md#what-is-measured);
- ``energy`` (N,) float64: the total of the raw signature before normalization;
- row parameters ``shape_id``, ``attitude_id``, ``material_id``, ``finish_id`` (int32) and
  ``quat`` (N, 4) float64 (body to sensor/world, scalar first);
- group attributes: ``spec`` (the :class:`DatabaseSpec`), ``sensor`` (fingerprint of the
  signature function: channels, bins, model), ``names``, per-shape ``grids`` with their
  stated angular resolution, ``chunk_rows``, ``n_rows``;
- ``_chunks/NNNNNN.json``: one completion marker per chunk, written atomically (temp file +
  fsync + rename) *after* the chunk's data, holding the BLAKE2b digest of its decoded
  ``signatures`` and ``energy`` bytes (``_chunks`` is an empty zarr group).

Every array carries zarr v3 ``dimension_names`` (``row``, ``channel``, ``bin``,
``quaternion_component``) and ``units`` / ``long_name`` attributes (the label indices also CF
``flag_values`` / ``flag_meanings``), so ``xarray.open_zarr(path, consolidated=False)`` opens
a database as a labelled dataset (no consolidated metadata: zarr v3 does not specify it).

A chunk is valid iff its marker exists and the digest matches the data. Building skips valid
chunks, so a build killed at any point and restarted recomputes only the missing (or
half-written) chunks; signatures are a deterministic function of the row, hence the
resumed database is byte-identical to an uninterrupted build. Reading checks every marker:
missing chunks raise :class:`IncompleteDatabaseError`, a digest mismatch (or an undecodable
chunk) raises :class:`CorruptChunkError`; ``build_database`` recomputes corrupt chunks.

Each chunk is evaluated on all local devices: the rows are padded to a multiple of the device
count and sharded over a 1-D ``jax.sharding.Mesh`` (axis ``"rows"``). Several processes or
hosts can share one build through the chunk store (``shard_index``/``num_shards``; see
``docs/distributed_builds.md``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import pydantic
import zarr
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

import ppr
from ppr.config import StrictModel, load_toml_model, validate_data

from ._grid import AttitudeGrid, as_symmetry, symmetry_group
from ._noise import MeasurementModel, canonical_sensor

FORMAT_VERSION = 1
PARAM_KEYS = ("shape_id", "attitude_id", "material_id", "finish_id")


class IncompleteDatabaseError(ValueError):
    """The database has chunks without a completion marker (build not finished)."""


class CorruptChunkError(ValueError):
    """A chunk's data does not match the digest in its completion marker."""


# ----------------------------------------------------------------------------- spec (config)
class ShapeSpec(StrictModel):
    name: str
    # a class name (inversion.symmetry_group), or "auto": the group of the shape's own mesh
    symmetry: str = "none"
    params: dict[str, float | int] = {}  # ppr.shapes parameters (model "ppr" only)

    @pydantic.field_validator("symmetry")
    @classmethod
    def _symmetry(cls, v):
        from ._grid import symmetry_group

        if v != "auto":
            symmetry_group(v)  # raises ValueError naming the group
        return v


class GridSpec(StrictModel):
    kind: Literal["hopf", "fibonacci"] = "hopf"
    size: int = pydantic.Field(2, ge=1)  # Hopf nside, or number of Fibonacci points
    reduce_symmetry: bool = True


class SensorSpec(StrictModel):
    channels: str = "full"

    @pydantic.field_validator("channels")
    @classmethod
    def _channels(cls, v):
        from ._noise import PRESETS

        if v not in PRESETS:
            raise ValueError(f"unknown channel preset; known: {', '.join(sorted(PRESETS))}")
        return v

    n_bins: int = pydantic.Field(64, ge=2)
    bin_width_m: float = pydantic.Field(0.01, gt=0)
    pulse_fwhm_s: float = pydantic.Field(100e-12, gt=0)


class DatabaseSpec(StrictModel):
    """Typed database description (``configs/databases/*.toml``)."""

    name: str = "database"
    model: Literal["synthetic", "ppr"] = "synthetic"
    shapes: tuple[ShapeSpec, ...]
    materials: tuple[str, ...]
    finishes: dict[str, float]
    grid: GridSpec = GridSpec()
    sensor: SensorSpec = SensorSpec()
    chunk_rows: int = pydantic.Field(256, ge=1)
    compute_dtype: Literal["float32", "float64"] = "float32"

    @pydantic.field_validator("shapes", "materials")
    @classmethod
    def _nonempty(cls, v):
        if len(v) == 0:
            raise ValueError("must not be empty")
        # the same entry twice builds every one of its rows twice (the classifier then
        # counts one template as two)
        seen: dict = {}
        for i, item in enumerate(v):
            key = item if isinstance(item, str) else repr(item.model_dump())
            if key in seen:
                what = repr(item) if isinstance(item, str) else f"shape {item.name!r}"
                raise ValueError(f"entries [{seen[key]}] and [{i}] are the same {what}")
            seen[key] = i
        return v

    @pydantic.field_validator("finishes")
    @classmethod
    def _finishes(cls, v):
        if len(v) == 0:
            raise ValueError("must not be empty")
        for k, m in v.items():
            if not 0 <= m <= 1e6:
                raise ValueError(f"finish {k!r}: Blinn-Phong m must lie in [0, 1e6], got {m}")
        return v

    @pydantic.model_validator(mode="after")
    def _synthetic_names(self):
        if self.model != "synthetic":
            return self  # model "ppr": checked by make_signature_fn (needs the library)
        from ._synthetic import SYNTHETIC_MATERIALS, SYNTHETIC_SHAPES

        for i, m in enumerate(self.materials):
            if m not in SYNTHETIC_MATERIALS:
                raise ValueError(
                    f"materials[{i}] = {m!r}: not a material of model 'synthetic' (known: "
                    f"{', '.join(sorted(SYNTHETIC_MATERIALS))})"
                )
        for i, sh in enumerate(self.shapes):
            if sh.name not in SYNTHETIC_SHAPES:
                raise ValueError(
                    f"shapes[{i}].name = {sh.name!r}: not a shape of model 'synthetic' (known: "
                    f"{', '.join(sorted(SYNTHETIC_SHAPES))})"
                )
            if sh.params:
                raise ValueError(
                    f"shapes[{i}].params = {sh.params!r}: shape parameters need model = 'ppr'"
                )
            if sh.symmetry == "auto":
                raise ValueError(
                    f"shapes[{i}].symmetry = 'auto': the group of the shape's own mesh needs "
                    "model = 'ppr' (model 'synthetic' has no mesh); name the class instead"
                )
        return self

    def canonical(self) -> str:
        return json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def load_spec(path: str | Path, overrides: dict | None = None) -> DatabaseSpec:
    """Read a database spec TOML (see ``configs/databases/``)."""
    return load_toml_model(DatabaseSpec, path, overrides)


def spec_from_dict(data: dict, source: str = "<dict>") -> DatabaseSpec:
    return validate_data(DatabaseSpec, data, source)


# ----------------------------------------------------------------------------- rows
def shape_symmetry(spec: DatabaseSpec, i: int):
    """Symmetry of shape ``i``: its class name, or for ``symmetry = "auto"`` the group of its
    mesh (``model = "ppr"``: :func:`ppr.mesh_symmetries` of the ``ppr.shapes`` mesh)."""
    s = spec.shapes[i]
    if s.symmetry != "auto":
        if spec.model == "ppr" and s.symmetry != "none":
            _check_declared_symmetry(s, i)
        return s.symmetry
    if spec.model != "ppr":
        raise ValueError(
            f"shapes[{i}] ({s.name!r}): symmetry = 'auto' computes the group from the shape's "
            f"mesh and needs model = 'ppr', got model = {spec.model!r}"
        )
    return as_symmetry(ppr.shapes.by_name(s.name, **s.params))


def _check_declared_symmetry(s, i: int) -> None:
    """A named class given for a ``ppr.shapes`` shape must be rotations of its mesh: the
    grid is reduced by them, so a group the shape does not have (a cube declared
    ``cyclic:7``) would merge attitudes that give different signatures."""
    mesh = ppr.shapes.by_name(s.name, **s.params)
    # the geometry's group: a database gives every part of a template one material
    whole = ppr.Mesh(mesh.vertices, mesh.faces)
    mesh_q = np.asarray(as_symmetry(whole).quaternions())
    for q in np.asarray(symmetry_group(s.symmetry), np.float64):
        if np.max(np.abs(mesh_q @ q)) < 1.0 - 1e-9:  # |q . p| = cos(angle / 2)
            angle = 2.0 * math.degrees(math.acos(min(1.0, abs(float(q[0])))))
            axis = q[1:] / max(float(np.linalg.norm(q[1:])), 1e-300)
            raise ValueError(
                f"shapes[{i}].symmetry = {s.symmetry!r}: shape {s.name!r} is not symmetric "
                f"under its {angle:.4g} deg rotation about {np.round(axis, 4).tolist()} (use "
                "symmetry = 'auto' for the mesh's own group)"
            )


def grids_for(spec: DatabaseSpec) -> list[AttitudeGrid]:
    return [
        AttitudeGrid(
            spec.grid.kind,
            spec.grid.size,
            shape_symmetry(spec, i) if spec.grid.reduce_symmetry else "none",
        )
        for i in range(len(spec.shapes))
    ]


def _names(spec: DatabaseSpec) -> dict:
    """Label names of a database; ``symmetry_group`` holds each shape's rotations (the
    group ``symmetry = "auto"`` resolves to, as quaternions)."""
    return {
        "shapes": [s.name for s in spec.shapes],
        "materials": list(spec.materials),
        "finishes": list(spec.finishes),
        "finish_m": list(spec.finishes.values()),
        "symmetry": [s.symmetry for s in spec.shapes],
        "symmetry_group": [
            symmetry_group(shape_symmetry(spec, i)).tolist() for i in range(len(spec.shapes))
        ],
    }


def enumerate_rows(
    spec: DatabaseSpec, grids: list[AttitudeGrid] | None = None
) -> dict[str, np.ndarray]:
    """Row parameters, shape-major then attitude, material, finish (finish fastest)."""
    grids = grids_for(spec) if grids is None else grids
    n_m, n_f = len(spec.materials), len(spec.finishes)
    cols = {k: [] for k in (*PARAM_KEYS, "quat")}
    for sid, g in enumerate(grids):
        n_a = len(g)
        if n_a == 0:
            raise ValueError(f"attitude grid of shape {spec.shapes[sid].name!r} is empty")
        a, m, f = np.meshgrid(np.arange(n_a), np.arange(n_m), np.arange(n_f), indexing="ij")
        cols["shape_id"].append(np.full(a.size, sid))
        cols["attitude_id"].append(a.ravel())
        cols["material_id"].append(m.ravel())
        cols["finish_id"].append(f.ravel())
        cols["quat"].append(g.quats[a.ravel()])
    rows = {k: np.concatenate(v).astype(np.int32) for k, v in cols.items() if k != "quat"}
    rows["quat"] = np.concatenate(cols["quat"]).astype(np.float64)
    return rows


def make_signature_fn(spec: DatabaseSpec):
    """The signature function a spec names (``model = "synthetic"`` or ``"ppr"``).

    Names the model does not know raise ``ValueError`` naming the field as written in the
    spec (``materials[1] = 'unobtainium': ...``)."""
    mm = MeasurementModel.preset(spec.sensor.channels)
    if spec.model == "synthetic":
        from ._synthetic import SyntheticSignatures

        return SyntheticSignatures(
            [s.name for s in spec.shapes],
            list(spec.materials),
            list(spec.finishes.values()),
            mm,
            n_bins=spec.sensor.n_bins,
            bin_width_m=spec.sensor.bin_width_m,
            pulse_fwhm_s=spec.sensor.pulse_fwhm_s,
        )
    from ._ppr_adapter import PprSignatures

    _check_ppr_names(spec)
    for i, s in enumerate(spec.shapes):  # a declared group must be the shape's own
        if s.symmetry not in ("auto", "none"):
            _check_declared_symmetry(s, i)
    try:
        return PprSignatures.from_spec(spec, mm)
    except ValueError as err:
        raise ValueError(f"model = 'ppr': {err}") from None


def _check_ppr_names(spec: DatabaseSpec) -> None:
    import ppr

    for i, s in enumerate(spec.shapes):
        try:
            ppr.shapes.by_name(s.name, **dict(s.params))
        except ValueError as err:
            params = f", params = {dict(s.params)!r}" if s.params else ""
            raise ValueError(f"shapes[{i}] (name = {s.name!r}{params}): {err}") from None
    for i, m in enumerate(spec.materials):
        try:
            ppr.load_material(m, ppr.DEFAULT_WAVELENGTH_M)
        except (KeyError, ValueError) as err:
            raise ValueError(f"materials[{i}] = {m!r}: {str(err).strip(chr(39))}") from None


# ----------------------------------------------------------------------------- device helpers
def device_mesh(devices=None) -> Mesh:
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), ("rows",))


@jax.jit
def _normalize(sig):
    total = jnp.sum(sig, axis=(1, 2))
    ok = total > 0
    return sig / jnp.where(ok, total, 1.0)[:, None, None], total


def evaluate_rows(signature_fn: Callable, rows: dict, mesh: Mesh, dtype, pad_to: int | None = None):
    """Evaluate and normalize ``rows`` on all devices of ``mesh``; returns (sig, energy) numpy.

    Rows are padded (repeating the last row) to ``pad_to`` (default: the next multiple of the
    device count) so that every call has the same shape (no recompilation). A row that returns
    nothing (e.g. a thin plate exactly edge-on) keeps an all-zero signature and ``energy = 0``;
    the classifier scores it 0 against everything.
    """
    n = len(rows["quat"])
    n_dev = mesh.devices.size
    target = n if pad_to is None else max(pad_to, n)
    target = -(-target // n_dev) * n_dev
    sharding = NamedSharding(mesh, PartitionSpec("rows"))
    batch = {}
    for k, v in rows.items():
        v = np.asarray(v)
        if target > n:
            v = np.concatenate([v, np.repeat(v[-1:], target - n, axis=0)])
        if k == "quat":
            v = v.astype(dtype)
        batch[k] = jax.device_put(v, sharding)
    sig = signature_fn(batch)
    if sig.ndim != 3 or sig.shape[0] != target:
        raise ValueError(f"signature_fn returned shape {sig.shape}, expected ({target}, C, B)")
    sig, total = _normalize(sig)
    sig = np.asarray(sig, dtype=np.float32)[:n]
    total = np.asarray(total, dtype=np.float64)[:n]
    if not np.all(np.isfinite(sig)):
        raise ValueError("signature_fn returned non-finite values")
    return sig, total


# ----------------------------------------------------------------------------- store
def _digest(sig: np.ndarray, energy: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=20)
    h.update(np.ascontiguousarray(sig, dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(energy, dtype="<f8").tobytes())
    return h.hexdigest()


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + f".tmp-{socket.gethostname()}-{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _remove_stale_temp(folder: Path) -> None:
    """Delete marker temp files left by killed builders of this host (never live ones)."""
    host = socket.gethostname()
    for tmp in folder.glob(f"*.tmp-{host}-*"):
        pid = int(tmp.name.rsplit("-", 1)[1])
        try:
            os.kill(pid, 0)
            alive = pid != os.getpid()
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive:
            tmp.unlink(missing_ok=True)


MARKERS = "_chunks"  # folder (an empty zarr group) of the completion markers NNNNNN.json

# dimension names of the arrays (zarr v3 ``dimension_names``, read by xarray)
ARRAY_DIMS = {
    "signatures": ("row", "channel", "bin"),
    "energy": ("row",),
    "shape_id": ("row",),
    "attitude_id": ("row",),
    "material_id": ("row",),
    "finish_id": ("row",),
    "quat": ("row", "quaternion_component"),
}


def _array_attrs(spec: DatabaseSpec, names: dict) -> dict[str, dict]:
    """Per-array attributes: ``units`` (UDUNITS strings, "1" for dimensionless), a
    ``long_name`` and, for the label indices, CF ``flag_values`` / ``flag_meanings``."""
    raw = "m2 sr-1" if spec.model == "ppr" else "1"  # ppr.render's bin-integrated return
    out = {
        "signatures": {
            "units": "1",
            "long_name": "energy-normalized signature (each row sums to 1 over channels and bins)",
            "bin_width_m": spec.sensor.bin_width_m,
            "channels": spec.sensor.channels,
        },
        "energy": {
            "units": raw,
            "long_name": "total of the raw signature before normalization"
            + ("" if spec.model == "ppr" else " (synthetic model: arbitrary units)"),
        },
        "attitude_id": {"units": "1", "long_name": "index of the attitude in its shape's grid"},
        "quat": {
            "units": "1",
            "long_name": "attitude quaternion, body -> sensor (w, x, y, z)",
        },
    }
    for key, label in (
        ("shape_id", "shapes"),
        ("material_id", "materials"),
        ("finish_id", "finishes"),
    ):
        out[key] = {
            "units": "1",
            "long_name": f"index into names.{label}",
            "flag_values": list(range(len(names[label]))),
            "flag_meanings": " ".join(str(x).replace(" ", "_") for x in names[label]),
        }
    return out


def _marker_path(path: Path, i: int) -> Path:
    return path / MARKERS / f"{i:06d}.json"


def _store_attrs(spec: DatabaseSpec, signature_fn) -> tuple[dict, list, dict]:
    """Group attributes of the store ``spec`` builds, its grids and rows."""
    sensor = canonical_sensor(signature_fn.sensor)
    grids = grids_for(spec)
    rows = enumerate_rows(spec, grids)
    n = len(rows["quat"])
    attrs = {
        "ppr_database": FORMAT_VERSION,
        "spec": json.loads(spec.canonical()),
        "sensor": json.loads(sensor),
        "names": _names(spec),
        "grids": [g.describe() for g in grids],
        "n_rows": n,
        "chunk_rows": spec.chunk_rows,
        "n_chunks": -(-n // spec.chunk_rows),
    }
    return attrs, grids, rows


def _open_store(path: Path, mode: str) -> zarr.Group:
    """The store's zarr group; unreadable metadata is an error naming its file."""
    try:
        return zarr.open_group(str(path), mode=mode)
    except OSError:  # permissions, I/O: the store may be intact; say what the system said
        raise
    except Exception as err:  # noqa: BLE001 - undecodable metadata, re-raised naming the file
        meta = Path(path) / "zarr.json"
        raise ValueError(
            f"database {path}: its metadata {meta} cannot be read ({type(err).__name__}: "
            f"{err}); the store is damaged beyond its chunk checksums: remove {path} and "
            "build it again"
        ) from None


def init_database(spec: DatabaseSpec, path: str | Path, signature_fn=None) -> zarr.Group:
    """Create (or reopen and check) the store for ``spec``; returns the zarr group.

    Safe to call from several processes after one of them has created the store. Reopening a
    store built from a different spec or sensor raises ``ValueError`` naming the differences.
    """
    path = Path(path)
    signature_fn = make_signature_fn(spec) if signature_fn is None else signature_fn
    attrs, _, rows = _store_attrs(spec, signature_fn)
    sensor = json.dumps(attrs["sensor"])
    n = attrs["n_rows"]
    if (path / "zarr.json").exists():
        group = _open_store(path, "r+")
        old = dict(group.attrs)
        if old.get("initialized"):
            _check_same(old, attrs, path)
            return group
    group = zarr.open_group(str(path), mode="w")
    c, b = signature_fn.n_channels, int(json.loads(sensor).get("n_bins", 0)) or None
    if b is None:
        raise ValueError("signature_fn.sensor must state 'n_bins'")
    cr = spec.chunk_rows
    labelled = _array_attrs(spec, attrs["names"])
    group.create_array(
        "signatures",
        shape=(n, c, b),
        chunks=(cr, c, b),
        dtype="float32",
        fill_value=0.0,
        dimension_names=ARRAY_DIMS["signatures"],
        attributes=labelled["signatures"],
    )
    group.create_array(
        "energy",
        shape=(n,),
        chunks=(cr,),
        dtype="float64",
        fill_value=0.0,
        dimension_names=ARRAY_DIMS["energy"],
        attributes=labelled["energy"],
    )
    for k in PARAM_KEYS:
        a = group.create_array(
            k,
            shape=(n,),
            chunks=(max(n, 1),),
            dtype="int32",
            fill_value=0,
            dimension_names=ARRAY_DIMS[k],
            attributes=labelled[k],
        )
        a[:] = rows[k]
    a = group.create_array(
        "quat",
        shape=(n, 4),
        chunks=(max(n, 1), 4),
        dtype="float64",
        fill_value=0.0,
        dimension_names=ARRAY_DIMS["quat"],
        attributes=labelled["quat"],
    )
    a[:] = rows["quat"]
    # the completion markers' folder is a (empty) zarr group, so readers of the hierarchy
    # (xarray.open_zarr) see a known component, not an unknown folder
    group.create_group(MARKERS, attributes={"description": "chunk completion markers"})
    group.attrs.update(attrs)
    group.attrs["initialized"] = True  # last: a store without it is re-created
    return group


_COMPARED = ("ppr_database", "spec", "sensor", "n_rows", "chunk_rows")


def _differences(old: dict, new: dict) -> list[str]:
    """What differs between stored and requested attributes, spec fields one by one."""
    diffs = []
    for key in _COMPARED:
        a, b = old.get(key), new.get(key)
        if key == "spec" and isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b)):
                if json.dumps(a.get(k), sort_keys=True) != json.dumps(b.get(k), sort_keys=True):
                    diffs.append(f"{k}: stored {a.get(k)!r} != requested {b.get(k)!r}")
        elif json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
            diffs.append(f"{key}: stored {a!r} != requested {b!r}")
    return list(dict.fromkeys(diffs))  # a field both in the spec and top level: said once


def _check_same(old: dict, new: dict, path: Path) -> None:
    diffs = _differences(old, new)
    if diffs:
        raise ValueError(
            f"database at {path} was built with other settings; refusing to mix them "
            f"(use a new path): " + "; ".join(diffs)
        )


def store_differences(spec: DatabaseSpec, path: str | Path, signature_fn=None) -> list[str] | None:
    """How the store at ``path`` differs from what ``spec`` builds: ``[]`` if it is a store of
    this spec (complete or not), a list of ``"field: stored ... != requested ..."`` if its
    settings differ, ``None`` if ``path`` is not an initialized signature database."""
    path = Path(path)
    try:
        old = dict(zarr.open_group(str(path), mode="r").attrs)
    except Exception:  # noqa: BLE001 - anything unreadable is not a database
        return None
    if not old.get("initialized"):
        return None
    signature_fn = make_signature_fn(spec) if signature_fn is None else signature_fn
    return _differences(old, _store_attrs(spec, signature_fn)[0])


def _read_chunk(group, i: int, cr: int, n: int):
    a, b = i * cr, min((i + 1) * cr, n)
    try:
        return np.asarray(group["signatures"][a:b]), np.asarray(group["energy"][a:b])
    except Exception as err:  # undecodable bytes -> corrupt
        raise CorruptChunkError(f"chunk {i} (rows {a}:{b}) cannot be decoded: {err}") from None


def chunk_status(path: str | Path, verify: bool = True) -> dict[str, list[int]]:
    """Chunks that are ``done``, ``missing`` (no marker) and ``corrupt`` (digest mismatch)."""
    path = Path(path)
    group = _open_store(path, "r")
    n, cr, n_chunks = group.attrs["n_rows"], group.attrs["chunk_rows"], group.attrs["n_chunks"]
    status = {"done": [], "missing": [], "corrupt": []}
    for i in range(n_chunks):
        mp = _marker_path(path, i)
        if not mp.exists():
            status["missing"].append(i)
            continue
        if verify:
            want = json.loads(mp.read_text())["digest"]
            try:
                sig, en = _read_chunk(group, i, cr, n)
                ok = _digest(sig, en) == want
            except CorruptChunkError:
                ok = False
            if not ok:
                status["corrupt"].append(i)
                continue
        status["done"].append(i)
    return status


@dataclass
class BuildReport:
    path: str
    n_rows: int
    n_chunks: int
    computed: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    recomputed_corrupt: list[int] = field(default_factory=list)
    seconds: float = 0.0
    n_devices: int = 1

    @property
    def rows_per_second(self) -> float:
        rows = len(self.computed) * (self.n_rows / max(self.n_chunks, 1))
        return rows / self.seconds if self.seconds > 0 else float("nan")


def build_database(
    spec: DatabaseSpec,
    path: str | Path,
    signature_fn=None,
    *,
    devices=None,
    progress: bool = True,
    verify: bool = True,
    shard_index: int = 0,
    num_shards: int = 1,
) -> BuildReport:
    """Build (or resume) the database of ``spec`` at ``path``, chunk by chunk.

    **Arguments:**

    - `signature_fn`: callable ``params -> (batch, C, B)`` with attributes ``n_channels`` and
      ``sensor`` (dict with ``n_bins``); default from ``spec.model``. ``params`` holds
      ``shape_id``, ``attitude_id``, ``material_id``, ``finish_id`` (int32) and ``quat``
      (``compute_dtype``), all sharded over the devices on their first axis.
    - `devices`: devices of the 1-D mesh (default ``jax.devices()``).
    - `verify`: re-check the digests of chunks already marked done; corrupt ones are
      recomputed (listed in ``BuildReport.recomputed_corrupt``).
    - `shard_index`, `num_shards`: build only chunks ``i`` with ``i % num_shards ==
      shard_index`` (several processes/hosts sharing one store).
    """
    if not (0 <= shard_index < num_shards):
        raise ValueError(f"need 0 <= shard_index < num_shards, got {shard_index}, {num_shards}")
    path = Path(path)
    signature_fn = make_signature_fn(spec) if signature_fn is None else signature_fn
    group = init_database(spec, path, signature_fn)
    rows = {k: np.asarray(group[k][:]) for k in (*PARAM_KEYS, "quat")}
    n, cr, n_chunks = group.attrs["n_rows"], spec.chunk_rows, group.attrs["n_chunks"]
    mesh = device_mesh(devices)
    report = BuildReport(str(path), n, n_chunks, n_devices=mesh.devices.size)
    _remove_stale_temp(path / MARKERS)
    status = chunk_status(path, verify=verify)
    mine = [i for i in range(n_chunks) if i % num_shards == shard_index]
    todo = [i for i in mine if i not in set(status["done"])]
    report.skipped = [i for i in mine if i in set(status["done"])]
    report.recomputed_corrupt = [i for i in todo if i in set(status["corrupt"])]
    for i in report.recomputed_corrupt:
        _marker_path(path, i).unlink(missing_ok=True)
    dtype = np.dtype(spec.compute_dtype)
    t0 = time.perf_counter()
    for i in tqdm(todo, desc=f"build {spec.name}", unit="chunk", disable=not progress, leave=False):
        a, b = i * cr, min((i + 1) * cr, n)
        sig, energy = evaluate_rows(
            signature_fn, {k: v[a:b] for k, v in rows.items()}, mesh, dtype, pad_to=cr
        )
        if not np.any(np.asarray(energy) > 0):
            # a whole chunk of templates with no signal is a sensor that sees nothing (a
            # pulse far longer than the bins, a gate that misses the shapes), not edge-on
            # plates: refuse it instead of writing a database of zeros (not marked done)
            raise ValueError(
                f"database {spec.name!r}: every signature of chunk {i} (rows {a}-{b - 1}) is "
                "zero: no return reaches the range bins; check the sensor's pulse and bins "
                "against the shapes (e.g. `ppr simulate` one of them)"
            )
        group["signatures"][a:b] = sig
        group["energy"][a:b] = energy
        # read back what the store will return, then mark the chunk done
        sig_r, en_r = _read_chunk(group, i, cr, n)
        _atomic_write(
            _marker_path(path, i),
            json.dumps(
                {"chunk": i, "rows": [a, b], "digest": _digest(sig_r, en_r)}, sort_keys=True
            ),
        )
        report.computed.append(i)
    report.seconds = time.perf_counter() - t0
    return report


# ----------------------------------------------------------------------------- reading
@dataclass
class TemplateBank:
    """Normalized signatures with their row parameters, in host memory.

    ``signatures`` (T, C, B) float32 (rows sum to 1); ``shape_id``, ``attitude_id``,
    ``material_id``, ``finish_id`` (T,) int; ``quat`` (T, 4); ``names`` the label names;
    ``sensor`` the canonical sensor fingerprint; ``resolution_deg`` per shape.
    """

    signatures: np.ndarray
    shape_id: np.ndarray
    attitude_id: np.ndarray
    material_id: np.ndarray
    finish_id: np.ndarray
    quat: np.ndarray
    names: dict
    sensor: str
    resolution_deg: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.signatures)

    @property
    def n_channels(self) -> int:
        return self.signatures.shape[1]

    @property
    def n_bins(self) -> int:
        return self.signatures.shape[2]

    def symmetry(self, shape_id: int):
        """Symmetry of a shape for the attitude-error helpers: its class name, or for
        ``symmetry = "auto"`` the ``(G, 4)`` rotations computed from its mesh."""
        name = self.names["symmetry"][int(shape_id)]
        if name == "auto":
            return np.asarray(self.names["symmetry_group"][int(shape_id)], np.float64)
        return name

    def labels(self, attribute: str) -> np.ndarray:
        """Integer class label per row for ``shape``, ``material``, ``finish`` or ``attitude``."""
        if attribute in ("shape", "material", "finish"):
            return getattr(self, f"{attribute}_id")
        if attribute == "attitude":
            return (
                self.shape_id.astype(np.int64) * (int(self.attitude_id.max()) + 1)
                + self.attitude_id
            )
        raise ValueError(
            f"unknown attribute {attribute!r}; use shape, material, finish or attitude"
        )


def load_database(path: str | Path, verify: bool = True) -> TemplateBank:
    """Read a complete database into a :class:`TemplateBank` (checking every chunk)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"database {path} does not exist")
    if not (path / "zarr.json").exists():
        raise ValueError(f"{path} is not a signature database (no zarr.json)")
    group = _open_store(path, "r")
    attrs = dict(group.attrs)
    if not attrs.get("initialized") or attrs.get("ppr_database") != FORMAT_VERSION:
        raise ValueError(
            f"{path} is not an initialized signature database (format {FORMAT_VERSION})"
        )
    status = chunk_status(path, verify=verify)
    if status["missing"]:
        m = status["missing"]
        raise IncompleteDatabaseError(
            f"database {path}: {len(m)} of {attrs['n_chunks']} chunks not built (first: {m[:5]}); "
            f"rerun build_database to resume"
        )
    if status["corrupt"]:
        c = status["corrupt"]
        raise CorruptChunkError(
            f"database {path}: chunks {c[:10]} do not match their checksums (corrupt); "
            f"rerun build_database to recompute them"
        )
    return TemplateBank(
        signatures=np.asarray(group["signatures"][:]),
        **{k: np.asarray(group[k][:]) for k in PARAM_KEYS},
        quat=np.asarray(group["quat"][:]),
        names=attrs["names"],
        sensor=canonical_sensor(attrs["sensor"]),
        resolution_deg=[g["resolution_deg"] for g in attrs["grids"]],
    )


def bank_in_memory(
    spec: DatabaseSpec, signature_fn=None, devices=None, batch: int = 4096
) -> TemplateBank:
    """Build a :class:`TemplateBank` without a store (small databases, evaluation)."""
    signature_fn = make_signature_fn(spec) if signature_fn is None else signature_fn
    grids = grids_for(spec)
    rows = enumerate_rows(spec, grids)
    mesh = device_mesh(devices)
    n = len(rows["quat"])
    sigs = []
    for a in range(0, n, batch):
        sig, _ = evaluate_rows(
            signature_fn,
            {k: v[a : a + batch] for k, v in rows.items()},
            mesh,
            np.dtype(spec.compute_dtype),
            pad_to=min(batch, n),
        )
        sigs.append(sig)
    return TemplateBank(
        signatures=np.concatenate(sigs),
        **{k: rows[k] for k in PARAM_KEYS},
        quat=rows["quat"],
        names=_names(spec),
        sensor=canonical_sensor(signature_fn.sensor),
        resolution_deg=[g.resolution_deg for g in grids],
    )
