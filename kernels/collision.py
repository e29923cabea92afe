"""Warp kernels of particle-capsule collision: pushing particles out of a set of capsules (the body).

A capsule ``c`` is the set of points within ``radius_c`` of the segment ``a_c b_c``. For a particle ``x`` and
one capsule (``d = b - a``)::

    t = clamp(dot(x - a, d) / dot(d, d), 0, 1)      (0 for a segment shorter than 1e-6)
    p = a + t d                                      closest point of the segment
    r = x - p,  n = r / |r|                          outward normal (a fixed perpendicular of d on the axis)
    push = (p + radius n) - x    if |r| < radius,    else 0

and the particle moves by the sum of the pushes of every capsule, all computed from the same input position
(Jacobi style): one pass is a pure function of its inputs; a caller may apply it again where capsules
overlap. On the axis (``|r| <= 1e-9``) the normal is ``normalize(cross(d, e))`` with ``e`` the coordinate
axis least aligned with ``d``, or ``+z`` for a degenerate segment; that fallback normal carries no gradient.

Launch plan: one thread per particle loops over the capsules (``capsule_push_out``); the hand-written
backward (``capsule_push_out_adjoint``, the loop has a run-time length) writes the particle's gradient and
adds the capsules' gradients atomically, one atomic per capsule that holds the particle. Everything is
float32.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = ["AXIS_EPSILON", "SEGMENT_EPSILON_SQ", "launch_capsule_push_out", "launch_capsule_push_out_adjoint"]

AXIS_EPSILON = wp.constant(1e-9)
"""Distance to the segment [world units] below which a particle counts as on the axis."""

SEGMENT_EPSILON_SQ = wp.constant(1e-12)
"""Squared segment length [world units^2] below which a capsule is a sphere around its start."""


@wp.func
def fallback_normal(d: wp.vec3):
    """A unit vector perpendicular to ``d`` (``+z`` for a degenerate ``d``), the normal of on-axis particles."""
    if wp.length_sq(d) <= SEGMENT_EPSILON_SQ:
        return wp.vec3(0.0, 0.0, 1.0)
    ax = wp.abs(d[0])
    ay = wp.abs(d[1])
    az = wp.abs(d[2])
    e = wp.vec3(1.0, 0.0, 0.0)
    if ay <= ax and ay <= az:
        e = wp.vec3(0.0, 1.0, 0.0)
    elif az < ax and az < ay:
        e = wp.vec3(0.0, 0.0, 1.0)
    return wp.normalize(wp.cross(d, e))


@wp.func
def outward_normal(r: wp.vec3, distance: float, d: wp.vec3):
    """``r / distance``, or the fallback normal of ``d`` for a particle on the axis."""
    if distance > AXIS_EPSILON:
        return r / distance
    return fallback_normal(d)


@wp.func
def segment_parameter(x: wp.vec3, a: wp.vec3, d: wp.vec3):
    """Unclamped parameter ``dot(x - a, d) / |d|^2`` of the closest point on the line (0 for a short segment)."""
    length_sq = wp.length_sq(d)
    if length_sq <= SEGMENT_EPSILON_SQ:
        return 0.0
    return wp.dot(x - a, d) / length_sq


@wp.func
def capsule_push(position: wp.vec3, a: wp.vec3, b: wp.vec3, capsule_radius: float):
    """The move of ``position`` out of the capsule ``(a, b, capsule_radius)`` onto its surface (0 if outside).

    A point inside lies within the segment's bounding box grown by the radius on every axis: points outside
    that box grown a little more (0.1 % of the radius and 1e-5, far above float32 rounding) are skipped early,
    with the same result."""
    margin = capsule_radius * 1.001 + 1.0e-5
    low = wp.min(a, b) - wp.vec3(margin)
    high = wp.max(a, b) + wp.vec3(margin)
    for k in range(3):
        if position[k] < low[k] or position[k] > high[k]:
            return wp.vec3(0.0)
    d = b - a
    t = wp.clamp(segment_parameter(position, a, d), 0.0, 1.0)
    closest = a + t * d
    r = position - closest
    distance = wp.length(r)
    if distance < capsule_radius:
        return closest + capsule_radius * outward_normal(r, distance, d) - position
    return wp.vec3(0.0)


@wp.kernel(enable_backward=False)
def capsule_push_out(
    x: wp.array(dtype=wp.vec3),
    segment_start: wp.array(dtype=wp.vec3),
    segment_end: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    x_out: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    position = x[i]
    total = wp.vec3(0.0)
    for c in range(segment_start.shape[0]):
        total = total + capsule_push(position, segment_start[c], segment_end[c], radius[c])
    x_out[i] = position + total


@wp.kernel(enable_backward=False)
def capsule_push_out_adjoint(
    x: wp.array(dtype=wp.vec3),
    segment_start: wp.array(dtype=wp.vec3),
    segment_end: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    grad_x_out: wp.array(dtype=wp.vec3),
    grad_x: wp.array(dtype=wp.vec3),
    grad_segment_start: wp.array(dtype=wp.vec3),
    grad_segment_end: wp.array(dtype=wp.vec3),
    grad_radius: wp.array(dtype=wp.float32),
):
    # With g = dL/dx_out, a capsule holding the particle adds push = p + R n - x, n = r/|r|, r = x - p:
    #   d push/d r = (R/|r|)(I - n n^T) - I  (symmetric; -I on the axis, where n is held fixed),
    #   g_r = (R/|r|)(g - n (n.g)) - g,  dL/dR = n.g,  dL/dx += g_r,  dL/dp = -g_r;
    #   p = a + t d with t = s = dot(x - a, d)/|d|^2 strictly inside (0, 1) (else t is constant), so with
    #   h = dot(dL/dp, d): dL/dx += h d/|d|^2, dL/da = (1 - t) dL/dp + h (2 s d - d - w)/|d|^2,
    #   dL/db = t dL/dp + h (w - 2 s d)/|d|^2, where w = x - a.
    i = wp.tid()
    position = x[i]
    g = grad_x_out[i]
    total = g
    for c in range(segment_start.shape[0]):
        a = segment_start[c]
        d = segment_end[c] - a
        s = segment_parameter(position, a, d)
        t = wp.clamp(s, 0.0, 1.0)
        closest = a + t * d
        r = position - closest
        distance = wp.length(r)
        capsule_radius = radius[c]
        if distance < capsule_radius:
            normal = outward_normal(r, distance, d)
            grad_r = -g
            if distance > AXIS_EPSILON:
                grad_r = (capsule_radius / distance) * (g - wp.dot(normal, g) * normal) - g
            wp.atomic_add(grad_radius, c, wp.dot(normal, g))
            total = total + grad_r
            grad_closest = -grad_r
            grad_a = (1.0 - t) * grad_closest
            grad_b = t * grad_closest
            length_sq = wp.length_sq(d)
            if s > 0.0 and s < 1.0 and length_sq > SEGMENT_EPSILON_SQ:
                h = wp.dot(grad_closest, d) / length_sq
                w = position - a
                total = total + h * d
                grad_a = grad_a + h * (2.0 * s * d - d - w)
                grad_b = grad_b + h * (w - 2.0 * s * d)
            wp.atomic_add(grad_segment_start, c, grad_a)
            wp.atomic_add(grad_segment_end, c, grad_b)
    grad_x[i] = total


def _check(x: wp.array, segment_start: wp.array, segment_end: wp.array, radius: wp.array, *per_particle) -> None:
    capsule_count = segment_start.shape[0]
    for name, array in (("segment_end", segment_end), ("radius", radius)):
        if array.shape[0] != capsule_count:
            raise ValueError(f"{name} must have {capsule_count} rows, got {array.shape[0]}")
    for array in per_particle:
        if array.shape[0] != x.shape[0]:
            raise ValueError(f"per-particle arrays must have {x.shape[0]} rows, got {array.shape[0]}")


def launch_capsule_push_out(
    x: wp.array, segment_start: wp.array, segment_end: wp.array, radius: wp.array, x_out: wp.array
) -> None:
    """Write every particle, pushed out of the capsules, to ``x_out``.

    Args:
        x: particle positions, vec3 ``[N]``.
        segment_start, segment_end: capsule segment endpoints, vec3 ``[C]``; radius: float32 ``[C]``.
        x_out: vec3 ``[N]`` output (every row written).
    """
    _check(x, segment_start, segment_end, radius, x_out)
    if x.shape[0] == 0:
        return
    launch(
        capsule_push_out,
        dim=x.shape[0],
        inputs=[x, segment_start, segment_end, radius],
        outputs=[x_out],
        device=x.device,
    )


def launch_capsule_push_out_adjoint(
    x: wp.array,
    segment_start: wp.array,
    segment_end: wp.array,
    radius: wp.array,
    grad_x_out: wp.array,
    grad_x: wp.array,
    grad_segment_start: wp.array,
    grad_segment_end: wp.array,
    grad_radius: wp.array,
) -> None:
    """Backward pass: writes ``grad_x [N]``, adds to the capsule gradients (``[C]``, zero on entry)."""
    _check(x, segment_start, segment_end, radius, grad_x_out, grad_x)
    _check(x, grad_segment_start, grad_segment_end, grad_radius)
    if x.shape[0] == 0:
        return
    launch(
        capsule_push_out_adjoint,
        dim=x.shape[0],
        inputs=[x, segment_start, segment_end, radius, grad_x_out],
        outputs=[grad_x, grad_segment_start, grad_segment_end, grad_radius],
        device=x.device,
    )
