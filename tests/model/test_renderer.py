"""Renderer.render_image: rendering in rounds (early ray termination) against every sample, in
each ray space, on an analytic field (no training: fast and independent of the grid encodings)."""

import math

import pytest
import torch

from warpnerf.geometry.rayspace import RaySpace
from warpnerf.model.occupancy import OccupancyGrid
from warpnerf.model.renderer import Renderer, default_step


class Blobs(torch.nn.Module):
    """Two soft balls of density (one dense, one thin) with position-dependent colour; the
    field's interface (``geometry``, ``color``) on the space the renderer hands it."""

    def __init__(self, centers, radius: float, densities):
        super().__init__()
        self.centers = torch.tensor(centers, dtype=torch.float32)
        self.radius = radius
        self.densities = torch.tensor(densities, dtype=torch.float32)

    def geometry(self, x, level_weights=None):
        dist = torch.cdist(x, self.centers)
        sigma = (self.densities * torch.sigmoid((self.radius - dist) * 40.0)).sum(1)
        return sigma, torch.cat([torch.sin(3 * x), torch.cos(2 * x)], 1)

    def color(self, geo, dirs):
        return torch.sigmoid(geo[:, :3] + geo[:, 3:] * dirs)


def renderer_for(kind: str) -> tuple[Renderer, torch.Tensor]:
    """A renderer in ray space ``kind`` and a camera-to-world looking at the blobs."""
    if kind == "euclidean":
        aabb = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
        space, step = RaySpace.euclidean(aabb, 0.1, 10.0), default_step(aabb, 256)
        field = Blobs([[0.0, 0.0, 0.0], [0.9, 0.5, 0.6]], 0.8, [100.0, 2.0])
        c2w = torch.tensor([[1.0, 0, 0, 0.1], [0, 1, 0, -0.1], [0, 0, 1, 2.2]])
    elif kind == "ndc":
        space = RaySpace.ndc(40.0, 48, 40)
        aabb, step = space.aabb, default_step(space.aabb, 256)
        field = Blobs([[0.0, 0.0, 0.0], [0.6, -0.5, -0.5]], 0.75, [150.0, 3.0])
        c2w = torch.tensor([[1.0, 0, 0, 0.0], [0, 1, 0, 0.0], [0, 0, 1, 0.0]])
    else:
        space = RaySpace.contracted(0.05, far=200.0)
        aabb, step = space.aabb, 4.0 / 256
        field = Blobs([[0.0, 0.0, 0.0], [1.1, 0.4, 0.4]], 0.8, [100.0, 1.5])
        c2w = torch.tensor([[1.0, 0, 0, 0.0], [0, 1, 0, 0.0], [0, 0, 1, 2.5]])
    occ = OccupancyGrid(aabb, 32)  # every cell occupied
    return Renderer(field, occ, space, step, background=(0.2, 0.4, 0.6)), c2w


@pytest.mark.parametrize("kind", ["euclidean", "ndc", "contracted"])
def test_rounds_render_the_image_of_every_sample(kind):
    r, c2w = renderer_for(kind)
    calls = []
    geometry = r.field.geometry

    def counting(x, lw=None):
        calls.append(x.shape[0])
        return geometry(x, lw)

    r.field.geometry = counting
    args = (c2w, 40, 48, 40.0, 24.0, 20.0)
    r.stop_transmittance = 0.0
    every = r.render_image(*args)
    marched, calls[:] = sum(calls), []
    r.stop_transmittance = 1e-4
    rounds = r.render_image(*args)
    evaluated, calls[:] = sum(calls), []
    r.round_samples, r.max_window = 701, 2  # many small rounds, chunks of 701 rays: same image
    tiny = r.render_image(*args, chunk=701)
    opacity = every["opacity"]
    # the scene is rendered: some rays opaque, some see the background, some the thin blob
    assert float(opacity.max()) > 0.999 and float(opacity.min()) < 0.01
    assert bool(((opacity > 0.05) & (opacity < 0.9)).any())
    # measured 0.71 / 0.68 / 0.79 of the samples (rays behind the dense ball stop)
    assert evaluated < 0.85 * marched, (evaluated, marched)
    assert (rounds["samples"], every["samples"]) == (evaluated, marched)  # what render_image reports
    # a ray stops once its transmittance is below stop_transmittance, so the light it leaves out is
    # below that too (measured up to 7.6e-5 in rgb on one CPU, < 1e-5 on others). Depth is divided
    # by opacity: on nearly transparent pixels a last-bit difference moves it by ~1 (measured 1.57
    # at opacity ~1e-7), so it is compared where the pixel shows something
    light_tol = 1e-4 + 1e-5
    seen = every["opacity"] > 0.01
    depth_tol = 1e-3 * float(every["depth"].abs().max())
    for other in (rounds, tiny):
        assert float((other["rgb"] - every["rgb"]).abs().max()) < light_tol, kind
        assert float((other["opacity"] - every["opacity"]).abs().max()) < light_tol, kind
        assert float((other["depth"] - every["depth"])[seen].abs().max()) < depth_tol, kind
    assert not math.isnan(float(rounds["depth"].sum()))


def test_skipping_empty_blocks_renders_the_same_image():
    """With an occupancy grid updated from the field (empty space marked empty), the renderer's
    march across empty blocks of cells (``OccupancyGrid.occupied_blocks``) gives exactly the
    image, and in training the colours, of the march that tests every candidate."""
    r, c2w = renderer_for("euclidean")
    occ = r.occupancy
    g = torch.Generator().manual_seed(0)
    occ.update(step=0, density_fn=lambda x: r.field.geometry(x)[0], generator=g)
    assert 0.05 < float(occ.occupied_blocks()[1].float().mean()) < 0.95  # some blocks are skipped
    args = (c2w, 40, 48, 40.0, 24.0, 20.0)
    o = c2w[:, 3].expand(300, 3).contiguous()
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    jitter = torch.rand(300, generator=g)
    skipped, trained = r.render_image(*args), r.render_rays(o, d, jitter=jitter)
    occ.occupied_blocks = lambda block=8: None  # every candidate tested
    full, trained_full = r.render_image(*args), r.render_rays(o, d, jitter=jitter)
    assert skipped["samples"] == full["samples"] and torch.equal(skipped["rgb"], full["rgb"])
    assert trained.n_samples == trained_full.n_samples > 1000 and torch.equal(trained.rgb, trained_full.rgb)


def test_field_without_autograd_evaluates_in_row_blocks_with_the_same_values():
    """Under no_grad the MLPs run on 4096 rows at a time (cache-sized): values equal the
    autograd path's to the bit."""
    from warpnerf.model.field import GridField, in_row_blocks
    from warpnerf.ops.hashgrid import HashGridSpec
    from warpnerf.model.encoders import HashGridEncoder

    torch.manual_seed(0)
    spec = HashGridSpec.create(3, 4, 2, 12, 4, 64)
    field = GridField((-1, -1, -1, 1, 1, 1), HashGridEncoder(spec, init_scale=0.5))
    x, d = torch.rand(10000, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(10000, 3), dim=1)
    sigma, geo = field.geometry(x)
    rgb = field.color(geo, d)
    with torch.no_grad():
        sigma_b, geo_b = field.geometry(x)
        rgb_b = field.color(geo_b, d)
    assert torch.equal(sigma.detach(), sigma_b) and torch.equal(geo.detach(), geo_b)
    assert torch.equal(rgb.detach(), rgb_b)
    rows = []
    with torch.no_grad():
        out = in_row_blocks(lambda a, b: rows.append(a.shape[0]) or a + b, x, d, rows=4096)
    assert rows == [4096, 4096, 1808] and torch.equal(out, x + d)
    rows.clear()  # with autograd: one call
    out = in_row_blocks(lambda a, b: rows.append(a.shape[0]) or a + b, x, d, rows=4096)
    assert rows == [10000] and torch.equal(out, x + d)


def test_density_of_is_the_geometry_density_and_its_gradient():
    """``GridField.density_of`` (the occupancy grid's and the compaction pass's density) computes
    only the first output of the density MLP's last layer: the same densities as ``geometry_of``
    up to float summation order, with and without autograd, and the same gradients."""
    from warpnerf.model.encoders import HashGridEncoder
    from warpnerf.model.field import GridField
    from warpnerf.ops.hashgrid import HashGridSpec

    torch.manual_seed(0)
    spec = HashGridSpec.create(3, 4, 2, 12, 4, 64)
    field = GridField((-1, -1, -1, 1, 1, 1), HashGridEncoder(spec, init_scale=0.5), density_shift=-0.5)
    x = torch.rand(9000, 3) * 2 - 1
    enc = field.encode(x)
    full = field.geometry_of(enc)[0]
    only = field.density_of(enc)
    assert only.shape == (9000,) and float(only.detach().std()) > 0
    torch.testing.assert_close(only, full, rtol=1e-6, atol=0)
    with torch.no_grad():  # in row blocks
        torch.testing.assert_close(field.density(x), full.detach(), rtol=1e-6, atol=0)
    params = list(field.parameters())
    g_full = torch.autograd.grad(full.square().sum(), params, retain_graph=True, allow_unused=True)
    g_only = torch.autograd.grad(only.square().sum(), params, allow_unused=True)
    for i, (a, b) in enumerate(zip(g_only, g_full)):
        if b is None or not b.any():  # the colour MLP and the geometry features' rows
            assert a is None or not a.any(), i
            continue
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6 * float(b.abs().max()), msg=lambda m, i=i: f"{i}: {m}")


class WithoutGeometryOf(torch.nn.Module):
    """A grid field that offers ``encode`` and ``density_of`` but not ``geometry_of``: the
    renderer must not hand it an encoding to continue from."""

    def __init__(self, field):
        super().__init__()
        self.inner = field

    def encode(self, x, level_weights=None, known_output=None):
        return self.inner.encode(x, level_weights, known_output)

    def density_of(self, enc):
        return self.inner.density_of(enc)

    def geometry(self, x, level_weights=None):
        return self.inner.geometry(x, level_weights)

    def color(self, geo, dirs):
        return self.inner.color(geo, dirs)


@pytest.mark.parametrize("field_kind", ["grid", "grid_without_geometry_of", "blobs"])
def test_training_compaction_keeps_pixels_and_gradients(field_kind):
    """Training (``render_rays`` with autograd) evaluates the field on every marched sample without
    autograd, then differentiates only the samples before each ray turned opaque, reusing their
    grid encoding (``Renderer.compact_training``): the pixels and every gradient (grid, MLPs,
    ray origins: the pose task's path) equal those of differentiating every sample, up to the
    MLPs' float summation order over fewer rows; the distortion loss too."""
    from warpnerf.model.encoders import HashGridEncoder
    from warpnerf.model.field import GridField
    from warpnerf.ops.hashgrid import HashGridSpec

    r, c2w = renderer_for("euclidean")
    if field_kind.startswith("grid"):
        torch.manual_seed(0)
        spec = HashGridSpec.create(3, 6, 2, 12, 4, 64)
        r.field = GridField((-1.5, -1.5, -1.5, 1.5, 1.5, 1.5), HashGridEncoder(spec, init_scale=0.5))
        with torch.no_grad():
            r.field.density_net[2].bias[0] = 2.0  # dense enough that rays turn opaque inside the box
        if field_kind == "grid_without_geometry_of":
            r.field = WithoutGeometryOf(r.field)
    g = torch.Generator().manual_seed(1)
    o = (c2w[:, 3] + 0.05 * torch.randn(400, 3, generator=g)).requires_grad_(True)
    d = torch.nn.functional.normalize(torch.randn(400, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    jitter = torch.rand(400, generator=g)
    weights = (1.0, 1.0, 1.0, 1.0, 0.5, 0.0)
    params = [o] + list(r.field.parameters())
    results = []
    for compact in (False, True):
        r.compact_training = compact
        out = r.render_rays(o, d, weights if field_kind.startswith("grid") else None, jitter, distortion=True)
        loss = (out.rgb * torch.linspace(0.5, 1.5, 3)).square().sum() + out.depth.sum() * 1e-2 + out.distortion.sum()
        results.append((out, torch.autograd.grad(loss, params, allow_unused=True)))
    (full, grads_full), (cut, grads_cut) = results
    assert full.n_samples == cut.n_samples == full.n_active
    # most samples lie behind an opaque surface: the case compaction is for
    assert cut.n_active < 0.6 * cut.n_samples, (cut.n_active, cut.n_samples)
    torch.testing.assert_close(cut.rgb, full.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(cut.opacity, full.opacity, rtol=0, atol=1e-6)
    # the distortion loss (warpnerf.model.losses) sees the same weights: those behind are exactly 0
    assert float(full.distortion.detach().max()) > 0
    torch.testing.assert_close(cut.distortion, full.distortion, rtol=1e-5, atol=1e-7)
    for i, (a, b) in enumerate(zip(grads_cut, grads_full)):
        if b is None:
            assert a is None
            continue
        scale = float(b.abs().max())
        assert scale > 0, i
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5 * scale, msg=lambda m, i=i: f"parameter {i}: {m}")


def test_render_pixels_renders_every_pixel_within_the_sample_budget():
    """Renderer.render_pixels splits the pixels into as many render_rays calls as the sample budget
    needs: the colours, and the pose gradient accumulated chunk by chunk (the callable camera
    form, rebuilt per chunk as after a backward), match one call with room for every sample."""
    r, c2w = renderer_for("euclidean")
    g = torch.Generator().manual_seed(0)
    n, intrinsics = 400, (40.0, 24.0, 20.0)
    u, v = torch.rand(n, generator=g) * 48, torch.rand(n, generator=g) * 40
    target = torch.rand(n, 3, generator=g)

    def run(budget: int):
        r.sample_budget = budget
        shift = torch.zeros(3, requires_grad=True)
        cameras = lambda first: torch.cat([c2w[:, :3], c2w[:, 3:] + shift[:, None]], 1).expand(n - first, 3, 4)
        chunks, rgb = 0, torch.empty(n, 3)
        for first, out in r.render_pixels(cameras, u, v, intrinsics):
            rgb[first:first + out.shape[0]] = out.detach()
            (out - target[first:first + out.shape[0]]).square().sum().backward()
            chunks += 1
        return chunks, rgb, shift.grad

    one, rgb_one, grad_one = run(1 << 22)
    many, rgb_many, grad_many = run(4096)
    assert one == 1 and many >= 5, (one, many)
    assert float(rgb_one.min()) < 0.5 < float(rgb_one.max())  # the pixels see the blobs
    torch.testing.assert_close(rgb_many, rgb_one, rtol=0, atol=1e-6)
    assert float(grad_one.abs().max()) > 1e-3
    # the same per-ray terms summed in another order (float32: measured 1.4e-6 apart)
    torch.testing.assert_close(grad_many, grad_one, rtol=1e-4, atol=1e-4 * float(grad_one.abs().max()))
    # the tensor form: pixels from ``first`` on read ``c2w[first:]``
    rays = c2w.expand(n, 3, 4)
    assert torch.equal(torch.cat([o for _, o in r.render_pixels(rays, u, v, intrinsics)]), rgb_many)
