"""Deployment files, checked against what the server accepts, and the services split into three
processes on loopback as the compose file and the Kubernetes manifests run them."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
import yaml
from conftest import fracture_pair, tiff_bytes
from tools import required_tool

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.sem.image import read_sem_image
from fractoscope.server.config import SERVICE_NAMES, ServerConfig, build_parser
from fractoscope.server.main import create_server
from fractoscope.specimen.tileset import content_uris
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_series_height_map
from fractoscope.synthetic.examples import write_multiscale_specimen

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
TOOLS = ROOT / ".tools"  # installed by `make test` (tests/tools.py)


def _k8s_documents() -> list[dict]:
    kustomization = yaml.safe_load((DEPLOY / "k8s" / "kustomization.yaml").read_text())
    documents = []
    for resource in kustomization["resources"]:
        documents += [d for d in yaml.safe_load_all((DEPLOY / "k8s" / resource).read_text()) if d]
    return documents


def test_kubernetes_deployments_are_probed_limited_and_unprivileged():
    documents = _k8s_documents()
    deployments = [d for d in documents if d["kind"] == "Deployment"]
    services = {d["metadata"]["name"]: d for d in documents if d["kind"] == "Service"}
    assert {d["metadata"]["name"] for d in deployments} == set(SERVICE_NAMES)
    for deployment in deployments:
        pod = deployment["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        (container,) = pod["containers"]
        assert container["image"] == "fractoscope"
        assert container["securityContext"]["readOnlyRootFilesystem"] is True
        assert container["readinessProbe"]["grpc"]["port"] == 50051
        assert {"grpc": 50051} == {p["name"]: p["containerPort"] for p in container["ports"] if p["name"] == "grpc"}
        assert container["resources"]["requests"]["cpu"] and container["resources"]["limits"]["memory"]
        args = build_parser().parse_args(container["args"])  # the real server accepts them
        assert args.services == deployment["metadata"]["name"]
        for variable in container.get("env", []):
            if variable["name"].endswith(("_ADDRESS", "_PEERS")):
                host = variable["value"].removeprefix("dns:///").split(".")[0]
                assert host in services and services[host]["spec"].get("clusterIP") == "None"  # headless: round-robin
        selector = services[deployment["metadata"]["name"]]["spec"]["selector"]
        assert selector.items() <= deployment["spec"]["template"]["metadata"]["labels"].items()
    assert next(d for d in deployments if d["metadata"]["name"] == "matching")["spec"]["replicas"] >= 2


def test_tile_replicas_share_object_storage_and_roll_over_one_at_a_time():
    """Tiles: two replicas or more, replaced one at a time, at least one through any voluntary
    disruption, scaled on CPU; specimens in object storage (no volume claim), its keys from a Secret."""
    documents = {(d["kind"], d["metadata"]["name"]): d for d in _k8s_documents()}
    assert not [kind for kind, _ in documents if kind == "PersistentVolumeClaim"]
    tiles = documents["Deployment", "tiles"]["spec"]
    assert tiles["replicas"] >= 2 and tiles["strategy"]["type"] == "RollingUpdate"
    assert tiles["strategy"]["rollingUpdate"]["maxUnavailable"] == 0
    pod = tiles["template"]["spec"]
    assert all("persistentVolumeClaim" not in volume for volume in pod["volumes"])
    (container,) = pod["containers"]
    environment = {variable["name"]: variable["value"] for variable in container["env"]}
    assert build_parser().parse_args([]).store is None  # the folder store stays the default
    assert environment["FRACTO_STORE"].startswith("s3://")
    assert container["envFrom"] == [{"secretRef": {"name": "object-store"}}]
    budget = documents["PodDisruptionBudget", "tiles"]["spec"]
    assert budget["minAvailable"] == 1 and budget["selector"]["matchLabels"] == {"app": "tiles"}
    autoscaler = documents["HorizontalPodAutoscaler", "tiles"]["spec"]
    assert autoscaler["scaleTargetRef"]["name"] == "tiles" and autoscaler["minReplicas"] >= 2
    assert autoscaler["metrics"][0]["resource"]["name"] == "cpu"


def _kubeconform(manifests: str) -> subprocess.CompletedProcess:
    kubeconform = required_tool(".tools/bin/kubeconform", ".tools/bin/kubeconform")
    required_tool(".tools/kubernetes-schemas/.written", ".tools/kubernetes-schemas/.written")
    schemas = TOOLS / "kubernetes-schemas"
    command = [
        kubeconform,
        "-strict",
        "-summary",
        "-schema-location",
        f"{schemas}/{{{{ .ResourceKind }}}}{{{{ .KindSuffix }}}}.json",
        "-",
    ]
    return subprocess.run(command, input=manifests, capture_output=True, text=True, timeout=60)


def _kustomize_build() -> str:
    built = subprocess.run(
        [required_tool(".tools/bin/kustomize", ".tools/bin/kustomize"), "build", str(DEPLOY / "k8s")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert built.returncode == 0, built.stderr
    return built.stdout


def test_kubernetes_manifests_are_valid_against_the_api_schemas():
    """`kubectl apply -k deploy/k8s` as kustomize renders it, checked by kubeconform against the
    Kubernetes 1.31 API with unknown fields refused."""
    manifests = _kustomize_build()
    result = _kubeconform(manifests)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Valid: 9, Invalid: 0, Errors: 0, Skipped: 0" in result.stdout
    version = (ROOT / "VERSION").read_text().strip()
    assert manifests.count("namespace: fractoscope") >= 7 and f"image: fractoscope:{version}" in manifests


def test_kubeconform_refuses_a_misspelt_field_and_a_wrong_type():
    manifests = _kustomize_build()
    for broken in (
        manifests.replace("readOnlyRootFilesystem", "readOnlyRootFilesytem"),
        manifests.replace("replicas: 3", "replicas: three"),
    ):
        assert broken != manifests
        result = _kubeconform(broken)
        assert result.returncode != 0 and "Invalid: 0" not in result.stdout, result.stdout


def test_compose_and_image_run_the_server_as_a_user():
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    assert set(compose["services"]) == {*SERVICE_NAMES, "s3", "gateway"}
    for name in SERVICE_NAMES:
        args = build_parser().parse_args(compose["services"][name]["command"])
        assert args.services == name
    tiles = compose["services"]["tiles"]
    assert build_parser().parse_args(tiles["command"]).store.startswith("s3://") and tiles["deploy"]["replicas"] >= 2
    assert "ports" not in tiles and compose["services"]["gateway"]["ports"] == ["50051:50051", "8080:8080"]
    assert tiles["environment"]["AWS_ENDPOINT_URL"] == "http://s3:8333"
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert dockerfile.count("\nFROM ") + dockerfile.startswith("FROM ") >= 2  # multi-stage
    assert "\nUSER 10001" in dockerfile and 'ENTRYPOINT ["fracto-server"]' in dockerfile


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _healthy(address: str) -> bool:
    return (
        subprocess.run(
            [sys.executable, "-m", "fractoscope.server.healthcheck", address], capture_output=True
        ).returncode
        == 0
    )


def _start_server(port: int, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fractoscope.server.main",
            "--address",
            f"127.0.0.1:{port}",
            "--http-address",
            "",
            *args,
        ],
        env={**os.environ, "GRPC_VERBOSITY": "ERROR"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _wait_until_healthy(ports, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not all(_healthy(f"127.0.0.1:{port}") for port in ports):
        assert time.monotonic() < deadline, "servers did not become healthy"
        time.sleep(0.5)


class Stack:
    """The three services as separate `fracto-server` processes on loopback, as deployed."""

    def __init__(self, data: Path):
        self.ports = {name: _free_port() for name in SERVICE_NAMES}
        self.commands = {
            "matching": ["--services", "matching"],
            "meshing": ["--services", "meshing"],
            "tiles": [
                "--services",
                "tiles",
                "--data",
                str(data),
                "--matching-address",
                f"dns:///127.0.0.1:{self.ports['matching']}",
                "--meshing-address",
                f"127.0.0.1:{self.ports['meshing']}",
            ],
        }
        self.processes = {name: self._start(name) for name in SERVICE_NAMES}
        self.wait_until_healthy()

    def _start(self, name: str) -> subprocess.Popen:
        return _start_server(self.ports[name], *self.commands[name])

    def wait_until_healthy(self) -> None:
        _wait_until_healthy(self.ports.values())

    def kill(self, name: str) -> None:
        self.processes[name].kill()
        self.processes[name].wait()

    def restart(self, name: str) -> None:
        self.processes[name] = self._start(name)
        self.wait_until_healthy()

    def stop(self) -> list[int]:
        for process in self.processes.values():
            process.terminate()
        return [process.wait(timeout=60) for process in self.processes.values()]


@pytest.mark.slow
def test_three_processes_build_a_specimen_and_answer_health_checks(tmp_path):
    stack = Stack(tmp_path / "data")
    try:
        write_multiscale_specimen(tmp_path / "input")
        specimen_id, rois = load_manifest(tmp_path / "input" / "manifest.json")
        with FractoscopeClient(f"127.0.0.1:{stack.ports['tiles']}", timeout_s=300) as client:
            summary = client.reconstruct_specimen(specimen_id, rois)
        assert [roi["id"] for roi in summary["rois"]] == ["overview", "zoom"]
        assert not _healthy(f"127.0.0.1:{_free_port()}")
    finally:
        assert stack.stop() == [0, 0, 0]  # SIGTERM: graceful stop


@pytest.mark.slow
@pytest.mark.parametrize(
    "victim, during", [("matching", "matching ROI overview"), ("meshing", "tile"), ("tiles", "tile")]
)
def test_a_service_killed_mid_reconstruction_leaves_nothing_half_written(tmp_path, victim, during):
    """One service dies mid-reconstruction (matching while the overview is matched, meshing or
    the tile service itself while tiles are meshed): the call fails as UNAVAILABLE, no specimen
    and no staging folder remain once the tile service runs, and the same request after a
    restart completes it."""
    import threading

    stack = Stack(tmp_path / "data")
    write_multiscale_specimen(tmp_path / "input")
    specimen_id, rois = load_manifest(tmp_path / "input" / "manifest.json")
    specimens = tmp_path / "data" / "specimens"
    try:
        with FractoscopeClient(f"127.0.0.1:{stack.ports['tiles']}", timeout_s=300) as client:
            reached = threading.Event()

            def watch(fraction: float, message: str) -> None:
                if message.startswith(during):
                    reached.set()

            outcome = {}

            def build() -> None:
                try:
                    outcome["summary"] = client.reconstruct_specimen(
                        specimen_id, rois, request_id="job-1", on_progress=watch
                    )
                except ClientError as error:
                    outcome["error"] = error

            worker = threading.Thread(target=build)
            worker.start()
            assert reached.wait(120)
            stack.kill(victim)
            worker.join(120)
            assert "error" in outcome, f"the build should have failed with {victim} gone"
            assert outcome["error"].code == grpc.StatusCode.UNAVAILABLE, outcome["error"]
            if victim != "tiles":  # the tile service lived to say so, and cleaned up after the failed build
                assert "retry" in str(outcome["error"])
                assert client.list_specimens() == [] and not list(specimens.glob(".staging-*"))
            else:
                assert list(specimens.glob(".staging-*")), list(
                    specimens.iterdir()
                )  # the killed build left its half-written folder
            stack.restart(victim)  # a restarted tile service discards what its killed self left
            assert client.list_specimens() == [] and not (specimens / specimen_id).exists()
            assert not list(specimens.glob(".staging-*"))
            summary = client.reconstruct_specimen(specimen_id, rois, request_id="job-1")
            tileset = client.get_tileset(specimen_id)
        uris = content_uris(tileset)
        assert summary["id"] == specimen_id and all((specimens / specimen_id / uri).is_file() for uri in uris)
    finally:
        stack.stop()


@pytest.mark.slow
def test_matching_replicas_share_the_strips_of_a_pair_and_the_stitched_map_is_exact():
    """A matching process with two strip peers (round-robin over their addresses) farms the strips
    of a pair out and stitches them: the height map is the one a single process computes, to
    the bit. With one peer killed, the other matches every strip."""
    pair = fracture_pair(seed=5)
    files = [tiff_bytes(image) for image in (pair.first, pair.second)]
    strip_pixels = 100_000
    local = compute_series_height_map(
        [read_sem_image(content) for content in files],
        tilt_deg=(-5.0, 5.0),
        pixel_size_um=0.1,
        options=MatchingOptions(strip_pixels=strip_pixels),
    )
    assert local.report["strip_count"] >= 3

    peer_ports = [_free_port(), _free_port()]
    coordinator_port = _free_port()
    peers = [_start_server(port, "--services", "matching") for port in peer_ports]
    coordinator = _start_server(
        coordinator_port,
        "--services",
        "matching",
        "--strip-pixels",
        str(strip_pixels),
        "--strip-peers",
        "ipv4:" + ",".join(f"127.0.0.1:{port}" for port in peer_ports),
    )
    try:
        _wait_until_healthy([*peer_ports, coordinator_port])
        with FractoscopeClient(f"127.0.0.1:{coordinator_port}", timeout_s=300) as client:

            def height_map():
                return client.compute_height_map(files, tilt_deg=(-5, 5), pixel_size_um=0.1)

            height_map()  # connects the coordinator to both peers
            farmed_out = height_map()
            np.testing.assert_array_equal(farmed_out.z_um, local.z_um)
            np.testing.assert_array_equal(farmed_out.sigma_um, local.sigma_um)
            assert farmed_out.report["strip_count"] == local.report["strip_count"]
            assert len(farmed_out.report["strip_workers"]) == 2
            json.loads(json.dumps(farmed_out.report))  # plain values, as specimens store reports

            # Normalized local contrast (the default) is computed before the split, so the peers
            # got float strips above; without it they get the images' own values.
            contrast_options = MatchingOptions(strip_pixels=strip_pixels, normalize_local_contrast=False)
            contrast_local = compute_series_height_map(
                [read_sem_image(content) for content in files],
                tilt_deg=(-5.0, 5.0),
                pixel_size_um=0.1,
                options=contrast_options,
            )
            contrast_farmed_out = client.compute_height_map(
                files, tilt_deg=(-5, 5), pixel_size_um=0.1, normalize_local_contrast=False
            )
            np.testing.assert_array_equal(contrast_farmed_out.z_um, contrast_local.z_um)
            assert not np.array_equal(contrast_local.z_um, local.z_um, equal_nan=True)

            # Propagation at full resolution runs inside each strip: the setting travels with them.
            propagated_local = compute_series_height_map(
                [read_sem_image(content) for content in files],
                tilt_deg=(-5.0, 5.0),
                pixel_size_um=0.1,
                options=MatchingOptions(strip_pixels=strip_pixels, propagate_at_full_resolution=True),
            )
            propagated_farmed_out = client.compute_height_map(
                files, tilt_deg=(-5, 5), pixel_size_um=0.1, propagate_at_full_resolution=True
            )
            np.testing.assert_array_equal(propagated_farmed_out.z_um, propagated_local.z_um)
            assert not np.array_equal(propagated_local.z_um, local.z_um, equal_nan=True)

            peers[0].kill()
            peers[0].wait()
            survivor = height_map()
            np.testing.assert_array_equal(survivor.z_um, local.z_um)
            assert len(survivor.report["strip_workers"]) == 1
    finally:
        for process in (*peers, coordinator):
            process.terminate()
            process.wait(timeout=60)


@pytest.mark.server
def test_a_replica_that_is_its_own_strip_peer_never_deadlocks():
    """Two height maps at once on a replica whose strip peer is itself: both farm their strips out
    to it, whose strips run on workers of their own that wait on nothing, and both finish."""
    from concurrent.futures import ThreadPoolExecutor

    pair = fracture_pair(size_px=384, seed=6)
    files = [tiff_bytes(image) for image in (pair.first, pair.second)]
    port = _free_port()
    server, _ = create_server(
        ServerConfig(
            address=f"127.0.0.1:{port}",
            services=("matching",),
            workers=2,
            build_workers=2,
            strip_peers=f"127.0.0.1:{port}",
            strip_pixels=50_000,
        )
    )
    server.start()
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=120) as client, ThreadPoolExecutor(2) as pool:
            jobs = [
                pool.submit(client.compute_height_map, files, tilt_deg=(-5, 5), pixel_size_um=0.1) for _ in range(2)
            ]
            reports = [job.result().report for job in jobs]
        assert all(report["strip_count"] >= 3 for report in reports)
        assert [len(report["strip_workers"]) for report in reports] == [1, 1]  # both farmed out, to this replica
    finally:
        server.stop(grace=None)


def test_a_strip_peer_that_refuses_strips_fails_the_map_with_a_clear_status():
    """A peer of another version or with other limits: FAILED_PRECONDITION saying so, not INTERNAL."""
    from concurrent import futures

    from fractoscope.v1 import matching_pb2_grpc

    class RefusingPeer(matching_pb2_grpc.MatchingServiceServicer):
        def MatchStrip(self, request, context):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "left: too large for this replica")

    peer = grpc.server(futures.ThreadPoolExecutor(2))
    matching_pb2_grpc.add_MatchingServiceServicer_to_server(RefusingPeer(), peer)
    peer_port = peer.add_insecure_port("127.0.0.1:0")
    peer.start()
    server, port = create_server(
        ServerConfig(
            address="127.0.0.1:0", services=("matching",), strip_peers=f"127.0.0.1:{peer_port}", strip_pixels=50_000
        )
    )
    server.start()
    pair = fracture_pair(size_px=256, seed=7)
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=60) as client:
            with pytest.raises(ClientError) as refused:
                client.compute_height_map(
                    [tiff_bytes(pair.first), tiff_bytes(pair.second)], tilt_deg=(-5, 5), pixel_size_um=0.1
                )
        assert refused.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "strip peer refused" in str(refused.value) and "too large for this replica" in str(refused.value)
    finally:
        server.stop(grace=None)
        peer.stop(grace=None)


def test_a_serving_process_freezes_its_start_up_objects_and_collects_garbage_less_often():
    """settle_garbage_collector, which fracto-server and `make run` call before serving (why: its
    docstring and the load figures in docs/performance.md), run in a fresh interpreter."""
    probe = (
        "import gc, json, fractoscope.server.main; from fractoscope.runtime.process import "
        "settle_garbage_collector;before = gc.get_threshold(); settle_garbage_collector();print(json.dumps([before, "
        "gc.get_threshold(), gc.get_freeze_count()]))"
    )
    before, after, frozen = json.loads(
        subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    )
    assert before == [700, 10, 10] and after == [50_000, 20, 10]
    assert frozen > 10_000  # the objects of start-up (modules, classes), no longer scanned
