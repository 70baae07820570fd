"""X3P files (ISO 25178-72), the open areal-surface format that Gwyddion, MountainsMap and
surfalize read.

An X3P file is a zip archive of `main.xml` (axes, grid, metadata), `bindata/data.bin` (the heights,
little-endian, x fastest) and `md5checksum.hex` (the MD5 of main.xml). Heights are written in
metres, as the standard requires, as float64 (Z data type "D"). Unknown points are NaN in the
point data: for IEEE 754 data types that is how ISO 25178-72 marks invalid points, as the openGPS
reference library does, and both Gwyddion and surfalize read it; `bindata/valid.bin` is needed only
for integer data, which this module reads but never writes.

Array row r, column c is the point X = x0 + c·Δ, Y = y0 + r·Δ (CX and CY are incremental axes whose
offsets place a region in its specimen), the point order Gwyddion and surfalize read, so that
Gwyddion shows the surface as the SEM image (row 0 at the top).

References: ISO 25178-72:2017, Geometrical product specifications (GPS) - Surface texture: Areal -
Part 72: XML file format x3p; the openGPS ISO 5436-2 XML schema, https://www.opengps.eu/2008/ISO5436_2
"""

from __future__ import annotations

import hashlib
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import BinaryIO
from xml.etree import ElementTree

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats._validate import height_grid, origin
from fractoscope.formats.calibration import Calibration, export_description, software

NAMESPACE = "http://www.opengps.eu/2008/ISO5436_2"
M_PER_UM = 1e-6
DATA_PATH = "bindata/data.bin"
CHECKSUM_PATH = "md5checksum.hex"
_Z_TYPES = {"I": "<i2", "L": "<i4", "F": "<f4", "D": "<f8"}
_ZIP64_BYTES = 2**31  # beyond this a member needs ZIP64 records, which a streamed write must announce


@dataclass(frozen=True)
class X3pSurface:
    """An areal surface read from an X3P file.

    z_um: (rows, cols) float64 heights, µm, NaN where invalid; row r is Y index r.
    step_x_um, step_y_um: grid increments along columns (X) and rows (Y), µm.
    origin_um: (x0, y0), the position of point (0, 0), µm (the CX and CY offsets).
    comment: Record2's Comment, "" when absent (Fractoscope writes `export_description` JSON).
    """

    z_um: np.ndarray
    step_x_um: float
    step_y_um: float
    origin_um: tuple[float, float]
    comment: str


def write_x3p(
    file: str | os.PathLike | BinaryIO,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    calibration: Calibration | None = None,
    compress: bool = False,
    block_rows: int = 256,
) -> None:
    """Write heights as an X3P file (ISO 25178-72), streamed in blocks of `block_rows` rows.

    z_um: (rows, cols) heights, µm, NaN (or ±inf) where unknown; any real dtype.
    pixel_size_um: grid step along rows and columns, µm (CX and CY increments, in metres in the file).
    origin_um: (x0, y0), µm, the position of pixel (0, 0) in the specimen (CX and CY offsets).
    calibration: recorded in Record2's Comment as JSON (`export_description`), null when None.
    compress: deflate the point data; float heights shrink little and deflating costs seconds per
        hundred megabytes, so it is off by default.
    Memory beyond `z_um` is one block of float64 rows.
    """
    z_um = height_grid(z_um, pixel_size_um)
    x0_um, y0_um = origin(origin_um)
    if block_rows < 1:
        raise ValueError(f"block_rows: must be at least 1, got {block_rows}")
    rows, cols = z_um.shape
    description = export_description(calibration, grid_step_um=float(pixel_size_um), z_unit="m")
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(file, "w", compression=method, compresslevel=1 if compress else None) as archive:
        digest = hashlib.md5()
        with archive.open(DATA_PATH, "w", force_zip64=rows * cols * 8 >= _ZIP64_BYTES) as member:
            for start in range(0, rows, block_rows):
                block = np.multiply(z_um[start : start + block_rows], M_PER_UM, dtype="<f8")
                block[~np.isfinite(block)] = np.nan
                flat = block.reshape(-1)
                digest.update(flat)
                member.write(flat)
        main_xml = _main_xml(
            rows,
            cols,
            pixel_size_um * M_PER_UM,
            (x0_um * M_PER_UM, y0_um * M_PER_UM),
            digest.hexdigest(),
            description,
            calibration,
        )
        archive.writestr("main.xml", main_xml)
        archive.writestr(CHECKSUM_PATH, f"{hashlib.md5(main_xml).hexdigest()} *main.xml\n")


def read_x3p(file: str | os.PathLike | BinaryIO, *, field: str | None = None) -> X3pSurface:
    """Read a surface (FeatureType SUR) with binary point data of any Z type from an X3P file.

    Checks the MD5 sums that main.xml gives; points that valid.bin marks invalid, and non-finite
    values, become NaN. Raises InvalidInputError naming `field` (default: the file's path or name)
    and saying which element or member is at fault.
    """
    field = field or _file_name(file)
    try:
        with zipfile.ZipFile(file) as archive:
            return _surface(archive)
    except InvalidInputError as error:
        raise InvalidInputError(field, str(error)) from None
    except (zipfile.BadZipFile, EOFError, zlib.error) as error:
        raise InvalidInputError(field, f"is not a readable X3P file (a zip archive): {error}") from None


def _file_name(file: str | os.PathLike | BinaryIO) -> str:
    """How errors name `file`: its path, else the stream's name, else "X3P file"."""
    if isinstance(file, (str, os.PathLike)):
        return os.fspath(file)
    return str(getattr(file, "name", "X3P file"))


def _surface(archive: zipfile.ZipFile) -> X3pSurface:
    """The surface in an X3P archive; InvalidInputError names the element at fault."""
    try:
        root = ElementTree.fromstring(archive.read("main.xml"))
    except KeyError:
        raise InvalidInputError("main.xml", "missing from the archive") from None
    except ElementTree.ParseError as error:
        raise InvalidInputError("main.xml", f"malformed XML ({error})") from None
    text = _element_text(root)
    if text("Record1/FeatureType") != "SUR":
        raise InvalidInputError(
            "Record1/FeatureType", f"only SUR surfaces are read, not {text('Record1/FeatureType')!r}"
        )
    for axis, kind in (("CX", "I"), ("CY", "I"), ("CZ", "A")):
        if text(f"Record1/Axes/{axis}/AxisType") != kind:
            raise InvalidInputError(f"Record1/Axes/{axis}/AxisType", f"only {kind} is read")
    z_type = text("Record1/Axes/CZ/DataType")
    if z_type not in _Z_TYPES:
        raise InvalidInputError("Record1/Axes/CZ/DataType", f"{z_type!r} is none of {sorted(_Z_TYPES)}")
    number = _number_at(text)
    cols, rows, layers = (number(f"Record3/MatrixDimension/Size{a}", int) for a in "XYZ")
    if layers != 1:
        raise InvalidInputError("Record3/MatrixDimension/SizeZ", f"only one layer is read, not {layers}")
    link = text("Record3/DataLink/PointDataLink")
    if not link:
        raise InvalidInputError("Record3/DataLink/PointDataLink", "no binary point data (XML DataList is not read)")
    raw = _member(archive, link, text("Record3/DataLink/MD5ChecksumPointData"))
    dtype = np.dtype(_Z_TYPES[z_type])
    if len(raw) != rows * cols * dtype.itemsize:
        raise InvalidInputError(link, f"{len(raw)} bytes for {cols} x {rows} points of type {z_type}")
    increment, offset = number("Record1/Axes/CZ/Increment", float, 1.0), number("Record1/Axes/CZ/Offset", float, 0.0)
    z_um = np.frombuffer(raw, dtype).reshape(rows, cols).astype(np.float64)
    z_um *= increment / M_PER_UM
    z_um += offset / M_PER_UM
    z_um[~np.isfinite(z_um)] = np.nan
    valid_link = text("Record3/DataLink/ValidPointsLink")
    if valid_link:
        bits = np.frombuffer(_member(archive, valid_link, text("Record3/DataLink/MD5ChecksumValidPoints")), np.uint8)
        if len(bits) != (rows * cols + 7) // 8:
            raise InvalidInputError(valid_link, f"{len(bits)} bytes for {rows * cols} points")
        # One bit per point in point order, least significant bit first, set where valid.
        z_um[~np.unpackbits(bits, count=rows * cols, bitorder="little").reshape(rows, cols).astype(bool)] = np.nan
    step_x_um, step_y_um = (_step_m(number, axis) / M_PER_UM for axis in ("CX", "CY"))
    origin_um = tuple(number(f"Record1/Axes/{a}/Offset", float, 0.0) / M_PER_UM for a in ("CX", "CY"))
    return X3pSurface(z_um, step_x_um, step_y_um, origin_um, text("Record2/Comment") or "")


def _main_xml(
    rows: int,
    cols: int,
    step_m: float,
    origin_m: tuple[float, float],
    data_md5: str,
    comment: str,
    calibration: Calibration | None,
) -> bytes:
    """main.xml of ISO 25178-72:2017 (Revision "ISO5436 - 2000"): the root element in the openGPS
    namespace, its children unqualified as the schema has them (Record2: `_record2`)."""
    root = ElementTree.Element("p:ISO5436_2", {"xmlns:p": NAMESPACE})

    def add(parent, tag, text=None):
        element = ElementTree.SubElement(parent, tag)
        if text is not None:
            element.text = str(text)
        return element

    record1 = add(root, "Record1")
    add(record1, "Revision", "ISO5436 - 2000")
    add(record1, "FeatureType", "SUR")
    axes = add(record1, "Axes")
    for name, offset_m in zip(("CX", "CY"), origin_m):
        axis = add(axes, name)
        add(axis, "AxisType", "I")
        add(axis, "DataType", "D")
        add(axis, "Increment", repr(float(step_m)))
        add(axis, "Offset", repr(float(offset_m)))
    cz = add(axes, "CZ")
    add(cz, "AxisType", "A")
    add(cz, "DataType", "D")

    _record2(add(root, "Record2"), add, comment, calibration)

    record3 = add(root, "Record3")
    dimension = add(record3, "MatrixDimension")
    for tag, size in (("SizeX", cols), ("SizeY", rows), ("SizeZ", 1)):
        add(dimension, tag, size)
    link = add(record3, "DataLink")
    add(link, "PointDataLink", DATA_PATH)
    add(link, "MD5ChecksumPointData", data_md5.upper())

    add(add(root, "Record4"), "ChecksumFile", CHECKSUM_PATH)
    ElementTree.indent(root)
    return (
        b'<?xml version="1.0" encoding="UTF-8"?>\n'
        + ElementTree.tostring(root, encoding="utf-8", xml_declaration=False)
        + b"\n"
    )


def _record2(record2, add, comment: str, calibration: Calibration | None) -> None:
    """Record2's children: the microscope the calibration names, and as CalibrationDate when the
    images were taken (their tilts and pixel size are that day's); the export's own time where the
    calibration knows neither."""
    now = datetime.now(UTC).isoformat(timespec="seconds")
    add(record2, "Date", now)
    add(record2, "Creator", software())
    instrument = add(record2, "Instrument")
    vendor, model = calibration.instrument if calibration and calibration.instrument else ("unknown", "")
    for tag, value in (
        ("Manufacturer", vendor),
        ("Model", f"{model} scanning electron microscope".strip()),
        ("Serial", "unknown"),
        ("Version", "unknown"),
    ):
        add(instrument, tag, value)
    add(record2, "CalibrationDate", (calibration.acquired_at if calibration else "") or now)
    probing = add(record2, "ProbingSystem")
    add(probing, "Type", "NonContacting")
    add(probing, "Identification", f"SEM stereo photogrammetry, {software()}")
    add(record2, "Comment", comment)


def _element_text(root: ElementTree.Element):
    """text(path) -> the stripped text at `path` below the root, None when absent."""

    def text(path: str) -> str | None:
        element = root.find(path)
        return element.text.strip() if element is not None and element.text else None

    return text


def _number_at(text):
    """number(path, kind, default) -> the element's text as `kind` (int or float), `default` when
    absent; InvalidInputError naming the element when it is no such number."""

    def number(path: str, kind: type, default=None):
        value = text(path)
        if value is None and default is not None:
            return default
        try:
            return kind(value)
        except (TypeError, ValueError):
            raise InvalidInputError(
                path, f"expected {'an integer' if kind is int else 'a number'}, got {value!r}"
            ) from None

    return number


def _step_m(number, axis: str) -> float:
    """The grid step of incremental axis `axis` (CX or CY), m: positive and finite."""
    path = f"Record1/Axes/{axis}/Increment"
    step_m = number(path, float, 1.0)
    if not (math.isfinite(step_m) and step_m > 0):
        raise InvalidInputError(path, f"the grid step must be positive and finite, got {step_m} m")
    return step_m


def _member(archive: zipfile.ZipFile, name: str, md5: str | None) -> bytes:
    try:
        content = archive.read(name)
    except KeyError:
        raise InvalidInputError(name, "linked from main.xml but missing from the archive") from None
    if md5 and hashlib.md5(content).hexdigest().lower() != md5.lower():
        raise InvalidInputError(name, "MD5 checksum does not match main.xml")
    return content
