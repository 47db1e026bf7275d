"""Typed configs: the pydantic base every config schema of ppr and :mod:`inversion` derives
from (:class:`StrictModel`: extra keys forbidden, NaN rejected, deprecated keys renamed with
a warning), TOML loading (:func:`load_toml_model`, :func:`read_toml`), validation of already
parsed data (:func:`validate_data`), :func:`first_nonfinite` (what an error about bad data
names) and :class:`ConfigError` (file, field as written, value in
one line; the ``ppr`` command exits with status 2)."""

from ._config import (
    ConfigDeprecationWarning,
    ConfigError,
    StrictModel,
    first_nonfinite,
    load_toml_model,
    read_toml,
    validate_data,
)

__all__ = [
    "ConfigDeprecationWarning",
    "ConfigError",
    "StrictModel",
    "first_nonfinite",
    "load_toml_model",
    "read_toml",
    "validate_data",
]
