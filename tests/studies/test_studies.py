"""The renderer studies (Fig. A-E) at --quick sizes: every table and figure is written and the numbers move
the way the studies claim (more samples: less noise; more lobes: better fit; optimisation: smaller error)."""
import csv

import pytest
import torch

from dibrpp.conventions import equirect_solid_angles
from studies.__main__ import main
from studies.common import procedural_envmap
from studies.joint_fit import PAPER_FIG_E
from studies.noise import unbiased_rmse

TABLES = ("fig_a_noise", "fig_a_summary", "fig_b_fit", "fig_c_ambiguity", "fig_de_joint")
FIGURES = ("fig_a_grid_brdf", "fig_a_grid_mis", "fig_a_noise", "fig_b_grid", "fig_b_error", "fig_c_ambiguity",
           "fig_e_sg", "fig_d_mc")


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("studies")
    threads = torch.get_num_threads()
    try:
        assert main(["--quick", "--out", str(out), "--threads", "1"]) == 0
    finally:
        torch.set_num_threads(threads)
    return out


def rows(out, name):
    return list(csv.DictReader(open(out / f"{name}.csv")))


def test_every_table_and_figure_is_written(quick):
    for name in TABLES:
        assert (quick / f"{name}.csv").stat().st_size > 0
        md = (quick / f"{name}.md").read_text()
        assert md.count("\n|") == len(rows(quick, name)) + 1  # header rule + one line per row
    for name in FIGURES:
        assert (quick / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
    # the optimised light, albedo and renders of every joint-optimisation row
    for r in rows(quick, "fig_de_joint"):
        tag = f"{r['shading'].lower()}_beta{float(r['beta_gt']):.2f}_ini{float(r['beta_ini']):.2f}"
        for part in ("env", "texture", "renders"):
            assert (quick / f"de_{tag}_{part}.png").exists()


def test_fig_a_noise_falls_with_samples_and_mis_helps_rough_surfaces(quick):
    table = rows(quick, "fig_a_noise")
    curve = lambda beta, sampling: [float(r["display_rmse"]) for r in table  # noqa: E731
                                    if float(r["beta"]) == beta and r["sampling"] == sampling]
    betas = sorted({float(r["beta"]) for r in table})
    for beta in betas[1:]:
        for sampling in ("BRDF", "BRDF+env MIS"):
            c = curve(beta, sampling)
            assert c[-1] < 0.7 * c[0], (beta, sampling, c)
    assert curve(betas[-1], "BRDF+env MIS")[-1] < curve(betas[-1], "BRDF")[-1]
    assert max(curve(0.0, "BRDF")) < 0.01  # a mirror is noise-free at once
    # rougher is noisier at a fixed sample count (without env-map sampling)
    assert curve(betas[-1], "BRDF")[-1] > curve(betas[1], "BRDF")[-1] > curve(0.0, "BRDF")[-1]


def test_fig_b_more_lobes_fit_better(quick):
    errors = [float(r["display_rmse"]) for r in rows(quick, "fig_b_fit")]
    assert all(b < a for a, b in zip(errors, errors[1:])), errors


def test_fig_c_fitted_smooth_light_matches_the_sharp_one(quick):
    table = {r["case"].split(",")[0]: r for r in rows(quick, "fig_c_ambiguity")}
    fitted, unfitted = table["smooth light fitted (SG)"], table["sharp light"]
    assert float(fitted["psnr_sg_view0_db"]) > float(unfitted["psnr_sg_view0_db"]) + 5
    assert float(fitted["median_lobe_sharpness"]) < float(unfitted["median_lobe_sharpness"])


def test_fig_de_joint_optimisation_reduces_the_image_error(quick):
    table = rows(quick, "fig_de_joint")
    assert {r["shading"] for r in table} == {"SG", "MC"}
    for r in table:
        assert float(r["image_l1_opt"]) < 0.5 * float(r["image_l1_init"]), r
        assert float(r["loss_last"]) < float(r["loss_first"]), r
        assert 0.035 <= float(r["beta_opt"]) <= 1 and 0 <= float(r["s_opt"]) <= 2
        assert r["within_tol"] == ("yes" if abs(float(r["beta_opt"]) - float(r["beta_gt"])) <= 0.02 else "no")
    sg = [r for r in table if r["shading"] == "SG"]
    assert all(float(r["paper_beta_opt"]) == PAPER_FIG_E[float(r["beta_gt"])][i][1] for i, r in enumerate(sg))


def test_procedural_envmap_is_hdr_and_varies_with_the_seed():
    a, b = procedural_envmap(32, 64, seed=0), procedural_envmap(32, 64, seed=1)
    assert a.image.shape == (1, 32, 64, 3) and (a.image > 0).all()
    assert a.image.max() > 100 * a.image.median()  # a sun
    assert not torch.equal(a.image, b.image)
    # an area-averaged coarse map keeps the light (mostly the sun's) that it would miss if point-sampled
    assert energy(procedural_envmap(16, 32, supersample=16)) == pytest.approx(
        energy(procedural_envmap(256, 512)), rel=0.03)
    assert not torch.equal(procedural_envmap(8, 16, sun=0.0).image, procedural_envmap(8, 16).image)


def energy(env):
    """Integral of the radiance over the sphere, (3,)."""
    h, w = env.image.shape[1:3]
    return float((equirect_solid_angles(h, w).unsqueeze(-1) * env.image[0]).sum())


def test_unbiased_rmse_ignores_the_reference_noise():
    g = torch.Generator().manual_seed(0)
    truth = torch.rand(1, 64, 64, 3, generator=g)
    noisy = lambda std: truth + std * torch.randn(truth.shape, generator=g)  # noqa: E731
    mask = torch.ones(1, 64, 64)
    rmse = unbiased_rmse(noisy(0.1), noisy(0.05), noisy(0.05), mask)
    assert rmse == pytest.approx(0.1, rel=0.05)  # the references' own noise (0.05) is not counted
