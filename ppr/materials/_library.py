"""Material library: sourced optical constants and finish presets from ``configs/materials.toml``.

``load_material(name, wavelength, finish)`` returns a :class:`ppr.Material`. The file is parsed
with a strict pydantic schema (unknown keys, NaN/inf, negative ``k`` or duplicate wavelengths
are errors naming the file, the field and the value).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Literal

import jax.numpy as jnp
import pydantic

from .._config import ConfigError, StrictModel, read_toml, validate_data
from ..optics.conventions import DEFAULT_WAVELENGTH_M
from ._material import Material

__all__ = [
    "DEFAULT_LIBRARY",
    "MaterialLibrary",
    "film_entries",
    "load_library",
    "load_material",
    "material_names",
]

_REPO_LIBRARY = Path(__file__).resolve().parents[2] / "configs" / "materials.toml"
# a wheel install carries a copy (pyproject: force-include) inside the package
_PACKAGED_LIBRARY = Path(__file__).resolve().parents[1] / "data" / "materials.toml"
DEFAULT_LIBRARY = _REPO_LIBRARY if _REPO_LIBRARY.is_file() else _PACKAGED_LIBRARY

# wavelengths match when within this many nanometres
_WAVELENGTH_TOL_NM = 0.5


class Finish(StrictModel):
    m: float = pydantic.Field(ge=0.0, le=1e6)
    corr_length: float = pydantic.Field(gt=0.0, le=1.0)
    description: str = ""


class IndexEntry(StrictModel):
    wavelength_nm: float = pydantic.Field(gt=0.0)
    n: float = pydantic.Field(gt=0.0)
    k: float = pydantic.Field(ge=0.0)
    source: str = pydantic.Field(min_length=3)
    approximate: bool = False


class FilmEntry(StrictModel):
    """One layer of a coated material: a bare library material (its index at the same
    wavelength) and a thickness."""

    material: str
    thickness_m: float = pydantic.Field(ge=0.0, le=1e-2)
    source: str = pydantic.Field(min_length=3)


class MaterialEntry(StrictModel):
    description: str = ""
    default_finish: str
    index: list[IndexEntry] | None = pydantic.Field(default=None, min_length=1)
    substrate: str | None = None
    films: list[FilmEntry] = []
    film_mode: Literal["auto", "coherent", "incoherent", "lobe"] = "auto"

    @pydantic.field_validator("index")
    @classmethod
    def _unique_wavelengths(cls, v: list[IndexEntry] | None) -> list[IndexEntry] | None:
        if v is None:
            return v
        wl = sorted(e.wavelength_nm for e in v)
        for a, b in zip(wl, wl[1:], strict=False):
            if b - a <= _WAVELENGTH_TOL_NM:
                raise ValueError(f"duplicate wavelength {b} nm")
        return v

    @pydantic.model_validator(mode="after")
    def _bare_or_coated(self) -> MaterialEntry:
        if (self.index is None) == (self.substrate is None):
            raise ValueError(
                "give exactly one of index (a bare material) and substrate (a coated one, "
                "with films)"
            )
        if self.substrate is not None and not self.films:
            raise ValueError("a coated material (substrate = ...) needs at least one film")
        if self.index is not None and self.films:
            raise ValueError("films need substrate = <bare material>, not index entries")
        return self


class MaterialLibrary(StrictModel):
    finishes: dict[str, Finish]
    materials: dict[str, MaterialEntry]

    @pydantic.model_validator(mode="after")
    def _finishes_exist(self) -> MaterialLibrary:
        for name, mat in self.materials.items():
            if mat.default_finish not in self.finishes:
                raise ValueError(
                    f"materials.{name}.default_finish = {mat.default_finish!r} is not one of the "
                    f"finishes {sorted(self.finishes)}"
                )
            refs = [("substrate", mat.substrate)] if mat.substrate else []
            refs += [(f"films[{i}].material", f.material) for i, f in enumerate(mat.films)]
            for field, ref in refs:
                other = self.materials.get(ref)
                if other is None or other.index is None:
                    bare = sorted(k for k, v in self.materials.items() if v.index is not None)
                    raise ValueError(
                        f"materials.{name}.{field} = {ref!r} is not a bare library material "
                        f"(one of {bare})"
                    )
        return self


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime: float) -> MaterialLibrary:
    return validate_data(MaterialLibrary, read_toml(path), path)


def load_library(path: str | Path | None = None) -> MaterialLibrary:
    """Parse and validate a material library file (default: ``configs/materials.toml``).

    Raises :class:`ppr._config.ConfigError` (a ``ValueError``) naming file, field and value.
    """
    p = Path(path) if path is not None else DEFAULT_LIBRARY
    if not p.is_file():
        raise ConfigError(f"{p}: no such material library file")
    return _load_cached(str(p), p.stat().st_mtime)


def material_names(path: str | Path | None = None) -> list[str]:
    """Sorted names of the materials in the library."""
    return sorted(load_library(path).materials)


def finish_names(path: str | Path | None = None) -> list[str]:
    """Sorted names of the finish presets in the library."""
    return sorted(load_library(path).finishes)


def _material_entry(lib: MaterialLibrary, name: str) -> MaterialEntry:
    if name not in lib.materials:
        avail = ", ".join(sorted(lib.materials))
        raise ValueError(f"unknown material {name!r}; available: {avail}")
    return lib.materials[name]


def _index_at(entry: MaterialEntry, name: str, wavelength: float | int) -> IndexEntry:
    """Index entry of a *bare* material at a wavelength (coated ones: resolve the substrate
    first, :func:`_substrate_entry`)."""
    try:
        wl_nm = float(wavelength) * 1e9
    except (TypeError, ValueError):
        raise ValueError(f"wavelength must be a number in metres, got {wavelength!r}") from None
    if not (0 < wl_nm < 1e6):
        raise ValueError(f"wavelength must be in metres (e.g. 532e-9), got {wavelength!r}")
    for e in entry.index:
        if abs(e.wavelength_nm - wl_nm) <= _WAVELENGTH_TOL_NM:
            return e
    avail = ", ".join(f"{e.wavelength_nm:g}e-9" for e in entry.index)
    raise ValueError(
        f"material {name!r} has no data at wavelength={wavelength!r} m; available: {avail}"
    )


def load_material(
    name: str,
    wavelength: float | int = DEFAULT_WAVELENGTH_M,
    finish: str | None = None,
    path: str | Path | None = None,
    dtype=None,
) -> Material:
    """A :class:`ppr.Material` from the library.

    **Arguments:**

    - `name`: material name (see :func:`material_names`), e.g. ``"aluminium"``.
    - `wavelength`: in metres; must match a tabulated wavelength within 0.5 nm (no
      interpolation: optical constants of metals are not smooth enough to interpolate
      between 532 and 1064 nm).
    - `finish`: finish preset name (``"mirror"``, ``"polished"``, ``"brushed"``, ``"rough"``,
      ``"matte"``); default: the material's ``default_finish``.
    - `path`: library file (default ``configs/materials.toml``).
    - `dtype`: real float dtype of the fields (default: JAX's default float, i.e. float32
      unless x64 is enabled); ``n`` gets the matching complex dtype.

    **Returns:** ``Material(n = n + i k, m, corr_length, name="<name>/<finish>@<nm>nm")``.

    Unknown names, wavelengths or finishes raise ``ValueError`` listing the available ones.
    """
    lib = load_library(path)
    entry = _material_entry(lib, name)
    idx = _index_at(_substrate_entry(lib, entry), name, wavelength)
    fin_name = entry.default_finish if finish is None else finish
    if fin_name not in lib.finishes:
        avail = ", ".join(sorted(lib.finishes))
        raise ValueError(f"unknown finish {finish!r}; available: {avail}")
    fin = lib.finishes[fin_name]
    fdt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    if not jnp.issubdtype(fdt, jnp.floating):
        raise ValueError(f"dtype must be a real float dtype, got {dtype!r}")
    cdt = jnp.result_type(fdt, jnp.complex64)
    films = ()
    if entry.films:
        films = tuple(
            (
                jnp.asarray(complex(e.n, e.k), cdt),
                jnp.asarray(f.thickness_m, fdt),
            )
            for f in entry.films
            for e in [_index_at(lib.materials[f.material], f.material, wavelength)]
        )
    return Material(
        n=jnp.asarray(complex(idx.n, idx.k), cdt),
        m=jnp.asarray(fin.m, fdt),
        corr_length=jnp.asarray(fin.corr_length, fdt),
        name=f"{name}/{fin_name}@{idx.wavelength_nm:g}nm",
        films=films,
        wavelength=jnp.asarray(float(wavelength), fdt) if films else None,
        film_mode=entry.film_mode,
    )


def _substrate_entry(lib: MaterialLibrary, entry: MaterialEntry) -> MaterialEntry:
    return entry if entry.substrate is None else lib.materials[entry.substrate]


def index_entry(
    name: str, wavelength: float | int = DEFAULT_WAVELENGTH_M, path: str | Path | None = None
) -> IndexEntry:
    """The raw library entry (index, source, approximate flag) of a material at a wavelength
    (a coated material's: its substrate's)."""
    lib = load_library(path)
    return _index_at(_substrate_entry(lib, _material_entry(lib, name)), name, wavelength)


def film_entries(
    name: str, wavelength: float | int = 532e-9, path: str | Path | None = None
) -> list[tuple[str, IndexEntry, FilmEntry]]:
    """A coated material's layers (outermost first): ``(film material, its index entry at
    the wavelength, the layer entry with thickness and source)``; ``[]`` for a bare one."""
    lib = load_library(path)
    entry = _material_entry(lib, name)
    return [
        (f.material, _index_at(lib.materials[f.material], f.material, wavelength), f)
        for f in entry.films
    ]
