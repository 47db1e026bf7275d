"""The polarized microfacet BRDF: single, double and multiple-scattering terms, the
Blinn-Phong lobe, the exact-backscatter tables of the double term and the albedo tables."""
