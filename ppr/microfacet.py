"""Blinn-Phong microfacet lobe: NDF, lobe averages and visibility
(see :mod:`ppr.brdf._microfacet`)."""

from .brdf._microfacet import (
    DEFAULT_ORDER,
    DEFAULT_ORDER_F32,
    joint_visibility,
    mean_cosine_n,
    mean_cosine_plus,
    ndf,
    visibility,
)

__all__ = [
    "DEFAULT_ORDER",
    "DEFAULT_ORDER_F32",
    "ndf",
    "mean_cosine_n",
    "mean_cosine_plus",
    "visibility",
    "joint_visibility",
]
