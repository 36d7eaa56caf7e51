"""Launch helpers shared by the per-ray ops (march, composite) and the occupancy grid.

Torch tensors become zero-copy Warp views that never touch autograd, and per-ray kernels are
cut into fixed CPU chunks (see :mod:`warpnerf.device`) so results never depend on the thread count.
"""

from __future__ import annotations

import torch

from ..device import init_warp, run_chunks, split_range

# fixed number of CPU ray chunks: rays differ a lot in cost (box misses, empty space), and
# four chunks balance two threads better than two; the launch overhead (~15 us each) is negligible
_CPU_RAY_CHUNKS = 4


def launch_over_rays(kernel, num_rays: int, inputs: list, device: torch.device) -> None:
    """Launch a per-ray kernel whose first parameter is ``first_ray`` over ``num_rays`` rays.

    The kernel must write only per-ray (or per-sample-of-ray) outputs: on CPU the rays are cut
    into ``_CPU_RAY_CHUNKS`` fixed chunks run on the thread pool; on CUDA it is one launch on
    torch's current stream.
    """
    wp = init_warp()
    if device.type == "cuda":
        wp_device = wp.device_from_torch(device)
        wp.launch(kernel, dim=num_rays, inputs=[0, *inputs], device=wp_device, stream=wp.stream_from_torch(device))
        return

    def launch(lo: int, hi: int):
        wp.launch(kernel, dim=hi - lo, inputs=[lo, *inputs], device="cpu")

    run_chunks([lambda lo=lo, hi=hi: launch(lo, hi) for lo, hi in split_range(num_rays, _CPU_RAY_CHUNKS) if hi > lo])


def check_grid_inputs(op: str, x, params, params_name: str, spec, spec_type: type, shapes) -> None:
    """Validate a grid op's points ``x`` and learnable ``params``: torch tensors, float32/float64 of
    one dtype, one cpu or cuda device, the shapes ``shapes(spec) -> (x_dim, params_shape)`` asks for,
    contiguous, finite x. One-line TypeError/ValueError naming ``op`` before any launch."""
    if not isinstance(x, torch.Tensor) or not isinstance(params, torch.Tensor):
        raise TypeError(f"{op}: x and {params_name} must be torch tensors")
    if not isinstance(spec, spec_type):
        raise TypeError(f"{op}: spec must be a {spec_type.__name__}, got {type(spec).__name__}")
    if x.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{op}: x must be float32 or float64, got {x.dtype}")
    if params.dtype != x.dtype:
        raise TypeError(f"{op}: {params_name} dtype {params.dtype} differs from x dtype {x.dtype}")
    if x.device != params.device:
        raise ValueError(f"{op}: x is on {x.device} but {params_name} is on {params.device}")
    if x.device.type not in ("cpu", "cuda"):
        raise ValueError(f"{op}: only cpu and cuda tensors are supported, got {x.device}")
    x_dim, params_shape = shapes(spec)
    if x.dim() != 2 or x.shape[1] != x_dim:
        raise ValueError(f"{op}: x must have shape (N, {x_dim}), got {tuple(x.shape)}")
    if tuple(params.shape) != tuple(params_shape):
        raise ValueError(f"{op}: {params_name} must have shape {tuple(params_shape)}, got {tuple(params.shape)}")
    if not x.is_contiguous() or not params.is_contiguous():
        raise ValueError(f"{op}: x and {params_name} must be contiguous (call .contiguous())")
    if x.numel() and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{op}: x contains NaN or inf")


def check_level_weights(op: str, level_weights, n_levels: int, x: torch.Tensor) -> torch.Tensor:
    """G²fR level weights for a grid op: all ones when None, else an (L,) tensor in [0, 1]
    (NaN rejected), returned detached, contiguous, on x's device and dtype."""
    if level_weights is None:
        return torch.ones(n_levels, dtype=x.dtype, device=x.device)
    if not isinstance(level_weights, torch.Tensor) or tuple(level_weights.shape) != (n_levels,):
        raise ValueError(f"{op}: level_weights must be a tensor of shape ({n_levels},)")
    w = level_weights.detach().to(device=x.device, dtype=x.dtype).contiguous()
    if not bool(((w >= 0) & (w <= 1)).all()):  # also rejects NaN
        raise ValueError(f"{op}: level weights must lie in [0, 1]")
    return w


class CachedLauncher:
    """Base of the grid ops' launchers: one instance (kernels, metadata arrays) per
    (launcher class, spec, device, dtype), built on first use."""

    _cache: dict = {}

    @classmethod
    def get(cls, spec, device: torch.device, dtype: torch.dtype):
        key = (cls, spec, str(device), dtype)
        if key not in CachedLauncher._cache:
            CachedLauncher._cache[key] = cls(spec, device, dtype)
        return CachedLauncher._cache[key]


class GridEncodeFunction(torch.autograd.Function):
    """Autograd glue shared by the level-major grid encodings (hash grid, CP lines).

    ``launcher`` owns the Warp work: ``forward(x, params, weights)`` and
    ``backward(x, params, weights, grad_out, want_x, want_params) -> (grad_x, grad_params)``.
    """

    @staticmethod
    def forward(ctx, x, params, weights, launcher):
        out = launcher.forward(x, params.detach(), weights)
        ctx.launcher = launcher
        ctx.save_for_backward(x, params, weights)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, params, weights = ctx.saved_tensors
        want_x, want_params = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (want_x or want_params):
            return None, None, None, None
        grad_x, grad_params = ctx.launcher.backward(x.detach(), params.detach(), weights, grad_out, want_x,
                                                    want_params)
        return grad_x, grad_params, None, None


def as_warp(t: torch.Tensor, dtype=None):
    """Zero-copy Warp view of ``t`` (copied first if not contiguous), never linked to autograd.

    ``wp.from_torch`` would otherwise allocate ``t.grad`` for tensors that require grad. Output
    buffers must be contiguous, or the kernel would write into the copy.
    """
    wp = init_warp()
    return wp.from_torch(t.detach().contiguous(), dtype=dtype, requires_grad=False)


def aabb_floats(aabb) -> tuple[list[float], list[float]]:
    """(min corner, max corner) of a 6-float box; ValueError unless min < max on every axis."""
    if isinstance(aabb, torch.Tensor):
        aabb = aabb.detach().cpu().reshape(-1).tolist()
    vals = [float(v) for v in aabb]
    if len(vals) != 6:
        raise ValueError(f"aabb must have 6 values (xmin, ymin, zmin, xmax, ymax, zmax), got {len(vals)}")
    lo, hi = vals[:3], vals[3:]
    if not all(l < h for l, h in zip(lo, hi)):
        raise ValueError(f"aabb must have min < max on every axis, got {tuple(vals)}")
    return lo, hi
