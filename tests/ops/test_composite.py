"""composite_rays: Warp kernel vs. its pure-torch twin, forward values and autograd gradients."""

import pytest
import torch

from warpnerf.ops.composite import active_sample_counts, composite_rays
from warpnerf.ops.reference.composite import active_sample_counts as active_sample_counts_ref
from warpnerf.ops.reference.composite import composite_rays as composite_rays_ref


def packed_samples(seed: int, num_rays: int = 96, max_count: int = 48, sigma_max: float = 60.0):
    """Random packed rays; a dense sigma range makes many rays terminate early, some are empty."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_count, (num_rays,), generator=g, dtype=torch.int32)
    counts[::7] = 0
    offsets = (torch.cumsum(counts, 0) - counts).int()
    n = int(counts.sum())
    deltas = torch.rand(n, generator=g) * 0.1 + 1e-3
    t_starts = 2.0 + torch.rand(n, generator=g) * 4.0
    sigmas = torch.rand(n, generator=g) * sigma_max
    sigmas[torch.rand(n, generator=g) < 0.3] = 0.0  # empty space between surfaces
    rgbs = torch.rand(n, 3, generator=g)
    background = torch.rand(num_rays, 3, generator=g)
    return sigmas, rgbs, t_starts, t_starts + deltas, offsets, counts, background


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("per_ray_background", [False, True])
def test_forward_matches_twin(seed, per_ray_background):
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(seed)
    background = bg if per_ray_background else (1.0, 0.5, 0.0)
    out = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, background, return_weights=True)
    ref = composite_rays_ref(sigmas, rgbs, t0, t1, offsets, counts, background, return_weights=True)
    # measured max abs error over seeds 0-9: rgb 2.4e-7, opacity 1.8e-7, weights 6.0e-8 (values <= 1),
    # depth 9.5e-7 (values <= 6); float32 sums in a different order
    for name, a, b, atol in zip(("rgb", "opacity", "depth", "weights"), out, ref, (1e-6, 1e-6, 4e-6, 1e-6)):
        torch.testing.assert_close(a, b, atol=atol, rtol=0, msg=lambda m, name=name: f"{name}: {m}")
    # the cases this test is about really occur: early termination and empty rays
    weights = out[3]
    terminated = (weights == 0) & (sigmas > 0)
    assert terminated.sum() > 100
    assert torch.equal(terminated, (ref[3] == 0) & (sigmas > 0))
    empty = counts == 0
    assert empty.any()
    expected_bg = bg[empty] if per_ray_background else torch.tensor(background).expand(int(empty.sum()), 3)
    assert torch.equal(out[0][empty], expected_bg)
    assert not out[1][empty].any() and not out[2][empty].any()


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("return_weights", [False, True])
def test_gradients_match_twin(seed, return_weights):
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(seed)
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    out = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=return_weights)
    ref = composite_rays_ref(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=return_weights)
    g = torch.Generator().manual_seed(100 + seed)
    cotangents = [torch.randn(x.shape, generator=g) for x in out]
    d_sigmas, d_rgbs = torch.autograd.grad(out, (sigmas, rgbs), cotangents)
    d_sigmas_ref, d_rgbs_ref = torch.autograd.grad(ref, (sigmas, rgbs), cotangents)
    # measured max abs error over seeds 0-9: d_sigmas 2.5e-7 (|values| <= 1.1), d_rgbs 1.2e-7 (|values| <= 3.6)
    torch.testing.assert_close(d_sigmas, d_sigmas_ref, atol=1e-6, rtol=0)
    torch.testing.assert_close(d_rgbs, d_rgbs_ref, atol=1e-6, rtol=0)
    # samples after termination and samples of empty rays get exactly zero gradient
    weights = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=True)[3]
    terminated = (weights == 0) & (sigmas > 0)
    assert terminated.any() and not d_sigmas[terminated].any() and not d_rgbs[terminated].any()


def test_gradient_of_single_output():
    """Only opacity used: the other outputs' gradients arrive as zeros and must not leak in."""
    sigmas, rgbs, t0, t1, offsets, counts, _ = packed_samples(2)
    sigmas.requires_grad_(True)
    opacity = composite_rays(sigmas, rgbs, t0, t1, offsets, counts)[1]
    opacity_ref = composite_rays_ref(sigmas, rgbs, t0, t1, offsets, counts)[1]
    (d_sigmas,) = torch.autograd.grad(opacity.square().sum(), sigmas)
    (d_sigmas_ref,) = torch.autograd.grad(opacity_ref.square().sum(), sigmas)
    # measured max abs error over seeds 0-9: 4.0e-8 (|values| <= 0.05)
    torch.testing.assert_close(d_sigmas, d_sigmas_ref, atol=1e-6, rtol=0)


def test_no_samples_at_all():
    counts = torch.zeros(5, dtype=torch.int32)
    sigmas = torch.zeros(0, requires_grad=True)
    rgbs = torch.zeros(0, 3, requires_grad=True)
    empty = torch.zeros(0)
    rgb, opacity, depth = composite_rays(sigmas, rgbs, empty, empty, counts, counts, (0.2, 0.3, 0.4))
    assert torch.equal(rgb, torch.tensor([[0.2, 0.3, 0.4]]).expand(5, 3))
    assert not opacity.any() and not depth.any()
    d_sigmas, d_rgbs = torch.autograd.grad(rgb.sum(), (sigmas, rgbs))
    assert d_sigmas.shape == (0,) and d_rgbs.shape == (0, 3)


def test_opaque_sample_hides_the_rest():
    """Hand-computed: an infinitely dense first sample takes all the weight."""
    sigmas = torch.tensor([1e9, 5.0, 5.0])
    rgbs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    t0, t1 = torch.tensor([2.0, 3.0, 4.0]), torch.tensor([3.0, 4.0, 5.0])
    one_ray = torch.tensor([0], dtype=torch.int32), torch.tensor([3], dtype=torch.int32)
    rgb, opacity, depth, weights = composite_rays(sigmas, rgbs, t0, t1, *one_ray, return_weights=True)
    assert rgb.tolist() == [[1.0, 0.0, 0.0]] and opacity.tolist() == [1.0] and depth.tolist() == [2.5]
    assert weights.tolist() == [1.0, 0.0, 0.0]


@pytest.mark.gradcheck
def test_twin_gradients_match_finite_differences():
    """The twin is the reference for the hand-written backward, so check it in float64 too."""
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(5, num_rays=6, max_count=16, sigma_max=60.0)
    sigmas, rgbs = sigmas.double().requires_grad_(True), rgbs.double().requires_grad_(True)
    t0, t1, bg = t0.double(), t1.double(), bg.double()
    weights = composite_rays_ref(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=True)[3]
    assert ((weights == 0) & (sigmas > 0)).any()  # early termination is part of the check

    def outputs(s, c):
        return composite_rays_ref(s, c, t0, t1, offsets, counts, bg, return_weights=True)

    assert torch.autograd.gradcheck(outputs, (sigmas, rgbs), fast_mode=True)


def test_two_threads_bit_identical(threads):
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(3, num_rays=400)
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    cotangents = None
    results = []
    for n_threads in (1, 2):
        threads(n_threads)
        out = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=True)
        if cotangents is None:
            g = torch.Generator().manual_seed(7)
            cotangents = [torch.randn(x.shape, generator=g) for x in out]
        results.append([x.detach() for x in out] + list(torch.autograd.grad(out, (sigmas, rgbs), cotangents)))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_bad_inputs_raise():
    sigmas, rgbs, t0, t1, offsets, counts, _ = packed_samples(4, num_rays=8)
    ok = dict(sigmas=sigmas, rgbs=rgbs, t_starts=t0, t_ends=t1, ray_offsets=offsets, ray_counts=counts)
    bad = [
        (TypeError, "sigmas must be torch.float32", dict(sigmas=sigmas.double())),
        (TypeError, "ray_counts must be torch.int32", dict(ray_counts=counts.long())),
        (TypeError, "rgbs must be a torch tensor", dict(rgbs=rgbs.numpy())),
        (ValueError, "rgbs must have shape", dict(rgbs=rgbs[:, :2])),
        (ValueError, "t_ends must have shape", dict(t_ends=t1[1:])),
        (ValueError, "sigmas must be", dict(sigmas=sigmas[:, None])),
        (ValueError, "must lie inside", dict(ray_offsets=offsets + 1)),
    ]
    for error, message, change in bad:
        with pytest.raises(error, match=message):
            composite_rays(**{**ok, **change})
    with pytest.raises(ValueError, match="background"):
        composite_rays(**ok, background=torch.ones(3, 3))
    with pytest.raises(ValueError, match="background"):
        composite_rays(**ok, background=(1.0, 1.0))
    with pytest.raises(ValueError, match="transmittance_eps"):
        composite_rays(**ok, transmittance_eps=-1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_active_counts_match_twin_and_the_composite_weights(seed):
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(seed, num_rays=300)
    active = active_sample_counts(sigmas, t0, t1, offsets, counts)
    assert active.dtype == torch.int32 and active.shape == counts.shape
    assert torch.equal(active, active_sample_counts_ref(sigmas, t0, t1, offsets, counts))
    # the case the count is about occurs: many rays stop before their last sample
    assert int((active < counts).sum()) > 50 and bool((active <= counts).all())
    # the composite gives no weight past the count, and (nearly always) some at the last counted sample
    weights = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, bg, return_weights=True)[3]
    for r in range(counts.shape[0]):
        lo, n, a = int(offsets[r]), int(counts[r]), int(active[r])
        assert not weights[lo + a:lo + n].any()


@pytest.mark.parametrize("seed", [3, 4])
def test_compositing_the_active_prefixes_gives_the_same_pixels_and_gradients(seed):
    """What the renderer's training compaction relies on: dropping every ray's samples past its
    active count changes neither the composite nor its gradient (bit for bit: the same float32
    operations on the same samples)."""
    sigmas, rgbs, t0, t1, offsets, counts, bg = packed_samples(seed, num_rays=200)
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    active = active_sample_counts(sigmas, t0, t1, offsets, counts)
    ray = torch.repeat_interleave(torch.arange(counts.shape[0]), active.long())
    new_offsets = (torch.cumsum(active, 0) - active).int()
    kept = torch.arange(ray.shape[0]) - new_offsets.long()[ray] + offsets.long()[ray]
    assert kept.shape[0] < 0.7 * sigmas.shape[0]
    full = composite_rays(sigmas, rgbs, t0, t1, offsets, counts, bg)
    cut = composite_rays(sigmas[kept], rgbs[kept], t0[kept], t1[kept], new_offsets, active, bg)
    for a, b in zip(full, cut):
        assert torch.equal(a, b)
    g = torch.Generator().manual_seed(seed)
    cot = [torch.randn(x.shape, generator=g) for x in full]
    grads_full = torch.autograd.grad(full, (sigmas, rgbs), cot)
    grads_cut = torch.autograd.grad(cut, (sigmas, rgbs), cot)
    for a, b in zip(grads_full, grads_cut):
        assert torch.equal(a, b)  # the gradient of every dropped sample is exactly 0 in both


def test_active_counts_bad_inputs_raise_in_one_line():
    sigmas, _, t0, t1, offsets, counts, _ = packed_samples(5, num_rays=8)
    with pytest.raises(TypeError, match="active_sample_counts: sigmas must be torch.float32"):
        active_sample_counts(sigmas.double(), t0, t1, offsets, counts)
    with pytest.raises(ValueError, match="active_sample_counts: every"):
        active_sample_counts(sigmas, t0, t1, offsets + 1, counts)
    with pytest.raises(ValueError, match="transmittance_eps"):
        active_sample_counts(sigmas, t0, t1, offsets, counts, transmittance_eps=-1.0)
