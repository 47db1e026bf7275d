"""``ppr brdf``: the Mueller BRDF of one material over incidence x bistatic angle."""

from __future__ import annotations

import sys
import time
from typing import Annotated, Any, Literal

import numpy as np
import pydantic

from . import _common as c
from ._help import describe, fields_text

NAME = "brdf"
DEFAULT_CONFIG = "cli/brdf.toml"
OUTPUTS = ["brdf.npz", "brdf.json", "brdf.png"]
SET_EXAMPLE = "wavelength_nm=1064"
EXAMPLES = [
    "ppr brdf --out out/brdf",
    'ppr brdf --set material="gold/polished" --set wavelength_nm=1064 --out out/brdf_gold',
    "ppr brdf --set 'incidence_deg=[10.0, 50.0]' --set plane=\"cross\" --out out/brdf_cross",
]


class BrdfConfig(c.StrictModel):
    """``ppr brdf``: a Mueller BRDF sweep over incidence and bistatic angle."""

    material: str | dict[str, Any] = pydantic.Field(
        description='library name ("aluminium", or "aluminium/rough" with a finish; see '
        "configs/materials.toml) or inline {n_real, n_imag, m = <Blinn-Phong exponent, "
        "0..1e6>, corr_length_m = <metres>}"
    )
    wavelength_nm: float = pydantic.Field(532.0, gt=0.0, lt=1e6, description="laser wavelength")
    terms: c.Terms = pydantic.Field("auto", description=c.TERMS_HELP)
    incidence_deg: Annotated[
        list[Annotated[float, pydantic.Field(ge=0.0, lt=90.0)]], pydantic.Field(min_length=1)
    ] = pydantic.Field([0.0, 30.0, 60.0], description="incidence angles from the normal, [0, 90)")
    bistatic_deg: (
        c.Range
        | Annotated[
            list[Annotated[float, pydantic.Field(ge=0.0, le=179.0)]], pydantic.Field(min_length=1)
        ]
    ) = pydantic.Field(
        c.Range(start=0.0, stop=10.0, num=41),
        description="angles between k_in and k_out, [0, 179]: a list or {start, stop, num}",
    )
    plane: Literal["in", "cross"] = pydantic.Field(
        "in",
        description='"in": k_out in the plane of incidence, toward the normal; "cross": '
        "rotated out of it",
    )
    dtype: Literal["float32", "float64"] = pydantic.Field("float32", description="precision")

    @pydantic.field_validator("bistatic_deg")
    @classmethod
    def _bistatic_ok(cls, v):
        vals = v.values() if isinstance(v, c.Range) else np.asarray(v)
        if vals.size == 0 or np.any(vals < 0) or np.any(vals > 179.0):
            raise ValueError("bistatic angles must lie in [0, 179] degrees")
        return v


def help_text() -> str:
    return describe(
        "Evaluate the Mueller BRDF of one material over a grid of incidence and bistatic "
        "angles. Stokes frames: the lab y axis (perpendicular to the plane of incidence) "
        "projected perpendicular to each beam.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", BrdfConfig),
        outputs="brdf.npz (mueller [1/sr] of shape (incidence, bistatic, 4, 4), "
        "polarimetric quantities), brdf.json, brdf.png.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    c.add_command(sub, sys.modules[__name__], "Mueller BRDF sweep of one material", "out/brdf")


def load(args):
    return c.load_config(args, BrdfConfig, DEFAULT_CONFIG)


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

    # above the horizon (k.n = 1e-12 is 1e-10 deg: any k_out a sweep meant to be above it),
    # and with a defined Stokes frame (k_out not along the frames' y axis)
    perp = y - k_out[..., 1:2] * k_out
    size = np.linalg.norm(perp, axis=-1, keepdims=True)
    valid = (k_out[..., 2] > 1e-12) & (size[..., 0] > 1e-9)
    f_out = np.where(valid[..., None], perp / np.where(valid[..., None], size, 1.0), np.nan)
    return k_in, k_out, frame(k_in), f_out, valid


def polarimetry(mueller: np.ndarray) -> dict[str, np.ndarray]:
    """Depolarization index, polarizance, diattenuation, retardance of normalized matrices."""
    from ..image._image import polarimetric_maps

    out = polarimetric_maps(mueller, np.ones(mueller.shape[:-2]))
    out.pop("reflectance")
    return out


def material_summary(mat) -> dict:
    n = complex(np.asarray(mat.n).reshape(-1)[0])
    out = {
        "name": getattr(mat, "name", ""),
        "n": [n.real, n.imag],
        "m": float(np.asarray(mat.m).reshape(-1)[0]),
        "corr_length_m": float(np.asarray(mat.corr_length).reshape(-1)[0]),
    }
    if getattr(mat, "films", ()):
        first = lambda a: np.asarray(a).reshape(-1)[0]  # noqa: E731
        out["films"] = [
            {
                "n": [complex(first(fn)).real, complex(first(fn)).imag],
                "thickness_m": float(first(ft)),
            }
            for fn, ft in mat.films
        ]
        out["film_mode"] = mat.film_mode
    return out


def run(args) -> int:
    cfg_path, cfg = load(args)
    c.maybe_x64(cfg.dtype)
    mat = c.resolve_material(cfg.material, cfg.wavelength_nm * 1e-9, "material", cfg_path)
    with c.outputs(args.out, OUTPUTS, args.overwrite) as out:
        from ..image import _image
        from ..plots import plot_brdf_sweep

        bis = (
            cfg.bistatic_deg.values()
            if isinstance(cfg.bistatic_deg, c.Range)
            else np.asarray(cfg.bistatic_deg, float)
        )
        inc = np.asarray(cfg.incidence_deg, float)
        k_in, k_out, f_in, f_out, valid = brdf_geometry(inc, bis, cfg.plane)
        # below the horizon: evaluated at k_in with its frame (a valid placeholder; NaN in
        # the outputs, valid = false), so a k_out along the frames' y axis raises nothing
        safe_out = np.where(valid[..., None], k_out, k_in)
        f_out = np.where(valid[..., None], f_out, f_in)
        if not valid.all() and not getattr(args, "quiet", False):
            bad = np.argwhere(~valid)[0]
            print(
                f"ppr {NAME}: {int((~valid).sum())} of {valid.size} geometries have k_out at or "
                f"below the horizon or along the Stokes frames' y axis (first: incidence "
                f"{float(inc[bad[0]]):.10g} deg, bistatic {float(bis[bad[1]]):.10g} deg, "
                f"{cfg.plane}-plane): NaN in "
                "brdf.npz (valid = false)",
                file=sys.stderr,
            )
        t0 = time.perf_counter()
        flat = [x.reshape(-1, 3) for x in (k_in, safe_out)]
        n_rows = len(flat[0])
        mueller = _image.evaluate_mueller(
            flat[0],
            flat[1],
            np.broadcast_to([0.0, 0.0, 1.0], (n_rows, 3)),
            f_in.reshape(-1, 3),
            f_out.reshape(-1, 3),
            [mat],
            np.zeros(n_rows, np.int32),
            terms=c.terms_arg(cfg.terms),
            wavelength=cfg.wavelength_nm * 1e-9,
            dtype=c.dtype(cfg.dtype),
            progress=c.progress(args),
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
            "material": material_summary(mat),
            "n_geometries": int(valid.sum()),
            "seconds": elapsed,
            "units": {"mueller": "1/sr", "angles": "deg", "retardance": "rad"},
            # the first bistatic angle's column, keyed by incidence (deg, as written)
            "backscatter" if float(bis[0]) == 0.0 else f"bistatic_{float(bis[0]):.10g}_deg": {
                f"{a:.10g}": {
                    "M00": mueller[i, 0, 0, 0],
                    **{k: v[i, 0] for k, v in quants.items()},
                }
                for i, a in enumerate(inc)
            },
            "outputs": OUTPUTS,
        }
        c.write_json(out.path("brdf.json"), summary, config=cfg)
        n = complex(np.asarray(mat.n).reshape(-1)[0])
        title = (
            f"{getattr(mat, 'name', '') or 'material'}: n = {n.real:.3g}+{n.imag:.3g}i, "
            f"m = {float(np.asarray(mat.m).reshape(-1)[0]):.3g}, {cfg.wavelength_nm:.0f} nm, "
            f"terms {cfg.terms}, {cfg.plane}-plane"
        )
        plot_brdf_sweep(out.path("brdf.png"), inc, bis, mueller, quants, title)
    c.wrote(args, NAME, OUTPUTS)
    return 0
