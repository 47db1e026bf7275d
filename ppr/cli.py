"""``ppr``: the command line of Pulse Polarization Ranging.

A thin layer over the library: every subcommand reads a TOML config (typed schema, unknown
keys are errors), applies ``--set key.sub=value`` overrides, runs the library function and
writes its outputs (arrays ``.npz``/``.zarr``, a JSON summary, PNG plots) into ``--out``.

Exit status: 0 on success; 2 for a bad config, a bad override, an input the library rejects
or an output that exists (``--overwrite`` replaces it); 130 on Ctrl-C, 143 on SIGTERM. Errors
are one line on stderr naming the file, the field as the user wrote it and the bad value
(``--debug`` shows the traceback instead). Configs are checked whole before any computation.

Outputs are staged, validated and swapped into ``--out`` as a whole (:mod:`ppr._outputs`):
a failed, interrupted or killed run leaves the previous result as it was.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
import pydantic

from . import _outputs
from ._config import ConfigError, StrictModel, load_toml_model, parse_override

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = REPO_ROOT / "configs"


class CLIError(Exception):
    """A usage error (existing output, missing input) reported as one line, exit status 2."""


# ============================================================================ output folder
# Outputs are staged, validated and swapped in as a whole (ppr/_outputs.py).
Outputs = _outputs.Outputs
outputs = _outputs.outputs


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, complex):
        return [obj.real, obj.imag]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, pydantic.BaseModel):
        return _jsonable(obj.model_dump())
    if hasattr(obj, "__array__"):
        return _jsonable(np.asarray(obj))
    return obj


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")


# ================================================================================ configs
Vec3 = tuple[float, float, float]
PositiveFloat = Annotated[float, pydantic.Field(gt=0.0)]
# random seeds: NumPy's generators take non-negative integers only
Seed = Annotated[int, pydantic.Field(ge=0)]

_T = TypeVar("_T")
NonEmpty = Annotated[list[_T], pydantic.Field(min_length=1)]  # lists the user must not empty


def resolve_material(spec: Any, wavelength: float, field: str, cfg_path: Path):
    """A config material spec -> :class:`ppr.Material`; errors name the file and field.

    Specs: a library name (``"aluminium"``, default finish) or ``"name/finish"``
    (``"aluminium/rough"``; see configs/materials.toml), or an inline table
    ``{n_real, n_imag, m, corr_length_m}`` as in scene configs."""
    sc = _scene_schema()
    if isinstance(spec, dict):
        spec = _sub_model(sc.InlineMaterial, spec, cfg_path, field)
        return sc._material_from_config(spec, wavelength, f"{cfg_path}: {field}")
    if not isinstance(spec, str):
        raise ConfigError(
            f"{cfg_path}: {field} = {spec!r}: expected a library material name ('name' or "
            "'name/finish') or an inline table {n_real, n_imag, m, corr_length_m}"
        )
    import ppr

    name, slash, finish = spec.partition("/")
    load = getattr(ppr, "load_material", None)
    if load is None:  # pragma: no cover - library always present once issue 2 landed
        return sc._material_from_config(spec, wavelength, f"{cfg_path}: {field}")
    try:
        return load(name, wavelength, finish if slash else None)
    except (ValueError, KeyError) as err:
        msg = str(err).strip(chr(39))
        if "wavelength" in msg:
            msg = f"at wavelength_nm = {wavelength * 1e9:g}: {msg}"
        raise ConfigError(f"{cfg_path}: {field} = {spec!r}: {msg}") from None


def _distinct(v: list) -> list:
    dup = sorted({x for x in v if v.count(x) > 1})
    if dup:
        raise ValueError(f"{dup[0]!r} is listed twice")
    return v


TermName = Literal["single", "double", "multiple"]
Terms = (
    Literal["auto", "all"]
    | Annotated[list[TermName], pydantic.Field(min_length=1), pydantic.AfterValidator(_distinct)]
)


def _terms_arg(terms):
    if terms == "all":
        return None
    return tuple(terms) if isinstance(terms, list) else terms


class Range(StrictModel):
    start: float
    stop: float
    num: int = pydantic.Field(ge=1, le=100_000)

    def values(self) -> np.ndarray:
        return np.linspace(self.start, self.stop, self.num)


class BrdfConfig(StrictModel):
    """``ppr brdf``: a Mueller BRDF sweep over incidence and bistatic angle."""

    material: str | dict[str, Any]
    wavelength_nm: float = pydantic.Field(532.0, gt=0.0, lt=1e6)  # nanometres
    terms: Terms = "auto"
    incidence_deg: Annotated[
        list[Annotated[float, pydantic.Field(ge=0.0, lt=90.0)]], pydantic.Field(min_length=1)
    ] = [0.0, 30.0, 60.0]
    bistatic_deg: (
        Range
        | Annotated[
            list[Annotated[float, pydantic.Field(ge=0.0, le=179.0)]], pydantic.Field(min_length=1)
        ]
    ) = Range(start=0.0, stop=10.0, num=41)
    plane: Literal["in", "cross"] = "in"
    dtype: Literal["float32", "float64"] = "float32"

    @pydantic.field_validator("bistatic_deg")
    @classmethod
    def _bistatic_ok(cls, v):
        vals = v.values() if isinstance(v, Range) else np.asarray(v)
        if vals.size == 0 or np.any(vals < 0) or np.any(vals > 179.0):
            raise ValueError("bistatic angles must lie in [0, 179] degrees")
        return v


class ViewConfig(StrictModel):
    """Sensor geometry of an image (same fields and meaning as configs/sensors/*.toml)."""

    wavelength_nm: float = pydantic.Field(532.0, gt=0.0, lt=1e6)  # nanometres
    line_of_sight: Vec3 = (-0.8, -0.3, -0.52)
    polarization_reference: Vec3 = (-0.5, 0.866, 0.0)
    bistatic_angle_urad: float = pydantic.Field(0.0, ge=0.0, lt=1.5e6)
    bistatic_azimuth_deg: float = 0.0

    @pydantic.model_validator(mode="after")
    def _geometry(self):
        _scene_schema().check_sensor_fields(
            self.line_of_sight,
            self.polarization_reference,
            None,
            self.bistatic_angle_urad,
            self.bistatic_azimuth_deg,
        )
        return self


class RenderConfig(StrictModel):
    n_pixels: int = pydantic.Field(128, ge=4, le=2048)
    half_width_m: float | None = pydantic.Field(None, gt=0.0)
    shading: Literal["flat", "smooth"] = "flat"
    terms: Terms = "auto"
    dtype: Literal["float32", "float64"] = "float32"


def _scene_schema():
    from . import _scene

    return _scene


class ImageConfig(StrictModel):
    """``ppr image``: per-pixel Mueller images of a mesh at a pose."""

    scene: str | None = None
    mesh: str | None = None
    shape: dict[str, Any] | None = None
    materials: dict[str, Any] = {}
    pose: dict[str, Any] | None = None
    view: ViewConfig | None = None
    render: RenderConfig = RenderConfig()

    @pydantic.model_validator(mode="after")
    def _geometry(self):
        given = [k for k in ("scene", "mesh", "shape") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of scene, mesh, [shape] (got {given or 'none'})")
        if self.scene is not None:
            extra = [k for k in ("materials", "pose", "view") if getattr(self, k)]
            if extra:
                raise ValueError(
                    f"{extra[0]} comes from the scene file when scene is given; remove it"
                )
        elif not self.materials:
            raise ValueError("materials: give a material per mesh part (or materials.default)")
        return self


# ============================================================================== helpers
def _overrides(args) -> dict:
    out = {}
    for text in args.set or []:
        key, value = parse_override(text)
        out[key] = value
    return out


def _config_path(args, default_name: str) -> Path:
    if args.config is not None:
        return Path(args.config)
    default = CONFIG_DIR / "cli" / default_name
    if not default.is_file():
        raise CLIError(f"no --config given and the default {default} does not exist")
    return default


def _resolve_path(value: str, config_path: Path) -> Path:
    p = Path(value).expanduser()
    if p.is_absolute() or p.exists():
        return p
    return config_path.parent / p


def _progress(args) -> bool:
    return not getattr(args, "quiet", False)


def _say(args, msg: str) -> None:
    if not getattr(args, "quiet", False):
        print(msg, file=sys.stderr, flush=True)


def _dtype(name: str):
    return np.float32 if name == "float32" else np.float64


def _maybe_x64(dtype_name: str) -> None:
    """float64 runs need JAX's x64 mode; the CLI is a program, so it may switch it on."""
    if dtype_name == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)


# ================================================================================= brdf
def brdf_geometry(incidence_deg, bistatic_deg, plane: str):
    """Directions (normal +z) for the sweep: ``k_in`` at polar angle theta in the x-z plane;
    ``k_out`` at bistatic angle psi from ``k_in``, in the plane of incidence toward the normal
    (``plane='in'``) or rotated out of it (``plane='cross'``). Stokes frames: the lab y axis
    projected perpendicular to each beam. Returns arrays of shape ``(I, B, 3)`` and a mask of
    geometries with ``k_out`` above the horizon."""
    th = np.deg2rad(np.asarray(incidence_deg, float))[:, None]
    ps = np.deg2rad(np.asarray(bistatic_deg, float))[None, :]
    th, ps = np.broadcast_arrays(th, ps)
    k_in = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
    if plane == "in":
        to = th - ps
        k_out = np.stack([np.sin(to), np.zeros_like(to), np.cos(to)], -1)
    else:
        axis = np.stack([np.cos(th), np.zeros_like(th), -np.sin(th)], -1)
        k_out = k_in * np.cos(ps)[..., None] + np.cross(axis, k_in) * np.sin(ps)[..., None]
    y = np.array([0.0, 1.0, 0.0])

    def frame(k):
        f = y - np.sum(y * k, -1, keepdims=True) * k
        return f / np.linalg.norm(f, axis=-1, keepdims=True)

    valid = k_out[..., 2] > 1e-6
    return k_in, k_out, frame(k_in), frame(k_out), valid


def polarimetry(mueller: np.ndarray) -> dict[str, np.ndarray]:
    """Depolarization index, polarizance, diattenuation, retardance of normalized matrices."""
    from ._image import polarimetric_maps

    out = polarimetric_maps(mueller, np.ones(mueller.shape[:-2]))
    out.pop("reflectance")
    return out


def cmd_brdf(args) -> int:
    cfg_path = _config_path(args, "brdf.toml")
    cfg = load_toml_model(BrdfConfig, cfg_path, _overrides(args))
    names = ["brdf.npz", "brdf.json", "brdf.png"]
    _maybe_x64(cfg.dtype)
    mat = resolve_material(cfg.material, cfg.wavelength_nm * 1e-9, "material", cfg_path)
    with outputs(args.out, names, args.overwrite) as out:
        from ._image import evaluate_mueller

        bis = (
            cfg.bistatic_deg.values()
            if isinstance(cfg.bistatic_deg, Range)
            else np.asarray(cfg.bistatic_deg, float)
        )
        inc = np.asarray(cfg.incidence_deg, float)
        k_in, k_out, f_in, f_out, valid = brdf_geometry(inc, bis, cfg.plane)
        safe_out = np.where(valid[..., None], k_out, k_in)
        t0 = time.perf_counter()
        flat = [x.reshape(-1, 3) for x in (k_in, safe_out)]
        n_rows = len(flat[0])
        mueller = evaluate_mueller(
            flat[0],
            flat[1],
            np.broadcast_to([0.0, 0.0, 1.0], (n_rows, 3)),
            f_in.reshape(-1, 3),
            f_out.reshape(-1, 3),
            [mat],
            np.zeros(n_rows, np.int32),
            terms=_terms_arg(cfg.terms),
            wavelength=cfg.wavelength_nm * 1e-9,
            dtype=_dtype(cfg.dtype),
            progress=_progress(args),
        ).reshape(*valid.shape, 4, 4)
        mueller = np.where(valid[..., None, None], mueller, np.nan)
        elapsed = time.perf_counter() - t0
        quants = polarimetry(mueller)
        np.savez_compressed(
            out.path("brdf.npz"),
            mueller=mueller,
            incidence_deg=inc,
            bistatic_deg=bis,
            k_in=k_in,
            k_out=k_out,
            frame_in=f_in,
            frame_out=f_out,
            valid=valid,
            **quants,
        )
        summary = {
            "command": "brdf",
            "config_file": str(cfg_path),
            "config": cfg,
            "material": _material_summary(mat),
            "n_geometries": int(valid.sum()),
            "seconds": elapsed,
            "units": {"mueller": "1/sr", "angles": "deg", "retardance": "rad"},
            "backscatter": {
                f"{a:g}": {"M00": mueller[i, 0, 0, 0], **{k: v[i, 0] for k, v in quants.items()}}
                for i, a in enumerate(inc)
            },
            "outputs": names,
        }
        write_json(out.path("brdf.json"), summary)
        _plot_brdf(out.path("brdf.png"), inc, bis, mueller, quants, cfg, mat)
    _say(args, f"ppr brdf: wrote {', '.join(str(Path(args.out) / n) for n in names)}")
    return 0


def _material_summary(mat) -> dict:
    n = complex(np.asarray(mat.n).reshape(-1)[0])
    return {
        "name": getattr(mat, "name", ""),
        "n": [n.real, n.imag],
        "m": float(np.asarray(mat.m).reshape(-1)[0]),
        "corr_length_m": float(np.asarray(mat.corr_length).reshape(-1)[0]),
    }


def _plot_brdf(path, inc, bis, mueller, quants, cfg, mat) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 5, figsize=(20, 4), constrained_layout=True)
    panels = [("M00 [1/sr]", mueller[..., 0, 0])] + [
        (k.replace("_", " ") + (" [rad]" if k == "retardance" else ""), v)
        for k, v in quants.items()
    ]
    for ax, (label, data) in zip(axes, panels, strict=True):
        for i, a in enumerate(inc):
            ax.plot(bis, data[i], label=f"incidence {a:g} deg")
        ax.set_xlabel("bistatic angle [deg]")
        ax.set_title(label)
        if label.startswith("M00") and np.any(np.nan_to_num(data) > 0):
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    n = complex(np.asarray(mat.n).reshape(-1)[0])
    fig.suptitle(
        f"{getattr(mat, 'name', '') or 'material'}: n = {n.real:.3g}+{n.imag:.3g}i, "
        f"m = {float(np.asarray(mat.m).reshape(-1)[0]):.3g}, {cfg.wavelength_nm:.0f} nm, "
        f"terms {cfg.terms}, {cfg.plane}-plane"
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ================================================================================ image
def _sub_model(model, data, cfg_path: Path, field: str):
    """Validate a sub-table with another module's schema; errors name ``field``."""
    try:
        return model.model_validate(data)
    except pydantic.ValidationError as err:
        from ._config import format_validation_error

        raise ConfigError(format_validation_error(err, str(cfg_path), data, field)) from None


def image_inputs(cfg: ImageConfig, cfg_path: Path):
    """Resolve an image config to ``(part mesh, materials, sensor, quaternion)``."""
    from . import _image
    from ._mesh import load_mesh

    sc = _scene_schema()
    smooth = cfg.render.shading == "smooth"
    if cfg.scene is not None:
        spath = _resolve_path(cfg.scene, cfg_path)
        if not spath.is_file():
            raise ConfigError(f"{cfg_path}: scene = {cfg.scene!r}: no such scene file ({spath})")
        scene = sc.load_scene(spath)
        mesh = part_mesh_from_ppr_mesh(scene.mesh, smooth)
        return mesh, list(scene.materials), scene.sensor, np.asarray(scene.pose.quaternion)
    if cfg.shape is not None:
        shape = _sub_model(sc.ShapeConfig, cfg.shape, cfg_path, "shape")
        from . import shapes

        try:
            pmesh = shapes.by_name(shape.name, **shape.params)
        except ValueError as err:
            raise ConfigError(f"{cfg_path}: shape = {cfg.shape!r}: {err}") from None
    else:
        path = (
            _image.EXAMPLE_SATELLITE if cfg.mesh == "example" else _resolve_path(cfg.mesh, cfg_path)
        )
        try:
            pmesh = load_mesh(path)
        except ValueError as err:
            raise ConfigError(f"{cfg_path}: mesh = {cfg.mesh!r}: {err}") from None
    mesh = part_mesh_from_ppr_mesh(pmesh, smooth)
    view = cfg.view or ViewConfig()
    try:
        sensor = sc.Sensor.make(
            view.line_of_sight,
            view.polarization_reference,
            bistatic_angle=view.bistatic_angle_urad * 1e-6,
            bistatic_azimuth=np.deg2rad(view.bistatic_azimuth_deg),
            wavelength=view.wavelength_nm * 1e-9,
        )
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: view: {err}") from None
    pose = _sub_model(sc.PoseConfig, cfg.pose or {}, cfg_path, "pose")
    try:
        from ._pose import check_quaternion

        quat = check_quaternion(pose.quaternion, "pose.quaternion")
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: {err}") from None
    wl = view.wavelength_nm * 1e-9
    mats = []
    for part in mesh.part_names:
        key = part if part in cfg.materials else "default"
        if key not in cfg.materials:
            raise ConfigError(
                f"{cfg_path}: materials: no material for mesh part {part!r} (parts: "
                f"{', '.join(mesh.part_names)}; add materials.{part} or materials.default)"
            )
        mats.append(resolve_material(cfg.materials[key], wl, f"materials.{key}", cfg_path))
    unknown = sorted(set(cfg.materials) - set(mesh.part_names) - {"default"})
    if unknown:
        raise ConfigError(
            f"{cfg_path}: materials.{unknown[0]}: the mesh has no part {unknown[0]!r} (parts: "
            f"{', '.join(mesh.part_names)})"
        )
    return mesh, mats, sensor, quat


def part_mesh_from_ppr_mesh(mesh, smooth: bool = False):
    """Adapter from :class:`ppr.Mesh`-like objects (vertices, faces, material_ids, parts)."""
    from . import _image

    verts = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, np.int64)
    vn = None
    if smooth:
        import trimesh

        vn = np.asarray(trimesh.Trimesh(verts, faces, process=False).vertex_normals, float)
    return _image.PartMesh(
        vertices=verts,
        faces=faces,
        part_ids=np.asarray(mesh.material_ids, np.int64),
        part_names=tuple(mesh.parts),
        vertex_normals=vn,
    )


def run_image(cfg: ImageConfig, cfg_path: Path, progress: bool = False, inputs=None):
    """Render the image a config describes (library entry used by the CLI and the demo);
    ``inputs``: :func:`image_inputs` of the config if already resolved."""
    from . import _image

    _maybe_x64(cfg.render.dtype)
    mesh, mats, sensor, quat = image_inputs(cfg, cfg_path) if inputs is None else inputs
    try:
        return _image.render_mueller_image(
            mesh,
            mats,
            laser_dir=np.asarray(sensor.laser_dir, float),
            receiver_dir=np.asarray(sensor.receiver_dir, float),
            frame_tx=np.asarray(sensor.frame_tx, float),
            frame_rx=np.asarray(sensor.frame_rx, float),
            quaternion=quat,
            n_pixels=cfg.render.n_pixels,
            half_width=cfg.render.half_width_m,
            wavelength=float(sensor.wavelength),
            terms=_terms_arg(cfg.render.terms),
            shading=cfg.render.shading,
            dtype=_dtype(cfg.render.dtype),
            progress=progress,
        )
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: {err}") from None


def write_image_outputs(img, cfg, cfg_path, out: Outputs, prefix: str = "image", seconds=None):
    from . import _image

    np.savez_compressed(out.path(f"{prefix}.npz"), **img.arrays())
    what = cfg.scene or cfg.mesh or (cfg.shape or {}).get("name", "shape")
    title = f"{what}: monostatic Mueller image" if img.monostatic else f"{what}: Mueller image"
    _image.plot_mueller_image(img, out.path(f"{prefix}.png"), title=title)
    _image.plot_mueller_elements(img, out.path(f"{prefix}_mueller.png"), title=title)
    per_part = {}
    for i, name in enumerate(img.part_names):
        sel = (img.part == i) & img.lit
        per_part[name] = {"lit_pixels": int(sel.sum())}
        for q, arr in img.quantities.items():
            vals = arr[sel]
            vals = vals[np.isfinite(vals)]
            per_part[name][f"mean_{q}"] = float(vals.mean()) if vals.size else None
    pixel_area = float((img.u[1] - img.u[0]) ** 2) if len(img.u) > 1 else 0.0
    refl = img.quantities["reflectance"]
    write_json(
        out.path(f"{prefix}.json"),
        {
            "command": "image",
            "config_file": str(cfg_path),
            "config": cfg,
            "n_pixels": [len(img.v), len(img.u)],
            "pixel_size_m": float(img.u[1] - img.u[0]) if len(img.u) > 1 else None,
            "hit_pixels": int((img.part >= 0).sum()),
            "lit_pixels": int(img.lit.sum()),
            "radar_cross_section_like_m2_per_sr": float(np.nansum(refl) * pixel_area),
            "parts": per_part,
            "seconds": seconds,
            "units": {"reflectance": "1/sr (M00 cos theta_in)", "retardance": "rad", "u, v": "m"},
        },
    )


IMAGE_OUTPUTS = ["image.npz", "image.png", "image_mueller.png", "image.json"]


def cmd_image(args) -> int:
    cfg_path = _config_path(args, "image.toml")
    cfg = load_toml_model(ImageConfig, cfg_path, _overrides(args))
    _maybe_x64(cfg.render.dtype)
    inputs = image_inputs(cfg, cfg_path)
    with outputs(args.out, IMAGE_OUTPUTS, args.overwrite) as out:
        t0 = time.perf_counter()
        img = run_image(cfg, cfg_path, progress=_progress(args), inputs=inputs)
        write_image_outputs(img, cfg, cfg_path, out, seconds=time.perf_counter() - t0)
    _say(args, f"ppr image: wrote {', '.join(str(Path(args.out) / n) for n in IMAGE_OUTPUTS)}")
    return 0


# ============================================================================= simulate
SIMULATE_OUTPUTS = ["simulate.npz", "simulate.json", "simulate.png"]


def cmd_simulate(args) -> int:
    import ppr

    cfg_path = Path(args.config) if args.config else CONFIG_DIR / "scenes" / "cubesat3u_panels.toml"
    states, terms = _simulate_flags(args)
    _maybe_x64(args.dtype)
    scene = ppr.load_scene(cfg_path, _overrides(args))
    with outputs(args.out, SIMULATE_OUTPUTS, args.overwrite) as out:
        t0 = time.perf_counter()
        try:
            multibounce = {"auto": "auto", "on": True, "off": False}[
                getattr(args, "multibounce", "auto")
            ]
            prof = ppr.simulate(
                scene,
                states=states,
                terms=terms,
                dtype=_dtype(args.dtype),
                multibounce=multibounce,
            )
            data = np.asarray(prof.data, float)
        except ValueError as err:
            raise ConfigError(f"{cfg_path}: {err}") from None
        seconds = time.perf_counter() - t0
        arrays = {
            "data": data,
            "range_m": np.asarray(prof.range_m, float),
            "time_s": np.asarray(prof.time_s, float),
            "edges_m": np.asarray(prof.edges_m, float),
            "visibility": np.asarray(prof.visibility, float),
            "labels": np.array([str(x) for x in prof.labels]),
        }
        np.savez_compressed(out.path("simulate.npz"), **arrays)
        width = float(np.diff(arrays["edges_m"]).mean())
        energy = data.sum(-1)
        r = arrays["range_m"]
        w00 = data[0, 0] if prof.kind == "mueller" else data.reshape(-1, data.shape[-1])[0]
        tot = float(w00.sum())
        summary = {
            "command": "simulate",
            "config_file": str(cfg_path),
            "overrides": _overrides(args),
            "kind": prof.kind,
            "labels": list(prof.labels),
            "shape": list(data.shape),
            "units": {
                "data": "m^2/sr per bin (bin-integrated)",
                "range_m": "m (one-way)",
                "time_s": "s (round trip)",
            },
            "reference_range_m": prof.reference_range_m,
            "bin_width_m": width,
            "n_faces": int(scene.mesh.n_faces),
            "lit_visible_faces": int((arrays["visibility"] > 0).sum()),
            "energy": energy,
            "mean_range_m": float((w00 * r).sum() / tot) if tot > 0 else None,
            "rms_depth_m": float(np.sqrt((w00 * (r - (w00 * r).sum() / tot) ** 2).sum() / tot))
            if tot > 0
            else None,
            "seconds": seconds,
        }
        write_json(out.path("simulate.json"), summary)
        _plot_profiles(out.path("simulate.png"), arrays, prof.kind, list(prof.labels), cfg_path)
    _say(
        args, f"ppr simulate: wrote {', '.join(str(Path(args.out) / n) for n in SIMULATE_OUTPUTS)}"
    )
    return 0


def _simulate_flags(args) -> tuple[list[str] | None, Any]:
    """``--states`` and ``--terms`` checked before anything runs."""
    from ._brdf import _resolve_terms
    from ._pulse import STOKES_STATES

    states = None
    if args.states is not None:
        states = [s.strip() for s in args.states.split(",")]
        bad = [s for s in states if s not in STOKES_STATES]
        if bad:
            raise CLIError(
                f"--states {args.states!r}: unknown state {bad[0]!r} (known: "
                f"{', '.join(STOKES_STATES)}; comma-separated, e.g. H,V)"
            )
    terms = None if args.terms == "all" else args.terms
    if terms not in (None, "auto"):
        terms = tuple(t.strip() for t in terms.split(","))
        try:
            _resolve_terms(terms)
        except ValueError as err:
            raise CLIError(f"--terms {args.terms!r}: {str(err).removeprefix('terms: ')}") from None
    return states, terms


def _plot_profiles(path, arrays, kind, labels, title) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    data, r = arrays["data"], arrays["range_m"]
    if kind == "mueller":
        fig, axes = plt.subplots(4, 4, figsize=(12, 9), sharex=True)
        fig.subplots_adjust(left=0.07, right=0.98, bottom=0.07, top=0.93, hspace=0.3, wspace=0.3)
        for i in range(4):
            for j in range(4):
                ax = axes[i, j]
                ax.plot(r, data[i, j], lw=1)
                ax.set_title(f"M{i}{j}", fontsize=9)
                ax.tick_params(labelsize=7)
        for ax in axes[-1]:
            ax.set_xlabel("range [m]")
    else:
        rows = data.reshape(-1, data.shape[-1]) if kind == "channels" else data[:, 0]
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for lab, row in zip(labels, rows, strict=False):
            ax.plot(r, row, label=str(lab))
        ax.set_xlabel("range [m]")
        ax.set_ylabel("return per bin [m^2/sr]")
        ax.legend(fontsize=8)
    fig.suptitle(f"{title}: range-resolved return ({kind})")
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ============================================================================ inversion
def _finite_or_inf(v: float | str) -> float:
    return float("inf") if v in ("inf", float("inf")) else float(v)


class NoiseConfig(StrictModel):
    """Noise of simulated observations (inversion.NoiseModel); "inf" switches a term off."""

    snr: Annotated[float, pydantic.Field(gt=0.0)] | Literal["inf"] = 30.0
    speckle_cells: Annotated[float, pydantic.Field(ge=1.0)] | Literal["inf"] = 50.0
    jitter_bins: float = pydantic.Field(0.2, ge=0.0)
    max_offset_bins: float = pydantic.Field(3.0, ge=0.0)
    gain_min: float = pydantic.Field(0.1, gt=0.0)
    gain_max: float = pydantic.Field(10.0, gt=0.0)

    @pydantic.model_validator(mode="after")
    def _gains(self):
        if self.gain_min > self.gain_max:
            raise ValueError(
                f"gain_min = {self.gain_min} exceeds gain_max = {self.gain_max} (the gain is "
                "drawn log-uniformly between them)"
            )
        return self

    def model(self):
        import inversion

        return inversion.NoiseModel(
            snr=_finite_or_inf(self.snr),
            speckle_cells=_finite_or_inf(self.speckle_cells),
            jitter_bins=self.jitter_bins,
            max_offset_bins=self.max_offset_bins,
            gain_min=self.gain_min,
            gain_max=self.gain_max,
        )


DATABASE_STORE = "database.zarr"
DATABASE_SUMMARY = "database.json"
PARTIAL = ".partial"


def _shards_ok(args) -> None:
    if args.num_shards < 1 or not 0 <= args.shard_index < args.num_shards:
        raise CLIError(
            f"--shard-index {args.shard_index} --num-shards {args.num_shards}: need "
            "num_shards >= 1 and 0 <= shard_index < num_shards"
        )


def database_target(spec, sig_fn, out: Path, overwrite: bool, say, shards: int = 1) -> Path | None:
    """Where ``ppr database build`` builds (see DATABASE_HELP): the existing store itself to
    repair missing or corrupt chunks of the same settings, else ``database.zarr.partial``
    (fresh builds and ``--overwrite``), committed over the old store only once complete.
    ``None``: a worker of a sharded build finds the database complete (nothing to do)."""
    import inversion

    final, partial = out / DATABASE_STORE, out / (DATABASE_STORE + PARTIAL)
    if final.exists() and not overwrite:
        diffs = inversion.store_differences(spec, final, sig_fn)
        keep = "the old one is kept until the new one is complete"
        if diffs is None:
            raise CLIError(
                f"{final} exists and is not a signature database; pass --overwrite to replace "
                f"it ({keep}), or choose another --out"
            )
        if diffs:
            raise CLIError(
                f"{final} was built with other settings ({'; '.join(diffs)}); pass --overwrite "
                f"to replace it ({keep}), or choose another --out"
            )
        status = inversion.chunk_status(final, verify=True)
        if not status["missing"] and not status["corrupt"] and shards > 1:
            say(f"ppr database build: {final} is complete; nothing to do for this shard")
            return None
        if not status["missing"] and not status["corrupt"]:
            raise CLIError(
                f"{final} already exists and is complete (every chunk matches its checksum); "
                "pass --overwrite to rebuild, or choose another --out"
            )
        say(
            f"ppr database build: {final}: recomputing {len(status['corrupt'])} corrupt and "
            f"{len(status['missing'])} missing chunks"
        )
        return final
    if partial.exists():
        diffs = inversion.store_differences(spec, partial, sig_fn)
        if diffs is None or diffs:
            what = "is not a signature database" if diffs is None else (
                "was started with other settings (" + "; ".join(diffs) + ")"
            )
            if not overwrite:
                raise CLIError(
                    f"{partial}: an unfinished build that {what}; pass --overwrite to discard "
                    "it, or choose another --out"
                )
            shutil.rmtree(partial)  # an unfinished build, never a result
        else:
            say(f"ppr database build: resuming {partial} (only missing chunks are computed)")
    return partial


def _rebuild_command(db: Path) -> str:
    """The ``ppr database build`` command that built ``db`` (from its database.json)."""
    import shlex

    folder = db.parent
    cmd = ["ppr", "database", "build"]
    try:
        info = json.loads((folder / DATABASE_SUMMARY).read_text())
        cmd += ["-c", info["config_file"]]
        for key, value in (info.get("overrides") or {}).items():
            cmd += ["--set", f"{key}={json.dumps(value)}"]
    except (OSError, ValueError, KeyError, TypeError):
        cmd += ["-c", "<its database config>"]
    cmd += ["-o", str(folder)]
    return " ".join(shlex.quote(c) if not c.startswith("<") else c for c in cmd)


def database_error_hint(db: Path, err: Exception) -> str:
    """A load error of ``db`` with the command that finishes or repairs it."""
    import inversion

    msg = _one_line(err)
    if isinstance(err, inversion.CorruptChunkError | inversion.IncompleteDatabaseError):
        msg = msg.split("; rerun build_database")[0]
        return f"{msg}; rerun `{_rebuild_command(db)}` to recompute them"
    partial = db.with_name(db.name + PARTIAL)
    if not db.exists() and partial.exists():
        return (
            f"{db} does not exist; an unfinished build is at {partial}: rerun "
            f"`{_rebuild_command(db)}` to finish it"
        )
    return msg


def _database_summary(args, cfg_path, db, report, status) -> dict:
    return {
        "command": "database build",
        "config_file": str(Path(cfg_path).resolve()),
        "overrides": _overrides(args),
        "path": str(db),
        "n_rows": report.n_rows,
        "n_chunks": report.n_chunks,
        "computed_chunks": len(report.computed),
        "skipped_chunks": len(report.skipped),
        "recomputed_corrupt": report.recomputed_corrupt,
        "missing_chunks": len(status["missing"]),
        "complete": not status["missing"],
        "seconds": report.seconds,
        "rows_per_second": report.rows_per_second,
        "n_devices": report.n_devices,
        "shard": [args.shard_index, args.num_shards],
    }


def _validate_store(path: Path) -> None:
    import inversion

    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist")
    status = inversion.chunk_status(path, verify=False)
    if status["missing"]:  # pragma: no cover - the command checks before committing
        raise RuntimeError(f"{path}: {len(status['missing'])} chunks missing; not committed")


def cmd_database_build(args) -> int:
    import inversion

    cfg_path = (
        Path(args.config) if args.config else CONFIG_DIR / "databases" / "synthetic_small.toml"
    )
    spec = inversion.load_spec(cfg_path, _overrides(args))
    _shards_ok(args)
    try:
        sig_fn = inversion.make_signature_fn(spec)
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: {_one_line(err)}") from None
    out = _outputs.check_out_folder(args.out)
    _outputs.recover(out)
    target = database_target(
        spec, sig_fn, out, args.overwrite, lambda m: _say(args, m), args.num_shards
    )
    if target is None:
        return 0
    made = [p for p in (out, *out.parents) if not p.exists()]
    args._interrupt_note = f"rerun the same command to resume {target}"
    try:
        report = inversion.build_database(
            spec,
            target,
            sig_fn,
            progress=_progress(args),
            shard_index=args.shard_index,
            num_shards=args.num_shards,
        )
    except BaseException:
        _drop_empty_build(target, made)
        raise
    status = inversion.chunk_status(target, verify=False)  # the build verified every chunk
    final = out / DATABASE_STORE
    if status["missing"]:  # other shards still building
        _say(
            args,
            f"ppr database build: shard {args.shard_index}/{args.num_shards} done "
            f"({len(report.computed)} chunks computed); {len(status['missing'])} chunks of other "
            f"shards missing in {target}: the builder that finishes last moves it to {final}",
        )
        return 0
    summary = _database_summary(args, cfg_path, final, report, status)
    names = [DATABASE_SUMMARY] if target == final else [DATABASE_STORE, DATABASE_SUMMARY]
    try:
        with outputs(
            out, names, overwrite=True, validators={DATABASE_STORE: _validate_store}
        ) as o:
            if target != final:
                o.adopt(DATABASE_STORE, target)
            write_json(o.path(DATABASE_SUMMARY), summary)
    except FileNotFoundError:
        if target.exists() or not final.exists():
            raise
        _say(args, f"ppr database build: another builder moved {target} to {final} first")
        return 0
    _say(
        args,
        f"ppr database build: {final} ({report.n_rows} rows, {len(report.computed)} chunks "
        f"computed, {len(report.skipped)} already done)",
    )
    return 0


def _drop_empty_build(target: Path, made: list[Path]) -> None:
    """After a failed build: remove a staged store without one finished chunk, and the
    folders made for it (a store with finished chunks is kept for resuming)."""
    if target.name.endswith(PARTIAL) and target.is_dir():
        chunks = target / "_chunks"
        if not (chunks.is_dir() and any(chunks.glob("*.json"))):
            shutil.rmtree(target, ignore_errors=True)
    for p in made:  # innermost first
        with contextlib.suppress(OSError):
            p.rmdir()


class ReportConfig(StrictModel):
    """``ppr report``: classifier evaluation on held-out simulated observations."""

    database: str
    database_path: str | None = None
    snrs: NonEmpty[PositiveFloat] = [10.0, 30.0, 100.0, 300.0]
    grid_sizes: NonEmpty[Annotated[int, pydantic.Field(ge=1, le=16)]] = [1, 2, 3]
    n_obs: int = pydantic.Field(32, ge=1)
    weight_kinds: NonEmpty[Literal["uniform", "channel", "range", "fisher"]] = [
        "uniform",
        "channel",
        "range",
        "fisher",
    ]
    speckle_cells: float = pydantic.Field(50.0, ge=1.0)
    jitter_bins: float = pydantic.Field(0.2, ge=0.0)
    max_offset_bins: float = pydantic.Field(4.0, ge=0.0)
    gain_range: tuple[PositiveFloat, PositiveFloat] = (0.1, 10.0)
    seed: Seed = 0
    top_k: int = pydantic.Field(5, ge=1)

    @pydantic.field_validator("gain_range")
    @classmethod
    def _gain_order(cls, v):
        if v[0] > v[1]:
            raise ValueError("must be [low, high] with low <= high")
        return v


REPORT_OUTPUTS = [
    "report.json",
    "report.md",
    "accuracy_vs_snr.png",
    "attitude_vs_snr.png",
    "attitude_vs_resolution.png",
    "confusion_shape.png",
    "confusion_material.png",
    "confusion_finish.png",
]


def cmd_report(args) -> int:
    import inversion

    cfg_path = _config_path(args, "report.toml")
    cfg = load_toml_model(ReportConfig, cfg_path, _overrides(args))
    spec_path = _resolve_path(cfg.database, cfg_path)
    try:
        spec = inversion.load_spec(spec_path)
        inversion.make_signature_fn(spec)  # names the model knows
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: database = {cfg.database!r}: {_one_line(err)}") from None
    bank = None
    if cfg.database_path is not None:
        bank = load_bank(cfg.database_path, cfg_path, "database_path")
    with outputs(args.out, REPORT_OUTPUTS, args.overwrite) as out:
        inversion.evaluate(
            spec,
            out.folder,
            snrs=tuple(cfg.snrs),
            grid_sizes=tuple(cfg.grid_sizes),
            n_obs=cfg.n_obs,
            weight_kinds=tuple(cfg.weight_kinds),
            speckle_cells=cfg.speckle_cells,
            jitter_bins=cfg.jitter_bins,
            max_offset_bins=cfg.max_offset_bins,
            gain_range=tuple(cfg.gain_range),
            seed=cfg.seed,
            bank=bank,
            k=cfg.top_k,
        )
    _say(args, f"ppr report: wrote {Path(args.out) / 'report.md'} and plots")
    return 0


class ClassifyConfig(StrictModel):
    """``ppr classify``: top-k database candidates for observations."""

    database: str
    observations: str = "simulate"
    attribute: Literal["shape", "material", "finish", "attitude"] = "shape"
    weights: Literal["uniform", "channel", "range", "fisher"] = "fisher"
    top_k: int = pydantic.Field(5, ge=1, le=1000)
    max_shift_bins: int | None = pydantic.Field(None, ge=0)
    n_simulated: int = pydantic.Field(16, ge=1, le=100_000)
    seed: Seed = 0
    noise: NoiseConfig = NoiseConfig()


CLASSIFY_OUTPUTS = ["classify.json", "classify.npz", "classify.png"]


def load_bank(value: str, cfg_path: Path, field: str):
    """``inversion.load_database`` of the config's ``field = value``, with errors naming them
    and, for unfinished or corrupt databases, the ``ppr database build`` command that
    completes them."""
    import inversion

    dbp = _resolve_path(value, cfg_path)
    try:
        return inversion.load_database(dbp)
    except (ValueError, OSError) as err:
        hint = database_error_hint(dbp, err)
        raise ConfigError(f"{cfg_path}: {field} = {value!r}: {hint}") from None


def read_observations(cfg, cfg_path: Path, bank) -> tuple[np.ndarray, str]:
    """Observations ``(N, channels, bins)`` from an .npz file, checked against the bank."""
    path = _resolve_path(cfg.observations, cfg_path)
    where = f"{cfg_path}: observations = {cfg.observations!r}"
    if not path.is_file():
        raise ConfigError(f"{where}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "data" not in z.files:
                raise ConfigError(f"{where}: no 'data' array (it has {', '.join(z.files)})")
            data = np.asarray(z["data"], np.float64)
            sensor = str(z["sensor"]) if "sensor" in z.files else bank.sensor
    except ConfigError:
        raise
    except (OSError, ValueError, EOFError):
        raise ConfigError(f"{where}: not a NumPy .npz file of arrays") from None
    if data.ndim == 2:
        data = data[None]
    want = (bank.n_channels, bank.n_bins)
    if data.ndim != 3 or data.shape[1:] != want or len(data) == 0:
        raise ConfigError(
            f"{where}: data has shape {data.shape}; this database needs (N, {want[0]} channels, "
            f"{want[1]} bins) or ({want[0]}, {want[1]})"
        )
    if not np.all(np.isfinite(data)):
        raise ConfigError(f"{where}: data holds {int((~np.isfinite(data)).sum())} NaN/inf values")
    return data, sensor


def cmd_classify(args) -> int:
    import jax.numpy as jnp

    import inversion

    cfg_path = _config_path(args, "classify.toml")
    cfg = load_toml_model(ClassifyConfig, cfg_path, _overrides(args))
    dbp = _resolve_path(cfg.database, cfg_path)
    bank = load_bank(cfg.database, cfg_path, "database")
    if cfg.max_shift_bins is not None and cfg.max_shift_bins > bank.n_bins - 1:
        raise ConfigError(
            f"{cfg_path}: max_shift_bins = {cfg.max_shift_bins}: at most n_bins - 1 = "
            f"{bank.n_bins - 1} for this database"
        )
    noise = cfg.noise.model()
    data = None
    if cfg.observations != "simulate":
        data, sensor = read_observations(cfg, cfg_path, bank)
    _outputs.refuse_existing(args.out, CLASSIFY_OUTPUTS, args.overwrite)
    truth = None
    if cfg.observations == "simulate":
        import zarr

        spec = inversion.spec_from_dict(
            dict(zarr.open_group(str(dbp), mode="r").attrs["spec"]), str(dbp)
        )
        sig_fn = inversion.make_signature_fn(spec)
        rng = np.random.default_rng(cfg.seed)
        import jax

        from inversion._grid import random_quaternions

        n = cfg.n_simulated
        truth = {
            "shape_id": rng.integers(0, len(spec.shapes), n).astype(np.int32),
            "material_id": rng.integers(0, len(spec.materials), n).astype(np.int32),
            "finish_id": rng.integers(0, len(spec.finishes), n).astype(np.int32),
            "attitude_id": np.zeros(n, np.int32),
            "quat": np.asarray(
                random_quaternions(jax.random.key(cfg.seed), n, jnp.float32), np.float64
            ),
        }
        clean = np.asarray(sig_fn({k: jnp.asarray(v) for k, v in truth.items()}), np.float64)
        data = np.stack(
            [
                np.asarray(inversion.observe(c, noise, seed=cfg.seed + i, sensor=bank.sensor).data)
                for i, c in enumerate(clean)
            ]
        )
        sensor = bank.sensor
    obs = [inversion.Observation(data=d, sensor=sensor) for d in data]
    with outputs(args.out, CLASSIFY_OUTPUTS, args.overwrite) as out:
        w = inversion.design_weights(bank, cfg.weights, cfg.attribute)
        prep = inversion.prepare(bank, w)
        try:
            res = inversion.classify(
                prep, obs, k=min(cfg.top_k, len(bank)), max_shift=cfg.max_shift_bins
            )
        except ValueError as err:
            raise ConfigError(f"{cfg_path}: observations: {err}") from None
        names = bank.names
        cands = []
        for i in range(len(data)):
            rows = []
            for j, r in enumerate(res.index[i]):
                rows.append(
                    {
                        "row": int(r),
                        "score": float(res.score[i, j]),
                        "shift_bins": float(res.shift_refined[i, j]),
                        "shape": names["shapes"][bank.shape_id[r]],
                        "material": names["materials"][bank.material_id[r]],
                        "finish": names["finishes"][bank.finish_id[r]],
                        "quaternion": bank.quat[r],
                    }
                )
            cands.append(rows)
        summary = {
            "command": "classify",
            "config_file": str(cfg_path),
            "config": cfg,
            "database": str(dbp),
            "n_templates": len(bank),
            "n_observations": len(data),
            "seconds": res.seconds,
            "ms_per_observation": 1e3 * res.seconds / len(data),
            "candidates": cands,
        }
        if truth is not None:
            best = res.best(bank)
            summary["accuracy"] = {
                a: float(np.mean(best[f"{a}_id"] == truth[f"{a}_id"]))
                for a in ("shape", "material", "finish")
            }
        write_json(out.path("classify.json"), summary)
        extra = {f"truth_{k}": v for k, v in (truth or {}).items()}
        np.savez_compressed(
            out.path("classify.npz"),
            data=data,
            sensor=np.array(sensor),
            index=res.index,
            score=res.score,
            shift=res.shift_refined,
            **extra,
        )
        _plot_classify(out.path("classify.png"), data, bank, res)
    _say(
        args, f"ppr classify: wrote {', '.join(str(Path(args.out) / n) for n in CLASSIFY_OUTPUTS)}"
    )
    return 0


def _plot_classify(path, data, bank, res) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.14, top=0.88, wspace=0.25)
    axes[0].hist(res.score[:, 0], bins=20, color="0.5")
    axes[0].set_xlabel("best score")
    axes[0].set_ylabel("observations")
    x = data[0] / max(float(data[0].sum()), 1e-300)
    y = bank.signatures[res.index[0, 0]]
    axes[1].plot(x.sum(0), label="observation 0 (all channels)")
    axes[1].plot(
        np.roll(y.sum(0), int(round(res.shift[0, 0]))), "--", label="best template, shifted"
    )
    axes[1].set_xlabel("range bin")
    axes[1].legend(fontsize=8)
    fig.suptitle("ppr classify")
    fig.savefig(path, dpi=90)
    plt.close(fig)


class InvertObservation(StrictModel):
    source: str = "simulate"  # "simulate" (from the scene's pose and materials) or an .npz
    photons: float = pydantic.Field(2e4, gt=0.0)  # expected total signal counts (gain)
    range_offset_m: float = 0.003
    seed: Seed = 0


def _invert_command_schema():
    """``ppr invert``'s schema: :class:`inversion.InvertConfig`'s fields (same names, top
    level) plus the scene, channels, BRDF, observation and the MCMC config file."""
    import inversion

    class InvertCommandConfig(inversion.InvertConfig):
        """``ppr invert``: classify, refine, weigh materials and modes, sample (invert)."""

        scene: str
        channels: Literal["full", "stokes", "copol", "circular"] = "copol"
        brdf: Literal["ppr", "glossy"] = "ppr"
        # priors and sampler (configs/inversion/*.toml); None: no posterior sampling
        mcmc: str | None = "../inversion/default.toml"  # type: ignore[assignment]
        mcmc_walkers: int | None = pydantic.Field(None, ge=4)
        mcmc_steps: int | None = pydantic.Field(None, ge=10)
        mcmc_burn_in: int | None = pydantic.Field(None, ge=0)
        mcmc_set: dict[str, Any] = {}
        observation: InvertObservation = InvertObservation()

    return InvertCommandConfig


# the sampler fields ppr invert sets directly, as written in its config
_MCMC_FIELDS = {"n_walkers": "mcmc_walkers", "n_steps": "mcmc_steps", "burn_in": "mcmc_burn_in"}


def invert_config(cfg, cfg_path: Path, progress: bool):
    """The library config (:class:`inversion.InvertConfig`) of a ``ppr invert`` config, with
    its MCMC file read and the sampler overrides applied: every field validated before any
    computation, errors naming the field as written in ``cfg_path`` (or the MCMC file)."""
    import inversion
    from inversion._mcmc import SamplerConfig

    mcfg = None
    if cfg.mcmc is not None:
        mpath = _resolve_path(cfg.mcmc, cfg_path)
        if not mpath.is_file():
            raise ConfigError(f"{cfg_path}: mcmc = {cfg.mcmc!r}: no such file ({mpath})")
        mcfg = inversion.load_mcmc_config(mpath, cfg.mcmc_set)
        upd = {k: getattr(cfg, v) for k, v in _MCMC_FIELDS.items() if getattr(cfg, v) is not None}
        samp = {**mcfg.sampler.model_dump(), **upd, "progress": progress}
        try:
            sampler = SamplerConfig.model_validate(samp)
        except pydantic.ValidationError as err:
            parts = []
            for e in err.errors():
                loc = e["loc"][0] if e["loc"] else None
                msg = str(e["msg"]).removeprefix("Value error, ")
                if loc in _MCMC_FIELDS:
                    parts.append(f"{_MCMC_FIELDS[loc]} = {samp[loc]!r}: {msg}")
                else:  # a check across fields (burn-in against steps)
                    parts.append(
                        f"mcmc_burn_in = {samp['burn_in']!r}, mcmc_steps = {samp['n_steps']!r} "
                        f"(with {cfg.mcmc}): {msg}"
                    )
            raise ConfigError(f"{cfg_path}: " + "; ".join(parts)) from None
        mcfg = mcfg.model_copy(update={"sampler": sampler})
    lib_fields = set(inversion.InvertConfig.model_fields) - {"mcmc", "progress"}
    data = {k: getattr(cfg, k) for k in lib_fields}
    return inversion.InvertConfig.model_validate({**data, "mcmc": mcfg, "progress": progress})


def _simulated_truth(model, scene, photons: float, offset: float):
    import jax.numpy as jnp

    import inversion

    mats = scene.materials
    truth = inversion.PhysicalParams(
        np.asarray(scene.pose.quaternion, np.float64),
        [float(np.asarray(m.m)) for m in mats],
        [complex(np.asarray(m.n)) for m in mats],
        [float(np.asarray(m.corr_length)) for m in mats],
        range_offset=offset,
        gain=1.0,
    )
    shape = np.asarray(model.expected(truth, model.prepare(truth)))
    gain = photons / max(float(shape.sum()), 1e-300)
    truth = eqx_replace(truth, gain=jnp.asarray(gain, jnp.float64))
    return truth, shape * gain


def run_invert(cfg, cfg_path: Path, out, overwrite: bool = False, progress: bool = False):
    """``ppr invert`` on a parsed config: validate everything (MCMC included), build the
    scene's forward model, read or simulate the observation, :func:`inversion.invert`,
    :meth:`inversion.Inversion.write` into ``out`` (atomically). Returns the Inversion."""
    import inversion
    import ppr

    lib_cfg = invert_config(cfg, cfg_path, progress)
    ob = cfg.observation
    data = None
    if ob.source != "simulate":
        path = _resolve_path(ob.source, cfg_path)
        where = f"{cfg_path}: observation.source = {ob.source!r}"
        if not path.is_file():
            raise ConfigError(f"{where}: no such file")
        try:
            with np.load(path, allow_pickle=False) as z:
                if "data" not in z.files:
                    raise ConfigError(f"{where}: no 'data' array (it has {', '.join(z.files)})")
                data = np.asarray(z["data"], np.float64)
        except (OSError, ValueError, EOFError) as err:
            if isinstance(err, ConfigError):
                raise
            raise ConfigError(f"{where}: not a NumPy .npz file of arrays") from None
    _maybe_x64("float64")  # inversion runs in float64 (the MCMC needs it)
    scene = ppr.load_scene(_resolve_path(cfg.scene, cfg_path))
    chm = inversion.MeasurementModel.preset(cfg.channels).channel_matrix()
    brdf = None
    if cfg.brdf == "glossy":
        from ._pulse import glossy_fresnel_mueller as brdf
    model = inversion.SimulatorModel(scene, chm, brdf=brdf, dense=True)
    if data is not None and data.shape != (model.n_channels, model.n_bins):
        raise ConfigError(
            f"{cfg_path}: observation.source = {ob.source!r}: data has shape {data.shape}; the "
            f"scene and channels give ({model.n_channels} channels, {model.n_bins} bins)"
        )
    _outputs.refuse_existing(out, inversion.INVERT_FILES, overwrite)
    truth = None
    if data is None:
        truth, expected = _simulated_truth(model, scene, ob.photons, ob.range_offset_m)
        # the kernel's roundoff can give -1e-22 counts; anything beyond roundoff is a bug
        if np.min(expected) < -1e-9 * max(float(np.max(expected)), 1e-300):
            raise RuntimeError(
                f"simulated expected counts are negative beyond roundoff "
                f"(min {np.min(expected):.3g}, max {np.max(expected):.3g}); refusing to observe"
            )
        data = np.random.default_rng(ob.seed).poisson(np.maximum(expected, 0.0)).astype(float)
    name = Path(cfg.scene).stem  # the candidate's name: its scene file
    try:
        inv = inversion.invert(data, {name: model}, config=lib_cfg)
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: {err}") from None
    extra = {"command": "invert", "config_file": str(cfg_path), "observation": ob}
    if truth is not None:
        noise = inversion.PoissonCounts(lib_cfg.background)
        crb = inversion.cramer_rao(model, truth, noise, free=tuple(inv.fit.parametrisation.free))
        ob_crb = crb.observability(line_of_sight=inv.line_of_sight_world)
        extra["truth"] = {
            "quaternion": np.asarray(truth.quaternion),
            "m": np.asarray(truth.m),
            "n": np.asarray(truth.n),
            "range_offset_m": float(truth.range_offset),
            "gain": float(truth.gain),
            "errors": inv.compare(truth, name),
            # what no unbiased estimator can beat (observable subspace; null: unobservable)
            "cramer_rao": {
                "labels": crb.labels,
                "sigma": ob_crb.to_dict()["sigma"],
                "unobservable": ob_crb.names,
            },
        }
    inv.write(out, overwrite=overwrite, extra=extra)
    return inv


def cmd_invert(args) -> int:
    cfg_path = _config_path(args, "invert.toml")
    cfg = load_toml_model(_invert_command_schema(), cfg_path, _overrides(args))
    if not getattr(args, "quiet", False):
        import logging

        logging.basicConfig(level=logging.WARNING, format="%(message)s")
        logging.getLogger("inversion.invert").setLevel(logging.INFO)
    inv = run_invert(cfg, cfg_path, args.out, args.overwrite, _progress(args))
    _say(args, inv.summary())
    _say(args, f"ppr invert: wrote {Path(args.out) / 'invert.json'} and the posterior files")
    return 0


def eqx_replace(module, **changes):
    import equinox as eqx

    for k, v in changes.items():
        module = eqx.tree_at(lambda m, k=k: getattr(m, k), module, v)
    return module


# ================================================================================= demo
def _find(module: str, names: Sequence[str]) -> Callable | None:
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name and (err.name == module or module.startswith(err.name + ".")):
            return None
        raise
    for n in names:
        fn = getattr(mod, n, None)
        if callable(fn):
            return fn
    return None


DEMO_STEPS: list[tuple[str, str, str, tuple[str, ...]]] = [
    # (key, label, module, candidate function names); the first one found per key runs
    ("brdf", "BRDF figures", "ppr.demo", ("brdf_figures",)),
    ("double", "double-bounce figures", "ppr.demo", ("double_figures", "double_bounce_figures")),
    ("double", "double-bounce figures", "ppr._double", ("double_figures", "double_bounce_figures")),
    ("pulse", "pulse figures", "ppr.demo", ("pulse_figures",)),
    ("pulse", "pulse figures", "ppr.plots_pulse", ("pulse_figures",)),
    ("pulse", "pulse figures", "ppr._pulse", ("pulse_figures",)),
]
DEMO_KEYS = ("brdf", "double", "pulse", "image")


def cmd_demo(args) -> int:
    only = DEMO_KEYS if not args.only else tuple(k.strip() for k in args.only.split(","))
    bad = [k for k in only if k not in DEMO_KEYS]
    if bad:
        raise CLIError(
            f"--only {args.only!r}: unknown step {bad[0]!r} (steps: {', '.join(DEMO_KEYS)})"
        )
    if not 4 <= args.pixels <= 2048:
        raise CLIError(f"--pixels {args.pixels}: the image size must lie in [4, 2048] pixels")
    cfg_path = CONFIG_DIR / "cli" / "image.toml"
    cfg = inputs = None
    if "image" in only:  # validate the image's config before drawing anything
        cfg = load_toml_model(
            ImageConfig, cfg_path, {"render.n_pixels": args.pixels, **_overrides(args)}
        )
        _maybe_x64(cfg.render.dtype)
        inputs = image_inputs(cfg, cfg_path)
    done: dict[str, float] = {}
    skipped: list[str] = []
    t_all = time.perf_counter()
    # every figure is staged and the whole set replaces the old one at the end
    with outputs(args.out, None, overwrite=True) as staged:
        out = staged.folder
        for key, label, module, names in DEMO_STEPS:
            if key not in only or label in done:
                continue
            fn = _find(module, names)
            if fn is None:
                continue
            _say(args, f"ppr demo: {label} ...")
            t0 = time.perf_counter()
            fn(out)
            done[label] = time.perf_counter() - t0
        for key, label, _, _ in DEMO_STEPS:
            if key in only and label not in done and label not in skipped:
                skipped.append(label)
        if cfg is not None:
            _say(args, "ppr demo: Mueller image of the example satellite ...")
            t0 = time.perf_counter()
            img = run_image(cfg, cfg_path, progress=_progress(args), inputs=inputs)
            write_image_outputs(img, cfg, cfg_path, staged, seconds=time.perf_counter() - t0)
            done["Mueller image"] = time.perf_counter() - t0
        for label in skipped:
            _say(args, f"ppr demo: skipped {label} (not available in this build)")
        summary = {
            "steps_seconds": done,
            "skipped": skipped,
            "total_seconds": time.perf_counter() - t_all,
        }
        write_json(out / "demo.json", summary)
        pngs = sorted(p.name for p in out.glob("*.png"))
    _say(
        args, f"ppr demo: {len(pngs)} figures in {args.out} ({summary['total_seconds']:.0f} s)"
    )
    return 0


# =============================================================================== parser
class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    pass


def _common(p: argparse.ArgumentParser, default_config: str | None, out_default: str) -> None:
    if default_config is not None:
        p.add_argument(
            "--config",
            "-c",
            metavar="TOML",
            default=None,
            help=f"config file (TOML); default: configs/{default_config}",
        )
    p.add_argument(
        "--set",
        "-s",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a config field, dotted keys, TOML values (repeatable), "
        "e.g. --set wavelength=1064e-9 --set pose.to_sensor=[0,0,1]",
    )
    p.add_argument("--out", "-o", metavar="DIR", default=out_default, help="output folder")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace existing outputs in --out (default: refuse)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or messages")


BRDF_HELP = """\
Evaluate the Mueller BRDF of one material over a grid of incidence and bistatic angles.

Config fields (configs/cli/brdf.toml):
  material       library name ("aluminium", or "aluminium/rough" with a finish; see
                 configs/materials.toml) or inline {n_real, n_imag, m = <Blinn-Phong
                 exponent, 0..1e6>, corr_length_m = <metres>}
  wavelength_nm  nanometres (default 532)
  terms          "auto", "all", or a list of "single", "double", "multiple"
  incidence_deg  incidence angles from the normal, degrees in [0, 90)
  bistatic_deg   bistatic angles (between k_in and k_out), degrees: a list or
                 {start, stop, num}
  plane          "in": k_out in the plane of incidence, toward the normal;
                 "cross": rotated out of the plane of incidence
  dtype          "float32" or "float64"
Stokes frames: the lab y axis (perpendicular to the plane of incidence) projected
perpendicular to each beam. Outputs: brdf.npz (mueller [1/sr] of shape (incidence,
bistatic, 4, 4), polarimetric quantities), brdf.json, brdf.png."""

IMAGE_HELP = """\
Render per-pixel Mueller images of a mesh at a pose (orthographic view from the receiver,
one embree ray per pixel, macro shadowing) as PNG panels with colour bars: total reflectance
M00 cos(theta_in) [1/sr], depolarization index, polarizance, diattenuation and retardance
[rad] (Lu-Chipman), plus the 16 normalized Mueller elements.

Config fields (configs/cli/image.toml); exactly one of scene, mesh, [shape]:
  scene          a scene config (configs/scenes/*.toml): mesh, materials, pose and sensor
                 all come from it
  mesh           "example" (the shipped example satellite) or a mesh file trimesh reads
                 (metres; one part per geometry), relative to the config's folder
  shape          {name = "sphere", params = {radius = 0.5}} (ppr.shapes)
  materials      part -> library material ("name" or "name/finish", configs/materials.toml)
                 or inline {n_real, n_imag, m (Blinn-Phong exponent, 0..1e6),
                 corr_length_m}; "default" covers unlisted parts
  pose           quaternion = [w, x, y, z] (body -> world), position_m
  view           wavelength_nm; line_of_sight (laser propagation, sensor -> object, world);
                 polarization_reference (sensor x axis, world); bistatic_angle_urad
                 (microradians; 0: monostatic, every visible point lit; > 0: shadow rays
                 toward the laser); bistatic_azimuth_deg
  render         n_pixels (image is n x n); half_width_m (half field of view, metres;
                 default fits the mesh); shading "flat" | "smooth"; terms "auto" | "all" |
                 list of "single", "double", "multiple"; dtype "float32" | "float64"
Outputs: image.npz (mueller (H, W, 4, 4) in 1/sr, NaN off the object; cos_in, normal, part,
lit, quantities), image.png, image_mueller.png, image.json."""

SIMULATE_HELP = """\
Simulate the range-resolved return of a scene: the Gaussian pulse stretched by the posed
mesh's range-depth profile, every lit and visible facet contributing its Mueller BRDF times
its projected area (closed-form triangle range-area density convolved with the pulse).

Config: a scene file (configs/scenes/*.toml: sensor, shape or mesh, materials per part,
pose.quaternion [w, x, y, z] body -> world, pose.position_m, visibility.samples_per_face)
referencing a sensor file (configs/sensors/*.toml: wavelength_nm, line_of_sight,
polarization_reference, bistatic_angle_urad [microradians], reference_range_km,
pulse.fwhm_ps, pulse.jitter_ps [picoseconds], bins.width_mm, bins.count, bins.start_m).
--set overrides apply to the scene file (e.g. --set pose.quaternion=[1,0,0,0]).
Outputs: simulate.npz (data in m^2/sr per bin, range_m one-way, time_s round trip, edges_m,
visibility per face), simulate.json (energies, mean range, rms depth), simulate.png."""

DATABASE_HELP = """\
Build a signature database (shapes x attitudes x materials x finishes) chunk by chunk into
--out/database.zarr (zarr v3). The build runs in --out/database.zarr.partial and is moved to
database.zarr only when every chunk is done and verified: rerunning the same command after
an interruption computes only the missing chunks; with --overwrite the old database stays
in place (and a config error deletes nothing) until the new one is complete. On an existing
database.zarr of the same settings the command verifies every chunk's checksum and
recomputes missing or corrupt chunks in place; a complete, valid one is not rebuilt unless
--overwrite. Summary: --out/database.json (rows, chunks, rows per second).

Config (configs/databases/*.toml): name; model ("synthetic" stand-in or "ppr"); materials
(library names); [finishes] name = Blinn-Phong exponent m; [[shapes]] name, symmetry
(a class such as "dihedral:4", or "auto": the group of the shape's own mesh, model "ppr");
[grid] kind ("hopf"), size (nside: angular resolution), reduce_symmetry; [sensor] channels
(full, stokes, copol, circular), n_bins, bin_width_m (metres), pulse_fwhm_s (seconds);
chunk_rows; compute_dtype. Several hosts: run with --shard-index i --num-shards N against
one shared --out (see docs/distributed_builds.md); the builder that finds every chunk done
when it finishes moves the database into place and writes database.json."""

CLASSIFY_HELP = """\
Classify observations against a built database: weighted inner product maximized over the
unknown range shift (FFT), top-k candidates with scores, shifts (bins) and their shape,
material, finish and attitude quaternion.

Config fields (configs/cli/classify.toml):
  database       path of a built database (.zarr, from `ppr database build`)
  observations   "simulate" (held-out noisy observations at random attitudes, from the
                 database's own signature model) or an .npz with data (N, channels, bins)
  attribute      weights tuned for "shape", "material", "finish" or "attitude"
  weights        "uniform", "channel", "range" or "fisher"
  top_k, max_shift_bins (bins; default: the classifier's)
  n_simulated, seed, [noise] snr (sqrt of expected total counts; "inf": none),
                 speckle_cells, jitter_bins, max_offset_bins (bins), gain_min, gain_max
Outputs: classify.json (candidates, accuracy if simulated, ms per observation),
classify.npz, classify.png."""

INVERT_HELP = """\
One observation -> shape, attitude, roughness m, material, range offset (metres) and gain,
and how far to believe them (inversion.invert): templates of the scene's mesh over an
attitude grid are matched to the data, screened starts are refined (optimistix
Levenberg-Marquardt), every library material is weighed by its evidence, every mirror image
and near symmetry of the mesh is refit as a mode, the fit is tested against its noise, the
unobservable directions are named, and each mode's posterior is sampled (emcee).

Config fields (configs/cli/invert.toml); every one, the MCMC file included, is checked
before any computation:
  scene          scene config (mesh, sensor, pulse, bins; its pose and materials are the
                 truth of simulated observations)
  channels       PSG/PSA preset (transmitted; analyzed): full (H,V,D,L; H,V,D,L), stokes
                 (H,L; H,V,D,L), copol (H; H,V), circular (L; L,R). R/L: right/left
                 circular, clockwise/counterclockwise seen looking into the beam
  brdf           "ppr" (ppr.mueller_brdf) or "glossy" (cheap polarizing stand-in)
  free           parameter groups to fit (attitude, m, n, corr_length, range_offset, gain)
  likelihood     "poisson" (photo-counts) or "gaussian"; solver "lm" | "dogleg" |
                 "gauss_newton"; max_steps, rounds, screen_tol
  materials      library materials weighed per mesh part (probabilities); finishes
                 {name = Blinn-Phong m} and [grid] kind, size: the templates' roughness
                 and attitudes (Hopf nside: 72 nside^3 attitudes, ~55/nside degrees apart)
  top_k, per_shape  distinct template attitudes refined
  symmetry       "auto" (the mesh's own group), a class (dihedral:n, octahedral) or
                 "none"; near_tol (fraction of the mesh size): near symmetries refit as
                 modes; ambiguity: weight above which a second mode is unresolved
  mismatch_p     goodness-of-fit p-value below which the model does not fit the data
  mcmc           priors + sampler config (configs/inversion/*.toml); mcmc_walkers,
                 mcmc_steps, mcmc_burn_in override its sampler; mcmc_set = {"dotted.key" =
                 value} overrides any of its fields (e.g. "priors.gain.high")
  [observation]  source ("simulate" or an .npz with data (channels, bins)), photons
                 (expected total counts), range_offset_m (metres), seed
Outputs: invert.json (converged, reliable and the reasons, goodness of fit, observability,
shapes, material probabilities, modes with weights, credible intervals and ArviZ
diagnostics, errors against a simulated truth), invert_posterior.nc (+ _mode<j>.nc: ArviZ
InferenceData, netCDF, physical units), invert_fit.npz (data and fitted counts),
invert_fit.png, invert_corner.png."""

REPORT_HELP = """\
Evaluate the classifier on held-out simulated observations (random attitudes off the grid,
random shape/material/finish, Poisson noise at each SNR, speckle, jitter, range offset and
gain): accuracy and attitude error (degrees) per weight design against SNR and database
angular resolution, confusion matrices, time per classification.

Config fields (configs/cli/report.toml): database (spec TOML, configs/databases/), optional
database_path (a built .zarr to use as the bank), snrs, grid_sizes (Hopf nside), n_obs,
weight_kinds, speckle_cells, jitter_bins and max_offset_bins (bins), gain_range, seed,
top_k. Outputs: report.json, report.md, accuracy_vs_snr.png, attitude_vs_snr.png,
attitude_vs_resolution.png, confusion_{shape,material,finish}.png."""

DEMO_HELP = """\
Write every demo figure into --out: the BRDF figures, the double-bounce (enhancement peak)
figures, the pulse figures and a Mueller image of the example satellite. The figures are
staged and replace their previous versions together at the end (the demo always overwrites
its own figures; other files in --out are kept). Steps whose library part is not present in
this build are listed as skipped."""


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line (``ppr simulate: error: ...``), exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="ppr",
        description="Pulse Polarization Ranging: polarized microfacet BRDF, pulse synthesis and "
        "inversion. Every command reads a TOML config (see configs/), accepts --set overrides "
        "and writes its results into --out.",
        formatter_class=_Formatter,
        epilog="Exit status: 0 success; 2 bad config/override/input or existing output; "
        "130 interrupted (Ctrl-C), 143 terminated. A failed or interrupted run leaves the "
        "previous outputs in --out as they were.",
    )
    parser.add_argument(
        "--debug", action="store_true", help="show tracebacks instead of one-line errors"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "demo", help="write all demo figures", description=DEMO_HELP, formatter_class=_Formatter
    )
    p.add_argument("--out", "-o", metavar="DIR", default="out/demo", help="output folder")
    p.add_argument("--pixels", type=int, default=160, help="Mueller image size (pixels per side)")
    p.add_argument(
        "--only",
        metavar="STEPS",
        default=None,
        help=f"comma-separated subset of the steps {', '.join(DEMO_KEYS)} (default: all)",
    )
    p.add_argument(
        "--set",
        "-s",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a field of the Mueller image's config (configs/cli/image.toml)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or messages")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "brdf",
        help="Mueller BRDF sweep of one material",
        description=BRDF_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "cli/brdf.toml", "out/brdf")
    p.set_defaults(func=cmd_brdf)

    p = sub.add_parser(
        "image",
        help="per-pixel Mueller images of a mesh",
        description=IMAGE_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "cli/image.toml", "out/image")
    p.set_defaults(func=cmd_image)

    p = sub.add_parser(
        "simulate",
        help="range-resolved Mueller/Stokes return of a scene",
        description=SIMULATE_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "scenes/cubesat3u_panels.toml", "out/simulate")
    p.add_argument(
        "--states",
        metavar="NAMES",
        default=None,
        help="transmitted states, comma-separated from H,V,D,A,R,L (Stokes profiles "
        "(S, 4, bins); R/L: right/left circular, clockwise/counterclockwise seen looking "
        "toward the laser, S3 = -1/+1); default: the full Mueller profile (4, 4, bins)",
    )
    p.add_argument(
        "--terms",
        default="auto",
        help="BRDF terms: auto, all, or a comma list of single,double,multiple",
    )
    p.add_argument(
        "--dtype", choices=["float32", "float64"], default="float32", help="kernel float precision"
    )
    p.add_argument(
        "--multibounce",
        choices=["auto", "on", "off"],
        default="auto",
        help="macro double bounce between the object's surfaces (panel against body): auto "
        "includes it where surfaces face each other",
    )
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "database", help="signature databases (database build)", formatter_class=_Formatter
    )
    dsub = p.add_subparsers(dest="database_command", metavar="SUBCOMMAND")
    pb = dsub.add_parser(
        "build",
        help="build or resume a signature database",
        description=DATABASE_HELP,
        formatter_class=_Formatter,
    )
    _common(pb, "databases/synthetic_small.toml", "out/database")
    pb.add_argument(
        "--shard-index",
        type=int,
        default=0,
        help="build only chunks i with i %% num_shards == shard_index (several "
        "processes or hosts sharing one --out)",
    )
    pb.add_argument("--num-shards", type=int, default=1, help="number of cooperating builders")
    pb.set_defaults(func=cmd_database_build)
    p.set_defaults(func=None, _sub=p)

    p = sub.add_parser(
        "classify",
        help="top-k database candidates for observations",
        description=CLASSIFY_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "cli/classify.toml", "out/classify")
    p.set_defaults(func=cmd_classify)

    p = sub.add_parser(
        "invert",
        help="least-squares + MCMC inversion of one observation",
        description=INVERT_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "cli/invert.toml", "out/invert")
    p.set_defaults(func=cmd_invert)

    p = sub.add_parser(
        "report",
        help="classifier evaluation report",
        description=REPORT_HELP,
        formatter_class=_Formatter,
    )
    _common(p, "cli/report.toml", "out/report")
    p.set_defaults(func=cmd_report)

    for extra in _EXTRA_COMMANDS:
        extra(sub)
    return parser


_EXTRA_COMMANDS: list[Callable[[Any], None]] = []


def enable_compile_cache() -> None:
    """Persistent XLA compilation cache for repeated ``ppr`` runs (the CLI is a program, so it
    may set JAX config; the library never does). ``PPR_JAX_CACHE=0`` turns it off,
    ``PPR_JAX_CACHE_DIR`` moves it (default ``~/.cache/ppr/jax``).

    JAX does not persist executables that contain host callbacks ("Not writing persistent
    cache entry ... because it uses host callbacks" in its debug log), and
    :func:`ppr.mueller_brdf`'s checks of *traced* inputs are one (``equinox``). The
    inversion's forward model (:class:`inversion.SimulatorModel`) therefore renders with
    :func:`ppr._brdf.mueller_brdf_unchecked` (its inputs are valid by construction), so the
    solver and sampler programs are cached: ``ppr invert -c configs/cli/invert.toml`` took
    192 s cold and 75 s warm (180 and 198 s before, nothing cached; 2-core VM). ``ppr
    simulate``, ``ppr image`` and database builds check concrete inputs on the host and
    compile the unchecked BRDF, so their programs are cached too (README.md)."""
    if os.environ.get("PPR_JAX_CACHE", "1") == "0":
        return
    import jax

    if jax.config.jax_compilation_cache_dir:
        return
    default = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "ppr" / "jax"
    jax.config.update(
        "jax_compilation_cache_dir", os.environ.get("PPR_JAX_CACHE_DIR", str(default))
    )
    # every program, not only those that took >= 1 s to compile (JAX's default): a command
    # also compiles dozens of small programs (eager ops on concrete arrays, unpadding,
    # parameter maps), 0.1-0.5 s each, which a warm run would otherwise compile again
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def _one_line(err: BaseException) -> str:
    msg = str(err).strip() or type(err).__name__
    return " ".join(part.strip() for part in msg.splitlines() if part.strip())


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that outputs are rolled back as on Ctrl-C."""


@contextlib.contextmanager
def _sigterm_raises():
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _command_name(args) -> str:
    sub = getattr(args, "database_command", None)
    return f"{args.command} {sub}" if sub else str(args.command)


USER_ERRORS = (ConfigError, CLIError, ValueError, pydantic.ValidationError)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``ppr`` command. Returns 0 on success; raises ``SystemExit(2)`` with
    a one-line message on stderr for config/usage errors, ``SystemExit(130)`` on Ctrl-C
    (``143`` on SIGTERM) after rolling back the outputs being written."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        (getattr(args, "_sub", None) or parser).print_help(sys.stderr)
        raise SystemExit(2)
    enable_compile_cache()
    name = _command_name(args)
    try:
        with _sigterm_raises():
            return int(args.func(args) or 0)
    except KeyboardInterrupt as err:
        if args.debug:
            raise
        what = "terminated" if isinstance(err, Terminated) else "interrupted"
        note = getattr(args, "_interrupt_note", None) or "previous outputs were left as they were"
        print(f"ppr {name}: {what}; {note}", file=sys.stderr)
        raise SystemExit(143 if isinstance(err, Terminated) else 130) from None
    except USER_ERRORS as err:
        if args.debug:
            raise
        print(f"ppr {name}: error: {_one_line(err)}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
