"""Autograd bridge of the particle-capsule collision kernels (:mod:`warpavatar.kernels.collision`)."""

from __future__ import annotations

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels.collision import launch_capsule_push_out, launch_capsule_push_out_adjoint

__all__ = ["push_out_of_capsules"]


def _nothing_to_do(x: torch.Tensor, radius: torch.Tensor) -> bool:
    return x.shape[0] == 0 or radius.shape[0] == 0


class _PushOutOfCapsules(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, segment_start, segment_end, radius):
        ctx.save_for_backward(x, segment_start, segment_end, radius)
        if _nothing_to_do(x, radius):  # (Warp rejects the strides of some empty tensors: skip them early)
            return x.clone()
        x_out = torch.empty_like(x)
        with torch_stream_scope(x.device):
            launch_capsule_push_out(
                to_warp(x, wp.vec3),
                to_warp(segment_start, wp.vec3),
                to_warp(segment_end, wp.vec3),
                to_warp(radius),
                to_warp(x_out, wp.vec3),
            )
        return x_out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x_out):
        x, segment_start, segment_end, radius = ctx.saved_tensors
        grad_x_out = grad_x_out.to(torch.float32).contiguous()
        grad_x = torch.empty_like(x)
        grad_start = torch.zeros_like(segment_start)
        grad_end = torch.zeros_like(segment_end)
        grad_radius = torch.zeros_like(radius)
        if _nothing_to_do(x, radius):
            return (grad_x_out.clone() if ctx.needs_input_grad[0] else None, grad_start, grad_end, grad_radius)
        with torch_stream_scope(x.device):
            launch_capsule_push_out_adjoint(
                to_warp(x, wp.vec3),
                to_warp(segment_start, wp.vec3),
                to_warp(segment_end, wp.vec3),
                to_warp(radius),
                to_warp(grad_x_out, wp.vec3),
                to_warp(grad_x, wp.vec3),
                to_warp(grad_start, wp.vec3),
                to_warp(grad_end, wp.vec3),
                to_warp(grad_radius),
            )
        needs = ctx.needs_input_grad
        return (
            grad_x if needs[0] else None,
            grad_start if needs[1] else None,
            grad_end if needs[2] else None,
            grad_radius if needs[3] else None,
        )


def push_out_of_capsules(
    x: torch.Tensor, segment_start: torch.Tensor, segment_end: torch.Tensor, radius: torch.Tensor
) -> torch.Tensor:
    """Push particles out of capsules (the body's collision shapes) onto their surfaces.

    Capsule ``c`` holds the points within ``radius[c]`` of the segment from ``segment_start[c]`` to
    ``segment_end[c]``. A particle strictly inside it is moved along the outward normal from the closest
    point ``p`` of the segment to the surface, ``p + radius * n``. With several capsules the moves of all
    capsules, each computed from the input position, are summed (a Jacobi pass: the result is a pure
    function of the inputs; apply it again where overlapping capsules leave a particle inside one). A
    particle on the segment's axis (closer than 1e-9) is pushed along a fixed perpendicular of the segment
    (``+z`` for a segment shorter than 1e-6, which acts as a sphere); a capsule of radius ``<= 0`` holds
    nothing. One kernel launch forward and one backward; no host synchronization.

    Args:
        x: particle positions [world units], float32 ``[N, 3]``.
        segment_start: first endpoint of each capsule's segment [world units], float32 ``[C, 3]``.
        segment_end: second endpoint of each capsule's segment [world units], float32 ``[C, 3]``.
        radius: capsule radii [world units], float32 ``[C]``.

    Returns:
        The pushed positions, float32 ``[N, 3]``, on the inputs' device (``x`` itself is not modified).

    Gradients: with respect to ``x``, ``segment_start``, ``segment_end`` and ``radius`` (hand-written
    backward kernel, not twice differentiable). The map is piecewise smooth; at its kinks (a particle on a
    capsule's surface, or level with an end of the segment) the gradient of the side taken by the forward
    pass is returned. The fallback normal on the axis carries no gradient.

    Raises:
        TypeError: an input is not a float32 tensor.
        ValueError: bad shapes, or inputs on different devices.
    """
    check_tensor("x", x, (None, 3))
    device = x.device
    check_tensor("segment_start", segment_start, (None, 3), device=device)
    capsule_count = segment_start.shape[0]
    check_tensor("segment_end", segment_end, (capsule_count, 3), device=device)
    check_tensor("radius", radius, (capsule_count,), device=device)
    for name, tensor in (("x", x), ("segment_start", segment_start), ("segment_end", segment_end),
                         ("radius", radius)):
        if tensor.dtype != torch.float32:
            raise TypeError(f"{name} must be float32, got {tensor.dtype}")
    return _PushOutOfCapsules.apply(x.contiguous(), segment_start.contiguous(), segment_end.contiguous(),
                                    radius.contiguous())
