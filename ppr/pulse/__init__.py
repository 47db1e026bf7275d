"""Range-resolved pulses: scenes, sensors and poses, the facet-sum pulse synthesis and the
macro double bounce between a mesh's surfaces."""
