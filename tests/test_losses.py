"""The backscatter excess loss: zero below the image, relative above it, finite on extreme input."""

import torch


def test_backscatter_excess_is_zero_below_the_image_and_relative_above():
    from seathru_nerfstudio.losses import backscatter_excess_loss

    image = torch.tensor([[0.2, 0.1, 0.4], [0.05, 0.3, 0.0]])
    below = image * 0.9
    assert backscatter_excess_loss(below, image) == 0
    backscatter = torch.tensor([[0.3, 0.05, 0.4], [0.05, 0.6, 0.01]], requires_grad=True)
    loss = backscatter_excess_loss(backscatter, image, eps=1e-3)
    excess = torch.tensor([[0.1 / 0.201, 0.0, 0.0], [0.0, 0.3 / 0.301, 0.01 / 0.001]])
    torch.testing.assert_close(loss, (excess**2).mean())
    loss.backward()
    # only the pixels whose backscatter is above the image get a gradient, and it lowers them
    assert (backscatter.grad[excess == 0] == 0).all() and (backscatter.grad[excess > 0] > 0).all()
    # finite difference of one entry above the image
    h = 1e-4
    bumped = backscatter.detach().clone()
    bumped[1, 1] += h
    numeric = (backscatter_excess_loss(bumped, image) - backscatter_excess_loss(backscatter.detach(), image)) / h
    torch.testing.assert_close(backscatter.grad[1, 1], numeric, rtol=1e-2, atol=0)


def test_backscatter_excess_is_finite_for_extreme_input():
    from seathru_nerfstudio.losses import backscatter_excess_loss

    backscatter = torch.tensor([[3e38, 0.0, 1e-30]], requires_grad=True)
    image = torch.tensor([[0.0, 1e30, -1.0]])
    loss = backscatter_excess_loss(backscatter, image)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(backscatter.grad).all()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        small = backscatter_excess_loss(torch.tensor([[0.5, 0.1, 0.2]]), torch.tensor([[0.1, 0.1, 0.0]]))
    assert torch.isfinite(small)
