"""Shared fixtures: synthetic stereo pairs with known truth, the shared real data, a loopback server."""

from __future__ import annotations

import io
import os
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

import cv2
import meshoptimizer
import numpy as np
import pygltflib
import pytest
import tifffile
import trimesh
from probe_servers import live, server_process  # noqa: F401 - fixtures: the probe suite's servers (tests/hostile)
from s3_server import s3_endpoint, s3_objects  # noqa: F401 - fixtures: a real S3 server for the store tests

from fractoscope import synthetic
from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.model import RoiEntry, write_description, write_roi_arrays
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey, TileRecord
from fractoscope.store.folder import SpecimenStore
from fractoscope.synthetic.examples import write_multiscale_specimen

# No instrument profile of the machine's user reaches a test (sem.instruments): each test that
# wants profiles names its own file.
os.environ["FRACTO_INSTRUMENTS"] = str(Path(tempfile.gettempdir()) / "fractoscope-tests" / "no-instruments.json")


def pytest_addoption(parser):
    parser.addoption("--load", action="store_true", help="also run the probe suite's long cases (make load)")


# Fixtures that start a server (gRPC, HTTP, S3 or a server process): a test that uses one, itself
# or through another fixture, is marked `server`, which `make check` leaves out.
SERVER_FIXTURES = {
    "server_address",
    "built",
    "live",
    "server_process",
    "s3_endpoint",
    "guarded",
    "served",
    "endpoint",
    "server",
}


def pytest_collection_modifyitems(config, items):
    """Tests that use a server's fixture are marked `server`; tests marked `load` (minutes of
    hostile load) run with --load only."""
    for item in items:
        if SERVER_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.server)
    if config.getoption("--load"):
        return
    skip = pytest.mark.skip(reason="a long probe: make load runs it (pytest --load)")
    for item in items:
        if "load" in item.keywords:
            item.add_marker(skip)


SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
POLLEN_SERIES = SHARED_DATA / "real" / "potamogeton-tilt-series"


def fracture_pair(
    *, tilt_deg=(-5.0, 5.0), size_px=640, seed=1, tilt_axis_deg=90.0, shift_px=(0.0, 0.0), rotation_deg=0.0, bits=8
) -> synthetic.StereoPair:
    """A self-affine fracture surface (H = 0.8, 2.5 µm RMS at 0.1 µm/px) seen at two tilts, 2 % noise."""
    margin = size_px // 2 if (tilt_axis_deg != 90.0 or rotation_deg) else 64
    surface = synthetic.reference_surface("self_affine", size_px + margin, seed=seed)
    return synthetic.render_stereo_pair(
        surface,
        pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM,
        tilt_deg=tilt_deg,
        output_shape=(size_px, size_px),
        tilt_axis_deg=tilt_axis_deg,
        second_shift_px=shift_px,
        second_rotation_deg=rotation_deg,
        seed=seed,
        bits=bits,
    )


def dimple_pair(*, tilt_deg=(-5.0, 5.0), size_px=640, seed=1, **render) -> synthetic.StereoPair:
    """Ductile dimples (radius ~4 µm, ~3 µm deep, sharp rims) at 0.1 µm/px, 2 % noise unless
    `render` (see synthetic.render_stereo_pair) says otherwise."""
    return _reference_pair("dimples", tilt_deg, size_px, seed, **render)


def cleavage_pair(*, tilt_deg=(-5.0, 5.0), size_px=640, seed=1) -> synthetic.StereoPair:
    """Cleavage facets (~16 µm grains, 0.5 µm river steps, slopes up to 0.2) at 0.1 µm/px, 2 % noise."""
    return _reference_pair("cleavage", tilt_deg, size_px, seed)


def _reference_pair(kind, tilt_deg, size_px, seed, **render) -> synthetic.StereoPair:
    return synthetic.render_surface_pair(kind, size_px, tilt_deg=tilt_deg, seed=seed, **render)


def tiff_bytes(image: np.ndarray) -> bytes:
    """An image as the bytes of a TIFF file, as clients send it."""
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, image)
    return buffer.getvalue()


def inner_mask(shape, border_px=16) -> np.ndarray:
    mask = np.zeros(shape, bool)
    mask[border_px:-border_px, border_px:-border_px] = True
    return mask


def write_small_specimen(
    store: SpecimenStore, specimen_id: str, *, height_um: float = 1.0, request_id: str = "job"
) -> None:
    """A one-ROI specimen without building it: a 16 x 24 map of `height_um` at 0.5 µm/px and its
    root tile, whose GLB is b"glTF" followed by the byte int(height_um)."""
    root = TileKey(0, 0, 0)
    roi = PlacedRoi(
        "overview", 100.0, 0.5, (2.0, 3.0), np.full((16, 24), height_um, np.float32), np.full((16, 24), 7, np.uint8)
    )
    entry = RoiEntry(
        roi.id,
        "",
        roi.magnification,
        roi.pixel_size_um,
        roi.origin_um,
        roi.z_um.shape,
        matching={"valid_fraction": 1.0},
    )
    record = TileRecord(root, roi.id, roi.magnification, OPTICAL, 0.0, height_um, height_um)
    with store.writing(specimen_id) as staging:
        (staging / root.uri).parent.mkdir(parents=True)
        (staging / root.uri).write_bytes(b"glTF" + bytes([int(height_um)]))
        (staging / "tileset.json").write_text("{}")
        write_roi_arrays(staging, roi)
        write_description(
            staging,
            specimen_id=specimen_id,
            request_id=request_id,
            rois=[entry],
            layout=QuadtreeLayout((2.0, 3.0), 12.0),
            tiles={root: record},
        )


@pytest.fixture(scope="session")
def pollen_series() -> Path:
    if not (POLLEN_SERIES / "pot_00.tif").is_file():
        pytest.skip(f"shared real data not found at {POLLEN_SERIES}")
    return POLLEN_SERIES


@pytest.fixture()
def server_address(tmp_path):
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"))
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=None)


@pytest.fixture()
def client(server_address):
    with FractoscopeClient(server_address, timeout_s=120) as connected:
        yield connected


@pytest.fixture(scope="session")
def built(tmp_path_factory):
    """(truth, client, data directory, summary) with the example specimen (synthetic.examples)
    reconstructed by a loopback server, for the tile service's and the browser's tests."""
    root = tmp_path_factory.mktemp("specimen")
    truth = write_multiscale_specimen(root / "input")
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=root / "data"))
    server.start()
    with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=300) as client:
        specimen_id, rois = load_manifest(root / "input" / "manifest.json")
        summary = client.reconstruct_specimen(specimen_id, rois, request_id="first")
        yield truth, client, root / "data", summary
    server.stop(grace=None)


@dataclass(frozen=True)
class DecodedGlb:
    """A GLB's one mesh as a client sees it: positions (N, 3) metres after the node's transform,
    normals (N, 3), texture coordinates (N, 2), the surface's triangles (M, 3), the walls' (K, 3)
    and the unmeasured areas' floor's (F, 3; mesh.outline)."""

    positions_m: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray
    wall_triangles: np.ndarray
    floor_triangles: np.ndarray


def decode_glb(glb: bytes) -> DecodedGlb:
    """Decodes one of our GLBs the way a glTF client does: meshoptimizer's decoder for the
    EXT_meshopt_compression views, then KHR_mesh_quantization's normalization and node transform;
    plain views (float32, no extensions) as they are."""
    gltf = pygltflib.GLTF2.load_from_bytes(glb)
    blob = gltf.binary_blob()
    primitives = gltf.meshes[0].primitives
    primitive = primitives[0]

    def values(accessor_index: int) -> np.ndarray:
        accessor = gltf.accessors[accessor_index]
        view = gltf.bufferViews[accessor.bufferView]
        if "EXT_meshopt_compression" not in view.extensions:
            dtype = {
                pygltflib.FLOAT: np.float32,
                pygltflib.UNSIGNED_SHORT: np.uint16,
                pygltflib.UNSIGNED_INT: np.uint32,
            }[accessor.componentType]
            components = {pygltflib.SCALAR: 1, pygltflib.VEC2: 2, pygltflib.VEC3: 3}[accessor.type]
            raw = np.frombuffer(blob, dtype, accessor.count * components, view.byteOffset + (accessor.byteOffset or 0))
            return (
                raw.reshape(accessor.count, components).astype(np.float64) if components > 1 else raw.astype(np.int64)
            )
        compressed = view.extensions["EXT_meshopt_compression"]
        data = blob[compressed["byteOffset"] : compressed["byteOffset"] + compressed["byteLength"]]
        if compressed["mode"] == "TRIANGLES":
            return meshoptimizer.decode_index_buffer(compressed["count"], 4, data).astype(np.int64)
        dtype = {pygltflib.BYTE: np.int8, pygltflib.UNSIGNED_SHORT: np.uint16}[accessor.componentType]
        components = {pygltflib.VEC2: 2, pygltflib.VEC3: 3}[accessor.type]
        vertices = meshoptimizer.decode_vertex_buffer(compressed["count"], compressed["byteStride"], data).view(
            np.uint8
        )
        decoded = vertices.reshape(compressed["count"], -1).view(dtype)[:, :components].astype(np.float64)
        if accessor.normalized:
            decoded = np.maximum(decoded / np.iinfo(dtype).max, -1.0)
        return decoded

    node = gltf.nodes[0]
    positions_m = np.asarray(node.translation or (0.0, 0.0, 0.0)) + values(primitive.attributes.POSITION) * np.asarray(
        node.scale or (1.0, 1.0, 1.0)
    )

    def triangles(material_name: str) -> np.ndarray:
        chosen = [
            values(p.indices).reshape(-1, 3) for p in primitives if gltf.materials[p.material].name == material_name
        ]
        return np.concatenate(chosen) if chosen else np.zeros((0, 3), np.int64)

    return DecodedGlb(
        positions_m,
        values(primitive.attributes.NORMAL),
        values(primitive.attributes.TEXCOORD_0),
        triangles("surface"),
        triangles("wall"),
        triangles("unmeasured"),
    )


def rough_with_hole(size=600):
    """A rough surface (H = 0.8, 2 µm RMS) with a 60 x 80 px hole, float32 µm, and a texture from its heights."""
    z = synthetic.self_affine_surface((size, size), hurst=0.8, rms_um=2.0, seed=4).astype(np.float32)
    z[200:260, 300:380] = np.nan
    texture = np.clip((z - np.nanmin(z)) / (np.nanmax(z) - np.nanmin(z)) * 255, 0, 255)
    return z, np.nan_to_num(texture).astype(np.uint8)


def rotated_to_lowest_first(triangles: np.ndarray) -> np.ndarray:
    """Each triangle rotated (winding kept) to start at its lowest index: the index codec may
    rotate triangles."""
    shift = np.argmin(triangles, axis=1)[:, None]
    return np.take_along_axis(triangles, (shift + np.arange(3)) % 3, axis=1)


VALIDATOR = Path(__file__).resolve().parent / "services" / "mesh" / "validate_gltf.mjs"


def validate_glbs(glbs: list[bytes], directory: Path) -> list[dict]:
    """Runs the Khronos glTF Validator (npm gltf-validator, installed by `make install`) on GLBs;
    one report per GLB with its error and warning counts and messages."""
    import json
    import shutil
    import subprocess

    if shutil.which("node") is None:
        pytest.fail("node is needed to run the glTF validator (installed with the project's toolchain)")
    paths = []
    for index, glb in enumerate(glbs):
        path = directory / f"tile_{index}.glb"
        path.write_bytes(glb)
        paths.append(str(path))
    reports = []
    for start in range(0, len(paths), 200):
        done = subprocess.run(
            ["node", str(VALIDATOR), *paths[start : start + 200]],
            capture_output=True,
            text=True,
            check=True,
            cwd=VALIDATOR.parents[3],
            timeout=300,
        )
        reports += [json.loads(line) for line in done.stdout.splitlines()]
    assert len(reports) == len(glbs)
    return reports


class ReportNumbers(HTMLParser):
    """A measurement report's HTML read back: data-name -> data-value of every number cell
    (`values`) and the page's text pieces (`text`)."""

    def __init__(self, html: str = ""):
        super().__init__()
        self.values, self.text = {}, []
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        attributes = dict(attrs)
        if "data-value" in attributes:
            self.values[attributes["data-name"]] = float(attributes["data-value"])

    def handle_data(self, data):
        self.text.append(data)


def glb_texture(glb: bytes) -> np.ndarray:
    """The grey texture image of a GLB."""
    gltf = pygltflib.GLTF2.load_from_bytes(glb)
    view = gltf.bufferViews[gltf.images[0].bufferView]
    data = gltf.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength]
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)


def tile_seams_grey_levels(data: Path) -> list[int]:
    """The largest grey difference along each shared border of neighbouring tiles of one level of
    a stored specimen's folder `data`."""
    textures = {
        tuple(int(p) for p in path.with_suffix("").parts[-3:]): glb_texture(path.read_bytes())
        for path in data.glob("tiles/*/*/*.glb")
    }
    worst = []
    for (level, col, row), texture in textures.items():
        for neighbour, mine, theirs in (
            ((level, col + 1, row), np.s_[:, -1], np.s_[:, 0]),
            ((level, col, row + 1), np.s_[-1], np.s_[0]),
        ):
            if neighbour in textures:
                worst.append(int(np.abs(texture[mine].astype(int) - textures[neighbour][theirs]).max()))
    return worst


def mesh_component_areas_um2(glbs: Iterable[bytes]) -> np.ndarray:
    """The area, µm², of each connected piece of the meshes of `glbs` (tiles of one level: surface
    and wall triangles, joined across tile borders where their vertices meet)."""
    meshes = []
    for glb in glbs:
        decoded = decode_glb(glb)
        triangles = np.concatenate([decoded.triangles, decoded.wall_triangles.reshape(-1, 3)])
        meshes.append(trimesh.Trimesh(decoded.positions_m, triangles, process=False))
    merged = trimesh.util.concatenate(meshes)
    merged.merge_vertices(digits_vertex=8)
    labels = trimesh.graph.connected_component_labels(merged.edges, node_count=len(merged.vertices))
    areas_m2 = np.bincount(labels[merged.faces[:, 0]], weights=merged.area_faces)
    return areas_m2[areas_m2 > 0] * 1e12
