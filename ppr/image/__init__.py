"""Polarimetric images of a mesh (per-pixel Mueller matrices)."""
