"""Autograd bridge of a cloth substep's edge terms (:mod:`warpavatar.kernels.cloth`)."""

from __future__ import annotations

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.springs import _check_edges, _check_float32, _prepare_edges
from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels.cloth import launch_cloth_edge_terms, launch_cloth_edge_terms_adjoint

__all__ = ["cloth_edge_terms"]


class _ClothEdgeTerms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v, edges, rest_length, edge_damping):
        ctx.save_for_backward(x, v, edges, rest_length, edge_damping)
        rest_offset = torch.zeros(edges.shape[0], 3, dtype=x.dtype, device=x.device)
        damping_force = torch.zeros_like(x)
        if edges.shape[0] and x.shape[0]:  # (Warp rejects the strides of some empty tensors: skip them early)
            with torch_stream_scope(x.device):
                launch_cloth_edge_terms(
                    to_warp(x, wp.vec3), to_warp(v, wp.vec3), to_warp(edges), to_warp(rest_length),
                    to_warp(edge_damping), to_warp(rest_offset, wp.vec3), to_warp(damping_force, wp.vec3),
                )
        return rest_offset, damping_force

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rest_offset, grad_damping_force):
        x, v, edges, rest_length, edge_damping = ctx.saved_tensors
        grad_x, grad_v = torch.zeros_like(x), torch.zeros_like(v)
        grad_rest_length, grad_edge_damping = torch.zeros_like(rest_length), torch.zeros_like(edge_damping)
        if edges.shape[0] and x.shape[0]:
            with torch_stream_scope(x.device):
                launch_cloth_edge_terms_adjoint(
                    to_warp(x, wp.vec3), to_warp(v, wp.vec3), to_warp(edges), to_warp(rest_length),
                    to_warp(edge_damping),
                    to_warp(grad_rest_offset.to(torch.float32).contiguous(), wp.vec3),
                    to_warp(grad_damping_force.to(torch.float32).contiguous(), wp.vec3),
                    to_warp(grad_x, wp.vec3), to_warp(grad_v, wp.vec3), to_warp(grad_rest_length),
                    to_warp(grad_edge_damping),
                )
        needs = ctx.needs_input_grad
        return (grad_x if needs[0] else None, grad_v if needs[1] else None, None,
                grad_rest_length if needs[3] else None, grad_edge_damping if needs[4] else None)


def cloth_edge_terms(
    x: torch.Tensor, v: torch.Tensor, edges: torch.Tensor, rest_length: torch.Tensor, edge_damping: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The edge terms of a cloth substep: length-spring rest offsets and edge damping forces, in one pass.

    For every directed edge ``e = (i, j)`` (``i = edges[e, 0]`` receives), with ``d = x_i - x_j``::

        rest_offset_e   = min(rest_length_e, 2 |d|) * d / |d|      (0 where |d| <= 1e-12)
        damping_force_i = -sum over edges e received by i of  edge_damping_e * (v_i - v_j)

    Passed as ``rest_offset`` to :func:`spring_step` (same edges, both directions of each pair), the offsets
    make its spring term the exact length spring ``k_e (|d| - L'_e) d / |d|``, with the rest length clamped
    to ``L'_e = min(L_e, 2 |d|)`` so that a spring squeezed below half its length cannot push harder than
    ``k_e |d|`` (bounded transverse stiffness). Edges with an endpoint outside ``[0, M)`` are ignored (zero
    offset, no force). One kernel launch forward and one backward; no host synchronization.

    Args:
        x: node positions [world units], float32 ``[M, 3]``.
        v: node velocities [world units / s], float32 ``[M, 3]``.
        edges: (receiver, sender) node ids, integer ``[E, 2]`` (int32 avoids a conversion per call).
        rest_length: rest length ``L_e`` of each edge [world units], float32 ``[E]``.
        edge_damping: damping coefficient ``c_e`` of each edge [force * s / world unit], float32 ``[E]``.

    Returns:
        ``(rest_offset [E, 3], damping_force [M, 3])``, float32, on the inputs' device.

    Gradients: with respect to ``x``, ``v``, ``rest_length`` and ``edge_damping`` (hand-written backward,
    not twice differentiable). At the clamp's kink (``L_e = 2 |d|``) the clamped side's gradient is used; an
    edge shorter than 1e-12 passes no gradient to positions or rest length.

    Raises:
        TypeError: a float input is not float32, or ``edges`` is not an integer tensor.
        ValueError: inconsistent shapes or devices.
    """
    check_tensor("x", x, (None, 3))
    device = x.device
    node_count = x.shape[0]
    check_tensor("v", v, (node_count, 3), device=device)
    _check_edges(edges, device)
    edge_count = edges.shape[0]
    check_tensor("rest_length", rest_length, (edge_count,), device=device)
    check_tensor("edge_damping", edge_damping, (edge_count,), device=device)
    for name, tensor in (("x", x), ("v", v), ("rest_length", rest_length), ("edge_damping", edge_damping)):
        _check_float32(name, tensor)
    return _ClothEdgeTerms.apply(x.contiguous(), v.contiguous(), _prepare_edges(edges, node_count),
                                 rest_length.contiguous(), edge_damping.contiguous())
