"""Warp kernel of a whole cloth substep, fused: one thread per node, no atomics, for rollouts without gradients.

A substep of :meth:`warpavatar.sim.ClothModel.step` run op by op is about twenty launches (edge terms, the
spring step, the attachment, the capsules' interpolation, the push out of them, the velocity correction);
``cloth_substep`` does all of it for one node ``i`` in one thread, reading the state of the substep before
(``x, v``) and writing new arrays (``x_out, v_out``), so no thread reads what another writes:

* its edges, from a CSR adjacency sorted by receiver (``row_start [M+1]``, ``neighbour [E]`` and per directed
  edge ``stiffness``, ``rest_length``, ``edge_damping``): the exact length spring with the rest offset
  ``min(L, 2 |d|) d / |d|`` (:func:`~warpavatar.kernels.cloth.length_spring_offset`) and the edge damping
  ``-c (v_i - v_j)``, summed in registers;
* the semi-implicit Euler update of :func:`warpavatar.ops.spring_step`, ``a = (F + f_damp - drag v - s) / m``,
  ``v' = v + h a``, ``x' = x + h v'``;
* an attached node instead goes to its target on the straight line from its position at the frame's start
  (``frame_start``) to ``attachment_targets[slot]`` at this substep's fraction (the target itself at the last
  substep), with that line's velocity;
* a free node is then pushed out of the capsules interpolated at the substep's fraction between the frame's
  first and last ones (:func:`~warpavatar.kernels.collision.capsule_push`, the sum of every capsule's push
  from the same position) and its velocity corrected by the move over ``h``.

A frame is one launch per substep (plus one per Jacobi pass of strain limiting after each, with
:func:`record_strain_limit`); a single launch looping over the substeps would need every node's previous substep,
i.e. a grid-wide synchronization between substeps, which a Warp kernel does not have. Float32.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.cloth import length_spring_offset
from warpavatar.kernels.collision import capsule_push

__all__ = ["record_cloth_substep", "record_strain_limit"]


@wp.kernel(enable_backward=False)
def cloth_substep(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    frame_start: wp.array(dtype=wp.vec3),
    row_start: wp.array(dtype=wp.int32),
    neighbour: wp.array(dtype=wp.int32),
    stiffness: wp.array(dtype=wp.float32),
    rest_length: wp.array(dtype=wp.float32),
    edge_damping: wp.array(dtype=wp.float32),
    drag: wp.array(dtype=wp.float32),
    mass: wp.array(dtype=wp.float32),
    constant_force: wp.array(dtype=wp.vec3),
    attached_slot: wp.array(dtype=wp.int32),
    attachment_targets: wp.array(dtype=wp.vec3),
    frame_interval: float,
    capsule_start_before: wp.array(dtype=wp.vec3),
    capsule_end_before: wp.array(dtype=wp.vec3),
    capsule_radius_before: wp.array(dtype=wp.float32),
    capsule_start_after: wp.array(dtype=wp.vec3),
    capsule_end_after: wp.array(dtype=wp.vec3),
    capsule_radius_after: wp.array(dtype=wp.float32),
    substep: int,
    substeps: int,
    h: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    fraction = float(substep) / float(substeps)
    slot = attached_slot[i]
    if slot >= 0:
        start = frame_start[i]
        target = attachment_targets[slot]
        if substep < substeps:
            target = start + fraction * (target - start)
        x_out[i] = target
        v_out[i] = (attachment_targets[slot] - start) / frame_interval
        return
    position = x[i]
    velocity = v[i]
    spring = wp.vec3(0.0)
    damping_force = wp.vec3(0.0)
    for e in range(row_start[i], row_start[i + 1]):
        j = neighbour[e]
        delta = position - x[j]
        damping_force = damping_force - edge_damping[e] * (velocity - v[j])
        spring = spring + stiffness[e] * (delta - length_spring_offset(delta, rest_length[e]))
    acceleration = ((constant_force[i] + damping_force) - drag[i] * velocity - spring) / mass[i]
    velocity_next = velocity + h * acceleration
    position_next = position + h * velocity_next
    push = wp.vec3(0.0)
    for c in range(capsule_start_after.shape[0]):
        a = capsule_start_before[c]
        b = capsule_end_before[c]
        r = capsule_radius_before[c]
        a = a + fraction * (capsule_start_after[c] - a)
        b = b + fraction * (capsule_end_after[c] - b)
        r = r + fraction * (capsule_radius_after[c] - r)
        push = push + capsule_push(position_next, a, b, r)
    pushed = position_next + push
    v_out[i] = velocity_next + (pushed - position_next) / h
    x_out[i] = pushed


STRAIN_RAMP = wp.constant(0.01)
"""An edge counts fully in a node's mean of strain corrections once it is this fraction past its limit."""


@wp.kernel(enable_backward=False)
def limit_strain(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    row_start: wp.array(dtype=wp.int32),
    neighbour: wp.array(dtype=wp.int32),
    limit_length: wp.array(dtype=wp.float32),
    attached_slot: wp.array(dtype=wp.int32),
    h: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    # one Jacobi pass of strain limiting for node i (see record_strain_limit)
    i = wp.tid()
    position = x[i]
    if attached_slot[i] >= 0:
        x_out[i] = position
        v_out[i] = v[i]
        return
    move = wp.vec3(0.0)
    counted = float(0.0)  # the violated edges, each weighted by how far past its limit (up to 1)
    for e in range(row_start[i], row_start[i + 1]):
        limit = limit_length[e]
        if limit > 0.0:
            j = neighbour[e]
            delta = x[j] - position
            length = wp.length(delta)
            if length > limit:
                share = float(0.5)
                if attached_slot[j] >= 0:
                    share = 1.0
                move = move + (share * (length - limit) / length) * delta
                counted = counted + wp.min(1.0, (length - limit) / (STRAIN_RAMP * limit))
    move = move / wp.max(counted, 1.0)
    x_out[i] = position + move
    v_out[i] = v[i] + move / h


def record_strain_limit(x: wp.array, v: wp.array, row_start: wp.array, neighbour: wp.array, limit_length: wp.array,
                        attached_slot: wp.array, h: float, x_out: wp.array, v_out: wp.array) -> wp.Launch | None:
    """Record one Jacobi pass of strain limiting (Provot 1995) without running it; None when there are no nodes.

    Every free node ``i`` moves by the sum, over its edges ``e = (i, j)`` longer than their limit ``l_e``
    (``limit_length [E]``, 0: no limit, e.g. a bend edge), of ``s (|d| - l_e) d / |d|`` with ``d = x_j - x_i``
    and ``s`` 1/2 (both ends move) or 1 (``j`` attached), over ``max(1, n)``: ``n`` counts those edges, each
    by ``min(1, (|d| - l_e) / (STRAIN_RAMP l_e))`` (a mean over the violated edges that does not jump when an
    edge crosses its limit); its velocity changes by the move over ``h`` [s].
    Attached nodes stay. Arrays as in :func:`record_cloth_substep`; ``x_out, v_out`` distinct from ``x, v``.
    """
    node_count = x.shape[0]
    _check_graph(node_count, (v, attached_slot, x_out, v_out), row_start, neighbour, (limit_length,))
    if node_count == 0:
        return None
    return wp.launch(limit_strain, dim=node_count,
                     inputs=[x, v, row_start, neighbour, limit_length, attached_slot, float(h)],
                     outputs=[x_out, v_out], device=x.device, record_cmd=True)


def _check_graph(node_count: int, per_node, row_start, neighbour, per_edge) -> None:
    """Rows of the per-node arrays, of the CSR offsets and of the per-edge arrays."""
    for array in per_node:
        if array.shape[0] != node_count:
            raise ValueError(f"per-node arrays must have {node_count} rows, got {array.shape[0]}")
    if row_start.shape[0] != node_count + 1:
        raise ValueError(f"row_start must have {node_count + 1} rows, got {row_start.shape[0]}")
    for array in per_edge:
        if array.shape[0] != neighbour.shape[0]:
            raise ValueError(f"per-edge arrays must have {neighbour.shape[0]} rows, got {array.shape[0]}")


def _check(x, v, frame_start, row_start, neighbour, stiffness, rest_length, edge_damping, drag, mass,
           constant_force, attached_slot, capsules_before, capsules_after, x_out, v_out) -> None:
    # (attachment_targets is indexed through attached_slot: its rows are the caller's business)
    _check_graph(x.shape[0], (v, frame_start, drag, mass, constant_force, attached_slot, x_out, v_out), row_start,
                 neighbour, (stiffness, rest_length, edge_damping))
    capsule_count = capsules_after[0].shape[0]
    for array in (*capsules_before, *capsules_after):
        if array.shape[0] != capsule_count:
            raise ValueError(f"capsule arrays must have {capsule_count} rows, got {array.shape[0]}")


def record_cloth_substep(
    x: wp.array,
    v: wp.array,
    frame_start: wp.array,
    row_start: wp.array,
    neighbour: wp.array,
    stiffness: wp.array,
    rest_length: wp.array,
    edge_damping: wp.array,
    drag: wp.array,
    mass: wp.array,
    constant_force: wp.array,
    attached_slot: wp.array,
    attachment_targets: wp.array,
    frame_interval: float,
    capsules_before: tuple[wp.array, wp.array, wp.array],
    capsules_after: tuple[wp.array, wp.array, wp.array],
    substep: int,
    substeps: int,
    h: float,
    x_out: wp.array,
    v_out: wp.array,
) -> wp.Launch | None:
    """Check the arrays and record the launch of one substep without running it (``.launch()`` runs it, as
    often as wanted, on the device's current stream); None when there are no nodes.

    Args:
        x, v: the state of the substep before, vec3 ``[M]`` [world units, world units / s].
        frame_start: the positions at the frame's start, vec3 ``[M]`` (the attached nodes' lines start there).
        row_start: int32 ``[M+1]``, node ``i``'s edges are ``row_start[i]:row_start[i+1]``; ``neighbour``:
            int32 ``[E]`` the sender of each edge (every id in ``[0, M)``).
        stiffness, rest_length, edge_damping: float32 ``[E]`` per directed edge.
        drag, mass: float32 ``[M]``; constant_force: vec3 ``[M]`` (gravity and external forces) [N].
        attached_slot: int32 ``[M]``, the row of ``attachment_targets`` (vec3 ``[A]``) of an attached node, -1
            for a free one.
        frame_interval: the frame's duration [s] (the attached nodes' velocity).
        capsules_before, capsules_after: ``(segment_start, segment_end, radius)`` of the capsules at the frame's
            start and end, vec3/vec3/float32 ``[C]`` each (the same arrays twice for capsules that stay put).
        substep: ``1..substeps``, this substep's number (its fraction of the frame is ``substep / substeps``).
        h: the substep's duration [s].
        x_out, v_out: vec3 ``[M]`` outputs, every row written; distinct from ``x``, ``v`` and ``frame_start``.
    """
    _check(x, v, frame_start, row_start, neighbour, stiffness, rest_length, edge_damping, drag, mass,
           constant_force, attached_slot, capsules_before, capsules_after, x_out, v_out)
    if x.shape[0] == 0:
        return None
    return wp.launch(
        cloth_substep,
        dim=x.shape[0],
        inputs=[x, v, frame_start, row_start, neighbour, stiffness, rest_length, edge_damping, drag, mass,
                constant_force, attached_slot, attachment_targets, float(frame_interval), *capsules_before,
                *capsules_after, int(substep), int(substeps), float(h)],
        outputs=[x_out, v_out],
        device=x.device,
        record_cmd=True,
    )
