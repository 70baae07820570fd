"""Object storage on a real S3 server (SeaweedFS): conditional writes as publishing needs them,
build leases that one holder has at a time and that run out, builds killed at any write that
leave the published specimen whole and only objects that the sweep removes, jobs of a replica
that stopped, and a restart of the object store that clients see as 503 and recover from."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import requests
from conftest import write_small_specimen
from s3_server import BUCKET, SeaweedFs, environment

from fractoscope.errors import ResourceExhaustedError
from fractoscope.http.server import start_http_server
from fractoscope.specimen.quadtree import TileKey
from fractoscope.store.leases import Lease, LeaseLost, held
from fractoscope.store.objects import ObjectMissing, PreconditionFailed, S3Objects
from fractoscope.store.s3 import ObjectSpecimenStore

ROOT_TILE = TileKey(0, 0, 0)


def test_conditional_writes_are_enforced(s3_objects):
    first = s3_objects.put("pointer", b"1", if_absent=True)
    with pytest.raises(PreconditionFailed):
        s3_objects.put("pointer", b"2", if_absent=True)
    second = s3_objects.put("pointer", b"3", if_match=first)
    with pytest.raises(PreconditionFailed):
        s3_objects.put("pointer", b"4", if_match=first)  # a writer that read before the last write
    assert s3_objects.get("pointer") == (b"3", second)
    with pytest.raises(ObjectMissing):
        s3_objects.get("nothing")
    assert [listed.key for listed in s3_objects.list()] == ["pointer"]


def test_a_lease_has_one_holder_until_it_runs_out(s3_objects):
    # Both hold for long, so that no step depends on how fast a busy machine makes it; the first
    # holder's death is its record running out, written so.
    first = Lease(s3_objects, "leases/steel-1.json", what="specimen 'steel-1'", ttl_s=60.0)
    second = Lease(s3_objects, "leases/steel-1.json", what="specimen 'steel-1'", ttl_s=60.0)
    first.take()
    with pytest.raises(ResourceExhaustedError) as busy:
        second.take()
    assert "another replica" in str(busy.value) and 0 < busy.value.retry_after_s <= 60.0
    ran_out = {"holder": first.holder, "expires_s": time.time() - 1.0}  # the first holder died: its lease ran out
    s3_objects.put("leases/steel-1.json", json.dumps(ran_out).encode())
    second.take()
    with pytest.raises(LeaseLost):
        first.renew()
    first.release()  # not the holder any more: the lease stays
    with pytest.raises(ResourceExhaustedError):
        first.take()
    second.release()
    with held(first):
        assert json.loads(s3_objects.get("leases/steel-1.json").data)["holder"] == first.holder
    with pytest.raises(ObjectMissing):
        s3_objects.get("leases/steel-1.json")


def test_a_held_lease_is_renewed_while_its_build_runs(s3_objects):
    builder = Lease(s3_objects, "leases/steel-1.json", what="specimen 'steel-1'", ttl_s=6.0)
    with held(builder):
        time.sleep(12.0)  # twice its time: renewed meanwhile (every 2 s, so a late renewal still comes in time)
        with pytest.raises(ResourceExhaustedError):
            Lease(s3_objects, "leases/steel-1.json", what="specimen 'steel-1'", ttl_s=6.0).take()


# Publishes build 1, then writes build 2 in a forked child killed just before its k-th object
# write (blobs, manifest, pointer), for each k until one completes.
_KILLING_WRITER = """
import os, signal, sys
sys.path.insert(0, sys.argv[1])
from conftest import write_small_specimen
from fractoscope.store.objects import S3Objects
from fractoscope.store.s3 import ObjectSpecimenStore

bucket, prefix, scratch = sys.argv[2:5]
store = lambda: ObjectSpecimenStore(S3Objects(bucket, prefix), scratch, pointer_ttl_s=0.0)
write_small_specimen(store(), "steel-1", height_um=1.0, request_id="build-1")
for kill_at in range(1, 100):
    child = os.fork()
    if child == 0:
        original, steps = S3Objects.put, []
        def put(self, *args, **kwargs):
            steps.append(1)
            if len(steps) == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            return original(self, *args, **kwargs)
        S3Objects.put = put
        write_small_specimen(store(), "steel-1", height_um=2.0, request_id="build-2")
        os._exit(0)
    _, status = os.waitpid(child, 0)
    print(kill_at, os.waitstatus_to_exitcode(status), store().load("steel-1").request_id, flush=True)
    if status == 0:
        break
"""


def test_a_build_killed_at_any_write_leaves_the_published_one_whole(s3_objects, tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            _KILLING_WRITER,
            str(Path(__file__).parents[2]),
            s3_objects.bucket,
            s3_objects.prefix,
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    runs = [line.split() for line in done.stdout.splitlines()]
    assert len(runs) >= 6  # four files, the manifest, the pointer
    assert all(code == str(-signal.SIGKILL) and served == "build-1" for _, code, served in runs[:-1])
    assert runs[-1][1:] == ["0", "build-2"]
    store = ObjectSpecimenStore(s3_objects, tmp_path, pointer_ttl_s=0.0)
    published = store.load("steel-1")
    before = {listed.key for listed in s3_objects.list("builds/")}
    assert len({key.split("/")[2] for key in before}) > 2  # killed builds left objects (those killed late)
    assert store.sweep() == 0  # all within the grace period
    assert store.sweep(now_s=time.time() + store.grace_s + 60) > 0
    after = {listed.key for listed in s3_objects.list("builds/")}
    assert {key.split("/")[2] for key in after} == {published.version}
    assert published.tile_bytes(ROOT_TILE.uri) == b"glTF\x02"
    np.testing.assert_array_equal(published.heights("overview").z_um, np.full((16, 24), 2.0, np.float32))


def test_replicas_on_one_bucket_see_each_others_builds(s3_objects, tmp_path):
    writer = ObjectSpecimenStore(s3_objects, tmp_path / "a", pointer_ttl_s=0.0)
    reader = ObjectSpecimenStore(s3_objects, tmp_path / "b", pointer_ttl_s=0.0)
    write_small_specimen(writer, "steel-1", height_um=1.0)
    assert reader.ids() == ["steel-1"] and reader.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x01"
    with writer.building("steel-1"), pytest.raises(ResourceExhaustedError):
        with reader.building("steel-1"):
            pass
    write_small_specimen(writer, "steel-1", height_um=3.0)
    assert reader.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x03"


def test_a_job_whose_replica_stopped_is_reported_failed(s3_objects):
    """Another replica's unfinished job whose record went unwritten for the set time is listed and
    answered as failed (UNAVAILABLE); a fresh one and a finished one stay as written. A replica
    rewrites its own unfinished jobs' records six times as often, so they stay fresh."""
    from fractoscope.http.build_jobs import BuildJobs, HttpBuildJob

    records = {}
    for name, state, age_s in (("fresh", "running", 0), ("silent", "running", 120), ("done", "succeeded", 120)):
        job = HttpBuildJob(f"{len(records):032x}", "s", name, "", state=state)
        record = json.loads(job.record())
        record["updated_s"] -= age_s
        s3_objects.put(f"jobs/{job.id}.json", json.dumps(record).encode())
        records[name] = job.id
    jobs = BuildJobs(None, workers=1, queue_limit=1, objects=s3_objects, lost_after_s=60)
    try:
        assert jobs.get(records["fresh"]).state == "running" and jobs.get(records["done"]).state == "succeeded"
        lost = jobs.get(records["silent"])
        assert lost.state == "failed" and lost.error["code"] == "UNAVAILABLE" and "stopped" in lost.error["error"]
        assert {job.request_id: job.state for job in jobs.listed()} == {
            "fresh": "running",
            "silent": "failed",
            "done": "succeeded",
        }
    finally:
        jobs.close()
    own = BuildJobs(None, workers=1, queue_limit=1, objects=s3_objects, lost_after_s=0.6)
    try:
        mine = HttpBuildJob("f" * 32, "s", "mine", "", state="running")
        own._jobs[mine.id] = mine  # as submit() keeps it while its build runs
        own._write(mine)
        key = f"jobs/{mine.id}.json"
        written_s, deadline = json.loads(s3_objects.get(key).data)["updated_s"], time.monotonic() + 60
        while json.loads(s3_objects.get(key).data)["updated_s"] == written_s:  # rewritten, unchanged
            assert time.monotonic() < deadline, "the record of an unfinished job was not rewritten"
            time.sleep(0.05)
        assert own.get(mine.id).state == "running"  # from memory
    finally:
        own.close()


@pytest.mark.server
def test_an_object_store_restart_is_answered_503_then_served_again_with_nothing_lost(tmp_path):
    """A replica whose object store stops answers what it has not cached with 503 and a retry
    hint (a timeout at most, never a hang or a 500), serves what it cached, and once the store is
    back serves everything it stored before, unchanged."""
    server = SeaweedFs(tmp_path / "weed")
    (tmp_path / "weed").mkdir()
    server.start()
    try:
        with environment(server.environment):
            store = ObjectSpecimenStore(S3Objects(BUCKET, "restart"), tmp_path / "scratch", pointer_ttl_s=0.0)
        write_small_specimen(store, "read-before", height_um=1.0)
        write_small_specimen(store, "read-after", height_um=2.0)
        http = start_http_server(store)
        base = f"http://127.0.0.1:{http.server_port}/specimens"
        try:
            assert requests.get(f"{base}/read-before/{ROOT_TILE.uri}", timeout=30).content == b"glTF\x01"
            server.stop()
            cached = requests.get(f"{base}/read-before/{ROOT_TILE.uri}", timeout=60)
            assert cached.status_code in (200, 503)  # the body cache holds it; the pointer may be looked up again
            down = requests.get(f"{base}/read-after/{ROOT_TILE.uri}", timeout=60)
            assert down.status_code == 503 and down.headers["Retry-After"] == "5", down.text
            server.start()
            again = requests.get(f"{base}/read-after/{ROOT_TILE.uri}", timeout=60)
            assert again.status_code == 200 and again.content == b"glTF\x02"
            assert requests.get(f"{base}/read-before/{ROOT_TILE.uri}", timeout=60).content == b"glTF\x01"
        finally:
            http.shutdown()
    finally:
        server.stop()
