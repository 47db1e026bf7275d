"""``ppr simulate``: the range-resolved Mueller/Stokes return of a scene."""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from . import _common as c
from ._help import describe, fields_text

NAME = "simulate"
DEFAULT_CONFIG = "scenes/cubesat3u_panels.toml"
OUTPUTS = ["simulate.npz", "simulate.nc", "simulate.json", "simulate.png"]
SET_EXAMPLE = "pose.quaternion=[1,0,0,0]"
EXAMPLES = [
    "ppr simulate --out out/sim",
    "ppr simulate --states H,V,R --set pose.quaternion=[1,0,0,0] --out out/sim_stokes",
    'ppr simulate --set sensor="leo_aberration_1064" --multibounce off --out out/sim_1064',
]


def help_text() -> str:
    from ..pulse import _scene

    return describe(
        "Simulate the range-resolved return of a scene: the Gaussian pulse stretched by the "
        "posed mesh's range-depth profile, every lit and visible facet contributing its "
        "Mueller BRDF times its projected area (closed-form triangle range-area density "
        "convolved with the pulse), plus the macro double bounce between the object's "
        "surfaces (--multibounce). The config is a scene file; --set overrides apply to it.",
        fields_text(f"Scene fields (configs/{DEFAULT_CONFIG})", _scene.SceneConfig),
        fields_text(
            "Sensor fields (configs/sensors/*.toml, named by the scene's sensor)",
            _scene.SensorConfig,
        ),
        outputs="simulate.npz (data in m^2/sr per bin, range_m one-way, time_s round trip, "
        "edges_m, visibility per face), simulate.nc (the same as a labelled xarray dataset with "
        "units: xarray.open_dataset), simulate.json (energies, mean range, rms depth), "
        "simulate.png.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    p = c.add_command(
        sub,
        sys.modules[__name__],
        "range-resolved Mueller/Stokes return of a scene",
        "out/simulate",
    )
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


def load(args):
    """The scene (``--config`` or the shipped default) with its overrides."""
    from ..pulse import _scene

    path = c.config_path(args, DEFAULT_CONFIG)
    return path, _scene.load_scene(path, c.overrides(args))


def flags(args) -> tuple[list[str] | None, Any]:
    """``--states`` and ``--terms`` checked before anything runs."""
    from ..brdf._brdf import _resolve_terms
    from ..pulse._pulse import STOKES_STATES

    states = None
    if args.states is not None:
        states = [s.strip() for s in args.states.split(",")]
        bad = [s for s in states if s not in STOKES_STATES]
        if bad:
            raise c.CLIError(
                f"--states {args.states!r}: unknown state {bad[0]!r} (known: "
                f"{', '.join(STOKES_STATES)}; comma-separated, e.g. H,V)"
            )
        dup = sorted({s for s in states if states.count(s) > 1})
        if dup:
            raise c.CLIError(
                f"--states {args.states!r}: {dup[0]!r} is listed twice (each transmitted state "
                "is one channel)"
            )
    terms = None if args.terms == "all" else args.terms
    if terms not in (None, "auto"):
        terms = tuple(t.strip() for t in terms.split(","))
        try:
            _resolve_terms(terms)
        except ValueError as err:
            raise c.CLIError(
                f"--terms {args.terms!r}: {str(err).removeprefix('terms: ')}"
            ) from None
    return states, terms


def run(args) -> int:
    from ..plots import plot_profiles
    from ..pulse import _pulse

    states, terms = flags(args)
    c.maybe_x64(args.dtype)
    cfg_path, scene = load(args)
    with c.outputs(args.out, OUTPUTS, args.overwrite) as out:
        t0 = time.perf_counter()
        try:
            multibounce = {"auto": "auto", "on": True, "off": False}[args.multibounce]
            prof = _pulse.simulate(
                scene,
                states=states,
                terms=terms,
                dtype=c.dtype(args.dtype),
                multibounce=multibounce,
            )
            data = np.asarray(prof.data, float)
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: {err}") from None
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
        config = _scene_config(cfg_path, args)
        prov = c.provenance(config)
        prof.to_xarray(provenance=prov).to_netcdf(out.path("simulate.nc"), engine="h5netcdf")
        width = float(np.diff(arrays["edges_m"]).mean())
        energy = data.sum(-1)
        r = arrays["range_m"]
        w00 = data[0, 0] if prof.kind == "mueller" else data.reshape(-1, data.shape[-1])[0]
        tot = float(w00.sum())
        mean_r = float((w00 * r).sum() / tot) if tot > 0 else None
        summary = {
            "command": "simulate",
            "config_file": str(cfg_path),
            "overrides": c.overrides(args),
            "flags": {
                "states": args.states,
                "terms": args.terms,
                "dtype": args.dtype,
                "multibounce": args.multibounce,
            },
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
            "mean_range_m": mean_r,
            "rms_depth_m": float(np.sqrt((w00 * (r - mean_r) ** 2).sum() / tot))
            if tot > 0
            else None,
            "seconds": seconds,
        }
        c.write_json(out.path("simulate.json"), summary, config=config)
        plot_profiles(
            out.path("simulate.png"), data, r, prof.kind, list(prof.labels), str(cfg_path)
        )
    c.wrote(args, NAME, OUTPUTS)
    return 0


def _scene_config(cfg_path, args) -> dict:
    """The resolved scene config (file + overrides, defaults filled in) and its sensor's."""
    from .._config import load_toml_model
    from ..pulse import _scene

    scene = load_toml_model(_scene.SceneConfig, cfg_path, c.overrides(args))
    sensor_file = _scene._find_sensor(scene.sensor, cfg_path)
    sensor = load_toml_model(_scene.SensorConfig, sensor_file)
    return {
        "scene": scene.model_dump(),
        "sensor_file": str(sensor_file),
        "sensor": sensor.model_dump(),
    }
