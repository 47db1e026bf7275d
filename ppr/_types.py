"""Shape/dtype aliases used in jaxtyping annotations across ppr and inversion."""

from jaxtyping import Array, ArrayLike, Bool, Complex, Float, Int, Shaped

Scalar = Float[Array, ""]
ScalarLike = Float[ArrayLike, ""] | float
Vec3 = Float[Array, "*batch 3"]
Mueller = Float[Array, "*batch 4 4"]
Stokes = Float[Array, "*batch 4"]
Jones = Complex[Array, "*batch 2 2"]
Vertices = Float[Array, "V 3"]
Faces = Int[Array, "F 3"]
FaceMask = Bool[Array, "F"]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Complex",
    "Float",
    "Int",
    "Shaped",
    "Scalar",
    "ScalarLike",
    "Vec3",
    "Mueller",
    "Stokes",
    "Jones",
    "Vertices",
    "Faces",
    "FaceMask",
]
