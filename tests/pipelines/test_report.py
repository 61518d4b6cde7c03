"""The HTML report is one static page with the tables beside the figures; checked in a headless browser."""
import json
import shutil
import subprocess

import numpy as np
import pytest

from dibrpp.io import write_png
from pipelines.report import write_report

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def fake_eval(root, run_dir):
    d = root / "glossy"
    d.mkdir(parents=True)
    r = dict(run=str(run_dir), dataset="glossy", shading="sg", lobes=32, seed=0, iteration=10, trained_iterations=10,
             test_views=8, image=0.05, iou=0.1, light=0.3, texture=0.2, chamfer=0.01)
    (d / f"{run_dir.name}.json").write_text(json.dumps(r))
    write_png(d / f"{run_dir.name}.png", np.random.default_rng(0).random((40, 120, 3)).astype(np.float32))
    run_dir.mkdir(parents=True)
    write_png(run_dir / "loss.png", np.ones((20, 30, 3), np.float32))


@pytest.mark.skipif(BROWSER is None, reason="no chromium (make setup installs it)")
def test_report_renders_in_a_headless_browser(tmp_path):
    fake_eval(tmp_path / "eval", tmp_path / "runs" / "sg-seed0")
    page = write_report(tmp_path / "eval")
    cmd = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", page.as_uri()]
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout
    assert dom.count("<table>") == 5 and "Table F" in dom and "missing: make train-metallic" in dom
    assert dom.count("data:image/png;base64") == 2  # the run's figure and its loss curve, embedded
    shot = tmp_path / "shot.png"
    subprocess.run([BROWSER, "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
                    "--window-size=1200,900", page.as_uri()], capture_output=True, timeout=120, check=True)
    assert shot.stat().st_size > 10_000
