"""Occupancy grid over the scene box (instant-ngp / nerfacc style).

Warp only. Each kernel is launched by the op of the same name in ``warpnerf/ops/occupancy.py``
(torch twins in ``warpnerf/ops/reference/occupancy.py``); the grid that runs them is
``warpnerf/model/occupancy.py`` (class ``OccupancyGrid``), and the ray marcher that reads the grid
is ``kernels/raymarch.py``.

Cell layout, shared with the marcher through :func:`grid_coords` and :func:`cell_index`:
  grid coordinates  g = (p - aabb_min) * grid_scale,  grid_scale = res / (aabb_max - aabb_min)
  cell of point p   (ix, iy, iz) = floor(g), valid when 0 <= g < res on every axis
  flat index        idx = (ix * res + iy) * res + iz
  density, bitfield (res^3,) arrays in that order; bitfield 1 = occupied.
"""

import warp as wp

# the backward is never used: updates run under no_grad
wp.set_module_options({"enable_backward": False})


@wp.func
def grid_coords(p: wp.vec3, aabb_min: wp.vec3, grid_scale: wp.vec3):
    """Continuous grid coordinates of world point ``p`` (cell units, 0 at aabb_min)."""
    return wp.cw_mul(p - aabb_min, grid_scale)


@wp.func
def cell_index(g: wp.vec3, res: int):
    """Flat cell index of grid coordinates ``g``, or -1 outside [0, res)^3 (also for NaN).

    Bounds are tested on the floats before the int cast so far-away points never overflow it.
    """
    fres = float(res)
    if not (g[0] >= 0.0 and g[0] < fres and g[1] >= 0.0 and g[1] < fres and g[2] >= 0.0 and g[2] < fres):
        return -1
    ix = int(wp.floor(g[0]))
    iy = int(wp.floor(g[1]))
    iz = int(wp.floor(g[2]))
    return (ix * res + iy) * res + iz


@wp.kernel
def occupancy_sample_points(
    cells: wp.array(dtype=wp.int32),
    jitter: wp.array(dtype=wp.vec3),
    aabb_min: wp.vec3,
    cell_size: wp.vec3,
    res: int,
    points: wp.array(dtype=wp.vec3),
):
    """World position of each sampled cell at its jittered offset (``jitter`` in [0, 1)^3)."""
    i = wp.tid()
    c = cells[i]
    ix = c // (res * res)
    iy = (c // res) % res
    iz = c % res
    ijk = wp.vec3(float(ix), float(iy), float(iz))
    points[i] = aabb_min + wp.cw_mul(ijk + jitter[i], cell_size)


@wp.kernel
def occupancy_scatter_max(
    points: wp.array(dtype=wp.vec3),
    sigmas: wp.array(dtype=float),
    aabb_min: wp.vec3,
    grid_scale: wp.vec3,
    res: int,
    fresh: wp.array(dtype=float),
):
    """Max of the new density samples per cell into ``fresh`` (pre-filled with -1 = not sampled).

    A sample is credited to the cell the marcher would look up for its position, so rounding at
    a cell face never makes the grid and the marcher disagree. Several samples may hit one cell:
    the max is order-independent, so the result does not depend on launch order.
    """
    i = wp.tid()
    c = cell_index(grid_coords(points[i], aabb_min, grid_scale), res)
    if c >= 0:
        wp.atomic_max(fresh, c, sigmas[i])


@wp.kernel
def occupancy_ema(fresh: wp.array(dtype=float), decay: float, density: wp.array(dtype=float)):
    """density = max(density * decay, fresh) for the cells sampled in this update."""
    c = wp.tid()
    f = fresh[c]
    if f >= 0.0:
        density[c] = wp.max(density[c] * decay, f)


@wp.kernel
def occupancy_bitfield(density: wp.array(dtype=float), threshold: float, bitfield: wp.array(dtype=wp.uint8)):
    """bitfield = density > threshold."""
    c = wp.tid()
    if density[c] > threshold:
        bitfield[c] = wp.uint8(1)
    else:
        bitfield[c] = wp.uint8(0)
