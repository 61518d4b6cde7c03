"""The HTML report is one static page with the tables beside the figures; checked in a headless browser."""
import json
import shutil
import subprocess

import numpy as np
import pytest

from dibrpp.io import write_png
from pipelines.evaluation.report import write_report

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def fake_eval(root, run_dir, dataset="glossy", variant="", width=120):
    d = root / dataset
    d.mkdir(parents=True, exist_ok=True)
    r = dict(run=str(run_dir), dataset=dataset, dataset_kind=dataset.split("-")[0], shading="sg", lobes=32, seed=0,
             iteration=10, trained_iterations=10, test_views=8, split="test", image_whole=0.02, image_foreground=0.05,
             iou=0.1, light_ldr=0.2, light_hdr=0.3, texture=0.2, chamfer=0.01, variant=variant)
    (d / f"{run_dir.name}.json").write_text(json.dumps(r))
    write_png(d / f"{run_dir.name}.png", np.random.default_rng(0).random((40, width, 3)).astype(np.float32))
    run_dir.mkdir(parents=True)
    write_png(run_dir / "loss.png", np.ones((20, 30, 3), np.float32))


def test_report_shows_every_evaluated_run_whatever_its_dataset_is_called(tmp_path):
    fake_eval(tmp_path / "eval", tmp_path / "runs" / "glossy" / "sg-seed0")
    fake_eval(tmp_path / "eval", tmp_path / "runs" / "hdri" / "sg-seed0", dataset="glossy-hdri")
    fake_eval(tmp_path / "eval", tmp_path / "runs" / "mine" / "probe", dataset="mydata", variant="probe-light")
    (tmp_path / "eval" / "mydata" / "notes.json").write_text("{not json")  # not a result: left out, no crash
    page = write_report(tmp_path / "eval").read_text()
    assert "Every evaluated run (3)" in page
    for heading in ("glossy / sg-seed0", "glossy-hdri / sg-seed0", "mydata / probe"):
        assert f"<h3>{heading}</h3>" in page
    assert page.count("data:image/png;base64") == 6  # each run's figure and loss curve
    assert "img{max-width:100%;height:auto}" in page and "max-width:1500px" not in page
    # the tables' line on what they leave out, each metric of each run, the split named
    assert "glossy-hdri (glossy, the tables show glossy): in all_runs.md only" in page
    assert "mydata: not one of the paper&#x27;s" in page
    assert "image_whole 0.0200, image_foreground 0.0500, iou 0.1000, light_ldr 0.2000, light_hdr 0.3000" in page
    assert "<p>Test split: unseen objects under unseen env maps." in page


@pytest.mark.skipif(BROWSER is None, reason="no chromium (make setup installs it)")
def test_report_renders_in_a_headless_browser(tmp_path):
    fake_eval(tmp_path / "eval", tmp_path / "runs" / "sg-seed0", width=2400)  # wider than any window: scaled down
    page = write_report(tmp_path / "eval")
    cmd = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", page.as_uri()]
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout
    # Tables 1 (glossy rows only), D, E and F hold the run; Table C, with no diffuse run, is left out
    assert dom.count("<table>") == 5 and "Table F" in dom and "missing: make train-glossy" in dom
    assert "Table C:" not in dom and "Table C left out" in dom
    assert "Every evaluated run (1)" in dom
    assert dom.count("data:image/png;base64") == 2  # the run's figure and its loss curve, embedded
    shot = tmp_path / "shot.png"
    subprocess.run([BROWSER, "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
                    "--window-size=1200,900", page.as_uri()], capture_output=True, timeout=120, check=True)
    assert shot.stat().st_size > 10_000
