"""Numbers for people: an uncertainty's two significant digits set the value's, and a unit follows."""

import pytest

from fractoscope.numbers import decimals_for, measured, uncertainty_text, value_text, with_uncertainty


@pytest.mark.parametrize(
    ("value", "uncertainty", "unit", "text"),
    [
        (16.115, 1.62, "µm", "16.1 ± 1.6 µm"),  # the report once wrote 16.115 ± 1.6
        (31.2234, 0.00089, "%", "31.22340 ± 0.00089 %"),  # and 31.22 ± 0.00089
        (5.0, 0.0996, "µm", "5.00 ± 0.10 µm"),  # 0.0996 rounds to 0.10: still two digits
        (1234.5, 150.0, "µm", "1230 ± 150 µm"),
        (-0.0001, 0.02, "µm", "0.000 ± 0.020 µm"),  # never "-0.000"
        (0.9063, 0.0014, "1", "0.9063 ± 0.0014 1"),  # a dimensionless quantity keeps its unit 1
        (2.5, None, "µm", "2.50 µm"),  # no uncertainty: three significant digits
        (None, 0.1, "µm", "n/a µm"),
    ],
)
def test_digits_follow_the_uncertainty(value, uncertainty, unit, text):
    assert with_uncertainty(value, uncertainty, unit) == text


def test_the_parts_of_a_table_agree_with_the_whole():
    assert value_text(16.115, 1.62) + " ± " + uncertainty_text(1.62) + " µm" == with_uncertainty(16.115, 1.62, "µm")
    assert uncertainty_text(None) == "—" and value_text(float("nan"), 1.0) == "n/a"
    assert measured(5683.2, "1/µm") == "5680 1/µm" and measured(0.0, "µm") == "0 µm"
    assert decimals_for(0.00089) == 5 and decimals_for(1.6) == 1 and decimals_for(150) == -1
