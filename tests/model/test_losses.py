"""warpnerf.model.losses: the weights against the composite op, the distortion loss against its definition."""

import pytest
import torch

from warpnerf.model.losses import distortion_loss, packed_weights
from warpnerf.ops.composite import composite_rays
from warpnerf.ops.raymarch import PackedSamples


def random_packed(seed: int = 0, num_rays: int = 7, max_count: int = 9):
    """Packed samples with increasing, gapped intervals per ray, one ray empty, and densities of
    every scale (some rays turn opaque, so the transmittance cut-off is exercised)."""
    gen = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_count + 1, (num_rays,), generator=gen)
    counts[2] = 0
    offsets = torch.cumsum(counts, 0) - counts
    ray = torch.repeat_interleave(torch.arange(num_rays), counts)
    gaps = torch.rand(ray.shape[0], generator=gen) * 0.3
    lengths = 0.05 + torch.rand(ray.shape[0], generator=gen) * 0.2
    t_ends = torch.zeros(ray.shape[0])
    t_starts = torch.zeros(ray.shape[0])
    for r in range(num_rays):
        sl = slice(int(offsets[r]), int(offsets[r] + counts[r]))
        ends = 1.0 + torch.cumsum(gaps[sl] + lengths[sl], 0)
        t_ends[sl], t_starts[sl] = ends, ends - lengths[sl]
    sigmas = torch.exp(torch.randn(ray.shape[0], generator=gen) * 3.0)
    packed = PackedSamples(ray.int(), t_starts, t_ends, offsets.int(), counts.int())
    return packed, sigmas


def brute_force_distortion(weights, packed):
    """The definition: sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (t1_i - t0_i), per ray."""
    out = []
    for r in range(packed.ray_offsets.shape[0]):
        sl = slice(int(packed.ray_offsets[r]), int(packed.ray_offsets[r] + packed.ray_counts[r]))
        w = weights[sl].double()
        m = 0.5 * (packed.t_starts[sl] + packed.t_ends[sl]).double()
        s = (packed.t_ends[sl] - packed.t_starts[sl]).double()
        out.append((w[:, None] * w[None, :] * (m[:, None] - m[None, :]).abs()).sum() + (w * w * s).sum() / 3.0)
    return torch.stack(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_packed_weights_are_the_composite_weights(seed):
    packed, sigmas = random_packed(seed)
    ref = composite_rays(sigmas, torch.zeros(sigmas.shape[0], 3), packed.t_starts, packed.t_ends, packed.ray_offsets,
                         packed.ray_counts, (0.0, 0.0, 0.0), return_weights=True)[3]
    got = packed_weights(sigmas, packed)
    assert bool((ref == 0).any()) and bool((ref > 0).any())  # the cut-off and visible samples both occur
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-7)
    assert torch.equal(got == 0, ref == 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distortion_loss_matches_its_definition_values_and_gradients(seed):
    packed, sigmas = random_packed(seed)
    sig_a = sigmas.clone().requires_grad_(True)
    sig_b = sigmas.clone().requires_grad_(True)
    got = distortion_loss(packed_weights(sig_a, packed), packed, packed.ray_offsets.shape[0])
    ref = brute_force_distortion(packed_weights(sig_b, packed), packed)
    assert got.dtype == torch.float32 and got.shape == (packed.ray_offsets.shape[0],)
    assert float(got.detach()[2]) == 0.0  # the empty ray
    torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=1e-8)
    cot = torch.rand(got.shape[0], generator=torch.Generator().manual_seed(seed))
    (got * cot).sum().backward()
    (ref * cot.double()).sum().backward()
    assert sig_a.grad.abs().sum() > 0
    torch.testing.assert_close(sig_a.grad, sig_b.grad, rtol=1e-4, atol=1e-7)


def test_distortion_loss_prefers_concentrated_weight():
    """The same total weight in one sample scores lower than spread over the ray."""
    n = 10
    t0 = torch.arange(n, dtype=torch.float32) * 0.1
    packed = PackedSamples(torch.zeros(n, dtype=torch.int32), t0, t0 + 0.1, torch.tensor([0], dtype=torch.int32),
                           torch.tensor([n], dtype=torch.int32))
    spread = distortion_loss(torch.full((n,), 0.1), packed, 1)
    one = distortion_loss(torch.eye(n)[4], packed, 1)
    assert float(one) == pytest.approx(0.1 / 3, rel=1e-6)
    assert float(spread) > 5 * float(one)


def test_no_samples():
    empty = torch.zeros(0)
    packed = PackedSamples(torch.zeros(0, dtype=torch.int32), empty, empty, torch.zeros(3, dtype=torch.int32),
                           torch.zeros(3, dtype=torch.int32))
    assert packed_weights(empty, packed).shape == (0,)
    assert distortion_loss(empty, packed, 3).tolist() == [0.0, 0.0, 0.0]
