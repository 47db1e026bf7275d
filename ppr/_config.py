"""Config files (TOML) parsed into typed pydantic schemas with errors that name the file,
the field and the offending value. Every config loader in ppr and inversion goes through
:func:`load_toml_model`; the CLI turns :class:`ConfigError` into a one-line message and exit
status 2.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any, TypeVar

import pydantic

M = TypeVar("M", bound=pydantic.BaseModel)


class ConfigError(ValueError):
    """A config file (or override) is invalid. ``str(err)`` is a single line."""


class StrictModel(pydantic.BaseModel):
    """Base schema: unknown keys are errors, NaN/inf floats are errors, models are frozen."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _find_nan(obj: Any, path: str = "") -> str | None:
    if isinstance(obj, float) and not math.isfinite(obj):
        return path or "<root>"
    if isinstance(obj, dict):
        for k, v in obj.items():
            p = _find_nan(v, f"{path}.{k}" if path else str(k))
            if p:
                return p
    if isinstance(obj, list):
        for i, v in enumerate(obj):
            p = _find_nan(v, f"{path}[{i}]")
            if p:
                return p
    return None


def format_validation_error(err: pydantic.ValidationError, source: str) -> str:
    parts = []
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "<root>"
        val = e.get("input")
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        parts.append(f"{loc} = {val!r}: {msg}")
    return f"{source}: " + "; ".join(parts)


def validate_data(model: type[M], data: dict, source: str) -> M:
    """Validate a mapping against ``model``; raise ConfigError naming source/field/value."""
    bad = _find_nan(data)
    if bad is not None:
        raise ConfigError(f"{source}: {bad} is not finite (NaN/inf are not allowed in configs)")
    try:
        return model.model_validate(data)
    except pydantic.ValidationError as err:
        raise ConfigError(format_validation_error(err, source)) from None


def read_toml(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from None


def load_toml_model(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Read a TOML file, apply dotted-key ``overrides`` (``{"pulse.fwhm_ps": 80}``), validate."""
    data = read_toml(path)
    for key, value in (overrides or {}).items():
        node = data
        *head, last = key.split(".")
        for k in head:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{path}: override {key!r}: {k!r} is not a table")
        node[last] = value
    return validate_data(model, data, str(path))


def parse_override(text: str) -> tuple[str, Any]:
    """Parse a command-line override ``key.sub=value`` (value parsed as a TOML value)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.strip(), value
