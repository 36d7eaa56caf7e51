"""Rays -> packed samples -> field -> composited pixels.

Data flow of one batch (DESIGN §2):

    c2w, pixels --pixel_rays--> o, d           torch, differentiable w.r.t. c2w (pose task)
    o, d --ray_space.apply--> o, d              torch: the scene's ray space (DESIGN §6)
    o, d --occupancy.sample--> packed (ray, t0, t1)   Warp march through the grid, no gradient
    x = to_field(o[ray] + t_mid d[ray])         torch, differentiable w.r.t. o and d (contraction
                                                for unbounded scenes, else the identity)
    field(x, d, level weights) -> sigma, rgb    Warp hash grid + torch MLPs
    composite_rays -> rgb, opacity, depth       Warp, hand-written backward

Rendering an image (no autograd) instead marches every ray a few samples at a time
(``OccupancyGrid.march_window``), composites in torch and drops rays once they are opaque
(``Renderer.render_rays_in_rounds``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from warpnerf.geometry.rayspace import RaySpace
from warpnerf.model.losses import distortion_loss, packed_weights
from warpnerf.model.occupancy import OccupancyGrid
from warpnerf.ops.composite import TRANSMITTANCE_EPS, active_sample_counts, composite_rays
from warpnerf.ops.raymarch import MarchState, PackedSamples, prefix_rows


def gather_rows(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t[idx]`` for a 1-D index, with a deterministic backward.

    The backward of ``t[idx]`` is ``index_put_(accumulate=True)``, which on CPU adds the rows of
    repeated indices from several threads in no fixed order: the gradient of a ray (or camera)
    with many samples changed in its last bits from run to run. ``index_select``'s backward
    (``index_add_``) sums them in index order, so training is bit-reproducible (and resumable).
    """
    return t.index_select(0, idx)


def pixel_rays(c2w: torch.Tensor, u: torch.Tensor, v: torch.Tensor, focal: float, cx: float, cy: float):
    """World rays through pixel positions.

    Args:
        c2w: (B, 3, 4) camera-to-world per ray (OpenGL: x right, y up, looking down -z).
            Differentiable.
        u, v: (B,) pixel coordinates (column, row); the centre of pixel (i, j) is (i + 0.5, j + 0.5).
        focal, cx, cy: intrinsics in pixels.

    Returns:
        origins (B, 3), unit directions (B, 3).
    """
    dirs = torch.stack([(u - cx) / focal, -(v - cy) / focal, -torch.ones_like(u)], dim=-1)
    d = (c2w[:, :, :3] @ dirs[:, :, None])[:, :, 0]
    return c2w[:, :, 3], torch.nn.functional.normalize(d, dim=-1)


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # (R, 3)
    opacity: torch.Tensor  # (R,)
    depth: torch.Tensor  # (R,) expected distance along the (unit) ray, divided by opacity
    n_samples: int  # packed samples in this batch
    # rays [0, n_rays) were rendered; with a sample budget the rest got no samples (see render_rays)
    n_rays: int = -1
    # samples evaluated with autograd: training drops those behind each ray's opaque point
    # (Renderer.compact_training); n_samples counts every marched sample
    n_active: int = -1
    # (R,) mip-NeRF 360's distortion loss per ray, when render_rays was asked for it
    distortion: Optional[torch.Tensor] = None


class Renderer:
    """Volume renderer over an occupancy grid.

    ``render_image`` (evaluation, videos, the viewer) marches rays in rounds and drops each once
    its transmittance < ``stop_transmittance``: samples behind it are neither marched nor
    evaluated (:meth:`render_rays_in_rounds`).

    Color is evaluated only where it can matter: after the density pass, a no-grad composite
    finds each sample's weight, and samples with weight <= ``color_weight_eps`` (empty space in
    front of a surface, or hidden behind it) get color 0 without running the color MLP. Their
    contribution to a pixel is below ``color_weight_eps`` each; density gradients are unchanged.

    Args:
        field: module with ``geometry(x, level_weights) -> (sigma, features)`` and
            ``color(features, dirs) -> rgb``.
        occupancy: the grid the rays are marched through (:meth:`OccupancyGrid.sample`,
            :meth:`OccupancyGrid.march_window`): it skips the empty space it knows of.
        ray_space: the scene's :class:`~warpnerf.geometry.rayspace.RaySpace`: world rays are mapped
            by ``ray_space.apply`` and marched from its ``near`` to its ``far`` (DESIGN §6); the
            field sees positions in that space, while the color MLP still gets the world directions.
        step: marching step (units of the ray space).
        background: 3 floats composited behind every ray.
    """

    def __init__(self, field, occupancy: OccupancyGrid, ray_space: RaySpace, step: float,
                 background=(1.0, 1.0, 1.0), max_samples_per_ray: int = 1024, color_weight_eps: float = 1e-4,
                 sample_budget: int = 1 << 18, stop_transmittance: float = 1e-4):
        self.field = field
        self.occupancy = occupancy
        self.ray_space = ray_space
        self.near, self.far, self.step = float(ray_space.near), float(ray_space.far), float(step)
        self.background = tuple(float(b) for b in background)
        self.max_samples_per_ray = int(max_samples_per_ray)
        self.color_weight_eps = float(color_weight_eps)
        # packed samples per render_rays call at most (memory bound); one ray must always fit
        self.sample_budget = max(int(sample_budget), self.max_samples_per_ray)
        # render_image marches a ray until its transmittance < this (render_rays_in_rounds; 0 = every sample)
        self.stop_transmittance = float(stop_transmittance)
        # render_rays_in_rounds: samples per round (~; smaller rounds keep the MLP activations in
        # reused heap memory: 2^17 rendered lego 0.87 s/view where 2^18 took 1.3) and per ray per round
        self.round_samples = 1 << 17
        self.max_window = 16
        # render_rays with autograd (training) encodes every sample and evaluates its density without
        # autograd, then differentiates only those before each ray turned opaque (_active_prefixes);
        # the trainer passes ``compact`` per step (on only while it pays)
        self.compact_training = True

    def render_rays(self, rays_o: torch.Tensor, rays_d: torch.Tensor, level_weights: Optional[torch.Tensor] = None,
                    jitter: Optional[torch.Tensor] = None, background: Optional[torch.Tensor] = None,
                    compact: Optional[bool] = None, distortion: bool = False) -> RenderOutput:
        """Render (R, 3) rays (unit directions). Differentiable w.r.t. the field and the rays.

        At most ``sample_budget`` samples are taken: if the rays would need more, only the first
        ``out.n_rays`` rays are rendered (the others come back as background with no samples), so
        memory stays bounded however empty or full the occupancy grid is. ``background``: optional
        (R, 3) per-ray colours replacing the renderer's constant one (random backgrounds). ``compact``:
        with autograd, differentiate only the samples before each ray turned opaque
        (:meth:`_active_prefixes`; same pixels and gradients); ``None``: ``compact_training``.
        ``distortion``: also return each ray's distortion loss (:func:`warpnerf.model.losses.distortion_loss`)."""
        view_dirs = rays_d
        o, d = self.ray_space.apply(rays_o, rays_d)
        with torch.no_grad():
            packed, n_marched = self.occupancy.sample(
                o.detach().contiguous(), d.detach().contiguous(), self.near, self.far, self.step,
                self.max_samples_per_ray, jitter, max_total_samples=self.sample_budget,
                contract=self.ray_space.is_contracted)
        n_samples = int(packed.ray_indices.shape[0])
        known = None
        if (self.compact_training if compact is None else compact) and torch.is_grad_enabled() and n_samples:
            packed, known = self._active_prefixes(o, d, packed, level_weights)
        ray, x = self._points(o, d, packed)
        if known is None:
            sigma, geo = self.field.geometry(x, level_weights)
        else:  # the grid encoding of these samples is known: only its backward is left to build
            sigma, geo = self.field.geometry_of(self.field.encode(x, level_weights, known_output=known))
        rgb = self._sample_colors(sigma, geo, view_dirs, ray, packed)
        bg = self.background if background is None else background
        color, opacity, depth = composite_rays(sigma, rgb, packed.t_starts, packed.t_ends, packed.ray_offsets,
                                               packed.ray_counts, bg)
        dist = None
        if distortion:  # the weights again, with autograd (the composite's are not returned differentiably)
            dist = distortion_loss(packed_weights(sigma, packed), packed, rays_o.shape[0])
        return RenderOutput(color, opacity, depth / opacity.clamp_min(1e-6), n_samples, n_marched,
                            int(ray.shape[0]), dist)

    def render_pixels(self, c2w, u: torch.Tensor, v: torch.Tensor, intrinsics, level_weights=None):
        """Render pixel positions (u, v) in as many ``render_rays`` calls as the sample budget needs
        (a call returns the rays past the budget as background: every ray here is rendered).

        c2w: (B, 3, 4) camera per pixel, or a callable ``first -> (B - first, 3, 4)`` for the pixels
        from ``first`` on, for a pose graph that a caller's ``backward`` frees between chunks.
        intrinsics: (focal, cx, cy). Yields ``(first, rgb)``: the (n, 3) colours of pixels
        ``first .. first + n``; a caller may backpropagate each chunk's loss before the next.
        """
        cameras = c2w if callable(c2w) else (lambda first: c2w[first:])
        first = 0
        while first < u.shape[0]:
            o, d = pixel_rays(cameras(first), u[first:], v[first:], *intrinsics)
            out = self.render_rays(o.contiguous(), d.contiguous(), level_weights)
            n = max(out.n_rays, 1)  # the budget holds at least one ray's samples
            yield first, out.rgb[:n]
            first += n

    def _points(self, o: torch.Tensor, d: torch.Tensor, packed: PackedSamples):
        """Ray index (S,) int64 and field-space position (S, 3) of every packed sample's midpoint."""
        ray = packed.ray_indices.long()
        t_mid = (packed.t_starts + packed.t_ends) * 0.5
        return ray, self.ray_space.to_field(gather_rows(o, ray) + t_mid[:, None] * gather_rows(d, ray))

    def _active_prefixes(self, o, d, packed: PackedSamples, level_weights):
        """``packed`` cut to the samples compositing can weigh (instant-ngp's compaction), and
        their grid encoding (``None`` for a field without ``encode``/``density_of``/``geometry_of``).

        A first pass without autograd encodes every sample and evaluates its density, and counts,
        per ray, the samples before its transmittance fell below the compositing threshold
        (:func:`~warpnerf.ops.composite.active_sample_counts`); the samples behind get weight 0
        and gradient 0 in :func:`~warpnerf.ops.composite.composite_rays`, so the differentiable
        pass skips them and reuses the kept samples' encoding: the grid's forward runs once, its
        backward and the MLPs only on the kept samples (chair few-shot at step 500: 35 % of them).
        One sample past the count stays, in case the differentiable pass's density differs from
        this one in the last bit and the ray stops one sample later.
        """
        # the encoding is reused only by a field that can continue from it (render_rays: geometry_of)
        reuse = all(hasattr(self.field, m) for m in ("encode", "density_of", "geometry_of"))
        with torch.no_grad():
            _, x = self._points(o.detach(), d.detach(), packed)
            enc = self.field.encode(x, level_weights) if reuse else None
            sigma = (self.field.density_of(enc) if reuse else self.field.geometry(x, level_weights)[0]).float()
            active = active_sample_counts(sigma, packed.t_starts, packed.t_ends, packed.ray_offsets,
                                          packed.ray_counts)
            counts = torch.minimum(active + 1, packed.ray_counts)
            if bool((counts == packed.ray_counts).all()):
                return packed, enc
            ray, kept = prefix_rows(packed.ray_offsets, counts)
            offsets = torch.cumsum(counts, 0, dtype=torch.int32) - counts
            cut = PackedSamples(ray.int(), packed.t_starts[kept], packed.t_ends[kept], offsets, counts)
            return cut, None if enc is None else gather_rows(enc, kept)

    @torch.no_grad()
    def render_rays_in_rounds(self, rays_o: torch.Tensor, rays_d: torch.Tensor,
                              level_weights: Optional[torch.Tensor] = None) -> RenderOutput:
        """:meth:`render_rays` without autograd, marching each ray only as far as it is visible
        (instant-ngp's inference loop: early ray termination with compaction).

        Round after round, every ray still alive takes its next ``window`` samples
        (:meth:`~warpnerf.model.occupancy.OccupancyGrid.march_window`; ``window`` grows as rays die so a
        round holds about ``round_samples`` samples), the field is evaluated there, the samples
        are composited onto the ray's running colour, and rays whose transmittance fell below
        ``stop_transmittance`` (or that have no samples left) leave. Samples behind that point
        are never marched nor evaluated; each would have weighed less than ``stop_transmittance``.
        Same samples and compositing as :meth:`render_rays` (up to float summation order).
        """
        view_dirs = rays_d
        o, d = self.ray_space.apply(rays_o, rays_d)
        o, d = o.contiguous(), d.contiguous()
        num, dev = o.shape[0], o.device
        rgb = torch.zeros(num, 3, device=dev)
        opacity = torch.zeros(num, device=dev)
        depth = torch.zeros(num, device=dev)
        alive = torch.arange(num, device=dev)
        trans = torch.ones(num, device=dev)
        state = MarchState.start(num, self.near, dev)
        n_samples = 0
        while alive.numel():
            n_alive = alive.numel()
            window = max(1, min(self.round_samples // n_alive, self.max_window))
            t_starts, t_ends, counts = self.occupancy.march_window(o, d, state, window, self.near, self.far, self.step,
                                                                   self.max_samples_per_ray,
                                                                   contract=self.ray_space.is_contracted)
            rows, cols = torch.nonzero(torch.arange(window, device=dev) < counts[:, None], as_tuple=True)
            if rows.numel():
                n_samples += rows.numel()
                t0, t1 = t_starts[rows, cols], t_ends[rows, cols]
                t_mid = (t0 + t1) * 0.5
                x = self.ray_space.to_field(o.index_select(0, rows) + t_mid[:, None] * d.index_select(0, rows))
                sigma, geo = self.field.geometry(x, level_weights)
                # the composite kernel's arithmetic, row-wise: keep_i = exp(-sigma_i dt_i),
                # T_i = T * prod_{j<i} keep_j, w_i = T_i (1 - keep_i), 0 once T_i < eps
                keep = torch.ones(n_alive, window, device=dev)
                keep[rows, cols] = torch.exp(-sigma.float() * (t1 - t0))
                t_before = trans[:, None] * torch.cumprod(torch.cat([keep.new_ones(n_alive, 1), keep[:, :-1]], 1), 1)
                w = torch.where(t_before < TRANSMITTANCE_EPS, 0.0, t_before * (1.0 - keep))[rows, cols]
                trans = torch.where(t_before[:, -1] < TRANSMITTANCE_EPS, 0.0, t_before[:, -1] * keep[:, -1])
                ray = alive.index_select(0, rows)
                opacity.index_add_(0, ray, w)
                depth.index_add_(0, ray, w * t_mid)
                lit = torch.nonzero(w > self.color_weight_eps).squeeze(1)
                colors = self.field.color(geo.index_select(0, lit), view_dirs.index_select(0, ray.index_select(0, lit)))
                rgb.index_add_(0, ray.index_select(0, lit), w.index_select(0, lit)[:, None] * colors.float())
            more = torch.nonzero(~state.finished & (trans >= self.stop_transmittance)).squeeze(1)
            alive, trans, o, d = (v.index_select(0, more) for v in (alive, trans, o, d))
            state = state.select(more)
        bg = torch.tensor(self.background, device=dev, dtype=rgb.dtype)
        rgb += (1.0 - opacity)[:, None] * bg
        return RenderOutput(rgb, opacity, depth / opacity.clamp_min(1e-6), n_samples, num)

    def step_at(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) marching step (along the marched ray) at (N, 3) points of the field's space: ``step``;
        for unbounded scenes beyond the unit ball the longest step the marcher takes there (on a
        ray leaving the scene radially), ``step * r^2`` with r the uncontracted radius. The
        occupancy grid thresholds density times this step."""
        if not self.ray_space.is_contracted:
            return torch.full(x.shape[:1], self.step, dtype=x.dtype, device=x.device)
        r = x.norm(dim=-1).clamp(1.0, 2.0 - 1e-3)  # |uncontract(x)| = 1 / (2 - |x|) beyond the ball
        return self.step / (2.0 - r) ** 2

    def _sample_colors(self, sigma, geo, view_dirs, ray, packed) -> torch.Tensor:
        if self.color_weight_eps <= 0 or sigma.shape[0] == 0:
            return self.field.color(geo, gather_rows(view_dirs, ray))
        with torch.no_grad():
            dummy = torch.zeros(sigma.shape[0], 3, device=sigma.device)
            weights = composite_rays(sigma.detach(), dummy, packed.t_starts, packed.t_ends, packed.ray_offsets,
                                     packed.ray_counts, self.background, return_weights=True)[3]
            keep = torch.nonzero(weights > self.color_weight_eps).squeeze(1)
        rgb = torch.zeros(sigma.shape[0], 3, device=sigma.device, dtype=geo.dtype)
        colors = self.field.color(gather_rows(geo, keep), gather_rows(view_dirs, ray[keep]))
        return rgb.index_put((keep,), colors)

    @torch.no_grad()
    def render_image(self, c2w: torch.Tensor, height: int, width: int, focal: float, cx: float, cy: float,
                     level_weights: Optional[torch.Tensor] = None, chunk: Optional[int] = None) -> dict:
        """Render a full (height, width) image from one (3, 4) pose, in chunks of ``chunk`` rays,
        without autograd: :meth:`render_rays_in_rounds` (default chunk 2^18 rays: its rounds bound
        the samples), or with ``stop_transmittance`` = 0 :meth:`render_rays`, every sample
        (default chunk 2^16).

        Returns ``rgb`` (H, W, 3), ``depth`` (H, W), ``opacity`` (H, W) and ``samples``, the
        number of samples the field was evaluated at.
        """
        rounds = self.stop_transmittance > 0
        chunk = int(chunk or (1 << 18 if rounds else 1 << 16))
        dev = c2w.device
        v, u = torch.meshgrid(torch.arange(height, device=dev, dtype=torch.float32) + 0.5,
                              torch.arange(width, device=dev, dtype=torch.float32) + 0.5, indexing="ij")
        u, v = u.reshape(-1), v.reshape(-1)
        rgbs, depths, opac = [], [], []
        lo = samples = 0
        while lo < u.shape[0]:
            uu, vv = u[lo:lo + chunk], v[lo:lo + chunk]
            o, d = pixel_rays(c2w[None].expand(uu.shape[0], 3, 4), uu, vv, focal, cx, cy)
            if rounds:
                out = self.render_rays_in_rounds(o.contiguous(), d.contiguous(), level_weights)
            else:
                out = self.render_rays(o.contiguous(), d.contiguous(), level_weights)
            # rays past the sample budget were not rendered: the next chunk starts with them
            done = max(out.n_rays, 1)
            samples += out.n_samples
            rgbs.append(out.rgb[:done])
            depths.append(out.depth[:done])
            opac.append(out.opacity[:done])
            lo += done
        return {
            "rgb": torch.cat(rgbs).view(height, width, 3),
            "depth": torch.cat(depths).view(height, width),
            "opacity": torch.cat(opac).view(height, width),
            "samples": samples,
        }


def default_step(aabb, steps_per_diagonal: int = 1024) -> float:
    """Marching step: the box diagonal over ``steps_per_diagonal`` (instant-ngp: 1024)."""
    size = [aabb[i + 3] - aabb[i] for i in range(3)]
    return math.sqrt(sum(s * s for s in size)) / steps_per_diagonal
