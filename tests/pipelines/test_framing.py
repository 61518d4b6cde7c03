"""An image re-framed as the training views frame their object: hand-made masks."""
import pytest
import torch

from pipelines.model import framing


def image_with_box(height, width, top, left, box_h, box_w):
    rgba = torch.zeros(height, width, 4)
    rgba[top:top + box_h, left:left + box_w] = torch.tensor([0.5, 0.2, 0.1, 1.0])
    return rgba


def test_the_extent_of_a_hand_made_mask():
    alpha = image_with_box(40, 60, 5, 10, 20, 30)[..., 3]
    assert framing.object_extent(alpha) == pytest.approx((15.0, 25.0, 600 ** 0.5))
    assert framing.object_extent(torch.zeros(8, 8)) is None
    seen = framing.image_framing(alpha)  # over the longer side, as the image is padded to a square
    assert seen["object_size"] == pytest.approx(600 ** 0.5 / 60)
    assert seen["object_centre"] == pytest.approx([(15 + 10) / 60, 25 / 60])


def test_the_training_framing_is_the_median_over_views():
    views = torch.stack([image_with_box(32, 32, 8, 8, 16, 16)[..., 3], image_with_box(32, 32, 10, 8, 16, 16)[..., 3],
                         image_with_box(32, 32, 8, 8, 8, 8)[..., 3], image_with_box(32, 32, 12, 8, 16, 16)[..., 3]])
    trained = framing.training_framing(views)
    assert trained["object_size"] == pytest.approx(16 / 32)
    assert trained["object_centre"] == pytest.approx([(16 + 18) / 2 / 32, 16 / 32], abs=1e-4)  # even count: the middle two


@pytest.mark.parametrize("top, left", [(0, 0), (70, 130), (30, 60)])
def test_reframing_gives_the_object_the_training_size_and_place(top, left):
    rgba = image_with_box(100, 200, top, left, 30, 60)  # a wide photo, its object anywhere, even at an edge
    trained = {"object_size": 0.5, "object_centre": [0.55, 0.5]}
    out = framing.reframe(rgba, trained)
    assert out.shape[:2] == (85, 85)  # sqrt(30 x 60) = 42.4 pixels is half the side
    assert framing.image_framing(out[..., 3])["object_centre"] == pytest.approx([0.55, 0.5], abs=1 / 85)
    assert torch.equal(out[out[..., 3] > 0][:, :3].unique(dim=0), torch.tensor([[0.5, 0.2, 0.1]]))
    assert float(out[..., 3].sum()) == 30 * 60  # nothing of the object is lost, nothing else is added
    assert not framing.frames_like(framing.image_framing(rgba[..., 3]), trained)
    assert framing.frames_like(framing.image_framing(out[..., 3]), trained)
