"""Smoke runs of the benchmarks: they run end to end and write their tables (numbers are not asserted)."""
import csv

import pytest

from benchmarks import renderer as bench_renderer
from benchmarks import train_step as bench_train


@pytest.mark.slow  # torch.compile of the SG shader and every case once: ~25 CPU-s, ~45 s on 2 busy cores
def test_renderer_benchmark_quick(tmp_path):
    bench_renderer.main(["--quick", "--out", str(tmp_path)])
    rows = list(csv.DictReader(open(tmp_path / "renderer.csv")))
    cases = {r["case"] for r in rows}
    assert any("torch.compile" in c for c in cases) and any(c.startswith("MC") for c in cases)
    assert all(float(r["ms"]) > 0 for r in rows)
    assert (tmp_path / "renderer.md").read_text().count("\n") == len(rows) + 2
    table_a = (tmp_path / "table_a.md").read_text()  # quick mode measures K, N in {1, 4}: the rest is blank
    assert "| paper, GPU, forward (ms) | 2.6 |" in table_a and "| ours with MIS, path replay, forward (ms) | " in table_a
    assert "| ours with MIS, plain autograd, forward+backward (ms) | " in table_a


def test_training_benchmark_splits_an_iteration(tiny_glossy, tmp_path):
    assert bench_train.main(["--dataset", str(tiny_glossy), "--shading", "sh", "--iterations", "1", "--warmup", "1",
                             "--out", str(tmp_path)]) == 0
    row = next(csv.DictReader(open(tmp_path / "train.csv")))
    parts = sum(float(row[k]) for k in bench_train.PHASES)
    assert abs(parts - float(row["total"])) < 0.05 * float(row["total"]) + 1
    assert bench_train.main(["--dataset", str(tmp_path / "missing")]) == 2
    assert bench_train.main(["--dataset", str(tiny_glossy), "--variant", "no-such-variant"]) == 2


def test_training_benchmark_puts_each_step_against_sgs(tmp_path):
    from pipelines.training.config import TrainConfig

    phases = dict(data=0.0, encoder=40.0, backward=100.0, optimizer=5.0)
    results = [{"shading": s, **phases, "render+losses": r, "total": 145.0 + r} for s, r in (("sg", 55.0), ("mc", 255.0))]
    bench_train.write_results(results, TrainConfig(), 64, 3, tmp_path)
    rows = {r["shading"]: r for r in csv.DictReader(open(tmp_path / "train.csv"))}
    assert float(rows["sg"]["x SG"]) == 1.0 and float(rows["mc"]["x SG"]) == 2.0
    assert "| mc | 0 | 40 | 255 | 100 | 5 | 400 | 2.00 |" in (tmp_path / "train.md").read_text()
