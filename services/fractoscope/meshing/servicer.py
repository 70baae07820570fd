"""MeshingService: height maps to filtered, tiled, textured GLB levels of detail."""

from __future__ import annotations

import logging

from fractoscope.mesh.pipeline import EncodedTile, MeshReport, mesh_height_map
from fractoscope.meshing import messages as rpc_meshing
from fractoscope.progress import ProgressCallback
from fractoscope.rpc.status import abort_on_error
from fractoscope.runtime import budget
from fractoscope.runtime.jobs import Job, JobRunner
from fractoscope.v1 import common_pb2, meshing_pb2, meshing_pb2_grpc

_log = logging.getLogger("fractoscope.meshing")


class MeshingServicer(meshing_pb2_grpc.MeshingServiceServicer):
    """Checks the request against the memory budget, then runs `mesh_height_map` as one of the
    `builds` jobs, streaming progress, tiles and the filter report."""

    def __init__(self, *, builds: JobRunner, budget: budget.Budget):
        self._builds, self._budget = builds, budget

    @abort_on_error
    def BuildMesh(self, request, context):
        arguments = _mesh_arguments(request)
        rows, cols = arguments["z_um"].shape
        estimate = budget.mesh_bytes((rows, cols))
        self._budget.check(estimate, f"a mesh of a {cols} x {rows} height map")

        def work(job: Job):
            with self._budget.held(estimate):
                return mesh_height_map(**arguments, progress=job.progress)

        for event in self._builds.follow(context, work):
            if isinstance(event, common_pb2.Progress):
                yield meshing_pb2.BuildMeshResponse(progress=event)
                continue
            tiles, report = event
            for tile in tiles:
                yield rpc_meshing.tile_response(tile)
            yield rpc_meshing.filter_report_response(report)
            _log.info("mesh done", extra={"request_id": request.request_id})

    def mesh(
        self, request: meshing_pb2.BuildMeshRequest, progress: ProgressCallback
    ) -> tuple[list[EncodedTile], MeshReport]:
        """BuildMesh's work, in the thread of a job (this call's, or a specimen build's that calls it
        in-process): the tiles, finest level first, and the filter report."""
        return mesh_height_map(**_mesh_arguments(request), progress=progress)


def _mesh_arguments(request: meshing_pb2.BuildMeshRequest) -> dict:
    """`mesh_height_map`'s arguments from a request, validated (InvalidInputError names the field)."""
    z_um, texture, pixel_size_um, sigma_um = rpc_meshing.height_map_arrays(request.height_map)
    return {
        "z_um": z_um,
        "texture": texture,
        "pixel_size_um": pixel_size_um,
        "sigma_um": sigma_um,
        "origin_um": rpc_meshing.origin_from_request(request),
        "options": rpc_meshing.options_from_request(request),
    }
