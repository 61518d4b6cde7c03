import os
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from dibrpp import io
from dibrpp.conventions import equirect_directions
from dibrpp.mesh import icosphere


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    m = icosphere(3)
    io.save_mesh(root / "sphere.obj", m.verts[0], m.faces)
    d = equirect_directions(32, 64)
    env = 0.3 + d[..., 2:].clamp_min(0) * torch.tensor([0.4, 0.6, 1.0]) + 5 * (d[..., :1] > 0.9)
    io.write_exr(root / "env.exr", env)
    (root / "broken.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    (root / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    # no triangle with area: collinear corners, a repeated corner
    (root / "flat.obj").write_text("v 0 0 0\nv 0.5 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 4 4\n")
    io.save_mesh(root / "big.obj", 18 * m.verts[0], m.faces)  # a dataset's scale: [-18, 18]
    return root


def run(*args):
    return subprocess.run([sys.executable, "-m", "dibrpp", "render", *map(str, args)], capture_output=True, text=True)


BASE = ("--distance", 3, "--resolution", 24, "--spp", 8)


@pytest.mark.parametrize("shading", ["mc", "sg", "sh"])
def test_cli_renders_exr_and_png(assets, shading):
    for ext in ("exr", "png"):
        out = assets / f"out_{shading}.{ext}"
        r = run("--mesh", assets / "sphere.obj", "--envmap", assets / "env.exr", "--shading", shading,
                "--sg-lobes", 4, *BASE, "--out", out)
        assert r.returncode == 0, r.stderr
        img = io.read_exr(out, "RGBA") if ext == "exr" else io.read_png(out)
        assert img.shape == (24, 24, 4)
        assert img[12, 12, 3] == 1 and img[0, 0, 3] == 0 and img[12, 12, :3].max() > 0.05


def test_cli_albedo_only(assets):
    out = assets / "albedo.exr"
    r = run("--mesh", assets / "sphere.obj", "--albedo", "0.2,0.4,0.6", "--albedo-only", *BASE, "--out", out)
    assert r.returncode == 0, r.stderr
    img = io.read_exr(out, "RGBA")
    assert np.allclose(img[12, 12], [0.2, 0.4, 0.6, 1.0], atol=1e-6)


@pytest.mark.parametrize("args,message", [
    (("--mesh", "{a}/missing.obj", "--envmap", "{a}/env.exr"), "no such file"),
    (("--mesh", "{a}/nan.obj", "--envmap", "{a}/env.exr"), "NaN"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/broken.exr"), "not a readable OpenEXR"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--roughness", "1.5"), "--roughness"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--shading", "pbr"), "invalid choice"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--albedo", "1,2"), "R,G,B"),
    (("--mesh", "{a}/sphere.obj",), "--envmap is required"),
    (("--mesh", "{a}/sphere.obj", "--texture", "{a}/env.exr", "--albedo-only"), "UV"),
])
def test_cli_bad_input_gives_one_error_line_and_no_output(assets, args, message):
    out = assets / "should_not_exist.exr"
    r = run(*[a.format(a=assets) for a in args], *BASE, "--out", out)
    assert r.returncode != 0
    lines = [line for line in r.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], r.stderr
    assert not out.exists()


def _read_only_folder(tmp_path):
    """A folder this process cannot create files in (root ignores permission bits: use sysfs there)."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").touch()
    except PermissionError:
        return folder
    (folder / "probe").unlink()
    if _cannot_create_in("/sys"):
        return Path("/sys")
    pytest.skip("no folder this process cannot write to")


def _cannot_create_in(folder) -> bool:
    try:
        with tempfile.TemporaryFile(dir=folder):
            return False
    except OSError:
        return True


@pytest.fixture(scope="module")
def more_assets(assets):
    d = equirect_directions(32, 32)  # square: not an equirect map
    io.write_exr(assets / "square.exr", 0.5 + d[..., 2:].clamp_min(0).expand(-1, -1, 3))
    return assets


@pytest.mark.parametrize("args,message", [
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/square.exr"), "{a}/square.exr: 32 x 32 pixels is not an equirect"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--distance", "nan"), "--distance nan: must be a finite"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--azimuth", "inf"), "--azimuth inf: must be a finite"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--fov", "180"), "--fov 180.0"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--spp", "many"), "--spp: invalid int value"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/env.exr", "--resolution", "0"), "--resolution 0"),
    (("--mesh", "{a}/sphere.obj", "--envmap", "{a}/missing.exr"), "missing.exr: no such file"),
    (("--mesh", "{a}/sphere.obj", "--texture", "{a}/missing.png", "--albedo-only"), "missing.png: no such file"),
    (("--mesh", "{a}", "--envmap", "{a}/env.exr"), "--mesh {a}: is a folder; --mesh takes one file"),
    (("--mesh", "{a}/flat.obj", "--envmap", "{a}/env.exr"), "flat.obj: the mesh has no triangle with area"),
    (("--mesh", "{a}/big.obj", "--albedo-only"), "--distance 3: the camera at distance 3 is inside the mesh's bounds "
     "(radius 18 around the origin it looks at); pass --distance larger than 18, e.g. 54"),
])
def test_cli_more_bad_input_gives_one_error_line(more_assets, args, message):
    out = more_assets / "should_not_exist.exr"
    r = run(*BASE, *[a.format(a=more_assets) for a in args], "--out", out)  # args last: they win over BASE
    lines = [line for line in r.stderr.strip().splitlines() if line]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.stderr
    assert message.format(a=more_assets) in lines[0], r.stderr
    assert not out.exists()


def test_cli_output_into_a_read_only_folder_or_onto_a_folder(assets, tmp_path):
    folder = _read_only_folder(tmp_path)
    for out, message in ((folder / "image.png", f"cannot write into folder {folder}"),
                         (assets, "is a folder"), (tmp_path / "x.png" / "y.png", "does not exist")):
        if out == assets:
            out = assets / "dir.png"
            out.mkdir(exist_ok=True)
        r = run("--mesh", assets / "sphere.obj", "--albedo-only", *BASE, "--out", out)
        lines = [line for line in r.stderr.strip().splitlines() if line]
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], r.stderr


def test_cli_output_follows_the_umask(assets):
    out = assets / "umask.png"
    r = subprocess.run([sys.executable, "-m", "dibrpp", "render", "--mesh", str(assets / "sphere.obj"), "--albedo-only",
                        *map(str, BASE), "--out", str(out)], capture_output=True, text=True,
                       preexec_fn=lambda: os.umask(0o022))
    assert r.returncode == 0, r.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o644


def test_a_camera_outside_the_bounds_of_a_big_mesh_renders_it(assets):
    out = assets / "big.exr"
    r = run("--mesh", assets / "big.obj", "--albedo-only", *BASE, "--distance", 54, "--out", out)
    assert r.returncode == 0, r.stderr
    alpha = io.read_exr(out, "RGBA")[..., 3]
    assert alpha[12, 12] == 1 and alpha[0, 0] == 0


REPO = Path(__file__).resolve().parents[2]
# The example of README.md and docs/renderer.md: it runs as written on a fresh clone (the files are in examples/).
EXAMPLE = ("python -m dibrpp render --mesh examples/car.obj --albedo 0.8,0.2,0.2 --roughness 0.3 "
           "--envmap examples/sky.exr --elevation 20 --azimuth 45 --shading mc --spp 64 --resolution 128 --out car.png")


def test_the_documented_example_runs_as_written(tmp_path):
    documented = " ".join((REPO / "docs" / "renderer.md").read_text().replace("\\\n", " ").split())
    assert EXAMPLE.replace("python", ".venv/bin/python", 1) in documented
    argv = EXAMPLE.split()[1:]
    argv[-1] = str(tmp_path / "car.png")  # the same command, writing elsewhere than the checkout
    r = subprocess.run([sys.executable, *argv], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    img = io.read_png(tmp_path / "car.png")
    assert img.shape == (128, 128, 4) and img[64, 64, 3] == 1 and img[0, 0, 3] == 0
    assert 0.1 < img[..., :3][img[..., 3] == 1].mean() < 0.9  # neither black nor blown out


def test_the_examples_are_what_examples_make_writes(tmp_path):
    """The shipped example files are small and remade exactly by ``python -m examples.make``."""
    r = subprocess.run([sys.executable, "-m", "examples.make", "--out", str(tmp_path)], capture_output=True, text=True,
                       cwd=REPO)
    assert r.returncode == 0, r.stderr
    shipped = REPO / "examples"
    assert (tmp_path / "car.obj").read_text() == (shipped / "car.obj").read_text()
    assert np.array_equal(io.read_exr(tmp_path / "sky.exr"), io.read_exr(shipped / "sky.exr"))
    assert (shipped / "car.obj").stat().st_size < 200_000 and io.read_exr(shipped / "sky.exr").shape == (64, 128, 3)
    # the photo is a Cycles render: remade up to another CPU's rounding and the sampler's noise, not bit for bit
    photo, remade = io.read_exr(shipped / "car_photo.exr", "RGBA"), io.read_exr(tmp_path / "car_photo.exr", "RGBA")
    assert photo.shape == remade.shape == (208, 256, 4)
    assert np.abs(photo[..., 3] - remade[..., 3]).mean() < 1e-3 and np.abs(photo - remade)[..., :3].mean() < 1e-2
    assert (shipped / "car_photo.exr").stat().st_size + (shipped / "car_photo.png").stat().st_size < 1_000_000
