"""The tile service's messages to and from the specimen package's types: stored specimens and
their tiles, ROI specs, checked regions, and the analysis chain's requests and results."""

from __future__ import annotations

import contextlib
import hashlib
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.matching import messages as rpc_matching
from fractoscope.reconstruction.build import RoiRequest, given_child_origin_um, ordered_rois
from fractoscope.rpc import calls, wire
from fractoscope.rpc.calls import CHUNK_BYTES
from fractoscope.rpc.limits import MAX_ROIS
from fractoscope.sem.image import nominal_magnification
from fractoscope.specimen import exports
from fractoscope.specimen.exports import ExportedFile
from fractoscope.specimen.fusion import footprint_um, overlaps
from fractoscope.specimen.model import Specimen
from fractoscope.specimen.quadtree import TileRecord
from fractoscope.specimen.queries import ChainRequest, SpecimenProfile, checked_region
from fractoscope.stereo.geometry import validate_pixel_size_um, validate_tilts
from fractoscope.store.base import StoredSpecimens
from fractoscope.surface.areal_parameters import UNITS
from fractoscope.surface.datum import LEVELS
from fractoscope.surface.roughness import SurfaceAnalysis, SurfaceChain
from fractoscope.units import METRES_PER_UM
from fractoscope.v1 import common_pb2, matching_pb2, tiles_pb2


def specimen_message(specimen: Specimen) -> tiles_pb2.Specimen:
    message = tiles_pb2.Specimen(id=specimen.id, tileset_uri=f"/specimens/{specimen.id}/tileset.json")
    for roi in specimen.rois:
        message.rois.append(
            tiles_pb2.RoiSummary(
                id=roi.id,
                parent=roi.parent,
                magnification=roi.magnification,
                pixel_size_um=roi.pixel_size_um,
                region=wire.region_message(roi.region_um),
                alignment_residual_um=roi.alignment_residual_um,
                matching=wire.report_to_message(roi.matching),
                registration_score=roi.registration_score,
                level=(roi.datum or {}).get("level", ""),
                datum=datum_message(roi.datum),
                coverage=coverage_message(roi.coverage) if roi.coverage else None,
            )
        )
    return message


def datum_message(datum: dict | None) -> tiles_pb2.HeightDatum | None:
    """A stored datum (surface.datum.Datum.to_dict) as its message, None for none; a specimen built
    before datums checked themselves has their plane only. An unknown figure (None) is NaN, or
    absent where the field is optional."""
    if not datum:
        return None
    fields = tiles_pb2.HeightDatum.DESCRIPTOR.fields_by_name
    values = {
        key: math.nan if value is None else value
        for key, value in datum.items()
        if key in fields and not (value is None and fields[key].has_presence)
    }
    return tiles_pb2.HeightDatum(**values)


def with_tile(response, specimen: Specimen, record: TileRecord):
    """`response` (a message with a `tile` field) holding the tile and its GLB. The GLB is set on
    the response's own tile: nesting a filled message copies it, which for a tile of tens of kB
    costs more than the rest of the call."""
    response.tile.CopyFrom(tile_message(specimen, record))
    response.tile.glb = specimen.tile_bytes(record.key.uri)
    return response


def tile_message(specimen: Specimen, record: TileRecord, *, upsampled: bool = False) -> tiles_pb2.Tile:
    """A tile's identity without its GLB (see `with_tile`); `upsampled` marks a tile shown
    beyond its resolution (digital)."""
    zoom = tiles_pb2.ZOOM_KIND_DIGITAL if upsampled else wire.ZOOM_KINDS[record.zoom]
    return tiles_pb2.Tile(
        uri=record.key.uri,
        roi=record.roi,
        magnification=record.magnification,
        zoom=zoom,
        geometric_error_m=record.geometric_error_um * METRES_PER_UM,
    )


def roi_request(spec: tiles_pb2.RoiSpec, index: int) -> RoiRequest:
    """An ROI spec's placement, validated (errors name `rois[index]`'s fields); without a
    magnification, the one its reference image's metadata states."""
    if len(spec.images) < 2:
        raise InvalidInputError(
            f"rois[{index}].images",
            f"an ROI needs a stereo pair or a tilt series of 3 or more images, got {len(spec.images)} images",
        )
    if spec.parameters.calibrate_tilt and len(spec.images) < 3:
        raise InvalidInputError(
            f"rois[{index}].parameters.calibrate_tilt", "tilt calibration needs a series of 3 or more images"
        )
    if spec.HasField("pixel_size_um"):
        validate_pixel_size_um(spec.pixel_size_um, field=f"rois[{index}].pixel_size_um")
    if not (math.isfinite(spec.magnification) and spec.magnification >= 0):
        raise InvalidInputError(f"rois[{index}].magnification", "must be finite and >= 0")
    if spec.level and (spec.level not in LEVELS or spec.parent):
        raise InvalidInputError(
            f"rois[{index}].level", f"must be empty or one of {', '.join(LEVELS)}, and is for the overview only"
        )
    centre = None
    if spec.HasField("center_um"):
        centre = (spec.center_um.x_um, spec.center_um.y_um)
        if not all(math.isfinite(v) for v in centre):
            raise InvalidInputError(f"rois[{index}].center_um", "must be finite")
    magnification = spec.magnification or nominal_magnification(spec.images[0].image.content) or 0.0
    images = tuple((item.image.filename, item.image.content) for item in spec.images)
    return RoiRequest(spec.id, spec.parent, magnification, centre, spec.level, images)


def checked_rois(
    specs: Sequence[tiles_pb2.RoiSpec], request_id: str = ""
) -> tuple[list[RoiRequest], list[matching_pb2.ComputeHeightMapRequest], list[tuple[int, int]]]:
    """A reconstruction's ROIs, their height-map requests and their first images' (rows, cols),
    all checked before any work: their number, placements, parents, images, given tilts and
    matching parameters (InvalidInputError names `rois[index]`'s field)."""
    if len(specs) > MAX_ROIS:
        raise InvalidInputError("rois", f"at most {MAX_ROIS} ROIs make one specimen, got {len(specs)}")
    rois = [roi_request(spec, index) for index, spec in enumerate(specs)]
    ordered_rois(rois)
    height_requests = [roi_height_map_request(spec, request_id) for spec in specs]
    shapes = []
    for index, request in enumerate(height_requests):
        with in_roi(index):
            shapes.append(rpc_matching.checked_height_map_request(request)[0])
            _validate_given_tilts(request)
    return rois, height_requests, shapes


def _validate_given_tilts(request: matching_pb2.ComputeHeightMapRequest) -> None:
    """The tilts a height-map request gives, checked as the matching pipeline checks them against the
    first view's (a tilt left to an image's metadata is known once the image is read)."""
    given = [item.tilt_deg if item.HasField("tilt_deg") else None for item in request.images]
    for index in range(1, len(given)):
        if given[0] is not None and given[index] is not None:
            validate_tilts((given[0], given[index]), field=f"images[{index}].tilt_deg")


def check_child_centres(
    specs: Sequence[tiles_pb2.RoiSpec], shapes: Sequence[tuple[int, int]], pixel_sizes_um: Sequence[float]
) -> None:
    """Refuses a given centre that puts an ROI (of its first image's (rows, cols) `shapes[i]` and
    pixels of `pixel_sizes_um[i]`) wholly outside its parent: the build places it there and then
    refuses it for want of overlap (registration.align_heights). Errors name `rois[i].center_um`."""
    index_of = {spec.id: index for index, spec in enumerate(specs)}
    for index, spec in enumerate(specs):
        if not (spec.parent and spec.HasField("center_um")):
            continue
        parent = index_of[spec.parent]
        # Both in the parent's frame: its pixel (0, 0) at the origin.
        centre_um = (spec.center_um.x_um, spec.center_um.y_um)
        origin_um = given_child_origin_um(centre_um, shapes[index], pixel_sizes_um[index])
        parent_um = footprint_um((0.0, 0.0), shapes[parent], pixel_sizes_um[parent])
        if not overlaps(footprint_um(origin_um, shapes[index], pixel_sizes_um[index]), parent_um):
            raise InvalidInputError(
                f"rois[{index}].center_um",
                f"places ROI {spec.id!r} outside its parent {spec.parent!r}, which spans "
                f"{parent_um[2]:.6g} x {parent_um[3]:.6g} µm from its first pixel's centre",
            )


def roi_height_map_request(spec: tiles_pb2.RoiSpec, request_id: str) -> matching_pb2.ComputeHeightMapRequest:
    """The ComputeHeightMap of one ROI's pair or tilt series."""
    tilts = [item.tilt_deg for item in spec.images] if all(item.HasField("tilt_deg") for item in spec.images) else None
    return calls.height_map_request(
        [(item.image.content, "") for item in spec.images],
        tilt_deg=tilts,
        pixel_size_um=spec.pixel_size_um if spec.HasField("pixel_size_um") else None,
        tilt_axis_deg=spec.tilt_axis_deg if spec.HasField("tilt_axis_deg") else None,
        parameters=spec.parameters,
        request_id=request_id,
    )


@contextlib.contextmanager
def in_roi(index: int):
    """Input errors about a height-map request, renamed as fields of `rois[index]`."""
    try:
        yield
    except InvalidInputError as error:
        raise InvalidInputError(f"rois[{index}].{error.field}", error.message) from None


def region(message: tiles_pb2.RegionUm, field: str) -> tuple[float, float, float, float]:
    """A RegionUm as (x_min, y_min, x_max, y_max) µm, checked."""
    return checked_region(wire.message_to_region(message), field)


@contextlib.contextmanager
def chain_fields(field: str = "chain"):
    """Errors the queries raise about the chain's settings, named as the request's fields
    (``chain.s_filter_um``)."""
    try:
        yield
    except InvalidInputError as error:
        if error.field in wire.CHAIN_FIELDS:
            raise InvalidInputError(f"{field}.{error.field}", error.message) from None
        raise


# A profile's chain is its form and its two filters; the rest is areal roughness only.
PROFILE_CHAIN_FIELDS = ("form", "s_filter_um", "l_filter_um")
AREAL_ONLY_CHAIN_FIELDS = tuple(name for name in wire.CHAIN_FIELDS if name not in PROFILE_CHAIN_FIELDS)
# The chain's settings given as plain values, named alike in SurfaceChain and ChainRequest.
_CHAIN_VALUES = tuple(name for name in wire.CHAIN_FIELDS if name not in ("form", "levelling_region"))


def profile_chain_request(message: tiles_pb2.SurfaceChain, field: str = "chain") -> ChainRequest:
    """`chain_request` for a profile: a field that only areal roughness takes is refused (as the
    HTTP API refuses its query parameter) rather than ignored."""
    for name in AREAL_ONLY_CHAIN_FIELDS:
        if message.HasField(name):
            raise InvalidInputError(
                f"{field}.{name}",
                f"profiles take only {', '.join(PROFILE_CHAIN_FIELDS[:-1])} and {PROFILE_CHAIN_FIELDS[-1]}",
            )
    return chain_request(message, field)


def chain_request(message: tiles_pb2.SurfaceChain, field: str = "chain") -> ChainRequest:
    """A request's SurfaceChain as the queries take it (absent fields None: the defaults); errors
    name `field`'s members (``chain.form``), or the fields alone where `field` is empty (the
    HTTP API's query parameters)."""

    def named(name: str) -> str:
        return f"{field}.{name}" if field else name

    if message.form not in wire.FORMS.values() and message.form != tiles_pb2.FORM_UNSPECIFIED:
        raise InvalidInputError(named("form"), f"unknown form {message.form}")
    return ChainRequest(
        form=wire.form_name(message.form) if message.form else None,
        levelling_region_um=region(message.levelling_region, named("levelling_region"))
        if message.HasField("levelling_region")
        else None,
        **{name: getattr(message, name) if message.HasField(name) else None for name in _CHAIN_VALUES},
    )


def _used_chain(chain: SurfaceChain, levelling_region_um) -> tiles_pb2.SurfaceChain:
    return wire.chain_message(
        form=chain.form,
        s_filter_um=chain.lambda_s_um,
        l_filter_um=chain.lambda_c_um,
        direction_deg=chain.direction_deg,
        levelling_region_um=levelling_region_um,
        window_px=chain.window_px,
        min_windows=chain.min_windows,
        robust_form=chain.robust_form,
    )


def roughness_response(analysis: SurfaceAnalysis, request: ChainRequest) -> tiles_pb2.GetRoughnessResponse:
    """Everything the chain found, with the chain as run (NaN for what is unknown)."""
    nan = float("nan")
    response = wire.values_to_roughness_response(analysis.legacy())
    response.chain.CopyFrom(_used_chain(analysis.chain, request.levelling_region_um))
    response.pixel_size_um = analysis.pixel_size_um
    u = analysis.uncertainty
    for name, value in analysis.parameters.items():
        parts = (u.u_total.get(name, nan), u.u_tilt.get(name, nan), u.u_noise.get(name, nan)) if u else (nan, nan, nan)
        response.parameters.add(
            name=name, value=value, unit=UNITS[name], u_total=parts[0], u_tilt=parts[1], u_noise=parts[2]
        )
    response.sa_noise_bias_um = u.noise_bias.get("Sa", nan) if u else nan
    response.sq_noise_bias_um = u.noise_bias.get("Sq", nan) if u else nan
    response.tilt_rel_uncertainty = nan if analysis.tilt_rel_uncertainty is None else analysis.tilt_rel_uncertainty
    for method, fits in analysis.hurst.fits.items():
        for side, fit in fits.items():
            response.hurst_fits.add(
                method=wire.HURST_METHODS[method],
                direction_deg=fit.direction_deg % 360.0,
                across=side == "across",
                hurst=fit.hurst,
                hurst_stderr=fit.hurst_stderr,
                fit_min_um=fit.fit_min_um,
                fit_max_um=fit.fit_max_um,
                fit_min_windows=analysis.hurst.min_windows,
                scale_um=fit.scale_um,
                value=fit.value,
                in_fit=fit.in_fit.tolist(),
                not_determinable=fit.not_determinable,
            )
    response.hurst_note = analysis.hurst.note
    response.psd_q_per_um.extend(analysis.psd_q_per_um)
    response.psd_um4.extend(analysis.psd_um4)
    if analysis.coverage is not None:
        response.coverage.CopyFrom(coverage_message(analysis.coverage.to_dict()))
    response.caveats.extend(analysis.caveats)
    return response


def coverage_message(coverage: dict) -> tiles_pb2.Coverage:
    """A Coverage (surface.measurement.Coverage.to_dict) as its message."""
    return tiles_pb2.Coverage(**{key: value for key, value in coverage.items() if key.endswith("_fraction")})


def profile_response(found: SpecimenProfile) -> tiles_pb2.GetProfileResponse:
    """A profile's samples, its roughness profile and parameters, and the chain that made them."""
    response = tiles_pb2.GetProfileResponse(
        distance_um=found.distance_um, z_um=found.z_um, source_index=found.source_index, sources=found.sources
    )
    if found.parameters:
        response.parameters.CopyFrom(wire.profile_parameters_message(found.parameters))
    if found.roughness is not None:
        made = found.roughness
        response.roughness_um.extend(found.r_um)
        response.chain.CopyFrom(
            wire.chain_message(form=made.form, s_filter_um=made.lambda_s_um, l_filter_um=made.lambda_c_um)
        )
        response.cutoffs_from_iso_table = made.cutoffs.from_iso_table
        response.spacing_within_iso = made.cutoffs.sampling_ok
    return response


def streamed_file(first, path: Path, *, file_name: str, media_type: str) -> Iterator:
    """A file's stream: `first` (a fresh ExportResponse or GetReportResponse, which may carry more)
    with its FileHeader, then the file's bytes in chunks of calls.CHUNK_BYTES, read as they go."""
    first.file.CopyFrom(
        tiles_pb2.FileHeader(file_name=file_name, media_type=media_type, size_bytes=path.stat().st_size)
    )
    yield first
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            yield type(first)(chunk=chunk)


def area_of(message: tiles_pb2.SpecimenArea, field: str) -> dict:
    """A SpecimenArea as the keyword arguments roi / region_um (neither: the overview), checked;
    errors name `field`'s members."""
    kind = message.WhichOneof("area")
    if kind == "region":
        return {"roi": None, "region_um": region(message.region, f"{field}.region")}
    return {"roi": message.roi if kind == "roi" else None, "region_um": None}


def export_options(request: tiles_pb2.ExportRequest) -> dict:
    """An ExportRequest's file settings as the exports take them (file_format, solid, units), and
    its pixel_size_um (None: the source's own), checked."""
    return {
        "file_format": wire.export_format_name(request.format),
        "solid": request.solid,
        "units": wire.length_unit_name(request.units),
        "pixel_size_um": request.pixel_size_um or None,
    }


def export(request: tiles_pb2.ExportRequest, directory: Path, store: StoredSpecimens) -> ExportedFile:
    """The file an ExportRequest asks for, written in `directory`."""
    options = export_options(request)
    pixel_size_um = options.pop("pixel_size_um")
    if request.WhichOneof("source") == "specimen":
        area = request.specimen
        return exports.export_area(
            store.load(area.specimen_id), directory, **area_of(area, "specimen"), pixel_size_um=pixel_size_um, **options
        )
    if request.WhichOneof("source") != "height_map":
        raise InvalidInputError("source", "give a specimen area or a height map")
    height_map = request.height_map
    z_um = wire.raster_to_array(height_map.z_um, field="height_map.z_um")
    sigma_um = (
        wire.raster_to_array(height_map.sigma_um, field="height_map.sigma_um")
        if height_map.HasField("sigma_um")
        else None
    )
    calibration = (
        Calibration.from_report(wire.message_to_report(request.report)) if request.HasField("report") else None
    )
    return exports.export_height_map(
        directory,
        z_um,
        pixel_size_um=validate_pixel_size_um(height_map.pixel_size_um, field="height_map.pixel_size_um"),
        sigma_um=sigma_um,
        calibration=calibration,
        export_pixel_size_um=pixel_size_um,
        **options,
    )


def export_grid(exported: ExportedFile) -> tiles_pb2.ExportGrid:
    rows, cols = exported.shape
    return tiles_pb2.ExportGrid(
        rows=rows,
        cols=cols,
        pixel_size_um=exported.pixel_size_um,
        origin_um=common_pb2.PointUm(x_um=exported.origin_um[0], y_um=exported.origin_um[1]),
    )


def request_digest(request: tiles_pb2.ReconstructSpecimenRequest) -> str:
    """What identifies a build request's content: the SHA-256 (hex) of the request serialized
    deterministically with its request_id cleared. It is fed the specimen id, then one ROI at a
    time, then the build options (the same bytes: a message's encoding is its fields' in turn by
    number, a repeated field's its elements'), so a request of hundreds of MB of images is never
    copied whole."""
    digest = hashlib.sha256(
        tiles_pb2.ReconstructSpecimenRequest(specimen_id=request.specimen_id).SerializeToString(deterministic=True)
    )
    for roi in request.rois:
        digest.update(tiles_pb2.ReconstructSpecimenRequest(rois=[roi]).SerializeToString(deterministic=True))
    options = tiles_pb2.ReconstructSpecimenRequest(unmeasured=request.unmeasured)
    digest.update(options.SerializeToString(deterministic=True))
    return digest.hexdigest()
