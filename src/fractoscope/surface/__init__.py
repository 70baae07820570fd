"""Height maps as surfaces: cleaning (`filtering`), areal roughness and fracture metrics
(`roughness`) and profiles (`profiles`)."""
