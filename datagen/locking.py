"""One datagen run per output folder and shard at a time: two runs of one shard would render the same views
twice, and a run with other settings must not slip in between another's manifest check and its write.

A run holds an exclusive ``flock`` on its shard's lock file for as long as it runs (shards of one dataset
may run side by side, on one machine or several sharing the folder), and briefly the folder's manifest
lock while it checks and writes the manifest. The kernel drops a lock when its process ends, however it
ends (kill -9 included), so a stale lock file never blocks anyone. Lock files are left in place: deleting
one races with a run that has just opened it.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from dibrpp.io import DataError

from .layout import DatasetLayout


class FolderBusy(DataError):
    """Another datagen run is writing the same shard into the folder."""


@contextlib.contextmanager
def exclusive_run(out, shard: tuple[int, int] = (0, 1)):
    """Hold the lock of ``shard`` in ``out`` for the block; FolderBusy at once (no waiting) if another run
    holds it: a user who started the same command twice wants to know, not to wait an hour."""
    fd = os.open(DatasetLayout(out).run_lock(*shard), os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            which = "" if shard == (0, 1) else f", shard {shard[0]}/{shard[1]}"
            raise FolderBusy(f"{Path(out)} is being written by another datagen run (pid {_holder(fd)}{which}); "
                             "wait for it or choose another --out") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())  # named in the message of a run refused meanwhile
        try:
            yield
        finally:
            os.ftruncate(fd, 0)  # a finished run leaves an empty file (the same after every run)
    finally:
        os.close(fd)  # releases the lock


@contextlib.contextmanager
def manifest_lock(out):
    """Hold ``out``'s manifest lock for the block (waiting for it: others hold it for milliseconds)."""
    fd = os.open(DatasetLayout(out).manifest_lock, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _holder(fd: int) -> str:
    """The pid the lock file names ('unknown' while its holder has not written it yet)."""
    text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    return text if text.isdigit() else "unknown"
