"""Fixtures shared by the suites (tests/pipelines, tests/benchmarks): a tiny Cycles-rendered dataset."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

# torch.compile's cache (and its build locks) in this checkout, not in /tmp shared with every other clone and job on
# the machine: a compile there waits up to 10 min on another process's lock. The tests' subprocesses inherit it.
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".cache" / "torchinductor"))
# One torch thread per process: pytest-xdist runs a worker per core, and torch's threads wait on each other at every
# step when they outnumber the cores (a training step several times slower). Runs repeat bit for bit at one thread.
os.environ.setdefault("OMP_NUM_THREADS", "1")


def _tiny_glossy(out, objects: int, envmaps: int, envs_per_object: int, views: int):
    pytest.importorskip("bpy")
    cmd = [sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(out), "--num-objects", str(objects),
           "--num-envmaps", str(envmaps), "--envs-per-object", str(envs_per_object), "--views", str(views),
           "--resolution", "32", "--spp", "4", "--workers", "1"]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


@pytest.fixture(scope="session")
def tiny_glossy(tmp_path_factory):
    """A real (tiny) glossy dataset rendered by Cycles: 4 objects, 1 env map each, 4 views, 32 px."""
    return _tiny_glossy(tmp_path_factory.mktemp("data") / "glossy", 4, 2, 1, 4)


@pytest.fixture(scope="session")
def tiny_glossy_two_maps(tmp_path_factory):
    """Every object under two env maps: 4 objects, 2 maps each (of 3), 2 views, 32 px."""
    return _tiny_glossy(tmp_path_factory.mktemp("data") / "glossy-two-maps", 4, 3, 2, 2)
