"""Help text generated from the config schemas: every field with its default, unit, allowed
values and description, so ``ppr COMMAND --help`` cannot drift from what the command reads.

Units come from the field's ``json_schema_extra={"unit": ...}`` or its name's suffix
(``_nm`` nanometres, ``_m`` metres, ``_s`` seconds, ``_deg`` degrees, ``_urad``
microradians, ``_bins`` bins, ...); a ``dict`` field validated later by another schema names
it with ``json_schema_extra={"schema": "module:Class"}``."""

from __future__ import annotations

import importlib
import textwrap
import types
import typing
from typing import Any, Literal

import annotated_types
import pydantic
from pydantic_core import PydanticUndefined

WIDTH = 90

_SUFFIX_UNITS = (
    ("_urad", "microradians"),
    ("_deg", "degrees"),
    ("_rad", "radians"),
    ("_nm", "nanometres"),
    ("_mm", "millimetres"),
    ("_km", "kilometres"),
    ("_m", "metres"),
    ("_ps", "picoseconds"),
    ("_s", "seconds"),
    ("_bins", "bins"),
)


def unit_of(name: str, field: pydantic.fields.FieldInfo | None = None) -> str | None:
    extra = (field.json_schema_extra if field is not None else None) or {}
    if isinstance(extra, dict) and "unit" in extra:
        return str(extra["unit"])
    for suffix, unit in _SUFFIX_UNITS:
        if name.endswith(suffix):
            return unit
    return None


def _toml(value: Any) -> str:
    """A default as the user writes it in TOML."""
    if isinstance(value, pydantic.BaseModel):
        value = value.model_dump()
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def _literals(tp) -> list:
    """The allowed values of a ``Literal`` inside ``tp`` (unions and ``Annotated`` seen
    through)."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        return list(typing.get_args(tp))
    if origin is typing.Annotated:
        return _literals(typing.get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        out = []
        for a in typing.get_args(tp):
            out += _literals(a)
        return out
    return []


def _models(tp) -> list[type[pydantic.BaseModel]]:
    """Schema classes a field holds directly (``Model`` or ``Model | None``)."""
    if isinstance(tp, type) and issubclass(tp, pydantic.BaseModel):
        return [tp]
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return _models(args[0])
    return []


def _bounds(field: pydantic.fields.FieldInfo) -> str:
    lo = hi = None
    for m in field.metadata:
        if isinstance(m, annotated_types.Gt):
            lo = f"> {m.gt:g}"
        elif isinstance(m, annotated_types.Ge):
            lo = f">= {m.ge:g}"
        elif isinstance(m, annotated_types.Lt):
            hi = f"< {m.lt:g}"
        elif isinstance(m, annotated_types.Le):
            hi = f"<= {m.le:g}"
    return ", ".join(x for x in (lo, hi) if x)


def _sub_schema(field: pydantic.fields.FieldInfo):
    extra = field.json_schema_extra
    if isinstance(extra, dict) and "schema" in extra:
        module, _, name = str(extra["schema"]).partition(":")
        return getattr(importlib.import_module(module), name)
    return None


def field_lines(model: type[pydantic.BaseModel], prefix: str = "") -> list[str]:
    """One entry per field of ``model`` (nested schemas flattened to dotted keys)."""
    lines: list[str] = []
    for name, f in model.model_fields.items():
        key = f"{prefix}{name}"
        subs = _models(f.annotation) or [m for m in [_sub_schema(f)] if m is not None]
        if subs:
            head = f"[{key}]"
            lines += _wrap(head + (f"  {f.description}" if f.description else ""), "  ", "      ")
            lines += field_lines(subs[0], f"{key}.")
            continue
        if f.is_required():
            default = "(required)"
        elif f.default is PydanticUndefined or f.default is None:
            default = "(not set)" if f.default is None else ""
        else:
            default = _toml(f.default)
        notes = []
        unit = unit_of(name, f)
        if unit:
            notes.append(unit)
        bounds = _bounds(f)
        if bounds:
            notes.append(bounds)
        choices = _literals(f.annotation)
        if choices and not f.description:
            notes.append(" | ".join(_toml(c) for c in choices))
        head = f"{key} = {default}" if default else key
        if notes:
            head += f"  [{'; '.join(notes)}]"
        lines += _wrap(head + (f"  {f.description}" if f.description else ""), "  ", "      ")
    return lines


def _wrap(text: str, first: str, rest: str) -> list[str]:
    return textwrap.wrap(
        text, WIDTH, initial_indent=first, subsequent_indent=rest, break_on_hyphens=False
    )


def fields_text(title: str, model: type[pydantic.BaseModel]) -> str:
    return "\n".join([f"{title}, with defaults and [unit; bounds]:", *field_lines(model)])


def paragraph(text: str) -> str:
    return "\n".join(textwrap.wrap(" ".join(text.split()), WIDTH))


def examples_text(examples: list[str]) -> str:
    return "\n".join(["Examples:", *(f"  {e}" for e in examples)])


def describe(summary: str, *sections: str, examples: list[str] = (), outputs: str = "") -> str:
    """A command's ``--help`` description: summary, schema sections, outputs, examples."""
    parts = [paragraph(summary), *sections]
    if outputs:
        parts.append(paragraph("Outputs: " + outputs))
    parts.append(paragraph(PATH_RULE))
    if examples:
        parts.append(examples_text(list(examples)))
    return "\n\n".join(parts)


PATH_RULE = (
    "Relative paths written in a config file are relative to that file; relative paths given "
    "with --set are relative to the current folder (docs/configs.md)."
)
