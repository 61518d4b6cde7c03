"""The dataset loader reads what datagen wrote, yields multi-view items with dibrpp cameras, and refuses
damaged data with errors that name the file."""
import json
import shutil

import numpy as np
import pytest
import torch

from dibrpp import rasterize
from dibrpp.io import DataError, write_exr
from datagen.reader import MultiViewDataset, collate


def test_items_are_multiview_pairs_with_cameras_that_reproduce_the_mask(tiny_glossy):
    ds = MultiViewDataset(tiny_glossy, split="all", views_per_item=2)
    assert len(ds) == 4 * 1 * 4  # objects x env maps per object x views
    batch = collate([ds[0], ds[5]])
    assert batch["image"].shape == (2, 2, 32, 32, 4) and batch["albedo"].shape == (2, 2, 32, 32, 3)
    assert batch["envmap"].dim() == 4 and batch["envmap"].shape[-1] == 3
    assert batch["views"][0, 0] == 0 and batch["views"][0, 1] != 0  # the item's view plus another one
    # the stored camera rasterises the GT mesh onto the Cycles alpha
    item = ds[1]
    cams = ds.cameras(item)
    frags = rasterize(ds.mesh(item["object"]), cams)
    gt = item["mask"] > 0.5
    iou = (frags.mask.bool() & gt).sum() / (frags.mask.bool() | gt).sum()
    assert iou > 0.85, float(iou)  # 32 px images: the boundary pixels weigh a lot


def test_views_are_deterministic_per_seed(tiny_glossy):
    a = MultiViewDataset(tiny_glossy, split="all", views_per_item=3, seed=1)
    b = MultiViewDataset(tiny_glossy, split="all", views_per_item=3, seed=1)
    assert [a.views_for(i) for i in range(len(a))] == [b.views_for(i) for i in range(len(b))]


@pytest.fixture
def damaged(tiny_glossy, tmp_path):
    root = tmp_path / "glossy"
    shutil.copytree(tiny_glossy, root)
    sample = sorted((root / "samples").iterdir())[0]
    return root, sample


def test_missing_view_is_named(damaged):
    root, sample = damaged
    (sample / "view_02.exr").unlink()
    with pytest.raises(DataError, match=r"view_02\.exr.*rerun"):
        MultiViewDataset(root, split="all")


def test_nan_pixels_and_wrong_shapes_are_named(damaged):
    root, sample = damaged
    bad = np.full((32, 32, 4), np.nan, np.float32)
    write_exr(sample / "view_00.exr", bad, "RGBA")
    ds = MultiViewDataset(root, split="all", views_per_item=1)
    idx = [i for i in range(len(ds)) if ds.samples[i // ds.num_views] == tuple(
        int(x) for x in sample.name.split("_")[1::2])][0]
    with pytest.raises(DataError, match="view_00.exr"):
        ds[idx]
    write_exr(sample / "view_00.exr", np.zeros((16, 16, 4), np.float32), "RGBA")
    with pytest.raises(DataError, match="expected"):
        MultiViewDataset(root, split="all", views_per_item=1)[idx]


def test_not_a_dataset_and_bad_arguments(tmp_path, tiny_glossy):
    with pytest.raises(DataError, match="manifest.json"):
        MultiViewDataset(tmp_path)
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(DataError, match="corrupt JSON"):
        MultiViewDataset(tmp_path)
    with pytest.raises(ValueError, match="split"):
        MultiViewDataset(tiny_glossy, split="val")
    with pytest.raises(ValueError, match="views_per_item"):
        MultiViewDataset(tiny_glossy, views_per_item=99)


def test_corrupt_camera_is_named(damaged):
    root, sample = damaged
    (sample / "view_01.json").write_text(json.dumps({"world_to_camera": [[1, 0], [0, 1]], "fov": 0.69}))
    ds = MultiViewDataset(root, split="all")
    obj, env = (int(x) for x in sample.name.split("_")[1::2])
    with pytest.raises(DataError, match="view_01.json"):
        ds.camera(obj, env, 1)
    assert torch.is_tensor(ds.camera(obj, env, 0)[0])


def test_camera_setup_comes_from_the_manifest_and_matches_every_view(tiny_glossy):
    ds = MultiViewDataset(tiny_glossy, split="all", views_per_item=1)
    cam = ds.camera_setup
    assert (cam.distance, cam.elevation_deg) == (60.0, 27.0) and cam.resolution == ds.resolution == 32
    assert len(cam.azimuths_deg) == ds.num_views
    from dibrpp.conventions import orbit_world_to_camera

    for v, az in enumerate(cam.azimuths_deg):
        m, fov = ds.camera(*ds.samples[0], v)
        assert fov == pytest.approx(cam.fov)
        expected = orbit_world_to_camera(torch.tensor(cam.distance, dtype=torch.float64), cam.elevation_deg, az)
        torch.testing.assert_close(m, expected.float(), atol=1e-4, rtol=0)


def test_missing_camera_setup_is_named(damaged):
    root, _ = damaged
    m = json.loads((root / "manifest.json").read_text())
    del m["camera"]
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(DataError, match="camera set-up"):
        MultiViewDataset(root, split="all").camera_setup
