"""Warp kernels of a cloth substep's edge terms: the rest offsets of exact length springs and edge damping.

Per directed edge ``e = (i, j)`` (receiver ``i = edges[e, 0]``, sender ``j = edges[e, 1]``), with
``d = x_i - x_j`` and ``l = |d|``::

    rest_offset_e     = min(L_e, 2 l) * d / l          (0 where l <= 1e-12)
    damping_force_i  -= c_e * (v_i - v_j)               (summed over the edges that node i receives)

Given to :func:`warpavatar.ops.spring_step` as its rest offsets, the first makes ``k_e (x_i - x_j -
rest_offset_e)`` the exact length-spring force ``k_e (l - L'_e) d / l``; the clamp ``L'_e = min(L_e, 2 l)``
keeps a spring squeezed below half its rest length from pushing harder than ``k_e l`` (its transverse
stiffness stays within ``[-k_e, k_e]``). One thread per edge (``cloth_edge_terms``); the hand-written
backward (``cloth_edge_terms_adjoint``) writes the per-edge gradients and adds the node gradients with atomics.
Edges with an endpoint outside ``[0, M)`` are skipped (zero offset, no force, zero gradients). Float32.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch
from warpavatar.kernels.springs import edge_is_valid

__all__ = ["SHORT_EDGE", "launch_cloth_edge_terms", "launch_cloth_edge_terms_adjoint"]

SHORT_EDGE = wp.constant(1e-12)
"""Edge length [world units] at or below which an edge has no direction (its rest offset is 0)."""


@wp.func
def length_spring_offset(delta: wp.vec3, rest_length: float):
    """``min(L, 2 |d|) d / |d|`` of an edge ``d = x_i - x_j`` with rest length ``L`` (0 for ``|d| <= 1e-12``)."""
    length = wp.length(delta)
    if length > SHORT_EDGE:
        return (wp.min(rest_length, 2.0 * length) / length) * delta
    return wp.vec3(0.0)


@wp.kernel(enable_backward=False)
def cloth_edge_terms(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float32),
    edge_damping: wp.array(dtype=wp.float32),
    rest_offset: wp.array(dtype=wp.vec3),
    damping_force: wp.array(dtype=wp.vec3),
):
    # damping_force must be zero on entry.
    e = wp.tid()
    receiver = edges[e, 0]
    sender = edges[e, 1]
    if not edge_is_valid(receiver, sender, x.shape[0]):
        rest_offset[e] = wp.vec3(0.0)
        return
    rest_offset[e] = length_spring_offset(x[receiver] - x[sender], rest_length[e])
    wp.atomic_sub(damping_force, receiver, edge_damping[e] * (v[receiver] - v[sender]))


@wp.kernel(enable_backward=False)
def cloth_edge_terms_adjoint(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float32),
    edge_damping: wp.array(dtype=wp.float32),
    grad_rest_offset: wp.array(dtype=wp.vec3),
    grad_damping_force: wp.array(dtype=wp.vec3),
    grad_x: wp.array(dtype=wp.vec3),
    grad_v: wp.array(dtype=wp.vec3),
    grad_rest_length: wp.array(dtype=wp.float32),
    grad_edge_damping: wp.array(dtype=wp.float32),
):
    # grad_x and grad_v must be zero on entry. With u = d / l and g = dL/d rest_offset_e:
    #   unclamped (L < 2 l): d offset/d d = (L / l)(I - u u^T), d offset/d L = u;
    #   clamped (offset = 2 d): d offset/d d = 2 I, d offset/d L = 0.
    # With h = dL/d damping_force_i: dL/dc_e = -h . (v_i - v_j), dL/dv_i -= c_e h, dL/dv_j += c_e h.
    e = wp.tid()
    receiver = edges[e, 0]
    sender = edges[e, 1]
    if not edge_is_valid(receiver, sender, x.shape[0]):
        grad_rest_length[e] = 0.0
        grad_edge_damping[e] = 0.0
        return
    g = grad_rest_offset[e]
    delta = x[receiver] - x[sender]
    length = wp.length(delta)
    grad_delta = wp.vec3(0.0)
    grad_length = float(0.0)
    if length > SHORT_EDGE:
        unit = delta / length
        rest = rest_length[e]
        if rest < 2.0 * length:
            grad_delta = (rest / length) * (g - wp.dot(unit, g) * unit)
            grad_length = wp.dot(unit, g)
        else:
            grad_delta = 2.0 * g
    grad_rest_length[e] = grad_length
    wp.atomic_add(grad_x, receiver, grad_delta)
    wp.atomic_sub(grad_x, sender, grad_delta)
    h = grad_damping_force[receiver]
    c = edge_damping[e]
    grad_edge_damping[e] = -wp.dot(h, v[receiver] - v[sender])
    wp.atomic_sub(grad_v, receiver, c * h)
    wp.atomic_add(grad_v, sender, c * h)


def _check(x: wp.array, v: wp.array, edges: wp.array, *per_edge: wp.array, per_node=()) -> None:
    if edges.ndim != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape [E, 2], got {edges.shape}")
    for array in per_edge:
        if array.shape[0] != edges.shape[0]:
            raise ValueError(f"per-edge arrays must have {edges.shape[0]} rows, got {array.shape[0]}")
    for array in (v, *per_node):
        if array.shape[0] != x.shape[0]:
            raise ValueError(f"per-node arrays must have {x.shape[0]} rows, got {array.shape[0]}")


def launch_cloth_edge_terms(
    x: wp.array,
    v: wp.array,
    edges: wp.array,
    rest_length: wp.array,
    edge_damping: wp.array,
    rest_offset: wp.array,
    damping_force: wp.array,
) -> None:
    """Write ``rest_offset`` (vec3 ``[E]``) and add the edge damping into ``damping_force`` (vec3 ``[M]``, zero
    on entry); ``x, v`` vec3 ``[M]``, ``edges`` int32 ``[E, 2]``, ``rest_length, edge_damping`` float32 ``[E]``."""
    _check(x, v, edges, rest_length, edge_damping, rest_offset, per_node=(damping_force,))
    if edges.shape[0] == 0:
        return
    launch(
        cloth_edge_terms,
        dim=edges.shape[0],
        inputs=[x, v, edges, rest_length, edge_damping],
        outputs=[rest_offset, damping_force],
        device=x.device,
    )


def launch_cloth_edge_terms_adjoint(
    x: wp.array,
    v: wp.array,
    edges: wp.array,
    rest_length: wp.array,
    edge_damping: wp.array,
    grad_rest_offset: wp.array,
    grad_damping_force: wp.array,
    grad_x: wp.array,
    grad_v: wp.array,
    grad_rest_length: wp.array,
    grad_edge_damping: wp.array,
) -> None:
    """Backward pass: adds to ``grad_x, grad_v`` (``[M]``, zero on entry), writes the per-edge gradients."""
    _check(x, v, edges, rest_length, edge_damping, grad_rest_offset, grad_rest_length, grad_edge_damping,
           per_node=(grad_damping_force, grad_x, grad_v))
    if edges.shape[0] == 0:
        return
    launch(
        cloth_edge_terms_adjoint,
        dim=edges.shape[0],
        inputs=[x, v, edges, rest_length, edge_damping, grad_rest_offset, grad_damping_force],
        outputs=[grad_x, grad_v, grad_rest_length, grad_edge_damping],
        device=x.device,
    )
