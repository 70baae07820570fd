"""A new user's first hour: `fracto demo` shows its viewer before the specimens are built, gRPC's
transport chatter stays off the terminal, and `fracto height` leaves nothing behind in the folder
it runs in. Each runs the commands as a user does, as subprocesses on loopback."""

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

FRACTO = str(Path(sys.executable).with_name("fracto"))
FRACTO_SERVER = str(Path(sys.executable).with_name("fracto-server"))
# What gRPC core writes when it logs (its glog-style prefix, e.g. "I1206 15:55:17.742296  8043
# chttp2_transport.cc:1403]"), and the words of its transport events.
GRPC_LOG_LINE = re.compile(r"^[IWEF]\d{4} \d\d:\d\d:\d\d\.\d+ +\d+ [\w./-]+:\d+\]", re.MULTILINE)
TRANSPORT_WORDS = ("goaway", "chttp2", "transport")
ANSI_ESCAPE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")  # rich's cursor moves and colours around its bar


def _environment() -> dict[str, str]:
    """The user's environment: no server named, and gRPC's logging left at its defaults."""
    return {k: v for k, v in os.environ.items() if k not in ("FRACTO_SERVER", "GRPC_VERBOSITY", "GRPC_TRACE")}


def _assert_no_grpc_chatter(stderr: str) -> None:
    assert not GRPC_LOG_LINE.search(stderr), stderr
    assert not any(word in stderr.lower() for word in TRANSPORT_WORDS), stderr


@pytest.mark.slow
def test_demo_shows_the_viewer_before_the_first_specimen_is_built(tmp_path):
    data = tmp_path / "data"
    arguments = ["--data", data, "--shared-data", tmp_path / "none", "--port", 0, "--http-port", 0]
    process = subprocess.Popen(
        [FRACTO, "demo", *map(str, arguments)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_environment(),
    )
    try:
        lines = [process.stdout.readline()]
        assert lines[0].startswith("viewer: http://127.0.0.1:"), lines[0] + process.stderr.read()
        viewer = lines[0].split()[1]
        # The URL came before the build stored anything, and the page answers: the demo serves while it builds.
        assert not (data / "specimens" / "synthetic" / "tileset.json").exists()
        with urllib.request.urlopen(viewer, timeout=30) as page:
            assert page.status == 200 and b"3d-tiles-renderer" in page.read()
        while not lines[-1].startswith("synthetic: built in "):
            lines.append(process.stdout.readline())
            assert lines[-1], "the demo stopped before the specimen was built: " + process.stderr.read()
        assert lines[-1].split()[-1] == viewer  # the link to the built specimen, the one first shown
        progress = [line for line in lines if line.startswith("synthetic: ") and " % " in line]
        assert len(progress) >= 4 and "matching ROI overview" in progress[0]  # the build was shown going on
        root = viewer.split("/viewer/")[0]
        with urllib.request.urlopen(f"{root}/api/specimens/synthetic", timeout=30) as answer:
            assert [roi["id"] for roi in json.load(answer)["rois"]] == ["overview", "zoom"]
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 0
        _assert_no_grpc_chatter(process.stderr.read())
    finally:
        if process.poll() is None:
            process.kill()


@pytest.fixture
def fracto_server(tmp_path):
    """fracto-server on a free loopback port (SIGTERM stops it at once: no grace), its JSON log
    read up to the line naming the port; yields the process and its address, killed at the end
    if still running."""
    server = subprocess.Popen(
        [FRACTO_SERVER, "--address", "127.0.0.1:0", "--http-address", "", "--data", str(tmp_path / "data")]
        + ["--grace-s", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=_environment(),
    )
    try:
        address = None
        while address is None:
            line = server.stdout.readline()
            assert line, f"fracto-server exited with {server.wait()} before serving"
            served = re.search(r"serving .* on port (\d+)", json.loads(line)["message"])
            address = served and f"127.0.0.1:{served[1]}"
        yield server, address
    finally:
        if server.poll() is None:
            server.kill()


@pytest.mark.slow
def test_a_server_that_stops_during_a_call_is_one_plain_line(fracto_server, tmp_path):
    """The server stops (SIGTERM) while `fracto reconstruct` waits on it: gRPC's client receives
    the server's GOAWAY, which neither the command nor the server may print as gRPC's own log
    lines; the command says in one sentence what happened."""
    from fractoscope.synthetic.examples import write_multiscale_specimen

    server, address = fracto_server
    write_multiscale_specimen(tmp_path / "input")
    command = subprocess.Popen(
        [FRACTO, "reconstruct", str(tmp_path / "input" / "manifest.json"), "--server", address],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**_environment(), "TTY_COMPATIBLE": "1"},  # rich draws its progress bar on the pipe
    )
    try:
        seen = b""
        while b"reconstructing: " not in seen:  # the bar shows the server's first progress message
            chunk = command.stderr.read1(4096)
            assert chunk, f"fracto reconstruct ended before its build started: {seen.decode()}"
            seen += chunk
        server.send_signal(signal.SIGTERM)
        assert command.wait(timeout=120) == 3  # UNAVAILABLE's exit code
        stderr = ANSI_ESCAPE.sub("", (seen + command.stderr.read()).decode())
        _assert_no_grpc_chatter(stderr)
        said = stderr.rstrip().splitlines()[-1]
        assert said.startswith(f"error: the Fractoscope server at {address} ") and said.endswith(
            ("closed the connection during the call (stopped?); try again", "at a running one")
        ), stderr
        assert server.wait(timeout=60) == 0
        for line in server.stdout.read().splitlines():
            json.loads(line)  # the server's log stays JSON, one object a line
    finally:
        if command.poll() is None:
            command.kill()


@pytest.mark.slow
@pytest.mark.real_data
def test_height_in_process_leaves_no_data_folder(pollen_series, tmp_path):
    """`fracto height` runs matching in-process, without the tile service and its specimen store:
    the folder it runs in holds afterwards what it wrote and nothing else."""
    left, right = pollen_series / "pot_02.tif", pollen_series / "pot_04.tif"
    done = subprocess.run(
        [FRACTO, "height", str(left), str(right), "--method", "fast", "-o", "pot.npz"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=_environment(),
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == ["pot.npz"]  # no ./data/specimens
    _assert_no_grpc_chatter(done.stderr)
