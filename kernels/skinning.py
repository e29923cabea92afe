"""Skinning kernels: trilinear sampling of a voxel field and linear blend skinning (LBS), forward and backward.

Two groups of kernels live here, both with hand-written backward passes (Warp never differentiates them):

* ``sample_grid_*``: trilinear interpolation of a channel-last voxel grid ``[D, H, W, C]`` spanning an
  axis-aligned box, with the grid's corner samples on the box's corners and points outside the box clamped
  onto it (``grid_sample(..., align_corners=True, padding_mode="border")`` semantics). A point ``(x, y, z)``
  indexes the grid's ``(W, H, D)`` axes. Two thread layouts exist for each pass: one thread per point that
  loops over the channels (best on CPU, where it computes the cell and weights once), and one thread per
  (point, channel) pair (best on CUDA: neighbouring threads read, write and atomically add neighbouring
  channels, so memory accesses coalesce). Grid gradients are accumulated with atomics.
* ``lbs_*``: the per-point blended affine ``T_i = sum_k W_ik B_k`` applied to positions (or inverted, for
  inverse LBS) and its rotation part applied to (w, x, y, z) quaternions. The rotation of a blended affine
  ``A`` is the proper rotation closest to it in the Frobenius norm (the rotation maximizing ``tr(R^T A)``,
  i.e. the polar factor of ``A`` when ``det A > 0``). It is computed from Warp's ``svd3`` and polished by
  Newton steps on SO(3), because ``svd3`` alone runs a fixed number of Jacobi sweeps and can be off by
  1e-2 on some matrices. Its derivative uses ``S = sym(R^T A)`` only: a rotation cotangent ``omega`` (in
  the body frame of ``R``) pulls back to ``dL/dA = R [k]_x`` with ``(tr(S) I - S) k = omega``, which stays
  well defined when singular values repeat (blends of rotations about one axis), unlike SVD derivatives.

Quaternions are stored as ``wp.vec4`` in (w, x, y, z) order (Warp's own ``wp.quat`` is (x, y, z, w)).
Launchers take Warp arrays, check their sizes and skip empty work; the torch bridge is
:mod:`warpavatar._src.skinning`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch
from .quaternion import quat_conjugate, quat_from_rotation_matrix, quat_multiply, quat_to_matrix

__all__ = [
    "SAMPLE_GRID_LAYOUTS",
    "ROTATION_NEWTON_STEPS",
    "mat34",
    "sample_grid_forward",
    "sample_grid_backward",
    "lbs_forward",
    "lbs_backward",
]

SAMPLE_GRID_LAYOUTS = ("point", "channel")
"""Thread layouts of the grid sampler: one thread per point looping channels, or one per (point, channel)."""

ROTATION_NEWTON_STEPS = 2
"""Newton steps on SO(3) that polish the ``svd3`` estimate of the closest rotation (error ~e^2 per step)."""

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
"""Row-major 3x4 float32 matrix: the top three rows of a 4x4 affine transform."""


# ---------------------------------------------------------------------------------------------------------
# Trilinear grid sampling
# ---------------------------------------------------------------------------------------------------------


@wp.func
def _axis_coordinate(position: float, low: float, high: float, size: int):
    """Map a world coordinate onto one grid axis.

    Returns:
        cell: index of the lower sample of the interpolation interval, in ``[0, max(size - 2, 0)]``.
        fraction: position inside the interval in [0, 1] (NaN when ``position`` is NaN, so NaN propagates).
        slope: d(continuous index)/d(position) [samples per world unit], 0 where the coordinate is clamped.
            As in torch's grid_sampler, a coordinate exactly on the box's border also counts as clamped.
    """
    last = float(size - 1)
    scale = last / (high - low)
    index = (position - low) * scale
    slope = float(0.0)
    clamped = index
    if index >= last:
        clamped = last
    elif index <= 0.0:
        clamped = 0.0
    else:
        # strictly inside (a NaN index fails every comparison and keeps slope 0)
        slope = scale
    cell = int(0)
    fraction = clamped
    if clamped >= 0.0:
        cell = wp.min(int(wp.floor(clamped)), wp.max(size - 2, 0))
        fraction = clamped - float(cell)
    return cell, fraction, slope


@wp.func
def _box_low(box: wp.array(dtype=wp.vec3), box_low: wp.vec3):
    # The box is read from device memory when given as an array, else from the launch arguments.
    if box.shape[0] == 2:
        return box[0]
    return box_low


@wp.func
def _box_high(box: wp.array(dtype=wp.vec3), box_high: wp.vec3):
    if box.shape[0] == 2:
        return box[1]
    return box_high


@wp.func
def _grid_cell(box: wp.array(dtype=wp.vec3), box_low: wp.vec3, box_high: wp.vec3, p: wp.vec3, depth: int,
               height: int, width: int):
    """The cell of point ``p`` in a grid of ``depth x height x width`` samples spanning the box: its lower corner
    (z0, y0, x0), its upper corner (z1, y1, x1) clamped to the grid, the fractions (fz, fy, fx) and the grid
    indices per world unit along each axis (sz, sy, sx)."""
    low = _box_low(box, box_low)
    high = _box_high(box, box_high)
    x0, fx, sx = _axis_coordinate(p[0], low[0], high[0], width)
    y0, fy, sy = _axis_coordinate(p[1], low[1], high[1], height)
    z0, fz, sz = _axis_coordinate(p[2], low[2], high[2], depth)
    x1 = wp.min(x0 + 1, width - 1)
    y1 = wp.min(y0 + 1, height - 1)
    z1 = wp.min(z0 + 1, depth - 1)
    return z0, y0, x0, z1, y1, x1, fz, fy, fx, sz, sy, sx


@wp.func
def _trilinear(
    grid: wp.array4d(dtype=float),
    z0: int, y0: int, x0: int, z1: int, y1: int, x1: int,
    fz: float, fy: float, fx: float,
    channel: int,
):
    c00 = grid[z0, y0, x0, channel] + fx * (grid[z0, y0, x1, channel] - grid[z0, y0, x0, channel])
    c01 = grid[z0, y1, x0, channel] + fx * (grid[z0, y1, x1, channel] - grid[z0, y1, x0, channel])
    c10 = grid[z1, y0, x0, channel] + fx * (grid[z1, y0, x1, channel] - grid[z1, y0, x0, channel])
    c11 = grid[z1, y1, x0, channel] + fx * (grid[z1, y1, x1, channel] - grid[z1, y1, x0, channel])
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    return c0 + fz * (c1 - c0)


@wp.func
def _trilinear_fraction_gradient(
    grid: wp.array4d(dtype=float),
    z0: int, y0: int, x0: int, z1: int, y1: int, x1: int,
    fz: float, fy: float, fx: float,
    channel: int,
):
    """d(value)/d(fx, fy, fz) of the trilinear interpolant of one channel."""
    v000 = grid[z0, y0, x0, channel]
    v001 = grid[z0, y0, x1, channel]
    v010 = grid[z0, y1, x0, channel]
    v011 = grid[z0, y1, x1, channel]
    v100 = grid[z1, y0, x0, channel]
    v101 = grid[z1, y0, x1, channel]
    v110 = grid[z1, y1, x0, channel]
    v111 = grid[z1, y1, x1, channel]
    gx0 = (1.0 - fy) * (v001 - v000) + fy * (v011 - v010)
    gx1 = (1.0 - fy) * (v101 - v100) + fy * (v111 - v110)
    c00 = v000 + fx * (v001 - v000)
    c01 = v010 + fx * (v011 - v010)
    c10 = v100 + fx * (v101 - v100)
    c11 = v110 + fx * (v111 - v110)
    gy0 = c01 - c00
    gy1 = c11 - c10
    c0 = c00 + fy * gy0
    c1 = c10 + fy * gy1
    return wp.vec3(
        (1.0 - fz) * gx0 + fz * gx1,
        (1.0 - fz) * gy0 + fz * gy1,
        c1 - c0,
    )


@wp.func
def _scatter_trilinear(
    grad_grid: wp.array4d(dtype=float),
    z0: int, y0: int, x0: int, z1: int, y1: int, x1: int,
    fz: float, fy: float, fx: float,
    channel: int,
    grad_value: float,
):
    gz0 = (1.0 - fz) * grad_value
    gz1 = fz * grad_value
    g00 = (1.0 - fy) * gz0
    g01 = fy * gz0
    g10 = (1.0 - fy) * gz1
    g11 = fy * gz1
    wp.atomic_add(grad_grid, z0, y0, x0, channel, (1.0 - fx) * g00)
    wp.atomic_add(grad_grid, z0, y0, x1, channel, fx * g00)
    wp.atomic_add(grad_grid, z0, y1, x0, channel, (1.0 - fx) * g01)
    wp.atomic_add(grad_grid, z0, y1, x1, channel, fx * g01)
    wp.atomic_add(grad_grid, z1, y0, x0, channel, (1.0 - fx) * g10)
    wp.atomic_add(grad_grid, z1, y0, x1, channel, fx * g10)
    wp.atomic_add(grad_grid, z1, y1, x0, channel, (1.0 - fx) * g11)
    wp.atomic_add(grad_grid, z1, y1, x1, channel, fx * g11)


@wp.kernel(enable_backward=False)
def sample_grid_forward_point_kernel(
    grid: wp.array4d(dtype=float),
    points: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec3),
    box_low: wp.vec3,
    box_high: wp.vec3,
    values: wp.array2d(dtype=float),
):
    """One thread per point: values[i, :] = trilinear(grid, points[i]) for every channel."""
    i = wp.tid()
    z0, y0, x0, z1, y1, x1, fz, fy, fx, sz, sy, sx = _grid_cell(
        box, box_low, box_high, points[i], grid.shape[0], grid.shape[1], grid.shape[2])
    for channel in range(grid.shape[3]):
        values[i, channel] = _trilinear(grid, z0, y0, x0, z1, y1, x1, fz, fy, fx, channel)


@wp.kernel(enable_backward=False)
def sample_grid_forward_channel_kernel(
    grid: wp.array4d(dtype=float),
    points: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec3),
    box_low: wp.vec3,
    box_high: wp.vec3,
    values: wp.array2d(dtype=float),
):
    """One thread per (point, channel): values[i, channel] = trilinear(grid[..., channel], points[i])."""
    i, channel = wp.tid()
    z0, y0, x0, z1, y1, x1, fz, fy, fx, sz, sy, sx = _grid_cell(
        box, box_low, box_high, points[i], grid.shape[0], grid.shape[1], grid.shape[2])
    values[i, channel] = _trilinear(grid, z0, y0, x0, z1, y1, x1, fz, fy, fx, channel)


@wp.kernel(enable_backward=False)
def sample_grid_backward_point_kernel(
    grid: wp.array4d(dtype=float),
    points: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec3),
    box_low: wp.vec3,
    box_high: wp.vec3,
    grad_values: wp.array2d(dtype=float),
    compute_grad_grid: int,
    compute_grad_points: int,
    grad_grid: wp.array4d(dtype=float),
    grad_points: wp.array(dtype=wp.vec3),
):
    """One thread per point, looping channels: scatters grad_grid (atomics) and writes grad_points[i]."""
    i = wp.tid()
    z0, y0, x0, z1, y1, x1, fz, fy, fx, sz, sy, sx = _grid_cell(
        box, box_low, box_high, points[i], grid.shape[0], grid.shape[1], grid.shape[2])
    grad_fraction = wp.vec3(0.0, 0.0, 0.0)
    for channel in range(grid.shape[3]):
        grad_value = grad_values[i, channel]
        if compute_grad_grid != 0:
            _scatter_trilinear(grad_grid, z0, y0, x0, z1, y1, x1, fz, fy, fx, channel, grad_value)
        if compute_grad_points != 0:
            grad_fraction += grad_value * _trilinear_fraction_gradient(
                grid, z0, y0, x0, z1, y1, x1, fz, fy, fx, channel
            )
    if compute_grad_points != 0:
        grad_points[i] = wp.vec3(grad_fraction[0] * sx, grad_fraction[1] * sy, grad_fraction[2] * sz)


@wp.kernel(enable_backward=False)
def sample_grid_backward_grid_channel_kernel(
    points: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec3),
    box_low: wp.vec3,
    box_high: wp.vec3,
    grad_values: wp.array2d(dtype=float),
    grad_grid: wp.array4d(dtype=float),
):
    """One thread per (point, channel): scatters grad_values[i, channel] onto the 8 cell corners (atomics)."""
    i, channel = wp.tid()
    z0, y0, x0, z1, y1, x1, fz, fy, fx, sz, sy, sx = _grid_cell(
        box, box_low, box_high, points[i], grad_grid.shape[0], grad_grid.shape[1], grad_grid.shape[2])
    _scatter_trilinear(grad_grid, z0, y0, x0, z1, y1, x1, fz, fy, fx, channel, grad_values[i, channel])


def _check_sample_grid_arrays(grid, points, box, values_like, values_name):
    if grid.ndim != 4:
        raise ValueError(f"grid must be a 4D array [D, H, W, C], got {grid.ndim} dimensions")
    if min(grid.shape[:3]) < 1:
        raise ValueError(f"grid must have at least one sample along D, H and W, got shape {grid.shape}")
    point_count = points.shape[0]
    if values_like.shape != (point_count, grid.shape[3]):
        raise ValueError(
            f"{values_name} must have shape [{point_count}, {grid.shape[3]}], got {list(values_like.shape)}"
        )
    if box is not None and box.shape[0] != 2:
        raise ValueError(f"box must hold 2 vec3 (low and high corners), got {box.shape[0]}")
    return point_count


def sample_grid_forward(
    grid: wp.array4d,
    points: wp.array,
    values: wp.array2d,
    *,
    box: wp.array | None = None,
    box_low=(0.0, 0.0, 0.0),
    box_high=(1.0, 1.0, 1.0),
    layout: str = "point",
) -> None:
    """Launch the trilinear sampler: ``values[i, c] = grid(points[i])[c]``.

    Args:
        grid: float32 ``[D, H, W, C]`` samples; sample ``(d, h, w)`` sits at
            ``low + (w, h, d) / (W - 1, H - 1, D - 1) * (high - low)``.
        points: ``wp.vec3`` ``[N]`` query positions (world units).
        values: float32 ``[N, C]`` output.
        box: optional ``wp.vec3`` ``[2]`` (low corner, high corner) in device memory; when given it overrides
            ``box_low`` and ``box_high``.
        box_low, box_high: the box's corners as launch arguments (world units), used when ``box`` is None.
        layout: ``"point"`` (a thread per point, looping channels) or ``"channel"`` (a thread per pair).
    """
    point_count = _check_sample_grid_arrays(grid, points, box, values, "values")
    if layout not in SAMPLE_GRID_LAYOUTS:
        raise ValueError(f"layout must be one of {SAMPLE_GRID_LAYOUTS}, got {layout!r}")
    channel_count = grid.shape[3]
    if point_count == 0 or channel_count == 0:
        return
    inputs = [grid, points, box, wp.vec3(*box_low), wp.vec3(*box_high)]
    if layout == "point":
        launch(sample_grid_forward_point_kernel, dim=point_count, inputs=inputs, outputs=[values])
    else:
        launch(
            sample_grid_forward_channel_kernel, dim=(point_count, channel_count), inputs=inputs, outputs=[values]
        )


def sample_grid_backward(
    grid: wp.array4d,
    points: wp.array,
    grad_values: wp.array2d,
    *,
    grad_grid: wp.array4d | None,
    grad_points: wp.array | None,
    box: wp.array | None = None,
    box_low=(0.0, 0.0, 0.0),
    box_high=(1.0, 1.0, 1.0),
    layout: str = "point",
) -> None:
    """Launch the sampler's backward pass.

    Args:
        grid, points, box, box_low, box_high: as in :func:`sample_grid_forward`.
        grad_values: float32 ``[N, C]`` cotangent of ``values``.
        grad_grid: float32 ``[D, H, W, C]`` accumulator, zero-filled by the caller, or None to skip it.
        grad_points: ``wp.vec3`` ``[N]`` output (overwritten), or None to skip it.
        layout: ``"point"``: one launch computes both gradients; ``"channel"``: the grid gradient is
            scattered by one thread per (point, channel), and the point gradient (a sum over channels) by a
            second, per-point launch.
    """
    point_count = _check_sample_grid_arrays(grid, points, box, grad_values, "grad_values")
    if layout not in SAMPLE_GRID_LAYOUTS:
        raise ValueError(f"layout must be one of {SAMPLE_GRID_LAYOUTS}, got {layout!r}")
    if grad_grid is not None and grad_grid.shape != grid.shape:
        raise ValueError(f"grad_grid must have the grid's shape {grid.shape}, got {grad_grid.shape}")
    if grad_points is not None and grad_points.shape[0] != point_count:
        raise ValueError(f"grad_points must hold {point_count} points, got {grad_points.shape[0]}")
    channel_count = grid.shape[3]
    if point_count == 0 or (grad_grid is None and grad_points is None):
        return
    if channel_count == 0:
        if grad_points is not None:
            grad_points.zero_()
        return
    box_args = [box, wp.vec3(*box_low), wp.vec3(*box_high)]
    scatter_here = grad_grid is not None and layout == "point"
    if grad_grid is not None and layout == "channel":
        launch(
            sample_grid_backward_grid_channel_kernel,
            dim=(point_count, channel_count),
            inputs=[points, *box_args, grad_values],
            outputs=[grad_grid],
        )
    if scatter_here or grad_points is not None:
        launch(
            sample_grid_backward_point_kernel,
            dim=point_count,
            inputs=[grid, points, *box_args, grad_values, int(scatter_here), int(grad_points is not None)],
            outputs=[grad_grid if scatter_here else None, grad_points],
        )


# ---------------------------------------------------------------------------------------------------------
# The closest rotation of a 3x3 matrix (quaternions (w, x, y, z): kernels/quaternion.py)
# ---------------------------------------------------------------------------------------------------------


@wp.func
def _rotation_hessian(s: wp.mat33):
    """``tr(S) I - S`` for symmetric ``S``: the (negated) Hessian of ``tr(R^T A)`` on SO(3) at ``R``."""
    t = s[0, 0] + s[1, 1] + s[2, 2]
    return wp.mat33(
        t - s[0, 0], -s[0, 1], -s[0, 2],
        -s[1, 0], t - s[1, 1], -s[1, 2],
        -s[2, 0], -s[2, 1], t - s[2, 2],
    )


@wp.func
def _is_positive_definite(h: wp.mat33):
    # Sylvester's criterion, with a relative floor so that near-singular systems are not solved.
    floor = 1.0e-6 * (h[0, 0] + h[1, 1] + h[2, 2])
    minor2 = h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]
    return h[0, 0] > floor and minor2 > floor * floor and wp.determinant(h) > floor * floor * floor


@wp.func
def closest_rotation(a: wp.mat33):
    """Unit (w, x, y, z) quaternion, with w >= 0, of the rotation R maximizing ``tr(R^T a)``.

    For ``det a > 0`` this is the rotation of the polar decomposition ``a = R S``. Warp's ``svd3`` gives a
    first estimate ``U V^T`` (U and V are proper rotations, the sign of det lives in the last singular
    value), then Newton steps on ``R <- R exp([omega]_x)`` maximize ``tr(R^T a)``: with ``M = R^T a``, the
    gradient is ``axial(M - M^T)`` and the negated Hessian ``tr(sym M) I - sym M``.
    """
    u = wp.mat33()
    sigma = wp.vec3()
    v = wp.mat33()
    wp.svd3(a, u, sigma, v)
    q = quat_from_rotation_matrix(u * wp.transpose(v))
    for _step in range(ROTATION_NEWTON_STEPS):
        m = wp.transpose(quat_to_matrix(q)) * a
        gradient = wp.vec3(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])
        hessian = _rotation_hessian(0.5 * (m + wp.transpose(m)))
        omega = wp.vec3(0.0, 0.0, 0.0)
        if _is_positive_definite(hessian):
            omega = wp.inverse(hessian) * gradient
        else:
            # far from the maximum (or a degenerate matrix): a damped gradient step
            omega = gradient / (wp.abs(m[0, 0] + m[1, 1] + m[2, 2]) + 1.0e-30)
        q = wp.normalize(quat_multiply(q, wp.vec4(1.0, 0.5 * omega[0], 0.5 * omega[1], 0.5 * omega[2])))
    if q[0] < 0.0:
        q = -q
    return q


@wp.func
def closest_rotation_backward(a: wp.mat33, q: wp.vec4, grad_q: wp.vec4):
    """Pull the cotangent ``grad_q`` of ``q = closest_rotation(a)`` back to ``a`` (a 3x3 cotangent).

    With ``dR = R [omega]_x``, ``dq = q * (0, omega / 2)``, so the cotangent of ``omega`` is
    ``vec(conj(q) * grad_q) / 2``; implicit differentiation of ``sym(R^T a) = R^T a`` gives
    ``dL/da = R [k]_x`` with ``(tr(S) I - S) k = omega_cotangent`` and ``S = sym(R^T a)``.
    """
    body = quat_multiply(quat_conjugate(q), grad_q)
    grad_omega = wp.vec3(0.5 * body[1], 0.5 * body[2], 0.5 * body[3])
    r = quat_to_matrix(q)
    m = wp.transpose(r) * a
    hessian = _rotation_hessian(0.5 * (m + wp.transpose(m)))
    k = wp.vec3(0.0, 0.0, 0.0)
    if _is_positive_definite(hessian):
        k = wp.inverse(hessian) * grad_omega
    return r * wp.skew(k)


# ---------------------------------------------------------------------------------------------------------
# Linear blend skinning
# ---------------------------------------------------------------------------------------------------------


@wp.func
def _blend_transforms(weights: wp.array2d(dtype=float), bones: wp.array(dtype=wp.mat44), i: int):
    """``sum_k weights[i, k] * bones[k]``, top three rows: linear part ``a`` (3x3) and translation ``t``."""
    a = wp.mat33(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    t = wp.vec3(0.0, 0.0, 0.0)
    for k in range(weights.shape[1]):
        w = weights[i, k]
        b = bones[k]
        a += w * wp.mat33(b[0, 0], b[0, 1], b[0, 2], b[1, 0], b[1, 1], b[1, 2], b[2, 0], b[2, 1], b[2, 2])
        t += w * wp.vec3(b[0, 3], b[1, 3], b[2, 3])
    return a, t


@wp.kernel(enable_backward=False)
def lbs_forward_kernel(
    points: wp.array(dtype=wp.vec3),
    weights: wp.array2d(dtype=float),
    bones: wp.array(dtype=wp.mat44),
    quats: wp.array(dtype=wp.vec4),
    inverse: int,
    points_out: wp.array(dtype=wp.vec3),
    quats_out: wp.array(dtype=wp.vec4),
):
    """Forward LBS (``x' = A x + t``, ``q' = q(R) q``) or, with ``inverse``, its inverse per point."""
    i = wp.tid()
    a, t = _blend_transforms(weights, bones, i)
    if inverse == 0:
        points_out[i] = a * points[i] + t
    else:
        points_out[i] = wp.inverse(a) * (points[i] - t)
    if quats.shape[0] > 0:
        rotation = closest_rotation(a)
        if inverse == 0:
            quats_out[i] = quat_multiply(rotation, quats[i])
        else:
            quats_out[i] = quat_multiply(quat_conjugate(rotation), quats[i])


@wp.kernel(enable_backward=False)
def lbs_backward_kernel(
    points: wp.array(dtype=wp.vec3),
    weights: wp.array2d(dtype=float),
    bones: wp.array(dtype=wp.mat44),
    quats: wp.array(dtype=wp.vec4),
    grad_points_out: wp.array(dtype=wp.vec3),
    grad_quats_out: wp.array(dtype=wp.vec4),
    inverse: int,
    grad_points: wp.array(dtype=wp.vec3),
    grad_quats: wp.array(dtype=wp.vec4),
    grad_weights: wp.array2d(dtype=float),
    grad_blend: wp.array(dtype=mat34),
):
    """Backward of :func:`lbs_forward_kernel`; outputs with zero length are skipped.

    ``grad_blend[i]`` receives the cotangent of the point's blended transform (top three rows); the caller
    reduces it over points into the bones' gradient (``W^T @ grad_blend``, a GEMM, instead of atomics on
    12 J addresses).
    """
    i = wp.tid()
    a, t = _blend_transforms(weights, bones, i)
    g = grad_points_out[i]
    grad_a = wp.mat33(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    grad_t = wp.vec3(0.0, 0.0, 0.0)
    if inverse == 0:
        # x' = a x + t
        grad_a = wp.outer(g, points[i])
        grad_t = g
        if grad_points.shape[0] > 0:
            grad_points[i] = wp.transpose(a) * g
    else:
        # x = a^-1 (x' - t): dx = -a^-1 da x - a^-1 dt + a^-1 dx'
        a_inv = wp.inverse(a)
        back = wp.transpose(a_inv) * g
        grad_a = -wp.outer(back, a_inv * (points[i] - t))
        grad_t = -back
        if grad_points.shape[0] > 0:
            grad_points[i] = back
    if quats.shape[0] > 0:
        rotation = closest_rotation(a)
        q = quats[i]
        gq = grad_quats_out[i]
        grad_rotation = wp.vec4(0.0, 0.0, 0.0, 0.0)
        if inverse == 0:
            # q' = r q
            grad_rotation = quat_multiply(gq, quat_conjugate(q))
            if grad_quats.shape[0] > 0:
                grad_quats[i] = quat_multiply(quat_conjugate(rotation), gq)
        else:
            # q = conj(r) q'
            grad_rotation = quat_multiply(q, quat_conjugate(gq))
            if grad_quats.shape[0] > 0:
                grad_quats[i] = quat_multiply(rotation, gq)
        grad_a += closest_rotation_backward(a, rotation, grad_rotation)
    grad_affine = mat34(
        grad_a[0, 0], grad_a[0, 1], grad_a[0, 2], grad_t[0],
        grad_a[1, 0], grad_a[1, 1], grad_a[1, 2], grad_t[1],
        grad_a[2, 0], grad_a[2, 1], grad_a[2, 2], grad_t[2],
    )
    if grad_blend.shape[0] > 0:
        grad_blend[i] = grad_affine
    if grad_weights.shape[0] > 0:
        for k in range(weights.shape[1]):
            b = bones[k]
            total = float(0.0)
            for row in range(3):
                for col in range(4):
                    total += grad_affine[row, col] * b[row, col]
            grad_weights[i, k] = total


def _check_lbs_arrays(points, weights, bones, quats):
    point_count = points.shape[0]
    if weights.ndim != 2 or weights.shape[0] != point_count:
        raise ValueError(f"weights must have shape [{point_count}, J], got {list(weights.shape)}")
    if bones.shape[0] != weights.shape[1]:
        raise ValueError(f"bones must hold J={weights.shape[1]} transforms, got {bones.shape[0]}")
    if quats is not None and quats.shape[0] != point_count:
        raise ValueError(f"quats must hold {point_count} quaternions, got {quats.shape[0]}")
    return point_count


def lbs_forward(
    points: wp.array,
    weights: wp.array2d,
    bones: wp.array,
    points_out: wp.array,
    *,
    quats: wp.array | None = None,
    quats_out: wp.array | None = None,
    inverse: bool = False,
) -> None:
    """Launch (inverse) linear blend skinning of positions and, optionally, (w, x, y, z) quaternions.

    Args:
        points: ``wp.vec3`` ``[N]`` positions (rest pose, or posed when ``inverse``), world units.
        weights: float32 ``[N, J]`` skinning weights, used as given (not renormalized).
        bones: ``wp.mat44`` ``[J]`` bone transforms; the bottom row is ignored (taken as 0 0 0 1).
        points_out: ``wp.vec3`` ``[N]`` output positions.
        quats: optional ``wp.vec4`` ``[N]`` quaternions (w, x, y, z), not necessarily unit.
        quats_out: ``wp.vec4`` ``[N]`` output quaternions, required with ``quats``.
        inverse: apply the inverse of each point's blended transform instead.
    """
    point_count = _check_lbs_arrays(points, weights, bones, quats)
    if points_out.shape[0] != point_count:
        raise ValueError(f"points_out must hold {point_count} points, got {points_out.shape[0]}")
    if quats is not None and (quats_out is None or quats_out.shape[0] != point_count):
        raise ValueError(f"quats_out must hold {point_count} quaternions when quats are given")
    if point_count == 0:
        return
    launch(
        lbs_forward_kernel,
        dim=point_count,
        inputs=[points, weights, bones, quats, int(inverse)],
        outputs=[points_out, quats_out if quats is not None else None],
    )


def lbs_backward(
    points: wp.array,
    weights: wp.array2d,
    bones: wp.array,
    grad_points_out: wp.array,
    *,
    quats: wp.array | None = None,
    grad_quats_out: wp.array | None = None,
    inverse: bool = False,
    grad_points: wp.array | None = None,
    grad_quats: wp.array | None = None,
    grad_weights: wp.array2d | None = None,
    grad_blend: wp.array | None = None,
) -> None:
    """Launch the backward pass of :func:`lbs_forward`; each gradient output left None is skipped.

    Args:
        points, weights, bones, quats, inverse: the forward's inputs.
        grad_points_out: ``wp.vec3`` ``[N]`` cotangent of the output positions.
        grad_quats_out: ``wp.vec4`` ``[N]`` cotangent of the output quaternions (required with ``quats``).
        grad_points: ``wp.vec3`` ``[N]`` output.
        grad_quats: ``wp.vec4`` ``[N]`` output.
        grad_weights: float32 ``[N, J]`` output.
        grad_blend: ``mat34`` ``[N]`` output: cotangent of each point's blended transform, whose weighted sum
            over points (``weights^T @ grad_blend``) is the bones' gradient.
    """
    point_count = _check_lbs_arrays(points, weights, bones, quats)
    if grad_points_out.shape[0] != point_count:
        raise ValueError(f"grad_points_out must hold {point_count} points, got {grad_points_out.shape[0]}")
    if quats is not None and (grad_quats_out is None or grad_quats_out.shape[0] != point_count):
        raise ValueError(f"grad_quats_out must hold {point_count} quaternions when quats are given")
    for name, array in (("grad_points", grad_points), ("grad_quats", grad_quats), ("grad_blend", grad_blend)):
        if array is not None and array.shape[0] != point_count:
            raise ValueError(f"{name} must hold {point_count} elements, got {array.shape[0]}")
    if grad_weights is not None and grad_weights.shape != weights.shape:
        raise ValueError(f"grad_weights must have the weights' shape {weights.shape}, got {grad_weights.shape}")
    if grad_quats is not None and quats is None:
        raise ValueError("grad_quats needs quats")
    if point_count == 0 or all(x is None for x in (grad_points, grad_quats, grad_weights, grad_blend)):
        return
    launch(
        lbs_backward_kernel,
        dim=point_count,
        inputs=[
            points, weights, bones, quats,
            grad_points_out, grad_quats_out if quats is not None else None, int(inverse),
        ],
        outputs=[grad_points, grad_quats, grad_weights, grad_blend],
    )
