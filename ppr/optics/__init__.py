"""Optics: Fresnel reflection, beam frames and Mueller/Jones rotations, polarimetric
decompositions, and the conventions every module follows (:mod:`ppr.optics.conventions`)."""
