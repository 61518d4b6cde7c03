import pytest
import torch

from dibrpp import Cameras, Renderer
from dibrpp.io import DataError
from dibrpp.mesh import icosphere
from pipelines import shape_prior
from pipelines.model import Encoder, ModelConfig
from pipelines.losses import normal_loss
from pipelines.shape_prior import build, fit, fit_cameras, fit_template, read
from pipelines.template import mirror_index


def _templates(n: int, seed: int = 0) -> torch.Tensor:
    """Templates with known degrees of freedom: the sphere stretched along x and z by random amounts."""
    g = torch.Generator().manual_seed(seed)
    dirs = icosphere(3).verts[0]
    stretch = 1 + 0.3 * torch.randn(n, 1, 3, generator=g) * torch.tensor([1.0, 0.0, 1.0])
    return 12 * dirs * stretch


def test_the_prior_finds_the_templates_degrees_of_freedom():
    prior = fit(_templates(30), components=3)
    assert prior["explained"][1] > 0.9999  # two stretches, two components
    basis = prior["basis"].flatten(1)
    torch.testing.assert_close(basis @ basis.T, torch.eye(3), atol=1e-4, rtol=0)
    assert prior["std"][1] > 1e3 * prior["std"][2]


def test_a_model_with_the_prior_starts_at_its_mean_car_and_moves_along_its_components():
    prior = fit(_templates(30), components=2)
    model = Encoder(ModelConfig(image_size=32, shape_prior=2))
    model.set_shape_prior(prior)
    raw = model.shape_head.bias.detach()[None].clone()
    torch.testing.assert_close(model._shape(raw)[0], prior["mean"], atol=1e-4, rtol=0)
    raw[0, -5] = 1.0  # the first coefficient: one spread of the first component (tanh's bound barely bends it)
    moved = model._shape(raw)[0] - prior["mean"]
    expected = 3.0 * torch.tanh(torch.tensor(1 / 3.0)) * prior["std"][0] * prior["basis"][0]
    torch.testing.assert_close(moved, expected, atol=1e-4, rtol=0)


def test_the_smoothness_leaves_the_prior_s_car_alone():
    prior = fit(_templates(30), components=2)
    model = Encoder(ModelConfig(image_size=32, shape_prior=2))
    model.set_shape_prior(prior)
    with torch.no_grad():
        pred = model(torch.rand(2, 4, 32, 32), Cameras.orbit(60.0, 27.0, torch.tensor([0.0, 90.0]), 39.6, 32))
    torch.testing.assert_close(pred.deformation(), pred.verts - pred.prior_shape)
    # untrained, the offsets are zero and the scale the template radius: what is left to smooth is the sphere
    torch.testing.assert_close(pred.deformation(), 12 * model.template_dirs.expand(2, -1, -1), atol=1e-4, rtol=0)
    assert float(pred.select([0]).prior_shape.sub(prior["mean"][None] - 12 * model.template_dirs).abs().max()) < 1e-4


def test_a_prior_of_another_size_is_refused():
    model = Encoder(ModelConfig(image_size=32, shape_prior=4))
    with pytest.raises(ValueError, match="make shape-prior"):
        model.set_shape_prior(fit(_templates(30), components=2))


def test_the_template_fitted_to_a_box_takes_its_normals():
    """A box-like car stand-in (a rounded, flattened shape is smooth; a box has the breaks a car's panels have): the
    fit lowers the normals' error from its start, the sphere scaled to the box, well below it."""
    box = icosphere(3)
    v = box.verts[0]
    v = v / v.abs().amax(-1, keepdim=True)  # the sphere pushed out onto the cube
    mesh = box.with_verts((v * torch.tensor([16.0, 7.0, 5.0]))[None])
    cameras, renderer = fit_cameras(), Renderer("sg")
    target = renderer.render_normals(mesh.expand(len(cameras)), cameras)

    def error(verts):
        out = renderer.render_normals(box.with_verts(verts[None].expand(len(cameras), -1, -1)), cameras)
        return float(normal_loss(out.image, target.image))

    start = error(box.verts[0] * torch.tensor([16.0, 7.0, 5.0]))
    fitted = fit_template(mesh, steps=60)
    assert error(fitted) < 0.5 * start
    mirror = mirror_index(box.verts[0])
    torch.testing.assert_close(fitted[mirror] * torch.tensor([1.0, -1.0, 1.0]), fitted)  # symmetric


def test_the_prior_is_cached_refitted_when_the_generator_changes_and_read_only_when_current(tmp_path, monkeypatch):
    monkeypatch.setattr(shape_prior, "fit_template", lambda mesh, steps: _templates(1, int(mesh.verts.sum()) % 97)[0])
    monkeypatch.setattr(shape_prior, "car_mesh", lambda i: icosphere(1).with_verts(icosphere(1).verts * (1 + i)))
    with pytest.raises(DataError, match="make shape-prior"):
        read(tmp_path / "prior")
    first = build(tmp_path / "prior", cars=6, components=2, steps=5, progress=False)
    calls = []
    monkeypatch.setattr(shape_prior, "fit", lambda *a, **k: calls.append(1) or first)
    build(tmp_path / "prior", cars=6, components=2, steps=5, progress=False)
    assert not calls  # read from the cache
    with pytest.raises(DataError, match="other settings"):
        read(tmp_path / "prior")  # fitted with settings other than the defaults a run is built with
    monkeypatch.setattr(shape_prior, "generator_digest", lambda: "changed")
    build(tmp_path / "prior", cars=6, components=2, steps=5, progress=False)
    assert calls  # refitted


def test_the_fits_resume_where_they_stopped(tmp_path, monkeypatch):
    made = []
    monkeypatch.setattr(shape_prior, "fit_template", lambda mesh, steps: made.append(1) or _templates(1)[0])
    monkeypatch.setattr(shape_prior, "car_mesh", lambda i: icosphere(1))
    (tmp_path / "prior").mkdir()
    shape_prior.fit_cars(tmp_path / "prior", 3, 5, progress=False)
    assert len(made) == 3
    fits = shape_prior.fit_cars(tmp_path / "prior", 5, 5, progress=False)  # two more, the first three kept
    assert len(made) == 5 and fits.shape == (5, 642, 3)


def test_a_run_trains_with_the_prior_and_keeps_it(tiny_glossy, tmp_path, capsys):
    from pipelines import train
    from pipelines.runs import load_run

    folder = tmp_path / "prior"
    folder.mkdir()
    torch.save({**fit(_templates(30), shape_prior.COMPONENTS), "key": shape_prior.prior_key()},
               folder / shape_prior.PRIOR_FILE)
    out = tmp_path / "runs" / "glossy" / "sg-shape-prior-seed0"
    args = ["--preset", "smoke", "--dataset", str(tiny_glossy), "--image-size", "32", "--shape-prior", str(folder),
            "--out", str(out), "--no-progress"]
    assert train.main(args + ["--iterations", "2"]) == 0
    saved = load_run(out).model.prior_basis.clone()
    (folder / shape_prior.PRIOR_FILE).unlink()  # the run holds its prior
    assert saved.abs().sum() > 0 and torch.equal(load_run(out).model.prior_basis, saved)
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--shape-prior", str(folder),
                       "--out", str(tmp_path / "other"), "--no-progress"]) == 2
    assert "make shape-prior" in capsys.readouterr().err
