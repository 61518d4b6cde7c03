"""studies.noise_study (how noisy a dataset's Cycles render is): its measures on hand-made images, its command
line, and one tiny run through Cycles."""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from studies import noise_study

ROOT = Path(__file__).resolve().parents[2]


def test_imports_no_learning_code_and_no_blender():
    code = ("import sys, studies.noise_study; bad = [m for m in ('pipelines', 'bpy') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_measures_remove_the_reference_noise():
    ref_img = np.zeros((4, 4, 4), np.float32)
    ref_img[..., :3] = 0.5
    ref_img[1:3, 1:3, 3] = 1.0
    mask = ref_img[..., 3] > 0.5
    ref = noise_study.Reference(ref_img, mask, noise=0.03, mean_foreground=0.5)
    img = ref_img.copy()
    img[..., :3] += 0.05  # RMSE 0.05 over the foreground
    m = noise_study.measure(img, ref)
    assert m["rmse"] == pytest.approx(0.05, rel=1e-5)
    assert m["rmse_corrected"] == pytest.approx(0.04, rel=1e-4)  # sqrt(0.05^2 - 0.03^2)
    assert m["psnr"] == pytest.approx(-20 * math.log10(0.04), rel=1e-4)
    assert m["rel"] == pytest.approx(0.08, rel=1e-4)
    assert noise_study.measure(ref_img, ref)["rmse_corrected"] == 0.0  # never below zero


def test_azimuths_table_and_file_names():
    from datagen.config import make_config

    cfg = make_config("diffuse")
    picked = noise_study.pick_azimuths(cfg, 2)
    assert len(picked) == 2 and picked[0] > -90 and picked[-1] < 90  # spread, ends left out
    summary = {name: dict(rmse_corrected=0.1, rel=0.2, psnr=20.0, cpu_seconds=c, seconds=1.0, rmse=0.1)
               for name, c in ((noise_study.BASELINE, 2.0), ("64 spp", 4.0))}
    args = noise_study.build_parser().parse_args(["--out", "x", "--variants", noise_study.BASELINE, "64 spp"])
    lines = noise_study.table(summary, [0.01], args, 1, 2, 64)
    assert lines[2].endswith("1.0x |") and lines[3].endswith("2.0x |") and "1 objects x 2 views" in lines[-1]
    assert noise_study.variant_file_name("adaptive 0.01, <=256 spp") == "adaptive_0.01_<=256_spp"
    assert noise_study.variant_file_name(noise_study.BASELINE) == "32_spp"


def test_an_unknown_variant_is_refused_by_the_command_line():
    r = subprocess.run([sys.executable, "-m", "studies.noise_study", "--out", "x", "--variants", "9 spp"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "invalid choice: '9 spp'" in r.stderr


@pytest.mark.cycles
@pytest.mark.slow
def test_a_tiny_run_writes_its_table(tmp_path):
    pytest.importorskip("bpy")
    pytest.importorskip("xatlas")
    variants = [noise_study.BASELINE, "16 spp + OIDN"]
    assert noise_study.main(["--dataset", "glossy", "--objects", "1", "--views", "1", "--resolution", "16",
                             "--ref-spp", "8", "--out", str(tmp_path), "--variants", *variants]) == 0
    result = json.loads((tmp_path / "noise.json").read_text())
    assert list(result["summary"]) == variants and len(result["reference_noise"]) == 1
    assert all(s["rmse_corrected"] >= 0 and s["cpu_seconds"] > 0 for s in result["summary"].values())
    rows = [line for line in (tmp_path / "noise.md").read_text().splitlines() if line.startswith("| ")]
    assert len(rows) == 3  # header + 2 variants
    assert (tmp_path / "obj_0000_view_0_ref.exr").exists() and (tmp_path / "obj_0000_view_0_16_spp_+_OIDN.exr").exists()
    assert (tmp_path / "assets" / "objects" / "obj_0000" / "object.json").exists()
