import subprocess
import sys

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
