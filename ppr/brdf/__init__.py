"""The polarized microfacet BRDF: single, double and multiple-scattering terms, the
Blinn-Phong lobe (:mod:`ppr.microfacet`), the exact-backscatter tables of the double term and
the albedo tables of the multiple-scattering term.

Public door of the subpackage: :func:`mueller_brdf` and its unchecked twin
:func:`mueller_brdf_unchecked` (no traced checks: for kernels whose inputs are valid by
construction), the term functions and their registry, and three modules for benches and the
table-regeneration scripts: :mod:`albedo` (white-surface albedo tables: ``albedo_nodes``,
``grid_nodes``, ``build_table``, ``save_table``, ``load_table``, ``deficit``),
:mod:`double` (the double-bounce quadrature: ``double_bounce_term``, ``coherence_factor``,
``DEFAULT_ORDER``, ``INNER_ORDER``, the ``terms="auto"`` rule ``AUTO_*``) and
:mod:`double_table` (its exact-backscatter tables: ``build_table``, ``save_table``,
``load_table``, ``double_backscatter_term``, ``PSI_MAX``).
"""

from . import albedo, double, double_table
from ._brdf import (
    TERMS,
    explicit_terms,
    implemented_terms,
    mueller_brdf,
    mueller_brdf_unchecked,
    multiple_scattering_term,
    single_bounce_term,
)
from ._sampling import bistatic_geometry
from .double import coherence_factor, double_bounce_term
from .double_table import PSI_MAX as BACKSCATTER_PSI_MAX
from .double_table import double_bounce_term_auto, double_term_dispatch

__all__ = [
    "BACKSCATTER_PSI_MAX",
    "TERMS",
    "albedo",
    "bistatic_geometry",
    "coherence_factor",
    "double",
    "double_bounce_term",
    "double_bounce_term_auto",
    "double_table",
    "double_term_dispatch",
    "explicit_terms",
    "implemented_terms",
    "mueller_brdf",
    "mueller_brdf_unchecked",
    "multiple_scattering_term",
    "single_bounce_term",
]
