"""Scratch folders of exports, reports and builds, named after the process that made them, so
that a store made by another process clears a killed one's and leaves a running one's."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

# Scratch folders: `{purpose}-{pid}.{start}-{random}`, named after the process that made them.
_SCRATCH_NAME = re.compile(r"[a-z-]+-(?P<pid>[0-9]+)\.(?P<start>[0-9]+)-[a-z0-9_]+")


@contextlib.contextmanager
def scratch_folder(root: Path, purpose: str) -> Iterator[Path]:
    """A new folder under `root` (a store's scratch_root) for one export's or report's files,
    removed on exit. Its name carries `purpose` (lower-case letters and '-') and this process's
    identity, so that a store made by another process removes it only once this one has gone."""
    root.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=f"{purpose}-{process_identity(os.getpid())}-", dir=root))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def remove_abandoned_scratch(root: Path) -> None:
    """Removes the scratch folders under `root` of processes that no longer run (killed mid-export);
    those of running processes stay, this one's included: several servers of one process, or
    processes of one host, may share a data directory. (Processes of separate PID namespaces, e.g.
    containers, must not share one: each would take the other's processes for gone.)"""
    if not root.is_dir():
        return
    for folder in root.iterdir():
        named = _SCRATCH_NAME.fullmatch(folder.name)
        if named and process_identity(int(named["pid"])) != f"{named['pid']}.{named['start']}":
            shutil.rmtree(folder, ignore_errors=True)


def process_identity(pid: int) -> str | None:
    """`{pid}.{start}` of a running process, its start time (clock ticks after boot, field 22 of
    /proc/PID/stat) telling it apart from a later process given the same pid, as a restarted
    container's server is; None when no process has that pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return f"{pid}.{stat.rpartition(')')[2].split()[19]}"
