"""Config files (TOML) parsed into typed pydantic schemas with errors that name the file,
the field and the offending value. Every config loader in ppr and inversion goes through
:func:`load_toml_model`; the CLI turns :class:`ConfigError` into a one-line message and exit
status 2.
"""

from __future__ import annotations

import math
import re
import tomllib
import types
import typing
import warnings
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import pydantic

M = TypeVar("M", bound=pydantic.BaseModel)


class ConfigError(ValueError):
    """A config file (or override) is invalid. ``str(err)`` is a single line."""


class ConfigDeprecationWarning(FutureWarning):
    """A config uses a deprecated key (shown once per key and process)."""


# new key -> deprecated key, over every schema (error messages name the key as written)
_WRITTEN_AS: dict[str, str] = {}
_WARNED: set[tuple[str, str]] = set()


class StrictModel(pydantic.BaseModel):
    """Base schema: unknown keys are errors, NaN/inf floats are errors, models are frozen.

    ``renamed = {"old_key": ("new_key", factor)}``: a deprecated spelling still accepted
    (its value times ``factor``, e.g. picoseconds -> seconds) with a
    :class:`ConfigDeprecationWarning` once per key and process."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    renamed: ClassVar[dict[str, tuple[str, float]]] = {}

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs):
        super().__pydantic_init_subclass__(**kwargs)
        for old, (new, _) in cls.renamed.items():
            _WRITTEN_AS[new] = old

    @pydantic.model_validator(mode="before")
    @classmethod
    def _deprecated_keys(cls, data):
        if not cls.renamed or not isinstance(data, dict):
            return data
        data = dict(data)
        for old, (new, factor) in cls.renamed.items():
            if old not in data:
                continue
            if new in data:
                raise ValueError(f"give {new} or the deprecated {old}, not both")
            value = data.pop(old)
            number = isinstance(value, int | float) and not isinstance(value, bool)
            # the unit conversion applies to numbers only: a quoted "5" would pass it by
            data[new] = value * factor if number else _Refused(value) if factor != 1 else value
            if (cls.__name__, old) not in _WARNED:
                _WARNED.add((cls.__name__, old))
                unit = f" (x {factor:g})" if factor != 1 else ""
                warnings.warn(
                    f"config key {old!r} is deprecated; write {new!r}{unit}",
                    ConfigDeprecationWarning,
                    stacklevel=2,
                )
        return data

    @pydantic.model_validator(mode="before")
    @classmethod
    def _no_casts(cls, data):
        """Refuse what pydantic would otherwise convert without a word: a string or a
        boolean where a number belongs (``"256"``, ``true`` -> 1), a string or a number where
        true/false belongs (``"no"``, ``1``). Fields that also take strings (a name, "auto")
        keep them. The value is swapped for a marker that fails the field's own type check,
        so the error names the field and the value as written."""
        if not isinstance(data, dict):
            return data
        out = None
        for name, field in cls.model_fields.items():
            key = field.alias or name
            if key in data:
                checked = _refuse_casts(field.annotation, data[key])
                if checked is not data[key]:
                    out = dict(data) if out is None else out
                    out[key] = checked
        return data if out is None else out


class _Refused:
    """A config value refused before validation (it would only pass by conversion): no
    pydantic type accepts it; its repr is the value's, for the error message."""

    def __init__(self, value):
        self.value = value

    def __repr__(self) -> str:
        return repr(self.value)


def _scalar_kind(annotation) -> str | None:
    """``"number"``, ``"bool"`` or ``None`` (anything else) for a field's annotation,
    through ``Annotated`` and ``X | None``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _scalar_kind(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        kinds = {_scalar_kind(a) for a in typing.get_args(annotation) if a is not type(None)}
        return kinds.pop() if len(kinds) == 1 else None
    if annotation is bool:
        return "bool"
    if annotation in (int, float):
        return "number"
    return None


def _refuse_casts(annotation, value):
    """``value``, or (a copy of it with) each scalar that would reach a numeric or boolean
    field (or a list/tuple of them) only by conversion replaced by :class:`_Refused`."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _refuse_casts(typing.get_args(annotation)[0], value)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is None:
            return value
        if len(args) == 1:
            return _refuse_casts(args[0], value)
        return value if _scalar_kind(annotation) is None else _refuse_casts(args[0], value)
    if origin is dict and isinstance(value, dict) and len(typing.get_args(annotation)) == 2:
        v_type = typing.get_args(annotation)[1]
        new = {k: _refuse_casts(v_type, v) for k, v in value.items()}
        return value if all(new[k] is value[k] for k in value) else new
    if origin in (list, tuple) and isinstance(value, list | tuple):
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        if len(args) == 1:
            new = [_refuse_casts(args[0], v) for v in value]
        elif origin is tuple and len(args) == len(value):
            new = [_refuse_casts(a, v) for a, v in zip(args, value, strict=True)]
        else:
            return value
        if all(a is b for a, b in zip(new, value, strict=True)):
            return value
        return type(value)(new)
    kind = _scalar_kind(annotation)
    if kind == "number" and isinstance(value, str | bool):
        return _Refused(value)
    if kind == "bool" and not isinstance(value, bool):
        return _Refused(value)
    return value


def first_nonfinite(arr) -> tuple[int, tuple[int, ...], float] | None:
    """``(count, index, value)`` of the non-finite (NaN/inf) entries of an array and the first
    one in C order, or ``None`` when every entry is finite: what an error about bad data names."""
    import numpy as np

    a = np.asarray(arr)
    bad = ~np.isfinite(a)
    if not bad.any():
        return None
    first = tuple(int(i) for i in np.argwhere(bad)[0])
    return int(bad.sum()), first, float(a[first])


def _find_nan(obj: Any, path: str = "") -> tuple[str, float] | None:
    if isinstance(obj, float) and not math.isfinite(obj):
        return path or "<root>", obj
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


_TYPE_WORDS = {
    "string_type": "a string",
    "dict_type": "a table",
    "model_type": "a table",
    "model_attributes_type": "a table",
    "list_type": "a list",
    "tuple_type": "a list",
    "float_type": "a number",
    "float_parsing": "a number",
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "bool_type": "true or false",
    "bool_parsing": "true or false",
}


def _user_path(
    loc: tuple, data: Any, prefix: str = "", missing: bool = False
) -> tuple[str, Any, bool]:
    """A pydantic error location as the user writes the field (``shapes[0].symmetry``),
    skipping the tags pydantic adds for union members (``Range``, ``list[...]``, ``str``);
    with the value found there and whether a deprecated spelling was followed.
    ``missing``: the last part names a key absent from the data."""
    path, node, aliased = prefix, data, False
    for i, part in enumerate(loc):
        last = i == len(loc) - 1
        if isinstance(part, int) and isinstance(node, list | tuple) and part < len(node):
            path, node = f"{path}[{part}]", node[part]
        elif isinstance(part, str) and isinstance(node, dict):
            if part not in node and _WRITTEN_AS.get(part) in node:
                part, aliased = _WRITTEN_AS[part], True  # the user wrote the deprecated key
            if part in node or missing and last:
                path = f"{path}.{part}" if path else part
                node = node.get(part)
    return path, node, aliased


def _type_mismatch(e: dict) -> bool:
    """The input is not even of the member's type (the user meant another union member)."""
    if e["type"] in _TYPE_WORDS:
        return True
    return e["type"] == "literal_error" and isinstance(e.get("input"), dict | list)


def _message(e: dict) -> str:
    if e["type"] == "extra_forbidden":
        return "unknown key"
    if e["type"] == "missing":
        loc = e.get("loc", ())
        if loc and isinstance(loc[-1], int):  # a fixed-length list given too few values
            return f"too few values (no value at position {loc[-1]})"
        return "required field missing"
    if e["type"] in _TYPE_WORDS:
        return f"expected {_TYPE_WORDS[e['type']]}"
    if e["type"] == "too_short" and hasattr(e.get("input"), "__len__") and not e["input"]:
        return "must not be empty"
    msg = str(e["msg"]).replace(" after validation", "").replace("Input should be", "must be")
    for head in ("Value error, ", "Assertion failed, "):
        if msg.startswith(head):
            msg = msg[len(head) :]
    return msg.replace("valid dictionary", "table")


def format_validation_error(
    err: pydantic.ValidationError, source: str, data: Any = None, prefix: str = ""
) -> str:
    """One line naming ``source``, each bad field as the user wrote it (``data``: the
    validated input; ``prefix``: the path of ``data`` in the file) and its value.

    Errors of the members of a union are merged: messages at one field are joined with
    "or", and an error at a field is dropped when another names a field inside it (the
    user wrote a table or list, so the member that failed deeper is the one meant)."""
    if data is None:
        data = {}
    items: dict[str, list] = {}
    for e in err.errors():
        path, node, aliased = _user_path(tuple(e["loc"]), data, prefix, e["type"] == "missing")
        value = node if aliased else e.get("input")  # as written, not converted
        items.setdefault(path, [value, []])[1].append(e)
    paths = [
        p for p in items if not any(q != p and q.startswith(p) and q[len(p)] in ".[" for q in items)
    ]
    parts = []
    for p in paths:
        value, errs = items[p]
        meant = [e for e in errs if not _type_mismatch(e)] or errs
        msgs = list(dict.fromkeys(_message(e) for e in meant))
        if len(msgs) > 1 and all(m.startswith("expected ") for m in msgs):
            text = "expected " + " or ".join(m.removeprefix("expected ") for m in msgs)
        else:
            text = " or ".join(msgs)
        if not p:
            parts.append(text)
        elif isinstance(value, dict) or msgs == ["required field missing"]:
            parts.append(f"{p}: {text}")  # a whole table (model checks) or nothing to show
        else:
            parts.append(f"{p} = {value!r}: {text}")
    return f"{source}: " + "; ".join(parts)


def validate_data(model: type[M], data: dict, source: str) -> M:
    """Validate a mapping against ``model``; raise ConfigError naming source/field/value."""
    bad = _find_nan(data)
    if bad is not None:
        path, value = bad
        raise ConfigError(
            f"{source}: {path} = {value}: not finite (NaN/inf are not allowed in configs)"
        )
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = model.model_validate(data)
    except pydantic.ValidationError as err:
        raise ConfigError(format_validation_error(err, source, data)) from None
    finally:
        for w in caught:
            if issubclass(w.category, ConfigDeprecationWarning):
                # the file it is in, not pydantic's line that ran the validator
                warnings.warn(f"{source}: {w.message}", w.category, stacklevel=2)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return result


def read_toml(path: str | Path) -> dict:
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder, not a config file")
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from None
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"{path}: not a TOML text file (not UTF-8: byte {err.object[err.start]:#04x} at "
            f"position {err.start})"
        ) from None


def load_toml_model(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Read a TOML file, apply dotted-key ``overrides`` (``{"pulse.fwhm_s": 80e-12}``), validate."""
    data = read_toml(path)
    for key, value in (overrides or {}).items():
        _set_override(data, key, value, path)
    return validate_data(model, data, config_source(path, overrides))


_KEY_PART = re.compile(r"^([^\[\]]+)((?:\[\d+\])*)$")


def _set_override(data: dict, key: str, value, path) -> None:
    """``data[key] = value`` for a dotted key whose parts may index a list of tables
    (``shapes[0].symmetry``, the notation errors use); a missing table is created, a missing
    list entry is an error naming the list's length."""
    steps: list[str | int] = []
    for part in key.split("."):
        match = _KEY_PART.match(part)
        if match is None:
            raise ConfigError(
                f"{path}: override {key!r}: {part!r} is not a key (write key.sub or key[index].sub)"
            )
        steps.append(match.group(1))
        steps += [int(i) for i in re.findall(r"\[(\d+)\]", match.group(2))]
    node = data
    for i, step in enumerate(steps[:-1]):
        where = _written(steps[: i + 1])
        if isinstance(step, int):
            if not isinstance(node, list):
                raise ConfigError(
                    f"{path}: override {key!r}: {_written(steps[:i])!r} is a table, not a list"
                )
            if step >= len(node):
                raise ConfigError(
                    f"{path}: override {key!r}: {_written(steps[:i])!r} has {len(node)} "
                    f"entries (indices 0 to {len(node) - 1})"
                )
            node = node[step]
        else:
            if not isinstance(node, dict):
                raise ConfigError(
                    f"{path}: override {key!r}: {_written(steps[:i])!r} is a list: index it "
                    f"({_written(steps[:i])}[0].{step})"
                )
            if step not in node and isinstance(steps[i + 1], int):
                raise ConfigError(
                    f"{path}: override {key!r}: {where!r} is not in the config (an index "
                    "reaches an entry of a list the config holds)"
                )
            node = node.setdefault(step, {})
        if not isinstance(node, (dict, list)):
            raise ConfigError(f"{path}: override {key!r}: {where!r} is {node!r}, not a table")
    last = steps[-1]
    if isinstance(last, int):
        if not isinstance(node, list):
            raise ConfigError(
                f"{path}: override {key!r}: {_written(steps[:-1])!r} is a table, not a list"
            )
        if last >= len(node):
            n = len(node)
            raise ConfigError(
                f"{path}: override {key!r}: {_written(steps[:-1])!r} has {n} entries "
                "(an override replaces an entry; it cannot add one)"
            )
    elif isinstance(node, list):
        raise ConfigError(
            f"{path}: override {key!r}: {_written(steps[:-1])!r} is a list: index it "
            f"({_written(steps[:-1])}[0].{last})"
        )
    elif not isinstance(node, dict):
        raise ConfigError(f"{path}: override {key!r}: {_written(steps[:-1])!r} is not a table")
    node[last] = value


def _written(steps) -> str:
    out = ""
    for s in steps:
        out += f"[{s}]" if isinstance(s, int) else (f".{s}" if out else s)
    return out


def config_source(path: str | Path, overrides: dict | None = None) -> str:
    """How an error names a config: the file, and the command line's overrides applied to
    it (the value at fault may be one of theirs, not the file's)."""
    if not overrides:
        return str(path)
    return f"{path} with --set " + ", ".join(f"{k}={_as_written(v)}" for k, v in overrides.items())


def _as_written(value) -> str:
    """A value as a TOML file writes it (``true``, ``"4"``, ``[1, 2]``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace('"', '\\"') + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_as_written(v) for v in value) + "]"
    return repr(value)


def parse_override(text: str) -> tuple[str, Any]:
    """Parse a command-line override ``key.sub=value`` (value parsed as a TOML value)."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    if not key.strip() or any(not k.strip() for k in key.split(".")):
        raise ConfigError(f"--set {text!r}: empty key (expected key.sub=value)")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.strip(), value
