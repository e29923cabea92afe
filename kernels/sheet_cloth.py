"""Warp kernels of a triangle-mesh cloth (a garment sheet): membrane, bending and drag forces, and a substep.

The sheet is a triangle mesh with vertices ``x_i`` (masses ``m_i``), triangles ``t = (i, j, k)`` and hinges: the
interior edges ``h = (i0, i1, i2, i3)``, edge ``i0 i1`` shared by the triangles ``(i0, i1, i2)`` and
``(i1, i0, i3)``. Units: world units are metres, masses kilograms, times seconds.

Membrane (stretch and shear), per triangle: the Saint Venant-Kirchhoff membrane of "A simple approach to
nonlinear tensile stiffness for accurate cloth simulation" (Volino, Magnenat-Thalmann and Faure 2009), written
with a stretch and a shear modulus. With the rest triangle laid flat in its own plane (2D edge matrix ``D``,
``rest_inverse = D^-1``, rest area ``A``), the deformation gradient ``F = [x_j - x_i, x_k - x_i] D^-1`` (3x2),
the Green strain ``E = (F^T F - I) / 2`` (2x2) and::

    W = A * (k_stretch / 2 * tr(E)^2 + k_shear * |dev E|^2),      dev E = E - tr(E) / 2 * I

``tr(E)`` measures the change of area, ``dev E`` the change of shape (shear and unequal stretch); ``k_stretch``
and ``k_shear`` are in N/m (energy per unit rest area, per unit squared strain: a 2D StVK material with
``mu = k_shear`` and ``lambda = k_stretch - k_shear``). Beyond a Green strain of ``c = 0.5`` (``STRAIN_CAP``, a
stretch of about 1.4) each term grows linearly instead: ``k_stretch (c tr(E) - c^2 / 2)`` for ``tr(E) > c`` and
``k_shear (2 c |dev E| - c^2)`` for ``|dev E| > c``, so the stress is bounded and, unlike StVK's, the membrane's
stiffness stops growing with the stretch (an explicit step that is stable at rest stays stable however far a
collision or a pin pulls the cloth). The forces are ``f_j, f_k = -A P D^-T`` (columns), ``f_i = -f_j - f_k``,
with ``P = F S`` and ``S = dW/dE = k_stretch min(tr(E), c) I + 2 k_shear min(1, c / |dev E|) dev E``.

Bending, per hinge: the discrete-shell energy of "Discrete shells" (Grinspun, Hirani, Desbrun and Schroeder 2003),
``W = k_bend / 2 * w * (theta - theta0)^2`` with the dihedral angle ``theta`` (signed, 0 for a flat hinge), its rest
value ``theta0``, the weight ``w = 3 |e0|^2 / (A0 + A1)`` of the rest edge length and the rest areas of the two
triangles (dimensionless), and ``k_bend`` in N m (J). With ``e = x1 - x0``, ``n0 = e x (x2 - x0)`` and
``n1 = (x3 - x0) x e`` (unnormalized normals, equal for a flat hinge), ``theta = atan2((n0 x n1) . e / |e|,
n0 . n1)`` and the gradient of "Simulation of clothing with folds and wrinkles" (Bridson, Marino and Fedkiw
2003)::

    dtheta/dx2 = -|e| n0 / |n0|^2                    dtheta/dx3 = -|e| n1 / |n1|^2
    dtheta/dx0 = -((x2 - x1).e n0 / |n0|^2 + (x3 - x1).e n1 / |n1|^2) / |e|
    dtheta/dx1 =  ((x2 - x0).e n0 / |n0|^2 + (x3 - x0).e n1 / |n1|^2) / |e|

and ``f_a = -k_bend w (theta - theta0) dtheta/dx_a`` (the angle difference wrapped into ``[-pi, pi]``).

Aerodynamic drag, per triangle: ``f = -k_drag A_now (n . v_mean) n`` with the current area ``A_now`` and unit
normal ``n`` and the mean velocity of its corners (the air at rest), a third on each corner; ``k_drag`` in
N s / m^3 (force per unit area per unit normal speed).

A substep of ``h`` seconds (semi-implicit Euler) for a free vertex, with gravity ``g`` and the linear velocity
damping ``c_i`` [1/s]::

    v' = v + h (f / m + g - c v),   x' = x + h v',
    x'' = x' + push(x'),   v'' = v' + push(x') / h

``push`` the sum of the moves out of every capsule of the substep
(:func:`~warpavatar.kernels.collision.capsule_push`, all from the same position). A pinned vertex goes to its
target of the substep with its given velocity (no force, no collision).

Launch plan per substep: ``sheet_forces`` (a thread per triangle, then one per hinge) adds into a force buffer
with atomics, then ``sheet_integrate`` (a thread per vertex) reads and clears it and writes the new state: two
launches. The force kernel is straight-line code that Warp differentiates (``adjoint=True`` launches); the
rollout's backward walks the substeps in reverse with ``sheet_collision_adjoint_input``,
:func:`~warpavatar.kernels.collision.launch_capsule_push_out_adjoint` and the hand-written
``sheet_integrate_adjoint``. Degenerate elements (a triangle normal, hinge normal or hinge edge whose squared
length is below 1e-24) exert no force. Float32.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.collision import capsule_push
from warpavatar.kernels.launch import launch

__all__ = [
    "DEGENERATE_SQ",
    "launch_sheet_forces",
    "launch_sheet_forces_adjoint",
    "launch_sheet_integrate",
    "launch_sheet_collision_adjoint_input",
    "launch_sheet_integrate_adjoint",
]

DEGENERATE_SQ = wp.constant(1e-24)
"""Squared length [m^2 or m^4] below which an edge or an unnormalized normal counts as degenerate (no force)."""

STRAIN_CAP = wp.constant(0.5)
"""Green strain beyond which the membrane's energy grows linearly instead of quadratically (its stress stops
growing), for ``tr(E)`` in tension and for ``|dev E|``."""

PI = wp.constant(3.14159265358979)


@wp.func
def membrane_forces(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, rest_inverse: wp.mat22, rest_area: float,
                    stretch: float, shear: float):
    """The StVK membrane forces on corners 1 and 2 of a triangle (corner 0 takes minus their sum) [N]."""
    d1 = x1 - x0
    d2 = x2 - x0
    fu = d1 * rest_inverse[0, 0] + d2 * rest_inverse[1, 0]
    fv = d1 * rest_inverse[0, 1] + d2 * rest_inverse[1, 1]
    e00 = 0.5 * (wp.dot(fu, fu) - 1.0)
    e11 = 0.5 * (wp.dot(fv, fv) - 1.0)
    e01 = 0.5 * wp.dot(fu, fv)
    # S = k_stretch min(tr E, cap) I + 2 k_shear min(1, cap / |dev E|) dev E
    bulk = stretch * wp.min(e00 + e11, STRAIN_CAP)
    deviator_sq = 0.5 * (e00 - e11) * (e00 - e11) + 2.0 * e01 * e01
    shear_scale = shear
    if deviator_sq > STRAIN_CAP * STRAIN_CAP:
        shear_scale = shear * STRAIN_CAP / wp.sqrt(deviator_sq)
    s00 = bulk + shear_scale * (e00 - e11)
    s11 = bulk + shear_scale * (e11 - e00)
    s01 = 2.0 * shear_scale * e01
    pu = fu * s00 + fv * s01
    pv = fu * s01 + fv * s11
    f1 = -rest_area * (pu * rest_inverse[0, 0] + pv * rest_inverse[0, 1])
    f2 = -rest_area * (pu * rest_inverse[1, 0] + pv * rest_inverse[1, 1])
    return f1, f2


@wp.func
def drag_share(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, drag: float):
    """Each corner's third of a triangle's drag ``-k A_now (n . v_mean) n`` [N] (0 for a degenerate triangle)."""
    c = wp.cross(x1 - x0, x2 - x0)  # |c| = 2 A_now
    length_sq = wp.dot(c, c)
    if length_sq <= DEGENERATE_SQ:
        return wp.vec3(0.0)
    mean_velocity = (v0 + v1 + v2) / 3.0
    # A n (n . v) = (|c| / 2) c (c . v) / |c|^2 = c (c . v) / (2 |c|)
    return (-drag * wp.dot(c, mean_velocity) / (6.0 * wp.sqrt(length_sq))) * c


@wp.func
def wrapped_angle(angle: float):
    """``angle`` moved by a multiple of 2 pi into ``[-pi, pi]``."""
    if angle > PI:
        return angle - 2.0 * PI
    if angle < -PI:
        return angle + 2.0 * PI
    return angle


@wp.func
def hinge_forces(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, rest_angle: float, weight: float,
                 bend: float):
    """The discrete-shell bending forces on the four vertices of a hinge [N] (zeros when degenerate)."""
    e = x1 - x0
    length_sq = wp.dot(e, e)
    n0 = wp.cross(e, x2 - x0)
    n1 = wp.cross(x3 - x0, e)
    q0 = wp.dot(n0, n0)
    q1 = wp.dot(n1, n1)
    zero = wp.vec3(0.0)
    if length_sq <= DEGENERATE_SQ or q0 <= DEGENERATE_SQ or q1 <= DEGENERATE_SQ:
        return zero, zero, zero, zero
    length = wp.sqrt(length_sq)
    angle = wp.atan2(wp.dot(wp.cross(n0, n1), e) / length, wp.dot(n0, n1))
    a = n0 / q0
    b = n1 / q1
    g2 = -length * a
    g3 = -length * b
    g0 = -(wp.dot(x2 - x1, e) * a + wp.dot(x3 - x1, e) * b) / length
    g1 = (wp.dot(x2 - x0, e) * a + wp.dot(x3 - x0, e) * b) / length
    scale = -bend * weight * wrapped_angle(angle - rest_angle)
    return scale * g0, scale * g1, scale * g2, scale * g3


@wp.kernel
def sheet_forces(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    triangles: wp.array2d(dtype=wp.int32),
    rest_inverse: wp.array(dtype=wp.mat22),
    rest_area: wp.array(dtype=wp.float32),
    stretch_stiffness: wp.array(dtype=wp.float32),
    shear_stiffness: wp.array(dtype=wp.float32),
    drag_coefficient: wp.array(dtype=wp.float32),
    hinges: wp.array2d(dtype=wp.int32),
    rest_angle: wp.array(dtype=wp.float32),
    hinge_weight: wp.array(dtype=wp.float32),
    bend_stiffness: wp.array(dtype=wp.float32),
    force: wp.array(dtype=wp.vec3),
):
    # Threads [0, T) take a triangle (membrane and drag), threads [T, T + H) a hinge (bending); force
    # accumulates (zero it first). Straight-line code: Warp's adjoint gives the backward.
    tid = wp.tid()
    triangle_count = triangles.shape[0]
    if tid < triangle_count:
        i = triangles[tid, 0]
        j = triangles[tid, 1]
        k = triangles[tid, 2]
        xi = x[i]
        xj = x[j]
        xk = x[k]
        fj, fk = membrane_forces(xi, xj, xk, rest_inverse[tid], rest_area[tid], stretch_stiffness[tid],
                                 shear_stiffness[tid])
        drag = drag_share(xi, xj, xk, v[i], v[j], v[k], drag_coefficient[tid])
        wp.atomic_add(force, i, drag - fj - fk)
        wp.atomic_add(force, j, drag + fj)
        wp.atomic_add(force, k, drag + fk)
    else:
        h = tid - triangle_count
        i0 = hinges[h, 0]
        i1 = hinges[h, 1]
        i2 = hinges[h, 2]
        i3 = hinges[h, 3]
        f0, f1, f2, f3 = hinge_forces(x[i0], x[i1], x[i2], x[i3], rest_angle[h], hinge_weight[h],
                                      bend_stiffness[h])
        wp.atomic_add(force, i0, f0)
        wp.atomic_add(force, i1, f1)
        wp.atomic_add(force, i2, f2)
        wp.atomic_add(force, i3, f3)


@wp.kernel(enable_backward=False)
def sheet_integrate(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    force: wp.array(dtype=wp.vec3),
    inverse_mass: wp.array(dtype=wp.float32),
    damping: wp.array(dtype=wp.float32),
    gravity: wp.vec3,
    pin_slot: wp.array(dtype=wp.int32),
    pin_targets: wp.array2d(dtype=wp.vec3),
    pin_velocities: wp.array2d(dtype=wp.vec3),
    capsule_start: wp.array2d(dtype=wp.vec3),
    capsule_end: wp.array2d(dtype=wp.vec3),
    capsule_radius: wp.array2d(dtype=wp.float32),
    capsule_count: int,
    substep: int,
    h: float,
    record_free_positions: int,
    free_positions: wp.array2d(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    # Reads this vertex's force and clears it for the next substep's force kernels.
    i = wp.tid()
    f = force[i]
    force[i] = wp.vec3(0.0)
    slot = pin_slot[i]
    if slot >= 0:
        x_out[i] = pin_targets[substep, slot]
        v_out[i] = pin_velocities[substep, slot]
        return
    velocity = v[i]
    velocity = velocity + h * (f * inverse_mass[i] + gravity - damping[i] * velocity)
    position = x[i] + h * velocity
    if record_free_positions != 0:
        free_positions[substep, i] = position
    push = wp.vec3(0.0)
    for c in range(capsule_count):
        push = push + capsule_push(position, capsule_start[substep, c], capsule_end[substep, c],
                                   capsule_radius[substep, c])
    x_out[i] = position + push
    v_out[i] = velocity + push / h


@wp.func
def state_gradient(grad_state: wp.array(dtype=wp.vec3), grad_output: wp.array2d(dtype=wp.vec3), frame: int,
                   i: int):
    """The gradient of a substep's output state: what later substeps sent back plus the loss's own (when the
    state is a recorded frame, ``frame >= 0``)."""
    g = grad_state[i]
    if frame >= 0:
        g = g + grad_output[frame, i]
    return g


@wp.kernel(enable_backward=False)
def sheet_collision_adjoint_input(
    pin_slot: wp.array(dtype=wp.int32),
    grad_state_x: wp.array(dtype=wp.vec3),
    grad_state_v: wp.array(dtype=wp.vec3),
    grad_output_x: wp.array2d(dtype=wp.vec3),
    grad_output_v: wp.array2d(dtype=wp.vec3),
    frame: int,
    h: float,
    grad_pushed: wp.array(dtype=wp.vec3),
):
    # x'' = x' + push(x') and v'' = v' + push(x') / h: the collision's upstream gradient is G_x + G_v / h for a
    # free vertex, 0 for a pinned one (never pushed, so it adds nothing to the capsules' gradients).
    i = wp.tid()
    if pin_slot[i] >= 0:
        grad_pushed[i] = wp.vec3(0.0)
        return
    grad_pushed[i] = (state_gradient(grad_state_x, grad_output_x, frame, i)
                      + state_gradient(grad_state_v, grad_output_v, frame, i) / h)


@wp.kernel(enable_backward=False)
def sheet_integrate_adjoint(
    v: wp.array(dtype=wp.vec3),
    inverse_mass: wp.array(dtype=wp.float32),
    damping: wp.array(dtype=wp.float32),
    pin_slot: wp.array(dtype=wp.int32),
    grad_output_x: wp.array2d(dtype=wp.vec3),
    grad_output_v: wp.array2d(dtype=wp.vec3),
    frame: int,
    grad_through_push: wp.array(dtype=wp.vec3),
    has_capsules: int,
    substep: int,
    h: float,
    grad_state_x: wp.array(dtype=wp.vec3),
    grad_state_v: wp.array(dtype=wp.vec3),
    grad_force: wp.array(dtype=wp.vec3),
    grad_damping: wp.array(dtype=wp.float32),
    grad_pin_targets: wp.array2d(dtype=wp.vec3),
    grad_pin_velocities: wp.array2d(dtype=wp.vec3),
):
    # In place: grad_state_* hold the gradient of the substep's output state on entry and that of its input
    # state (the direct terms; the force adjoints add the rest) on exit. grad_damping accumulates over substeps.
    # Free vertex, with G = the output state's gradient and J = d(x' + push)/dx' (grad_through_push = J^T (G_x +
    # G_v / h) from the capsules' adjoint):
    #   g_x' = J^T (G_x + G_v / h) - G_v / h   (G_x without capsules),   g_v' = G_v + h g_x',
    #   dL/dx = g_x',  dL/dv = (1 - h c) g_v',  dL/df = h / m g_v',  dL/dc = -h v . g_v'.
    i = wp.tid()
    gx = state_gradient(grad_state_x, grad_output_x, frame, i)
    gv = state_gradient(grad_state_v, grad_output_v, frame, i)
    slot = pin_slot[i]
    if slot >= 0:
        grad_pin_targets[substep, slot] = gx
        grad_pin_velocities[substep, slot] = gv
        grad_state_x[i] = wp.vec3(0.0)
        grad_state_v[i] = wp.vec3(0.0)
        grad_force[i] = wp.vec3(0.0)
        return
    grad_position = gx
    if has_capsules != 0:
        grad_position = grad_through_push[i] - gv / h
    grad_velocity = gv + h * grad_position
    c = damping[i]
    velocity = v[i]
    grad_state_x[i] = grad_position
    grad_state_v[i] = (1.0 - h * c) * grad_velocity
    grad_force[i] = (h * inverse_mass[i]) * grad_velocity
    grad_damping[i] = grad_damping[i] - h * wp.dot(velocity, grad_velocity)


# ----------------------------------------------------------------------------------------------------------
# Launchers. Array arguments are ``warp.array`` objects or launch descriptors
# (:func:`warpavatar._src.warp_utils.warp_descriptor`); launches run on Warp's current device.


def _rows(array) -> int:
    return array.shape[0]


def _check_rows(expected: int, arrays: tuple, names: str) -> None:
    """Raise unless every array of ``arrays`` has ``expected`` rows (``names``: their names, space-separated; read
    only to word the error, so a launch on the hot path costs a few comparisons)."""
    for index, array in enumerate(arrays):
        if array.shape[0] != expected:
            raise ValueError(f"{names.split()[index]} must have {expected} rows, got {array.shape[0]}")


def _check_forces(x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness, drag_coefficient,
                  hinges, rest_angle, hinge_weight, bend_stiffness, *per_vertex) -> int:
    triangle_count, hinge_count = triangles.shape[0], hinges.shape[0]
    _check_rows(triangle_count, (rest_inverse, rest_area, stretch_stiffness, shear_stiffness, drag_coefficient),
                "rest_inverse rest_area stretch_stiffness shear_stiffness drag_coefficient")
    _check_rows(hinge_count, (rest_angle, hinge_weight, bend_stiffness), "rest_angle hinge_weight bend_stiffness")
    _check_rows(x.shape[0], (v, *per_vertex), "v force grad_force grad_x grad_v")
    return triangle_count + hinge_count


def launch_sheet_forces(x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness,
                        drag_coefficient, hinges, rest_angle, hinge_weight, bend_stiffness, force) -> None:
    """Add every triangle's membrane and drag forces and every hinge's bending forces into ``force``.

    Args:
        x, v: vertex positions [m] and velocities [m/s], vec3 ``[V]``.
        triangles: vertex ids, int32 ``[T, 3]``.
        rest_inverse: inverse rest edge matrices ``D^-1`` [1/m], mat22 ``[T]``; rest_area [m^2], float32 ``[T]``.
        stretch_stiffness, shear_stiffness [N/m], drag_coefficient [N s/m^3]: float32 ``[T]``.
        hinges: (edge start, edge end, opposite vertex of the first triangle, of the second), int32 ``[H, 4]``.
        rest_angle: dihedral rest angles [rad]; hinge_weight: ``3 |e0|^2 / (A0 + A1)`` (dimensionless);
            bend_stiffness [N m]: float32 ``[H]``.
        force: vec3 ``[V]``, added to.
    """
    count = _check_forces(x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness,
                          drag_coefficient, hinges, rest_angle, hinge_weight, bend_stiffness, force)
    if count == 0:
        return
    launch(sheet_forces, dim=count,
           inputs=[x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness, drag_coefficient,
                   hinges, rest_angle, hinge_weight, bend_stiffness],
           outputs=[force])


def launch_sheet_forces_adjoint(x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness,
                                drag_coefficient, hinges, rest_angle, hinge_weight, bend_stiffness, scratch_force,
                                grad_force, grad_x, grad_v, grad_stretch_stiffness, grad_shear_stiffness,
                                grad_drag_coefficient, grad_bend_stiffness) -> None:
    """Warp's adjoint of :func:`launch_sheet_forces`: adds ``J^T grad_force`` into ``grad_x, grad_v`` (vec3 ``[V]``)
    and the parameters' gradients into ``grad_*_stiffness``, ``grad_drag_coefficient`` (float32 ``[T]`` or
    ``[H]``, or None). ``scratch_force`` (vec3 ``[V]``) is written by the adjoint's forward replay, never read."""
    count = _check_forces(x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness,
                          drag_coefficient, hinges, rest_angle, hinge_weight, bend_stiffness, scratch_force,
                          grad_force, grad_x, grad_v)
    if count == 0:
        return
    launch(sheet_forces, dim=count,
           inputs=[x, v, triangles, rest_inverse, rest_area, stretch_stiffness, shear_stiffness, drag_coefficient,
                   hinges, rest_angle, hinge_weight, bend_stiffness],
           outputs=[scratch_force],
           adj_inputs=[grad_x, grad_v, None, None, None, grad_stretch_stiffness, grad_shear_stiffness,
                       grad_drag_coefficient, None, None, None, grad_bend_stiffness],
           adj_outputs=[grad_force], adjoint=True)


def launch_sheet_integrate(x, v, force, inverse_mass, damping, gravity, pin_slot, pin_targets, pin_velocities,
                           capsule_start, capsule_end, capsule_radius, capsule_count: int, substep: int, h: float,
                           free_positions, x_out, v_out, *, record_free_positions: bool) -> None:
    """One substep's update of every vertex (and ``force`` cleared for the next substep).

    Args:
        x, v, force: the substep's input state [m, m/s] and the summed forces [N], vec3 ``[V]``.
        inverse_mass [1/kg], damping [1/s]: float32 ``[V]``.
        gravity: ``wp.vec3`` [m/s^2].
        pin_slot: each vertex's row in the pin arrays, -1 for a free vertex, int32 ``[V]``.
        pin_targets, pin_velocities: per substep, where the pinned vertices go [m] and their velocities [m/s],
            vec3 ``[S, P]`` (any non-empty array when nothing is pinned).
        capsule_start, capsule_end: per substep, the capsules' segments, vec3 ``[S, C]``; capsule_radius
            float32 ``[S, C]``; only the first ``capsule_count`` columns are read.
        substep: the row of this substep in the per-substep arrays; h: its length [s].
        free_positions: vec3 ``[S, V]``; with ``record_free_positions`` row ``substep`` receives the free
            vertices' positions before the collision (the backward pass reads them).
        x_out, v_out: the new state, vec3 ``[V]``.
    """
    count = _rows(x)
    _check_rows(count, (v, force, inverse_mass, damping, pin_slot, x_out, v_out),
                "v force inverse_mass damping pin_slot x_out v_out")
    if count == 0:
        return
    launch(sheet_integrate, dim=count,
           inputs=[x, v, force, inverse_mass, damping, gravity, pin_slot, pin_targets, pin_velocities, capsule_start,
                   capsule_end, capsule_radius, int(capsule_count), int(substep), float(h),
                   int(bool(record_free_positions)), free_positions],
           outputs=[x_out, v_out])


def launch_sheet_collision_adjoint_input(pin_slot, grad_state_x, grad_state_v, grad_output_x, grad_output_v,
                                         frame: int, h: float, grad_pushed) -> None:
    """Write the upstream gradient of a substep's collision, ``G_x + G_v / h`` per free vertex (0 when pinned),
    into ``grad_pushed`` (vec3 ``[V]``); ``frame`` is the row of ``grad_output_*`` (vec3 ``[F, V]``) of the
    substep's output state, or -1."""
    count = _rows(pin_slot)
    _check_rows(count, (grad_state_x, grad_state_v, grad_pushed), "grad_state_x grad_state_v grad_pushed")
    if count == 0:
        return
    launch(sheet_collision_adjoint_input, dim=count,
           inputs=[pin_slot, grad_state_x, grad_state_v, grad_output_x, grad_output_v, int(frame), float(h)],
           outputs=[grad_pushed])


def launch_sheet_integrate_adjoint(v, inverse_mass, damping, pin_slot, grad_output_x, grad_output_v, frame: int,
                                   grad_through_push, has_capsules: bool, substep: int, h: float, grad_state_x,
                                   grad_state_v, grad_force, grad_damping, grad_pin_targets,
                                   grad_pin_velocities) -> None:
    """The hand-written backward of :func:`launch_sheet_integrate` (see the kernel): ``grad_state_*`` (vec3
    ``[V]``) in place from the output state's gradient to the input state's direct terms; writes ``grad_force``,
    adds to ``grad_damping`` (float32 ``[V]``), writes row ``substep`` of ``grad_pin_*`` (vec3 ``[S, P]``)."""
    count = _rows(v)
    _check_rows(count, (inverse_mass, damping, pin_slot, grad_through_push, grad_state_x, grad_state_v, grad_force,
                        grad_damping),
                "inverse_mass damping pin_slot grad_through_push grad_state_x grad_state_v grad_force grad_damping")
    if count == 0:
        return
    launch(sheet_integrate_adjoint, dim=count,
           inputs=[v, inverse_mass, damping, pin_slot, grad_output_x, grad_output_v, int(frame), grad_through_push,
                   int(bool(has_capsules)), int(substep), float(h)],
           outputs=[grad_state_x, grad_state_v, grad_force, grad_damping, grad_pin_targets, grad_pin_velocities])
