"""The client is a leaf: importing it loads gRPC, protobuf and numpy, never the image processing
and meshing libraries the services run on."""

import json
import subprocess
import sys

HEAVY = ("cv2", "meshoptimizer", "fast_simplification", "scipy", "pygltflib", "tifffile", "PIL", "matplotlib")


def test_importing_the_client_loads_no_image_processing_or_meshing_library():
    probe = (
        "import json, sys; import fractoscope.client, fractoscope.client.manifest;"
        "print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))"
    )
    loaded = set(json.loads(subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout))
    assert {"fractoscope", "grpc", "numpy"} <= loaded  # the probe did import the client
    assert loaded.isdisjoint(HEAVY), sorted(loaded & set(HEAVY))
