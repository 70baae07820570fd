"""The floor under gRPC tile fetches: a bare gRPC Python server whose GetTile returns one cached,
already serialized response of a given size, with no store, no lookup and no protobuf work.
The serving benchmark loads it exactly as it loads the tile service, so the gap between the two
is what the tile service itself costs per call.

    python -m benchmarks.bare_grpc_server --address 127.0.0.1:PORT --tile-bytes N
"""

from __future__ import annotations

import argparse
import os
from concurrent import futures

import grpc

from fractoscope.runtime.process import settle_garbage_collector
from fractoscope.v1 import tiles_pb2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--address", required=True)
    parser.add_argument("--tile-bytes", type=int, required=True, help="size of the GLB in the cached response")
    args = parser.parse_args()
    response = tiles_pb2.GetTileResponse(
        tile=tiles_pb2.Tile(uri="tile.glb", glb=os.urandom(args.tile_bytes))
    ).SerializeToString()
    handler = grpc.method_handlers_generic_handler(
        "fractoscope.v1.TileService",
        {"GetTile": grpc.unary_unary_rpc_method_handler(lambda request, context: response)},  # bytes in, bytes out
    )
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=8))
    server.add_generic_rpc_handlers((handler,))
    server.add_insecure_port(args.address)
    settle_garbage_collector()  # as the tile service does
    server.start()
    server.wait_for_termination()


if __name__ == "__main__":
    main()
