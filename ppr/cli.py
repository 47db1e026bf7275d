"""``ppr``: the command line of Pulse Polarization Ranging.

A thin layer over the library: every subcommand reads a TOML config (typed schema, unknown
keys are errors), applies ``--set key.sub=value`` overrides, runs the library function and
writes its outputs (arrays ``.npz``/``.zarr``, a JSON summary, PNG plots) into ``--out``.

Exit status: 0 on success; 2 for a bad config, a bad override, an input the library rejects
or an output that exists (``--overwrite`` replaces it). Errors are one line on stderr naming
the file, the field and the bad value (``--debug`` shows the traceback instead).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import pydantic

from ._config import ConfigError, StrictModel, load_toml_model, parse_override

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = REPO_ROOT / "configs"


class CLIError(Exception):
    """A usage error (existing output, missing input) reported as one line, exit status 2."""


# ============================================================================ output folder
class Outputs:
    """Files one command writes into ``out``: refuses to replace existing ones unless
    ``overwrite``; files are written into a private temporary folder inside ``out`` and moved
    into place only when the command succeeds (no partial results)."""

    def __init__(self, out: str | Path, names: Sequence[str], overwrite: bool):
        self.out = Path(out)
        self.names = list(names)
        existing = [n for n in self.names if (self.out / n).exists()]
        if existing and not overwrite:
            raise CLIError(
                f"{self.out / existing[0]} already exists (and {len(existing) - 1} more outputs); "
                "pass --overwrite to replace, or choose another --out"
            )
        self.out.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=".ppr-tmp-", dir=self.out))
        self.written: list[Path] = []

    def path(self, name: str) -> Path:
        if name not in self.names:  # pragma: no cover - programming error
            raise KeyError(f"output {name!r} not declared")
        return self._tmp / name

    def commit(self) -> list[Path]:
        for name in self.names:
            src = self._tmp / name
            if not src.exists():
                continue
            dst = self.out / name
            if dst.is_dir():
                shutil.rmtree(dst)
            elif dst.exists():
                dst.unlink()
            os.replace(src, dst)
            self.written.append(dst)
        shutil.rmtree(self._tmp, ignore_errors=True)
        return self.written

    def discard(self) -> None:
        shutil.rmtree(self._tmp, ignore_errors=True)


@contextlib.contextmanager
def outputs(out, names, overwrite):
    o = Outputs(out, names, overwrite)
    try:
        yield o
    except BaseException:
        o.discard()
        raise
    o.commit()


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
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


class InlineMaterial(StrictModel):
    """A material given by its optical constants."""

    n: tuple[float, float] = pydantic.Field(description="complex index [n', n''], n'' >= 0")
    m: float = pydantic.Field(ge=0.0, le=1e6, description="Blinn-Phong exponent")
    corr_length: float = pydantic.Field(5e-6, gt=0.0, description="correlation length (m)")
    name: str = ""

    @pydantic.field_validator("n")
    @classmethod
    def _n_ok(cls, v):
        if v[0] <= 0 or v[1] < 0:
            raise ValueError("need n' > 0 and n'' >= 0")
        return v


class LibraryMaterial(StrictModel):
    """A material of the library (configs/materials.toml) with an optional finish."""

    name: str
    finish: str | None = None


MaterialSpec = str | LibraryMaterial | InlineMaterial


def resolve_material(spec: MaterialSpec, wavelength: float, field: str, source: str):
    """Turn a config material spec into a :class:`ppr.Material` (ConfigError on a bad name)."""
    import ppr

    if isinstance(spec, InlineMaterial):
        try:
            return ppr.Material(
                n=complex(*spec.n), m=spec.m, corr_length=spec.corr_length, name=spec.name
            )
        except ValueError as err:
            raise ConfigError(f"{source}: {field} = {spec.model_dump()!r}: {err}") from None
    name, finish = (spec, None) if isinstance(spec, str) else (spec.name, spec.finish)
    load = getattr(ppr, "load_material", None)
    if load is None:
        raise ConfigError(
            f"{source}: {field} = {name!r}: the material library is not available in this "
            "build; give the material inline as {{n = [n', n''], m = ...}}"
        )
    names = getattr(ppr, "material_names", None)
    if names is not None and name not in names():
        raise ConfigError(
            f"{source}: {field} = {name!r}: unknown material; known: {', '.join(names())}"
        )
    try:
        if finish is None:
            return load(name, wavelength)
        return load(name, wavelength, finish)
    except (ValueError, KeyError) as err:
        msg = str(err).strip("'\"")
        raise ConfigError(f"{source}: {field} = {name!r} (finish {finish!r}): {msg}") from None


Terms = Literal["auto", "all"] | list[Literal["single", "double", "multiple"]]


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

    material: MaterialSpec
    wavelength: float = pydantic.Field(532e-9, gt=0.0, lt=1e-3)
    terms: Terms = "auto"
    incidence_deg: list[Annotated[float, pydantic.Field(ge=0.0, lt=90.0)]] = [0.0, 30.0, 60.0]
    bistatic_deg: Range | list[Annotated[float, pydantic.Field(ge=0.0, le=179.0)]] = Range(
        start=0.0, stop=10.0, num=41
    )
    plane: Literal["in", "cross"] = "in"
    dtype: Literal["float32", "float64"] = "float32"

    @pydantic.field_validator("bistatic_deg")
    @classmethod
    def _bistatic_ok(cls, v):
        vals = v.values() if isinstance(v, Range) else np.asarray(v)
        if vals.size == 0 or np.any(vals < 0) or np.any(vals > 179.0):
            raise ValueError("bistatic angles must lie in [0, 179] degrees")
        return v


class PoseConfig(StrictModel):
    attitude: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    to_sensor: Vec3 = (1.0, 0.0, 0.0)
    sensor_x: Vec3 | None = None


class ShapeConfig(StrictModel):
    """A parametric shape of ``ppr.shapes`` (name plus its keyword parameters)."""

    model_config = pydantic.ConfigDict(extra="allow", frozen=True, allow_inf_nan=False)
    name: str


class ImageConfig(StrictModel):
    """``ppr image``: per-pixel monostatic Mueller images of a mesh at a pose."""

    mesh: str = "example"
    shape: ShapeConfig | None = None
    materials: dict[str, MaterialSpec]
    wavelength: float = pydantic.Field(532e-9, gt=0.0, lt=1e-3)
    terms: Terms = "auto"
    pose: PoseConfig = PoseConfig()
    n_pixels: int = pydantic.Field(128, ge=4, le=2048)
    half_width: float | None = pydantic.Field(None, gt=0.0)
    bistatic_angle: float = pydantic.Field(0.0, ge=0.0, lt=1.5)
    shading: Literal["flat", "smooth"] = "flat"
    dtype: Literal["float32", "float64"] = "float32"


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
    import jax.numpy as jnp

    import ppr

    m00 = mueller[..., 0, 0]
    ok = np.isfinite(m00) & (m00 > 0)
    out = {}
    flat = mueller[ok]
    flat = flat / flat[:, :1, :1] if flat.size else flat
    for name in ("depolarization_index", "polarizance", "diattenuation", "retardance"):
        fn = getattr(ppr, name, None)
        arr = np.full(m00.shape, np.nan)
        if fn is not None and flat.size:
            arr[ok] = np.asarray(fn(jnp.asarray(flat)))
        out[name] = arr
    return out


def cmd_brdf(args) -> int:
    cfg_path = _config_path(args, "brdf.toml")
    cfg = load_toml_model(BrdfConfig, cfg_path, _overrides(args))
    names = ["brdf.npz", "brdf.json", "brdf.png"]
    with outputs(args.out, names, args.overwrite) as out:
        _maybe_x64(cfg.dtype)
        import jax.numpy as jnp

        import ppr

        mat = resolve_material(cfg.material, cfg.wavelength, "material", str(cfg_path))
        bis = (
            cfg.bistatic_deg.values()
            if isinstance(cfg.bistatic_deg, Range)
            else np.asarray(cfg.bistatic_deg, float)
        )
        inc = np.asarray(cfg.incidence_deg, float)
        k_in, k_out, f_in, f_out, valid = brdf_geometry(inc, bis, cfg.plane)
        dt = _dtype(cfg.dtype)
        safe_out = np.where(valid[..., None], k_out, k_in)
        t0 = time.perf_counter()
        mueller = ppr.mueller_brdf(
            jnp.asarray(k_in, dt),
            jnp.asarray(safe_out, dt),
            jnp.asarray([0.0, 0.0, 1.0], dt),
            mat,
            terms=_terms_arg(cfg.terms),
            frame_in=jnp.asarray(f_in, dt),
            frame_out=jnp.asarray(f_out, dt),
            wavelength=cfg.wavelength,
        )
        mueller = np.where(valid[..., None, None], np.asarray(mueller, float), np.nan)
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
        if label.startswith("M00"):
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    n = complex(np.asarray(mat.n).reshape(-1)[0])
    fig.suptitle(
        f"{getattr(mat, 'name', '') or 'material'}: n = {n.real:.3g}+{n.imag:.3g}i, "
        f"m = {float(np.asarray(mat.m).reshape(-1)[0]):.3g}, {cfg.wavelength * 1e9:.0f} nm, "
        f"terms {cfg.terms}, {cfg.plane}-plane"
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ================================================================================ image
def _image_mesh(cfg: ImageConfig, cfg_path: Path):
    from . import _image

    smooth = cfg.shading == "smooth"
    if cfg.shape is not None:
        extra = dict(cfg.shape.model_extra or {})
        name = cfg.shape.name
        if name == "sphere" and smooth:
            import trimesh

            tm = trimesh.creation.icosphere(
                subdivisions=int(extra.get("subdivisions", 3)),
                radius=float(extra.get("radius", 0.5)),
            )
            return _image.part_mesh_from_trimeshes([(extra.get("part", "body"), tm)], smooth=True)
        try:
            shapes = importlib.import_module("ppr.shapes")
            mesh = shapes.by_name(name, **extra)
        except ModuleNotFoundError:
            raise ConfigError(
                f"{cfg_path}: shape.name = {name!r}: ppr.shapes is not available"
            ) from None
        except ValueError as err:
            raise ConfigError(f"{cfg_path}: shape = {cfg.shape.model_dump()!r}: {err}") from None
        return part_mesh_from_ppr_mesh(mesh, smooth)
    path = _image.EXAMPLE_SATELLITE if cfg.mesh == "example" else _resolve_path(cfg.mesh, cfg_path)
    if not path.is_file():
        raise ConfigError(f"{cfg_path}: mesh = {cfg.mesh!r}: no such mesh file ({path})")
    if smooth:
        import trimesh

        loaded = trimesh.load(path, force="mesh", process=True)
        return _image.part_mesh_from_trimeshes([(path.stem, loaded)], smooth=True)
    try:
        return _image.load_part_mesh(path)
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: mesh = {cfg.mesh!r}: {err}") from None


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


def _image_materials(cfg: ImageConfig, part_names, cfg_path: Path):
    mats = []
    for part in part_names:
        if part in cfg.materials:
            spec, field = cfg.materials[part], f"materials.{part}"
        elif "default" in cfg.materials:
            spec, field = cfg.materials["default"], "materials.default"
        else:
            raise ConfigError(
                f"{cfg_path}: materials: no material for mesh part {part!r} (parts: "
                f"{', '.join(part_names)}; add materials.{part} or materials.default)"
            )
        mats.append(resolve_material(spec, cfg.wavelength, field, str(cfg_path)))
    unknown = set(cfg.materials) - set(part_names) - {"default"}
    if unknown:
        bad = sorted(unknown)[0]
        raise ConfigError(
            f"{cfg_path}: materials.{bad}: the mesh has no part {bad!r} (parts: "
            f"{', '.join(part_names)})"
        )
    return mats


def run_image(cfg: ImageConfig, cfg_path: Path, progress: bool = False):
    """Render the image a config describes (library entry used by the CLI and the demo)."""
    from . import _image

    _maybe_x64(cfg.dtype)
    mesh = _image_mesh(cfg, cfg_path)
    mats = _image_materials(cfg, mesh.part_names, cfg_path)
    try:
        return _image.render_mueller_image(
            mesh,
            mats,
            to_sensor=cfg.pose.to_sensor,
            attitude=cfg.pose.attitude,
            sensor_x=cfg.pose.sensor_x,
            n_pixels=cfg.n_pixels,
            half_width=cfg.half_width,
            bistatic_angle=cfg.bistatic_angle,
            wavelength=cfg.wavelength,
            terms=_terms_arg(cfg.terms),
            shading=cfg.shading,
            dtype=_dtype(cfg.dtype),
            progress=progress,
        )
    except ValueError as err:
        raise ConfigError(f"{cfg_path}: {err}") from None


def write_image_outputs(img, cfg, cfg_path, out: Outputs, prefix: str = "image", seconds=None):
    from . import _image

    np.savez_compressed(out.path(f"{prefix}.npz"), **img.arrays())
    title = f"{cfg.mesh if cfg.shape is None else cfg.shape.name}, {cfg.wavelength * 1e9:.0f} nm"
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
    with outputs(args.out, IMAGE_OUTPUTS, args.overwrite) as out:
        t0 = time.perf_counter()
        img = run_image(cfg, cfg_path, progress=_progress(args))
        write_image_outputs(img, cfg, cfg_path, out, seconds=time.perf_counter() - t0)
    _say(args, f"ppr image: wrote {', '.join(str(Path(args.out) / n) for n in IMAGE_OUTPUTS)}")
    return 0


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


DEMO_STEPS: list[tuple[str, str, tuple[str, ...]]] = [
    ("BRDF figures", "ppr.demo", ("brdf_figures",)),
    ("double-bounce figures", "ppr.demo", ("double_bounce_figures", "enhancement_figures")),
    ("double-bounce figures", "ppr._double", ("double_bounce_figures", "enhancement_figures")),
    ("pulse figures", "ppr.demo", ("pulse_figures",)),
    ("pulse figures", "ppr._pulse", ("pulse_figures",)),
]


def cmd_demo(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    done: dict[str, float] = {}
    skipped: list[str] = []
    t_all = time.perf_counter()
    for label, module, names in DEMO_STEPS:
        if label in done:
            continue
        fn = _find(module, names)
        if fn is None:
            continue
        _say(args, f"ppr demo: {label} ...")
        t0 = time.perf_counter()
        fn(out)
        done[label] = time.perf_counter() - t0
    for label, _, _ in DEMO_STEPS:
        if label not in done and label not in skipped:
            skipped.append(label)
    import ppr

    if getattr(ppr, "mueller_brdf", None) is None or getattr(ppr, "retardance", None) is None:
        skipped.append("Mueller image")
    else:
        _say(args, "ppr demo: Mueller image of the example satellite ...")
        t0 = time.perf_counter()
        cfg_path = CONFIG_DIR / "cli" / "image.toml"
        cfg = load_toml_model(ImageConfig, cfg_path, {"n_pixels": args.pixels})
        img = run_image(cfg, cfg_path, progress=_progress(args))
        with outputs(out, IMAGE_OUTPUTS, overwrite=True) as demo_out:
            write_image_outputs(img, cfg, cfg_path, demo_out, seconds=time.perf_counter() - t0)
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
    _say(args, f"ppr demo: {len(pngs)} figures in {out} ({summary['total_seconds']:.0f} s)")
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
  material       library name (e.g. "aluminium"), {name = ..., finish = ...}, or inline
                 {n = [n', n''], m = <Blinn-Phong exponent, 0..1e6>, corr_length = <m>}
  wavelength     metres (default 532e-9)
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
Render per-pixel Mueller images of a mesh at a pose (orthographic view along the line of
sight, one embree ray per pixel, macro shadowing) as PNG panels with colour bars: total
reflectance M00 cos(theta_in) [1/sr], depolarization index, polarizance, diattenuation and
retardance [rad] (Lu-Chipman), plus the 16 normalized Mueller elements.

Config fields (configs/cli/image.toml):
  mesh           "example" (the shipped example satellite) or a mesh file trimesh reads
                 (metres; one part per geometry); relative to the config's folder
  shape          instead of mesh: {name = "sphere", radius = 0.5, ...} (ppr.shapes)
  materials      part name -> material (library name, {name, finish} or inline
                 {n = [n', n''], m = ...}); "default" for parts not listed
  wavelength     metres
  terms          "auto", "all", or a list of "single", "double", "multiple"
  pose.attitude  body-to-world quaternion [w, x, y, z]
  pose.to_sensor unit vector from the object toward the sensor (world frame)
  pose.sensor_x  the sensor's polarization x axis (world; default world z projected)
  n_pixels       image is n_pixels x n_pixels
  half_width     half field of view in metres (default: fit the mesh)
  bistatic_angle radians between laser and receiver (0: monostatic; > 0: shadow rays)
  shading        "flat" (face normals) or "smooth" (interpolated vertex normals)
  dtype          "float32" or "float64"
Outputs: image.npz (mueller (H, W, 4, 4) in 1/sr, NaN off the object; quantities), image.png,
image_mueller.png, image.json."""

DEMO_HELP = """\
Write every demo figure into --out: the BRDF figures, the double-bounce (enhancement peak)
figures, the pulse figures and a Mueller image of the example satellite. Figures that exist
are regenerated in place (the demo always overwrites its own figures). Steps whose library
part is not present in this build are listed as skipped."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ppr",
        description="Pulse Polarization Ranging: polarized microfacet BRDF, pulse synthesis and "
        "inversion. Every command reads a TOML config (see configs/), accepts --set overrides "
        "and writes its results into --out.",
        formatter_class=_Formatter,
        epilog="Exit status: 0 success; 2 bad config/override/input or existing output.",
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

    for extra in _EXTRA_COMMANDS:
        extra(sub)
    return parser


_EXTRA_COMMANDS: list[Callable[[Any], None]] = []


def _one_line(err: BaseException) -> str:
    msg = str(err).strip() or type(err).__name__
    return " ".join(part.strip() for part in msg.splitlines() if part.strip())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``ppr`` command. Returns 0 on success; raises ``SystemExit(2)`` with
    a one-line message on stderr for config/usage errors."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        raise SystemExit(2)
    try:
        return int(args.func(args) or 0)
    except (ConfigError, CLIError, ValueError, pydantic.ValidationError) as err:
        if args.debug:
            raise
        print(f"ppr {args.command}: error: {_one_line(err)}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
