"""The nominal magnification from Zeiss metadata, which makes "zoom" by magnification work."""

import pytest

from fractoscope.sem.image import nominal_magnification
from fractoscope.sem.metadata import zeiss_magnification


@pytest.mark.parametrize(
    "text, expected", [("1.00 K X", 1000.0), ("250 X", 250.0), ("1.5 M X", 1.5e6), ("12.34 kX", 12340.0)]
)
def test_zeiss_magnification_strings(text, expected):
    assert zeiss_magnification({"ap_mag": ("Mag", text)}) == pytest.approx(expected)


def test_absent_or_unreadable_magnifications_are_none():
    assert zeiss_magnification({}) is None
    assert zeiss_magnification({"ap_mag": ("Mag", "high")}) is None
    assert nominal_magnification(b"\x89PNG\r\n\x1a\n not a TIFF") is None


@pytest.mark.real_data
def test_the_pollen_series_states_1000x(pollen_series):
    assert nominal_magnification((pollen_series / "pot_02.tif").read_bytes()) == 1000.0
