"""Conversions between plain values (numpy arrays, report dicts, regions, roughness and profile
parameters by their ISO names) and the messages of the fractoscope.v1 API. Numpy and protobuf
only: both ends of the wire use them."""

from __future__ import annotations

from pathlib import PurePath

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.v1 import common_pb2, matching_pb2, tiles_pb2

_DTYPES = {
    common_pb2.DATA_TYPE_FLOAT32: np.dtype("<f4"),
    common_pb2.DATA_TYPE_UINT8: np.dtype("u1"),
    common_pb2.DATA_TYPE_UINT16: np.dtype("<u2"),
}
_DATA_TYPES = {dtype: code for code, dtype in _DTYPES.items()}


def fill_raster(raster: common_pb2.Raster, values: np.ndarray) -> None:
    """Writes a (rows, cols) float32, uint8 or uint16 array into `raster`, a field of the message
    being built. Filling it in place matters: nesting a finished message copies it, which for a
    4096² height map costs about a second."""
    if values.dtype.kind == "f":
        values = values.astype("<f4")
    dtype = np.dtype(values.dtype).newbyteorder("<") if values.dtype.itemsize > 1 else values.dtype
    code = _DATA_TYPES.get(dtype)
    if code is None or values.ndim != 2:
        raise ValueError(f"cannot encode a {values.ndim}D {values.dtype} array as a raster")
    raster.rows, raster.cols = values.shape
    raster.data_type = code
    raster.data = np.ascontiguousarray(values, dtype).tobytes()


def raster_to_array(raster: common_pb2.Raster, *, field: str = "raster") -> np.ndarray:
    """Raster message to a (rows, cols) array, validating sizes."""
    dtype = _DTYPES.get(raster.data_type)
    if dtype is None:
        raise InvalidInputError(f"{field}.data_type", "must be FLOAT32, UINT8 or UINT16")
    if raster.rows <= 0 or raster.cols <= 0:
        raise InvalidInputError(
            field, f"rows and cols must be positive, got {raster.cols} x {raster.rows} (cols x rows)"
        )
    expected = raster.rows * raster.cols * dtype.itemsize
    if len(raster.data) != expected:
        raise InvalidInputError(f"{field}.data", f"holds {len(raster.data)} bytes, expected {expected}")
    return np.frombuffer(raster.data, dtype).reshape(raster.rows, raster.cols)


REPORT_FIELDS = [field.name for field in matching_pb2.MatchingReport.DESCRIPTOR.fields]
_REPEATED_REPORT_FIELDS = {field.name for field in matching_pb2.MatchingReport.DESCRIPTOR.fields if field.is_repeated}
_MESSAGE_REPORT_FIELDS = {
    field.name for field in matching_pb2.MatchingReport.DESCRIPTOR.fields if field.message_type is not None
}


def report_to_message(report: dict) -> matching_pb2.MatchingReport:
    """The `report` dict of a height map (keys as in MatchingReport; `parameters` a dict of
    MatchingParameters fields) to its message."""
    fields = {key: report[key] for key in REPORT_FIELDS if key in report}
    if "parameters" in fields:
        parameters = dict(fields["parameters"])
        if report.get("method"):  # the parameters as used name the method run
            parameters["method"] = method_code(report["method"])
        if isinstance(parameters.get("relief_sign"), str):
            parameters["relief_sign"] = relief_sign_code(parameters["relief_sign"])
        fields["parameters"] = parameters
    return matching_pb2.MatchingReport(**fields)


def _enum_names(enum, prefix: str) -> tuple[str, ...]:
    """The names of an API enum's values (UNSPECIFIED aside), in its order, without `prefix`, in
    lower case: how the core, the CLI and the HTTP API name them."""
    return tuple(name.removeprefix(prefix).lower() for name, code in enum.items() if code)


_RELIEF_SIGN_PREFIX = "RELIEF_SIGN_MODE_"


def relief_sign_code(mode: str) -> int:
    """The ReliefSignMode value of a mode's name (one of relief_sign_names()); ValueError for another."""
    return matching_pb2.ReliefSignMode.Value(f"{_RELIEF_SIGN_PREFIX}{mode.upper()}")


def relief_sign_name(code: int) -> str:
    """A ReliefSignMode value's name ("auto" for UNSPECIFIED); ValueError for an unknown value."""
    name = matching_pb2.ReliefSignMode.Name(code or matching_pb2.RELIEF_SIGN_MODE_AUTO)
    return name.removeprefix(_RELIEF_SIGN_PREFIX).lower()


def relief_sign_names() -> tuple[str, ...]:
    """The relief sign modes' names the API knows, in the enum's order: ("auto", "nominal", "inverted")."""
    return _enum_names(matching_pb2.ReliefSignMode, _RELIEF_SIGN_PREFIX)


_METHOD_PREFIX = "MATCHING_METHOD_"


def method_code(method: str) -> int:
    """The MatchingMethod enum value of a matching method's name ("tgv_zncc": MATCHING_METHOD_TGV_ZNCC,
    "fast": MATCHING_METHOD_FAST); ValueError for a name the API does not know."""
    return matching_pb2.MatchingMethod.Value(f"{_METHOD_PREFIX}{method.upper()}")


def method_name(code: int) -> str:
    """A MatchingMethod value's name ("fast" for MATCHING_METHOD_FAST); ValueError for UNSPECIFIED
    or an unknown value."""
    if code == matching_pb2.MATCHING_METHOD_UNSPECIFIED:
        raise ValueError("MATCHING_METHOD_UNSPECIFIED names no method")
    return matching_pb2.MatchingMethod.Name(code).removeprefix(_METHOD_PREFIX).lower()


def method_names() -> tuple[str, ...]:
    """The matching methods' names the API knows, in the enum's order: ("tgv_zncc", "window_zncc", "fast")."""
    return _enum_names(matching_pb2.MatchingMethod, _METHOD_PREFIX)


def message_to_report(message: matching_pb2.MatchingReport) -> dict:
    """A MatchingReport message to a plain dict (lists for repeated fields, dicts of every field for
    messages), ready for JSON."""
    report = {}
    for key in REPORT_FIELDS:
        value = getattr(message, key)
        if key in _REPEATED_REPORT_FIELDS:
            value = list(value)
        elif key in _MESSAGE_REPORT_FIELDS:
            value = {field.name: getattr(value, field.name) for field in value.DESCRIPTOR.fields}
        report[key] = value
    return report


Region = tuple[float, float, float, float]


def region_message(region_um: Region) -> tiles_pb2.RegionUm:
    """(x_min, y_min, x_max, y_max) µm to a RegionUm."""
    x0, y0, x1, y1 = region_um
    return tiles_pb2.RegionUm(min=common_pb2.PointUm(x_um=x0, y_um=y0), max=common_pb2.PointUm(x_um=x1, y_um=y1))


def message_to_region(message: tiles_pb2.RegionUm) -> Region:
    """A RegionUm to (x_min, y_min, x_max, y_max) µm, unchecked."""
    return message.min.x_um, message.min.y_um, message.max.x_um, message.max.y_um


# The screen width StreamView assumes when a request leaves it out, pixels.
DEFAULT_VIEWPORT_PX = 1024

# Optical: the tile's data is measured at its resolution; digital: coarser data upsampled.
ZOOM_KINDS = {"optical": tiles_pb2.ZOOM_KIND_OPTICAL, "digital": tiles_pb2.ZOOM_KIND_DIGITAL}
_ZOOM_NAMES = {kind: name for name, kind in ZOOM_KINDS.items()}


def zoom_name(kind: int) -> str:
    return _ZOOM_NAMES.get(kind, "unknown")


# The forms of SurfaceChain by the names the analysis modules use ("none", "plane", "poly2", ...).
FORMS = {
    name[len("FORM_") :].lower(): value for name, value in tiles_pb2.Form.items() if value != tiles_pb2.FORM_UNSPECIFIED
}
_FORM_NAMES = {value: name for name, value in FORMS.items()} | {tiles_pb2.FORM_UNSPECIFIED: "plane"}
HURST_METHODS = {"hhc": tiles_pb2.HURST_METHOD_HEIGHT_HEIGHT_CORRELATION, "psd": tiles_pb2.HURST_METHOD_POWER_SPECTRUM}
_HURST_METHOD_NAMES = {value: name for name, value in HURST_METHODS.items()}
# The fields of SurfaceChain, the one list of the chain's settings: by these names requests,
# the HTTP API's query parameters and the CLI's flags give them; the numbers among them.
CHAIN_FIELDS = tuple(tiles_pb2.SurfaceChain.DESCRIPTOR.fields_by_name)
_CHAIN_NUMBERS = tuple(
    field.name for field in tiles_pb2.SurfaceChain.DESCRIPTOR.fields if field.type == field.TYPE_DOUBLE
)


def chain_message(
    *, form: str | None = None, levelling_region_um: Region | None = None, **settings: float | bool | None
) -> tiles_pb2.SurfaceChain:
    """A SurfaceChain with the given settings, the keywords of queries.ChainRequest: `form` by
    name, the levelling region (x0, y0, x1, y1) µm, and the other fields of SurfaceChain by their
    names (s_filter_um, ..., robust_form); None leaves a setting at its default."""
    if form is not None and form not in FORMS:
        raise InvalidInputError("chain.form", f"must be one of {', '.join(FORMS)}, not {form!r}")
    message = tiles_pb2.SurfaceChain(form=FORMS[form] if form else tiles_pb2.FORM_UNSPECIFIED)
    for name, value in settings.items():
        if name not in CHAIN_FIELDS or name in ("form", "levelling_region"):
            raise TypeError(f"chain_message() got an unexpected keyword argument {name!r}")
        if value is not None:
            setattr(message, name, value)
    if levelling_region_um is not None:
        message.levelling_region.CopyFrom(region_message(levelling_region_um))
    return message


def form_name(kind: int) -> str:
    return _FORM_NAMES.get(kind, "unknown")


def chain_to_dict(message: tiles_pb2.SurfaceChain) -> dict:
    """A response's SurfaceChain as {"form": name, each number or None, "levelling_region_um":
    [x0, y0, x1, y1] or None, "robust_form"}."""
    values = {"form": form_name(message.form)}
    values |= {name: getattr(message, name) if message.HasField(name) else None for name in _CHAIN_NUMBERS}
    values["levelling_region_um"] = (
        list(message_to_region(message.levelling_region)) if message.HasField("levelling_region") else None
    )
    values["robust_form"] = message.robust_form
    return values


def _number(value: float) -> float | None:
    """NaN (unknown) as None, which JSON can carry."""
    return None if value != value else value


# ISO names of the parameters (as the analysis modules return them) and their message fields.
_ROUGHNESS_FIELDS = {
    "Sa": "sa_um",
    "Sq": "sq_um",
    "Ssk": "ssk",
    "Sku": "sku",
    "Sp": "sp_um",
    "Sv": "sv_um",
    "Sz": "sz_um",
    "Sdq": "sdq",
    "Sdr": "sdr_percent",
}
_HURST_FIELDS = ("hurst_exponent", "hurst_fit_min_um", "hurst_fit_max_um", "fractal_dimension")
_PROFILE_FIELDS = {
    "Ra": "ra_um",
    "Rq": "rq_um",
    "Rz": "rz_um",
    "Rsk": "rsk",
    "Rku": "rku",
    "Rp": "rp_um",
    "Rv": "rv_um",
    "Rt": "rt_um",
    "Rdq": "rdq",
    "RSm": "rsm_um",
    "Rk": "rk_um",
    "Rpk": "rpk_um",
    "Rvk": "rvk_um",
    "Rmr1": "rmr1_percent",
    "Rmr2": "rmr2_percent",
}


def values_to_roughness_response(values: dict) -> tiles_pb2.GetRoughnessResponse:
    """The legacy scalars (Sa ... Sdr by ISO name, the Hurst fields) and the height-height curve
    of a roughness result into a response; the rest is filled by its builder (tiles.messages)."""
    response = tiles_pb2.GetRoughnessResponse(**{_ROUGHNESS_FIELDS[name]: values[name] for name in _ROUGHNESS_FIELDS})
    for name in _HURST_FIELDS:
        setattr(response, name, values[name])
    response.hhc_lag_um.extend(values.get("hhc_lag_um", []))
    response.hhc_rms_um.extend(values.get("hhc_rms_um", []))
    return response


def response_to_roughness(response: tiles_pb2.GetRoughnessResponse) -> dict:
    """A GetRoughnessResponse as plain values: every areal parameter by ISO name (its unit in
    "units", its uncertainty in "uncertainty": {name: {"u_total", "u_tilt", "u_noise"}}), the
    legacy Hurst keys, "chain", "pixel_size_um", "noise_bias" {"Sa", "Sq"}, "tilt_rel_uncertainty",
    "hurst" (one dict per fit: method "hhc" or "psd", side "along" or "across", direction_deg,
    hurst, hurst_stderr, fit_min_um, fit_max_um, fit_min_windows, scale_um, value, in_fit,
    not_determinable: why H is not determinable, "" when it is),
    "hurst_note", "psd" {"q_per_um", "c_um4"}, "coverage" {"measured_fraction",
    "filled_fraction", "unknown_fraction"} (None: not told) and "caveats" (lines). Unknown numbers
    are None."""
    values = {name: _number(getattr(response, field)) for name, field in _ROUGHNESS_FIELDS.items()}
    values |= {parameter.name: _number(parameter.value) for parameter in response.parameters}
    values |= {name: _number(getattr(response, name)) for name in _HURST_FIELDS}
    values["hhc_lag_um"], values["hhc_rms_um"] = list(response.hhc_lag_um), list(response.hhc_rms_um)
    values["units"] = {parameter.name: parameter.unit for parameter in response.parameters}
    values["uncertainty"] = {
        p.name: {"u_total": _number(p.u_total), "u_tilt": _number(p.u_tilt), "u_noise": _number(p.u_noise)}
        for p in response.parameters
    }
    values["chain"] = chain_to_dict(response.chain)
    values["pixel_size_um"] = response.pixel_size_um
    values["noise_bias"] = {"Sa": _number(response.sa_noise_bias_um), "Sq": _number(response.sq_noise_bias_um)}
    values["tilt_rel_uncertainty"] = _number(response.tilt_rel_uncertainty)
    values["hurst"] = [
        {
            "method": _HURST_METHOD_NAMES.get(fit.method, "unknown"),
            "side": "across" if fit.across else "along",
            "direction_deg": fit.direction_deg,
            "hurst": fit.hurst,
            "hurst_stderr": fit.hurst_stderr,
            "fit_min_um": fit.fit_min_um,
            "fit_max_um": fit.fit_max_um,
            "fit_min_windows": fit.fit_min_windows,
            "scale_um": list(fit.scale_um),
            "value": [_number(v) for v in fit.value],
            "in_fit": list(fit.in_fit),
            "not_determinable": fit.not_determinable,
        }
        for fit in response.hurst_fits
    ]
    values["hurst_note"] = response.hurst_note
    values["psd"] = {"q_per_um": list(response.psd_q_per_um), "c_um4": [_number(v) for v in response.psd_um4]}
    values["coverage"] = (
        {
            name: getattr(response.coverage, name)
            for name in ("measured_fraction", "filled_fraction", "unknown_fraction")
        }
        if response.HasField("coverage")
        else None
    )
    values["caveats"] = list(response.caveats)
    return values


_EXPORT_PREFIX = "EXPORT_FORMAT_"
_EXPORT_KEYS = [name.removeprefix(_EXPORT_PREFIX) for name, code in tiles_pb2.ExportFormat.items() if code]
# Export formats by name, as formats.exports names them and file extensions say: the API's
# ExportFormat names in lower case, where the usual extension is not that (TIFF's), the extension.
EXPORT_FORMATS = {
    {"TIFF": "tif"}.get(key, key.lower()): tiles_pb2.ExportFormat.Value(_EXPORT_PREFIX + key) for key in _EXPORT_KEYS
}
_EXPORT_NAMES = {code: name for name, code in EXPORT_FORMATS.items()}
LENGTH_UNITS = {"um": tiles_pb2.LENGTH_UNIT_MICROMETRE, "mm": tiles_pb2.LENGTH_UNIT_MILLIMETRE}
_UNIT_NAMES = {code: name for name, code in LENGTH_UNITS.items()} | {tiles_pb2.LENGTH_UNIT_UNSPECIFIED: "um"}
REPORT_FORMATS = {"html": tiles_pb2.REPORT_FORMAT_HTML, "pdf": tiles_pb2.REPORT_FORMAT_PDF}
_REPORT_NAMES = {code: name for name, code in REPORT_FORMATS.items()} | {tiles_pb2.REPORT_FORMAT_UNSPECIFIED: "html"}


def export_format_of(path: str) -> str:
    """The export format a file name asks for by its extension (.tiff is tif)."""
    suffix = PurePath(path).suffix.lower().lstrip(".")
    name = "tif" if suffix == "tiff" else suffix
    if name not in EXPORT_FORMATS:
        raise InvalidInputError(
            "output",
            f"extension {'.' + suffix if suffix else '(none)'} is none of "
            f"{', '.join('.' + n for n in EXPORT_FORMATS)} (.tiff too)",
        )
    return name


def export_format_name(code: int) -> str:
    if code not in _EXPORT_NAMES:
        raise InvalidInputError("format", f"must be one of {_EXPORT_PREFIX}{', _'.join(_EXPORT_KEYS)}")
    return _EXPORT_NAMES[code]


def length_unit_name(code: int) -> str:
    if code not in _UNIT_NAMES:
        raise InvalidInputError("units", "must be LENGTH_UNIT_MICROMETRE or LENGTH_UNIT_MILLIMETRE")
    return _UNIT_NAMES[code]


def report_format_name(code: int) -> str:
    if code not in _REPORT_NAMES:
        raise InvalidInputError("format", "must be REPORT_FORMAT_HTML or REPORT_FORMAT_PDF")
    return _REPORT_NAMES[code]


def specimen_area(
    specimen_id: str, *, roi: str | None = None, region_um: Region | None = None
) -> tiles_pb2.SpecimenArea:
    """A SpecimenArea: an ROI, a region (x0, y0, x1, y1) µm, or neither (the overview)."""
    area = tiles_pb2.SpecimenArea(specimen_id=specimen_id)
    if region_um is not None:
        area.region.CopyFrom(region_message(region_um))
    elif roi is not None:
        area.roi = roi
    return area


def profile_parameters_message(values: dict) -> tiles_pb2.ProfileParameters:
    """ISO 21920-2 profile parameters by ISO name (Ra ... Rmr2) to their message."""
    return tiles_pb2.ProfileParameters(**{field: values[name] for name, field in _PROFILE_FIELDS.items()})


def profile_unit(name: str) -> str:
    """The unit of a profile parameter by ISO name ("Ra" -> "µm", "Rmr1" -> "%", "Rsk" -> "1"), as
    its message field's name says it."""
    field = _PROFILE_FIELDS[name]
    return "µm" if field.endswith("_um") else "%" if field.endswith("_percent") else "1"


def message_to_profile_parameters(message: tiles_pb2.ProfileParameters) -> dict:
    return {name: _number(getattr(message, field)) for name, field in _PROFILE_FIELDS.items()}
