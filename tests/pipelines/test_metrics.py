"""Metrics on cases with answers known by hand."""
import numpy as np
import pytest
import torch
import trimesh

from pipelines import metrics


def test_identical_inputs_score_zero():
    img = torch.rand(2, 8, 8, 3)
    mask = (torch.rand(2, 8, 8) > 0.3).float()
    assert torch.all(metrics.image_l1(img, img, mask) == 0)
    assert torch.all(metrics.iou_loss(mask, mask) == 0)
    assert torch.allclose(metrics.ncc_loss(img, img), torch.zeros(2), atol=1e-6)


def test_ncc_ignores_a_global_scale_but_not_a_change_of_pattern():
    env = torch.rand(1, 16, 32, 3)
    assert metrics.ncc_loss(env, 3.7 * env).abs().item() < 1e-6
    other = torch.zeros_like(env)
    other[..., :16, :] = 1.0  # orthogonal to an image that is zero there
    masked = env.clone()
    masked[..., :16, :] = 0
    assert metrics.ncc_loss(masked, other).item() == pytest.approx(1.0)


def test_shifted_square_silhouette_iou_by_hand():
    gt = torch.zeros(1, 20, 20)
    gt[0, 5:15, 5:15] = 1  # 10 x 10
    pred = torch.zeros(1, 20, 20)
    pred[0, 5:15, 8:18] = 1  # shifted by 3 columns: overlap 10 x 7 = 70, union 130
    assert metrics.iou_loss(pred, gt).item() == pytest.approx(1 - 70 / 130)


def test_image_l1_counts_only_the_foreground():
    gt, pred = torch.zeros(1, 4, 4, 3), torch.zeros(1, 4, 4, 3)
    mask = torch.zeros(1, 4, 4)
    mask[0, :2] = 1
    pred[0, :2] = 0.25  # error 0.25 on the foreground
    pred[0, 2:] = 9.0  # background: ignored
    assert metrics.image_l1(pred, gt, mask).item() == pytest.approx(0.25)


def test_chamfer_zero_for_the_same_mesh_and_known_for_a_shift():
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    assert metrics.chamfer_distance(v, f, v, f, samples=4000) < 2e-3
    # a unit sphere vs a sphere of radius 1.1: every point is 0.1 away, in units of the GT diagonal
    s = trimesh.creation.icosphere(4)
    gt_v, sf = np.asarray(s.vertices), np.asarray(s.faces)
    diag = np.linalg.norm(gt_v.max(0) - gt_v.min(0))
    d = metrics.chamfer_distance(1.1 * gt_v, sf, gt_v, sf, samples=4000)
    assert d == pytest.approx((0.1 / diag) ** 2, rel=0.1)
    with pytest.raises(ValueError, match="degenerate"):
        metrics.chamfer_distance(v, f, np.zeros((3, 3)), np.array([[0, 1, 2]]))
