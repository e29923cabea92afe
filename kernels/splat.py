"""Warp kernels of the Gaussian-splatting rasterizer: projection, tile binning, compositing and their backward.

The pipeline of one forward pass (conventions in ``docs/conventions.md``):

1. :func:`launch_project` (one thread per Gaussian): EWA projection of each 3D Gaussian to a 2D mean, a 2D
   conic (inverse covariance), a camera depth, a per-axis pixel radius, an RGB colour (spherical harmonics
   evaluated) and the number of 16x16 pixel tiles it reaches. The extent is opacity-aware: the radius box
   bounds the ellipse where the Gaussian's alpha can reach 1/255 (:func:`reach_sigma`; Gaussians of opacity
   below 1/255 are culled), and of the box's tiles only those whose pixel centres that ellipse meets count
   (:func:`row_tile_span`, exact, O(1) per tile row), so thin diagonal Gaussians skip most of their box.
   The projection also writes the inputs of the depth sort: a float32 key per Gaussian (its depth, or
   ``FAR_PLANE`` when it reaches no tile) and a record (Gaussian, tile count).
2. Tile binning in two stable radix sorts (``wp.utils.radix_sort_pairs``, CUB's on CUDA) that together give
   the order (tile, depth, Gaussian index) of one sort of 64-bit ``tile | depth`` keys, with 4-byte keys:
   the records are sorted by their depth keys (:data:`DEPTH_SORT_BITS` bits, N entries; equal depths keep
   the index order); an inclusive prefix sum of their tile counts in that order (``wp.utils.array_scan``,
   read in place from the records) gives every Gaussian its slots; :func:`launch_emit_tile_keys`
   (:data:`EMIT_THREADS` threads per depth-ordered Gaussian on CUDA, each a run of its slots) writes an
   int32 key, the tile id, and the Gaussian of each reached (Gaussian, tile) pair into them, so the slots
   are in (depth, index) order (its threads also pad the unused slots of a fixed capacity and clear the
   tile ranges); the keys are sorted on their
   :func:`tile_key_bits` low bits (two 8-bit CUB passes up to 65k tiles), which keeps that order within each
   tile, and :func:`launch_tile_ranges` finds each tile's ``[start, end)`` range in the sorted list.
3. :func:`launch_composite_forward` (one 256-thread block per tile, one thread per pixel): front-to-back
   alpha compositing; the block loads batches of 256 Gaussian records into shared memory, every thread
   walks them for its pixel, and the block stops once all of its pixels are saturated. It stores the final
   transmittance and the list index of the last composited Gaussian of every pixel for the backward pass.

The backward pass:

4. :func:`launch_composite_backward` walks each pixel's list back to front from its last composited
   Gaussian, recovering the transmittance by division (the hardware's approximate reciprocal on CUDA), and
   accumulates per-Gaussian gradients of the 2D mean, conic, opacity, colour and depth; each warp sums its 32
   pixels' contributions with shuffles before one atomic add per value (native CUDA snippets; on CPU every
   thread adds its own). Two kernels share that code: one for grids of few tiles per multiprocessor and one,
   limited to 64 registers with a transposed warp sum, for many (:func:`backward_kernel_for`).
5. :func:`launch_project_backward` maps those to gradients of the means, quaternions, scales and colours
   (or SH coefficients) with Warp's automatic differentiation of the straight-line projection kernel
   :data:`project_differentiable_kernel`, which shares every ``@wp.func`` with the forward projection.

Kernels run on CPU and CUDA. On CUDA the tile kernels use ``block_dim=256``. On CPU every launcher uses
``block_dim=1`` (each pixel thread is then a block of its own; the same code stays correct, it only loads each
batch once per pixel) unless ``warp.config.enable_cpu_blocks`` is on, in which case the launchers pass
:data:`PIXELS_PER_TILE` and CPU fibers reproduce the CUDA block semantics (the tests use this mode to check
the cooperative code paths). All launches of this module on one device use one block size, so the module is
compiled once per device.
"""

from __future__ import annotations

import inspect

import warp as wp

from warpavatar.kernels.launch import launch
from .quaternion import quat_to_matrix

__all__ = [
    "TILE_SIZE",
    "PIXELS_PER_TILE",
    "GRAD_RECORD_FLOATS",
    "screen_grad_floats",
    "NEAR_PLANE",
    "FAR_PLANE",
    "BAD_MEANS",
    "BAD_QUATS",
    "BAD_SCALES",
    "BAD_OPACITIES",
    "BAD_COLORS",
    "BAD_CAMERA",
    "project_kernel",
    "emit_tile_keys_kernel",
    "tile_ranges_kernel",
    "composite_forward_kernel",
    "composite_backward_kernel",
    "composite_backward_wide_kernel",
    "WIDE_GRID_TILES_PER_SM",
    "backward_kernel_for",
    "project_differentiable_kernel",
    "launch_block_dim",
    "launch_project",
    "launch_emit_tile_keys",
    "launch_tile_ranges",
    "launch_composite_forward",
    "launch_composite_backward",
    "launch_project_backward",
    "tile_key_bits",
    "DEPTH_SORT_BITS",
    "EMIT_THREADS",
]

TILE_SIZE = wp.constant(16)
"""Side of a square pixel tile [px]; one tile is one thread block of the compositing kernels."""
PIXELS_PER_TILE = wp.constant(256)
"""Pixels (threads) per tile: ``TILE_SIZE ** 2``; also the number of Gaussians loaded per shared batch."""
NEAR_PLANE = wp.constant(0.01)
"""Gaussians with camera depth at or below this [world units] are culled (gsplat's default)."""
FAR_PLANE = wp.constant(1.0e10)
"""Gaussians with camera depth at or beyond this [world units] are culled (gsplat's default)."""
BLUR_EPS2D = wp.constant(0.3)
"""Added to the diagonal of every 2D covariance [px^2] (anti-aliasing low-pass of 3DGS)."""
ALPHA_THRESHOLD = wp.constant(1.0 / 255.0)
"""A Gaussian whose alpha at a pixel is below this is skipped there."""
ALPHA_MAX = wp.constant(0.999)
"""Alpha is clamped to this so that the transmittance stays invertible."""
TRANSMITTANCE_MIN = wp.constant(1.0e-4)
"""A pixel stops before the Gaussian that would bring its transmittance to or below this."""
SIGMA_MARGIN = wp.constant(0.05)
"""Added to the largest reachable exponent ``ln(255 opacity)`` of the extent test (see :func:`reach_sigma`)."""

GRAD_RECORD_FLOATS = 12
"""Floats of per-Gaussian screen-space gradient in the buffer written by the compositing backward.

The buffer is structure-of-arrays, ``[12 * gaussian_count]`` float32, segments in this order:
``d mean2d`` (vec2), ``d conic`` (vec3: a, b, c of ``a dx^2/2 + b dx dy + c dy^2/2``), ``d opacity``,
``d colour`` (vec3), ``d depth``, ``sum |d mean2d|`` per axis (vec2). Without the sums (no densification
statistics asked for) the buffer may end before them: :func:`screen_grad_floats`.
"""


def screen_grad_floats(with_abs: bool) -> int:
    """Floats per Gaussian the compositing backward's buffer needs: :data:`GRAD_RECORD_FLOATS`, less the two
    ``sum |d mean2d|`` floats when ``with_abs`` is False (they are then never written)."""
    return GRAD_RECORD_FLOATS if with_abs else GRAD_RECORD_FLOATS - 2

# Bits of the non-finite-input flag written by the projection kernel.
BAD_MEANS = wp.constant(1)
BAD_QUATS = wp.constant(2)
BAD_SCALES = wp.constant(4)
BAD_OPACITIES = wp.constant(8)
BAD_COLORS = wp.constant(16)
BAD_CAMERA = wp.constant(32)

# Real spherical-harmonics constants (Sloan, "Efficient Spherical Harmonic Evaluation", JCGT 2013).
SH_C0 = wp.constant(0.28209479177387814)
SH_C1 = wp.constant(0.4886025119029199)
SH_C2_XY = wp.constant(1.0925484305920792)
SH_C2_ZZ = wp.constant(0.9461746957575601)
SH_C2_ZZ_OFFSET = wp.constant(0.31539156525252005)
SH_C2_XX_YY = wp.constant(0.5462742152960396)
SH_C3_A = wp.constant(0.5900435899266435)
SH_C3_B = wp.constant(1.445305721320277)
SH_C3_C_ZZ = wp.constant(2.285228997322329)
SH_C3_C = wp.constant(0.4570457994644658)
SH_C3_D_ZZ = wp.constant(1.865881662950577)
SH_C3_D = wp.constant(1.119528997770346)


# ----------------------------------------------------------------------------------------------------------
# Projection helpers (shared by the forward kernel and the differentiable kernel)
# ----------------------------------------------------------------------------------------------------------


@wp.func
def camera_covariance(world_to_camera_rotation: wp.mat33, quat: wp.vec4, scale: wp.vec3) -> wp.mat33:
    """Camera-space 3D covariance ``W R S S^T R^T W^T`` [world units^2]."""
    transform = world_to_camera_rotation @ quat_to_matrix(wp.normalize(quat)) @ wp.diag(scale)
    return transform @ wp.transpose(transform)


@wp.func
def ewa_covariance_2d(mean_camera: wp.vec3, covariance_camera: wp.mat33, intrinsics: wp.mat33, width: float,
                      height: float) -> wp.vec3:
    """2D covariance (a, b, c) = (xx, xy, yy) [px^2] of the local affine approximation of the projection.

    In the Jacobian, ``x/z`` and ``y/z`` are clamped to the image's extent plus 0.3 times the half field of
    view on each side (1.3 times the half field of view for a centred principal point), as gsplat does.
    The 0.3 px^2 blur is not added here.
    """
    fx = intrinsics[0, 0]
    fy = intrinsics[1, 1]
    cx = intrinsics[0, 2] + 0.5  # gsplat's principal point (pixel centres at half-integers)
    cy = intrinsics[1, 2] + 0.5
    tan_half_fov_x = 0.5 * width / fx
    tan_half_fov_y = 0.5 * height / fy
    limit_x_pos = (width - cx) / fx + 0.3 * tan_half_fov_x
    limit_x_neg = cx / fx + 0.3 * tan_half_fov_x
    limit_y_pos = (height - cy) / fy + 0.3 * tan_half_fov_y
    limit_y_neg = cy / fy + 0.3 * tan_half_fov_y
    z = mean_camera[2]
    inv_z = 1.0 / z
    tx = z * wp.clamp(mean_camera[0] * inv_z, -limit_x_neg, limit_x_pos)
    ty = z * wp.clamp(mean_camera[1] * inv_z, -limit_y_neg, limit_y_pos)
    jacobian_row_x = wp.vec3(fx * inv_z, 0.0, -fx * tx * inv_z * inv_z)
    jacobian_row_y = wp.vec3(0.0, fy * inv_z, -fy * ty * inv_z * inv_z)
    cov_row_x = covariance_camera @ jacobian_row_x
    cov_row_y = covariance_camera @ jacobian_row_y
    return wp.vec3(
        wp.dot(jacobian_row_x, cov_row_x), wp.dot(jacobian_row_x, cov_row_y), wp.dot(jacobian_row_y, cov_row_y)
    )


@wp.func
def project_mean(mean_camera: wp.vec3, intrinsics: wp.mat33) -> wp.vec2:
    """Pixel position of a camera-space point, with pixel centres at half-integers (gsplat's convention)."""
    inv_z = 1.0 / mean_camera[2]
    return wp.vec2(
        intrinsics[0, 0] * mean_camera[0] * inv_z + intrinsics[0, 2] + 0.5,
        intrinsics[1, 1] * mean_camera[1] * inv_z + intrinsics[1, 2] + 0.5,
    )


@wp.func
def conic_of(covariance_2d: wp.vec3) -> wp.vec3:
    """Inverse (a, b, c) of the 2D covariance (xx, xy, yy) after adding the 0.3 px^2 blur."""
    a = covariance_2d[0] + BLUR_EPS2D
    b = covariance_2d[1]
    c = covariance_2d[2] + BLUR_EPS2D
    inv_det = 1.0 / (a * c - b * b)
    return wp.vec3(c * inv_det, -b * inv_det, a * inv_det)


@wp.func
def sh_color(coefficients: wp.array2d(dtype=wp.vec3), gaussian: int, sh_degree: int, direction: wp.vec3) -> wp.vec3:
    """RGB of real spherical harmonics of degree ``sh_degree`` (0..3) along a direction, before the offset.

    ``direction`` need not be unit: it is normalized here. Coefficient ``k`` of Gaussian ``gaussian`` is
    ``coefficients[gaussian, k]``.
    """
    d = wp.normalize(direction)
    x = d[0]
    y = d[1]
    z = d[2]
    color = SH_C0 * coefficients[gaussian, 0]
    if sh_degree >= 1:
        color += SH_C1 * (-y * coefficients[gaussian, 1] + z * coefficients[gaussian, 2] - x * coefficients[gaussian, 3])
        if sh_degree >= 2:
            zz = z * z
            c1 = x * x - y * y
            s1 = 2.0 * x * y
            color += 0.5 * SH_C2_XY * s1 * coefficients[gaussian, 4]
            color += -SH_C2_XY * z * y * coefficients[gaussian, 5]
            color += (SH_C2_ZZ * zz - SH_C2_ZZ_OFFSET) * coefficients[gaussian, 6]
            color += -SH_C2_XY * z * x * coefficients[gaussian, 7]
            color += SH_C2_XX_YY * c1 * coefficients[gaussian, 8]
            if sh_degree >= 3:
                c2 = x * c1 - y * s1
                s2 = x * s1 + y * c1
                band_c = -SH_C3_C_ZZ * zz + SH_C3_C
                color += -SH_C3_A * s2 * coefficients[gaussian, 9]
                color += SH_C3_B * z * s1 * coefficients[gaussian, 10]
                color += band_c * y * coefficients[gaussian, 11]
                color += z * (SH_C3_D_ZZ * zz - SH_C3_D) * coefficients[gaussian, 12]
                color += band_c * x * coefficients[gaussian, 13]
                color += SH_C3_B * z * c1 * coefficients[gaussian, 14]
                color += -SH_C3_A * c2 * coefficients[gaussian, 15]
    return color


@wp.func
def gaussian_color(coefficients: wp.array2d(dtype=wp.vec3), gaussian: int, sh_degree: int, mean: wp.vec3,
                   camera_center: wp.vec3) -> wp.vec3:
    """Colour of a Gaussian: its RGB when ``sh_degree < 0``, else ``max(SH(direction) + 0.5, 0)``."""
    if sh_degree < 0:
        return coefficients[gaussian, 0]
    value = sh_color(coefficients, gaussian, sh_degree, mean - camera_center) + wp.vec3(0.5)
    return wp.vec3(wp.max(value[0], 0.0), wp.max(value[1], 0.0), wp.max(value[2], 0.0))


@wp.func
def camera_center_of(world_to_camera: wp.mat44) -> wp.vec3:
    """Camera centre in world coordinates, ``-R^T t``."""
    rotation = wp.mat33(
        world_to_camera[0, 0], world_to_camera[0, 1], world_to_camera[0, 2],
        world_to_camera[1, 0], world_to_camera[1, 1], world_to_camera[1, 2],
        world_to_camera[2, 0], world_to_camera[2, 1], world_to_camera[2, 2],
    )  # fmt: skip
    translation = wp.vec3(world_to_camera[0, 3], world_to_camera[1, 3], world_to_camera[2, 3])
    return -(wp.transpose(rotation) @ translation)


@wp.func
def rotation_of(world_to_camera: wp.mat44) -> wp.mat33:
    """Upper-left 3x3 block of a 4x4 rigid transform."""
    return wp.mat33(
        world_to_camera[0, 0], world_to_camera[0, 1], world_to_camera[0, 2],
        world_to_camera[1, 0], world_to_camera[1, 1], world_to_camera[1, 2],
        world_to_camera[2, 0], world_to_camera[2, 1], world_to_camera[2, 2],
    )  # fmt: skip


@wp.func
def to_camera(world_to_camera: wp.mat44, point: wp.vec3) -> wp.vec3:
    """Camera-space coordinates of a world point."""
    return rotation_of(world_to_camera) @ point + wp.vec3(
        world_to_camera[0, 3], world_to_camera[1, 3], world_to_camera[2, 3]
    )


@wp.func
def tile_box(center: wp.vec2, radius: wp.vec2i, tiles_x: int, tiles_y: int) -> wp.vec4i:
    """Tiles ``[x0, x1) x [y0, y1)`` overlapped by the box ``center +- radius`` [px], clamped to the image."""
    rx = float(radius[0]) / float(TILE_SIZE)
    ry = float(radius[1]) / float(TILE_SIZE)
    tx = center[0] / float(TILE_SIZE)
    ty = center[1] / float(TILE_SIZE)
    x0 = wp.clamp(wp.floor(tx - rx), 0.0, float(tiles_x))
    x1 = wp.clamp(wp.ceil(tx + rx), 0.0, float(tiles_x))
    y0 = wp.clamp(wp.floor(ty - ry), 0.0, float(tiles_y))
    y1 = wp.clamp(wp.ceil(ty + ry), 0.0, float(tiles_y))
    return wp.vec4i(int(x0), int(x1), int(y0), int(y1))


@wp.func
def reach_sigma(opacity: float) -> float:
    """Largest exponent ``sigma = d^T conic d / 2`` at which a Gaussian of this opacity can still be composited.

    The compositing kernels take a Gaussian at a pixel only when ``sigma >= 0`` and
    ``min(ALPHA_MAX, opacity * exp(-sigma)) >= ALPHA_THRESHOLD``, i.e. ``sigma <= ln(255 opacity)`` in exact
    arithmetic (the clamp only lowers alpha, and ALPHA_MAX > ALPHA_THRESHOLD). The caller culls a Gaussian with
    ``opacity < ALPHA_THRESHOLD``: its alpha is below the threshold everywhere (``exp(-sigma) <= 1``).

    ``SIGMA_MARGIN`` (0.05, about 1 % of ``ln 255``, a box 0.5 % wider) covers the float32 rounding of the
    compositing's test: ``__expf`` is within 9 ulp (1.1e-6 relative) for ``|x| <= 6``, which moves the limit by
    1.1e-6; the float32 ``sigma`` of a pixel on the ellipse ``sigma = s`` is off by at most about
    ``4 eps s / (1 - rho^2)`` (eps = 6e-8, rho the 2D correlation; the terms of the quadratic form cancel for
    thin diagonal ellipses). The 0.3 px^2 blur bounds ``1 / (1 - rho^2)`` by ``lambda_max / 0.3``, so the margin
    covers every Gaussian whose major standard deviation is below about 100 px; beyond that a pixel where the
    float32 alpha sits within rounding of 1/255 may be skipped, a change of at most 1/255 of one colour there.
    """
    return wp.log(opacity / ALPHA_THRESHOLD) + SIGMA_MARGIN


@wp.func
def row_tile_span(center: wp.vec2, conic: wp.vec3, max_sigma: float, tile_y: int, box: wp.vec4i, width: int,
                  height: int) -> wp.vec2i:
    """Tiles ``[x0, x1)`` of tile row ``tile_y`` (within ``box``) whose pixel centres the ellipse
    ``sigma <= max_sigma`` meets, ``sigma = (a dx^2 + c dy^2) / 2 + b dx dy`` for ``conic = (a, b, c)``.

    The ellipse's part in the row's band of pixel-centre rows ``dy in [dy_lo, dy_hi]`` is convex, so its x
    extent is an interval and a tile is met exactly when its pixel-centre columns meet that interval. For a
    fixed ``dy`` the ellipse spans ``dx = -(b / a) dy +- h(dy)``, ``h = sqrt((2 max_sigma - (det / a) dy^2) / a)``
    (``det = a c - b^2``); the right end is concave in ``dy`` with its maximum (the ellipse's rightmost point) at
    ``dy_r = -b sqrt(2 max_sigma / (c det))``, the left end convex with its minimum at ``-dy_r``, so the band's
    extent is the ends at those points clamped to the band (cut to ``|dy| <= sqrt(2 max_sigma a / det)``).
    O(1) per row: the projection counts a Gaussian's tiles in O(rows) and the emission in O(rows + pairs).
    """
    a = conic[0]
    b = conic[1]
    c = conic[2]
    det = a * c - b * b
    row_lo = tile_y * TILE_SIZE
    row_hi = wp.min(row_lo + TILE_SIZE, height) - 1
    reach_y = wp.sqrt(2.0 * max_sigma * a / det)
    dy_lo = wp.max(float(row_lo) + 0.5 - center[1], -reach_y)
    dy_hi = wp.min(float(row_hi) + 0.5 - center[1], reach_y)
    if dy_lo > dy_hi:
        return wp.vec2i(0, 0)
    dy_right = -b * wp.sqrt(2.0 * max_sigma / (c * det))
    dy = wp.clamp(dy_right, dy_lo, dy_hi)
    x_max = center[0] - b / a * dy + wp.sqrt(wp.max(2.0 * max_sigma - det / a * dy * dy, 0.0) / a)
    dy = wp.clamp(-dy_right, dy_lo, dy_hi)
    x_min = center[0] - b / a * dy - wp.sqrt(wp.max(2.0 * max_sigma - det / a * dy * dy, 0.0) / a)
    # Pixel columns whose centres (column + 0.5) lie in [x_min, x_max], as tiles, within the box.
    column_first = wp.max(wp.ceil(x_min - 0.5), 0.0)
    column_last = wp.min(wp.floor(x_max - 0.5), float(width - 1))
    if column_first > column_last:
        return wp.vec2i(0, 0)
    x0 = wp.max(int(column_first) // TILE_SIZE, box[0])
    x1 = wp.min(int(column_last) // TILE_SIZE + 1, box[1])
    return wp.vec2i(x0, wp.max(x0, x1))


@wp.func
def finite_vec3(v: wp.vec3) -> bool:
    return wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])


# ----------------------------------------------------------------------------------------------------------
# 1. Projection
# ----------------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def project_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=wp.float32),
    coefficients: wp.array2d(dtype=wp.vec3),
    intrinsics: wp.array(dtype=wp.mat33),
    world_to_camera: wp.array(dtype=wp.mat44),
    width: int,
    height: int,
    tiles_x: int,
    tiles_y: int,
    sh_degree: int,
    used_coefficients: int,
    xy_opacity: wp.array(dtype=wp.vec3),
    conics: wp.array(dtype=wp.vec3),
    color_depth: wp.array(dtype=wp.vec4),
    radii: wp.array(dtype=wp.vec2i),
    depth_keys: wp.array(dtype=wp.float32),
    depth_order: wp.array(dtype=wp.vec2i),
    bad_input_flags: wp.array(dtype=wp.int32),
):
    """Project every Gaussian; culled ones get radius (0, 0), no tiles and zero mean2d, conic and colour.

    Outputs per Gaussian: ``xy_opacity`` (pixel x, y with pixel centres at half-integers, opacity),
    ``conics`` (a, b, c), ``color_depth`` (r, g, b, camera z), ``radii`` [px], and the depth sort's inputs:
    ``depth_keys`` (the camera z [world units] of a Gaussian that reaches a tile, else ``FAR_PLANE``, which
    sorts after every kept depth) and ``depth_order`` (the record (Gaussian index, tiles touched)).
    ``bad_input_flags[0]`` gets the ``BAD_*`` bits of the inputs holding non-finite values.
    """
    i = wp.tid()
    mean = means[i]
    quat = quats[i]
    scale = scales[i]
    opacity = opacities[i]
    K = intrinsics[0]
    view = world_to_camera[0]

    flags = int(0)
    if not finite_vec3(mean):
        flags = flags | BAD_MEANS
    if not (wp.isfinite(quat[0]) and wp.isfinite(quat[1]) and wp.isfinite(quat[2]) and wp.isfinite(quat[3])):
        flags = flags | BAD_QUATS
    if not finite_vec3(scale):
        flags = flags | BAD_SCALES
    if not wp.isfinite(opacity):
        flags = flags | BAD_OPACITIES
    for k in range(used_coefficients):
        if not finite_vec3(coefficients[i, k]):
            flags = flags | BAD_COLORS
    if i == 0:
        for r in range(3):
            if not finite_vec3(wp.vec3(K[r, 0], K[r, 1], K[r, 2])):
                flags = flags | BAD_CAMERA
        for r in range(4):
            if not (finite_vec3(wp.vec3(view[r, 0], view[r, 1], view[r, 2])) and wp.isfinite(view[r, 3])):
                flags = flags | BAD_CAMERA
    if flags != 0:
        wp.atomic_or(bad_input_flags, 0, flags)

    # Culled Gaussians keep zeros everywhere except their depth; the rest is written once at the end.
    center = wp.vec2(0.0)
    conic = wp.vec3(0.0)
    color = wp.vec3(0.0)
    radius = wp.vec2i(0, 0)
    touched = int(0)
    mean_camera = to_camera(view, mean)
    depth = mean_camera[2]
    if depth > NEAR_PLANE and depth < FAR_PLANE:
        covariance_2d = ewa_covariance_2d(
            mean_camera, camera_covariance(rotation_of(view), quat, scale), K, float(width), float(height)
        )
        a = covariance_2d[0] + BLUR_EPS2D
        c = covariance_2d[2] + BLUR_EPS2D
        det = a * c - covariance_2d[1] * covariance_2d[1]
        if det > 0.0 and opacity >= ALPHA_THRESHOLD:
            # The box of the ellipse sigma <= max_sigma: half-widths sqrt(2 max_sigma Sigma_xx), ... (Sigma
            # blurred); pixel centres are half-integers and tile edges integers, so no centre of the box lies
            # on a tile edge and tile_box's floor / ceil keep every tile holding one.
            max_sigma = reach_sigma(opacity)
            radius_x = wp.ceil(wp.sqrt(2.0 * max_sigma * a))
            radius_y = wp.ceil(wp.sqrt(2.0 * max_sigma * c))
            projected = project_mean(mean_camera, K)
            if (
                projected[0] + radius_x > 0.0
                and projected[0] - radius_x < float(width)
                and projected[1] + radius_y > 0.0
                and projected[1] - radius_y < float(height)
            ):
                center = projected
                conic = conic_of(covariance_2d)
                radius = wp.vec2i(int(radius_x), int(radius_y))
                box = tile_box(center, radius, tiles_x, tiles_y)
                color = gaussian_color(coefficients, i, sh_degree, mean, camera_center_of(view))
                for ty in range(box[2], box[3]):
                    span = row_tile_span(center, conic, max_sigma, ty, box, width, height)
                    touched += span[1] - span[0]
    xy_opacity[i] = wp.vec3(center[0], center[1], opacity)
    conics[i] = conic
    color_depth[i] = wp.vec4(color[0], color[1], color[2], depth)
    radii[i] = radius
    if touched > 0:
        depth_keys[i] = depth
    else:
        depth_keys[i] = FAR_PLANE
    depth_order[i] = wp.vec2i(i, touched)


def launch_block_dim(device) -> int:
    """Block size the launchers of this module use on ``device`` (one size per device, see module doc)."""
    device = wp.get_device(device)
    if device.is_cuda or wp.config.enable_cpu_blocks:
        return int(PIXELS_PER_TILE)
    return 1


def _device_of(array):
    """The device a launch with ``array`` runs on: a ``wp.array``'s own, or, for a launch descriptor
    (``warp_utils.warp_descriptor``, which carries no device), Warp's current device, where ``wp.launch`` runs
    it."""
    return getattr(array, "device", None)


def launch_project(
    means, quats, scales, opacities, coefficients, intrinsics, world_to_camera, *, width: int, height: int,
    sh_degree: int, used_coefficients: int, xy_opacity, conics, color_depth, radii, depth_keys, depth_order,
    bad_input_flags,
) -> None:
    """Launch :data:`project_kernel` over ``len(means)`` Gaussians (see the kernel for the arrays).

    ``coefficients`` is ``[gaussian_count, coefficient_count]`` of vec3 (coefficient_count is 1 for RGB with
    ``sh_degree=-1``); ``intrinsics`` and ``world_to_camera`` hold one mat33 / mat44 each. ``depth_keys``
    (float32) and ``depth_order`` (vec2i) are the first halves of the depth sort's double buffers.
    """
    gaussian_count = means.shape[0]
    for name, array in (("quats", quats), ("scales", scales), ("opacities", opacities), ("xy_opacity", xy_opacity),
                        ("conics", conics), ("color_depth", color_depth), ("radii", radii),
                        ("depth_keys", depth_keys), ("depth_order", depth_order)):
        if array.shape[0] != gaussian_count:
            raise ValueError(f"{name} has {array.shape[0]} entries, expected {gaussian_count}")
    if coefficients.shape[0] != gaussian_count or coefficients.shape[1] < used_coefficients:
        raise ValueError(f"coefficients has shape {coefficients.shape}, expected [{gaussian_count}, >= {used_coefficients}]")
    if gaussian_count == 0:
        return
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    launch(
        project_kernel,
        dim=gaussian_count,
        inputs=[means, quats, scales, opacities, coefficients, intrinsics, world_to_camera, width, height, tiles_x,
                tiles_y, sh_degree, used_coefficients],
        outputs=[xy_opacity, conics, color_depth, radii, depth_keys, depth_order, bad_input_flags],
        block_dim=launch_block_dim(_device_of(means)),
    )


# ----------------------------------------------------------------------------------------------------------
# 2. Tile binning
# ----------------------------------------------------------------------------------------------------------


DEPTH_SORT_BITS = 31
"""Low bits of the depth sort's float32 keys to radix-sort (``end_bit`` of ``wp.utils.radix_sort_pairs``).

The keys are positive floats, depths in (NEAR_PLANE, FAR_PLANE] = (0.01, 1e10]: their sign bit is clear and
the other 31 bits order like the values (the sort reads a float's bits as an integer, the sign bit flipped, so
the high bits it skips are the same for every key). Fewer would not do: the keys' bits span 0x3C23D70A to
0x501502F9. CUB sorts 31 bits in as many 8-bit digit passes (four) as 29.
"""


def tile_key_bits(tile_count: int) -> int:
    """Low bits of the tile sort's int32 keys to radix-sort: a tile id, or the padding id ``tile_count`` of
    :data:`emit_tile_keys_kernel`, which fits too and sorts after every tile."""
    return max(int(tile_count).bit_length(), 1)


EMIT_THREADS = 8
"""Threads that emit one Gaussian's pairs on CUDA (:data:`emit_tile_keys_kernel`; one on a CPU, where threads do
not wait for each other): thread ``r`` of a Gaussian writes the ``r``-th of eight equal runs of its slots. Large
Gaussians (a close-up at 1080p lists dozens of tiles each) then write their pairs eight at a time instead of one
thread writing them all while the rest of its warp waits."""


@wp.kernel(enable_backward=False)
def emit_tile_keys_kernel(
    xy_opacity: wp.array(dtype=wp.vec3),
    conics: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=wp.vec2i),
    depth_order: wp.array(dtype=wp.vec2i),
    tile_ends: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tiles_x: int,
    tiles_y: int,
    threads_per_gaussian: int,
    keys: wp.array(dtype=wp.int32),
    gaussian_ids: wp.array(dtype=wp.int32),
    tile_ranges: wp.array2d(dtype=wp.int32),
):
    """Threads ``P j`` to ``P (j + 1) - 1`` (``P = threads_per_gaussian``) write the tile id (key) and the Gaussian
    of every pair of the ``j``-th Gaussian in depth order into its slots ``[tile_ends[j] - count, tile_ends[j])``,
    its tiles in increasing id (row by row): each thread walks the Gaussian's rows for their spans (a few flops
    each) and writes the pairs that fall in its run of the slots (``ceil(count / P)`` slots each), so each pair
    still lands in the slot of its rank.

    ``depth_order[j]`` is the depth-sorted record (Gaussian, tile count) and ``tile_ends`` the inclusive prefix
    sum of those counts. A pair is emitted for each tile of the radius box in the rows' :func:`row_tile_span`,
    the spans that :data:`project_kernel` counted with. Should the spans ever hold fewer tiles here than when
    counting (a compiler contracting the arithmetic differently in the two kernels), the rest of the
    Gaussian's slots get the tile id ``tiles_x * tiles_y``, which sorts last and :data:`tile_ranges_kernel`
    ignores; more are never written. Nothing is written past the end of ``keys`` (buffers sized by a capacity
    below the pair count), and the slots past the pair count (buffers of a larger capacity) get the padding
    key ``tiles_x * tiles_y`` and Gaussian -1, shared out over the threads (slot ``pair count + t + k T``, ``T``
    threads). The threads also clear ``tile_ranges`` ([tiles, 2], for :data:`tile_ranges_kernel`, which writes
    only the tiles present), in the same way: one torch fill less a pass.
    """
    t = wp.tid()
    gaussian_count = depth_order.shape[0]
    thread_count = gaussian_count * threads_per_gaussian
    slot_count = keys.shape[0]
    tile_count = tiles_x * tiles_y
    padding = tile_ends[gaussian_count - 1] + t
    while padding < slot_count:
        keys[padding] = tile_count
        gaussian_ids[padding] = -1
        padding += thread_count
    tile = t
    while tile < tile_count:
        tile_ranges[tile, 0] = 0
        tile_ranges[tile, 1] = 0
        tile += thread_count
    j = t // threads_per_gaussian
    run = t - j * threads_per_gaussian
    record = depth_order[j]
    i = record[0]
    first = tile_ends[j] - record[1]
    run_length = (record[1] + threads_per_gaussian - 1) // threads_per_gaussian
    run_start = first + run * run_length  # this thread's slots: [run_start, run_end)
    run_end = wp.min(wp.min(run_start + run_length, tile_ends[j]), slot_count)
    if run_start >= run_end:
        return  # no tile, a short Gaussian's spare thread, or every slot past the capacity
    xyo = xy_opacity[i]
    center = wp.vec2(xyo[0], xyo[1])
    conic = conics[i]
    max_sigma = reach_sigma(xyo[2])
    box = tile_box(center, radii[i], tiles_x, tiles_y)
    slot = first
    for ty in range(box[2], box[3]):
        if slot >= run_end:
            break
        span = row_tile_span(center, conic, max_sigma, ty, box, width, height)
        row_end = slot + span[1] - span[0]
        if row_end > run_start:
            for s in range(wp.max(slot, run_start), wp.min(row_end, run_end)):
                keys[s] = ty * tiles_x + span[0] + s - slot
                gaussian_ids[s] = i
        slot = row_end
    for s in range(wp.max(slot, run_start), run_end):  # spans shorter than counted: padding of this Gaussian
        keys[s] = tile_count
        gaussian_ids[s] = i


def launch_emit_tile_keys(xy_opacity, conics, radii, depth_order, tile_ends, *, width: int, height: int, keys,
                          gaussian_ids, tile_ranges, threads_per_gaussian: int | None = None) -> None:
    """Launch :data:`emit_tile_keys_kernel` over the depth-ordered Gaussians, ``threads_per_gaussian`` threads each
    (default: :data:`EMIT_THREADS` on CUDA, 1 on a CPU; the pairs are the same for any count >= 1).

    ``xy_opacity``, ``conics`` and ``radii`` are :data:`project_kernel`'s outputs (indexed by Gaussian),
    ``depth_order`` the first half of the depth sort's values after the sort and ``tile_ends`` the inclusive
    prefix sum of its counts (both indexed by depth rank). ``keys`` / ``gaussian_ids`` (int32, the first
    halves of the tile sort's double buffers) hold the pair count (``tile_ends[-1]``) or a fixed capacity:
    pairs beyond their length are dropped, not written out of bounds, and slots past the pair count padded.
    ``tile_ranges`` ([tiles, 2] int32) is cleared; without Gaussians or slots nothing is launched and the
    caller clears it.
    """
    gaussian_count = xy_opacity.shape[0]
    for name, array in (("conics", conics), ("radii", radii), ("depth_order", depth_order),
                        ("tile_ends", tile_ends)):
        if array.shape[0] != gaussian_count:
            raise ValueError(f"{name} has {array.shape[0]} entries, expected {gaussian_count}")
    if keys.shape[0] != gaussian_ids.shape[0]:
        raise ValueError("keys and gaussian_ids must have the same length")
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    if tile_ranges.ndim != 2 or tile_ranges.shape[0] != tiles_x * tiles_y or tile_ranges.shape[1] != 2:
        raise ValueError(f"tile_ranges must be an int32 array of shape [{tiles_x * tiles_y}, 2]")
    if gaussian_count == 0 or keys.shape[0] == 0:
        return
    device = wp.get_device(_device_of(keys))
    if threads_per_gaussian is None:
        threads_per_gaussian = EMIT_THREADS if device.is_cuda else 1
    if threads_per_gaussian < 1:
        raise ValueError(f"threads_per_gaussian must be >= 1, got {threads_per_gaussian}")
    launch(
        emit_tile_keys_kernel,
        dim=gaussian_count * threads_per_gaussian,
        inputs=[xy_opacity, conics, radii, depth_order, tile_ends, width, height, tiles_x, tiles_y,
                threads_per_gaussian],
        outputs=[keys, gaussian_ids, tile_ranges],
        block_dim=launch_block_dim(_device_of(keys)),
    )


@wp.kernel(enable_backward=False)
def tile_ranges_kernel(sorted_keys: wp.array(dtype=wp.int32), pair_count: int, tile_ranges: wp.array2d(dtype=wp.int32)):
    """Write ``[start, end)`` of every tile present in the sorted tile keys (``tile_ranges`` starts zeroed)."""
    i = wp.tid()
    tile_count = tile_ranges.shape[0]
    tile = sorted_keys[i]
    if tile >= tile_count:
        return  # padding of emit_tile_keys_kernel, sorted after every real tile
    if i == 0:
        tile_ranges[tile, 0] = 0
    else:
        previous = sorted_keys[i - 1]
        if previous != tile:
            tile_ranges[tile, 0] = i
            tile_ranges[previous, 1] = i
    if i == pair_count - 1:
        tile_ranges[tile, 1] = pair_count
    else:
        following = sorted_keys[i + 1]
        if following >= tile_count:
            tile_ranges[tile, 1] = i + 1


def launch_tile_ranges(sorted_keys, pair_count: int, tile_ranges) -> None:
    """Launch :data:`tile_ranges_kernel` over the first ``pair_count`` sorted keys."""
    if sorted_keys.shape[0] < pair_count:
        raise ValueError(f"sorted_keys has {sorted_keys.shape[0]} entries, fewer than pair_count={pair_count}")
    if tile_ranges.ndim != 2 or tile_ranges.shape[1] != 2:
        raise ValueError("tile_ranges must be an int32 array of shape [tile_count, 2]")
    if pair_count == 0:
        return
    launch(tile_ranges_kernel, dim=pair_count, inputs=[sorted_keys, pair_count], outputs=[tile_ranges],
              block_dim=launch_block_dim(_device_of(sorted_keys)))


# ----------------------------------------------------------------------------------------------------------
# 3. Compositing, forward
# ----------------------------------------------------------------------------------------------------------


# exp for the per-pixel falloff: the fast hardware approximation on CUDA (as gsplat uses), exp on CPU.
_FAST_EXP_SNIPPET = r"""
#if defined(__CUDA_ARCH__)
    return __expf(x);
#else
    return wp::exp(x);
#endif
"""


@wp.func_native(_FAST_EXP_SNIPPET)
def fast_exp(x: float) -> float: ...


@wp.func
def gaussian_alpha(xyo: wp.vec3, conic: wp.vec3, pixel_x: float, pixel_y: float) -> wp.vec3:
    """(alpha, sigma, exp(-sigma)) of a Gaussian record at a pixel centre; alpha is clamped to 0.999."""
    dx = xyo[0] - pixel_x
    dy = xyo[1] - pixel_y
    sigma = 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
    falloff = fast_exp(-sigma)
    return wp.vec3(wp.min(ALPHA_MAX, xyo[2] * falloff), sigma, falloff)


@wp.func
def tile_pixel(tile: int, lane: int, tiles_x: int):
    """Column and row of the pixel that thread ``lane`` of tile ``tile`` (row-major, ``tiles_x`` a row) owns."""
    tile_row = tile // tiles_x
    return (tile - tile_row * tiles_x) * TILE_SIZE + lane % TILE_SIZE, tile_row * TILE_SIZE + lane // TILE_SIZE


@wp.kernel(enable_backward=False)
def composite_forward_kernel(
    tile_ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    xy_opacity: wp.array(dtype=wp.vec3),
    conics: wp.array(dtype=wp.vec3),
    color_depth: wp.array(dtype=wp.vec4),
    background: wp.array(dtype=wp.vec3),
    width: int,
    height: int,
    tiles_x: int,
    pixel_state: int,
    image: wp.array(dtype=wp.vec3),
    alpha: wp.array(dtype=wp.float32),
    depth: wp.array(dtype=wp.float32),
    final_transmittance: wp.array(dtype=wp.float32),
    last_index: wp.array(dtype=wp.int32),
):
    """Front-to-back compositing of one pixel per thread, one tile per block (launch dim [tiles, 256]).

    Per pixel (row-major ``y * width + x``): ``image`` = sum w_i c_i + T background, ``alpha`` = 1 - T,
    ``depth`` = sum w_i z_i and, when ``pixel_state`` is nonzero (what the backward pass reads),
    ``final_transmittance`` = T and ``last_index`` = position in the sorted list of the last composited Gaussian
    (-1 when none).
    """
    tile, lane = wp.tid()
    pixel_x, pixel_y = tile_pixel(tile, lane, tiles_x)
    inside = pixel_x < width and pixel_y < height
    center_x = float(pixel_x) + 0.5
    center_y = float(pixel_y) + 0.5

    range_start = tile_ranges[tile, 0]
    range_end = tile_ranges[tile, 1]
    batch_count = (range_end - range_start + PIXELS_PER_TILE - 1) // PIXELS_PER_TILE

    transmittance = float(1.0)
    color = wp.vec3(0.0)
    depth_sum = float(0.0)
    last = int(-1)
    done = int(1)
    if inside:
        done = 0
    for batch in range(batch_count):
        # Stop the whole block once every pixel is saturated (the count is block-uniform).
        done_count = wp.tile_sum(wp.tile(done))
        if done_count[0] == wp.block_dim():
            break
        batch_start = range_start + batch * PIXELS_PER_TILE
        ids = wp.tile_load(sorted_ids, shape=PIXELS_PER_TILE, offset=batch_start, storage="shared")
        batch_xyo = wp.tile_load_indexed(xy_opacity, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                         storage="shared")
        batch_conic = wp.tile_load_indexed(conics, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                           storage="shared")
        batch_color = wp.tile_load_indexed(color_depth, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                           storage="shared")
        batch_size = wp.min(PIXELS_PER_TILE, range_end - batch_start)
        for k in range(batch_size):
            if done != 0:
                break
            evaluated = gaussian_alpha(batch_xyo[k], batch_conic[k], center_x, center_y)
            a = evaluated[0]
            if evaluated[1] < 0.0 or a < ALPHA_THRESHOLD:
                continue
            next_transmittance = transmittance * (1.0 - a)
            if next_transmittance <= TRANSMITTANCE_MIN:
                done = 1
                break
            weight = a * transmittance
            rgbd = batch_color[k]
            color += weight * wp.vec3(rgbd[0], rgbd[1], rgbd[2])
            depth_sum += weight * rgbd[3]
            transmittance = next_transmittance
            last = batch_start + k
    if inside:
        pixel = pixel_y * width + pixel_x
        image[pixel] = color + transmittance * background[0]
        alpha[pixel] = 1.0 - transmittance
        depth[pixel] = depth_sum
        if pixel_state != 0:
            final_transmittance[pixel] = transmittance
            last_index[pixel] = last


def _check_pixel_arrays(width: int, height: int, **arrays) -> None:
    for name, array in arrays.items():
        if array.shape[0] != width * height:
            raise ValueError(f"{name} has {array.shape[0]} entries, expected width * height = {width * height}")


def launch_composite_forward(tile_ranges, sorted_ids, xy_opacity, conics, color_depth, background, *, width: int,
                             height: int, image, alpha, depth, final_transmittance, last_index,
                             pixel_state: bool = True) -> None:
    """Launch :data:`composite_forward_kernel` over all tiles of a ``width`` x ``height`` image.

    ``background`` holds one vec3; the pixel arrays are flat (``width * height`` entries). ``pixel_state=False``
    (no backward pass will run) leaves ``final_transmittance`` and ``last_index`` unwritten: 8 bytes a pixel
    less to store.
    """
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    if tile_ranges.shape[0] != tiles_x * tiles_y:
        raise ValueError(f"tile_ranges has {tile_ranges.shape[0]} rows, expected {tiles_x * tiles_y} tiles")
    _check_pixel_arrays(width, height, image=image, alpha=alpha, depth=depth, final_transmittance=final_transmittance,
                        last_index=last_index)
    if width * height == 0:
        return
    launch(
        composite_forward_kernel,
        dim=(tiles_x * tiles_y, int(PIXELS_PER_TILE)),
        inputs=[tile_ranges, sorted_ids, xy_opacity, conics, color_depth, background, width, height, tiles_x,
                int(pixel_state)],
        outputs=[image, alpha, depth, final_transmittance, last_index],
        block_dim=launch_block_dim(_device_of(image)),
    )


# ----------------------------------------------------------------------------------------------------------
# 4. Compositing, backward
# ----------------------------------------------------------------------------------------------------------

# The warp-sum snippets' shared parts: one Gaussian's gradient values as locals, and their atomic adds into the
# structure-of-arrays buffer (layout: GRAD_RECORD_FLOATS).
_RECORD_VALUES = r"""
    float m0 = v_mean2d[0], m1 = v_mean2d[1];
    float c0 = v_conic[0], c1 = v_conic[1], c2 = v_conic[2];
    float o0 = v_opacity;
    float r0 = v_color[0], r1 = v_color[1], r2 = v_color[2];
    float d0 = v_depth;
    float a0 = wp::abs(m0), a1 = wp::abs(m1);
"""

_ADD_RECORD = r"""
    const long long n = (long long)gaussian_count;
    const long long g = (long long)gaussian;
    float* base = grads.data;
    wp::atomic_add(base + 2 * g, m0);
    wp::atomic_add(base + 2 * g + 1, m1);
    wp::atomic_add(base + 2 * n + 3 * g, c0);
    wp::atomic_add(base + 2 * n + 3 * g + 1, c1);
    wp::atomic_add(base + 2 * n + 3 * g + 2, c2);
    wp::atomic_add(base + 5 * n + g, o0);
    wp::atomic_add(base + 6 * n + 3 * g, r0);
    wp::atomic_add(base + 6 * n + 3 * g + 1, r1);
    wp::atomic_add(base + 6 * n + 3 * g + 2, r2);
    wp::atomic_add(base + 9 * n + g, d0);
    if (with_abs) {
        wp::atomic_add(base + 10 * n + 2 * g, a0);
        wp::atomic_add(base + 10 * n + 2 * g + 1, a1);
    }
"""

# Sums one Gaussian's gradient contributions over the 32 lanes of each warp, then lane 0 adds them to the buffer
# (on CPU every thread adds its own). Every lane of a warp must reach the call together; the caller guarantees it
# by iterating block-uniform loops and passing ``active = 0`` from idle lanes.
_WARP_SUM_ADD_SNIPPET = _RECORD_VALUES + r"""#if defined(__CUDA_ARCH__)
    const unsigned int full_mask = 0xffffffffu;
    if (__any_sync(full_mask, active != 0) == 0)
        return;
    auto warp_sum = [full_mask](float v) {
        #pragma unroll
        for (int offset = 16; offset > 0; offset >>= 1)
            v += __shfl_down_sync(full_mask, v, offset);
        return v;
    };
    m0 = warp_sum(m0); m1 = warp_sum(m1);
    c0 = warp_sum(c0); c1 = warp_sum(c1); c2 = warp_sum(c2);
    o0 = warp_sum(o0);
    r0 = warp_sum(r0); r1 = warp_sum(r1); r2 = warp_sum(r2);
    d0 = warp_sum(d0);
    if (with_abs) {
        a0 = warp_sum(a0);
        a1 = warp_sum(a1);
    }
    if ((threadIdx.x & 31) != 0)
        return;
#else
    if (!active)
        return;
#endif
""" + _ADD_RECORD


@wp.func_native(_WARP_SUM_ADD_SNIPPET)
def warp_sum_atomic_add(
    grads: wp.array(dtype=wp.float32),
    gaussian_count: int,
    gaussian: int,
    active: int,
    with_abs: int,
    v_mean2d: wp.vec2,
    v_conic: wp.vec3,
    v_opacity: float,
    v_color: wp.vec3,
    v_depth: float,
): ...


# The same sum and add as _WARP_SUM_ADD_SNIPPET with fewer instructions, for the wide-grid kernel. The up to 12
# values are reduced by recursive halving ("transpose" reduction): at each of the five butterfly steps a lane
# keeps half of its values and swaps the other half with its partner, so the warp makes 8 + 4 + 2 + 1 + 1 = 16
# shuffles instead of 5 per value (60), and ends with lane pair (2j, 2j+1) holding the whole warp's sum of value
# j, which the even lanes add to the buffer together (one atomic instruction instead of 12 issued one after
# another by lane 0). Measured on an H100/H200 it is the faster of the two at 64 registers a thread (4 blocks a
# multiprocessor) and the slower at 96 (2 blocks), which is why each kernel has its own.
_WARP_SUM_ADD_TRANSPOSED_SNIPPET = r"""
#if defined(__CUDA_ARCH__)
    const unsigned int full_mask = 0xffffffffu;
    if (__any_sync(full_mask, active != 0) == 0)
        return;
    const unsigned int lane = threadIdx.x & 31u;
    float v[16] = {v_mean2d[0], v_mean2d[1], v_conic[0], v_conic[1], v_conic[2], v_opacity,
                   v_color[0], v_color[1], v_color[2], v_depth, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    if (with_abs) {
        v[10] = wp::abs(v_mean2d[0]);
        v[11] = wp::abs(v_mean2d[1]);
    }
    // Four halving steps keeping 8, 4, 2, 1 values: the lane whose bit 16, 8, 4, 2 is set keeps the upper half.
    // (Constant trip counts, so that v stays in registers.)
    bool upper = (lane & 16u) != 0;
    #pragma unroll
    for (int i = 0; i < 8; ++i)
        v[i] = (upper ? v[i + 8] : v[i]) + __shfl_xor_sync(full_mask, upper ? v[i] : v[i + 8], 16);
    upper = (lane & 8u) != 0;
    #pragma unroll
    for (int i = 0; i < 4; ++i)
        v[i] = (upper ? v[i + 4] : v[i]) + __shfl_xor_sync(full_mask, upper ? v[i] : v[i + 4], 8);
    upper = (lane & 4u) != 0;
    #pragma unroll
    for (int i = 0; i < 2; ++i)
        v[i] = (upper ? v[i + 2] : v[i]) + __shfl_xor_sync(full_mask, upper ? v[i] : v[i + 2], 4);
    upper = (lane & 2u) != 0;
    v[0] = (upper ? v[1] : v[0]) + __shfl_xor_sync(full_mask, upper ? v[0] : v[1], 2);
    const float total = v[0] + __shfl_xor_sync(full_mask, v[0], 1);
    if (lane & 1u)
        return;
    // Lane 2j holds value j (j from the lane's bits 4..1, most significant first).
    const int j = ((lane >> 4) & 1) * 8 + ((lane >> 3) & 1) * 4 + ((lane >> 2) & 1) * 2 + ((lane >> 1) & 1);
    if (j >= (with_abs ? 12 : 10))
        return;
    const long long n = (long long)gaussian_count;
    const long long g = (long long)gaussian;
    long long offset;
    if (j < 2)
        offset = 2 * g + j;
    else if (j < 5)
        offset = 2 * n + 3 * g + (j - 2);
    else if (j == 5)
        offset = 5 * n + g;
    else if (j < 9)
        offset = 6 * n + 3 * g + (j - 6);
    else if (j == 9)
        offset = 9 * n + g;
    else
        offset = 10 * n + 2 * g + (j - 10);
    wp::atomic_add(grads.data + offset, total);
#else
""" + _RECORD_VALUES + r"""
    if (!active)
        return;
""" + _ADD_RECORD + r"""
#endif
"""


@wp.func_native(_WARP_SUM_ADD_TRANSPOSED_SNIPPET)
def warp_sum_atomic_add_transposed(
    grads: wp.array(dtype=wp.float32),
    gaussian_count: int,
    gaussian: int,
    active: int,
    with_abs: int,
    v_mean2d: wp.vec2,
    v_conic: wp.vec3,
    v_opacity: float,
    v_color: wp.vec3,
    v_depth: float,
): ...


# 1 / x by the hardware's approximate reciprocal on CUDA (__fdividef: at most 2 ulp from the rounded quotient
# for |x| in [2^-126, 2^126]; the backward's 1 - alpha lies in [1 - ALPHA_MAX, 1]) instead of the IEEE division,
# whose correctly rounded sequence made the compositing backward 6-7 % slower on an H100/H200; exact on CPU.
_FAST_RECIPROCAL_SNIPPET = r"""
#if defined(__CUDA_ARCH__)
    return __fdividef(1.0f, x);
#else
    return 1.0f / x;
#endif
"""


@wp.func_native(_FAST_RECIPROCAL_SNIPPET)
def fast_reciprocal(x: float) -> float: ...


def _composite_backward_kernel(sum_and_add, **options):
    """The compositing backward kernel summing and adding each Gaussian's gradients with ``sum_and_add`` (one of
    the warp-sum-and-atomic-add functions above), built with the Warp kernel ``options`` (``launch_bounds``)."""

    @wp.kernel(enable_backward=False, **options)
    def composite_backward_kernel(
        tile_ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        xy_opacity: wp.array(dtype=wp.vec3),
        conics: wp.array(dtype=wp.vec3),
        color_depth: wp.array(dtype=wp.vec4),
        background: wp.array(dtype=wp.vec3),
        width: int,
        height: int,
        tiles_x: int,
        final_transmittance: wp.array(dtype=wp.float32),
        last_index: wp.array(dtype=wp.int32),
        grad_image: wp.array(dtype=wp.vec3),
        grad_alpha: wp.array(dtype=wp.float32),
        grad_depth: wp.array(dtype=wp.float32),
        with_abs: int,
        grads: wp.array(dtype=wp.float32),
    ):
        """Back-to-front gradient of the compositing, one pixel per thread, one tile per block.

        Adds into ``grads`` (structure-of-arrays, see ``GRAD_RECORD_FLOATS``; zeroed by the caller) the gradients
        of the loss with respect to each Gaussian's 2D mean, conic, opacity, colour and depth, and the per-axis
        sum of |d mean2d| over pixels when ``with_abs`` is 1.
        """
        tile, lane = wp.tid()
        gaussian_count = xy_opacity.shape[0]
        pixel_x, pixel_y = tile_pixel(tile, lane, tiles_x)
        inside = pixel_x < width and pixel_y < height
        center_x = float(pixel_x) + 0.5
        center_y = float(pixel_y) + 0.5

        range_start = tile_ranges[tile, 0]
        t_final = float(1.0)
        last = int(-1)
        g_color = wp.vec3(0.0)
        g_alpha = float(0.0)
        g_depth = float(0.0)
        if inside:
            pixel = pixel_y * width + pixel_x
            t_final = final_transmittance[pixel]
            last = last_index[pixel]
            g_color = grad_image[pixel]
            g_alpha = grad_alpha[pixel]
            g_depth = grad_depth[pixel]
        # Constant part of d pixel / d alpha_i * (1 - alpha_i): the alpha output and the background term.
        g_alpha_transmittance = t_final * (g_alpha - wp.dot(background[0], g_color))

        block_last = wp.tile_max(wp.tile(last))[0]
        batch_count = (block_last + 1 - range_start + PIXELS_PER_TILE - 1) // PIXELS_PER_TILE

        transmittance = t_final
        color_behind = wp.vec3(0.0)
        depth_behind = float(0.0)
        for batch in range(batch_count):
            batch_end = block_last + 1 - batch * PIXELS_PER_TILE
            batch_begin = wp.max(range_start, batch_end - PIXELS_PER_TILE)
            ids = wp.tile_load(sorted_ids, shape=PIXELS_PER_TILE, offset=batch_begin, storage="shared")
            batch_xyo = wp.tile_load_indexed(xy_opacity, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                             storage="shared")
            batch_conic = wp.tile_load_indexed(conics, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                               storage="shared")
            batch_color = wp.tile_load_indexed(color_depth, indices=ids, shape=(PIXELS_PER_TILE,), offset=(0,), axis=0,
                                               storage="shared")
            batch_size = batch_end - batch_begin
            for step in range(batch_size):
                k = batch_size - 1 - step
                xyo = batch_xyo[k]
                conic = batch_conic[k]
                active = int(0)
                v_mean2d = wp.vec2(0.0)
                v_conic = wp.vec3(0.0)
                v_opacity = float(0.0)
                v_color = wp.vec3(0.0)
                v_depth = float(0.0)
                if batch_begin + k <= last:
                    evaluated = gaussian_alpha(xyo, conic, center_x, center_y)
                    a = evaluated[0]
                    if evaluated[1] >= 0.0 and a >= ALPHA_THRESHOLD:
                        active = 1
                        rgbd = batch_color[k]
                        rgb = wp.vec3(rgbd[0], rgbd[1], rgbd[2])
                        inv_one_minus_alpha = fast_reciprocal(1.0 - a)
                        transmittance = transmittance * inv_one_minus_alpha
                        weight = a * transmittance
                        v_color = weight * g_color
                        v_depth = weight * g_depth
                        v_alpha = (
                            wp.dot(rgb * transmittance - color_behind * inv_one_minus_alpha, g_color)
                            + (rgbd[3] * transmittance - depth_behind * inv_one_minus_alpha) * g_depth
                            + g_alpha_transmittance * inv_one_minus_alpha
                        )
                        unclamped = xyo[2] * evaluated[2]
                        if unclamped <= ALPHA_MAX:
                            v_sigma = -unclamped * v_alpha
                            dx = xyo[0] - center_x
                            dy = xyo[1] - center_y
                            v_conic = wp.vec3(0.5 * v_sigma * dx * dx, v_sigma * dx * dy, 0.5 * v_sigma * dy * dy)
                            v_mean2d = v_sigma * wp.vec2(conic[0] * dx + conic[1] * dy, conic[1] * dx + conic[2] * dy)
                            v_opacity = evaluated[2] * v_alpha
                        color_behind += weight * rgb
                        depth_behind += weight * rgbd[3]
                sum_and_add(grads, gaussian_count, ids[k], active, with_abs, v_mean2d, v_conic, v_opacity, v_color,
                            v_depth)

    return composite_backward_kernel


# Up to 96 registers a thread (2 blocks of 256 a multiprocessor): the faster kernel where an image has few tiles
# per multiprocessor, as 384x384 on an H100 (4.4), where per-block latency and the last wave decide.
composite_backward_kernel = _composite_backward_kernel(warp_sum_atomic_add)

WIDE_GRID_TILES_PER_SM = 16
"""From this many tiles per multiprocessor on (4 waves of 4 blocks), :func:`backward_kernel_for` picks
:data:`composite_backward_wide_kernel`."""

# 64 registers a thread (4 blocks a multiprocessor, a few values spilled) with the transposed warp sum: 6-7 %
# faster than the other where images have many tiles (40k-500k Gaussians at 1024x1024 and 1920x1080, 31-62
# tiles per multiprocessor of an H100), 16 % slower at 384x384. Warp versions without ``launch_bounds`` use
# the default kernel for every grid.
if "launch_bounds" in inspect.signature(wp.kernel).parameters:
    composite_backward_wide_kernel = _composite_backward_kernel(warp_sum_atomic_add_transposed,
                                                                launch_bounds=(int(PIXELS_PER_TILE), 4))
else:  # pragma: no cover - older Warp
    composite_backward_wide_kernel = composite_backward_kernel


def backward_kernel_for(tile_count: int, device):
    """The compositing backward kernel :func:`launch_composite_backward` launches for ``tile_count`` tiles on
    ``device``: :data:`composite_backward_wide_kernel` on CUDA from :data:`WIDE_GRID_TILES_PER_SM` tiles per
    multiprocessor on, else :data:`composite_backward_kernel`."""
    device = wp.get_device(device)
    multiprocessors = int(getattr(device, "sm_count", 0) or 0) if device.is_cuda else 0
    if multiprocessors and tile_count >= WIDE_GRID_TILES_PER_SM * multiprocessors:
        return composite_backward_wide_kernel
    return composite_backward_kernel


def launch_composite_backward(tile_ranges, sorted_ids, xy_opacity, conics, color_depth, background, *, width: int,
                              height: int, final_transmittance, last_index, grad_image, grad_alpha, grad_depth,
                              with_abs: bool, grads) -> None:
    """Launch the compositing backward (the kernel :func:`backward_kernel_for` picks); ``grads`` is a zeroed
    float32 array of ``screen_grad_floats(with_abs) * gaussian_count``."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    if tile_ranges.shape[0] != tiles_x * tiles_y:
        raise ValueError(f"tile_ranges has {tile_ranges.shape[0]} rows, expected {tiles_x * tiles_y} tiles")
    _check_pixel_arrays(width, height, final_transmittance=final_transmittance, last_index=last_index,
                        grad_image=grad_image, grad_alpha=grad_alpha, grad_depth=grad_depth)
    floats = screen_grad_floats(with_abs)
    if grads.shape[0] != floats * xy_opacity.shape[0]:
        raise ValueError(f"grads has {grads.shape[0]} entries, expected {floats} * gaussian_count")
    if width * height == 0 or xy_opacity.shape[0] == 0:
        return
    launch(
        backward_kernel_for(tiles_x * tiles_y, _device_of(grads)),
        dim=(tiles_x * tiles_y, int(PIXELS_PER_TILE)),
        inputs=[tile_ranges, sorted_ids, xy_opacity, conics, color_depth, background, width, height, tiles_x,
                final_transmittance, last_index, grad_image, grad_alpha, grad_depth, int(bool(with_abs))],
        outputs=[grads],
        block_dim=launch_block_dim(_device_of(grads)),
    )


# ----------------------------------------------------------------------------------------------------------
# 5. Projection, backward (Warp autodiff of a straight-line kernel)
# ----------------------------------------------------------------------------------------------------------


@wp.kernel
def project_differentiable_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    coefficients: wp.array2d(dtype=wp.vec3),
    intrinsics: wp.array(dtype=wp.mat33),
    world_to_camera: wp.array(dtype=wp.mat44),
    radii: wp.array(dtype=wp.vec2i),
    width: int,
    height: int,
    sh_degree: int,
    mean2d: wp.array(dtype=wp.vec2),
    conic: wp.array(dtype=wp.vec3),
    depth: wp.array(dtype=wp.float32),
    color: wp.array(dtype=wp.vec3),
):
    """The differentiable outputs of :data:`project_kernel` for the Gaussians it kept (radius > 0).

    Only launched with ``adjoint=True``: its adjoint maps gradients of (mean2d, conic, depth, colour) to
    gradients of (means, quats, scales, coefficients). Culled Gaussians return at once and get none.
    """
    i = wp.tid()
    radius = radii[i]
    if radius[0] == 0 and radius[1] == 0:
        return
    K = intrinsics[0]
    view = world_to_camera[0]
    mean = means[i]
    mean_camera = to_camera(view, mean)
    covariance_2d = ewa_covariance_2d(
        mean_camera, camera_covariance(rotation_of(view), quats[i], scales[i]), K, float(width), float(height)
    )
    mean2d[i] = project_mean(mean_camera, K)
    conic[i] = conic_of(covariance_2d)
    depth[i] = mean_camera[2]
    color[i] = gaussian_color(coefficients, i, sh_degree, mean, camera_center_of(view))


def launch_project_backward(
    means, quats, scales, coefficients, intrinsics, world_to_camera, radii, *, width: int, height: int,
    sh_degree: int, scratch_mean2d, scratch_conic, scratch_depth, scratch_color, grad_mean2d, grad_conic,
    grad_depth, grad_color, grad_means, grad_quats, grad_scales, grad_coefficients,
) -> None:
    """Adjoint launch of :data:`project_differentiable_kernel`.

    ``grad_mean2d``/``grad_conic``/``grad_depth``/``grad_color`` are the incoming per-Gaussian gradients; the
    ``grad_means``/``grad_quats``/``grad_scales``/``grad_coefficients`` arrays (zeroed by the caller) receive
    the result. ``scratch_*`` arrays (``gaussian_count`` long, contents ignored) are written by the forward
    replay of the adjoint kernel and never read: ``warp_utils.write_only_descriptor`` lets them share one
    element.
    """
    gaussian_count = means.shape[0]
    for name, array in (("quats", quats), ("scales", scales), ("coefficients", coefficients), ("radii", radii),
                        ("grad_mean2d", grad_mean2d), ("grad_conic", grad_conic), ("grad_depth", grad_depth),
                        ("grad_color", grad_color), ("grad_means", grad_means), ("grad_quats", grad_quats),
                        ("grad_scales", grad_scales), ("grad_coefficients", grad_coefficients),
                        ("scratch_mean2d", scratch_mean2d), ("scratch_conic", scratch_conic),
                        ("scratch_depth", scratch_depth), ("scratch_color", scratch_color)):
        if array.shape[0] != gaussian_count:
            raise ValueError(f"{name} has {array.shape[0]} entries, expected {gaussian_count}")
    if gaussian_count == 0:
        return
    launch(
        project_differentiable_kernel,
        dim=gaussian_count,
        inputs=[means, quats, scales, coefficients, intrinsics, world_to_camera, radii, width, height, sh_degree],
        outputs=[scratch_mean2d, scratch_conic, scratch_depth, scratch_color],
        adj_inputs=[grad_means, grad_quats, grad_scales, grad_coefficients, None, None, None, 0, 0, 0],
        adj_outputs=[grad_mean2d, grad_conic, grad_depth, grad_color],
        adjoint=True,
        block_dim=launch_block_dim(_device_of(means)),
    )


# ----------------------------------------------------------------------------------------------------------
# Tile binning into buffers of a fixed capacity (no host read of the pair count: capturable in a CUDA graph)
# ----------------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def tile_ranges_padded_kernel(sorted_keys: wp.array(dtype=wp.int32), key_count: int,
                              tile_ranges: wp.array2d(dtype=wp.int32)):
    """:data:`tile_ranges_kernel` over sorted tile keys that end with padding keys (ids past the last tile),
    which belong to no tile (``tile_ranges`` starts zeroed)."""
    i = wp.tid()
    tile_count = tile_ranges.shape[0]
    tile = sorted_keys[i]
    if tile >= tile_count:
        tile = -1
    previous = -1
    if i > 0:
        previous = sorted_keys[i - 1]
        if previous >= tile_count:
            previous = -1
    if i == 0 or previous != tile:
        if tile >= 0:
            tile_ranges[tile, 0] = i
        if previous >= 0:
            tile_ranges[previous, 1] = i
    if i == key_count - 1 and tile >= 0:
        tile_ranges[tile, 1] = key_count


def launch_tile_ranges_padded(sorted_keys, key_count: int, tile_ranges) -> None:
    """Launch :data:`tile_ranges_padded_kernel` over the first ``key_count`` sorted keys (padding included)."""
    if sorted_keys.shape[0] < key_count:
        raise ValueError(f"sorted_keys has {sorted_keys.shape[0]} entries, fewer than key_count={key_count}")
    if key_count == 0:
        return
    launch(tile_ranges_padded_kernel, dim=key_count, inputs=[sorted_keys, key_count], outputs=[tile_ranges],
              block_dim=launch_block_dim(_device_of(sorted_keys)))


__all__ += ["tile_ranges_padded_kernel", "launch_tile_ranges_padded"]
