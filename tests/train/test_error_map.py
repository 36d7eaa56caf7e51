"""Error-guided pixel sampling (warpnerf.train.error_map.ErrorMap): where it draws, its weights, its state."""

import io

import pytest
import torch

from warpnerf.train.error_map import ErrorMap


def peaked_map(share=0.5, views=2, h=10, w=13, cells=4):
    em = ErrorMap(views, h, w, share=share, cells=cells)
    g = torch.Generator().manual_seed(3)
    em.sq_err.copy_(torch.rand(em.sq_err.shape, generator=g) ** 4)  # a few cells hold most of the error
    em.sq_err[5] = 0.0  # a fitted cell: drawn only by the uniform share
    return em


def test_cells_cover_the_image_and_cut_ones_count_their_pixels():
    em = ErrorMap(2, 10, 13, share=0.5, cells=4)  # 4-pixel cells: 3 x 4 per view, the last ones cut
    assert (em.cell, em.rows, em.cols) == (4, 3, 4)
    assert em.cell_h.tolist() == [4, 4, 2] and em.cell_w.tolist() == [4, 4, 4, 1]
    assert float(em.area.sum()) == 2 * 10 * 13


def test_samples_stay_inside_the_image_and_follow_the_mixture():
    em = peaked_map()
    n = 200_000
    idx, px, py, weight = em.sample(n, torch.Generator().manual_seed(0))
    assert idx.min() >= 0 and idx.max() < em.n_views
    assert px.min() >= 0 and px.max() < em.width and py.min() >= 0 and py.max() < em.height
    cell = em.cell_of(idx, px, py)
    freq = torch.bincount(cell, minlength=em.sq_err.numel()).double() / n
    prob = em.sq_err.sqrt() / em.sq_err.sqrt().sum()
    want = (1 - em.share) * em.area / em.area.sum() + em.share * prob
    assert torch.allclose(freq, want.double(), atol=4e-3)
    assert freq[5] > 0  # a zero-error cell is still drawn (uniform share)


def test_weighted_mean_estimates_the_uniform_mean_of_any_per_pixel_loss():
    """Unbiased: sum of weight x loss over the draws / n is the mean over all pixels."""
    em = peaked_map()
    # a loss that is high where the map's error is (as in training), plus per-pixel variation
    v, y, x = torch.meshgrid(torch.arange(em.n_views), torch.arange(em.height), torch.arange(em.width), indexing="ij")
    noise = torch.rand(em.n_views, em.height, em.width, generator=torch.Generator().manual_seed(1))
    loss = em.sq_err[em.cell_of(v, x, y)] + 0.1 * noise
    truth = float(loss.mean())
    est = []
    for seed in range(8):
        idx, px, py, weight = em.sample(50_000, torch.Generator().manual_seed(seed))
        est.append(float((weight * loss[idx, py, px]).mean()))
        assert weight.max() <= 1 / (1 - em.share) + 1e-6
    assert abs(sum(est) / len(est) - truth) < 0.01 * truth
    # the same draws without their weights overstate the loss: the weights are what makes it unbiased
    assert float(loss[idx, py, px].mean()) > 1.3 * truth


def test_update_blends_each_touched_cell_with_the_mean_of_its_rays():
    em = ErrorMap(1, 8, 8, share=0.5, cells=2, decay=0.5)  # 4-pixel cells, 2 x 2
    before = em.sq_err.clone()
    idx = torch.zeros(3, dtype=torch.long)
    px, py = torch.tensor([0, 3, 7]), torch.tensor([0, 1, 0])  # two rays in cell 0, one in cell 1
    em.update(idx, px, py, torch.tensor([0.2, 0.4, 1.0]))
    assert em.sq_err.tolist() == pytest.approx([0.5 * 1 + 0.5 * 0.3, 0.5 * 1 + 0.5 * 1.0, 1.0, 1.0])
    assert torch.equal(em.sq_err[2:], before[2:])  # untouched cells keep their value


def test_a_fitted_map_samples_uniformly():
    em = ErrorMap(1, 6, 6, share=0.5, cells=3)
    em.sq_err.zero_()
    idx, px, py, weight = em.sample(1000, torch.Generator().manual_seed(0))
    assert torch.allclose(weight, torch.ones_like(weight))


def test_huge_captures_get_fewer_cells_per_image():
    from warpnerf.train.error_map import MAX_CELLS

    em = ErrorMap(5000, 300, 400, share=0.5)  # 7-pixel cells, 43 x 58 each: 12.5M categories, fine
    assert (em.cell, em.rows, em.cols) == (7, 43, 58)
    em = ErrorMap(20000, 300, 400, share=0.5)  # 49.9M with those: 32 per side, 13-pixel cells, 14.9M
    assert (em.cell, em.rows, em.cols) == (13, 24, 31) and em.sq_err.numel() <= MAX_CELLS


def test_share_must_be_a_fraction():
    with pytest.raises(ValueError, match="error_sampling"):
        ErrorMap(1, 4, 4, share=1.0)


def test_trainer_with_error_sampling_learns_and_resumes_identically():
    from trainer_helpers import make_trainer

    t = make_trainer(iters=60, error_sampling=0.5)
    losses = [t.train_step(s)["loss"] for s in range(40)]
    assert sum(losses[-5:]) < 0.5 * sum(losses[:5])
    assert not torch.equal(t.error_map.sq_err, torch.ones_like(t.error_map.sq_err))  # the map learnt
    saved = io.BytesIO()  # through bytes, as a checkpoint: load_state_dict may keep the tensors it is given
    torch.save(t.state_dict(), saved)
    saved.seek(0)
    other = make_trainer(iters=60, error_sampling=0.5)
    other.load_state_dict(torch.load(saved, weights_only=False))
    assert torch.equal(other.error_map.sq_err, t.error_map.sq_err)
    assert [t.train_step(s)["loss"] for s in range(40, 45)] == [other.train_step(s)["loss"] for s in range(40, 45)]
