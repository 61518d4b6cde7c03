"""Worker processes never outlive their run: kill -9 of ``python -m datagen`` takes its bpy workers (~800 MB
each) with it, and none of them finishes a sample afterwards. Real processes, real Cycles, tiny sizes."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytest.importorskip("xatlas")

pytestmark = pytest.mark.cycles

ROOT = Path(__file__).resolve().parents[2]
# One sample of many views, so that the run is still rendering it when the test kills the parent.
ARGS = ["--dataset", "glossy", "--num-objects", "1", "--num-envmaps", "1", "--envs-per-object", "1", "--views", "48",
        "--resolution", "64", "--spp", "32", "--texture-size", "64", "--envmap-height", "8", "--grid", "32",
        "--workers", "2", "--no-preview", "--quiet"]


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for its reaper counts as dead)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _workers(parent: int) -> list[int]:
    """The multiprocessing workers ``parent`` has started."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent and b"spawn_main" in cmd:
            found.append(int(d.name))
    return found


def _wait_for(condition, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_the_run_takes_its_workers_along_and_frees_the_folder(tmp_path):
    out = tmp_path / "ds"
    run = subprocess.Popen([sys.executable, "-m", "datagen", *ARGS, "--out", str(out)], cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        sample = _wait_for(lambda: next(iter((out / "samples").glob("obj_*")), None) if run.poll() is None else
                           pytest.fail(f"datagen ended early: {run.stderr.read().decode()}"), 300, "a sample to start")
        workers = _wait_for(lambda: _workers(run.pid), 30, "the workers")
        # A second run into the same folder is refused at once while the first one renders.
        second = subprocess.run([sys.executable, "-m", "datagen", *ARGS, "--out", str(out)], cwd=ROOT,
                                capture_output=True, text=True, timeout=120)
        assert second.returncode == 2 and second.stderr.strip() == (
            f"error: {out} is being written by another datagen run (pid {run.pid}); wait for it or choose another "
            "--out"), second.stderr
        assert not (sample / "sample.json").exists(), "the sample finished before the test could kill the run"
        run.send_signal(signal.SIGKILL)
        run.wait(timeout=30)
        _wait_for(lambda: not any(_alive(w) for w in workers), 5, f"workers {workers} to die with their parent")
        time.sleep(2)
        assert not (sample / "sample.json").exists()  # no orphan finished the sample
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    # The lock died with the run: the same command resumes (checked without rendering: a changed setting is
    # refused by the manifest check, not by the lock).
    again = subprocess.run([sys.executable, "-m", "datagen", *ARGS, "--spp", "8", "--out", str(out)], cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "different settings" in again.stderr, again.stderr
