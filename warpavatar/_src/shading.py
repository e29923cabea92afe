"""Torch autograd bridge of the shading kernels (``kernels/shading.py``): view-dependent SH colour.

One forward pass is one Warp launch, one backward pass one Warp launch plus the torch allocations of the
gradients (and a sum when the origin needs a gradient); neither reads anything back to the host. The
plain-torch reference with the same signature is :func:`warpavatar._torch_impl.shading.view_colors`.
"""

from __future__ import annotations

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import shading as kernels

__all__ = ["view_colors"]


def _warp_inputs(means, quats, canonical_quats, coefficients, origin):
    return (to_warp(means, dtype=wp.vec3), to_warp(quats, dtype=wp.vec4), to_warp(canonical_quats, dtype=wp.vec4),
            to_warp(coefficients, dtype=wp.vec3), to_warp(origin.reshape(1, 3), dtype=wp.vec3))


class _ViewColorsFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, canonical_quats, coefficients, origin, degree):
        colors = torch.empty_like(means)
        ctx.save_for_backward(means, quats, canonical_quats, coefficients, origin)
        ctx.degree = degree
        with torch_stream_scope(means.device):
            kernels.view_colors_forward(*_warp_inputs(means, quats, canonical_quats, coefficients, origin),
                                        to_warp(colors, dtype=wp.vec3), degree=degree)
        return colors

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_colors):
        means, quats, canonical_quats, coefficients, origin = ctx.saved_tensors
        grad_means = torch.empty_like(means)
        grad_quats = torch.empty_like(quats)
        grad_canonical_quats = torch.empty_like(canonical_quats)
        # the kernel writes the first (degree + 1)^2 coefficients; any further ones get no gradient
        coefficient_count = (ctx.degree + 1) ** 2
        grad_coefficients = (torch.empty_like(coefficients) if coefficients.shape[1] == coefficient_count
                             else torch.zeros_like(coefficients))
        with torch_stream_scope(means.device):
            kernels.view_colors_backward(
                *_warp_inputs(means, quats, canonical_quats, coefficients, origin),
                to_warp(grad_colors.contiguous(), dtype=wp.vec3), to_warp(grad_means, dtype=wp.vec3),
                to_warp(grad_quats, dtype=wp.vec4), to_warp(grad_canonical_quats, dtype=wp.vec4),
                to_warp(grad_coefficients, dtype=wp.vec3), degree=ctx.degree,
            )
        # the direction is mean - origin, so the origin's gradient is minus the sum of the means'
        # at degree 0 the direction is unused: its inputs get no gradient (None, so autograd adds no zeros)
        needs = [need and (ctx.degree > 0 or index == 3) for index, need in enumerate(ctx.needs_input_grad)]
        grad_origin = -grad_means.sum(dim=0).reshape(origin.shape) if needs[4] else None
        return (grad_means if needs[0] else None, grad_quats if needs[1] else None,
                grad_canonical_quats if needs[2] else None, grad_coefficients if needs[3] else None, grad_origin,
                None)


def view_colors(means: torch.Tensor, quats: torch.Tensor, canonical_quats: torch.Tensor,
                sh_coefficients: torch.Tensor, origin: torch.Tensor, *, sh_degree: int | None = None
                ) -> torch.Tensor:
    """RGB of Gaussians seen from ``origin``, with SH evaluated in each Gaussian's canonical frame.

    Per Gaussian ``i``: ``d = normalize(means[i] - origin)``, rotated back by the skinning rotation,
    ``d' = R(canonical_quats[i]) R(quats[i])^T d`` (quaternions used as given, not normalized), renormalized;
    then ``max(sum_k basis_k(d') sh_coefficients[i, k] + 0.5, 0)`` with the real SH basis of the 3DGS
    coefficient order. At degree 0 the direction is not used. Lengths are clamped at 1e-12 before dividing.
    One fused Warp kernel forward, one backward; gradients flow to every tensor argument (the clamp passes
    none where the sum is negative).

    Args:
        means: float32 ``[N, 3]`` posed centres (world units), CPU or CUDA.
        quats: float32 ``[N, 4]`` posed orientations (w, x, y, z), on the same device.
        canonical_quats: float32 ``[N, 4]`` rest-pose orientations (w, x, y, z).
        sh_coefficients: float32 ``[N, K, 3]`` SH coefficients per RGB channel, ``K >= (sh_degree + 1)^2``.
        origin: float32 ``[3]`` the point view directions start from (a camera centre), world units.
        sh_degree: SH degree 0..3 to evaluate; default: the one ``K`` holds (``K`` must be 1, 4, 9 or 16).

    Returns:
        float32 ``[N, 3]`` colours (>= 0).
    """
    check_tensor("means", means, (None, 3), dtype_kind="float32")
    device = means.device
    count = means.shape[0]
    check_tensor("quats", quats, (count, 4), dtype_kind="float32", device=device)
    check_tensor("canonical_quats", canonical_quats, (count, 4), dtype_kind="float32", device=device)
    check_tensor("sh_coefficients", sh_coefficients, (count, None, 3), dtype_kind="float32", device=device)
    check_tensor("origin", origin, (3,), dtype_kind="float32", device=device)
    coefficient_count = sh_coefficients.shape[1]
    if sh_degree is None:
        sh_degree = round(coefficient_count ** 0.5) - 1
        if (sh_degree + 1) ** 2 != coefficient_count:
            raise ValueError(f"sh_coefficients holds {coefficient_count} coefficients per channel, not a square "
                             f"(1, 4, 9 or 16): pass sh_degree")
    if not 0 <= sh_degree <= kernels.SH_MAX_DEGREE:
        raise ValueError(f"sh_degree must be 0..{kernels.SH_MAX_DEGREE}, got {sh_degree}")
    if coefficient_count < (sh_degree + 1) ** 2:
        raise ValueError(f"sh_degree {sh_degree} needs {(sh_degree + 1) ** 2} coefficients per channel, "
                         f"sh_coefficients holds {coefficient_count}")
    if count == 0:  # empty tensors may carry strides Warp refuses; the product keeps the graph connected
        return means * 0.0
    return _ViewColorsFunction.apply(means.contiguous(), quats.contiguous(), canonical_quats.contiguous(),
                                     sh_coefficients.contiguous(), origin.contiguous(), sh_degree)
