"""Height maps as surfaces: cleaning (`filtering`), today's areal roughness and fracture metrics
(`roughness`) and profiles (`profiles`); and the ISO surface-texture chain: form removal
(`form_removal`), S- and L-filters (`iso_filters`, ISO 16610), areal and profile parameters
(`areal_parameters`, ISO 25178-2; `profile_parameters`, ISO 21920-2), scaling analysis
(`scaling`) and uncertainty propagation (`uncertainty`). Micrometres throughout."""
