"""``ppr image``: per-pixel Mueller images of a mesh at a pose."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pydantic

from . import _common as c
from ._help import describe, fields_text

NAME = "image"
DEFAULT_CONFIG = "cli/image.toml"
OUTPUTS = ["image.npz", "image.nc", "image.png", "image_mueller.png", "image.json"]
SET_EXAMPLE = "render.n_pixels=256"
EXAMPLES = [
    "ppr image --out out/image",
    "ppr image --set render.n_pixels=256 --set view.bistatic_angle_urad=50 --out out/image",
    'ppr image --set render.shading="smooth" --set materials.bus="gold" --out out/image_gold',
]


class ViewConfig(c.StrictModel):
    """Sensor geometry of an image (same fields and meaning as configs/sensors/*.toml)."""

    wavelength_nm: float = pydantic.Field(532.0, gt=0.0, lt=1e6, description="laser wavelength")
    line_of_sight: c.Vec3 = pydantic.Field(
        (-0.8, -0.3, -0.52), description="laser propagation direction (sensor -> object, world)"
    )
    polarization_reference: c.Vec3 = pydantic.Field(
        (-0.5, 0.866, 0.0), description="sensor x axis (world), projected per beam"
    )
    bistatic_angle_urad: float = pydantic.Field(
        0.0,
        ge=0.0,
        lt=1.5e6,
        description="0: monostatic (every visible point lit); > 0: shadow rays toward the laser",
    )
    bistatic_azimuth_deg: float = pydantic.Field(0.0, description="azimuth of the receiver offset")

    @pydantic.model_validator(mode="after")
    def _geometry(self):
        from ..pulse import _scene

        _scene.check_sensor_fields(
            self.line_of_sight,
            self.polarization_reference,
            None,
            self.bistatic_angle_urad,
            self.bistatic_azimuth_deg,
        )
        return self


class RenderConfig(c.StrictModel):
    n_pixels: int = pydantic.Field(128, ge=4, le=2048, description="the image is n x n pixels")
    half_width_m: float | None = pydantic.Field(
        None, gt=0.0, description="half field of view (default: fits the mesh)"
    )
    shading: Literal["flat", "smooth"] = pydantic.Field(
        "flat", description='face normals, or "smooth": interpolated vertex normals'
    )
    terms: c.Terms = pydantic.Field("auto", description=c.TERMS_HELP)
    dtype: Literal["float32", "float64"] = pydantic.Field("float32", description="precision")


class ImageConfig(c.StrictModel):
    """``ppr image``: per-pixel Mueller images of a mesh at a pose."""

    scene: str | None = pydantic.Field(
        None,
        description="a scene config (configs/scenes/*.toml): mesh, materials, pose and sensor "
        "all come from it",
    )
    mesh: str | dict[str, Any] | None = pydantic.Field(
        None,
        description='"example" (the shipped example satellite) or a mesh file trimesh reads '
        "(metres; one part per object), or a table {path, scale, on_degenerate, part_names} "
        "as in scene configs",
        json_schema_extra={"schema": "ppr.pulse._scene:MeshFileConfig"},
    )
    shape: dict[str, Any] | None = pydantic.Field(
        None,
        description='a parametric shape (ppr.shapes), e.g. {name = "sphere", params = {radius '
        "= 0.5}}",
        json_schema_extra={"schema": "ppr.pulse._scene:ShapeConfig"},
    )
    materials: dict[str, Any] = pydantic.Field(
        {},
        description='mesh part -> library material ("name" or "name/finish", '
        "configs/materials.toml) or inline {n_real, n_imag, m, corr_length_m}; "
        '"default" covers unlisted parts',
    )
    pose: dict[str, Any] | None = pydantic.Field(
        None,
        description="body -> world attitude (quaternion [w, x, y, z]) and position",
        json_schema_extra={"schema": "ppr.pulse._scene:PoseConfig"},
    )
    view: ViewConfig | None = pydantic.Field(None, description="sensor geometry")
    render: RenderConfig = pydantic.Field(RenderConfig(), description="image settings")

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


def help_text() -> str:
    return describe(
        "Render per-pixel Mueller images of a mesh at a pose (orthographic view from the "
        "receiver, one embree ray per pixel, macro shadowing) as PNG panels with colour bars: "
        "total reflectance M00 cos(theta_in) [1/sr], depolarization index, polarizance, "
        "diattenuation and retardance [rad] (Lu-Chipman), plus the 16 normalized Mueller "
        "elements. Geometry: exactly one of scene, mesh, [shape].",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", ImageConfig),
        outputs="image.npz (mueller (H, W, 4, 4) in 1/sr, NaN off the object; cos_in, normal, "
        "part, lit, quantities; u, v in metres), image.nc (the same as a labelled xarray dataset "
        "with units), image.png, image_mueller.png, image.json.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    c.add_command(sub, sys.modules[__name__], "per-pixel Mueller images of a mesh", "out/image")


def load(args):
    return c.load_config(args, ImageConfig, DEFAULT_CONFIG)


def part_mesh_from_ppr_mesh(mesh, smooth: bool = False):
    """Deprecated: the image renderer takes a :class:`ppr.Mesh` itself
    (:func:`ppr.image.render_mueller_image`, ``shading="smooth"`` for vertex normals).
    Returns ``mesh`` unchanged."""
    from .._deprecation import warn_deprecated

    del smooth
    warn_deprecated("ppr.cli.part_mesh_from_ppr_mesh", "the ppr.Mesh itself")
    return mesh


def image_inputs(cfg: ImageConfig, cfg_path: Path):
    """Resolve an image config to ``(mesh, materials, sensor, quaternion)``."""
    from ..geometry import shapes
    from ..geometry._mesh import load_mesh
    from ..geometry._rotation import check_quaternion
    from ..image import _image
    from ..pulse import _scene

    if cfg.scene is not None:
        spath = c.resolve_path(cfg.scene, cfg_path)
        if not spath.is_file():
            raise c.ConfigError(f"{cfg_path}: scene = {cfg.scene!r}: no such scene file ({spath})")
        scene = _scene.load_scene(spath)
        return scene.mesh, list(scene.materials), scene.sensor, np.asarray(scene.pose.quaternion)
    if cfg.shape is not None:
        shape = c.sub_model(_scene.ShapeConfig, cfg.shape, cfg_path, "shape")
        try:
            mesh = shapes.by_name(shape.name, **shape.params)
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: shape = {cfg.shape!r}: {err}") from None
    else:
        spec = cfg.mesh if isinstance(cfg.mesh, dict) else {"path": cfg.mesh}
        mcfg = c.sub_model(_scene.MeshFileConfig, spec, cfg_path, "mesh")
        path = (
            _image.EXAMPLE_SATELLITE
            if mcfg.path == "example"
            else c.resolve_path(mcfg.path, cfg_path)
        )
        try:
            mesh = load_mesh(
                path,
                scale=mcfg.scale,
                on_degenerate=mcfg.on_degenerate,
                part_names=mcfg.part_names,
            )
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: mesh = {cfg.mesh!r}: {err}") from None
    view = cfg.view or ViewConfig()
    try:
        sensor = _scene.Sensor.make(
            view.line_of_sight,
            view.polarization_reference,
            bistatic_angle=view.bistatic_angle_urad * 1e-6,
            bistatic_azimuth=np.deg2rad(view.bistatic_azimuth_deg),
            wavelength=view.wavelength_nm * 1e-9,
        )
    except ValueError as err:
        raise c.ConfigError(f"{cfg_path}: view: {err}") from None
    pose = c.sub_model(_scene.PoseConfig, cfg.pose or {}, cfg_path, "pose")
    try:
        quat = check_quaternion(pose.quaternion, "pose.quaternion")
    except ValueError as err:
        raise c.ConfigError(f"{cfg_path}: {err}") from None
    wl = view.wavelength_nm * 1e-9
    mats = []
    for part in mesh.parts:
        key = part if part in cfg.materials else "default"
        if key not in cfg.materials:
            raise c.ConfigError(
                f"{cfg_path}: materials: no material for mesh part {part!r} (parts: "
                f"{', '.join(mesh.parts)}; add materials.{part} or materials.default)"
            )
        mats.append(c.resolve_material(cfg.materials[key], wl, f"materials.{key}", cfg_path))
    unknown = sorted(set(cfg.materials) - set(mesh.parts) - {"default"})
    if unknown:
        raise c.ConfigError(
            f"{cfg_path}: materials.{unknown[0]}: the mesh has no part {unknown[0]!r} (parts: "
            f"{', '.join(mesh.parts)})"
        )
    return mesh, mats, sensor, quat


def run_image(cfg: ImageConfig, cfg_path: Path, progress: bool = False, inputs=None):
    """Render the image a config describes (used by ``ppr image`` and ``ppr demo``);
    ``inputs``: :func:`image_inputs` of the config if already resolved."""
    from ..image import _image

    c.maybe_x64(cfg.render.dtype)
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
            terms=c.terms_arg(cfg.render.terms),
            shading=cfg.render.shading,
            dtype=c.dtype(cfg.render.dtype),
            progress=progress,
        )
    except ValueError as err:
        raise c.ConfigError(f"{cfg_path}: {err}") from None


def write_image_outputs(img, cfg, cfg_path, out: c.Outputs, prefix: str = "image", seconds=None):
    """``image.npz``, ``image.nc``, the two PNGs and ``image.json`` (per-part means of the
    quantities)."""
    from ..image import _image

    np.savez_compressed(out.path(f"{prefix}.npz"), **img.arrays())
    img.to_xarray(provenance=c.provenance(cfg)).to_netcdf(
        out.path(f"{prefix}.nc"), engine="h5netcdf"
    )
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
    c.write_json(
        out.path(f"{prefix}.json"),
        {
            "command": "image",
            "config_file": str(cfg_path),
            "n_pixels": [len(img.v), len(img.u)],
            "pixel_size_m": float(img.u[1] - img.u[0]) if len(img.u) > 1 else None,
            "hit_pixels": int((img.part >= 0).sum()),
            "lit_pixels": int(img.lit.sum()),
            "radar_cross_section_like_m2_per_sr": float(np.nansum(refl) * pixel_area),
            "parts": per_part,
            "seconds": seconds,
            "units": {"reflectance": "1/sr (M00 cos theta_in)", "retardance": "rad", "u, v": "m"},
        },
        config=cfg,
    )


def run(args) -> int:
    cfg_path, cfg = load(args)
    c.maybe_x64(cfg.render.dtype)
    inputs = image_inputs(cfg, cfg_path)
    with c.outputs(args.out, OUTPUTS, args.overwrite) as out:
        t0 = time.perf_counter()
        img = run_image(cfg, cfg_path, progress=c.progress(args), inputs=inputs)
        write_image_outputs(img, cfg, cfg_path, out, seconds=time.perf_counter() - t0)
    c.wrote(args, NAME, OUTPUTS)
    if not (img.part >= 0).any():
        c.say(
            args,
            f"ppr image: warning: no pixel sees the mesh (hit_pixels = 0) in {cfg_path}: check "
            "view.line_of_sight, the pose and render.half_width_m",
        )
    return 0
