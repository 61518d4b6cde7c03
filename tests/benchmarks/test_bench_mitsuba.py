"""Table B benchmark (dibrpp vs Mitsuba 3 env-map optimisation): a --quick run end to end, and Mitsuba's
env-map convention against Blender's (numbers are not asserted, only that both optimisations converge)."""
import csv

import numpy as np
import pytest

from benchmarks import envmap_mitsuba
from benchmarks import mitsuba as bench_mitsuba
from benchmarks.envmap_mitsuba import MitsubaBackend
from benchmarks.envmap_task import Task


def _assert_converged(row: dict) -> None:
    assert row["status"] == "ok", row["status"]
    assert float(row["loss_final"]) < float(row["loss_init"])
    assert float(row["clean_loss_final"]) < float(row["clean_loss_init"])
    assert float(row["clean_loss_at_gt"]) < float(row["clean_loss_final"])
    assert float(row["env_rel_l2_final"]) < float(row["env_rel_l2_init"])
    assert float(row["time_s"]) > 0 and float(row["peak_mb"]) >= 0


@pytest.mark.slow  # six subprocesses (reference and optimisation per run) and Dr.Jit compiles: ~20 CPU-s
def test_quick_benchmark_optimises_with_both_renderers(tmp_path):
    # the PyTorch column (torch.compile, a minute of compilation) is left out here; tests/dibrpp covers that path
    runs = "dibrpp,dibrpp-2x,mitsuba"
    assert bench_mitsuba.main(["--quick", "--threads", "1", "--runs", runs, "--out", str(tmp_path)]) == 0
    rows = {r["run"]: r for r in csv.DictReader(open(tmp_path / "mitsuba.csv"))}
    assert list(rows) == runs.split(",")
    assert [int(rows[r]["spp"]) for r in ("dibrpp", "dibrpp-2x")] == [4, 8]
    md = (tmp_path / "mitsuba.md").read_text()
    assert "| time of 20 iterations (s) |" in md and "paper Mitsuba 2" in md and "| time / Mitsuba 3's" in md
    assert (tmp_path / "mitsuba.png").stat().st_size > 0
    _assert_converged(rows["dibrpp"])
    _assert_converged(rows["dibrpp-2x"])
    # twice the samples: a lower noise floor of the per-iteration loss
    assert float(rows["dibrpp-2x"]["loss_at_gt"]) < float(rows["dibrpp"]["loss_at_gt"])
    missing = envmap_mitsuba.mitsuba_missing(Task.variant)
    if missing:
        assert rows["mitsuba"]["status"].startswith("skipped")
        pytest.skip(envmap_mitsuba.install_hint(missing))
    _assert_converged(rows["mitsuba"])


def test_mitsuba_envmap_texels_sit_at_blender_directions():
    """Mitsuba's emitter (rotated by MITSUBA_ENV_TO_WORLD) returns texel (j, i) exactly in the world direction
    that Blender's mapping gives u = (i + .5) / W, v = j / (H - 1); a mirrored or rotated map would not."""
    task = Task(env_height=8, env_width=16, threads=1)
    missing = envmap_mitsuba.mitsuba_missing(task.variant)
    if missing:
        pytest.skip(envmap_mitsuba.install_hint(missing))
    mi, dr = envmap_mitsuba.import_mitsuba(task)
    backend = MitsubaBackend(task, mi, dr)
    data = np.random.default_rng(0).uniform(0.1, 1.0, (8, 16, 3)).astype(np.float32)
    backend.set_envmap(mi.TensorXf(data))
    dirs = backend.texel_directions().reshape(-1, 3).numpy()
    si = dr.zeros(mi.SurfaceInteraction3f, dirs.shape[0])
    si.wi = mi.Vector3f(-dirs[:, 0], -dirs[:, 1], -dirs[:, 2])  # eval() looks along -wi
    values = np.array(backend.scene.environment().eval(si)).T.reshape(data.shape)
    # the pole rows are a single point each: compare the rows in between
    np.testing.assert_allclose(values[1:-1], data[1:-1], rtol=1e-4)


def test_columns_are_named_for_the_device_they_ran_on():
    # dibrpp's C++ kernel shades on the CPU only: on CUDA its columns run PyTorch and must not claim the kernel
    runs = bench_mitsuba.RUNS
    assert runs["dibrpp"].title("cpu") == "dibrpp (C++ kernel)"
    assert runs["dibrpp"].title("cuda") == "dibrpp (PyTorch on cuda)"
    assert runs["dibrpp-2x"].title("cuda") == "dibrpp, 2x spp (PyTorch on cuda)"
    assert runs["dibrpp-pytorch"].title("cuda") == "dibrpp, PyTorch on cuda"
    assert runs["mitsuba"].title("cuda") == runs["mitsuba"].title("cpu") == "Mitsuba 3 (prb)"
