"""Height maps as surfaces: cleaning (`filtering`), profile sampling (`profiles`), and the ISO
surface-texture chain that every roughness and profile query runs (`roughness`): form removal
(`form_removal`), S- and L-filters (`iso_filters`, ISO 16610), areal and profile parameters
(`areal_parameters`, ISO 25178-2; `profile_parameters`, ISO 21920-2), scaling analysis
(`scaling`) and uncertainty propagation (`uncertainty`). Micrometres throughout."""

__all__ = [
    "areal_parameters",
    "datum",
    "filtering",
    "form_removal",
    "iso_filters",
    "profile_parameters",
    "profiles",
    "roughness",
    "scaling",
    "uncertainty",
]
