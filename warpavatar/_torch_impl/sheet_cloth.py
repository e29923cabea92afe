"""Plain-torch references of :func:`warpavatar.ops.sheet_forces` and :func:`warpavatar.ops.sheet_rollout`.

The conservative forces are minus torch autograd's gradient of the energies (:func:`membrane_energy`,
:func:`bending_energy`), written from their definitions in :mod:`warpavatar.kernels.sheet_cloth`, not from the
kernels' force formulas; the drag is written out. Same signatures as the Warp ops, dtype-generic (the mesh's
float32 data is cast to the positions' dtype: float64 for finite differences), differentiated by autograd
(the forces are built with ``create_graph``, so gradients of the forces flow too).
"""

from __future__ import annotations

import math

import torch

from warpavatar._torch_impl.collision import push_out_of_capsules

__all__ = ["membrane_energy", "bending_energy", "drag_forces", "sheet_forces", "sheet_rollout"]


def _corners(positions: torch.Tensor, ids: torch.Tensor) -> list[torch.Tensor]:
    ids = ids.long()
    return [positions[ids[:, column]] for column in range(ids.shape[1])]


STRAIN_CAP = 0.5
"""Green strain beyond which each membrane term grows linearly (as :mod:`warpavatar.kernels.sheet_cloth`)."""


def membrane_energy(positions, mesh, stretch_stiffness, shear_stiffness) -> torch.Tensor:
    """``sum_t A_t (k_stretch / 2 tr(E)^2 + k_shear |dev E|^2)`` [J], ``E`` the Green strain of ``F = Ds D^-1``,
    each term linear beyond a strain of :data:`STRAIN_CAP` (``tr(E)`` in tension, ``|dev E|``)."""
    x0, x1, x2 = _corners(positions, mesh.triangles)
    inverse = mesh.rest_inverse.to(positions.dtype)
    edges = torch.stack([x1 - x0, x2 - x0], dim=2)  # [T, 3, 2]
    deformation = edges @ inverse  # [T, 3, 2]
    strain = 0.5 * (deformation.transpose(1, 2) @ deformation - torch.eye(2, dtype=positions.dtype,
                                                                          device=positions.device))
    trace = strain[:, 0, 0] + strain[:, 1, 1]
    deviatoric_sq = 0.5 * (strain[:, 0, 0] - strain[:, 1, 1]) ** 2 + strain[:, 0, 1] ** 2 + strain[:, 1, 0] ** 2
    stretch, shear = stretch_stiffness.to(positions.dtype), shear_stiffness.to(positions.dtype)
    cap = STRAIN_CAP
    # quadratic up to the cap, linear beyond (tr(E) in tension; |dev E|)
    bulk = torch.where(trace <= cap, 0.5 * trace**2, cap * trace - 0.5 * cap**2)
    large = deviatoric_sq > cap**2
    deviator = torch.where(large, deviatoric_sq, torch.ones_like(deviatoric_sq)).sqrt()
    deviatoric = torch.where(large, 2.0 * cap * deviator - cap**2, deviatoric_sq)
    density = stretch * bulk + shear * deviatoric
    return (mesh.rest_area.to(positions.dtype) * density).sum()


def bending_energy(positions, mesh, bend_stiffness) -> torch.Tensor:
    """``sum_h k_bend / 2 w_h (theta_h - theta0_h)^2`` [J] (the angle difference wrapped into ``[-pi, pi]``)."""
    x0, x1, x2, x3 = _corners(positions, mesh.hinges)
    e = x1 - x0
    n0 = torch.linalg.cross(e, x2 - x0)
    n1 = torch.linalg.cross(x3 - x0, e)
    valid = ((e * e).sum(1) > 1e-24) & ((n0 * n0).sum(1) > 1e-24) & ((n1 * n1).sum(1) > 1e-24)
    length = torch.where(valid, e.norm(dim=1), torch.ones_like(e[:, 0]))
    angle = torch.atan2((torch.linalg.cross(n0, n1) * e).sum(1) / length, (n0 * n1).sum(1))
    difference = torch.remainder(angle - mesh.rest_angle.to(positions.dtype) + math.pi, 2 * math.pi) - math.pi
    energy = 0.5 * bend_stiffness.to(positions.dtype) * mesh.hinge_weight.to(positions.dtype) * difference**2
    return torch.where(valid, energy, torch.zeros_like(energy)).sum()


def drag_forces(positions, velocities, mesh, drag_coefficient) -> torch.Tensor:
    """``-k A_now (n . v_mean) n`` per triangle, a third on each corner [N], ``[V, 3]``."""
    x0, x1, x2 = _corners(positions, mesh.triangles)
    v0, v1, v2 = _corners(velocities, mesh.triangles)
    normal = torch.linalg.cross(x1 - x0, x2 - x0)
    double_area = normal.norm(dim=1)
    valid = double_area**2 > 1e-24
    unit = normal / torch.where(valid, double_area, torch.ones_like(double_area))[:, None]
    mean_velocity = (v0 + v1 + v2) / 3.0
    area = 0.5 * double_area
    force = -(drag_coefficient.to(positions.dtype) * area * (unit * mean_velocity).sum(1))[:, None] * unit
    force = torch.where(valid[:, None], force, torch.zeros_like(force)) / 3.0
    ids = mesh.triangles.long()
    total = torch.zeros_like(positions)
    for column in range(3):
        total = total.index_add(0, ids[:, column], force)
    return total


def sheet_forces(positions, velocities, mesh, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient
                 ) -> torch.Tensor:
    """Membrane and bending forces (minus the energies' gradient) plus drag [N], ``[V, 3]``."""
    with torch.enable_grad():
        x = positions if positions.requires_grad else positions.detach().requires_grad_(True)
        energy = (membrane_energy(x, mesh, stretch_stiffness, shear_stiffness)
                  + bending_energy(x, mesh, bend_stiffness))
        (gradient,) = torch.autograd.grad(energy, x, create_graph=True)
    return -gradient + drag_forces(positions, velocities, mesh, drag_coefficient)


def sheet_rollout(positions, velocities, mesh, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient,
                  damping, pin_targets, pin_velocities, *, substep, substeps_per_frame, gravity=(0.0, 0.0, -9.81),
                  capsules=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The substeps of the Warp op in a Python loop: ``(positions [F, V, 3], velocities [F, V, 3])``."""
    h = float(substep)
    dtype = positions.dtype
    gravity = torch.tensor(gravity, dtype=dtype, device=positions.device)
    inverse_mass = mesh.inverse_mass.to(dtype)[:, None]
    pinned = mesh.pinned
    free = torch.ones(positions.shape[0], 1, dtype=dtype, device=positions.device).index_fill(0, pinned, 0.0)
    x, v = positions, velocities
    frames_x, frames_v = [], []
    for k in range(pin_targets.shape[0]):
        force = sheet_forces(x, v, mesh, stretch_stiffness, shear_stiffness, bend_stiffness, drag_coefficient)
        v = v + h * (force * inverse_mass + gravity - damping.to(dtype)[:, None] * v)
        x = x + h * v
        if capsules is not None:
            pushed = push_out_of_capsules(x, capsules[0][k].to(dtype), capsules[1][k].to(dtype),
                                          capsules[2][k].to(dtype))
            move = (pushed - x) * free
            x = x + move
            v = v + move / h
        x = x.index_copy(0, pinned, pin_targets[k].to(dtype))
        v = v.index_copy(0, pinned, pin_velocities[k].to(dtype))
        if (k + 1) % substeps_per_frame == 0:
            frames_x.append(x)
            frames_v.append(v)
    empty = positions.new_zeros(0, positions.shape[0], 3)
    return (torch.stack(frames_x) if frames_x else empty, torch.stack(frames_v) if frames_v else empty)
