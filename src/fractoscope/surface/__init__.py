"""The ISO surface-texture chain for height maps: form removal (``form_removal``), S- and L-filters
(``iso_filters``, ISO 16610), areal and profile parameters (``areal_parameters``, ISO 25178-2;
``profile_parameters``, ISO 21920-2), scaling analysis (``scaling``) and uncertainty propagation
(``uncertainty``). Pure numpy/scipy: arrays in, arrays and dicts out, micrometres throughout."""
