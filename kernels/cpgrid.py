"""Multi-resolution CP (CANDECOMP/PARAFAC) grid encoding, the "Mtrf" of G²fR, with in-kernel level masking.

Warp only; the torch wrapper is ``warpnerf/ops/cpgrid.py`` and the pure-torch twin
``warpnerf/ops/reference/cpgrid.py`` (op name: ``cpgrid_encode``).

Each level l is a rank-R CP factorisation of a 3-D grid of s_l points per axis whose R
rank-one components are kept as R separate features (TensoRF sums them instead):
feature r of level l at x is  w_l * v^{l,x}_r(x) * v^{l,y}_r(y) * v^{l,z}_r(z), where every
v^{l,a}_r is a 1-D line of s_l values read with linear interpolation ("align corners").

Layout
  x          (N, 3)      input points in [0, 1]^3 (clamped)
  lines      (rows, 3)   vectors of length R: ``lines[offsets[l] + i, a]`` holds entry i of the
                         R lines of level l along axis a, i.e. a (rows, 3, R) tensor for torch
  out        (N, L)      vectors of length R, i.e. (N, L*R) for torch (level-major columns)
  levels     (K,)        the level ids a launch covers; dim = (K, ceil((stop - start) / chunk)),
                         thread (j, c) handles level levels[j] for up to ``chunk`` points from
                         start + c * chunk (CUDA: chunk 1; CPU: one loop per level, as the hash grid)
  weights    (L,)        G²fR level weights w_l; callers leave levels with w_l = 0 out of
                         ``levels``, so masked levels never touch ``lines``.

Kernels are generated per (R, dtype) by :func:`make_cpgrid_kernels`; float64 exists for
gradcheck. The cell lookup (clamping, x = 1 landing at fraction 1 of the last cell, zero
derivative outside the box) is shared with the hash grid so both encodings agree on borders.
Backward scatters into the two neighbouring entries of each line and, optionally,
accumulates the gradient with respect to x. On CPU the caller gives each thread disjoint
levels (hence disjoint rows of ``lines``) and its own dx buffer.
"""


import functools

import warp as wp

from warpnerf.kernels.hashgrid import chunk_points, hashgrid_cell, hashgrid_cell64


@functools.lru_cache(maxsize=None)
def make_cpgrid_kernels(rank: int, dtype=wp.float32):
    """Return ``(forward, backward, vec_type)`` kernels for CP rank R = ``rank``."""
    if rank < 1:
        raise ValueError(f"CP rank must be >= 1, got {rank}")
    vec = wp.types.vector(length=rank, dtype=dtype)
    cell = hashgrid_cell64 if dtype == wp.float64 else hashgrid_cell
    one = dtype(1.0)

    @wp.func
    def encode_point(x: wp.array2d(dtype=dtype), lines: wp.array2d(dtype=vec), n: int, s: int, off: int):
        bx, fx, dx_ = cell(x[n, 0], s)
        by, fy, dy_ = cell(x[n, 1], s)
        bz, fz, dz_ = cell(x[n, 2], s)
        vx = (one - fx) * lines[off + bx, 0] + fx * lines[off + bx + 1, 0]
        vy = (one - fy) * lines[off + by, 1] + fy * lines[off + by + 1, 1]
        vz = (one - fz) * lines[off + bz, 2] + fz * lines[off + bz + 1, 2]
        return wp.cw_mul(wp.cw_mul(vx, vy), vz)

    @wp.kernel(enable_backward=False, module="unique")
    def cpgrid_encode_fwd(
        x: wp.array2d(dtype=dtype),
        lines: wp.array2d(dtype=vec),
        levels: wp.array(dtype=wp.int32),
        resolutions: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        weights: wp.array(dtype=dtype),
        start: int,
        stop: int,
        chunk: int,
        out: wp.array2d(dtype=vec),
    ):
        j, c = wp.tid()
        lvl = levels[j]
        s = resolutions[lvl]
        off = offsets[lvl]
        w = weights[lvl]
        first, end = chunk_points(c, start, stop, chunk)
        for n in range(first, end):
            out[n, lvl] = encode_point(x, lines, n, s, off) * w

    @wp.func
    def is_zero(g: vec):
        # exact test per component (a squared norm would underflow for tiny non-zero gradients)
        nonzero = int(0)
        for f in range(wp.static(rank)):
            if g[f] != dtype(0.0):
                nonzero = 1
        return nonzero == 0

    @wp.func
    def scatter_point(x: wp.array2d(dtype=dtype), lines: wp.array2d(dtype=vec), g: vec, n: int, s: int, off: int,
                      want_lines: int, want_x: int, grad_lines: wp.array2d(dtype=vec), grad_x: wp.array2d(dtype=dtype)):
        bx, fx, dx_ = cell(x[n, 0], s)
        by, fy, dy_ = cell(x[n, 1], s)
        bz, fz, dz_ = cell(x[n, 2], s)
        rx = off + bx
        ry = off + by
        rz = off + bz
        lox = lines[rx, 0]
        hix = lines[rx + 1, 0]
        loy = lines[ry, 1]
        hiy = lines[ry + 1, 1]
        loz = lines[rz, 2]
        hiz = lines[rz + 1, 2]
        vx = (one - fx) * lox + fx * hix
        vy = (one - fy) * loy + fy * hiy
        vz = (one - fz) * loz + fz * hiz
        # d(loss)/d(interpolated line value) per axis: upstream gradient times the other two factors
        gx = wp.cw_mul(g, wp.cw_mul(vy, vz))
        gy = wp.cw_mul(g, wp.cw_mul(vx, vz))
        gz = wp.cw_mul(g, wp.cw_mul(vx, vy))
        if want_lines != 0:
            wp.atomic_add(grad_lines, rx, 0, (one - fx) * gx)
            wp.atomic_add(grad_lines, rx + 1, 0, fx * gx)
            wp.atomic_add(grad_lines, ry, 1, (one - fy) * gy)
            wp.atomic_add(grad_lines, ry + 1, 1, fy * gy)
            wp.atomic_add(grad_lines, rz, 2, (one - fz) * gz)
            wp.atomic_add(grad_lines, rz + 1, 2, fz * gz)
        if want_x != 0:
            # d(value)/d(fraction) = v[i+1] - v[i]; d(fraction)/dx = s - 1 inside the box, 0 if clamped
            wp.atomic_add(grad_x, n, 0, wp.dot(gx, hix - lox) * dx_)
            wp.atomic_add(grad_x, n, 1, wp.dot(gy, hiy - loy) * dy_)
            wp.atomic_add(grad_x, n, 2, wp.dot(gz, hiz - loz) * dz_)

    @wp.kernel(enable_backward=False, module="unique")
    def cpgrid_encode_bwd(
        x: wp.array2d(dtype=dtype),
        lines: wp.array2d(dtype=vec),
        grad_out: wp.array2d(dtype=vec),
        levels: wp.array(dtype=wp.int32),
        resolutions: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        weights: wp.array(dtype=dtype),
        want_lines: int,
        want_x: int,
        start: int,
        stop: int,
        chunk: int,
        grad_lines: wp.array2d(dtype=vec),
        grad_x: wp.array2d(dtype=dtype),
    ):
        j, c = wp.tid()
        lvl = levels[j]
        s = resolutions[lvl]
        off = offsets[lvl]
        w = weights[lvl]
        first, end = chunk_points(c, start, stop, chunk)
        for n in range(first, end):
            g = grad_out[n, lvl] * w
            # a sample the compositing ignores (behind an opaque surface, T < eps) gets an exact
            # zero gradient: skipping it leaves every sum unchanged (instant-ngp drops such samples)
            if not is_zero(g):
                scatter_point(x, lines, g, n, s, off, want_lines, want_x, grad_lines, grad_x)

    return cpgrid_encode_fwd, cpgrid_encode_bwd, vec
