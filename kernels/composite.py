"""Volume compositing along packed samples, forward and hand-written backward.

Warp only; the torch wrapper is ``warpnerf/ops/composite.py`` and the pure-torch twin
``warpnerf/ops/reference/composite.py`` (op name: ``composite_rays``).

Per ray with samples i = 0..n-1 (s_i = sigma_i * delta_i, delta_i = t_end_i - t_start_i):
    T_i = prod_{j<i} exp(-s_j),  alpha_i = 1 - exp(-s_i),  w_i = T_i alpha_i  (0 once T_i < eps)
    C = sum w_i c_i + (1 - O) bg,  O = sum w_i,  D = sum w_i z_i,  z_i = (t_start_i + t_end_i) / 2

Backward. With cotangents gC, gO, gD, gW_i the loss changes by sum_i v_i dw_i where
    v_i = gC . (c_i - bg) + gO + gD z_i + gW_i.
Since dw_i/ds_k = -w_i for k < i and dw_k/ds_k = T_k exp(-s_k) = T_{k+1},
    dL/dsigma_k = delta_k (v_k T_{k+1} - sum_{i>k} v_i w_i),   dL/dc_k = w_k gC.
The suffix sum is the ray total minus the running prefix, so one thread per ray needs two
passes and no per-sample storage. Terminated samples (T_k < eps) get zero gradient: their
weight is the constant 0 and no active weight depends on them.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def ray_background(r: int, bg: wp.array(dtype=wp.vec3), bg_per_ray: int, bg_const: wp.vec3):
    if bg_per_ray != 0:
        return bg[r]
    return bg_const


@wp.kernel
def composite_rays_fwd(
    first_ray: int,
    sigmas: wp.array(dtype=float),
    rgbs: wp.array(dtype=wp.vec3),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    ray_offsets: wp.array(dtype=wp.int32),
    ray_counts: wp.array(dtype=wp.int32),
    bg: wp.array(dtype=wp.vec3),
    bg_per_ray: int,
    bg_const: wp.vec3,
    eps: float,
    out_rgb: wp.array(dtype=wp.vec3),
    out_opacity: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    out_weights: wp.array(dtype=float),
):
    """Composite rays [first_ray, first_ray + dim); ``out_weights`` must be zero-filled (samples
    after termination are not written)."""
    r = first_ray + wp.tid()
    start = ray_offsets[r]
    trans = float(1.0)
    color = wp.vec3(0.0)
    opacity = float(0.0)
    depth = float(0.0)
    for i in range(start, start + ray_counts[r]):
        if trans < eps:
            break
        keep = wp.exp(-sigmas[i] * (t_ends[i] - t_starts[i]))
        w = trans * (1.0 - keep)
        out_weights[i] = w
        color += w * rgbs[i]
        opacity += w
        depth += w * (0.5 * (t_starts[i] + t_ends[i]))
        trans *= keep
    out_rgb[r] = color + (1.0 - opacity) * ray_background(r, bg, bg_per_ray, bg_const)
    out_opacity[r] = opacity
    out_depth[r] = depth


@wp.kernel
def composite_rays_bwd(
    first_ray: int,
    sigmas: wp.array(dtype=float),
    rgbs: wp.array(dtype=wp.vec3),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    ray_offsets: wp.array(dtype=wp.int32),
    ray_counts: wp.array(dtype=wp.int32),
    bg: wp.array(dtype=wp.vec3),
    bg_per_ray: int,
    bg_const: wp.vec3,
    eps: float,
    grad_rgb: wp.array(dtype=wp.vec3),
    grad_opacity: wp.array(dtype=float),
    grad_depth: wp.array(dtype=float),
    grad_weights: wp.array(dtype=float),
    has_grad_weights: int,
    grad_sigmas: wp.array(dtype=float),
    grad_rgbs: wp.array(dtype=wp.vec3),
):
    """Gradients w.r.t. sigmas and rgbs (zero-filled outputs; terminated samples are not written)."""
    r = first_ray + wp.tid()
    start = ray_offsets[r]
    end = start + ray_counts[r]
    g_rgb = grad_rgb[r]
    g_opacity = grad_opacity[r]
    g_depth = grad_depth[r]
    background = ray_background(r, bg, bg_per_ray, bg_const)

    # pass 1: total of v_i w_i over the active samples
    trans = float(1.0)
    total = float(0.0)
    for i in range(start, end):
        if trans < eps:
            break
        keep = wp.exp(-sigmas[i] * (t_ends[i] - t_starts[i]))
        v = wp.dot(g_rgb, rgbs[i] - background) + g_opacity + g_depth * (0.5 * (t_starts[i] + t_ends[i]))
        if has_grad_weights != 0:
            v += grad_weights[i]
        total += v * trans * (1.0 - keep)
        trans *= keep

    # pass 2: the suffix sum_{i>k} v_i w_i is the total minus the prefix up to and including k
    trans = float(1.0)
    prefix = float(0.0)
    for k in range(start, end):
        if trans < eps:
            break
        delta = t_ends[k] - t_starts[k]
        keep = wp.exp(-sigmas[k] * delta)
        w = trans * (1.0 - keep)
        v = wp.dot(g_rgb, rgbs[k] - background) + g_opacity + g_depth * (0.5 * (t_starts[k] + t_ends[k]))
        if has_grad_weights != 0:
            v += grad_weights[k]
        prefix += v * w
        trans *= keep
        grad_sigmas[k] = delta * (v * trans - (total - prefix))
        grad_rgbs[k] = w * g_rgb


@wp.kernel
def composite_active_counts(
    first_ray: int,
    sigmas: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    ray_offsets: wp.array(dtype=wp.int32),
    ray_counts: wp.array(dtype=wp.int32),
    eps: float,
    out_counts: wp.array(dtype=wp.int32),
):
    """Per ray, how many samples ``composite_rays_fwd`` visits: the ones before the transmittance
    fell below ``eps`` (the same float32 products in the same order, so the same count)."""
    r = first_ray + wp.tid()
    start = ray_offsets[r]
    trans = float(1.0)
    n = int(0)
    for i in range(start, start + ray_counts[r]):
        if trans < eps:
            break
        trans *= wp.exp(-sigmas[i] * (t_ends[i] - t_starts[i]))
        n += 1
    out_counts[r] = n
