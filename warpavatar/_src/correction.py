"""Torch bridge of the correction kernels (``kernels/correction.py``): a pose correction's network outputs applied
to canonical Gaussians in one launch, and a pose's frame code in two, for playback (no gradients). The torch
code they stand in for, which fits differentiate, is
:func:`warpavatar.extensions.pose_correction.corrected_gaussians` and
:meth:`~warpavatar.extensions.pose_correction.PoseCorrection.frame_code`."""

from __future__ import annotations

import torch
import warp as wp

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import correction as kernels

__all__ = ["apply_correction", "match_frame_code", "frame_bias"]


def apply_correction(outputs: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                     offset_scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Corrected canonical Gaussians from a pose correction's outputs, in one kernel.

    Per Gaussian: ``means + offset_scale * outputs[:, 0:3]``, ``q(outputs[:, 3:6]) * quats`` with
    ``q(v) = (1, v) / |(1, v)|`` (Hamilton product, (w, x, y, z)), and
    ``scales * exp(clamp(outputs[:, 6:9], -3, 3))``. Not differentiable (playback): raises when a gradient is
    asked for.

    Args:
        outputs: [N,C] float32 or float16 network outputs, C >= 9 (columns past the 9th are not read).
        means: float32 [N,3] canonical centres [world units].
        quats: float32 [N,4] unit orientations (w, x, y, z).
        scales: float32 [N,3] scales [world units].
        offset_scale: float32 [] or [1] world length of a unit offset output (a device tensor: no host read).

    Returns:
        ``(means [N,3], quats [N,4], scales [N,3])``, float32, new tensors.
    """
    if torch.is_grad_enabled() and any(t.requires_grad for t in (outputs, means, quats, scales, offset_scale)):
        raise ValueError("apply_correction has no gradients (playback only): call it under torch.no_grad()")
    check_tensor("means", means, (None, 3), dtype_kind="float32")
    count, device = means.shape[0], means.device
    check_tensor("outputs", outputs, (count, None), device=device)
    if outputs.shape[1] < 9:
        raise ValueError(f"outputs must have at least 9 columns, got {outputs.shape[1]}")
    if outputs.dtype not in (torch.float32, torch.float16):
        raise ValueError(f"outputs must be float32 or float16, got {outputs.dtype}")
    check_tensor("quats", quats, (count, 4), dtype_kind="float32", device=device)
    check_tensor("scales", scales, (count, 3), dtype_kind="float32", device=device)
    check_tensor("offset_scale", offset_scale.reshape(-1), (1,), dtype_kind="float32", device=device)
    means_out, quats_out, scales_out = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
    with torch_stream_scope(device):
        kernels.apply_correction(to_warp(outputs), to_warp(means, dtype=wp.vec3), to_warp(quats, dtype=wp.vec4),
                                 to_warp(scales, dtype=wp.vec3), to_warp(offset_scale.reshape(1)),
                                 to_warp(means_out, dtype=wp.vec3), to_warp(quats_out, dtype=wp.vec4),
                                 to_warp(scales_out, dtype=wp.vec3))
    return means_out, quats_out, scales_out


def match_frame_code(frame_poses: torch.Tensor, pose: torch.Tensor, codes: torch.Tensor, *,
                     tolerance: float = 1e-4) -> torch.Tensor:
    """The code [C] of the training frame whose pose equals ``pose`` (every entry within ``tolerance``), else
    zeros, in two kernels and without a host read: the values of
    ``codes[best] * (closest <= tolerance)`` with :func:`warpavatar.geometry.match_pose`'s ``best`` (the first
    closest on ties). No gradients.

    Args:
        frame_poses: float32 [T,J,4,4] the training frames' poses (T >= 1).
        pose: float32 [J',4,4] this frame's transforms (J' >= J: the first J are compared).
        codes: float32 [T,C] the frames' codes.
        tolerance: largest entry difference of a match.
    """
    if torch.is_grad_enabled() and codes.requires_grad:
        raise ValueError("match_frame_code has no gradients (playback only): call it under torch.no_grad()")
    device = pose.device
    check_tensor("frame_poses", frame_poses, (None, None, 4, 4), dtype_kind="float32", device=device)
    check_tensor("pose", pose, (None, 4, 4), dtype_kind="float32")
    count = frame_poses.shape[0]
    check_tensor("codes", codes, (count, None), dtype_kind="float32", device=device)
    if count == 0:
        raise ValueError("frame_poses holds no pose")
    differences = torch.empty(count, device=device)  # each frame's largest entry difference
    code = torch.empty(codes.shape[1], device=device)
    with torch_stream_scope(device):
        kernels.match_frame_code(to_warp(frame_poses.reshape(count, -1)), to_warp(pose.reshape(-1)), to_warp(codes),
                                 tolerance, to_warp(differences), to_warp(code))
    return code


def frame_bias(bone_transforms: torch.Tensor, parent_index: torch.Tensor, encoder_weight: torch.Tensor,
               encoder_bias: torch.Tensor, code: torch.Tensor | None, weight: torch.Tensor, bias: torch.Tensor, *,
               low: torch.Tensor, high: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The pose correction's first-layer bias of a frame [H] in two kernels, without a host read: the values of
    ``clamp(bias + weight @ cat([encoder_bias + encoder_weight @ f, code]), low, high)`` with ``f`` the pose
    feature of :func:`warpavatar.extensions.pose_correction.relative_rotations_6d` (float32 sums in another
    order than torch's: float32 rounding apart). No gradients.

    Args:
        bone_transforms: float32 [J',4,4] skinning transforms (the first J are the skeleton's).
        parent_index: int32 [J] each joint's parent, itself for roots.
        encoder_weight: float32 [P, 6J] and encoder_bias [P]: the pose encoder.
        code: float32 [C] the frame code, or None.
        weight: float32 [H, P+C] the first layer's pose and code columns; bias: [H] its bias.
        low, high: float32 [H] the clamp.
        dtype: float32 or float16, the output's.
    """
    device = bone_transforms.device
    check_tensor("bone_transforms", bone_transforms, (None, 4, 4), dtype_kind="float32")
    check_tensor("parent_index", parent_index, (None,), dtype_kind="int", device=device)
    if parent_index.dtype != torch.int32:
        raise TypeError(f"parent_index must be int32, got {parent_index.dtype}")
    for name, tensor in (("encoder_weight", encoder_weight), ("weight", weight)):
        check_tensor(name, tensor, (None, None), dtype_kind="float32", device=device)
    for name, tensor in (("encoder_bias", encoder_bias), ("bias", bias), ("low", low), ("high", high),
                         *(() if code is None else (("code", code),))):
        check_tensor(name, tensor, (None,), dtype_kind="float32", device=device)
    if torch.is_grad_enabled() and any(t.requires_grad for t in (encoder_weight, weight, bias, bone_transforms)):
        raise ValueError("frame_bias has no gradients (playback only): call it under torch.no_grad()")
    feature = torch.empty(weight.shape[1], device=device)
    out = torch.empty(bias.shape[0], device=device, dtype=dtype)
    with torch_stream_scope(device):
        kernels.frame_bias(to_warp(bone_transforms, dtype=wp.mat44), to_warp(parent_index),
                           to_warp(encoder_weight), to_warp(encoder_bias), None if code is None else to_warp(code),
                           to_warp(weight), to_warp(bias), to_warp(low), to_warp(high), to_warp(feature),
                           to_warp(out))
    return out
