"""Mass-spring-damper step of SMAD and its regularizers, as differentiable torch ops on Warp kernels.

Paper 000 (SMAD), Eq. 2-4: every Gaussian-graph node ``i`` is a point mass ``m_i`` with damping ``gamma_i``,
pulled by springs of stiffness ``k_e`` towards its rest offsets ``L_e`` from its neighbours, and driven by an
external force ``F_i``; one explicit (semi-implicit) Euler step advances positions and velocities. Eq. 11:
the isometry loss (edge lengths against rest lengths) and the damping loss (squared speeds).

The kernels are in :mod:`warpavatar.kernels.springs` (launch plan and edge handling documented there), the
plain-torch references with the same signatures in :mod:`warpavatar._torch_impl.springs`. Backward passes are
hand-written kernels; a rollout of many :func:`spring_step` calls backpropagates through time with ordinary
torch autograd (each step saves its inputs and the spring force sum, ``3 M`` floats).
"""

from __future__ import annotations

import math
import numbers

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels.springs import (
    launch_damping_adjoint,
    launch_damping_terms,
    launch_isometry_adjoint,
    launch_isometry_terms,
    launch_spring_force,
    launch_spring_force_adjoint,
    launch_spring_integrate,
    launch_spring_integrate_adjoint,
)

__all__ = ["spring_step", "isometry_loss", "damping_loss"]


def _check_float32(name: str, tensor: torch.Tensor) -> None:
    if tensor.dtype != torch.float32:
        raise TypeError(f"{name} must be float32, got {tensor.dtype}")


def _prepare_edges(edges: torch.Tensor, node_count: int) -> torch.Tensor:
    """Edges as contiguous int32; ids that int32 cannot hold are clamped to an invalid id first."""
    if edges.dtype != torch.int32:
        edges = edges.clamp(-1, node_count).to(torch.int32)
    return edges.contiguous()


def _check_edges(edges: torch.Tensor, device: torch.device) -> None:
    check_tensor("edges", edges, (None, 2), dtype_kind="int", device=device)
    if edges.dtype == torch.bool:
        raise TypeError("edges must be an integer tensor, got torch.bool")


class _SpringStep(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v, edges, rest_offset, stiffness, damping, mass, force, dt):
        spring_force_sum = torch.zeros_like(x)
        x_next = torch.empty_like(x)
        v_next = torch.empty_like(v)
        x_wp = to_warp(x, wp.vec3)
        with torch_stream_scope(x.device):
            launch_spring_force(
                x_wp,
                to_warp(edges),
                to_warp(rest_offset, wp.vec3),
                to_warp(stiffness),
                to_warp(spring_force_sum, wp.vec3),
            )
            launch_spring_integrate(
                x_wp,
                to_warp(v, wp.vec3),
                to_warp(damping),
                to_warp(mass),
                to_warp(force, wp.vec3),
                to_warp(spring_force_sum, wp.vec3),
                dt,
                to_warp(x_next, wp.vec3),
                to_warp(v_next, wp.vec3),
            )
        ctx.save_for_backward(x, v, edges, rest_offset, stiffness, damping, mass, force, spring_force_sum)
        ctx.dt = dt
        return x_next, v_next

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x_next, grad_v_next):
        x, v, edges, rest_offset, stiffness, damping, mass, force, spring_force_sum = ctx.saved_tensors
        grad_x_next = grad_x_next.to(torch.float32).contiguous()
        grad_v_next = grad_v_next.to(torch.float32).contiguous()
        grad_x = torch.empty_like(x)
        grad_v = torch.empty_like(v)
        grad_damping = torch.empty_like(damping)
        grad_mass = torch.empty_like(mass)
        grad_force = torch.empty_like(force)
        grad_rest_offset = grad_stiffness = None
        needs = ctx.needs_input_grad
        need_edge_pass = needs[0] or needs[3] or needs[4]
        with torch_stream_scope(x.device):
            grad_force_wp = to_warp(grad_force, wp.vec3)
            grad_x_wp = to_warp(grad_x, wp.vec3)
            launch_spring_integrate_adjoint(
                to_warp(v, wp.vec3),
                to_warp(damping),
                to_warp(mass),
                to_warp(force, wp.vec3),
                to_warp(spring_force_sum, wp.vec3),
                to_warp(grad_x_next, wp.vec3),
                to_warp(grad_v_next, wp.vec3),
                ctx.dt,
                grad_x_wp,
                to_warp(grad_v, wp.vec3),
                to_warp(grad_damping),
                to_warp(grad_mass),
                grad_force_wp,
            )
            if need_edge_pass:
                grad_rest_offset = torch.empty_like(rest_offset)
                grad_stiffness = torch.empty_like(stiffness)
                launch_spring_force_adjoint(
                    to_warp(x, wp.vec3),
                    to_warp(edges),
                    to_warp(rest_offset, wp.vec3),
                    to_warp(stiffness),
                    grad_force_wp,
                    grad_x_wp,
                    to_warp(grad_rest_offset, wp.vec3),
                    to_warp(grad_stiffness),
                )
        return (
            grad_x if needs[0] else None,
            grad_v if needs[1] else None,
            None,
            grad_rest_offset if needs[3] else None,
            grad_stiffness if needs[4] else None,
            grad_damping if needs[5] else None,
            grad_mass if needs[6] else None,
            grad_force if needs[7] else None,
            None,
        )


def spring_step(
    x: torch.Tensor,
    v: torch.Tensor,
    edges: torch.Tensor,
    rest_offset: torch.Tensor,
    stiffness: torch.Tensor,
    damping: torch.Tensor,
    mass: torch.Tensor,
    force: torch.Tensor,
    dt: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One semi-implicit Euler step of the mass-spring-damper system of SMAD (Eq. 2-4).

    For every node ``i``, with directed edges ``e = (i, j)`` where ``i = edges[e, 0]`` *receives* the spring
    force and ``j = edges[e, 1]`` sends it (the sender feels nothing from this edge; add ``(j, i)`` for the
    reaction)::

        a_i  = (force_i - damping_i * v_i - sum_{e: edges[e,0]=i} stiffness_e * (x_i - x_j - rest_offset_e)) / mass_i
        v'_i = v_i + dt * a_i
        x'_i = x_i + dt * v'_i

    Edges may come in any order; sorted by receiver (as ``knn_graph`` rows give them) they are cheapest.
    Edges with an endpoint outside ``[0, M)``, such as the ``-1`` padding of ``knn_graph``, are ignored.
    Cost per call: one zero-fill, an edge kernel and a node kernel forward; a node and an edge kernel
    backward. No host synchronization.

    Args:
        x: positions [world units], float32 ``[M, 3]``.
        v: velocities [world units / s], float32 ``[M, 3]``.
        edges: (receiver, sender) node ids, integer ``[E, 2]`` (int32 avoids a conversion per call).
        rest_offset: rest offsets ``L_e`` (rest value of ``x_i - x_j``) [world units], float32 ``[E, 3]``.
        stiffness: spring stiffness ``k_e`` [force / world unit], float32 ``[E]``.
        damping: damping coefficients ``gamma_i`` [force * s / world unit], float32 ``[M]``.
        mass: node masses ``g_i`` (must be nonzero; not checked, to avoid a host sync), float32 ``[M]``.
        force: external forces ``F_i^ext``, float32 ``[M, 3]``.
        dt: time step [s], a finite Python number.

    Returns:
        ``(x_next, v_next)``, float32 ``[M, 3]`` each, on the inputs' device.

    Gradients: with respect to ``x``, ``v``, ``rest_offset``, ``stiffness``, ``damping``, ``mass`` and
    ``force`` (hand-written backward kernels; not twice differentiable). None for ``edges`` and ``dt``.

    Raises:
        TypeError: a float input is not float32, ``edges`` is not an integer tensor, ``dt`` not a number.
        ValueError: inconsistent shapes, devices, or a non-finite ``dt``.
    """
    check_tensor("x", x, (None, 3))
    device = x.device
    node_count = x.shape[0]
    check_tensor("v", v, (node_count, 3), device=device)
    _check_edges(edges, device)
    edge_count = edges.shape[0]
    check_tensor("rest_offset", rest_offset, (edge_count, 3), device=device)
    check_tensor("stiffness", stiffness, (edge_count,), device=device)
    check_tensor("damping", damping, (node_count,), device=device)
    check_tensor("mass", mass, (node_count,), device=device)
    check_tensor("force", force, (node_count, 3), device=device)
    for name, tensor in (
        ("x", x), ("v", v), ("rest_offset", rest_offset), ("stiffness", stiffness),
        ("damping", damping), ("mass", mass), ("force", force),
    ):
        _check_float32(name, tensor)
    if isinstance(dt, bool) or not isinstance(dt, numbers.Real):
        raise TypeError(f"dt must be a Python number, got {type(dt).__name__}")
    dt = float(dt)
    if not math.isfinite(dt):
        raise ValueError(f"dt must be finite, got {dt}")
    return _SpringStep.apply(
        x.contiguous(),
        v.contiguous(),
        _prepare_edges(edges, node_count),
        rest_offset.contiguous(),
        stiffness.contiguous(),
        damping.contiguous(),
        mass.contiguous(),
        force.contiguous(),
        dt,
    )


class _IsometryLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, edges, rest_offset):
        terms = torch.empty((2, edges.shape[0]), dtype=torch.float32, device=x.device)
        with torch_stream_scope(x.device):
            launch_isometry_terms(to_warp(x, wp.vec3), to_warp(edges), to_warp(rest_offset, wp.vec3), to_warp(terms))
        totals = terms.sum(dim=1)
        valid_count = totals[1].clamp_min(1.0)
        ctx.save_for_backward(x, edges, rest_offset, valid_count)
        return totals[0] / valid_count

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_loss):
        x, edges, rest_offset, valid_count = ctx.saved_tensors
        grad_scale = (grad_loss.to(torch.float32) / valid_count).reshape(1).contiguous()
        grad_x = torch.zeros_like(x)
        grad_rest_offset = torch.empty_like(rest_offset)
        with torch_stream_scope(x.device):
            launch_isometry_adjoint(
                to_warp(x, wp.vec3),
                to_warp(edges),
                to_warp(rest_offset, wp.vec3),
                to_warp(grad_scale),
                to_warp(grad_x, wp.vec3),
                to_warp(grad_rest_offset, wp.vec3),
            )
        return grad_x, None, grad_rest_offset


def isometry_loss(x: torch.Tensor, edges: torch.Tensor, rest_offset: torch.Tensor) -> torch.Tensor:
    """Isometry regularizer of SMAD (Eq. 11), as a mean over edges.

    Computes ``mean over valid edges e = (i, j) of (|x_i - x_j| - |rest_offset_e|)^2``, i.e. Eq. 11's sum
    divided by the number of valid edges (edges with both ids in ``[0, M)``; others, such as ``-1`` padding,
    are ignored). No valid edge gives 0.

    Args:
        x: positions [world units], float32 ``[M, 3]``.
        edges: (i, j) node ids, integer ``[E, 2]``.
        rest_offset: rest offsets ``L_ij`` [world units], float32 ``[E, 3]``; only their lengths matter.

    Returns:
        Scalar float32 tensor [world units^2].

    Gradients: with respect to ``x`` and ``rest_offset``; where a current or rest length is 0 the direction
    is undefined and that edge contributes no gradient to it.
    """
    check_tensor("x", x, (None, 3))
    _check_edges(edges, x.device)
    check_tensor("rest_offset", rest_offset, (edges.shape[0], 3), device=x.device)
    _check_float32("x", x)
    _check_float32("rest_offset", rest_offset)
    return _IsometryLoss.apply(x.contiguous(), _prepare_edges(edges, x.shape[0]), rest_offset.contiguous())


class _DampingLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, velocity):
        vector_count = velocity.shape[0]
        terms = torch.empty(vector_count, dtype=torch.float32, device=velocity.device)
        with torch_stream_scope(velocity.device):
            launch_damping_terms(to_warp(velocity, wp.vec3), to_warp(terms))
        ctx.save_for_backward(velocity)
        return terms.sum() / max(vector_count, 1)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_loss):
        (velocity,) = ctx.saved_tensors
        grad_scale = (grad_loss.to(torch.float32) / max(velocity.shape[0], 1)).reshape(1).contiguous()
        grad_velocity = torch.empty_like(velocity)
        with torch_stream_scope(velocity.device):
            launch_damping_adjoint(to_warp(velocity, wp.vec3), to_warp(grad_scale), to_warp(grad_velocity, wp.vec3))
        return grad_velocity


def damping_loss(velocity: torch.Tensor) -> torch.Tensor:
    """Damping regularizer of SMAD (Eq. 11), as a mean over velocity vectors.

    Computes ``mean over all velocity vectors of |v|^2``: Eq. 11 sums ``|v_i(t)|^2`` over nodes ``i`` and
    frames ``t``; this divides that sum by the number of vectors (nodes x frames). Empty input gives 0.

    Args:
        velocity: velocities [world units / s], float32 ``[..., 3]``, e.g. ``[M, 3]`` or ``[T, M, 3]``.

    Returns:
        Scalar float32 tensor [world units^2 / s^2], differentiable with respect to ``velocity``.
    """
    if not isinstance(velocity, torch.Tensor):
        raise TypeError(f"velocity must be a torch.Tensor, got {type(velocity).__name__}")
    if velocity.dim() < 1 or velocity.shape[-1] != 3:
        raise ValueError(f"velocity must have shape [..., 3], got {list(velocity.shape)}")
    check_tensor("velocity", velocity, (None,) * velocity.dim())
    _check_float32("velocity", velocity)
    return _DampingLoss.apply(velocity.reshape(-1, 3).contiguous())
