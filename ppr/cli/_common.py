"""What every ``ppr`` command shares: config loading with ``--set`` overrides and the path
rule, the common flags, errors, JSON summaries with provenance, small schema types.

Light on purpose (pydantic, NumPy and the standard library): the parser is built from these
before JAX is imported."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
import pydantic

from .. import _outputs
from .._config import (
    ConfigError,
    StrictModel,
    first_nonfinite,
    load_toml_model,
    parse_override,
)
from .._resources import shipped_config

__all__ = [
    "CLIError",
    "ConfigError",
    "StrictModel",
    "add_common",
    "config_path",
    "load_config",
    "overrides",
    "resolve_path",
    "write_json",
]

Outputs = _outputs.Outputs
outputs = _outputs.outputs


class CLIError(Exception):
    """A usage error (existing output, missing input) reported as one line, exit status 2."""


# ================================================================================ configs
Vec3 = tuple[float, float, float]
PositiveFloat = Annotated[float, pydantic.Field(gt=0.0)]
# random seeds: NumPy's generators take non-negative integers only
Seed = Annotated[int, pydantic.Field(ge=0, description="random seed")]

_T = TypeVar("_T")


def _distinct(v: list) -> list:
    dup = sorted({x for x in v if v.count(x) > 1})
    if dup:
        raise ValueError(f"{dup[0]!r} is listed twice")
    return v


# lists the user must not empty, each entry once (a repeated SNR or weight design would
# only repeat rows of the report)
NonEmpty = Annotated[list[_T], pydantic.Field(min_length=1), pydantic.AfterValidator(_distinct)]


TermName = Literal["single", "double", "multiple"]
Terms = (
    Literal["auto", "all"]
    | Annotated[list[TermName], pydantic.Field(min_length=1), pydantic.AfterValidator(_distinct)]
)
TERMS_HELP = (
    'BRDF terms: "auto" (the double term where it matters), "all", or a list of "single", '
    '"double", "multiple"'
)


def terms_arg(terms):
    """A config's ``terms`` as the library takes them (``None``: all)."""
    if terms == "all":
        return None
    return tuple(terms) if isinstance(terms, list) else terms


class Range(StrictModel):
    """Evenly spaced values ``numpy.linspace(start, stop, num)``."""

    start: float
    stop: float
    num: int = pydantic.Field(ge=1, le=100_000)

    def values(self) -> np.ndarray:
        return np.linspace(self.start, self.stop, self.num)


# config fields holding paths, and the words that are not paths there (docs/configs.md)
PATH_KEYS = {
    "scene": (),
    "mesh": ("example",),
    "mesh.path": (),
    "database": (),
    "database_path": (),
    "observations": ("simulate",),
    "observation.source": ("simulate",),
    "mcmc": ("default", "none"),
}


def overrides(args) -> dict:
    """``--set key.sub=value`` overrides (TOML values). A relative path given on the command
    line is relative to the current folder (made absolute here); one written in a config file
    is relative to that file (:func:`resolve_path`)."""
    out = {}
    for text in getattr(args, "set", None) or []:
        key, value = parse_override(text)
        is_path = (
            key in PATH_KEYS
            and isinstance(value, str)
            and value.strip().lower() not in PATH_KEYS[key]
        )
        if key == "sensor" and isinstance(value, str):  # a shipped sensor's name, or a file
            is_path = "/" in value or value.endswith(".toml")
        if is_path:
            value = str(Path(value).expanduser().absolute())
        out[key] = value
    return out


def config_path(args, default: str) -> Path:
    """``--config`` if given, else the shipped default ``configs/<default>``."""
    if getattr(args, "config", None) is not None:
        return Path(args.config)
    try:
        return shipped_config(default)
    except FileNotFoundError as err:
        raise CLIError(f"no --config given and {err}") from None


def load_config(args, model: type[StrictModel], default: str) -> tuple[Path, Any]:
    """The command's config file (``--config`` or the shipped default) with its ``--set``
    overrides, validated whole against ``model``."""
    path = config_path(args, default)
    return path, load_toml_model(model, path, overrides(args))


def resolve_path(value: str, config_file: Path) -> Path:
    """A path written in a config: relative to the config file (``--set`` values were made
    absolute against the current folder by :func:`overrides`)."""
    p = Path(value).expanduser()
    return p if p.is_absolute() else config_file.parent / p


def read_npz(value: str, cfg_path: Path, field: str, optional: tuple[str, ...] = ()) -> dict:
    """The ``data`` array (float64) and the ``optional`` arrays present of the .npz file a
    config field names. Errors name the config file, the field as written, the value and the
    problem (no such file, a folder, not an .npz archive, no ``data``, a non-numeric, complex
    or boolean ``data``, NaN/inf with the first position); nothing is cast silently: strings,
    complex numbers (their imaginary part) and booleans are refused, not converted."""
    import zipfile

    where = f"{cfg_path}: {field} = {value!r}"
    if not str(value).strip():
        raise ConfigError(f"{where}: empty path; give an .npz file with a 'data' array")
    path = resolve_path(value, cfg_path)
    if path.is_dir():
        raise ConfigError(f"{where}: {path} is a folder, not an .npz file")
    if not path.is_file():
        raise ConfigError(f"{where}: no such file ({path})")
    save = "np.savez(path, data=array)"
    out = {}
    with open(path, "rb") as f:  # ours to close (np.load leaks a corrupt archive's handle)
        head = f.read(6)
        if not (head.startswith(b"PK") or head == b"\x93NUMPY"):
            # np.load would take it for a pickle and say so
            raise ConfigError(
                f"{where}: not a NumPy .npz file (no zip header); write it with {save}"
            )
        f.seek(0)
        try:
            z = np.load(f, allow_pickle=False)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise ConfigError(
                f"{where}: not a NumPy .npz file ({one_line(err)}); write it with {save}"
            ) from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ConfigError(
                f"{where}: a single .npy array, not an .npz archive; write it with {save}"
            )
        with z:
            if "data" not in z.files:
                has = f"it has {', '.join(z.files)}" if z.files else "it holds no arrays"
                raise ConfigError(f"{where}: no 'data' array ({has}); write it with {save}")
            for name in ("data", *optional):
                if name not in z.files:
                    continue
                try:
                    out[name] = z[name]
                except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
                    msg = one_line(err)
                    if "allow_pickle" in msg:
                        msg = "an object array (pickled Python objects), not numbers"
                    raise ConfigError(f"{where}: array {name!r} cannot be read: {msg}") from None
                if not isinstance(out[name], np.ndarray):
                    # NpzFile hands back the raw bytes of a member not in .npy format
                    raise ConfigError(
                        f"{where}: array {name!r} cannot be read: its member {name}.npy is not "
                        f"a .npy array; write the file with {save}"
                    )
    data = out["data"]
    kind = data.dtype.kind
    if kind not in "iuf":
        what = {
            "b": "booleans, not counts",
            "c": "complex numbers: the imaginary part would be lost",
            "U": "strings",
            "S": "strings",
            "O": "Python objects",
            "M": "dates",
            "m": "time differences",
            "V": "records (a structured array)",
        }.get(kind, "not real numbers")
        raise ConfigError(
            f"{where}: data has dtype {data.dtype} ({what}); expected real numbers "
            "(integer or float counts)"
        )
    data = data.astype(np.float64)
    bad = first_nonfinite(data)
    if bad is not None:
        count, first, value = bad
        raise ConfigError(
            f"{where}: data holds {count} NaN/inf value(s), first at index {first} "
            f"= {value}; mask or drop those bins before fitting"
        )
    out["data"] = data
    return out


def sub_model(model, data, cfg_path: Path, field: str):
    """Validate a sub-table with another module's schema; errors name ``field``."""
    try:
        return model.model_validate(data)
    except pydantic.ValidationError as err:
        from .._config import format_validation_error

        raise ConfigError(format_validation_error(err, str(cfg_path), data, field)) from None


def resolve_material(spec: Any, wavelength: float, field: str, cfg_path: Path):
    """A config material spec -> :class:`ppr.Material`; errors name the file and field.

    Specs: a library name (``"aluminium"``, default finish) or ``"name/finish"``
    (``"aluminium/rough"``; see configs/materials.toml), or an inline table
    ``{n_real, n_imag, m, corr_length_m}`` as in scene configs."""
    from ..materials._library import load_material
    from ..pulse import _scene

    if isinstance(spec, dict):
        spec = sub_model(_scene.InlineMaterial, spec, cfg_path, field)
        return _scene._material_from_config(spec, wavelength, f"{cfg_path}: {field}")
    if not isinstance(spec, str):
        raise ConfigError(
            f"{cfg_path}: {field} = {spec!r}: expected a library material name ('name' or "
            "'name/finish') or an inline table {n_real, n_imag, m, corr_length_m}"
        )
    name, slash, finish = spec.partition("/")
    try:
        return load_material(name, wavelength, finish if slash else None)
    except (ValueError, KeyError) as err:
        msg = str(err).strip(chr(39))
        if "wavelength" in msg:
            msg = f"at wavelength_nm = {wavelength * 1e9:g}: {msg}"
        raise ConfigError(f"{cfg_path}: {field} = {spec!r}: {msg}") from None


# ============================================================================== helpers
def progress(args) -> bool:
    return not getattr(args, "quiet", False)


def say(args, msg: str) -> None:
    if not getattr(args, "quiet", False):
        print(msg, file=sys.stderr, flush=True)


def wrote(args, command: str, names) -> None:
    say(args, f"ppr {command}: wrote {', '.join(str(Path(args.out) / n) for n in names)}")


def dtype(name: str):
    return np.float32 if name == "float32" else np.float64


def maybe_x64(dtype_name: str) -> None:
    """float64 runs need JAX's x64 mode; the CLI is a program, so it may switch it on."""
    if dtype_name == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)


def one_line(err: BaseException) -> str:
    msg = str(err).strip() or type(err).__name__
    return " ".join(part.strip() for part in msg.splitlines() if part.strip())


# ============================================================================ JSON outputs
def jsonable(obj: Any) -> Any:
    """``obj`` with arrays, paths, complex numbers and schemas turned into JSON values
    (non-finite floats become ``null``)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, complex):
        return [obj.real, obj.imag]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, pydantic.BaseModel):
        return jsonable(obj.model_dump())
    if hasattr(obj, "__array__"):
        return jsonable(np.asarray(obj))
    return obj


# the ``ppr`` command line being run (set by ppr.cli.main), recorded in every JSON output
COMMAND_LINE: list[str] | None = None


def provenance(config: Any = None) -> dict:
    """The provenance record of a command's outputs (:func:`ppr.outputs.provenance` with the
    resolved ``config`` as JSON values and the command line)."""
    return _outputs.provenance(config=jsonable(config), command_line=COMMAND_LINE)


def write_json(path: Path, data: dict, config: Any = None) -> None:
    """Write a command's JSON summary with its provenance (:func:`ppr._outputs.provenance`:
    versions, the command line, the time, the resolved ``config``)."""
    record = {**data, "provenance": provenance(config)}
    path.write_text(json.dumps(jsonable(record), indent=2, allow_nan=False) + "\n")


# =============================================================================== parser
class Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written (generated, already wrapped); an option's default is shown
    unless its help states it or there is none (flags, unset values)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (
            "default" in text
            or not action.option_strings
            or action.default in (None, False, [], argparse.SUPPRESS)
        ):
            return text
        return text + " (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """Usage errors as one line (``ppr simulate: error: ...``), exit status 2; the
    description may be a callable, evaluated when the help is shown (it may import the
    library to read its schemas)."""

    def __init__(self, *args, describe=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._describe = describe

    def format_help(self):
        if self._describe is not None:
            self.description, self._describe = self._describe(), None
        return super().format_help()

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def add_command(sub, module, help: str, out_default: str) -> argparse.ArgumentParser:
    """Register a config-driven command of ``module`` (its ``NAME``, ``help_text``,
    ``DEFAULT_CONFIG``, ``SET_EXAMPLE``, ``run`` and ``load``): the subparser with the common
    options (:func:`add_common`); returned for the command's own flags."""
    p = sub.add_parser(module.NAME, help=help, describe=module.help_text, formatter_class=Formatter)
    add_common(p, module.DEFAULT_CONFIG, out_default, module.SET_EXAMPLE)
    p.set_defaults(func=module.run, load=module.load)
    return p


def add_common(
    p: argparse.ArgumentParser, default_config: str | None, out_default: str, set_example: str
) -> None:
    """``--config``, ``--set``, ``--out``, ``--overwrite``, ``--quiet``; ``set_example``: a
    ``--set`` of this command's config (tested: tests/test_cli.py)."""
    if default_config is not None:
        p.add_argument(
            "--config",
            "-c",
            metavar="TOML",
            default=None,
            help=f"config file (TOML); default: the shipped configs/{default_config}",
        )
    p.add_argument(
        "--set",
        "-s",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a config field: dotted keys (key[0].sub for an entry of a list of "
        "tables), TOML values, repeatable (e.g. --set "
        f"{set_example}); relative paths are relative to the current folder",
    )
    p.add_argument("--out", "-o", metavar="DIR", default=out_default, help="output folder")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace existing outputs in --out (default: refuse)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or messages")
