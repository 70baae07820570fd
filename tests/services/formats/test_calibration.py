"""The calibration record read from a matching report: each value's source and sigma."""

from __future__ import annotations

import math

from fractoscope.formats.calibration import Calibration


def test_nominal_tilts_carry_the_nominal_uncertainty_and_their_sources():
    report = {
        "tilt_deg": [-5.0, 5.0],
        "tilt_source": ["argument", "metadata"],
        "pixel_size_um": 0.1,
        "pixel_size_source": "metadata",
        "parameters": {"tilt_uncertainty_deg": 0.5},
        "tilt_sigma_deg": [],
    }
    calibration = Calibration.from_report(report)
    assert calibration.tilt_sigma_deg == (0.5, 0.5) and calibration.tilt_source == ("argument", "metadata")
    assert not calibration.tilt_calibrated and calibration.pixel_size_source == "metadata"


def test_calibrated_tilts_carry_the_calibration_sigma():
    report = {
        "tilt_deg": [-5.0, 0.1, 5.2],
        "tilt_source": ["metadata", "tilt_calibration", "tilt_calibration"],
        "tilt_sigma_deg": [0.0, 0.02, 0.03],
        "pixel_size_um": 0.1,
        "pixel_size_source": "argument",
        "parameters": {"tilt_uncertainty_deg": 0.5},
    }
    calibration = Calibration.from_report(report)
    assert calibration.tilt_calibrated and calibration.tilt_sigma_deg == (0.5, 0.02, 0.03)


def test_a_report_without_sources_gives_no_calibration():
    assert Calibration.from_report({"tilt_deg": [-5.0, 5.0], "pixel_size_um": 0.1}) is None
    unknown_sigma = Calibration.from_report(
        {
            "tilt_deg": [-5.0, 5.0],
            "tilt_source": ["metadata"] * 2,
            "pixel_size_um": 0.1,
            "pixel_size_source": "metadata",
        }
    )
    assert all(math.isnan(s) for s in unknown_sigma.tilt_sigma_deg)


def test_a_calibration_reads_back_from_the_report_it_states():
    calibration = Calibration(
        (-5.0, 0.0, 5.0), ("argument", "tilt_calibration", "tilt_calibration"), (0.5, 0.03, 0.04), 0.2, "metadata"
    )
    assert Calibration.from_report(calibration.to_report()) == calibration
