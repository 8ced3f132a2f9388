import numpy as np
import pytest
import torch

from torch_diffavatar.chamfer import chamfer_distance, nearest_indices, one_sided_chamfer, robust_penalty


def _cloud(n, seed, dtype=torch.float64):
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_nearest_indices_match_brute_force():
    x, y = _cloud(50, 0), _cloud(80, 1)
    brute = torch.cdist(x, y).argmin(1).numpy()
    np.testing.assert_array_equal(nearest_indices(x, y), brute)


def test_one_and_two_sided_values_match_brute_force():
    x, y = _cloud(40, 2), _cloud(30, 3)
    d = torch.cdist(x, y) ** 2
    torch.testing.assert_close(one_sided_chamfer(x, y), d.min(1).values.mean())
    torch.testing.assert_close(one_sided_chamfer(x, y, reduction="sum"), d.min(1).values.sum())
    xy, yx = chamfer_distance(x, y, reduction="none")
    assert xy.shape == (1, 40) and yx.shape == (1, 30)
    torch.testing.assert_close(chamfer_distance(x, y), d.min(1).values.mean() + d.min(0).values.mean())


def test_batched_and_weighted():
    x = torch.stack([_cloud(20, 4), _cloud(20, 5)])
    y = _cloud(25, 6)
    per = one_sided_chamfer(x, y, reduction="none")
    assert per.shape == (2, 20)
    w = torch.zeros(2, 20, dtype=torch.float64)
    w[:, 0] = 1.0
    torch.testing.assert_close(one_sided_chamfer(x, y, x_weights=w), per[:, 0].mean())


def test_robust_kernels():
    sq = torch.tensor([0.0, 1e-6, 1e-2, 1.0], dtype=torch.float64)
    for kind in ("l2", "geman_mcclure", "huber"):
        out = robust_penalty(sq, kind, scale=0.01)
        assert out[0] == 0 and abs(out[1] - 1e-6) < 1e-8  # all behave like d² near zero
    gm = robust_penalty(sq, "geman_mcclure", scale=0.01)
    assert gm[-1] < 1e-4  # saturates at s²
    hub = robust_penalty(sq, "huber", scale=0.01)
    torch.testing.assert_close(hub[-1], torch.tensor(0.01 * (2 * 1.0 - 0.01), dtype=torch.float64))


def test_bad_arguments_are_rejected():
    x = _cloud(5, 7)
    with pytest.raises(ValueError, match="reduction"):
        chamfer_distance(x, x, reduction="avg")
    with pytest.raises(ValueError, match="robust"):
        chamfer_distance(x, x, robust="cauchy")
    with pytest.raises(ValueError, match="shape"):
        one_sided_chamfer(x[:, :2], x)
    with pytest.raises(ValueError, match="empty"):
        one_sided_chamfer(x, x[:0])


@pytest.mark.parametrize("robust", ["l2", "geman_mcclure", "huber"])
def test_gradcheck(robust):
    # Well-separated points, so small perturbations do not change the nearest-neighbour assignment.
    grid = torch.stack(torch.meshgrid(*[torch.arange(3.0, dtype=torch.float64)] * 3, indexing="ij"), -1)
    x = (grid.reshape(-1, 3)[:8] + 0.1 * _cloud(8, 8)).requires_grad_()
    y = (grid.reshape(-1, 3)[:10] + 0.1 * _cloud(10, 9)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: chamfer_distance(a, b, robust=robust, scale=0.1), (x, y))
