"""Shading kernels: view-dependent colour of posed Gaussians from spherical harmonics, forward and backward.

One thread per Gaussian does the whole shading chain that :meth:`warpavatar.model.Avatar.view_colors` used to
run as some fifty torch ops: the unit direction from the shading origin to the posed mean, rotated back into
the Gaussian's canonical frame (inverse of the posed quaternion, then the canonical one), the real SH basis up
to degree 3 (3DGS coefficient order and signs), the weighted sum over coefficients, ``+ 0.5`` and the clamp at
zero. The backward kernel is written by hand and writes every gradient of its Gaussian without atomics.

Quaternions are ``wp.vec4`` in (w, x, y, z) order and are used as given, not normalized: a vector is rotated
by ``v + w t + a x t`` with ``t = 2 a x v`` (``a`` the vector part), which is the rotation for unit
quaternions and the same polynomial as :func:`warpavatar.geometry.quat_rotate` for any other. The direction
is normalized before and after the two rotations (lengths clamped at 1e-12), as the torch code does.
Launchers take Warp arrays, check their sizes and skip empty work; the torch bridge is
:mod:`warpavatar._src.shading`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = ["SH_MAX_DEGREE", "NORM_FLOOR", "vec16", "view_colors_forward", "view_colors_backward"]

SH_MAX_DEGREE = 3
"""Highest spherical-harmonics degree the kernels evaluate ((3 + 1)^2 = 16 coefficients per channel)."""

NORM_FLOOR = 1e-12
"""Smallest length a direction is divided by (the torch code's ``clamp_min(1e-12)``)."""

vec16 = wp.types.vector(length=16, dtype=wp.float32)
"""Sixteen float32 values: the SH basis (or its cotangent) up to degree 3, unused entries zero."""

# Real SH constants (3DGS order): band 0, band 1, band 2, band 3.
_C0 = wp.constant(0.28209479177387814)
_C1 = wp.constant(0.4886025119029199)
_C2_XY = wp.constant(1.0925484305920792)
_C2_ZZ = wp.constant(0.9461746957575601)
_C2_OFFSET = wp.constant(0.31539156525252005)
_C2_XX_YY = wp.constant(0.5462742152960396)
_C3_S2 = wp.constant(0.5900435899266435)
_C3_ZS1 = wp.constant(1.445305721320277)
_C3_BAND_ZZ = wp.constant(2.285228997322329)
_C3_BAND = wp.constant(0.4570457994644658)
_C3_ZZZ = wp.constant(1.865881662950577)
_C3_Z = wp.constant(1.119528997770346)
_NORM_FLOOR = wp.constant(NORM_FLOOR)


@wp.func
def _sh_basis(degree: int, u: wp.vec3):
    """Real SH basis of a unit direction ``u`` up to ``degree``; entries past ``(degree + 1)^2`` stay zero."""
    x = u[0]
    y = u[1]
    z = u[2]
    b = vec16()
    b[0] = _C0
    if degree >= 1:
        b[1] = -_C1 * y
        b[2] = _C1 * z
        b[3] = -_C1 * x
    if degree >= 2:
        zz = z * z
        b[4] = _C2_XY * x * y
        b[5] = -_C2_XY * z * y
        b[6] = _C2_ZZ * zz - _C2_OFFSET
        b[7] = -_C2_XY * z * x
        b[8] = _C2_XX_YY * (x * x - y * y)
    if degree >= 3:
        zz = z * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        band = -_C3_BAND_ZZ * zz + _C3_BAND
        b[9] = -_C3_S2 * s2
        b[10] = _C3_ZS1 * z * s1
        b[11] = band * y
        b[12] = z * (_C3_ZZZ * zz - _C3_Z)
        b[13] = band * x
        b[14] = _C3_ZS1 * z * c1
        b[15] = -_C3_S2 * c2
    return b


@wp.func
def _sh_basis_vjp(degree: int, u: wp.vec3, g: vec16):
    """``sum_k g[k] d basis_k / d u`` with ``u``'s components taken as independent (not yet on the sphere)."""
    x = u[0]
    y = u[1]
    z = u[2]
    gx = float(0.0)
    gy = float(0.0)
    gz = float(0.0)
    if degree >= 1:
        gx -= _C1 * g[3]
        gy -= _C1 * g[1]
        gz += _C1 * g[2]
    if degree >= 2:
        gx += _C2_XY * (y * g[4] - z * g[7]) + 2.0 * _C2_XX_YY * x * g[8]
        gy += _C2_XY * (x * g[4] - z * g[5]) - 2.0 * _C2_XX_YY * y * g[8]
        gz += -_C2_XY * (y * g[5] + x * g[7]) + 2.0 * _C2_ZZ * z * g[6]
    if degree >= 3:
        zz = z * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        band = -_C3_BAND_ZZ * zz + _C3_BAND
        d_band_dz = -2.0 * _C3_BAND_ZZ * z
        # s2 = 3x^2 y - y^3 and c2 = x^3 - 3 x y^2, so ds2/dx = 6xy = -dc2/dy and ds2/dy = 3 c1 = dc2/dx
        gx += (-_C3_S2 * 3.0 * s1 * g[9] + _C3_ZS1 * z * 2.0 * y * g[10] + band * g[13]
               + _C3_ZS1 * z * 2.0 * x * g[14] - _C3_S2 * 3.0 * c1 * g[15])
        gy += (-_C3_S2 * 3.0 * c1 * g[9] + _C3_ZS1 * z * 2.0 * x * g[10] + band * g[11]
               - _C3_ZS1 * z * 2.0 * y * g[14] + _C3_S2 * 3.0 * s1 * g[15])
        gz += (_C3_ZS1 * s1 * g[10] + d_band_dz * (y * g[11] + x * g[13])
               + (3.0 * _C3_ZZZ * zz - _C3_Z) * g[12] + _C3_ZS1 * c1 * g[14])
    return wp.vec3(gx, gy, gz)


@wp.func
def _rotate(w: float, a: wp.vec3, v: wp.vec3):
    """``v + w t + a x t`` with ``t = 2 a x v``: ``v`` rotated by the quaternion (w, a) when it is unit."""
    t = 2.0 * wp.cross(a, v)
    return v + w * t + wp.cross(a, t)


@wp.func
def _normalize_vjp(v: wp.vec3, g: wp.vec3):
    """Cotangent of ``v`` for ``v / max(|v|, NORM_FLOOR)`` given the result's cotangent ``g``."""
    length = wp.length(v)
    if length > _NORM_FLOOR:
        u = v / length
        return (g - u * wp.dot(u, g)) / length
    return g / _NORM_FLOOR


@wp.func
def _safe_normalize(v: wp.vec3):
    return v / wp.max(wp.length(v), _NORM_FLOOR)


@wp.func
def _canonical_direction(mean: wp.vec3, origin: wp.vec3, quat: wp.vec4, canonical_quat: wp.vec4):
    """Unit view direction in the canonical frame and the two intermediate directions the backward needs."""
    d0 = _safe_normalize(mean - origin)
    # inverse of the posed rotation: the vector part negated
    d1 = _rotate(quat[0], -wp.vec3(quat[1], quat[2], quat[3]), d0)
    d2 = _rotate(canonical_quat[0], wp.vec3(canonical_quat[1], canonical_quat[2], canonical_quat[3]), d1)
    return d0, d1, d2


@wp.func
def _shade(means: wp.array(dtype=wp.vec3), quats: wp.array(dtype=wp.vec4),
           canonical_quats: wp.array(dtype=wp.vec4), coefficients: wp.array2d(dtype=wp.vec3),
           origin: wp.array(dtype=wp.vec3), degree: int, i: int):
    """Gaussian i's directions (d0, d1, d2), unit canonical direction, SH basis and unclamped colour."""
    d0 = wp.vec3()
    d1 = wp.vec3()
    d2 = wp.vec3()
    u = wp.vec3(0.0, 0.0, 1.0)  # unused at degree 0 (the constant band has no direction)
    if degree > 0:
        d0, d1, d2 = _canonical_direction(means[i], origin[0], quats[i], canonical_quats[i])
        u = _safe_normalize(d2)
    basis = _sh_basis(degree, u)
    color = wp.vec3(0.5, 0.5, 0.5)
    for k in range((degree + 1) * (degree + 1)):
        color += basis[k] * coefficients[i, k]
    return d0, d1, d2, u, basis, color


@wp.kernel(enable_backward=False)
def view_colors_forward_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    canonical_quats: wp.array(dtype=wp.vec4),
    coefficients: wp.array2d(dtype=wp.vec3),
    origin: wp.array(dtype=wp.vec3),
    degree: int,
    colors: wp.array(dtype=wp.vec3),
):
    """One thread per Gaussian: colors[i] = max(sum_k basis_k(direction_i) coefficients[i, k] + 0.5, 0)."""
    i = wp.tid()
    d0, d1, d2, u, basis, color = _shade(means, quats, canonical_quats, coefficients, origin, degree, i)
    colors[i] = wp.vec3(wp.max(color[0], 0.0), wp.max(color[1], 0.0), wp.max(color[2], 0.0))


@wp.func
def _rotate_vjp(w: float, a: wp.vec3, v: wp.vec3, g: wp.vec3):
    """Cotangents (of w, of a, of v) of ``_rotate(w, a, v)`` given the result's cotangent ``g``."""
    t = 2.0 * wp.cross(a, v)
    g_t = w * g + wp.cross(g, a)
    g_w = wp.dot(g, t)
    g_a = wp.cross(t, g) + 2.0 * wp.cross(v, g_t)
    g_v = g + 2.0 * wp.cross(g_t, a)
    return g_w, g_a, g_v


@wp.kernel(enable_backward=False)
def view_colors_backward_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    canonical_quats: wp.array(dtype=wp.vec4),
    coefficients: wp.array2d(dtype=wp.vec3),
    origin: wp.array(dtype=wp.vec3),
    degree: int,
    grad_colors: wp.array(dtype=wp.vec3),
    grad_means: wp.array(dtype=wp.vec3),
    grad_quats: wp.array(dtype=wp.vec4),
    grad_canonical_quats: wp.array(dtype=wp.vec4),
    grad_coefficients: wp.array2d(dtype=wp.vec3),
):
    """One thread per Gaussian: every gradient of Gaussian i (the clamp passes none where the sum is < 0)."""
    i = wp.tid()
    d0, d1, d2, u, basis, color = _shade(means, quats, canonical_quats, coefficients, origin, degree, i)
    coefficient_count = (degree + 1) * (degree + 1)
    g_out = grad_colors[i]
    g_color = wp.vec3(0.0, 0.0, 0.0)
    for c in range(3):
        if color[c] >= 0.0:  # torch's clamp_min passes the gradient where input >= bound
            g_color[c] = g_out[c]
    g_basis = vec16()
    for k in range(coefficient_count):
        grad_coefficients[i, k] = basis[k] * g_color
        g_basis[k] = wp.dot(coefficients[i, k], g_color)
    if degree == 0:
        grad_means[i] = wp.vec3(0.0, 0.0, 0.0)
        grad_quats[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        grad_canonical_quats[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        return
    g_d2 = _normalize_vjp(d2, _sh_basis_vjp(degree, u, g_basis))
    qc = canonical_quats[i]
    gc_w, gc_a, g_d1 = _rotate_vjp(qc[0], wp.vec3(qc[1], qc[2], qc[3]), d1, g_d2)
    grad_canonical_quats[i] = wp.vec4(gc_w, gc_a[0], gc_a[1], gc_a[2])
    q = quats[i]
    gq_w, gq_neg_a, g_d0 = _rotate_vjp(q[0], -wp.vec3(q[1], q[2], q[3]), d0, g_d1)
    grad_quats[i] = wp.vec4(gq_w, -gq_neg_a[0], -gq_neg_a[1], -gq_neg_a[2])
    grad_means[i] = _normalize_vjp(means[i] - origin[0], g_d0)


def _check_sizes(means, quats, canonical_quats, coefficients, origin, degree):
    if not 0 <= degree <= SH_MAX_DEGREE:
        raise ValueError(f"SH degree must be 0..{SH_MAX_DEGREE}, got {degree}")
    count = means.shape[0]
    for name, array in (("quats", quats), ("canonical_quats", canonical_quats)):
        if array.shape[0] != count:
            raise ValueError(f"{name} holds {array.shape[0]} entries, means holds {count}")
    if coefficients.shape[0] != count or coefficients.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"coefficients must be [{count}, >= {(degree + 1) ** 2}] at degree {degree}, "
                         f"got {list(coefficients.shape)}")
    if origin.shape[0] != 1:
        raise ValueError(f"origin must hold one point, got {origin.shape[0]}")
    return count


def view_colors_forward(means: wp.array, quats: wp.array, canonical_quats: wp.array, coefficients: wp.array,
                        origin: wp.array, colors: wp.array, *, degree: int) -> None:
    """Launch :func:`view_colors_forward_kernel` on ``means``' device.

    Args:
        means: ``vec3[N]`` posed centres (world units).
        quats: ``vec4[N]`` posed orientations (w, x, y, z).
        canonical_quats: ``vec4[N]`` rest-pose orientations (w, x, y, z).
        coefficients: ``vec3[N, K]`` SH coefficients per RGB channel, ``K >= (degree + 1)^2``.
        origin: ``vec3[1]`` the point directions start from (world units).
        colors: ``vec3[N]`` output RGB.
        degree: SH degree 0..3.
    """
    count = _check_sizes(means, quats, canonical_quats, coefficients, origin, degree)
    if colors.shape[0] != count:
        raise ValueError(f"colors holds {colors.shape[0]} entries, means holds {count}")
    if count:
        launch(view_colors_forward_kernel, dim=count,
                  inputs=[means, quats, canonical_quats, coefficients, origin, degree], outputs=[colors],
                  device=means.device)


def view_colors_backward(means: wp.array, quats: wp.array, canonical_quats: wp.array, coefficients: wp.array,
                         origin: wp.array, grad_colors: wp.array, grad_means: wp.array, grad_quats: wp.array,
                         grad_canonical_quats: wp.array, grad_coefficients: wp.array, *, degree: int) -> None:
    """Launch :func:`view_colors_backward_kernel`: the forward's inputs, ``grad_colors`` ``vec3[N]``, and the
    outputs ``grad_means`` ``vec3[N]``, ``grad_quats`` and ``grad_canonical_quats`` ``vec4[N]``,
    ``grad_coefficients`` ``vec3[N, K]`` (entries past ``(degree + 1)^2`` are left as they are)."""
    count = _check_sizes(means, quats, canonical_quats, coefficients, origin, degree)
    for name, array in (("grad_colors", grad_colors), ("grad_means", grad_means), ("grad_quats", grad_quats),
                        ("grad_canonical_quats", grad_canonical_quats), ("grad_coefficients", grad_coefficients)):
        if array.shape[0] != count:
            raise ValueError(f"{name} holds {array.shape[0]} entries, means holds {count}")
    if count:
        launch(view_colors_backward_kernel, dim=count,
                  inputs=[means, quats, canonical_quats, coefficients, origin, degree, grad_colors],
                  outputs=[grad_means, grad_quats, grad_canonical_quats, grad_coefficients], device=means.device)
