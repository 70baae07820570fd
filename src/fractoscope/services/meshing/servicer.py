"""MeshingService: height maps to filtered, tiled, textured GLB levels of detail."""

from __future__ import annotations

import logging

from fractoscope.mesh.pipeline import mesh_height_map
from fractoscope.rpc import meshing as rpc_meshing
from fractoscope.rpc.status import abort_on_error
from fractoscope.services.streaming import stream_progress
from fractoscope.v1 import common_pb2, meshing_pb2, meshing_pb2_grpc

_log = logging.getLogger("fractoscope.meshing")


class MeshingServicer(meshing_pb2_grpc.MeshingServiceServicer):
    """Decodes the request, runs `mesh_height_map`, streams progress, tiles and the filter report."""

    @abort_on_error
    def BuildMesh(self, request, context):
        z_um, texture, pixel_size_um, sigma_um = rpc_meshing.height_map_arrays(request.height_map)
        options = rpc_meshing.options_from_request(request)
        origin_um = rpc_meshing.origin_from_request(request)

        def work(progress):
            return mesh_height_map(
                z_um, texture, pixel_size_um=pixel_size_um, origin_um=origin_um, options=options, sigma_um=sigma_um, progress=progress
            )

        for event in stream_progress(context, work):
            if isinstance(event, common_pb2.Progress):
                yield meshing_pb2.BuildMeshResponse(progress=event)
                continue
            tiles, report = event
            for tile in tiles:
                yield rpc_meshing.tile_response(tile)
            yield rpc_meshing.filter_report_response(report)
            _log.info("mesh done", extra={"request_id": request.request_id})
