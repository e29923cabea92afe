"""Warp kernels of the mass-spring-damper step of SMAD (Eq. 2-4) and its regularizers (Eq. 11).

Step (per node ``i``, directed edges ``e = (i, j)``: receiver ``i = edges[e, 0]``, sender ``j = edges[e, 1]``)::

    s_i  = sum over edges e with receiver i of  k_e * (x_i - x_j - L_e)          (spring force sum)
    a_i  = (F_i - gamma_i * v_i - s_i) / m_i
    v'_i = v_i + dt * a_i
    x'_i = x_i + dt * v'_i

Launch plan, per step: ``spring_force`` (one thread per run of ``edges_per_thread`` consecutive edges) then
``spring_integrate`` (one thread per node); backward: ``spring_integrate_adjoint`` then ``spring_force_adjoint``.
Edges may come in any order. The edge kernels accumulate consecutive edges with the same receiver in
registers and flush each run with one atomic add, so edges sorted by receiver (as ``knn_graph`` produces
them) cost one atomic per node and chunk instead of one per edge; unsorted edges stay correct, just slower.
Edges with an endpoint outside ``[0, M)`` (such as the ``-1`` padding of ``knn_graph``) are skipped and get
zero gradients. Everything is float32.

Isometry and damping losses: one thread per edge (per velocity) writes its term, torch sums the terms (a
deterministic reduction), and the adjoint kernels scatter ``d loss / d input`` scaled by a device scalar,
so neither direction synchronizes with the host.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = [
    "EDGES_PER_THREAD",
    "launch_spring_force",
    "launch_spring_integrate",
    "launch_spring_integrate_adjoint",
    "launch_spring_force_adjoint",
    "launch_isometry_terms",
    "launch_isometry_adjoint",
    "launch_damping_terms",
    "launch_damping_adjoint",
]

EDGES_PER_THREAD = 8
"""Consecutive edges handled by one thread of the edge kernels (a run shares one atomic per receiver)."""


@wp.func
def edge_is_valid(receiver: int, sender: int, node_count: int):
    """Whether both endpoints of an edge index a node (``-1`` padding and out-of-range ids are not)."""
    return receiver >= 0 and receiver < node_count and sender >= 0 and sender < node_count


@wp.kernel(enable_backward=False)
def spring_force(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_offset: wp.array(dtype=wp.vec3),
    stiffness: wp.array(dtype=wp.float32),
    edges_per_thread: int,
    spring_force_sum: wp.array(dtype=wp.vec3),
):
    # spring_force_sum must be zero on entry; it receives s_i = sum_e k_e (x_i - x_j - L_e).
    tid = wp.tid()
    node_count = x.shape[0]
    begin = tid * edges_per_thread
    end = wp.min(begin + edges_per_thread, edges.shape[0])
    run_receiver = int(-1)
    run_force = wp.vec3(0.0)
    for e in range(begin, end):
        receiver = edges[e, 0]
        sender = edges[e, 1]
        if not edge_is_valid(receiver, sender, node_count):
            continue
        force = stiffness[e] * (x[receiver] - x[sender] - rest_offset[e])
        if receiver == run_receiver:
            run_force = run_force + force
        else:
            if run_receiver >= 0:
                wp.atomic_add(spring_force_sum, run_receiver, run_force)
            run_receiver = receiver
            run_force = force
    if run_receiver >= 0:
        wp.atomic_add(spring_force_sum, run_receiver, run_force)


@wp.kernel(enable_backward=False)
def spring_integrate(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    damping: wp.array(dtype=wp.float32),
    mass: wp.array(dtype=wp.float32),
    force: wp.array(dtype=wp.vec3),
    spring_force_sum: wp.array(dtype=wp.vec3),
    dt: float,
    x_next: wp.array(dtype=wp.vec3),
    v_next: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    velocity = v[i]
    acceleration = (force[i] - damping[i] * velocity - spring_force_sum[i]) / mass[i]
    velocity_next = velocity + dt * acceleration
    v_next[i] = velocity_next
    x_next[i] = x[i] + dt * velocity_next


@wp.kernel(enable_backward=False)
def spring_integrate_adjoint(
    v: wp.array(dtype=wp.vec3),
    damping: wp.array(dtype=wp.float32),
    mass: wp.array(dtype=wp.float32),
    force: wp.array(dtype=wp.vec3),
    spring_force_sum: wp.array(dtype=wp.vec3),
    grad_x_next: wp.array(dtype=wp.vec3),
    grad_v_next: wp.array(dtype=wp.vec3),
    dt: float,
    grad_x: wp.array(dtype=wp.vec3),
    grad_v: wp.array(dtype=wp.vec3),
    grad_damping: wp.array(dtype=wp.float32),
    grad_mass: wp.array(dtype=wp.float32),
    grad_force: wp.array(dtype=wp.vec3),
):
    # Node part of the backward pass. grad_x receives only the direct term d x'/d x = I here; the spring
    # terms are added by spring_force_adjoint, which reads grad_force (d L / d s_i = -grad_force_i).
    i = wp.tid()
    velocity = v[i]
    inverse_mass = 1.0 / mass[i]
    acceleration = (force[i] - damping[i] * velocity - spring_force_sum[i]) * inverse_mass
    grad_velocity_next = grad_v_next[i] + dt * grad_x_next[i]  # x' depends on v'
    grad_f = dt * inverse_mass * grad_velocity_next  # d L / d F_i = dt / m_i * dL/dv'_i
    grad_force[i] = grad_f
    grad_x[i] = grad_x_next[i]
    grad_v[i] = grad_velocity_next - damping[i] * grad_f
    grad_damping[i] = -wp.dot(velocity, grad_f)
    grad_mass[i] = -wp.dot(acceleration, grad_f)


@wp.kernel(enable_backward=False)
def spring_force_adjoint(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_offset: wp.array(dtype=wp.vec3),
    stiffness: wp.array(dtype=wp.float32),
    grad_force: wp.array(dtype=wp.vec3),
    edges_per_thread: int,
    grad_x: wp.array(dtype=wp.vec3),
    grad_rest_offset: wp.array(dtype=wp.vec3),
    grad_stiffness: wp.array(dtype=wp.float32),
):
    # Edge part of the backward pass: with g = d L / d s_i = -grad_force_i for the receiver i of edge e,
    #   dL/dk_e = g . (x_i - x_j - L_e),  dL/dL_e = -k_e g,  dL/dx_i += k_e g,  dL/dx_j -= k_e g.
    # grad_x already holds the node term; receiver terms are accumulated per run, sender terms atomically.
    tid = wp.tid()
    node_count = x.shape[0]
    begin = tid * edges_per_thread
    end = wp.min(begin + edges_per_thread, edges.shape[0])
    run_receiver = int(-1)
    run_grad = wp.vec3(0.0)
    for e in range(begin, end):
        receiver = edges[e, 0]
        sender = edges[e, 1]
        if not edge_is_valid(receiver, sender, node_count):
            grad_rest_offset[e] = wp.vec3(0.0)
            grad_stiffness[e] = 0.0
            continue
        grad_sum = -grad_force[receiver]
        k = stiffness[e]
        grad_stiffness[e] = wp.dot(grad_sum, x[receiver] - x[sender] - rest_offset[e])
        weighted = k * grad_sum
        grad_rest_offset[e] = -weighted
        wp.atomic_sub(grad_x, sender, weighted)
        if receiver == run_receiver:
            run_grad = run_grad + weighted
        else:
            if run_receiver >= 0:
                wp.atomic_add(grad_x, run_receiver, run_grad)
            run_receiver = receiver
            run_grad = weighted
    if run_receiver >= 0:
        wp.atomic_add(grad_x, run_receiver, run_grad)


@wp.kernel(enable_backward=False)
def isometry_terms(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_offset: wp.array(dtype=wp.vec3),
    terms: wp.array2d(dtype=wp.float32),
):
    # terms[0, e] = (|x_i - x_j| - |L_e|)^2 and terms[1, e] = 1 for a valid edge; zeros otherwise.
    e = wp.tid()
    receiver = edges[e, 0]
    sender = edges[e, 1]
    if edge_is_valid(receiver, sender, x.shape[0]):
        residual = wp.length(x[receiver] - x[sender]) - wp.length(rest_offset[e])
        terms[0, e] = residual * residual
        terms[1, e] = 1.0
    else:
        terms[0, e] = 0.0
        terms[1, e] = 0.0


@wp.kernel(enable_backward=False)
def isometry_adjoint(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest_offset: wp.array(dtype=wp.vec3),
    grad_scale: wp.array(dtype=wp.float32),
    grad_x: wp.array(dtype=wp.vec3),
    grad_rest_offset: wp.array(dtype=wp.vec3),
):
    # d/dx_i (|d| - |L|)^2 = 2 (|d| - |L|) d / |d| with d = x_i - x_j (0 when |d| = 0), times grad_scale[0]
    # = upstream gradient / valid edge count; the rest-offset term is the same with -L / |L|.
    e = wp.tid()
    receiver = edges[e, 0]
    sender = edges[e, 1]
    if not edge_is_valid(receiver, sender, x.shape[0]):
        grad_rest_offset[e] = wp.vec3(0.0)
        return
    delta = x[receiver] - x[sender]
    rest = rest_offset[e]
    length = wp.length(delta)
    rest_length = wp.length(rest)
    weight = 2.0 * (length - rest_length) * grad_scale[0]
    if length > 0.0:
        grad_delta = (weight / length) * delta
        wp.atomic_add(grad_x, receiver, grad_delta)
        wp.atomic_sub(grad_x, sender, grad_delta)
    if rest_length > 0.0:
        grad_rest_offset[e] = (-weight / rest_length) * rest
    else:
        grad_rest_offset[e] = wp.vec3(0.0)


@wp.kernel(enable_backward=False)
def damping_terms(v: wp.array(dtype=wp.vec3), terms: wp.array(dtype=wp.float32)):
    i = wp.tid()
    terms[i] = wp.length_sq(v[i])


@wp.kernel(enable_backward=False)
def damping_adjoint(
    v: wp.array(dtype=wp.vec3),
    grad_scale: wp.array(dtype=wp.float32),
    grad_v: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    grad_v[i] = (2.0 * grad_scale[0]) * v[i]


def _edge_thread_count(edge_count: int, edges_per_thread: int) -> int:
    return (edge_count + edges_per_thread - 1) // edges_per_thread


def _check_edge_arrays(edges: wp.array, *per_edge: wp.array) -> None:
    if edges.ndim != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape [E, 2], got {edges.shape}")
    for array in per_edge:
        if array.shape[0] != edges.shape[0]:
            raise ValueError(f"per-edge arrays must have {edges.shape[0]} rows, got {array.shape[0]}")


def _check_node_arrays(node_count: int, *per_node: wp.array) -> None:
    for array in per_node:
        if array.shape[0] != node_count:
            raise ValueError(f"per-node arrays must have {node_count} rows, got {array.shape[0]}")


def launch_spring_force(
    x: wp.array,
    edges: wp.array,
    rest_offset: wp.array,
    stiffness: wp.array,
    spring_force_sum: wp.array,
    *,
    edges_per_thread: int = EDGES_PER_THREAD,
) -> None:
    """Accumulate ``s_i`` into ``spring_force_sum`` (vec3 ``[M]``, zero on entry).

    Args:
        x: positions, vec3 ``[M]``.
        edges: int32 ``[E, 2]``, (receiver, sender) rows.
        rest_offset: vec3 ``[E]``; stiffness: float32 ``[E]``.
        spring_force_sum: vec3 ``[M]`` output.
        edges_per_thread: consecutive edges per thread.
    """
    _check_edge_arrays(edges, rest_offset, stiffness)
    _check_node_arrays(x.shape[0], spring_force_sum)
    if edges.shape[0] == 0 or x.shape[0] == 0:
        return
    launch(
        spring_force,
        dim=_edge_thread_count(edges.shape[0], edges_per_thread),
        inputs=[x, edges, rest_offset, stiffness, edges_per_thread],
        outputs=[spring_force_sum],
        device=x.device,
    )


def launch_spring_integrate(
    x: wp.array,
    v: wp.array,
    damping: wp.array,
    mass: wp.array,
    force: wp.array,
    spring_force_sum: wp.array,
    dt: float,
    x_next: wp.array,
    v_next: wp.array,
) -> None:
    """Semi-implicit Euler update of every node (all arrays ``[M]``: vec3 or float32)."""
    node_count = x.shape[0]
    _check_node_arrays(node_count, v, damping, mass, force, spring_force_sum, x_next, v_next)
    if node_count == 0:
        return
    launch(
        spring_integrate,
        dim=node_count,
        inputs=[x, v, damping, mass, force, spring_force_sum, float(dt)],
        outputs=[x_next, v_next],
        device=x.device,
    )


def launch_spring_integrate_adjoint(
    v: wp.array,
    damping: wp.array,
    mass: wp.array,
    force: wp.array,
    spring_force_sum: wp.array,
    grad_x_next: wp.array,
    grad_v_next: wp.array,
    dt: float,
    grad_x: wp.array,
    grad_v: wp.array,
    grad_damping: wp.array,
    grad_mass: wp.array,
    grad_force: wp.array,
) -> None:
    """Node part of the step's backward pass; writes every output row (``grad_x`` gets ``grad_x_next``)."""
    node_count = v.shape[0]
    _check_node_arrays(
        node_count, damping, mass, force, spring_force_sum, grad_x_next, grad_v_next,
        grad_x, grad_v, grad_damping, grad_mass, grad_force,
    )
    if node_count == 0:
        return
    launch(
        spring_integrate_adjoint,
        dim=node_count,
        inputs=[v, damping, mass, force, spring_force_sum, grad_x_next, grad_v_next, float(dt)],
        outputs=[grad_x, grad_v, grad_damping, grad_mass, grad_force],
        device=v.device,
    )


def launch_spring_force_adjoint(
    x: wp.array,
    edges: wp.array,
    rest_offset: wp.array,
    stiffness: wp.array,
    grad_force: wp.array,
    grad_x: wp.array,
    grad_rest_offset: wp.array,
    grad_stiffness: wp.array,
    *,
    edges_per_thread: int = EDGES_PER_THREAD,
) -> None:
    """Edge part of the step's backward pass: adds spring terms to ``grad_x``, writes per-edge gradients."""
    _check_edge_arrays(edges, rest_offset, stiffness, grad_rest_offset, grad_stiffness)
    _check_node_arrays(x.shape[0], grad_force, grad_x)
    if edges.shape[0] == 0:
        return
    launch(
        spring_force_adjoint,
        dim=_edge_thread_count(edges.shape[0], edges_per_thread),
        inputs=[x, edges, rest_offset, stiffness, grad_force, edges_per_thread],
        outputs=[grad_x, grad_rest_offset, grad_stiffness],
        device=x.device,
    )


def launch_isometry_terms(x: wp.array, edges: wp.array, rest_offset: wp.array, terms: wp.array) -> None:
    """Per-edge squared length residuals and validity flags, float32 ``terms[2, E]``."""
    _check_edge_arrays(edges, rest_offset)
    if terms.shape != (2, edges.shape[0]):
        raise ValueError(f"terms must have shape (2, {edges.shape[0]}), got {terms.shape}")
    if edges.shape[0] == 0:
        return
    launch(isometry_terms, dim=edges.shape[0], inputs=[x, edges, rest_offset], outputs=[terms], device=x.device)


def launch_isometry_adjoint(
    x: wp.array,
    edges: wp.array,
    rest_offset: wp.array,
    grad_scale: wp.array,
    grad_x: wp.array,
    grad_rest_offset: wp.array,
) -> None:
    """Add the isometry gradient to ``grad_x`` (vec3 ``[M]``, zero on entry); write ``grad_rest_offset [E]``."""
    _check_edge_arrays(edges, rest_offset, grad_rest_offset)
    _check_node_arrays(x.shape[0], grad_x)
    if edges.shape[0] == 0:
        return
    launch(
        isometry_adjoint,
        dim=edges.shape[0],
        inputs=[x, edges, rest_offset, grad_scale],
        outputs=[grad_x, grad_rest_offset],
        device=x.device,
    )


def launch_damping_terms(v: wp.array, terms: wp.array) -> None:
    """Squared speed of every velocity vector, float32 ``[N]``."""
    _check_node_arrays(v.shape[0], terms)
    if v.shape[0] == 0:
        return
    launch(damping_terms, dim=v.shape[0], inputs=[v], outputs=[terms], device=v.device)


def launch_damping_adjoint(v: wp.array, grad_scale: wp.array, grad_v: wp.array) -> None:
    """``grad_v = 2 * grad_scale[0] * v`` for every velocity vector."""
    _check_node_arrays(v.shape[0], grad_v)
    if v.shape[0] == 0:
        return
    launch(damping_adjoint, dim=v.shape[0], inputs=[v, grad_scale], outputs=[grad_v], device=v.device)
