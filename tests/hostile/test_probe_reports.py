"""Reports of a specimen whose image files bear names a formatter would read as its own markup
(issue 49, item 5): matplotlib's mathtext (`$\\frac{1}{$`) and rare Unicode. The names are drawn
as plain text: every report, HTML and PDF, over HTTP and gRPC, is written, and the next ones too."""

from __future__ import annotations

import subprocess

import grpc
import pytest
import requests
from probe_servers import READ, READ_METADATA, write_map_specimen

from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

NAMES = (r"$\frac{1}{$.tif", "\U0001f9ea\u0301\u202e\U000e0020 \u0000 x.tif", r"$x^$.tif")


@pytest.fixture(scope="module")
def specimen(live):
    write_map_specimen(live.store, "markup", size_px=128, view_names=NAMES)
    return "markup"


@pytest.mark.parametrize("file_format", ["html", "pdf"])
def test_a_report_of_images_named_as_mathtext_is_written_each_time(live, specimen, file_format, tmp_path):
    """Once a 500 (ValueError from mathtext's parser) for this report and every later one."""
    for _ in range(2):
        answer = requests.get(
            f"{live.http}/api/specimens/{specimen}/report", params={"format": file_format}, headers=READ, timeout=300
        )
        assert answer.status_code == 200, answer.text[:500]
    if file_format == "pdf":
        (tmp_path / "report.pdf").write_bytes(answer.content)
        text = subprocess.run(["pdftotext", str(tmp_path / "report.pdf"), "-"], capture_output=True, text=True).stdout
        assert r"$\frac{1}{$" in text  # drawn as written
    else:
        assert r"$\frac{1}{$.tif" in answer.text


def test_get_report_of_images_named_as_mathtext_streams_a_pdf(live, specimen):
    with grpc.insecure_channel(live.grpc_address) as channel:
        stub = tiles_pb2_grpc.TileServiceStub(channel)
        request = tiles_pb2.GetReportRequest(
            area=tiles_pb2.SpecimenArea(specimen_id=specimen), format=tiles_pb2.REPORT_FORMAT_PDF
        )
        chunks = list(stub.GetReport(request, metadata=READ_METADATA, timeout=300))
    assert b"".join(chunk.chunk for chunk in chunks).startswith(b"%PDF")
