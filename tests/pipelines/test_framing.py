"""An image re-framed as the training views frame their object: hand-made boxes."""
import pytest
import torch

from pipelines.model import framing


def image_with_box(height, width, top, left, box_h, box_w):
    rgba = torch.zeros(height, width, 4)
    rgba[top:top + box_h, left:left + box_w] = torch.tensor([0.5, 0.2, 0.1, 1.0])
    return rgba


def test_the_box_of_a_hand_made_mask():
    alpha = image_with_box(40, 60, 5, 10, 20, 30)[..., 3]
    assert framing.object_box(alpha) == (15.0, 25.0, 20.0, 30.0)
    assert framing.object_box(torch.zeros(8, 8)) is None
    assert framing.image_fill(alpha) == pytest.approx(30 / 60)


def test_the_fill_is_the_median_over_views_of_the_longer_side():
    views = torch.stack([image_with_box(32, 32, 0, 0, 8, 16)[..., 3], image_with_box(32, 32, 4, 4, 24, 8)[..., 3],
                         image_with_box(32, 32, 2, 2, 20, 20)[..., 3], image_with_box(32, 32, 2, 2, 12, 2)[..., 3]])
    assert framing.object_fill(views) == pytest.approx((16 / 32 + 20 / 32) / 2)  # even count: the two middle ones


@pytest.mark.parametrize("top, left", [(0, 0), (70, 130), (30, 60)])
def test_reframing_centres_the_object_and_gives_it_the_training_share_of_the_frame(top, left):
    rgba = image_with_box(100, 200, top, left, 30, 60)  # a wide photo, its object anywhere, even at an edge
    out = framing.reframe(rgba, 0.6)
    assert out.shape == (100, 100, 4)  # the box's longer side, 60, is 0.6 of the new side
    cy, cx, h, w = framing.object_box(out[..., 3])
    assert (cy, cx, h, w) == (50.0, 50.0, 30.0, 60.0)
    assert torch.equal(out[out[..., 3] > 0][:, :3].unique(dim=0), torch.tensor([[0.5, 0.2, 0.1]]))
    assert float(out[..., 3].sum()) == 30 * 60  # nothing of the object is lost, nothing else is added
