"""Ray tracing of triangle meshes with procedural materials (renders the built-in scenes).

One thread per pixel of one view: a primary ray through the pixel centre, closest hit with
``wp.mesh_query_ray``, shading normal interpolated from per-vertex normals, albedo from a small
material table evaluated at the world-space hit point, Lambert shading from a key light (with a
hard shadow ray) plus an unshadowed fill light and an ambient term.

Conventions match :mod:`warpnerf.data.scene`: cameras are OpenGL (x right, y up, looking down
-z), pixel (u, v) has its centre at (u + 0.5, v + 0.5). Depth is the distance along the camera
z axis (not along the ray), 0 where the ray misses. Alpha is exact: 1 on a hit, 0 on a miss
(one ray per pixel, no antialiasing), so compositing on any background is lossless.

The noise used by the textures is a hash-based value noise written here rather than
``wp.noise``: its values depend only on float arithmetic, so a scene renders the same on
CPU and CUDA and across Warp versions (``wp.noise`` documents no such guarantee).
"""

import warp as wp

# Material patterns (``mat_pattern``). Every material also has two colours (a, b), a frequency
# (features per scene unit), an axis (0/1/2 = x/y/z) and an origin; their meaning per pattern:
PATTERN_SOLID = wp.constant(0)  # colour a
PATTERN_WOOD = wp.constant(1)  # growth rings around a line through `origin` along `axis`; a = light, b = dark
PATTERN_WEAVE = wp.constant(2)  # plain weave of threads, `freq` threads per unit; a = warp, b = weft thread
PATTERN_STRIPES = wp.constant(3)  # hard stripes across `axis`, `freq` stripes (a+b pairs) per unit
PATTERN_ANGULAR = wp.constant(4)  # hard stripes by angle around the `axis` line through `origin`; `freq` pairs per turn
PATTERN_GLAZE = wp.constant(5)  # smooth blend a -> b along `axis` over [-1, 1], low-frequency noise of scale `freq`
PATTERN_MARBLE = wp.constant(6)  # turbulent veins of b in a, `freq` veins per unit

_TWO_PI = wp.constant(6.283185307179586)


@wp.func
def hash_unit(ix: int, iy: int, iz: int, seed: int) -> float:
    """A pseudo-random value in [0, 1] for an integer lattice point."""
    # Constants stay below 2^31: Warp types integer literals as int32.
    h = wp.uint32(ix) * wp.uint32(73856093)
    h = h ^ (wp.uint32(iy) * wp.uint32(19349663))
    h = h ^ (wp.uint32(iz) * wp.uint32(83492791))
    h = h ^ (wp.uint32(seed) * wp.uint32(0x165667B1))
    # Integer finaliser (a low-bias 32-bit mixer): the lattice products alone are too regular.
    h = h ^ (h >> wp.uint32(16))
    h = h * wp.uint32(0x21F0AAAD)
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(0x735A2D97)
    h = h ^ (h >> wp.uint32(15))
    return float(h & wp.uint32(0xFFFFFF)) / 16777215.0


@wp.func
def value_noise(p: wp.vec3, seed: int) -> float:
    """Smooth value noise in [0, 1], one feature per unit (trilinear blend of lattice hashes)."""
    fx = wp.floor(p[0])
    fy = wp.floor(p[1])
    fz = wp.floor(p[2])
    ix = int(fx)
    iy = int(fy)
    iz = int(fz)
    tx = p[0] - fx
    ty = p[1] - fy
    tz = p[2] - fz
    # Smoothstep weights make the field C1, so shading shows no lattice creases.
    sx = tx * tx * (3.0 - 2.0 * tx)
    sy = ty * ty * (3.0 - 2.0 * ty)
    sz = tz * tz * (3.0 - 2.0 * tz)
    c00 = wp.lerp(hash_unit(ix, iy, iz, seed), hash_unit(ix + 1, iy, iz, seed), sx)
    c10 = wp.lerp(hash_unit(ix, iy + 1, iz, seed), hash_unit(ix + 1, iy + 1, iz, seed), sx)
    c01 = wp.lerp(hash_unit(ix, iy, iz + 1, seed), hash_unit(ix + 1, iy, iz + 1, seed), sx)
    c11 = wp.lerp(hash_unit(ix, iy + 1, iz + 1, seed), hash_unit(ix + 1, iy + 1, iz + 1, seed), sx)
    return wp.lerp(wp.lerp(c00, c10, sy), wp.lerp(c01, c11, sy), sz)


@wp.func
def fbm(p: wp.vec3, seed: int) -> float:
    """Three octaves of value noise, in [0, 1]."""
    return (
        0.5714 * value_noise(p, seed)
        + 0.2857 * value_noise(p * 2.03, seed + 1)
        + 0.1429 * value_noise(p * 4.01, seed + 2)
    )


@wp.func
def axis_frame(p: wp.vec3, axis: int) -> wp.vec3:
    """``p`` permuted so that ``axis`` comes last: (u, v, along)."""
    if axis == 0:
        return wp.vec3(p[1], p[2], p[0])
    if axis == 1:
        return wp.vec3(p[2], p[0], p[1])
    return p


@wp.func
def material_albedo(
    pattern: int,
    color_a: wp.vec3,
    color_b: wp.vec3,
    freq: float,
    axis: int,
    origin: wp.vec3,
    p: wp.vec3,
    n: wp.vec3,
) -> wp.vec3:
    """Albedo in [0, 1]^3 of a material at world point ``p`` with shading normal ``n``."""
    if pattern == PATTERN_WOOD:
        q = axis_frame(p - origin, axis)
        # Noise stretched along the grain (low frequency along `axis`) bends the rings into
        # long streaks, which is what sawn wood shows on a face parallel to the grain.
        warp_q = wp.vec3(q[0] * 4.0, q[1] * 4.0, q[2] * 0.35)
        r = wp.sqrt(q[0] * q[0] + q[1] * q[1]) + 0.08 * fbm(warp_q, 11)
        ring = wp.frac(r * freq)
        # Late wood: a narrow dark band at the end of each ring, sharp on its outer edge.
        dark = wp.smoothstep(0.55, 0.85, ring) * (1.0 - wp.smoothstep(0.93, 1.0, ring))
        streak = value_noise(wp.vec3(q[0] * 70.0, q[1] * 70.0, q[2] * 1.5), 17)
        c = wp.lerp(color_a, color_b, dark)
        return c * (0.8 + 0.35 * streak)
    if pattern == PATTERN_WEAVE:
        # Weave on the plane most facing the normal (triplanar pick, good for box-like cushions).
        an = wp.vec3(wp.abs(n[0]), wp.abs(n[1]), wp.abs(n[2]))
        s = p[0]
        t = p[1]
        if an[0] >= an[1] and an[0] >= an[2]:
            s = p[1]
            t = p[2]
        elif an[1] >= an[2]:
            s = p[0]
            t = p[2]
        s = s * freq
        t = t * freq
        i = int(wp.floor(s))
        j = int(wp.floor(t))
        fs = s - wp.floor(s)
        ft = t - wp.floor(t)
        c = color_a
        profile = wp.sin(3.14159265 * ft)
        if (i + j) % 2 != 0:
            c = color_b
            profile = wp.sin(3.14159265 * fs)
        fleck = value_noise(p * (freq * 0.5), 23)
        return c * (0.45 + 0.55 * profile) * (0.9 + 0.2 * fleck)
    if pattern == PATTERN_STRIPES:
        q = axis_frame(p - origin, axis)
        if wp.frac(q[2] * freq) < 0.5:
            return color_a
        return color_b
    if pattern == PATTERN_ANGULAR:
        q = axis_frame(p - origin, axis)
        turn = (wp.atan2(q[1], q[0]) + 3.14159265) / _TWO_PI
        if wp.frac(turn * freq) < 0.5:
            return color_a
        return color_b
    if pattern == PATTERN_GLAZE:
        q = axis_frame(p - origin, axis)
        blend = wp.clamp(0.5 + 0.5 * q[2] + 0.25 * (fbm(p * freq, 31) - 0.5), 0.0, 1.0)
        return wp.lerp(color_a, color_b, wp.smoothstep(0.0, 1.0, blend))
    if pattern == PATTERN_MARBLE:
        turbulence = fbm(p * 3.0, 41)
        vein = 0.5 + 0.5 * wp.sin(freq * _TWO_PI * (p[0] + 0.6 * p[1]) + 9.0 * turbulence)
        return wp.lerp(color_a, color_b, wp.pow(vein, 6.0))
    return color_a


@wp.kernel
def render_mesh(
    mesh: wp.uint64,
    tri_indices: wp.array(dtype=wp.int32),  # (3F,) vertex ids of each face
    vertex_normals: wp.array(dtype=wp.vec3),  # (V,) unit shading normals
    face_material: wp.array(dtype=wp.int32),  # (F,) row of the material table
    mat_pattern: wp.array(dtype=wp.int32),  # (M,) PATTERN_*
    mat_color_a: wp.array(dtype=wp.vec3),  # (M,)
    mat_color_b: wp.array(dtype=wp.vec3),  # (M,)
    mat_freq: wp.array(dtype=wp.float32),  # (M,) features per scene unit (per turn for ANGULAR)
    mat_axis: wp.array(dtype=wp.int32),  # (M,) 0, 1, 2
    mat_origin: wp.array(dtype=wp.vec3),  # (M,)
    cam_rot: wp.array(dtype=wp.mat33),  # (N,) camera-to-world rotation, OpenGL columns
    cam_pos: wp.array(dtype=wp.vec3),  # (N,) camera centre, world units
    focal: float,  # pixels
    cx: float,
    cy: float,
    key_dir: wp.vec3,  # unit vector towards the key light
    key_strength: float,
    fill_dir: wp.vec3,  # unit vector towards the fill light (never shadowed)
    fill_strength: float,
    ambient: float,
    shadows: int,  # 1: trace a shadow ray towards the key light
    out_rgba: wp.array3d(dtype=wp.vec4),  # (N, H, W) straight (not premultiplied) colour + alpha
    out_depth: wp.array3d(dtype=wp.float32),  # (N, H, W) camera-z distance, 0 on a miss
):
    view, row, col = wp.tid()
    # Camera-space direction with z = -1: the hit parameter t is then the camera-z depth.
    d_cam = wp.vec3((float(col) + 0.5 - cx) / focal, -(float(row) + 0.5 - cy) / focal, -1.0)
    o = cam_pos[view]
    d = cam_rot[view] * d_cam

    hit = wp.mesh_query_ray(mesh, o, d, 1.0e6)
    if not hit.result:
        out_rgba[view, row, col] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        out_depth[view, row, col] = 0.0
        return

    f = hit.face
    i0 = tri_indices[3 * f + 0]
    i1 = tri_indices[3 * f + 1]
    i2 = tri_indices[3 * f + 2]
    # Same barycentric convention as wp.mesh_eval_position: p0*u + p1*v + p2*(1-u-v).
    n = wp.normalize(
        vertex_normals[i0] * hit.u + vertex_normals[i1] * hit.v + vertex_normals[i2] * (1.0 - hit.u - hit.v)
    )
    # Surfaces are two-sided (open lamp shade, vase mouth): shade the side facing the camera.
    if wp.dot(n, d) > 0.0:
        n = -n
    geo_n = hit.normal
    if wp.dot(geo_n, d) > 0.0:
        geo_n = -geo_n

    p = o + d * hit.t
    m = face_material[f]
    albedo = material_albedo(
        mat_pattern[m], mat_color_a[m], mat_color_b[m], mat_freq[m], mat_axis[m], mat_origin[m], p, n
    )

    key = wp.max(wp.dot(n, key_dir), 0.0)
    if shadows != 0 and key > 0.0:
        # Offset along the geometric normal: the interpolated normal can point below the face
        # near silhouettes and would make the surface shadow itself.
        start = p + geo_n * 1.0e-3
        if wp.mesh_query_ray_anyhit(mesh, start, key_dir, 1.0e6):
            key = 0.0
    light = ambient + key_strength * key + fill_strength * wp.max(wp.dot(n, fill_dir), 0.0)
    c = albedo * light
    out_rgba[view, row, col] = wp.vec4(
        wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0), 1.0
    )
    out_depth[view, row, col] = hit.t
