"""Measured numbers as Fractoscope writes them for people (the command line, the report; the
viewer's measure.js follows the same rule): the uncertainty with two significant digits, the
value to the same decimal place, and the unit.

    with_uncertainty(16.115, 1.62, "µm") == "16.1 ± 1.6 µm"
    with_uncertainty(31.2234, 0.00089, "%") == "31.22340 ± 0.00089 %"
    measured(0.66348, "µm") == "0.663 µm"  (no uncertainty known: three significant digits)

A dimensionless quantity has the unit "1" (ISO 80000-1), which is written as such: a number
without a unit is never printed.
"""

from __future__ import annotations

import math

UNCERTAINTY_DIGITS = 2  # significant digits of an uncertainty (GUM 7.2.6: at most two)
UNKNOWN_UNCERTAINTY_DIGITS = 3  # significant digits of a value whose uncertainty is not known
_MAX_DECIMALS = 12


def decimals_for(uncertainty: float, digits: int = UNCERTAINTY_DIGITS) -> int:
    """The decimal places at which `uncertainty` (> 0) shows `digits` significant digits (negative:
    tens, hundreds, ...)."""
    exponent = math.floor(math.log10(abs(uncertainty)))
    rounded = round(abs(uncertainty), digits - 1 - exponent)
    exponent = math.floor(math.log10(rounded)) if rounded > 0 else exponent  # 0.0996 rounds to 0.10
    return min(digits - 1 - exponent, _MAX_DECIMALS)


def with_uncertainty(value: float | None, uncertainty: float | None, unit: str) -> str:
    """ "value ± uncertainty unit", both to the decimal place of the uncertainty's two significant
    digits (see the module's docstring); the value alone (`measured`) when the uncertainty is
    unknown or zero; "n/a unit" when the value is."""
    if value is None or not math.isfinite(value):
        return f"n/a {unit}".rstrip()
    if uncertainty is None or not math.isfinite(uncertainty) or uncertainty <= 0:
        return measured(value, unit)
    places = decimals_for(uncertainty)
    shown = f"{_plain(value, places)} ± {_plain(uncertainty, places)}"
    return f"{shown} {unit}"


def measured(value: float | None, unit: str, *, digits: int = UNKNOWN_UNCERTAINTY_DIGITS) -> str:
    """ "value unit" with `digits` significant digits (no exponent), or "n/a unit"."""
    if value is None or not math.isfinite(value):
        return f"n/a {unit}".rstrip()
    if value == 0:
        return f"0 {unit}"
    return f"{_plain(value, decimals_for(value, digits))} {unit}"


def value_text(value: float | None, uncertainty: float | None) -> str:
    """The value alone as `with_uncertainty` writes it (no unit, no uncertainty): for a table
    whose columns give those."""
    if value is None or not math.isfinite(value):
        return "n/a"
    if uncertainty is None or not math.isfinite(uncertainty) or uncertainty <= 0:
        return measured(value, "").rstrip()
    return _plain(value, decimals_for(uncertainty))


def uncertainty_text(uncertainty: float | None) -> str:
    """An uncertainty alone with two significant digits ("—" when unknown)."""
    if uncertainty is None or not math.isfinite(uncertainty) or uncertainty <= 0:
        return "—"
    return _plain(uncertainty, decimals_for(uncertainty))


def _plain(value: float, places: int) -> str:
    """`value` rounded to `places` decimals (negative: to tens, hundreds, ...) without an exponent,
    never "-0"."""
    text = f"{value:.{places}f}" if places >= 0 else f"{round(value, places):.0f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text
