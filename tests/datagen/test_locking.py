"""One datagen run per output folder (and shard) at a time: a second run is refused at once with one
``error:`` line naming the folder and the pid holding it, exit status 2. No rendering here: the lock is taken
before anything renders."""
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from datagen.layout import DatasetLayout
from datagen.locking import FolderBusy, exclusive_run

ROOT = Path(__file__).resolve().parents[2]

HOLD = """
import sys
from datagen.locking import exclusive_run
with exclusive_run(sys.argv[1], (int(sys.argv[2]), int(sys.argv[3]))):
    print("locked", flush=True)
    sys.stdin.read()  # hold until the test closes stdin (or kills this process)
"""


def _holder(out: Path, shard=(0, 1)) -> subprocess.Popen:
    """Another process holding the lock of ``shard`` in ``out``."""
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(out), *map(str, shard)], cwd=ROOT, text=True,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert p.stdout.readline().strip() == "locked"
    return p


def _release(p: subprocess.Popen) -> None:
    p.stdin.close()
    p.wait(timeout=30)


def test_a_second_datagen_into_the_same_folder_is_refused(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    holder = _holder(out)
    try:
        r = subprocess.run([sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(out),
                            "--num-objects", "1", "--num-envmaps", "1", "--envs-per-object", "1", "--quiet"],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    finally:
        _release(holder)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == [f"error: {out} is being written by another datagen run (pid {holder.pid}); wait for it or "
                     "choose another --out"], r.stderr
    assert not DatasetLayout(out).manifest.exists()  # refused before writing anything
    with exclusive_run(out):  # free again once the other run has ended
        pass


def test_a_killed_run_leaves_no_lock_behind(tmp_path):
    holder = _holder(tmp_path)
    with pytest.raises(FolderBusy):
        with exclusive_run(tmp_path):
            pass
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=30)
    assert DatasetLayout(tmp_path).run_lock().exists()  # the file stays; the lock died with its process
    with exclusive_run(tmp_path):
        pass


def test_other_shards_of_one_folder_may_run_side_by_side(tmp_path):
    holder = _holder(tmp_path, (0, 2))
    try:
        with exclusive_run(tmp_path, (1, 2)):
            pass
        with pytest.raises(FolderBusy, match=rf"\(pid {holder.pid}, shard 0/2\)"):
            with exclusive_run(tmp_path, (0, 2)):
                pass
    finally:
        _release(holder)


def test_lock_files_are_left_empty_after_a_run(tmp_path):
    with exclusive_run(tmp_path):
        assert DatasetLayout(tmp_path).run_lock().read_text() == f"{os.getpid()}\n"
    assert DatasetLayout(tmp_path).run_lock().read_text() == ""
