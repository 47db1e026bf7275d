"""Blinn-Phong microfacet lobe: NDF, lobe averages and visibility (implemented in
:mod:`ppr.brdf._microfacet`, whose docstring holds the formulas).

The kernel's knobs are public too, for benches and accuracy studies: ``TABLE_NODES`` and
:func:`visibility_one_material` (the per-call tabulated correction of the float32 BRDF), and
``NODE_AXIS_MAX`` / ``NODE_AXIS_PARTIALS`` / ``COMPACT_MIN`` (how the ``<h.k>+`` quadrature is
laid out and compacted)."""

from .brdf._microfacet import (
    COMPACT_MIN,
    DEFAULT_ORDER,
    DEFAULT_ORDER_F32,
    NODE_AXIS_MAX,
    NODE_AXIS_PARTIALS,
    TABLE_NODES,
    joint_visibility,
    mean_cosine_n,
    mean_cosine_plus,
    ndf,
    visibility,
    visibility_one_material,
)

__all__ = [
    "COMPACT_MIN",
    "DEFAULT_ORDER",
    "DEFAULT_ORDER_F32",
    "NODE_AXIS_MAX",
    "NODE_AXIS_PARTIALS",
    "TABLE_NODES",
    "ndf",
    "mean_cosine_n",
    "mean_cosine_plus",
    "visibility",
    "visibility_one_material",
    "joint_visibility",
]
