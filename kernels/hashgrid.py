"""Multi-resolution hash-grid encoding (Instant-NGP) with in-kernel G²fR level masking.

Warp only; the torch wrapper is ``warpnerf/ops/hashgrid.py`` and the pure-torch twin
``warpnerf/ops/reference/hashgrid.py`` (op name: ``hashgrid_encode``).

Layout
  x          (N, D)      input points in [0, 1]^D (clamped; D = 1, 2 or 3)
  table      (rows,)     feature vectors of length F, all levels in one flat table
  out        (N, L)      feature vectors of length F, i.e. (N, L*F) for torch
  levels     (K,)        the level ids a launch covers
  weights    (L,)        G²fR level weights w_m (paper eq. 15); callers leave levels with
                         w_m = 0 out of ``levels``, so masked levels never touch the table.
  launch     dim = (K, ceil((stop - start) / chunk)): thread (j, c) handles level levels[j] for
             the points start + c * chunk ... (at most chunk of them, below stop). CUDA launches
             chunk = 1 (a thread per point and level); CPU launches chunk = the whole range: one
             loop per level over the points, so a level's table stays in cache while it is read
             and no per-point thread index is decomposed (1.3-1.6x faster than a thread each).

Kernels are generated per (D, F, dtype) by :func:`make_hashgrid_kernels`; float64 exists for
gradcheck. Backward is hand written: one kernel scatters into the table gradient and,
optionally, accumulates the gradient with respect to x (the pose task's only path to the
cameras). On CPU the caller gives each thread disjoint levels and its own dx buffer.
"""


import functools

import warp as wp

# Instant-NGP's spatial-hash primes for y and z (x uses 1); uint32 arithmetic wraps like the paper's
PRIME_Y = wp.constant(wp.uint32(2654435761))
PRIME_Z = wp.constant(wp.uint32(805459861))


@wp.func
def hashgrid_axis_terms(base: int, multiplier: wp.uint32):
    """Row terms of the lower and upper grid point along one axis: base * m and (base + 1) * m.

    A corner's row combines one term per axis: hashed levels XOR them (Instant-NGP's spatial
    hash, multipliers 1, PRIME_Y, PRIME_Z), dense levels add them (multipliers 1, s, s^2).
    """
    return wp.uint32(base) * multiplier, wp.uint32(base + 1) * multiplier


@wp.func
def hashgrid_row(tx: wp.uint32, ty: wp.uint32, tz: wp.uint32, hashed: int, hash_mask: wp.uint32, offset: int):
    """Flat table row of the grid point whose axis terms are tx, ty, tz (see hashgrid_axis_terms)."""
    if hashed != 0:
        return offset + int((tx ^ ty ^ tz) & hash_mask)
    return offset + int(tx + ty + tz)


@wp.func
def chunk_points(c: int, start: int, stop: int, chunk: int):
    """[first, end) of the points thread column c handles: up to ``chunk`` points from
    start + c * chunk, below ``stop`` (the grid kernels' launch layout, module docstring)."""
    first = start + c * chunk
    return first, wp.min(first + chunk, stop)


@wp.func
def hashgrid_cell(u: float, s: int):
    """Base grid point, fraction and d(position)/du for one coordinate u at a level of s points.

    Coordinates outside [0, 1] (and NaN) are clamped, so their derivative is 0; x = 1 lands at
    fraction 1 of the last cell instead of reading past the grid.
    """
    inside = float(1.0)
    if not (u >= 0.0):  # also catches NaN: never index the table with garbage
        u = 0.0
        inside = 0.0
    if u > 1.0:
        u = 1.0
        inside = 0.0
    p = u * float(s - 1)
    base = wp.min(int(wp.floor(p)), s - 2)
    return base, p - float(base), inside * float(s - 1)


@wp.func
def hashgrid_cell64(u: wp.float64, s: int):
    """float64 twin of :func:`hashgrid_cell` (used by gradcheck kernels)."""
    inside = wp.float64(1.0)
    if not (u >= wp.float64(0.0)):
        u = wp.float64(0.0)
        inside = wp.float64(0.0)
    if u > wp.float64(1.0):
        u = wp.float64(1.0)
        inside = wp.float64(0.0)
    p = u * wp.float64(s - 1)
    base = wp.min(int(wp.floor(p)), s - 2)
    return base, p - wp.float64(base), inside * wp.float64(s - 1)


@functools.lru_cache(maxsize=None)
def make_hashgrid_kernels(dim: int, n_features: int, dtype=wp.float32):
    """Return ``(forward, backward, vec_type)`` kernels for input dimension ``dim`` and F = ``n_features``."""
    if dim not in (1, 2, 3):
        raise ValueError(f"hash grid input dimension must be 1, 2 or 3, got {dim}")
    vec = wp.types.vector(length=n_features, dtype=dtype)
    cell = hashgrid_cell64 if dtype == wp.float64 else hashgrid_cell
    n_corners = 1 << dim
    one = dtype(1.0)
    zero = dtype(0.0)

    @wp.func
    def corner_weight(c: int, fx: dtype, fy: dtype, fz: dtype):
        # interpolation weight of corner c (bit d set = upper neighbour along axis d)
        w = wp.where((c & 1) != 0, fx, one - fx)
        if wp.static(dim >= 2):
            w = w * wp.where((c & 2) != 0, fy, one - fy)
        if wp.static(dim >= 3):
            w = w * wp.where((c & 4) != 0, fz, one - fz)
        return w

    @wp.func
    def locate(x: wp.array2d(dtype=dtype), n: int, s: int, hashed: int):
        """Cell of point n at a level of s points per axis: base point, fractions, d(position)/dx
        and the axis multipliers of its rows (a missing axis: base 0, fraction 0, multiplier 0)."""
        bx, fx, dx_ = cell(x[n, 0], s)
        by, fy, dy_ = 0, zero, zero
        bz, fz, dz_ = 0, zero, zero
        my = wp.uint32(0)
        mz = wp.uint32(0)
        if wp.static(dim >= 2):
            by, fy, dy_ = cell(x[n, 1], s)
            my = wp.where(hashed != 0, PRIME_Y, wp.uint32(s))
        if wp.static(dim >= 3):
            bz, fz, dz_ = cell(x[n, 2], s)
            mz = wp.where(hashed != 0, PRIME_Z, wp.uint32(s) * wp.uint32(s))
        return bx, by, bz, fx, fy, fz, dx_, dy_, dz_, my, mz

    @wp.func
    def encode_point(x: wp.array2d(dtype=dtype), table: wp.array(dtype=vec), n: int, s: int, off: int, hsh: int,
                     hash_mask: wp.uint32):
        bx, by, bz, fx, fy, fz, dx_, dy_, dz_, my, mz = locate(x, n, s, hsh)
        tx0, tx1 = hashgrid_axis_terms(bx, wp.uint32(1))
        ty0, ty1 = hashgrid_axis_terms(by, my)
        tz0, tz1 = hashgrid_axis_terms(bz, mz)
        acc = vec()
        for c in range(wp.static(n_corners)):
            row = hashgrid_row(wp.where((c & 1) != 0, tx1, tx0), wp.where((c & 2) != 0, ty1, ty0),
                               wp.where((c & 4) != 0, tz1, tz0), hsh, hash_mask, off)
            acc = acc + corner_weight(c, fx, fy, fz) * table[row]
        return acc

    @wp.kernel(enable_backward=False, module="unique")
    def hashgrid_encode_fwd(
        x: wp.array2d(dtype=dtype),
        table: wp.array(dtype=vec),
        levels: wp.array(dtype=wp.int32),
        resolutions: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        hashed: wp.array(dtype=wp.int32),
        hash_mask: wp.uint32,
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
        hsh = hashed[lvl]
        w = weights[lvl]
        first, end = chunk_points(c, start, stop, chunk)
        for n in range(first, end):
            out[n, lvl] = encode_point(x, table, n, s, off, hsh, hash_mask) * w

    @wp.func
    def is_zero(g: vec):
        # exact test per component (a squared norm would underflow for tiny non-zero gradients)
        nonzero = int(0)
        for f in range(wp.static(n_features)):
            if g[f] != zero:
                nonzero = 1
        return nonzero == 0

    @wp.func
    def scatter_point(x: wp.array2d(dtype=dtype), table: wp.array(dtype=vec), g: vec, n: int, s: int, off: int,
                      hsh: int, hash_mask: wp.uint32, want_table: int, want_x: int, grad_table: wp.array(dtype=vec),
                      grad_x: wp.array2d(dtype=dtype)):
        bx, by, bz, fx, fy, fz, dx_, dy_, dz_, my, mz = locate(x, n, s, hsh)
        tx0, tx1 = hashgrid_axis_terms(bx, wp.uint32(1))
        ty0, ty1 = hashgrid_axis_terms(by, my)
        tz0, tz1 = hashgrid_axis_terms(bz, mz)
        gx = zero
        gy = zero
        gz = zero
        for c in range(wp.static(n_corners)):
            ux = (c & 1) != 0
            uy = (c & 2) != 0
            uz = (c & 4) != 0
            row = hashgrid_row(wp.where(ux, tx1, tx0), wp.where(uy, ty1, ty0), wp.where(uz, tz1, tz0), hsh,
                               hash_mask, off)
            wx = wp.where(ux, fx, one - fx)
            wy = one
            wz = one
            if wp.static(dim >= 2):
                wy = wp.where(uy, fy, one - fy)
            if wp.static(dim >= 3):
                wz = wp.where(uz, fz, one - fz)
            if want_table != 0:
                wp.atomic_add(grad_table, row, (wx * wy * wz) * g)
            if want_x != 0:
                # d(corner weight)/d(fraction) is +-1 times the other axes' weights
                gf = wp.dot(g, table[row])
                gx += gf * wp.where(ux, one, -one) * wy * wz
                if wp.static(dim >= 2):
                    gy += gf * wp.where(uy, one, -one) * wx * wz
                if wp.static(dim >= 3):
                    gz += gf * wp.where(uz, one, -one) * wx * wy
        if want_x != 0:
            wp.atomic_add(grad_x, n, 0, gx * dx_)
            if wp.static(dim >= 2):
                wp.atomic_add(grad_x, n, 1, gy * dy_)
            if wp.static(dim >= 3):
                wp.atomic_add(grad_x, n, 2, gz * dz_)

    @wp.kernel(enable_backward=False, module="unique")
    def hashgrid_encode_bwd(
        x: wp.array2d(dtype=dtype),
        table: wp.array(dtype=vec),
        grad_out: wp.array2d(dtype=vec),
        levels: wp.array(dtype=wp.int32),
        resolutions: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        hashed: wp.array(dtype=wp.int32),
        hash_mask: wp.uint32,
        weights: wp.array(dtype=dtype),
        want_table: int,
        want_x: int,
        start: int,
        stop: int,
        chunk: int,
        grad_table: wp.array(dtype=vec),
        grad_x: wp.array2d(dtype=dtype),
    ):
        j, c = wp.tid()
        lvl = levels[j]
        s = resolutions[lvl]
        off = offsets[lvl]
        hsh = hashed[lvl]
        w = weights[lvl]
        first, end = chunk_points(c, start, stop, chunk)
        for n in range(first, end):
            g = grad_out[n, lvl] * w
            # a sample the compositing ignores (behind an opaque surface, T < eps) gets an exact
            # zero gradient: skipping it leaves every sum unchanged (instant-ngp drops such samples)
            if not is_zero(g):
                scatter_point(x, table, g, n, s, off, hsh, hash_mask, want_table, want_x, grad_table, grad_x)

    return hashgrid_encode_fwd, hashgrid_encode_bwd, vec
