"""Tile URLs a viewer keeps or a hostile user makes up (issue 49, items 9 and 10): a tile asked for
under a build since replaced is 410 Gone, never the new build's bytes under the old URL (the web
viewer then loads the tileset again); a percent-encoded path is no alias of a tile."""

from __future__ import annotations

import json
import time

import requests
from probe_servers import READ, write_map_specimen


def _tile_url(live, specimen_id: str) -> str:
    tileset = requests.get(f"{live.http}/specimens/{specimen_id}/tileset.json", headers=READ, timeout=30)
    assert tileset.status_code == 200, tileset.text
    return f"{live.http}/specimens/{specimen_id}/" + json.loads(tileset.content)["root"]["content"]["uri"]


def test_a_tile_of_a_replaced_build_is_gone_not_the_new_builds(live):
    """Once the new build's bytes (or a 404 where its tree changed) under the old `?v=`."""
    write_map_specimen(live.store, "rebuilt", size_px=64, tile_bytes=b"glTF-first")
    old = _tile_url(live, "rebuilt")
    first = requests.get(old, headers=READ, timeout=30)
    assert first.status_code == 200 and first.content == b"glTF-first"
    assert "immutable" in first.headers["Cache-Control"]
    time.sleep(0.01)  # a new description's modification time: a new build
    write_map_specimen(live.store, "rebuilt", size_px=64, tile_bytes=b"glTF-second")
    gone = requests.get(old, headers=READ, timeout=30)
    assert gone.status_code == 410, gone.text
    assert "tileset.json" in gone.text and gone.headers["Cache-Control"] == "no-store"
    new = _tile_url(live, "rebuilt")
    assert new != old
    assert requests.get(new, headers=READ, timeout=30).content == b"glTF-second"
    # Without a build named the current one is served, looked at again soon.
    current = requests.get(old.partition("?")[0], headers=READ, timeout=30)
    assert current.content == b"glTF-second" and "immutable" not in current.headers["Cache-Control"]


def test_a_percent_encoded_tile_path_is_not_the_tile(live):
    """`tiles%2F0%2F0%2F0.glb` decodes to the root tile's path: it was served as a second URL of it."""
    write_map_specimen(live.store, "aliased", size_px=64)
    assert requests.get(_tile_url(live, "aliased"), headers=READ, timeout=30).status_code == 200
    for alias in ("tiles%2F0%2F0%2F0.glb", "tiles/0%2F0/0.glb", "tiles%2f0%2f0%2f0.glb"):
        answer = requests.get(f"{live.http}/specimens/aliased/{alias}", headers=READ, timeout=30)
        assert answer.status_code == 404, (alias, answer.status_code)
