"""Plain-torch references of the correction ops (:mod:`warpavatar._src.correction`): a pose correction's
outputs applied to canonical Gaussians, a pose's frame code, and the first-layer bias of a frame."""

from __future__ import annotations

import torch

from warpavatar.geometry import match_pose, quat_from_vector, quat_multiply

__all__ = ["apply_correction", "match_frame_code", "frame_bias"]


def apply_correction(outputs, means, quats, scales, offset_scale):
    """Reference of :func:`warpavatar.ops.apply_correction` (the first 9 columns of ``outputs`` are read)."""
    outputs = outputs[:, :9].float()
    rotated = quat_multiply(quat_from_vector(outputs[:, 3:6]), quats)
    return means + outputs[:, :3] * offset_scale, rotated, scales * torch.exp(outputs[:, 6:9].clamp(-3.0, 3.0))


def match_frame_code(frame_poses, pose, codes, *, tolerance=1e-4):
    """Reference of :func:`warpavatar.ops.match_frame_code`."""
    best, matched = match_pose(frame_poses, pose, tolerance=tolerance)
    return codes[best] * matched


def frame_bias(bone_transforms, parent_index, encoder_weight, encoder_bias, code, weight, bias, *, low, high,
               dtype=torch.float32):
    """Reference of :func:`warpavatar.ops.frame_bias`."""
    rotations = bone_transforms[: parent_index.shape[0], :3, :3]
    relative = rotations[parent_index.long()].transpose(1, 2) @ rotations - torch.eye(3, device=rotations.device)
    feature = encoder_weight @ relative[:, :, :2].reshape(-1) + encoder_bias
    if code is not None:
        feature = torch.cat([feature, code])
    return torch.maximum(torch.minimum(weight @ feature + bias, high), low).to(dtype)
