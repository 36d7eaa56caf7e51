"""cpgrid_encode (kernels/cpgrid.py, warpnerf/ops/cpgrid.py) against its pure-torch twin."""

import pytest
import torch

from test_hashgrid import sparse_cotangent
from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines
from warpnerf.ops.reference import cpgrid as twin


def small_spec(**kw):
    args = dict(n_levels=6, rank=4, base_resolution=4, max_resolution=96)
    args.update(kw)
    return CPGridSpec.create(**args)


def random_inputs(spec, n=2000, dtype=torch.float32, seed=0):
    gen = torch.Generator().manual_seed(seed)
    # mixed signs and magnitudes ~1 exercise the products more than a near-constant init would
    lines = torch.randn(spec.lines_shape, generator=gen, dtype=dtype)
    x = torch.rand(n, 3, generator=gen, dtype=dtype)
    return x, lines


# zero, fractional and full weights
WEIGHTS = torch.tensor([1.0, 1.0, 0.5, 0.0, 1.0, 0.25])


def test_spec_defaults_and_geometry():
    spec = CPGridSpec.create()
    assert (spec.n_levels, spec.rank, spec.base_resolution, spec.max_resolution) == (16, 16, 16, 512)
    assert spec.resolutions[0] == 16 and spec.resolutions[-1] == 512
    assert all(a < b for a, b in zip(spec.resolutions, spec.resolutions[1:]))
    assert spec.offsets[0] == 0
    assert all(spec.offsets[m + 1] - spec.offsets[m] == spec.resolutions[m] for m in range(spec.n_levels))
    assert spec.n_rows == sum(spec.resolutions) == spec.offsets[-1]
    assert spec.out_dim == 256 and spec.lines_shape == (spec.n_rows, 3, 16)
    # geometric growth: 16 * 32^(m/15), floored
    assert spec.resolutions[5] == int(16 * 32 ** (5 / 15))
    assert CPGridSpec.create(n_levels=1, base_resolution=8, max_resolution=8).resolutions == (8,)


@pytest.mark.parametrize(
    "kw, err",
    [
        (dict(n_levels=0), ValueError),
        (dict(rank=0), ValueError),
        (dict(rank=10_000), ValueError),
        (dict(base_resolution=1), ValueError),
        (dict(base_resolution=64, max_resolution=32), ValueError),
        (dict(rank=4.0), TypeError),
        (dict(n_levels=True), TypeError),
    ],
)
def test_spec_validation(kw, err):
    with pytest.raises(err):
        CPGridSpec.create(**kw)


def test_forward_matches_twin():
    spec = small_spec()
    x, lines = random_inputs(spec)
    ours = cpgrid_encode(x, lines, spec, WEIGHTS)
    ref = twin.cpgrid_encode(x, lines, spec, WEIGHTS)
    assert ours.shape == (x.shape[0], spec.out_dim)
    # measured max |diff| 0 (same operation order); the slack allows FMA contraction elsewhere
    torch.testing.assert_close(ours, ref, atol=1e-6, rtol=1e-6)
    # the masked level (weight 0) is exactly zero
    assert torch.equal(ours[:, 3 * spec.rank : 4 * spec.rank], torch.zeros(x.shape[0], spec.rank))


@pytest.mark.parametrize("wrt, sparse", [("both", False), ("x", False), ("lines", False), ("both", True)])
def test_gradients_match_twin(wrt, sparse):
    """Dense cotangents, and sparse ones (see tests/ops/test_hashgrid.py: skipped zero rows leave the
    gradients equal to the twin's)."""
    spec = small_spec()
    x, lines = random_inputs(spec, seed=3 if sparse else 1)
    x.requires_grad_(wrt in ("both", "x"))
    lines.requires_grad_(wrt in ("both", "lines"))
    inputs = [t for t in (x, lines) if t.requires_grad]
    ours = cpgrid_encode(x, lines, spec, WEIGHTS)
    ref = twin.cpgrid_encode(x, lines, spec, WEIGHTS)
    if sparse:
        cot, tiny = sparse_cotangent(ours.shape, seed=4)
    else:
        cot = torch.randn(ours.shape, generator=torch.Generator().manual_seed(7))
    g_ours = torch.autograd.grad(ours, inputs, cot)
    g_ref = torch.autograd.grad(ref, inputs, cot)
    for t, a, b in zip(inputs, g_ours, g_ref):
        if t is x:
            # measured max |diff| 1.8e-4 for |dx| up to 1.7e3 (scaled by s-1 = 95, summed over 20 features)
            torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-5)
        else:
            # measured max |diff| 1.9e-5 for |dlines| up to 37 (sums over many points per entry)
            torch.testing.assert_close(a, b, atol=2e-4, rtol=1e-5)
    if sparse:
        zero_rows = ~cot.any(dim=1)
        assert zero_rows.sum() > 500 and not g_ours[0][zero_rows].any()
        assert g_ours[0][tiny].abs().sum() > 0


@pytest.mark.gradcheck
def test_float64_gradcheck():
    spec = CPGridSpec.create(n_levels=3, rank=2, base_resolution=3, max_resolution=9)
    x, lines = random_inputs(spec, n=7, dtype=torch.float64, seed=2)
    # keep points away from the box border, where clamping makes the map non-smooth
    x = (x * 0.8 + 0.1).requires_grad_()
    lines.requires_grad_()
    w = torch.tensor([1.0, 0.7, 0.3], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: cpgrid_encode(a, b, spec, w), (x, lines), eps=1e-6, atol=1e-7)
    torch.testing.assert_close(cpgrid_encode(x, lines, spec, w), twin.cpgrid_encode(x, lines, spec, w), atol=1e-12, rtol=0)


def test_masked_levels_contribute_nothing_and_read_nothing():
    spec = small_spec()
    x, lines = random_inputs(spec, seed=3)
    masked = 3  # WEIGHTS[3] == 0
    lo, hi = spec.offsets[masked], spec.offsets[masked + 1]
    # poison the masked level: any read of it would turn the output or dx into NaN
    lines[lo:hi] = float("nan")
    lines.requires_grad_()
    x.requires_grad_()
    out = cpgrid_encode(x, lines, spec, WEIGHTS)
    assert torch.isfinite(out).all()
    cols = slice(masked * spec.rank, (masked + 1) * spec.rank)
    assert torch.equal(out[:, cols], torch.zeros_like(out[:, cols]))
    out.backward(torch.randn_like(out))
    assert torch.equal(lines.grad[lo:hi], torch.zeros_like(lines.grad[lo:hi]))
    assert torch.isfinite(x.grad).all()
    # active levels do receive gradient
    assert lines.grad[spec.offsets[0] : spec.offsets[1]].abs().sum() > 0
    assert lines.grad[spec.offsets[5] : spec.offsets[6]].abs().sum() > 0


def test_level_weight_scales_features_and_gradients():
    spec = small_spec()
    x, lines = random_inputs(spec, seed=4)
    lines.requires_grad_()
    full = cpgrid_encode(x, lines, spec)
    half = cpgrid_encode(x, lines, spec, torch.full((spec.n_levels,), 0.5))
    torch.testing.assert_close(half, 0.5 * full, atol=0, rtol=0)
    cot = torch.randn_like(full)
    (g_full,) = torch.autograd.grad(full, lines, cot)
    (g_half,) = torch.autograd.grad(half, lines, cot)
    torch.testing.assert_close(g_half, 0.5 * g_full, atol=0, rtol=0)


def test_two_threads_bit_identical_to_one(threads):
    spec = small_spec(n_levels=8, max_resolution=256)
    x, lines = random_inputs(spec, n=5000, seed=5)
    weights = torch.tensor([1.0, 1.0, 0.5, 0.0, 1.0, 0.25, 1.0, 0.75])
    results = []
    for n_threads in (1, 2):
        threads(n_threads)
        xi, li = x.clone().requires_grad_(), lines.clone().requires_grad_()
        out = cpgrid_encode(xi, li, spec, weights)
        out.backward(torch.linspace(-1, 1, out.numel()).view_as(out))
        results.append((out.detach(), xi.grad, li.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_grid_points_return_products_of_stored_values():
    spec = CPGridSpec.create(n_levels=2, rank=2, base_resolution=3, max_resolution=9)
    lines = torch.arange(spec.n_rows * 3 * 2, dtype=torch.float32).view(spec.lines_shape) / 100 + 0.5
    # level 1 has 9 points per axis: x = (5/8, 2/8, 1) sits on grid point (5, 2, 8), the last one
    pts = torch.tensor([[5 / 8, 2 / 8, 1.0], [0.0, 0.5, 1.0]])
    out = cpgrid_encode(pts, lines, spec)
    off = spec.offsets[1]
    expected = lines[off + 5, 0] * lines[off + 2, 1] * lines[off + 8, 2]
    torch.testing.assert_close(out[0, 2:4], expected, atol=1e-6, rtol=1e-6)
    # level 0 has 3 points: (0, 1/2, 1) is grid point (0, 1, 2)
    expected0 = lines[0, 0] * lines[1, 1] * lines[2, 2]
    torch.testing.assert_close(out[1, 0:2], expected0, atol=1e-6, rtol=1e-6)
    # halfway between two points: the average of the two entries (linear interpolation)
    mid = cpgrid_encode(torch.tensor([[0.25, 0.0, 0.0]]), lines, spec)
    expected_mid = 0.5 * (lines[0, 0] + lines[1, 0]) * lines[0, 1] * lines[0, 2]
    torch.testing.assert_close(mid[0, 0:2], expected_mid, atol=1e-6, rtol=1e-6)


def test_points_outside_box_are_clamped_with_zero_gradient():
    spec = small_spec()
    _, lines = random_inputs(spec, seed=6)
    lines.requires_grad_()
    x = torch.tensor([[-0.5, 0.3, 1.7], [0.2, 0.4, 0.6], [2.0, -1.0, 0.5]], requires_grad=True)
    out = cpgrid_encode(x, lines, spec, WEIGHTS)
    torch.testing.assert_close(out, cpgrid_encode(x.detach().clamp(0, 1), lines, spec, WEIGHTS), atol=0, rtol=0)
    out.sum().backward()
    assert x.grad[0, 0] == 0 and x.grad[0, 2] == 0 and x.grad[0, 1] != 0
    assert x.grad[2, 0] == 0 and x.grad[2, 1] == 0 and x.grad[2, 2] != 0
    # same gradients as the twin (whose torch.clamp zeroes them)
    xr, lr = x.detach().clone().requires_grad_(), lines.detach().clone().requires_grad_()
    twin.cpgrid_encode(xr, lr, spec, WEIGHTS).sum().backward()
    torch.testing.assert_close(x.grad, xr.grad, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(lines.grad, lr.grad, atol=1e-5, rtol=1e-5)


def test_empty_input_and_all_masked():
    spec = small_spec()
    _, lines = random_inputs(spec)
    lines.requires_grad_()
    x0 = torch.zeros(0, 3, requires_grad=True)
    out0 = cpgrid_encode(x0, lines, spec)
    assert out0.shape == (0, spec.out_dim)
    out0.sum().backward()
    assert x0.grad.shape == (0, 3) and torch.equal(lines.grad, torch.zeros_like(lines))
    x = torch.rand(4, 3, requires_grad=True)
    out = cpgrid_encode(x, lines, spec, torch.zeros(spec.n_levels))
    assert torch.equal(out, torch.zeros_like(out))
    out.sum().backward()
    assert torch.equal(x.grad, torch.zeros_like(x))


@pytest.mark.parametrize(
    "make, err, match",
    [
        (lambda x, t: (x.double(), t), TypeError, "dtype"),
        (lambda x, t: (x.half(), t.half()), TypeError, "float32 or float64"),
        (lambda x, t: (x[:, :2].contiguous(), t), ValueError, "shape"),
        (lambda x, t: (x, t[:-1]), ValueError, "lines must have shape"),
        (lambda x, t: (x, t[:, :2].contiguous()), ValueError, "lines must have shape"),
        (lambda x, t: (x, t.transpose(1, 2).contiguous().transpose(1, 2)), ValueError, "contiguous"),
        (lambda x, t: (x.t().contiguous().t(), t), ValueError, "contiguous"),
        (lambda x, t: (torch.full_like(x, float("nan")), t), ValueError, "NaN"),
        (lambda x, t: (x.to("meta"), t), ValueError, "meta"),
        (lambda x, t: (x.to("meta"), t.to("meta")), ValueError, "cpu and cuda"),
        (lambda x, t: (x.numpy(), t), TypeError, "torch tensors"),
    ],
)
def test_bad_input_is_a_clear_error(make, err, match):
    spec = small_spec()
    x, lines = random_inputs(spec, n=8)
    xb, lb = make(x, lines)
    with pytest.raises(err, match=match):
        cpgrid_encode(xb, lb, spec)


def test_bad_spec_and_level_weights():
    spec = small_spec()
    x, lines = random_inputs(spec, n=8)
    with pytest.raises(TypeError, match="CPGridSpec"):
        cpgrid_encode(x, lines, object())
    with pytest.raises(ValueError, match="shape"):
        cpgrid_encode(x, lines, spec, torch.ones(3))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        cpgrid_encode(x, lines, spec, torch.full((spec.n_levels,), 2.0))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        cpgrid_encode(x, lines, spec, torch.full((spec.n_levels,), float("nan")))


def test_init_cp_lines_tensorf_scale_and_live_gradients():
    spec = small_spec()
    a = init_cp_lines(spec, torch.Generator().manual_seed(0))
    b = init_cp_lines(spec, torch.Generator().manual_seed(0))
    assert a.shape == spec.lines_shape and a.dtype == torch.float32 and a.is_contiguous()
    assert torch.equal(a, b)
    # TensoRF's CP init: zero-mean, std 0.2
    assert abs(float(a.mean())) < 0.03 and 0.17 < float(a.std()) < 0.23
    lines = a.requires_grad_()
    out = cpgrid_encode(torch.rand(500, 3, generator=torch.Generator().manual_seed(1)), lines, spec)
    # products of three N(0, 0.2^2) factors, each linearly interpolated between two line values
    # (std 0.2 * sqrt(2/3) ~ 0.163 on average): std ~ 0.0044 (measured 0.0040), both signs
    assert out.min() < 0 < out.max() and 0.003 < float(out.detach().std()) < 0.016
    out.sum().backward()
    touched = lines.grad[lines.grad != 0]
    assert touched.numel() > 0 and bool(touched.abs().gt(0).all())
    assert init_cp_lines(spec, dtype=torch.float64).dtype == torch.float64
    assert float(init_cp_lines(spec, scale=0.5).std()) > 0.4
    with pytest.raises(ValueError):
        init_cp_lines(spec, scale=0.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    spec = small_spec()
    x, lines = random_inputs(spec, seed=8)
    outs, grads = [], []
    for dev in ("cpu", "cuda"):
        xi = x.to(dev).requires_grad_()
        li = lines.to(dev).requires_grad_()
        out = cpgrid_encode(xi, li, spec, WEIGHTS.to(dev))
        out.backward(torch.ones_like(out))
        outs.append(out.detach().cpu())
        grads.append((xi.grad.cpu(), li.grad.cpu()))
    torch.testing.assert_close(outs[0], outs[1], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(grads[0][0], grads[1][0], atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(grads[0][1], grads[1][1], atol=2e-4, rtol=1e-5)
