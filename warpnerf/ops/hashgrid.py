"""``hashgrid_encode``: the Warp multi-resolution hash-grid encoding as a torch op.

Forward gathers D-linear interpolated features per level (level-major launches); backward
scatters into the table gradient and, when asked, returns the gradient with respect to the
input points. G²fR level weights (paper eq. 15) are applied inside the kernels: a level with
weight 0 is never launched, so it reads and writes no table memory and its output is 0.

CPU threading (see :mod:`warpnerf.device`): the forward is split by points; the backward by
*levels* (active levels dealt alternately to two fixed chunks), so each chunk scatters into a
disjoint table slice and its own dx buffer. The chunking does not depend on the thread count,
which makes 1- and 2-thread results bit-identical. On CUDA each pass is a single launch.

Positions outside [0, 1]^D are clamped to the box (their gradient is 0, like ``torch.clamp``);
non-finite positions are an error.
"""

from __future__ import annotations

import torch

from ..device import init_warp, run_chunks, num_threads, split_range
from .hashgrid_spec import HashGridSpec
from .launch import CachedLauncher, GridEncodeFunction, check_grid_inputs, check_level_weights

__all__ = ["hashgrid_encode", "HashGridSpec"]

# backward level chunks: fixed (not the thread count) so the dx summation order never changes
_BWD_LEVEL_CHUNKS = 2


def hashgrid_encode(
    x: torch.Tensor, table: torch.Tensor, spec: HashGridSpec, level_weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Encode points with a multi-resolution hash grid.

    Args:
        x: (N, D) float32 (or float64) points, expected in [0, 1]^D; outside values are clamped.
            Differentiable (gradient 0 where clamped).
        table: (spec.n_rows, F) features of all levels, same dtype and device as ``x``. Differentiable.
        spec: the grid geometry (:class:`HashGridSpec`).
        level_weights: (L,) G²fR weights w_m in [0, 1]; ``None`` means all ones. Not differentiable.

    Returns:
        (N, L*F) features; columns [m*F, (m+1)*F) belong to level m and are scaled by w_m.

    Example:
        >>> spec = HashGridSpec.create(dim=3, n_levels=4, log2_table_size=12, base_resolution=4, max_resolution=32)
        >>> table = torch.randn(spec.n_rows, spec.n_features) * 1e-2
        >>> hashgrid_encode(torch.rand(5, 3), table, spec).shape
        torch.Size([5, 8])
    """
    weights = _check_inputs(x, table, spec, level_weights)
    return GridEncodeFunction.apply(x, table, weights, _Launcher.get(spec, x.device, x.dtype))


def _check_inputs(x, table, spec, level_weights) -> torch.Tensor:
    check_grid_inputs("hashgrid_encode", x, table, "table", spec, HashGridSpec,
                      lambda s: (s.dim, (s.n_rows, s.n_features)))
    return check_level_weights("hashgrid_encode", level_weights, spec.n_levels, x)


class _Launcher(CachedLauncher):
    """Per (spec, device, dtype) Warp state: kernels and the small per-level metadata arrays."""

    def __init__(self, spec: HashGridSpec, device: torch.device, dtype: torch.dtype):
        wp = init_warp()
        from ..kernels.hashgrid import make_hashgrid_kernels

        self.wp = wp
        self.spec = spec
        self.on_cpu = device.type == "cpu"
        self.wp_dtype = wp.float64 if dtype == torch.float64 else wp.float32
        self.fwd, self.bwd, self.vec = make_hashgrid_kernels(spec.dim, spec.n_features, self.wp_dtype)
        self.device = "cpu" if self.on_cpu else f"cuda:{device.index or 0}"
        as_i32 = lambda v: wp.array(list(v), dtype=wp.int32, device=self.device)  # noqa: E731
        self.resolutions = as_i32(spec.resolutions)
        self.offsets = as_i32(spec.offsets[:-1])
        self.hashed = as_i32(int(h) for h in spec.hashed)
        self.hash_mask = wp.uint32(spec.table_size - 1)
        self._levels: dict = {}
        # compile/load now: two threads hitting a cold module at once would both compile it
        for kernel in (self.fwd, self.bwd):
            wp.load_module(kernel.module, device=self.device)

    def launch_kw(self, device: torch.device) -> dict:
        """CPU launches, or launches on torch's *current* CUDA stream (ordered with torch's work)."""
        return {"device": "cpu"} if self.on_cpu else {"stream": self.wp.stream_from_torch(device)}

    def levels(self, ids: tuple[int, ...]):
        if ids not in self._levels:
            self._levels[ids] = self.wp.array(list(ids), dtype=self.wp.int32, device=self.device)
        return self._levels[ids]

    def forward(self, x: torch.Tensor, table: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        wp, spec = self.wp, self.spec
        n = x.shape[0]
        out = torch.zeros(n, spec.n_levels, spec.n_features, dtype=x.dtype, device=x.device)
        active = tuple(m for m, w in enumerate(weights.tolist()) if w > 0)
        if n == 0 or not active:
            return out.view(n, spec.out_dim)
        args = dict(
            x=wp.from_torch(x, dtype=self.wp_dtype, requires_grad=False),
            table=wp.from_torch(table, dtype=self.vec, requires_grad=False),
            levels=self.levels(active),
            resolutions=self.resolutions,
            offsets=self.offsets,
            hashed=self.hashed,
            hash_mask=self.hash_mask,
            weights=wp.from_torch(weights, dtype=self.wp_dtype, requires_grad=False),
            out=wp.from_torch(out, dtype=self.vec, requires_grad=False),
        )
        chunks = split_range(n, num_threads()) if self.on_cpu else [(0, n)]

        inputs = list(args.values())
        kw = self.launch_kw(x.device)

        def launch(lo: int, hi: int):
            wp.launch(self.fwd, dim=(len(active), hi - lo), inputs=[*inputs[:-1], lo, inputs[-1]], **kw)

        run_chunks([lambda lo=lo, hi=hi: launch(lo, hi) for lo, hi in chunks])
        return out.view(n, spec.out_dim)

    def backward(self, x, table, weights, grad_out, want_x: bool, want_table: bool):
        wp, spec = self.wp, self.spec
        n = x.shape[0]
        active = [m for m, w in enumerate(weights.tolist()) if w > 0]
        grad_table = torch.zeros_like(table) if want_table else None
        n_chunks = _BWD_LEVEL_CHUNKS if self.on_cpu else 1
        # deal levels alternately: coarse (dense, cache-friendly) and fine (hashed) levels balance out
        groups = [tuple(active[k::n_chunks]) for k in range(n_chunks)]
        groups = [g for g in groups if g]
        grad_x_parts = torch.zeros(max(len(groups), 1), n, spec.dim, dtype=x.dtype, device=x.device) if want_x else None
        if n == 0 or not groups:
            return (grad_x_parts.sum(0) if want_x else None), grad_table
        go = grad_out.contiguous().view(n, spec.n_levels, spec.n_features)
        common = [
            wp.from_torch(x, dtype=self.wp_dtype, requires_grad=False),
            wp.from_torch(table, dtype=self.vec, requires_grad=False),
            wp.from_torch(go, dtype=self.vec, requires_grad=False),
        ]
        meta = [self.resolutions, self.offsets, self.hashed, self.hash_mask, wp.from_torch(weights, dtype=self.wp_dtype, requires_grad=False),
                int(want_table), int(want_x)]
        # kernels need valid arrays even for outputs they skip
        gt = wp.from_torch(grad_table if want_table else table.new_zeros(1, spec.n_features), dtype=self.vec)
        gx_parts = grad_x_parts if want_x else x.new_zeros(len(groups), 1, spec.dim)
        kw = self.launch_kw(x.device)

        def launch(k: int):
            wp.launch(self.bwd, dim=(len(groups[k]), n),
                      inputs=[*common[:3], self.levels(groups[k]), *meta, gt, wp.from_torch(gx_parts[k], dtype=self.wp_dtype, requires_grad=False)],
                      **kw)

        run_chunks([lambda k=k: launch(k) for k in range(len(groups))])
        grad_x = None
        if want_x:
            grad_x = grad_x_parts[0]
            for k in range(1, len(groups)):
                grad_x = grad_x + grad_x_parts[k]
        return grad_x, grad_table
