"""Plain-torch reference of the shading op (:mod:`warpavatar._src.shading`), same signature.

This is the op-by-op code :meth:`warpavatar.model.Avatar.view_colors` ran before the fused kernel: the
geometry helpers :func:`~warpavatar.geometry.quat_rotate` and :func:`~warpavatar.geometry.sh_basis`, in the
inputs' dtype (float64 included), differentiated by autograd.
"""

from __future__ import annotations

import torch

from warpavatar.geometry import SH_C0, quat_rotate, sh_basis

__all__ = ["view_colors"]


def view_colors(means: torch.Tensor, quats: torch.Tensor, canonical_quats: torch.Tensor,
                sh_coefficients: torch.Tensor, origin: torch.Tensor, *, sh_degree: int | None = None
                ) -> torch.Tensor:
    """Reference of :func:`warpavatar.ops.view_colors`: ``[N, 3]`` colours of Gaussians seen from ``origin``.

    Args:
        means: ``[N, 3]`` posed centres; quats, canonical_quats: ``[N, 4]`` (w, x, y, z), used as given;
        sh_coefficients: ``[N, K, 3]``; origin: ``[3]``; sh_degree: 0..3 (default from ``K``).
    """
    if sh_degree is None:
        sh_degree = round(sh_coefficients.shape[1] ** 0.5) - 1
    coefficients = sh_coefficients[:, :(sh_degree + 1) ** 2]
    if sh_degree == 0:
        return torch.clamp_min(coefficients[:, 0] * SH_C0 + 0.5, 0.0)
    directions = means - origin.to(means)
    directions = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # skinning rotation R_i = R(q_posed) R(q_canonical)^T, so R_i^T d = R(q_canonical) R(q_posed)^T d
    directions = quat_rotate(canonical_quats, quat_rotate(quats, directions, inverse=True))
    basis = sh_basis(sh_degree, directions)  # [N,(d+1)^2]
    return torch.clamp_min((basis[:, :, None] * coefficients).sum(dim=1) + 0.5, 0.0)
