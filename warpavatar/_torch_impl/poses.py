"""Plain-torch references of the refined-pose ops (:mod:`warpavatar._src.poses`): corrected poses composed joint by
joint down the skeleton (the exponential map by ``torch.linalg.matrix_exp``), and the priors of a refined motion
written with torch's pooling and slicing."""

from __future__ import annotations

import torch

from warpavatar.geometry import skeleton_levels

__all__ = ["corrected_poses", "pose_priors"]


def _skew(vectors: torch.Tensor) -> torch.Tensor:
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*vectors.shape[:-1], 3, 3)


def corrected_poses(bone_transforms, heads, parents, rotation, translation):
    """Reference of :func:`warpavatar.ops.corrected_poses`."""
    given = bone_transforms[..., :3, :3]
    pivots = (given @ heads[:, :, None])[..., 0] + bone_transforms[..., :3, 3]
    turn = given @ torch.linalg.matrix_exp(_skew(rotation)) @ given.transpose(-1, -2)
    roots = torch.as_tensor([int(p) < 0 for p in parents], dtype=bone_transforms.dtype,
                            device=bone_transforms.device)
    shift = pivots - (turn @ pivots[..., None])[..., 0] + roots[:, None] * translation[..., None, :]
    local = torch.zeros_like(bone_transforms)
    local[..., :3, :3] = turn
    local[..., :3, 3] = shift
    local[..., 3, 3] = 1.0
    world = [None] * len(parents)
    for level in skeleton_levels(parents):
        for joint in level:
            parent = int(parents[joint])
            world[joint] = local[..., joint, :, :] if parent < 0 else world[parent] @ local[..., joint, :, :]
    return torch.stack(world, dim=-3) @ bone_transforms


def _acceleration(values: torch.Tensor, gaps: torch.Tensor) -> torch.Tensor:
    gaps = gaps.reshape(-1, *([1] * (values.dim() - 1)))
    slopes = (values[1:] - values[:-1]) / gaps
    return (slopes[1:] - slopes[:-1]) * (2.0 / (gaps[1:] + gaps[:-1]))


def pose_priors(poses, heads, rotation, translation, *, target_rotation, target_translation, target_pivots,
                view_axes, gaps, scale, depth_window):
    """Reference of :func:`warpavatar.ops.pose_priors`."""
    prior = ((rotation - target_rotation).square().sum(-1).mean()
             + ((translation - target_translation) * scale).square().sum(-1).mean())
    pivots = ((poses[..., :3, :3] @ heads[:, :, None])[..., 0] + poses[..., :3, 3]) * scale
    depth = ((pivots - target_pivots) * view_axes[:, None, :]).sum(-1)  # [T,J]
    if depth.shape[0] >= depth_window:
        depth = torch.nn.functional.avg_pool1d(depth.T[:, None, :], depth_window, stride=1,
                                               padding=depth_window // 2, count_include_pad=False)[:, 0].T
    depth = depth.square().mean()
    if poses.shape[0] >= 3:
        smooth = (_acceleration(pivots, gaps).square().sum(-1).mean()
                  + _acceleration(poses[:, :, :3, :3], gaps).square().sum((-2, -1)).mean())
    else:
        smooth = torch.zeros((), dtype=poses.dtype, device=poses.device)
    return torch.stack([prior, depth, smooth])
