"""The one launcher of every Warp op: grid encodings, marching, compositing, occupancy, ray tracing.

* :func:`launch` is the only place that calls ``wp.launch``. On CUDA it picks the stream: torch's
  current stream when the inputs are torch tensors (so a launch is ordered with the torch work
  that produced its inputs and consumes its outputs, with no device-wide sync), Warp's stream
  when the inputs are Warp arrays Warp itself uploaded (the mesh renderer).
* :func:`launch_over_rays` cuts per-ray kernels into fixed CPU chunks on the thread pool.
* :func:`twin_dispatch` marks a public op: under ``warpnerf.ops.use_backend("torch")``
  (:mod:`warpnerf.ops.registry`) the call goes to its same-name pure-torch twin instead.
* :class:`GridLauncher` owns everything the level-major grid encodings (hash grid, CP lines)
  share: forward/backward launches, level groups, the CPU thread split, the per-chunk ``grad_x``
  sums, and the per-level metadata, uploaded once. An encoding supplies only its kernels and
  metadata (see :class:`GridLauncher`).

Thread split and determinism (docs/design.md): chunking never depends on the thread count, so
results are bit-identical whether the chunks run on one thread or several.
"""

from __future__ import annotations

import functools
from typing import Optional, Sequence

import torch

from warpnerf.device import init_warp, num_threads, run_chunks, split_range

# fixed number of CPU ray chunks: rays differ a lot in cost (box misses, empty space), and
# four chunks balance two threads better than two; the launch overhead (~15 us each) is negligible
_CPU_RAY_CHUNKS = 4
# grid backward: fixed number of CPU level groups (not the thread count), so the grad_x summation
# order never changes; each group scatters into disjoint rows of the parameter gradient
_BWD_LEVEL_CHUNKS = 2


# the backend switch: None = the Warp ops run; else {op module name: twin module} filled by
# warpnerf.ops.registry.use_backend("torch") (which imports the twins: they import the ops, so the
# ops cannot import them). One process-wide setting, read on the calling thread at each call.
_TWIN_MODULES: Optional[dict] = None


def twin_dispatch(op):
    """Decorator of a public op: call ``op``, or, while the torch backend is on, the function of the
    same name in its twin module (``warpnerf.ops.X`` -> ``warpnerf.ops.reference.X``), looked up at
    call time. ``op.__twin__`` names the twin (module, function)."""
    twin_module = op.__module__.replace("warpnerf.ops.", "warpnerf.ops.reference.", 1)

    @functools.wraps(op)
    def dispatch(*args, **kwargs):
        twins = _TWIN_MODULES
        if twins is None:
            return op(*args, **kwargs)
        return getattr(twins[twin_module], op.__name__)(*args, **kwargs)

    dispatch.__twin__ = (twin_module, op.__name__)
    return dispatch


def twins_on() -> bool:
    """Whether the ops run their torch twins (:func:`set_twin_modules`)."""
    return _TWIN_MODULES is not None


def set_twin_modules(modules: Optional[dict]) -> Optional[dict]:
    """Route every :func:`twin_dispatch` op to ``modules`` ({twin module name: module}), or back to
    Warp with ``None``; returns the previous setting. Use :func:`warpnerf.ops.use_backend`."""
    global _TWIN_MODULES
    previous, _TWIN_MODULES = _TWIN_MODULES, modules
    return previous


def launch(kernel, dim, inputs: list, device, outputs: list | None = None) -> None:
    """Launch ``kernel`` over ``dim`` on ``device``, on the stream that owns the inputs.

    ``device`` is a ``torch.device`` when the arrays are views of torch tensors: on CUDA the launch
    goes on torch's *current* stream. A Warp device string (``"cpu"``, ``"cuda:0"``) means the
    arrays were made by Warp: the launch goes on Warp's current stream for that device.
    """
    wp = init_warp()
    outputs = outputs or []
    if isinstance(device, torch.device):
        if device.type == "cuda":
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, stream=wp.stream_from_torch(device))
        else:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device="cpu")
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=str(device))


_LOADED: set = set()  # (module id, device) pairs load_here has loaded


def load_here(kernel, device: str = "cpu") -> None:
    """Compile or load ``kernel``'s module on the calling thread, once per module and device.

    Call it before handing a kernel to worker threads: Warp's first compile on a thread pays a
    per-thread start-up (~2 s on 2 cores, measured), and two pool threads meeting a cold module both
    compile it (raymarch: 6.8 s each in the first training step, 1 s on one thread).
    """
    key = (id(kernel.module), str(device))
    if key not in _LOADED:
        init_warp().load_module(kernel.module, device=str(device))
        _LOADED.add(key)


def launch_over_rays(kernel, num_rays: int, inputs: list, device: torch.device) -> None:
    """Launch a per-ray kernel whose first parameter is ``first_ray`` over ``num_rays`` rays.

    The kernel must write only per-ray (or per-sample-of-ray) outputs: on CPU the rays are cut
    into ``_CPU_RAY_CHUNKS`` fixed chunks run on the thread pool; on CUDA it is one launch on
    torch's current stream.
    """
    if device.type == "cuda":
        launch(kernel, num_rays, [0, *inputs], device)
        return
    load_here(kernel)
    run_chunks([lambda lo=lo, hi=hi: launch(kernel, hi - lo, [lo, *inputs], device)
                for lo, hi in split_range(num_rays, _CPU_RAY_CHUNKS) if hi > lo])


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


def level_weight_values(op: str, level_weights, n_levels: int) -> tuple[float, ...]:
    """G²fR level weights for a grid op as host floats: all ones for None; a
    :class:`~warpnerf.model.g2fr.LevelWeights` or a sequence of floats is read as is (no device
    access); an (L,) tensor is read once (a device sync on CUDA: pass host weights in hot loops).
    ValueError unless there are L values in [0, 1] (NaN rejected)."""
    if level_weights is None:
        return (1.0,) * n_levels
    if isinstance(level_weights, torch.Tensor):
        if tuple(level_weights.shape) != (n_levels,):
            raise ValueError(f"{op}: level_weights must be a tensor of shape ({n_levels},)")
        values = tuple(level_weights.detach().cpu().tolist())
    else:
        try:
            values = tuple(float(w) for w in level_weights)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{op}: level_weights must be {n_levels} floats, LevelWeights or a tensor") from e
        if len(values) != n_levels:
            raise ValueError(f"{op}: level_weights must have shape ({n_levels},), got {len(values)} values")
    if not all(0.0 <= w <= 1.0 for w in values):  # also rejects NaN
        raise ValueError(f"{op}: level weights must lie in [0, 1]")
    return values


class GridLauncher:
    """Warp work of a level-major grid encoding; one instance per (class, spec, device, dtype).

    An encoding subclasses it and supplies only :meth:`make_kernels` and :meth:`metadata`; the
    kernels follow one argument layout::

        fwd(x, params, levels, *meta, weights, start, stop, chunk, out)
        bwd(x, params, grad_out, levels, *meta, weights, want_params, want_x, start, stop, chunk,
            grad_params, grad_x)

    launched over dim = (len(levels), ceil((stop - start) / chunk)): thread (j, c) handles level
    ``levels[j]`` for the points ``start + c * chunk`` up to ``chunk`` of them (below ``stop``).
    CUDA launches use chunk 1, a thread per (level, point). CPU launches use one chunk, a thread
    per level looping over the points in order: the level's rows stay in cache while it is read,
    no per-point thread index is decomposed (1.3-1.6x faster), and every parameter row still
    receives its gradient terms in point order, as before.

    ``levels`` are the level ids of the launch, ``meta`` the encoding's per-level int32 arrays
    followed by its scalars, ``weights`` the (L,) level weights, ``out`` (N, L) vectors of F,
    ``grad_x`` one (N, D) buffer per backward level group.

    CPU split: the forward (a gather) by points over the threads; the backward (a scatter) by
    levels into ``_BWD_LEVEL_CHUNKS`` fixed groups, active levels dealt alternately (coarse,
    cache-friendly levels and fine ones balance out), each group with its own ``grad_x`` buffer,
    summed in group order. Levels own disjoint parameter rows, so the groups never write the same
    memory. On CUDA each pass is one launch on torch's current stream.
    """

    _cache: dict = {}
    op = "grid_encode"

    @classmethod
    def get(cls, spec, device: torch.device, dtype: torch.dtype) -> "GridLauncher":
        key = (cls, spec, str(device), dtype)
        if key not in GridLauncher._cache:
            GridLauncher._cache[key] = cls(spec, device, dtype)
        return GridLauncher._cache[key]

    # --- what an encoding supplies ------------------------------------------------------------

    @staticmethod
    def make_kernels(spec, wp_dtype):
        """``(fwd, bwd, vec)``: the kernels for this spec and dtype, and the feature vector type."""
        raise NotImplementedError

    @staticmethod
    def metadata(spec) -> tuple[list[Sequence[int]], list]:
        """``(per-level int arrays, scalars)`` passed after ``levels``, e.g. resolutions and offsets."""
        raise NotImplementedError

    # --- shared machinery ---------------------------------------------------------------------

    def __init__(self, spec, device: torch.device, dtype: torch.dtype):
        wp = init_warp()
        self.wp, self.spec, self.torch_device, self.dtype = wp, spec, torch.device(device), dtype
        self.on_cpu = self.torch_device.type == "cpu"
        self.wp_device = "cpu" if self.on_cpu else f"cuda:{self.torch_device.index or 0}"
        self.wp_dtype = wp.float64 if dtype == torch.float64 else wp.float32
        self.fwd, self.bwd, self.vec = self.make_kernels(spec, self.wp_dtype)
        arrays, scalars = self.metadata(spec)
        # uploaded once, through Warp's stream: _uploaded() waits for them before any launch
        self.meta = [wp.array(list(a), dtype=wp.int32, device=self.wp_device) for a in arrays] + list(scalars)
        self._levels: dict = {}
        self._weights: dict = {}
        for kernel in (self.fwd, self.bwd):
            load_here(kernel, self.wp_device)
        self._uploaded()

    def _uploaded(self) -> None:
        # Warp uploads on its own stream, launches run on torch's: finish the (one-time) uploads first
        if not self.on_cpu:
            self.wp.synchronize_device(self.wp_device)

    def levels(self, ids: tuple[int, ...]):
        """int32 array of level ids, built once per distinct tuple (on the calling thread)."""
        if ids not in self._levels:
            self._levels[ids] = self.wp.array(list(ids), dtype=self.wp.int32, device=self.wp_device)
            self._uploaded()
        return self._levels[ids]

    def weights(self, values: tuple[float, ...]) -> torch.Tensor:
        """(L,) weights on the device. On CUDA: copied from pinned memory on torch's current stream
        (ordered with the launch, no host sync) and kept for reuse (backward, repeated steps)."""
        if self.on_cpu:
            return torch.tensor(values, dtype=self.dtype)
        if values not in self._weights:
            if len(self._weights) >= 8:  # G²fR ramps change weights every step: keep only recent ones
                self._weights.pop(next(iter(self._weights)))
            host = torch.tensor(values, dtype=self.dtype).pin_memory()
            self._weights[values] = host.to(self.torch_device, non_blocking=True)
        return self._weights[values]

    def _view(self, t: torch.Tensor, dtype):
        return self.wp.from_torch(t, dtype=dtype, requires_grad=False)

    def forward(self, x: torch.Tensor, params: torch.Tensor, values: tuple[float, ...]) -> torch.Tensor:
        """(N, D) points, detached parameters, host weights -> (N, L * F) features."""
        n = x.shape[0]
        n_levels, n_features = len(values), self.vec._length_
        out = torch.zeros(n, n_levels, n_features, dtype=x.dtype, device=x.device)
        active = tuple(m for m, w in enumerate(values) if w > 0.0)
        if n == 0 or not active:
            return out.view(n, n_levels * n_features)
        head = [self._view(x, self.wp_dtype), self._view(params, self.vec), self.levels(active), *self.meta,
                self._view(self.weights(values), self.wp_dtype)]
        out_wp = self._view(out, self.vec)
        # a gather: every output written once, so splitting by points is thread-count independent
        chunks = split_range(n, num_threads()) if self.on_cpu else [(0, n)]
        run_chunks([lambda lo=lo, hi=hi: launch(self.fwd, self._dim(len(active), hi - lo),
                                                [*head, *self._span(lo, hi), out_wp], x.device)
                    for lo, hi in chunks])
        return out.view(n, n_levels * n_features)

    def _dim(self, n_levels: int, n_points: int) -> tuple[int, int]:
        # CUDA: a thread per (level, point); CPU: a thread per level looping over its points
        return (n_levels, 1 if self.on_cpu else n_points)

    def _span(self, lo: int, hi: int) -> tuple[int, int, int]:
        """(start, stop, chunk) kernel arguments for points lo..hi-1 (see :meth:`_dim`)."""
        return lo, hi, (1 if not self.on_cpu else max(hi - lo, 1))

    def backward(self, x, params, values, grad_out, want_x: bool, want_params: bool):
        """-> (grad_x (N, D) or None, grad_params like ``params`` or None)."""
        n, dim = x.shape
        active = [m for m, w in enumerate(values) if w > 0.0]
        grad_params = torch.zeros_like(params) if want_params else None
        n_groups = _BWD_LEVEL_CHUNKS if self.on_cpu else 1
        groups = [g for g in (tuple(active[k::n_groups]) for k in range(n_groups)) if g]
        grad_x_parts = torch.zeros(max(len(groups), 1), n, dim, dtype=x.dtype, device=x.device) if want_x else None
        if n == 0 or not groups:
            return (grad_x_parts.sum(0) if want_x else None), grad_params
        go = grad_out.contiguous().view(n, len(values), self.vec._length_)
        head = [self._view(x, self.wp_dtype), self._view(params, self.vec), self._view(go, self.vec)]
        tail = [self._view(self.weights(values), self.wp_dtype), int(want_params), int(want_x)]
        # kernels need valid arrays even for outputs they skip
        gp = self._view(grad_params if want_params else params.new_zeros(1, *params.shape[1:]), self.vec)
        gx_parts = grad_x_parts if want_x else x.new_zeros(len(groups), 1, dim)
        level_arrays = [self.levels(g) for g in groups]  # built here, not inside the worker threads

        def run(k: int):
            launch(self.bwd, self._dim(len(groups[k]), n),
                   [*head, level_arrays[k], *self.meta, *tail, *self._span(0, n), gp,
                    self._view(gx_parts[k], self.wp_dtype)], x.device)

        run_chunks([lambda k=k: run(k) for k in range(len(groups))])
        grad_x = None
        if want_x:  # fixed summation order: group 0, then 1, ...
            grad_x = grad_x_parts[0]
            for k in range(1, len(groups)):
                grad_x = grad_x + grad_x_parts[k]
        return grad_x, grad_params


class GridEncodeFunction(torch.autograd.Function):
    """Autograd glue of the grid encodings: ``apply(x, params, values, launcher, known)`` with host
    level weights ``values`` (a tuple of floats, not differentiated). ``known``: ``None``, or this
    forward's output already computed (without autograd) for the same inputs, returned instead of
    launching the forward again; the backward is the same either way."""

    @staticmethod
    def forward(ctx, x, params, values, launcher, known=None):
        out = launcher.forward(x, params.detach(), values) if known is None else known.detach()
        ctx.launcher, ctx.values = launcher, values
        ctx.save_for_backward(x, params)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, params = ctx.saved_tensors
        want_x, want_params = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (want_x or want_params):
            return None, None, None, None, None
        grad_x, grad_params = ctx.launcher.backward(x.detach(), params.detach(), ctx.values, grad_out, want_x,
                                                    want_params)
        return grad_x, grad_params, None, None, None


def check_known_output(op: str, known: Optional[torch.Tensor], x: torch.Tensor, out_dim: int) -> None:
    """A grid op's ``known_output`` must be (N, out_dim) of ``x``'s dtype and device."""
    if known is None:
        return
    if not isinstance(known, torch.Tensor):
        raise TypeError(f"{op}: known_output must be a torch tensor or None, got {type(known).__name__}")
    if tuple(known.shape) != (x.shape[0], out_dim) or known.dtype != x.dtype or known.device != x.device:
        raise ValueError(
            f"{op}: known_output must be ({x.shape[0]}, {out_dim}) {x.dtype} on {x.device}, got "
            f"{tuple(known.shape)} {known.dtype} on {known.device}"
        )


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
