"""Plain-torch references of the skinning ops (:mod:`warpavatar._src.skinning`), same signatures.

``sample_grid`` is ``torch.nn.functional.grid_sample`` on normalized coordinates; the closest rotation of a
blended affine is taken from ``torch.linalg.svd`` (the Warp kernels use a different algorithm: an SVD
estimate refined by Newton steps, differentiated implicitly), so agreement between the two is a real check.
They run in the inputs' dtype, float64 included, and are differentiated by autograd.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from warpavatar.geometry import quat_conjugate, quat_from_matrix, quat_multiply

__all__ = ["sample_grid", "lbs", "inverse_lbs", "closest_rotation_quat"]


def sample_grid(grid: torch.Tensor, points: torch.Tensor, bbox_min, bbox_max) -> torch.Tensor:
    """Reference of :func:`warpavatar.ops.sample_grid`: ``grid_sample`` (bilinear, align_corners, border).

    Args:
        grid: ``[D, H, W, C]`` samples.
        points: ``[N, 3]`` positions (x runs along W, y along H, z along D).
        bbox_min, bbox_max: the box's corners, tensors of shape [3] or 3 floats.

    Returns:
        ``[N, C]`` values.
    """
    low = torch.as_tensor(bbox_min, dtype=points.dtype, device=points.device).reshape(3)
    high = torch.as_tensor(bbox_max, dtype=points.dtype, device=points.device).reshape(3)
    point_count, channel_count = points.shape[0], grid.shape[3]
    if point_count == 0 or channel_count == 0:
        return (grid.sum() + points.sum()) * points.new_zeros(point_count, channel_count)
    normalized = 2.0 * (points - low) / (high - low) - 1.0
    volume = grid.permute(3, 0, 1, 2).unsqueeze(0)  # [1, C, D, H, W]
    sampled = F.grid_sample(
        volume, normalized.view(1, point_count, 1, 1, 3),
        mode="bilinear", padding_mode="border", align_corners=True,
    )  # [1, C, N, 1, 1]
    return sampled.view(channel_count, point_count).t()


def closest_rotation_quat(linear: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) quaternions, w >= 0, of the proper rotations closest to ``linear`` ``[N, 3, 3]``.

    ``R = U diag(1, 1, sign det(U V^T)) V^T`` from the SVD ``linear = U S V^T``: the rotation maximizing
    ``tr(R^T linear)`` (the polar factor when the determinant is positive).
    """
    u, _, vh = torch.linalg.svd(linear)
    sign = torch.where(torch.linalg.det(u @ vh) < 0, -1.0, 1.0).to(linear.dtype)
    flip = torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], -1)
    return quat_from_matrix((u * flip.unsqueeze(1)) @ vh)


def _blend(weights: torch.Tensor, bone_transforms: torch.Tensor):
    blended = torch.einsum("nj,jab->nab", weights, bone_transforms[:, :3, :])  # [N, 3, 4]
    return blended[:, :, :3], blended[:, :, 3]


def lbs(points: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor, *,
        quats: torch.Tensor | None = None):
    """Reference of :func:`warpavatar.ops.lbs`: ``x' = A x + t``, ``q' = q(closest rotation of A) * q``."""
    linear, translation = _blend(weights, bone_transforms)
    points_posed = (linear @ points.unsqueeze(-1)).squeeze(-1) + translation
    if quats is None:
        return points_posed, None
    if points.shape[0] == 0:
        return points_posed, quats * 1.0
    return points_posed, quat_multiply(closest_rotation_quat(linear), quats)


def inverse_lbs(points_posed: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor, *,
                quats: torch.Tensor | None = None):
    """Reference of :func:`warpavatar.ops.inverse_lbs`: ``x = A^-1 (x' - t)``, ``q = conj(q(R)) * q'``."""
    linear, translation = _blend(weights, bone_transforms)
    points = torch.linalg.solve(linear, (points_posed - translation).unsqueeze(-1)).squeeze(-1)
    if quats is None:
        return points, None
    if points_posed.shape[0] == 0:
        return points, quats * 1.0
    return points, quat_multiply(quat_conjugate(closest_rotation_quat(linear)), quats)
