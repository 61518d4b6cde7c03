"""Fixtures shared by the suites (tests/pipelines, tests/benchmarks): a tiny Cycles-rendered dataset."""
import subprocess
import sys

import pytest


@pytest.fixture(scope="session")
def tiny_glossy(tmp_path_factory):
    """A real (tiny) glossy dataset rendered by Cycles: 4 objects, 1 env map each, 4 views, 32 px."""
    pytest.importorskip("bpy")
    out = tmp_path_factory.mktemp("data") / "glossy"
    cmd = [sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(out), "--num-objects", "4",
           "--num-envmaps", "2", "--envs-per-object", "1", "--views", "4", "--resolution", "32", "--spp", "4",
           "--workers", "1"]
    subprocess.run(cmd, check=True, capture_output=True)
    return out
