"""hashgrid_encode (kernels/hashgrid.py, warpnerf/ops/hashgrid.py) against its pure-torch twin."""

import math

import pytest
import torch

from warpnerf.model.g2fr import G2fRSchedule, g2fr_level_weight, g2fr_tau, g2fr_weights
from warpnerf.ops.hashgrid import HashGridSpec, hashgrid_encode
from warpnerf.ops.reference import hashgrid as twin


def small_spec(dim, **kw):
    args = dict(dim=dim, n_levels=6, n_features=2, log2_table_size=10, base_resolution=4, max_resolution=96)
    args.update(kw)
    return HashGridSpec.create(**args)


def random_inputs(spec, n=2000, dtype=torch.float32, seed=0):
    gen = torch.Generator().manual_seed(seed)
    table = torch.randn(spec.n_rows, spec.n_features, generator=gen, dtype=dtype) * 0.1
    x = torch.rand(n, spec.dim, generator=gen, dtype=dtype)
    return x, table


WEIGHTS = torch.tensor([1.0, 1.0, 0.5, 0.0, 1.0, 0.25])


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_spec_has_dense_and_hashed_levels(dim):
    spec = small_spec(dim)
    assert spec.resolutions[0] == 4 and spec.resolutions[-1] == 96
    if dim >= 2:  # 96^2 > 2^10: the finest levels must be hashed, the coarsest dense
        assert spec.hashed[-1] and not spec.hashed[0]


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_forward_matches_twin(dim):
    spec = small_spec(dim)
    x, table = random_inputs(spec)
    ours = hashgrid_encode(x, table, spec, WEIGHTS)
    ref = twin.hashgrid_encode(x, table, spec, WEIGHTS)
    assert ours.shape == (x.shape[0], spec.out_dim)
    # measured max |diff| 3.0e-8 (float32 summation order of the 2^D corners)
    torch.testing.assert_close(ours, ref, atol=1e-6, rtol=0)


def sparse_cotangent(shape, seed):
    """Random cotangent whose rows are mostly exact zeros (samples the compositing ignores, which the
    backward kernels skip) with a few tiny non-zero entries that must not be skipped."""
    gen = torch.Generator().manual_seed(seed)
    cot = torch.randn(shape, generator=gen)
    cot[torch.rand(shape[0], generator=gen) < 0.6] = 0.0
    tiny = torch.nonzero(cot[:, 0] == 0).squeeze(1)[::7]
    cot[tiny, -1] = 1e-30  # squares to 0 in float32: a norm test would wrongly skip these rows
    return cot, tiny


@pytest.mark.parametrize("sparse", [False, True])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_gradients_match_twin(dim, sparse):
    """Dense cotangents, and sparse ones: the backward skips (point, level) pairs whose upstream
    gradient is exactly zero, so rows with a zero cotangent get a zero d/dx, tiny non-zero rows
    still count, and the result still equals the twin's."""
    spec = small_spec(dim)
    x, table = random_inputs(spec, seed=3 if sparse else 1)
    x.requires_grad_()
    table.requires_grad_()
    ours = hashgrid_encode(x, table, spec, WEIGHTS)
    ref = twin.hashgrid_encode(x, table, spec, WEIGHTS)
    cot, tiny = sparse_cotangent(ours.shape, seed=4) if sparse else (torch.randn_like(ours), None)
    g_ours = torch.autograd.grad(ours, (x, table), cot)
    g_ref = torch.autograd.grad(ref, (x, table), cot)
    # measured max |diff|: dx 3.8e-6 (values ~ 1e1, scaled by s-1 = 95), dtable 2.1e-5 (sums over ~100 points)
    torch.testing.assert_close(g_ours[0], g_ref[0], atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(g_ours[1], g_ref[1], atol=1e-4, rtol=1e-5)
    if sparse:
        zero_rows = ~cot.any(dim=1)
        assert zero_rows.sum() > 500 and not g_ours[0][zero_rows].any()
        # the tiny rows are not skipped: their x-gradient is non-zero, as the twin's (where the level is active)
        assert g_ours[0][tiny].abs().sum() > 0 and torch.equal(g_ours[0][tiny] != 0, g_ref[0][tiny] != 0)


@pytest.mark.gradcheck
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_float64_gradcheck(dim):
    spec = HashGridSpec.create(dim=dim, n_levels=3, n_features=2, log2_table_size=5, base_resolution=3, max_resolution=9)
    x, table = random_inputs(spec, n=7, dtype=torch.float64, seed=2)
    # keep points away from cell borders, where the piecewise-linear map has kinks
    x = (x * 0.8 + 0.1).requires_grad_()
    table.requires_grad_()
    w = torch.tensor([1.0, 0.7, 0.3], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: hashgrid_encode(a, b, spec, w), (x, table), eps=1e-6, atol=1e-7)


def test_masked_levels_contribute_nothing_and_read_nothing():
    spec = small_spec(3)
    x, table = random_inputs(spec, seed=3)
    masked = 3  # WEIGHTS[3] == 0
    lo, hi = spec.offsets[masked], spec.offsets[masked + 1]
    # poison the masked level: any read of it would turn the output into NaN
    table[lo:hi] = float("nan")
    table.requires_grad_()
    out = hashgrid_encode(x, table, spec, WEIGHTS)
    assert torch.isfinite(out).all()
    cols = slice(masked * spec.n_features, (masked + 1) * spec.n_features)
    assert torch.equal(out[:, cols], torch.zeros_like(out[:, cols]))
    out.backward(torch.randn_like(out))
    assert torch.equal(table.grad[lo:hi], torch.zeros_like(table.grad[lo:hi]))
    # an active level does receive gradient
    assert table.grad[spec.offsets[0] : spec.offsets[1]].abs().sum() > 0


def test_level_weight_scales_features():
    spec = small_spec(2)
    x, table = random_inputs(spec, seed=4)
    full = hashgrid_encode(x, table, spec)
    half = hashgrid_encode(x, table, spec, torch.full((spec.n_levels,), 0.5))
    torch.testing.assert_close(half, 0.5 * full, atol=0, rtol=0)


def test_two_threads_bit_identical_to_one(threads):
    spec = small_spec(3, log2_table_size=12, max_resolution=256)
    x, table = random_inputs(spec, n=5000, seed=5)
    results = []
    for n_threads in (1, 2):
        threads(n_threads)
        xi, ti = x.clone().requires_grad_(), table.clone().requires_grad_()
        out = hashgrid_encode(xi, ti, spec, WEIGHTS)
        out.backward(torch.linspace(-1, 1, out.numel()).view_as(out))
        results.append((out.detach(), xi.grad, ti.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_grid_point_returns_stored_feature_and_hash_formula():
    spec = HashGridSpec.create(dim=3, n_levels=2, n_features=1, log2_table_size=6, base_resolution=3, max_resolution=9)
    assert spec.hashed == (False, True)
    table = torch.zeros(spec.n_rows, 1)
    ix, iy, iz = 5, 2, 7
    # Instant-NGP hash, computed here with Python integers
    row = ((ix * 1) ^ ((iy * 2654435761) % 2**32) ^ ((iz * 805459861) % 2**32)) % 2**6
    table[spec.offsets[1] + row] = 1.0
    dense_row = 1 + 3 * (2 + 3 * 0)  # grid point (1, 2, 0) of the 3x3x3 level
    table[dense_row] = 2.0
    pts = torch.tensor([[ix / 8, iy / 8, iz / 8], [1 / 2, 1.0, 0.0]])
    out = hashgrid_encode(pts, table, spec)
    assert out[0, 1].item() == pytest.approx(1.0, abs=1e-6)
    assert out[1, 0].item() == pytest.approx(2.0, abs=1e-6)


def test_points_outside_box_are_clamped_with_zero_gradient():
    spec = small_spec(3)
    _, table = random_inputs(spec, seed=6)
    x = torch.tensor([[-0.5, 0.3, 1.7], [0.2, 0.4, 0.6]], requires_grad=True)
    out = hashgrid_encode(x, table, spec)
    torch.testing.assert_close(out, hashgrid_encode(x.detach().clamp(0, 1), table, spec), atol=0, rtol=0)
    out.sum().backward()
    assert x.grad[0, 0] == 0 and x.grad[0, 2] == 0 and x.grad[0, 1] != 0


def test_empty_input_and_all_masked():
    spec = small_spec(3)
    _, table = random_inputs(spec)
    assert hashgrid_encode(torch.zeros(0, 3), table, spec).shape == (0, spec.out_dim)
    out = hashgrid_encode(torch.rand(4, 3), table, spec, torch.zeros(spec.n_levels))
    assert torch.equal(out, torch.zeros_like(out))


@pytest.mark.parametrize(
    "make, err, match",
    [
        (lambda x, t: (x.double(), t), TypeError, "dtype"),
        (lambda x, t: (x.half(), t.half()), TypeError, "float32 or float64"),
        (lambda x, t: (x[:, :2].contiguous(), t), ValueError, "shape"),
        (lambda x, t: (x, t[:-1]), ValueError, "table must have shape"),
        (lambda x, t: (x.t().contiguous().t(), t), ValueError, "contiguous"),
        (lambda x, t: (torch.full_like(x, float("nan")), t), ValueError, "NaN"),
        (lambda x, t: (x.to("meta"), t), ValueError, "meta"),
        (lambda x, t: (x.numpy(), t), TypeError, "torch tensors"),
    ],
)
def test_bad_input_is_a_clear_error(make, err, match):
    spec = small_spec(3)
    x, table = random_inputs(spec, n=8)
    xb, tb = make(x, table)
    with pytest.raises(err, match=match):
        hashgrid_encode(xb, tb, spec)


def test_bad_level_weights():
    spec = small_spec(3)
    x, table = random_inputs(spec, n=8)
    with pytest.raises(ValueError, match="shape"):
        hashgrid_encode(x, table, spec, torch.ones(3))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        hashgrid_encode(x, table, spec, torch.full((spec.n_levels,), 2.0))


# --- the G²fR schedule (paper eq. 15) ---------------------------------------------------


def test_tau_follows_eq15():
    # tau = M * min(t / (beta T), 1): M=16, T=1000, beta=0.5 -> tau = 16 t / 500 until t = 500
    assert g2fr_tau(0, 1000, 16, 0.5) == 0.0
    assert g2fr_tau(125, 1000, 16, 0.5) == pytest.approx(4.0)
    assert g2fr_tau(500, 1000, 16, 0.5) == pytest.approx(16.0)
    assert g2fr_tau(900, 1000, 16, 0.5) == pytest.approx(16.0)


def test_cosine_weights_at_hand_computed_points():
    # level i ramps over i-1 <= tau < i (BARF's 0-based form of eq. 15, see the warpnerf.model.g2fr docstring)
    assert g2fr_level_weight(1, 0.0) == 1.0  # w_1 = 1 always
    assert g2fr_level_weight(3, 1.99) == 0.0  # before the ramp
    assert g2fr_level_weight(3, 2.0) == pytest.approx(0.0)  # ramp starts
    assert g2fr_level_weight(3, 2.5) == pytest.approx(0.5)  # (1 - cos(pi/2)) / 2
    assert g2fr_level_weight(3, 2.25) == pytest.approx((1 - math.cos(math.pi / 4)) / 2)
    assert g2fr_level_weight(3, 3.0) == 1.0  # ramp done
    assert g2fr_level_weight(3, 2.5, "binary") == 0.0  # binary: on at the end of the ramp
    assert g2fr_level_weight(3, 3.0, "binary") == 1.0


def test_every_level_is_on_after_beta_T():
    # the literal eq. 15 would leave the finest level at 0 forever (tau <= M); ours must not
    assert torch.equal(g2fr_weights(50, 100, 16, 0.5), torch.ones(16))
    assert torch.equal(g2fr_weights(50, 100, 16, 0.5, "binary"), torch.ones(16))


def test_weights_vector_and_schedule():
    # M=4, T=100, beta=0.5: at t=30, tau = 4*30/50 = 2.4 -> [1, 1, (1-cos(0.4 pi))/2, 0]
    w = g2fr_weights(30, 100, 4, 0.5)
    expected = torch.tensor([1.0, 1.0, (1 - math.cos(0.4 * math.pi)) / 2, 0.0])
    torch.testing.assert_close(w, expected)
    sched = G2fRSchedule(4, 100, beta=0.5)
    assert sched.active_levels(0) == 1 and sched.active_levels(50) == 4
    assert torch.equal(G2fRSchedule(4, 100, enabled=False)(0), torch.ones(4))
    with pytest.raises(ValueError, match="beta"):
        G2fRSchedule(4, 100, beta=0.0)
    with pytest.raises(ValueError, match="mask mode"):
        G2fRSchedule(4, 100, mode="smooth")


@pytest.mark.parametrize("op", ["hashgrid", "cpgrid"])
def test_known_output_skips_the_forward_and_keeps_the_backward(op):
    """``known_output`` (the renderer's compaction reuses an encoding computed without autograd):
    the call returns that tensor's values and its backward equals a fresh call's, to the bit."""
    from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines

    if op == "hashgrid":
        spec = small_spec(3)
        x, params = random_inputs(spec, n=500, seed=3)
        encode = hashgrid_encode
    else:
        spec = CPGridSpec.create(n_levels=4, rank=4, base_resolution=4, max_resolution=32)
        x, params = torch.rand(500, 3, generator=torch.Generator().manual_seed(3)), init_cp_lines(spec)
        encode = cpgrid_encode
    weights = [1.0] * (spec.n_levels - 2) + [0.5, 0.0]
    x.requires_grad_(True)
    params.requires_grad_(True)
    with torch.no_grad():
        known = encode(x, params, spec, weights)
    fresh = encode(x, params, spec, weights)
    reused = encode(x, params, spec, weights, known_output=known)
    assert torch.equal(fresh.detach(), reused.detach())
    cot = torch.randn(fresh.shape, generator=torch.Generator().manual_seed(4))
    grads_fresh = torch.autograd.grad(fresh, (x, params), cot)
    grads_reused = torch.autograd.grad(reused, (x, params), cot)
    for a, b in zip(grads_fresh, grads_reused):
        assert torch.equal(a, b) and bool(a.abs().sum() > 0)
    # proof that the forward really is skipped: the known values come back even when they are not the encoding
    assert torch.equal(encode(x, params, spec, weights, known_output=known + 1.0).detach(), known + 1.0)
    for bad in (known[1:], known.double(), known[:, :-1]):
        with pytest.raises(ValueError, match=f"{op}_encode: known_output must be"):
            encode(x, params, spec, weights, known_output=bad)
