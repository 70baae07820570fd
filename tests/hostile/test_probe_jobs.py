"""A job lost in a restart (issue 49, item 10): the folder store's server, killed while it builds a
job submitted over HTTP and started again, reports that job failed (UNAVAILABLE, submit it again),
as the object store's replicas do, where it answered 404 "no job"."""

from __future__ import annotations

import json
import time

import requests
from probe_servers import WRITE

from fractoscope.synthetic.examples import write_multiscale_specimen


def test_a_job_running_when_the_server_was_killed_is_failed_after_its_restart(server_process, tmp_path):
    example = tmp_path / "input"
    write_multiscale_specimen(example)
    manifest = json.loads((example / "manifest.json").read_text())
    parts = [("manifest", (None, json.dumps(manifest), "application/json"))]
    parts += [("images", (path.name, path.read_bytes(), "image/png")) for path in sorted(example.glob("*.png"))]
    first = server_process()
    answer = requests.post(f"{first.http}/api/jobs", files=parts, headers=WRITE, timeout=120)
    assert answer.status_code == 202, answer.text
    job_id = answer.json()["job_id"]
    deadline = time.monotonic() + 300
    while (state := requests.get(f"{first.http}/api/jobs/{job_id}", headers=WRITE, timeout=30).json())["state"] != (
        "running"
    ):
        assert state["state"] == "queued" and time.monotonic() < deadline, state
        time.sleep(0.2)
    first.stop()  # kill -9, mid-build
    second = server_process()
    job = requests.get(f"{second.http}/api/jobs/{job_id}", headers=WRITE, timeout=30)
    assert job.status_code == 200, job.text
    assert job.json()["state"] == "failed" and job.json()["error"]["code"] == "UNAVAILABLE", job.json()
    assert "submit it again" in job.json()["error"]["error"]
    listed = requests.get(f"{second.http}/api/jobs", headers=WRITE, timeout=30).json()
    assert [entry["state"] for entry in listed["jobs"] if entry["job_id"] == job_id] == ["failed"]
