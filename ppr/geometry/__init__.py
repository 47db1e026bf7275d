"""Geometry: triangle meshes and their kernel arrays, rotations, parametric shapes, mesh
symmetries and ray-cast visibility."""
