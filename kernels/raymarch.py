"""Occupancy-grid ray marching with a fixed step along t.

Warp only; the torch wrapper is ``warpnerf/ops/raymarch.py`` and the pure-torch twin
``warpnerf/ops/reference/raymarch.py`` (op name: ``march_rays``).

Per ray, x(t) = o + t d. The marched interval [t0, t1] is [near, far] intersected with the
ray-box interval. Candidate sample k covers
    t_start = t0 + (k + u) * step,   t_end = min(t_start + step, t1),   while t_start < t1,
where u in [0, 1) is the ray's jitter. It is emitted when its midpoint lies in an occupied cell
(which also means inside the box), at most ``max_samples`` per ray.

One kernel serves both passes (count, then fill at the ray's packed offset) so the two passes
run the same loop and cannot disagree.

``march_rays_contracted`` is the unbounded-scene variant (MipNeRF-360 scene contraction,
``warpnerf/contraction.py``): the ray is marched in the normalised world from ``near`` to
``far`` with no box, each step is one ``step`` long *in the contracted space* (to first order),
and the occupancy cell is looked up at the contracted midpoint (the grid covers the contracted
ball, box [-2, 2]^3):

    dt(t)  = step / |J(x) d|,   x = x(t)          (= step inside the unit ball)
    |J d|^2 = (d_r / r^2)^2 + (1 - d_r^2) ((2 - 1/r) / r)^2,   r = |x|, d_r = d . x / r
    t_0    = t0 + u * dt(t0),   t_{k+1} = t_k + dt(t_k),   sample k = [t_k, min(t_{k+1}, t1)]

J is the contraction's Jacobian: 1 / r^2 along x, (2 - 1/r) / r across it. A ray leaving the
scene (mostly radial) takes world steps ~ step * r^2, so ~1 / step steps reach any distance; no
step jumps more than ~one contracted cell, also on rays passing the ball sideways. Every step tests its cell: that costs ~4 ns per step on
CPU, while jumping to the exit of an empty cell (DDA) measured 3x slower overall at the usual
2-5 steps per cell, and a jump could disagree with the per-midpoint rule at cell faces.
"""

import warp as wp

from warpnerf.kernels.occupancy import cell_index, grid_coords

wp.set_module_options({"enable_backward": False})

# Hard cap on the candidate steps of one ray, whatever reaches the kernel: a ray the interval
# test lets through by accident (NaN/inf that slips past it, a step far too small for the box)
# costs at most this many steps instead of hanging the launch, which Ctrl-C cannot interrupt.
# A unit-direction ray crossing the box diagonal takes 512 steps with the presets; the wrapper
# rejects step sizes that would need more than MAX_STEPS along the diagonal.
MAX_STEPS_PER_RAY = 65536
MAX_STEPS = wp.constant(MAX_STEPS_PER_RAY)


@wp.struct
class MarchGrid:
    """The occupancy grid as the marchers read it (``warpnerf/ops/raymarch.py`` ``_march_grid``).

    Cell layout as in ``kernels/occupancy.py``; the box around the occupied cells and the block
    bits only let the uniform marches skip candidates that are never samples (the contracted
    march reads the first four fields only)."""

    aabb_min: wp.vec3  # the box the grid covers
    aabb_max: wp.vec3
    grid_scale: wp.vec3  # res / (aabb_max - aabb_min)
    bitfield: wp.array(dtype=wp.uint8)  # (res^3,) 1 = occupied
    res: int
    box_min: wp.vec3  # a box holding every occupied cell (the scene box when unknown)
    box_max: wp.vec3
    blocks: wp.array(dtype=wp.uint8)  # (ceil(res / block)^3,) 1 = some cell of the block occupied
    block: int


@wp.func
def finite3(v: wp.vec3):
    return wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])


@wp.func
def ray_aabb_interval(o: wp.vec3, d: wp.vec3, aabb_min: wp.vec3, aabb_max: wp.vec3, near: float, far: float):
    """[t0, t1] of the ray inside the box and [near, far]; t1 <= t0 when it misses.

    Axes with d = 0 are tested on the origin instead of divided by zero (avoids 0 * inf = NaN);
    d = 0 on every axis is a miss, or an infinite ``far`` would never end the march.
    """
    t0 = near
    t1 = far
    if d[0] == 0.0 and d[1] == 0.0 and d[2] == 0.0:
        t1 = t0
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < aabb_min[a] or o[a] > aabb_max[a]:
                t1 = t0
        else:
            ta = (aabb_min[a] - o[a]) / d[a]
            tb = (aabb_max[a] - o[a]) / d[a]
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec2(t0, t1)


@wp.func
def occupied_box_span(o: wp.vec3, d: wp.vec3, t0: float, t1: float, box_min: wp.vec3, box_max: wp.vec3, near: float,
                      far: float, step: float):
    """(first candidate step, end of the march) of a uniform march over [t0, t1] that visits only the
    candidates whose midpoints can lie in the box [box_min, box_max] around the occupied cells:
    start one step before the first such candidate and stop one step past the box (margins far
    above float rounding); the candidate grid t0 + k step is unchanged, so are the samples.
    First step -1: the ray misses that box (no candidate is ever a sample)."""
    tight = ray_aabb_interval(o, d, box_min, box_max, near, far)
    if not (tight[1] > tight[0]):
        return -1, t1
    return wp.max(0, int(wp.floor((tight[0] - t0) / step - 0.5)) - 1), wp.min(t1, tight[1] + step)


@wp.func
def occupied(p: wp.vec3, aabb_min: wp.vec3, grid_scale: wp.vec3, occ_bitfield: wp.array(dtype=wp.uint8), res: int):
    """Point p (the grid's space) lies in an occupied cell of the grid (False outside it)."""
    c = cell_index(grid_coords(p, aabb_min, grid_scale), res)
    return c >= 0 and occ_bitfield[c] != wp.uint8(0)


@wp.func
def empty_block_skip(g: wp.vec3, d: wp.vec3, tm: float, grid_scale: wp.vec3, res: int,
                     blocks: wp.array(dtype=wp.uint8), block: int, t0: float, u: float, step: float, k: int):
    """Next candidate step after candidate k, whose midpoint ``tm`` lies in the grid at grid
    coordinates ``g`` in an empty cell: k + 1, or
    when that midpoint's block of ``block``^3 cells holds no occupied cell, the first candidate
    whose midpoint can be outside the block (every candidate skipped has its midpoint inside
    the empty block, so none is a sample: the same samples as stepping through it).

    ``blocks``: (nb^3,) uint8, nb = ceil(res / block), 1 where some cell of the block is occupied,
    flat index (bx * nb + by) * nb + bz with b = floor(cell / block). The exit is taken 1e-3 cells
    inside the block's faces (far above float rounding of the grid coordinates, which stay < res)."""
    nb = (res + block - 1) // block
    bx = int(wp.floor(g[0])) // block
    by = int(wp.floor(g[1])) // block
    bz = int(wp.floor(g[2])) // block
    if blocks[(bx * nb + by) * nb + bz] != wp.uint8(0):
        return k + 1
    gd = wp.cw_mul(d, grid_scale)  # grid cells per unit of t
    b = wp.vec3(float(bx), float(by), float(bz)) * float(block)
    dt = float(3.4e38)
    for a in range(3):
        if gd[a] > 0.0:
            dt = wp.min(dt, (b[a] + float(block) - 1.0e-3 - g[a]) / gd[a])
        elif gd[a] < 0.0:
            dt = wp.min(dt, (b[a] + 1.0e-3 - g[a]) / gd[a])
    # first j with midpoint t0 + (j + u + 0.5) step >= tm + dt; cap the jump: a ray along a face
    j = wp.ceil(wp.min((tm + dt - t0) / step - u - 0.5, float(MAX_STEPS)))
    return wp.max(k + 1, int(j))


@wp.func
def sample_slots(fill: int, r: int, max_samples: int, ray_offsets: wp.array(dtype=wp.int32),
                 ray_counts: wp.array(dtype=wp.int32)):
    """(first packed slot, most samples) of ray r: the count pass may keep up to ``max_samples``;
    the fill pass writes from the ray's offset and stops at its counted last sample."""
    if fill != 0:
        return ray_offsets[r], ray_counts[r]
    return 0, max_samples


@wp.func
def store_sample(fill: int, slot: int, r: int, ts: float, te: float, ray_indices: wp.array(dtype=wp.int32),
                 t_starts: wp.array(dtype=float), t_ends: wp.array(dtype=float)):
    """Fill pass: write sample [ts, te] of ray r at packed ``slot`` (the count pass writes nothing)."""
    if fill != 0:
        ray_indices[slot] = r
        t_starts[slot] = ts
        t_ends[slot] = te


@wp.kernel
def march_rays(
    first_ray: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    jitter: wp.array(dtype=float),
    has_jitter: int,
    grid: MarchGrid,
    near: float,
    far: float,
    step: float,
    max_samples: int,
    fill: int,
    ray_offsets: wp.array(dtype=wp.int32),
    ray_counts: wp.array(dtype=wp.int32),
    ray_indices: wp.array(dtype=wp.int32),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
):
    """Count (``fill`` = 0: writes ray_counts) or emit (``fill`` = 1: writes the packed samples
    at ray_offsets) the samples of rays [first_ray, first_ray + dim).

    Only candidates near the box ``[grid.box_min, grid.box_max]`` holding every occupied cell (the
    scene box when unknown) are visited, as in :func:`march_rays_window`: the same samples, without
    stepping through the empty rest of the scene box."""
    aabb_min = grid.aabb_min
    aabb_max = grid.aabb_max
    grid_scale = grid.grid_scale
    occ_bitfield = grid.bitfield
    res = grid.res
    box_min = grid.box_min
    box_max = grid.box_max
    blocks = grid.blocks
    block = grid.block
    r = first_ray + wp.tid()
    o = rays_o[r]
    d = rays_d[r]
    span = ray_aabb_interval(o, d, aabb_min, aabb_max, near, far)
    t0 = span[0]
    t1 = span[1]
    n = int(0)
    # a non-finite ray or interval is a miss (NaN poses, an unbounded interval): 0 samples
    if finite3(o) and finite3(d) and wp.isfinite(t0) and wp.isfinite(t1) and t1 > t0:
        # jitter shifts candidates by less than a step: occupied_box_span's one-step margins cover it
        k, t1 = occupied_box_span(o, d, t0, t1, box_min, box_max, near, far, step)
        u = float(0.0)
        if has_jitter != 0:
            u = jitter[r]
        base, limit = sample_slots(fill, r, max_samples, ray_offsets, ray_counts)
        while k >= 0 and n < limit and k < MAX_STEPS:  # k = -1: the ray misses the occupied box
            ts = t0 + (float(k) + u) * step
            if ts >= t1:
                break
            te = wp.min(ts + step, t1)
            tm = 0.5 * (ts + te)
            g = grid_coords(o + d * tm, aabb_min, grid_scale)
            c = cell_index(g, res)
            if c >= 0 and occ_bitfield[c] != wp.uint8(0):
                store_sample(fill, base + n, r, ts, te, ray_indices, t_starts, t_ends)
                n += 1
                k += 1
            elif c >= 0:
                k = empty_block_skip(g, d, tm, grid_scale, res, blocks, block, t0, u, step, k)
            else:
                k += 1
    if fill == 0:
        ray_counts[r] = n


@wp.func
def contract_point(p: wp.vec3):
    """MipNeRF-360's contraction: p inside the unit ball, (2 - 1/r) p / r outside (r = |p|)."""
    r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    if r2 <= 1.0:
        return p
    r = wp.sqrt(r2)
    return p * ((2.0 - 1.0 / r) / r)


@wp.func
def contracted_step(o: wp.vec3, d: wp.vec3, t: float, step: float):
    """World step at x = o + t d (unit d) that moves ``step`` in the contracted space (module doc)."""
    p = o + d * t
    r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    if r2 <= 1.0:
        return step
    r = wp.sqrt(r2)
    dr = (d[0] * p[0] + d[1] * p[1] + d[2] * p[2]) / r
    a = dr / r2
    s = (2.0 - 1.0 / r) / r
    b2 = wp.max(1.0 - dr * dr, 0.0)
    return step / wp.sqrt(a * a + b2 * (s * s))


@wp.kernel
def march_rays_contracted(
    first_ray: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    jitter: wp.array(dtype=float),
    has_jitter: int,
    grid: MarchGrid,
    near: float,
    far: float,
    step: float,
    max_samples: int,
    fill: int,
    ray_offsets: wp.array(dtype=wp.int32),
    ray_counts: wp.array(dtype=wp.int32),
    ray_indices: wp.array(dtype=wp.int32),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
):
    """:func:`march_rays` for contracted unbounded scenes (module doc): [near, far] in the
    normalised world, growing steps, occupancy looked up at the contracted sample midpoint."""
    aabb_min = grid.aabb_min
    grid_scale = grid.grid_scale
    occ_bitfield = grid.bitfield
    res = grid.res
    r = first_ray + wp.tid()
    o = rays_o[r]
    d = rays_d[r]
    t0 = near
    t1 = far
    n = int(0)
    nonzero = d[0] != 0.0 or d[1] != 0.0 or d[2] != 0.0
    if finite3(o) and finite3(d) and nonzero and wp.isfinite(t0) and wp.isfinite(t1) and t1 > t0:
        u = float(0.0)
        if has_jitter != 0:
            u = jitter[r]
        base, limit = sample_slots(fill, r, max_samples, ray_offsets, ray_counts)
        ts = t0 + u * contracted_step(o, d, t0, step)
        k = int(0)
        while n < limit and k < MAX_STEPS and ts < t1:
            te = wp.min(ts + contracted_step(o, d, ts, step), t1)
            if occupied(contract_point(o + d * (0.5 * (ts + te))), aabb_min, grid_scale, occ_bitfield, res):
                store_sample(fill, base + n, r, ts, te, ray_indices, t_starts, t_ends)
                n += 1
            ts = te
            k += 1
    if fill == 0:
        ray_counts[r] = n


@wp.kernel
def march_rays_window(
    first_ray: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    contract: int,
    grid: MarchGrid,
    near: float,
    far: float,
    step: float,
    max_samples: int,
    window: int,
    ray_k: wp.array(dtype=wp.int32),
    ray_t: wp.array(dtype=float),
    ray_taken: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
):
    """The next at most ``window`` samples of each ray, resuming where its last window stopped:
    the samples :func:`march_rays` (``contract`` = 0) or :func:`march_rays_contracted` (= 1)
    emits without jitter, ``window`` at a time (inference renders ray by ray in rounds and stops
    a ray once it is opaque, instead of marching it to the end).

    Per-ray state, read and updated: ``ray_k`` the next candidate step (-1 once the ray is
    finished: past its interval, out of steps, or ``max_samples`` taken), ``ray_t`` the next
    sample's start (contracted march only; the uniform one recomputes it from k), ``ray_taken``
    the samples emitted so far. Writes ``counts[r]`` samples at ``[r * window, ...)``. The uniform
    march only visits candidates near the box ``[grid.box_min, grid.box_max]`` holding every
    occupied cell (the scene box when unknown): the same samples, without stepping through the
    empty rest."""
    aabb_min = grid.aabb_min
    aabb_max = grid.aabb_max
    grid_scale = grid.grid_scale
    occ_bitfield = grid.bitfield
    res = grid.res
    box_min = grid.box_min
    box_max = grid.box_max
    blocks = grid.blocks
    block = grid.block
    r = first_ray + wp.tid()
    k = int(ray_k[r])
    n = int(0)
    if k >= 0:
        o = rays_o[r]
        d = rays_d[r]
        t0 = near
        t1 = far
        ok = finite3(o) and finite3(d) and (d[0] != 0.0 or d[1] != 0.0 or d[2] != 0.0)
        if contract == 0:
            span = ray_aabb_interval(o, d, aabb_min, aabb_max, near, far)
            t0 = span[0]
            t1 = span[1]
            if ok and wp.isfinite(t0) and wp.isfinite(t1):
                first, t1 = occupied_box_span(o, d, t0, t1, box_min, box_max, near, far, step)
                if first < 0:
                    ok = False
                elif k == 0:
                    k = first
        if not (ok and wp.isfinite(t0) and wp.isfinite(t1) and t1 > t0):
            k = -1
        else:
            taken = int(ray_taken[r])
            limit = wp.min(window, max_samples - taken)
            ts = ray_t[r]
            while n < limit:
                if contract == 0:
                    ts = t0 + float(k) * step
                if k >= MAX_STEPS or ts >= t1:
                    k = -1
                    break
                te = float(0.0)
                p = wp.vec3(0.0)
                if contract == 0:
                    te = wp.min(ts + step, t1)
                    p = o + d * (0.5 * (ts + te))
                else:
                    te = wp.min(ts + contracted_step(o, d, ts, step), t1)
                    p = contract_point(o + d * (0.5 * (ts + te)))
                g = grid_coords(p, aabb_min, grid_scale)
                c = cell_index(g, res)
                if c >= 0 and occ_bitfield[c] != wp.uint8(0):
                    t_starts[r * window + n] = ts
                    t_ends[r * window + n] = te
                    n += 1
                    k += 1
                elif c >= 0 and contract == 0:
                    k = empty_block_skip(g, d, 0.5 * (ts + te), grid_scale, res, blocks, block, t0, 0.0, step, k)
                else:
                    k += 1
                ts = te
            if taken + n >= max_samples:
                k = -1
            ray_t[r] = ts
            ray_taken[r] = taken + n
    ray_k[r] = k
    counts[r] = n
