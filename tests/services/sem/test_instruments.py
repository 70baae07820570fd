"""Instrument profiles (issue 46): what the files name keys a profile, a profile applies at its own
scan rotation only, and the detector's place comes from a request, a profile, or nowhere."""

import json
import math

import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import read_sem_image
from fractoscope.sem.instruments import InstrumentProfile, detector_place, load_profiles, profiles_path, save_profile
from fractoscope.sem.metadata import InstrumentKey, detector_has_side
from fractoscope.synthetic.files import fei_tiff

ETD = InstrumentKey("FEI/Thermo Fisher", "Quanta 250 FEG", "ETD", 0.0)


def test_the_files_name_their_instrument_detector_and_scan_rotation(pollen_series):
    import numpy as np

    fei = read_sem_image(
        fei_tiff(np.zeros((64, 80), np.uint8) + 7, tilt_deg=-5.0, pixel_size_um=0.1, scan_rotation_deg=30)
    )
    assert fei.instrument == InstrumentKey("FEI/Thermo Fisher", "Quanta 250 FEG", "ETD", 30.0)
    zeiss = read_sem_image((pollen_series / "pot_02.tif").read_bytes())
    assert zeiss.instrument == InstrumentKey("Zeiss", "Auriga 60", "SE2", 0.0)  # 'Scan Rot' off
    assert zeiss.acquired_at == "2016-03-08T10:39:14" and fei.acquired_at == "2016-03-08T10:39:14"


@pytest.mark.parametrize(
    ("name", "side"), [("SE2", True), ("ETD", True), ("InLens", False), ("TLD", False), ("BSD", None), ("", None)]
)
def test_the_detectors_name_tells_whether_it_has_a_side(name, side):
    assert detector_has_side(name) is side


def test_a_profile_is_saved_replaced_and_loaded(tmp_path):
    path = tmp_path / "config" / "instruments.json"
    save_profile(path, InstrumentProfile(ETD, 100.0, 5.0, "a.tif, b.tif", "2026-12-07"))
    save_profile(path, InstrumentProfile(ETD, 110.0, 4.0, "c.tif, d.tif", "2026-12-08"))  # the same instrument
    rotated = InstrumentKey(ETD.vendor, ETD.model, ETD.detector, 45.0)
    profiles = save_profile(path, InstrumentProfile(rotated, 20.0, 6.0))
    assert load_profiles(path) == profiles and len(profiles) == 2
    assert [p.detector_from_tilt_axis_deg for p in profiles] == [110.0, 20.0]
    assert load_profiles(tmp_path / "absent.json") == ()


def test_a_broken_profile_file_is_refused_naming_it(tmp_path):
    path = tmp_path / "instruments.json"
    path.write_text(json.dumps({"profiles": [{"vendor": "Zeiss"}]}))
    with pytest.raises(InvalidInputError, match="instruments.json is not an instrument profile file"):
        load_profiles(path)


def test_the_profile_file_is_found_from_the_environment(tmp_path):
    assert profiles_path({"FRACTO_INSTRUMENTS": str(tmp_path / "x.json")}) == tmp_path / "x.json"
    assert profiles_path({"XDG_CONFIG_HOME": str(tmp_path)}) == tmp_path / "fractoscope" / "instruments.json"


def test_the_detectors_place_comes_from_the_request_then_a_profile_then_nowhere():
    profile = InstrumentProfile(ETD, 100.0, 5.0)
    assert detector_place([ETD, ETD], 30.0, [profile]).source == "given"
    applied = detector_place([ETD, ETD], math.nan, [profile])
    assert (applied.source, applied.from_tilt_axis_deg, applied.profile) == ("profile", 100.0, profile.name)
    elsewhere = detector_place([InstrumentKey(ETD.vendor, ETD.model, "ETD", 30.0)] * 2, math.nan, [profile])
    assert elsewhere.source == "unknown" and "scan rotation 0°, not these images' 30°" in elsewhere.note
    in_lens = InstrumentKey("Zeiss", "Auriga 60", "InLens", 0.0)
    assert detector_place([in_lens, in_lens], math.nan, [profile]).source == "in-lens"
    assert detector_place([None, None], math.nan, [profile]).source == "unknown"
    mixed = detector_place([ETD, in_lens], math.nan, [profile])
    assert mixed.source == "unknown" and "different instruments" in mixed.note
