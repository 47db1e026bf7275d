"""ppr: Pulse Polarization Ranging in JAX.

Polarized microfacet BRDF (Blinn-Phong normals, Ashikhmin shadowing, complex Fresnel as
Mueller matrices, double bounce with coherent enhanced backscatter, depolarizing multiple
scattering) and facet-sum pulse synthesis over triangle meshes.

Conventions (directions, frames, Stokes handedness, complex index sign, units) are fixed in
:mod:`ppr._conventions`. The library never enables ``jax_enable_x64``; dtypes follow inputs.
"""

from ._material import Material

__all__ = ["Material"]
__version__ = "0.1.0"
