"""Materials: the :class:`Material` pytree (complex index, roughness exponent, correlation
length), :func:`stack_materials` (one batched material per mesh part) and the sourced material
library (``configs/materials.toml``: :func:`load_material`, :func:`material_names`,
:func:`finish_names`, :func:`load_library`)."""

from ._library import finish_names, load_library, load_material, material_names
from ._material import Material, film_fit_layers, stack_materials

__all__ = [
    "Material",
    "film_fit_layers",
    "finish_names",
    "load_library",
    "load_material",
    "material_names",
    "stack_materials",
]
