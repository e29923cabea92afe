"""Autograd bridge of the triangle-mesh cloth kernels (:mod:`warpavatar.kernels.sheet_cloth`).

Two ops: :func:`sheet_forces`, the membrane, bending and drag forces of one state, and :func:`sheet_rollout`, a
whole rollout of semi-implicit Euler substeps with pinned vertices and capsule collision, as one
``torch.autograd.Function``. The rollout's forward is two kernel launches per substep and keeps, when a
gradient is needed, every substep's state (and the positions before each collision, with capsules): ``6 V`` floats
a substep, ``9 V`` with capsules. Its backward walks the substeps in reverse, a handful of launches each: the
collision's adjoint (:func:`~warpavatar.kernels.collision.launch_capsule_push_out_adjoint`), the integration's
hand-written adjoint, and Warp's adjoint of the straight-line force kernel, which adds every substep's
parameter gradients into the same buffers. No host synchronization in either direction.

:class:`SheetMesh` holds what a rollout does not learn (topology, rest shape, masses, pins), :func:`sheet_mesh`
builds it from a rest mesh. The plain-torch references of both ops are in
:mod:`warpavatar._torch_impl.sheet_cloth`.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope, warp_descriptor
from warpavatar.kernels.collision import launch_capsule_push_out_adjoint
from warpavatar.kernels.sheet_cloth import (
    launch_sheet_collision_adjoint_input,
    launch_sheet_forces,
    launch_sheet_forces_adjoint,
    launch_sheet_integrate,
    launch_sheet_integrate_adjoint,
)

__all__ = ["SheetMesh", "sheet_mesh", "rest_triangle_frames", "dihedral_angles", "hinge_weights", "sheet_forces",
           "sheet_rollout"]


@dataclass(frozen=True)
class SheetMesh:
    """The constant part of a sheet: topology, rest shape, masses and pins (:func:`sheet_mesh` builds it).

    Attributes:
        triangles: vertex ids of each triangle, int32 ``[T, 3]``.
        rest_inverse: inverse of each rest triangle's 2D edge matrix ``D`` [1/m], float32 ``[T, 2, 2]``.
        rest_area: rest area of each triangle [m^2], float32 ``[T]``.
        hinges: interior edges ``(i0, i1, i2, i3)`` (edge ``i0 i1``, opposite vertices ``i2``, ``i3``), int32
            ``[H, 4]``.
        rest_angle: dihedral angle of each hinge in the rest shape [rad], float32 ``[H]``.
        hinge_weight: ``3 |e0|^2 / (A0 + A1)`` of each hinge (rest edge length and areas; dimensionless), float32
            ``[H]``.
        inverse_mass: ``1 / m_i`` of each vertex [1/kg], float32 ``[V]``.
        pin_slot: each vertex's row in the pin arrays (its index in ``pinned``), -1 for a free vertex, int32
            ``[V]``.
        pinned: the pinned vertex ids, int64 ``[P]``.
    """

    triangles: torch.Tensor
    rest_inverse: torch.Tensor
    rest_area: torch.Tensor
    hinges: torch.Tensor
    rest_angle: torch.Tensor
    hinge_weight: torch.Tensor
    inverse_mass: torch.Tensor
    pin_slot: torch.Tensor
    pinned: torch.Tensor

    @property
    def vertex_count(self) -> int:
        return self.inverse_mass.shape[0]

    @property
    def triangle_count(self) -> int:
        return self.triangles.shape[0]

    @property
    def hinge_count(self) -> int:
        return self.hinges.shape[0]

    @property
    def pinned_count(self) -> int:
        return self.pinned.shape[0]

    @property
    def device(self) -> torch.device:
        return self.inverse_mass.device


def rest_triangle_frames(rest_positions: torch.Tensor, triangles: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each rest triangle laid flat in its own plane: ``(rest_inverse [T, 2, 2], rest_area [T])``.

    The 2D frame of triangle ``(i, j, k)`` has its first axis along ``x_j - x_i`` and its second in the
    triangle's plane, so ``D = [[|e1|, e2.u], [0, e2.w]]`` with ``e1 = x_j - x_i``, ``e2 = x_k - x_i``. A
    degenerate triangle (area below 1e-12 of its squared longest edge) gets a zero inverse and zero area: it
    exerts no force. Computed in float64, returned in the dtype of ``rest_positions``.
    """
    rest = rest_positions.detach().double()
    corner = triangles.long()
    e1 = rest[corner[:, 1]] - rest[corner[:, 0]]
    e2 = rest[corner[:, 2]] - rest[corner[:, 0]]
    normal = torch.linalg.cross(e1, e2)
    double_area = normal.norm(dim=1)
    longest_sq = torch.stack([(e1 * e1).sum(1), (e2 * e2).sum(1), ((e2 - e1) ** 2).sum(1)], dim=1).amax(dim=1)
    valid = double_area > 1e-12 * longest_sq.clamp_min(1e-300)
    length = e1.norm(dim=1).clamp_min(1e-300)
    u = e1 / length[:, None]
    w = torch.linalg.cross(normal, e1) / (double_area * length).clamp_min(1e-300)[:, None]
    matrix = torch.zeros(corner.shape[0], 2, 2, dtype=torch.float64, device=rest.device)
    matrix[:, 0, 0] = length
    matrix[:, 0, 1] = (e2 * u).sum(1)
    matrix[:, 1, 1] = (e2 * w).sum(1)
    matrix[~valid] = torch.eye(2, dtype=torch.float64, device=rest.device)
    inverse = torch.linalg.inv(matrix) * valid[:, None, None]
    area = 0.5 * double_area * valid
    return inverse.to(rest_positions.dtype), area.to(rest_positions.dtype)


def dihedral_angles(positions: torch.Tensor, hinges: torch.Tensor) -> torch.Tensor:
    """The signed dihedral angle of every hinge [rad], ``[H]`` (0 flat; the convention of the kernels:
    ``atan2((n0 x n1) . e / |e|, n0 . n1)`` with ``e = x1 - x0``, ``n0 = e x (x2 - x0)``, ``n1 = (x3 - x0) x e``)."""
    corner = hinges.long()
    x0, x1, x2, x3 = (positions[corner[:, a]] for a in range(4))
    e = x1 - x0
    n0 = torch.linalg.cross(e, x2 - x0)
    n1 = torch.linalg.cross(x3 - x0, e)
    sine = (torch.linalg.cross(n0, n1) * e).sum(1) / e.norm(dim=1).clamp_min(1e-30)
    return torch.atan2(sine, (n0 * n1).sum(1))


def hinge_weights(rest_positions: torch.Tensor, hinges: torch.Tensor, rest_area_pair: torch.Tensor) -> torch.Tensor:
    """The discrete-shell weight ``3 |e0|^2 / (A0 + A1)`` of every hinge (dimensionless), ``[H]``, from the rest edge
    and the rest areas of its two triangles (``rest_area_pair [H, 2]``); 0 where both areas are 0."""
    corner = hinges.long()
    edge_sq = ((rest_positions[corner[:, 1]] - rest_positions[corner[:, 0]]) ** 2).sum(1)
    total = rest_area_pair.sum(1)
    return torch.where(total > 0, 3.0 * edge_sq / total.clamp_min(1e-300), torch.zeros_like(total))


def sheet_mesh(rest_positions: torch.Tensor, triangles: torch.Tensor, hinges: torch.Tensor, hinge_triangles:
               torch.Tensor, vertex_mass: torch.Tensor, pinned: torch.Tensor) -> SheetMesh:
    """The :class:`SheetMesh` of a rest mesh.

    Args:
        rest_positions: rest vertex positions [m], float ``[V, 3]``.
        triangles: vertex ids, integer ``[T, 3]``.
        hinges: interior edges ``(i0, i1, i2, i3)``, integer ``[H, 4]``.
        hinge_triangles: the two triangles of each hinge (rows of ``triangles``), integer ``[H, 2]``.
        vertex_mass: mass of each vertex [kg], float ``[V]`` (positive).
        pinned: pinned vertex ids, integer ``[P]`` (distinct).

    Raises:
        ValueError: ids out of range, repeated pins, or a non-positive mass.
    """
    vertex_count = rest_positions.shape[0]
    device = rest_positions.device
    for name, ids, columns in (("triangles", triangles, 3), ("hinges", hinges, 4)):
        if ids.dim() != 2 or ids.shape[1] != columns:
            raise ValueError(f"{name} must have shape [*, {columns}], got {list(ids.shape)}")
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= vertex_count):
            raise ValueError(f"{name} must hold vertex ids in [0, {vertex_count})")
    pinned = torch.as_tensor(pinned, device=device).reshape(-1).long()
    if pinned.numel() and (int(pinned.min()) < 0 or int(pinned.max()) >= vertex_count
                           or pinned.unique().numel() != pinned.numel()):
        raise ValueError(f"pinned must hold distinct vertex ids in [0, {vertex_count})")
    mass = torch.as_tensor(vertex_mass, device=device).reshape(-1)
    if mass.shape[0] != vertex_count or (vertex_count and not bool((mass > 0).all())):
        raise ValueError(f"vertex_mass must hold {vertex_count} positive masses")
    rest_inverse, rest_area = rest_triangle_frames(rest_positions, triangles)
    rest = rest_positions.detach().double()
    pair_area = rest_area.double()[hinge_triangles.long()] if hinges.shape[0] else rest.new_zeros(0, 2)
    pin_slot = torch.full((vertex_count,), -1, dtype=torch.int32, device=device)
    pin_slot[pinned] = torch.arange(pinned.shape[0], dtype=torch.int32, device=device)
    return SheetMesh(
        triangles=triangles.to(torch.int32).contiguous(),
        rest_inverse=rest_inverse.float().contiguous(),
        rest_area=rest_area.float().contiguous(),
        hinges=hinges.to(torch.int32).contiguous(),
        rest_angle=dihedral_angles(rest, hinges).float().contiguous(),
        hinge_weight=hinge_weights(rest, hinges, pair_area).float().contiguous(),
        inverse_mass=(1.0 / mass.double()).float().contiguous(),
        pin_slot=pin_slot,
        pinned=pinned,
    )


# ----------------------------------------------------------------------------------------------------------
# Forces of one state


def _float32(name: str, tensor: torch.Tensor, shape: tuple, device) -> None:
    check_tensor(name, tensor, shape, dtype_kind="float32", device=device)


def _check_mesh(mesh: SheetMesh, device) -> None:
    if not isinstance(mesh, SheetMesh):
        raise TypeError(f"mesh must be a SheetMesh, got {type(mesh).__name__}")
    if mesh.device != device:
        raise ValueError(f"the mesh is on {mesh.device} but the state is on {device}")


class _SheetForces(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v, stretch, shear, bend, drag, mesh):
        force = torch.zeros_like(x)
        if x.shape[0]:
            with torch_stream_scope(x.device):
                constant = _constant_descriptors(mesh, stretch, shear, bend, drag, None)
                launch_sheet_forces(warp_descriptor(x, wp.vec3), warp_descriptor(v, wp.vec3), *_force_inputs(constant),
                                    warp_descriptor(force, wp.vec3))
        ctx.save_for_backward(x, v, stretch, shear, bend, drag)
        ctx.mesh = mesh
        return force

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_force):
        x, v, stretch, shear, bend, drag = ctx.saved_tensors
        mesh = ctx.mesh
        grad_force = grad_force.to(torch.float32).contiguous()
        grads = [torch.zeros_like(t) for t in (x, v, stretch, shear, bend, drag)]
        if x.shape[0]:
            grad_x, grad_v, grad_stretch, grad_shear, grad_bend, grad_drag = grads
            scratch = torch.empty_like(x)
            with torch_stream_scope(x.device):
                constant = _constant_descriptors(mesh, stretch, shear, bend, drag, None)
                launch_sheet_forces_adjoint(
                    warp_descriptor(x, wp.vec3), warp_descriptor(v, wp.vec3), *_force_inputs(constant),
                    warp_descriptor(scratch, wp.vec3), warp_descriptor(grad_force, wp.vec3),
                    warp_descriptor(grad_x, wp.vec3), warp_descriptor(grad_v, wp.vec3), warp_descriptor(grad_stretch),
                    warp_descriptor(grad_shear), warp_descriptor(grad_drag), warp_descriptor(grad_bend))
        needs = ctx.needs_input_grad
        return (*(grad if need else None for grad, need in zip(grads, needs[:6])), None)


def _check_parameters(mesh: SheetMesh, device, stretch_stiffness, shear_stiffness, bend_stiffness,
                      drag_coefficient) -> None:
    for name, tensor, count in (("stretch_stiffness", stretch_stiffness, mesh.triangle_count),
                                ("shear_stiffness", shear_stiffness, mesh.triangle_count),
                                ("bend_stiffness", bend_stiffness, mesh.hinge_count),
                                ("drag_coefficient", drag_coefficient, mesh.triangle_count)):
        _float32(name, tensor, (count,), device)


def sheet_forces(positions: torch.Tensor, velocities: torch.Tensor, mesh: SheetMesh, stretch_stiffness: torch.Tensor,
                 shear_stiffness: torch.Tensor, bend_stiffness: torch.Tensor, drag_coefficient: torch.Tensor
                 ) -> torch.Tensor:
    """The internal and air forces on every vertex of a sheet: StVK membrane (stretch and shear), discrete-shell
    bending and aerodynamic drag, as :mod:`warpavatar.kernels.sheet_cloth` defines them.

    Args:
        positions: vertex positions [m], float32 ``[V, 3]``.
        velocities: vertex velocities [m/s], float32 ``[V, 3]``.
        mesh: the sheet's constant data (:func:`sheet_mesh`), on the same device.
        stretch_stiffness: area-stretch modulus of each triangle [N/m], float32 ``[T]``.
        shear_stiffness: shear modulus of each triangle [N/m], float32 ``[T]``.
        bend_stiffness: bending stiffness of each hinge [N m], float32 ``[H]``.
        drag_coefficient: drag of each triangle [N s/m^3], float32 ``[T]``.

    Returns:
        The force on every vertex [N], float32 ``[V, 3]`` (gravity and damping not included).

    Gradients: with respect to the positions, velocities and all four parameters (Warp's adjoint of the
    straight-line force kernel; not twice differentiable).
    """
    check_tensor("positions", positions, (None, 3), dtype_kind="float32")
    device = positions.device
    _check_mesh(mesh, device)
    vertex_count = mesh.vertex_count
    _float32("positions", positions, (vertex_count, 3), device)
    _float32("velocities", velocities, (vertex_count, 3), device)
    _check_parameters(mesh, device, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient)
    return _SheetForces.apply(positions.contiguous(), velocities.contiguous(), stretch_stiffness.contiguous(),
                              shear_stiffness.contiguous(), bend_stiffness.contiguous(), drag_coefficient.contiguous(),
                              mesh)


# ----------------------------------------------------------------------------------------------------------
# Rollout


def _nonempty(tensor: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``tensor``, or a zero tensor of ``shape`` when it holds nothing (Warp needs an array, the kernels never read
    it then)."""
    return tensor.contiguous() if tensor.numel() else tensor.new_zeros(shape)


class _SheetRollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x0, v0, stretch, shear, bend, drag, damping, pin_targets, pin_velocities, capsule_start,
                capsule_end, capsule_radius, mesh, gravity, h, substeps_per_frame, keep):
        device = x0.device
        vertex_count = x0.shape[0]
        substep_count = pin_targets.shape[0]
        frame_count = substep_count // substeps_per_frame
        capsule_count = capsule_radius.shape[1]
        positions = torch.empty(frame_count, vertex_count, 3, dtype=x0.dtype, device=device)
        velocities = torch.empty_like(positions)
        pins = (_nonempty(pin_targets, (1, 1, 3)), _nonempty(pin_velocities, (1, 1, 3)))
        capsules = (_nonempty(capsule_start, (1, 1, 3)), _nonempty(capsule_end, (1, 1, 3)),
                    _nonempty(capsule_radius, (1, 1)))
        if keep:
            states_x = torch.empty(substep_count + 1, vertex_count, 3, dtype=x0.dtype, device=device)
            states_v = torch.empty_like(states_x)
            states_x[0], states_v[0] = x0, v0
            free_positions = (torch.empty(substep_count, vertex_count, 3, dtype=x0.dtype, device=device)
                              if capsule_count else x0.new_zeros(1, 1, 3))
        else:
            scratch = [(torch.empty_like(x0), torch.empty_like(v0)) for _ in range(2)]
            free_positions = x0.new_zeros(1, 1, 3)
        if vertex_count and substep_count:
            force = torch.zeros_like(x0)
            with torch_stream_scope(device):
                constant = _constant_descriptors(mesh, stretch, shear, bend, drag, damping)
                force_inputs = _force_inputs(constant)
                pin_wp = [warp_descriptor(t, wp.vec3) for t in pins]
                capsule_wp = [warp_descriptor(capsules[0], wp.vec3), warp_descriptor(capsules[1], wp.vec3),
                              warp_descriptor(capsules[2])]
                free_wp = warp_descriptor(free_positions, wp.vec3)
                force_wp = warp_descriptor(force, wp.vec3)
                gravity_wp = wp.vec3(*gravity)
                x_in, v_in = x0.contiguous(), v0.contiguous()
                for k in range(substep_count):
                    if keep:
                        x_out, v_out = states_x[k + 1], states_v[k + 1]
                    elif (k + 1) % substeps_per_frame == 0:
                        x_out, v_out = positions[(k + 1) // substeps_per_frame - 1], velocities[
                            (k + 1) // substeps_per_frame - 1]
                    else:
                        x_out, v_out = scratch[k % 2]
                    x_wp, v_wp = warp_descriptor(x_in, wp.vec3), warp_descriptor(v_in, wp.vec3)
                    launch_sheet_forces(x_wp, v_wp, *force_inputs, force_wp)
                    launch_sheet_integrate(x_wp, v_wp, force_wp, constant["inverse_mass"], constant["damping"],
                                           gravity_wp, constant["pin_slot"], pin_wp[0], pin_wp[1], *capsule_wp,
                                           capsule_count, k, h, free_wp, warp_descriptor(x_out, wp.vec3),
                                           warp_descriptor(v_out, wp.vec3), record_free_positions=keep and
                                           capsule_count > 0)
                    x_in, v_in = x_out, v_out
        if keep:
            positions.copy_(states_x[substeps_per_frame::substeps_per_frame])
            velocities.copy_(states_v[substeps_per_frame::substeps_per_frame])
            ctx.save_for_backward(states_x, states_v, free_positions, stretch, shear, bend, drag, damping, pins[0],
                                  capsules[0], capsules[1], capsules[2])
            ctx.mesh, ctx.h, ctx.substeps_per_frame = mesh, h, substeps_per_frame
            ctx.capsule_count, ctx.pin_count = capsule_count, pin_targets.shape[1]
        return positions, velocities

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_positions, grad_velocities):
        (states_x, states_v, free_positions, stretch, shear, bend, drag, damping, pin_targets, capsule_start,
         capsule_end, capsule_radius) = ctx.saved_tensors
        mesh, h, substeps_per_frame = ctx.mesh, ctx.h, ctx.substeps_per_frame
        capsule_count, pin_count = ctx.capsule_count, ctx.pin_count
        substep_count = states_x.shape[0] - 1
        vertex_count = states_x.shape[1]
        device = states_x.device

        def upstream(grad):
            shape = (substep_count // substeps_per_frame, vertex_count, 3)
            if grad is None:
                return torch.zeros(shape, dtype=torch.float32, device=device)
            return grad.to(torch.float32).contiguous()

        grad_output_x, grad_output_v = upstream(grad_positions), upstream(grad_velocities)
        grad_x = torch.zeros(vertex_count, 3, dtype=torch.float32, device=device)
        grad_v = torch.zeros_like(grad_x)
        grad_stretch, grad_shear, grad_drag = (torch.zeros_like(stretch), torch.zeros_like(shear),
                                               torch.zeros_like(drag))
        grad_bend, grad_damping = torch.zeros_like(bend), torch.zeros_like(damping)
        grad_pin_targets = torch.zeros(substep_count, pin_count, 3, dtype=torch.float32, device=device)
        grad_pin_velocities = torch.zeros_like(grad_pin_targets)
        grad_capsule_start = torch.zeros(substep_count, capsule_count, 3, dtype=torch.float32, device=device)
        grad_capsule_end = torch.zeros_like(grad_capsule_start)
        grad_capsule_radius = torch.zeros(substep_count, capsule_count, dtype=torch.float32, device=device)
        if vertex_count and substep_count:
            grad_force = torch.empty_like(grad_x)
            scratch = torch.empty_like(grad_x)
            grad_pushed_in = torch.empty_like(grad_x)
            grad_pushed_out = torch.empty_like(grad_x)
            with torch_stream_scope(device):
                constant = _constant_descriptors(mesh, stretch, shear, bend, drag, damping)
                force_inputs = _force_inputs(constant)
                grad_out_wp = (warp_descriptor(grad_output_x, wp.vec3), warp_descriptor(grad_output_v, wp.vec3))
                pins_wp = [warp_descriptor(_nonempty(t, (1, 1, 3)), wp.vec3)
                           for t in (grad_pin_targets, grad_pin_velocities)]
                grad_x_wp, grad_v_wp = warp_descriptor(grad_x, wp.vec3), warp_descriptor(grad_v, wp.vec3)
                grad_force_wp, scratch_wp = warp_descriptor(grad_force, wp.vec3), warp_descriptor(scratch, wp.vec3)
                pushed_in_wp = warp_descriptor(grad_pushed_in, wp.vec3)
                pushed_out = to_warp(grad_pushed_out, wp.vec3)
                parameter_grads = tuple(warp_descriptor(grad) for grad in (grad_stretch, grad_shear, grad_drag,
                                                                           grad_bend))
                grad_damping_wp = warp_descriptor(grad_damping)
                for k in reversed(range(substep_count)):
                    frame = (k + 1) // substeps_per_frame - 1 if (k + 1) % substeps_per_frame == 0 else -1
                    if capsule_count:
                        launch_sheet_collision_adjoint_input(constant["pin_slot"], grad_x_wp, grad_v_wp,
                                                             *grad_out_wp, frame, h, pushed_in_wp)
                        launch_capsule_push_out_adjoint(
                            to_warp(free_positions[k], wp.vec3), to_warp(capsule_start[k], wp.vec3),
                            to_warp(capsule_end[k], wp.vec3), to_warp(capsule_radius[k]),
                            to_warp(grad_pushed_in, wp.vec3), pushed_out, to_warp(grad_capsule_start[k], wp.vec3),
                            to_warp(grad_capsule_end[k], wp.vec3), to_warp(grad_capsule_radius[k]))
                    x_wp, v_wp = warp_descriptor(states_x[k], wp.vec3), warp_descriptor(states_v[k], wp.vec3)
                    launch_sheet_integrate_adjoint(v_wp, constant["inverse_mass"], constant["damping"],
                                                   constant["pin_slot"], *grad_out_wp, frame, pushed_out,
                                                   capsule_count > 0, k, h, grad_x_wp, grad_v_wp, grad_force_wp,
                                                   grad_damping_wp, *pins_wp)
                    launch_sheet_forces_adjoint(x_wp, v_wp, *force_inputs, scratch_wp, grad_force_wp, grad_x_wp,
                                                grad_v_wp, *parameter_grads)
        needs = ctx.needs_input_grad
        grads = (grad_x, grad_v, grad_stretch, grad_shear, grad_bend, grad_drag, grad_damping, grad_pin_targets,
                 grad_pin_velocities, grad_capsule_start, grad_capsule_end, grad_capsule_radius)
        return (*(grad if need else None for grad, need in zip(grads, needs)), None, None, None, None, None)


def _force_inputs(constant: dict) -> tuple:
    """The inputs of the force kernel after the state, in its order."""
    return tuple(constant[name] for name in ("triangles", "rest_inverse", "rest_area", "stretch", "shear", "drag",
                                             "hinges", "rest_angle", "hinge_weight", "bend"))


def _constant_descriptors(mesh: SheetMesh, stretch, shear, bend, drag, damping) -> dict:
    """Launch descriptors of the arrays every substep reads (on Warp's current device; ``damping`` may be None)."""
    return {"triangles": warp_descriptor(mesh.triangles), "rest_inverse": warp_descriptor(mesh.rest_inverse, wp.mat22),
            "rest_area": warp_descriptor(mesh.rest_area), "hinges": warp_descriptor(mesh.hinges),
            "rest_angle": warp_descriptor(mesh.rest_angle), "hinge_weight": warp_descriptor(mesh.hinge_weight),
            "inverse_mass": warp_descriptor(mesh.inverse_mass), "pin_slot": warp_descriptor(mesh.pin_slot),
            "stretch": warp_descriptor(stretch), "shear": warp_descriptor(shear), "bend": warp_descriptor(bend),
            "drag": warp_descriptor(drag), "damping": None if damping is None else warp_descriptor(damping)}


def _check_gravity(gravity) -> tuple[float, float, float]:
    values = tuple(float(g) for g in gravity)
    if len(values) != 3 or not all(math.isfinite(g) for g in values):
        raise ValueError(f"gravity must be three finite numbers, got {gravity!r}")
    return values


def sheet_rollout(positions: torch.Tensor, velocities: torch.Tensor, mesh: SheetMesh, stretch_stiffness: torch.Tensor,
                  shear_stiffness: torch.Tensor, bend_stiffness: torch.Tensor, drag_coefficient: torch.Tensor,
                  damping: torch.Tensor, pin_targets: torch.Tensor, pin_velocities: torch.Tensor, *, substep: float,
                  substeps_per_frame: int, gravity=(0.0, 0.0, -9.81),
                  capsules: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Roll a sheet out over ``S = F * substeps_per_frame`` semi-implicit Euler substeps of ``substep`` seconds.

    Each substep (see :mod:`warpavatar.kernels.sheet_cloth`) sums the :func:`sheet_forces`, updates every free
    vertex with ``v' = v + h (f / m + g - c v)``, ``x' = x + h v'``, pushes it out of the substep's capsules
    (velocity corrected by the move over ``h``), and puts every pinned vertex at its target of the substep with its
    given velocity. The caller interpolates the pins and capsules between frames (the rows are per substep).

    Args:
        positions, velocities: the initial state [m, m/s], float32 ``[V, 3]``.
        mesh: the sheet's constant data (:func:`sheet_mesh`).
        stretch_stiffness, shear_stiffness [N/m], drag_coefficient [N s/m^3]: float32 ``[T]``.
        bend_stiffness: [N m], float32 ``[H]``.
        damping: linear velocity damping of each vertex [1/s], float32 ``[V]``.
        pin_targets: where the pinned vertices are at the end of each substep [m], float32 ``[S, P, 3]``.
        pin_velocities: their velocities then [m/s], float32 ``[S, P, 3]``.
        substep: the substep's length ``h`` [s], a positive Python number.
        substeps_per_frame: substeps between two recorded frames (``S`` must be a multiple of it).
        gravity: gravitational acceleration [m/s^2], three numbers.
        capsules: ``(segment_start [S, C, 3], segment_end [S, C, 3], radius [S, C])`` float32, the body's capsules
            at each substep, or None (no collision).

    Returns:
        ``(positions [F, V, 3], velocities [F, V, 3])``: the state at the end of every frame.

    Gradients: with respect to the initial state, the five parameter arrays, the pin targets and velocities and
    the capsules (hand-written backward through every substep; not twice differentiable). The stability of the
    explicit step is the caller's: :class:`warpavatar.sim.SheetCloth` bounds the parameters for its substep.

    Raises:
        TypeError, ValueError: bad shapes, dtypes or devices, or a bad ``substep`` or ``substeps_per_frame``.
    """
    check_tensor("positions", positions, (None, 3), dtype_kind="float32")
    device = positions.device
    _check_mesh(mesh, device)
    vertex_count, pinned_count = mesh.vertex_count, mesh.pinned_count
    _float32("positions", positions, (vertex_count, 3), device)
    _float32("velocities", velocities, (vertex_count, 3), device)
    _check_parameters(mesh, device, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient)
    _float32("damping", damping, (vertex_count,), device)
    _float32("pin_targets", pin_targets, (None, pinned_count, 3), device)
    substep_count = pin_targets.shape[0]
    _float32("pin_velocities", pin_velocities, (substep_count, pinned_count, 3), device)
    if isinstance(substep, bool) or not isinstance(substep, numbers.Real) or not (math.isfinite(substep)
                                                                                  and substep > 0):
        raise ValueError(f"substep must be a positive number of seconds, got {substep!r}")
    if isinstance(substeps_per_frame, bool) or not isinstance(substeps_per_frame, int) or substeps_per_frame < 1:
        raise ValueError(f"substeps_per_frame must be an integer >= 1, got {substeps_per_frame!r}")
    if substep_count % substeps_per_frame:
        raise ValueError(f"the {substep_count} substeps of pin_targets are not a whole number of frames of "
                         f"{substeps_per_frame} substeps")
    if capsules is None:
        capsule_start = torch.zeros(substep_count, 0, 3, dtype=torch.float32, device=device)
        capsule_end, capsule_radius = capsule_start, torch.zeros(substep_count, 0, dtype=torch.float32, device=device)
    else:
        capsule_start, capsule_end, capsule_radius = capsules
        _float32("capsule segment_start", capsule_start, (substep_count, None, 3), device)
        capsule_count = capsule_start.shape[1]
        _float32("capsule segment_end", capsule_end, (substep_count, capsule_count, 3), device)
        _float32("capsule radius", capsule_radius, (substep_count, capsule_count), device)
    tensors = (positions, velocities, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient, damping,
               pin_targets, pin_velocities, capsule_start, capsule_end, capsule_radius)
    keep_states = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    return _SheetRollout.apply(
        positions.contiguous(), velocities.contiguous(), stretch_stiffness.contiguous(), shear_stiffness.contiguous(),
        bend_stiffness.contiguous(), drag_coefficient.contiguous(), damping.contiguous(), pin_targets.contiguous(),
        pin_velocities.contiguous(), capsule_start.contiguous(), capsule_end.contiguous(), capsule_radius.contiguous(),
        mesh, _check_gravity(gravity), float(substep), substeps_per_frame, keep_states)
