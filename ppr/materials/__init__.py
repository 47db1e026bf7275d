"""Materials: the `Material` pytree (complex index, roughness exponent, correlation length)
and the sourced material library (`configs/materials.toml`)."""
