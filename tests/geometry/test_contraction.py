"""MipNeRF-360 scene contraction: identity inside the unit ball, bounded by radius 2, continuous,
invertible; disparity spacing becomes uniform spacing after contraction."""

import torch

from warpnerf.geometry.contraction import contract, disparity_spaced, uncontract


def test_identity_inside_unit_ball():
    g = torch.Generator().manual_seed(0)
    x = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g, dtype=torch.float64), dim=-1)
    x = x * torch.rand(1000, 1, generator=g, dtype=torch.float64)  # |x| <= 1
    assert torch.equal(contract(x), x)


def test_bounded_by_two_and_monotone_in_radius():
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64), dim=-1)
    r = torch.logspace(0, 12, 500, dtype=torch.float64)[:, None]
    y = contract(d * r).norm(dim=-1)
    assert (y < 2.0).all() and (y[1:] >= y[:-1]).all()
    assert abs(float(y[-1]) - 2.0) < 1e-9
    torch.testing.assert_close(y, 2.0 - 1.0 / r[:, 0])


def test_continuous_with_continuous_derivative_at_the_sphere():
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    for eps in (1e-4, 1e-6, 1e-8):
        inner, outer = contract(d * (1 - eps)), contract(d * (1 + eps))
        assert (outer - inner).norm() < 3 * eps  # Lipschitz 1 across the boundary
    x = (d * 1.0000001).requires_grad_(True)
    jac_out = torch.autograd.functional.jacobian(contract, x)[0, :, 0, :]
    x_in = (d * 0.9999999).requires_grad_(True)
    jac_in = torch.autograd.functional.jacobian(contract, x_in)[0, :, 0, :]
    torch.testing.assert_close(jac_out, jac_in, atol=1e-5, rtol=0)


def test_uncontract_inverts_and_gradients_are_finite():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2000, 3, generator=g, dtype=torch.float64) * 20
    torch.testing.assert_close(uncontract(contract(x)), x, rtol=1e-9, atol=1e-9)
    x = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    contract(x).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_disparity_spacing_is_uniform_after_contraction():
    t = disparity_spaced(1.0, float("inf"), 16, dtype=torch.float64)
    assert t[0] == 1.0 and t[-1] >= 1e11  # "infinity": 1 / the clamped disparity 1e-12
    r = contract(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) * t[:-1, None]).norm(dim=-1)
    steps = r[1:] - r[:-1]
    torch.testing.assert_close(steps, torch.full_like(steps, 1.0 / 16))
