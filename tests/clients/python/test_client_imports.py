"""The client is a leaf: importing it loads gRPC, protobuf and numpy, never the image processing
and meshing libraries the services run on; and it installs alone, from clients/python, into a
fresh environment that then holds none of them."""

import json
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
HEAVY = ("cv2", "meshoptimizer", "fast_simplification", "scipy", "pygltflib", "tifffile", "PIL", "matplotlib")
# Distributions a lab that only calls the API must not be made to install.
HEAVY_DISTRIBUTIONS = {"opencv-python-headless", "scipy", "numba", "matplotlib", "trimesh", "aiohttp", "pillow"}


def test_importing_the_client_loads_no_image_processing_or_meshing_library():
    probe = (
        "import json, sys; import fractoscope.client, "
        "fractoscope.client.manifest;print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))"
    )
    loaded = set(
        json.loads(subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout)
    )
    assert {"fractoscope", "grpc", "numpy"} <= loaded  # the probe did import the client
    assert loaded.isdisjoint(HEAVY), sorted(loaded & set(HEAVY))


@pytest.mark.slow
def test_the_client_installs_alone_into_a_fresh_environment(tmp_path):
    """`pip install clients/python` (not editable: a wheel built from the tree, stubs generated
    from proto/ by its build) in a new venv: the client and its stubs import, and nothing of the
    services' stack is installed."""
    environment = tmp_path / "venv"
    venv.create(environment, with_pip=True)
    python = environment / "bin" / "python"
    install = subprocess.run(
        [python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", str(ROOT / "clients" / "python")],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert install.returncode == 0, install.stderr[-3000:]
    probe = (
        "import json, importlib.metadata as m; import fractoscope.client, fractoscope.v1.tiles_pb2_grpc; "
        "print(json.dumps(sorted(d.metadata['Name'].lower() for d in m.distributions())))"
    )
    done = subprocess.run([python, "-c", probe], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    installed = set(json.loads(done.stdout))
    assert "fractoscope-client" in installed and "grpcio" in installed and "numpy" in installed
    assert installed.isdisjoint(HEAVY_DISTRIBUTIONS), sorted(installed & HEAVY_DISTRIBUTIONS)
    assert not any(name.startswith("fractoscope-services") for name in installed)
