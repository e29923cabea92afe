"""Torch bridge of the refined-pose kernels (``kernels/poses.py``): every frame's corrected poses down the skeleton,
and the priors of the refined motion, each a few launches forward and backward (their torch forms took some 450
small kernels a step of pose refinement).
"""

from __future__ import annotations

import functools
from typing import Sequence

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.geometry import skeleton_levels
from warpavatar.kernels import poses as kernels

__all__ = ["corrected_poses", "pose_priors"]


@functools.lru_cache(maxsize=64)
def _skeleton_tables(parents: tuple[int, ...], device: torch.device) -> tuple[torch.Tensor, ...]:
    """(parents int32 [J], root float32 [J], subtree_offsets int32 [J+1], subtree_members int32: each joint's
    subtree, itself and its descendants) on ``device``, made once per skeleton and device (no host work on later
    calls, so a captured step can replay them)."""
    levels = skeleton_levels(parents)  # raises on a cycle
    subtrees = [[joint] for joint in range(len(parents))]
    for level in reversed(levels):  # children before their parents
        for joint in level:
            if parents[joint] >= 0:
                subtrees[parents[joint]] += subtrees[joint]
    offsets = [0]
    for subtree in subtrees:
        offsets.append(offsets[-1] + len(subtree))
    return (torch.tensor(parents, dtype=torch.int32, device=device),
            torch.tensor([float(p < 0) for p in parents], dtype=torch.float32, device=device),
            torch.tensor(offsets, dtype=torch.int32, device=device),
            torch.tensor([joint for subtree in subtrees for joint in subtree], dtype=torch.int32, device=device))


def _parents_tuple(parents: Sequence[int], joints: int) -> tuple[int, ...]:
    if isinstance(parents, torch.Tensor):
        raise TypeError("parents must be a sequence of ints (host data: a device tensor would need a host read)")
    parents = tuple(int(p) for p in parents)
    if len(parents) != joints:
        raise ValueError(f"parents has {len(parents)} entries, expected one per joint ({joints})")
    if any(not -1 <= p < joints for p in parents):
        raise ValueError(f"parents must lie in [-1, {joints}), got {parents}")
    return parents


class _CorrectedPoses(torch.autograd.Function):
    @staticmethod
    def forward(ctx, bone_transforms, heads, rotation, translation, parents, root, subtree_offsets, subtree_members):
        frames, joints = bone_transforms.shape[:2]
        motions = torch.empty_like(bone_transforms)
        world = torch.empty_like(bone_transforms)
        corrected = torch.empty_like(bone_transforms)
        if frames * joints:
            with torch_stream_scope(bone_transforms.device):
                poses = to_warp(bone_transforms, wp.mat44)
                kernels.launch_local_motions(poses, to_warp(heads, wp.vec3), to_warp(root),
                                             to_warp(rotation, wp.vec3), to_warp(translation, wp.vec3),
                                             to_warp(motions, wp.mat44))
                kernels.launch_compose_motions(poses, to_warp(parents), to_warp(motions, wp.mat44),
                                               to_warp(world, wp.mat44), to_warp(corrected, wp.mat44))
        ctx.save_for_backward(bone_transforms, heads, rotation, translation, parents, root, subtree_offsets,
                              subtree_members, world)
        return corrected

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_corrected):
        (bone_transforms, heads, rotation, translation, parents, root, subtree_offsets, subtree_members,
         world) = ctx.saved_tensors
        grad_rotation = torch.zeros_like(rotation)
        grad_translation = torch.zeros_like(translation)
        if bone_transforms.shape[0] * bone_transforms.shape[1]:
            grad_corrected = grad_corrected.to(torch.float32).contiguous()
            terms = torch.empty_like(world)  # scratch: the composition's backward, then the adjoint's replay
            adj_motions = torch.empty_like(world)
            with torch_stream_scope(bone_transforms.device):
                poses = to_warp(bone_transforms, wp.mat44)
                kernels.launch_compose_motions_adjoint(poses, to_warp(parents), to_warp(subtree_offsets),
                                                       to_warp(subtree_members), to_warp(world, wp.mat44),
                                                       to_warp(grad_corrected, wp.mat44), to_warp(terms, wp.mat44),
                                                       to_warp(adj_motions, wp.mat44))
                kernels.launch_local_motions_adjoint(poses, to_warp(heads, wp.vec3), to_warp(root),
                                                     to_warp(rotation, wp.vec3), to_warp(translation, wp.vec3),
                                                     to_warp(terms, wp.mat44),
                                                     to_warp(adj_motions, wp.mat44), to_warp(grad_rotation, wp.vec3),
                                                     to_warp(grad_translation, wp.vec3))
        needs = ctx.needs_input_grad
        return (None, None, grad_rotation if needs[2] else None, grad_translation if needs[3] else None, None, None,
                None, None)


def corrected_poses(bone_transforms: torch.Tensor, heads: torch.Tensor, parents: Sequence[int],
                    rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Poses with every joint turned by ``exp(rotation[t, j])`` in its own posed frame, after its given rotation
    relative to its parent, and the roots moved by ``translation[t]``; each child keeps its pivot's offset from its
    parent's pivot in the parent's frame, so the skeleton stays rigid (``kernels/poses.py`` gives the formulas).
    Two launches forward, three backward; no host read after a skeleton's first call.

    Args:
        bone_transforms: float32 [T,J,4,4] the given rest-to-posed transforms of T frames.
        heads: float32 [J,3] rest-pose pivots [world units].
        parents: J ints, each joint's parent (-1 for a root): host data (a list, a tuple).
        rotation: float32 [T,J,3] axis-angle corrections [rad]; differentiable.
        translation: float32 [T,3] the roots' offsets [world units]; differentiable.

    Returns:
        float32 [T,J,4,4] the corrected poses (the given ones where both corrections are zero).

    Raises:
        ValueError: shapes that do not agree, parents out of range or forming a cycle, or gradients asked of
            ``bone_transforms`` or ``heads``.
    """
    check_tensor("bone_transforms", bone_transforms, (None, None, 4, 4), dtype_kind="float32")
    frames, joints = bone_transforms.shape[:2]
    device = bone_transforms.device
    check_tensor("heads", heads, (joints, 3), dtype_kind="float32", device=device)
    check_tensor("rotation", rotation, (frames, joints, 3), dtype_kind="float32", device=device)
    check_tensor("translation", translation, (frames, 3), dtype_kind="float32", device=device)
    if bone_transforms.requires_grad or heads.requires_grad:
        raise ValueError("corrected_poses differentiates the corrections only, not bone_transforms or heads")
    return _CorrectedPoses.apply(bone_transforms.contiguous(), heads.contiguous(), rotation.contiguous(),
                                 translation.contiguous(), *_skeleton_tables(_parents_tuple(parents, joints), device))


class _PosePriors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                view_axes, gaps, scale, half):
        frames, joints = poses.shape[:2]
        shares = torch.empty(frames, joints, 3, dtype=torch.float32, device=poses.device)
        with torch_stream_scope(poses.device):
            kernels.launch_prior_shares(*_prior_arrays(poses, heads, rotation, translation, target_rotation,
                                                       target_translation, target_pivots, view_axes, gaps),
                                        scale=scale, half=half, shares=to_warp(shares, wp.vec3))
        ctx.save_for_backward(poses, heads, rotation, translation, target_rotation, target_translation,
                              target_pivots, view_axes, gaps)
        ctx.scale, ctx.half = scale, half
        return shares.sum((0, 1))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_priors):
        inputs = ctx.saved_tensors
        poses, rotation, translation = inputs[0], inputs[2], inputs[3]
        grad_poses = torch.empty_like(poses)
        grad_rotation = torch.empty_like(rotation)
        grad_translation = torch.empty_like(translation)
        with torch_stream_scope(poses.device):
            kernels.launch_prior_shares_adjoint(*_prior_arrays(*inputs), scale=ctx.scale, half=ctx.half,
                                                adj_priors=to_warp(grad_priors.to(torch.float32).contiguous()),
                                                adj_poses=to_warp(grad_poses, wp.mat44),
                                                adj_rotation=to_warp(grad_rotation, wp.vec3),
                                                adj_translation=to_warp(grad_translation, wp.vec3))
        needs = ctx.needs_input_grad
        return (grad_poses if needs[0] else None, None, grad_rotation if needs[2] else None,
                grad_translation if needs[3] else None, *([None] * 7))


def _prior_arrays(poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                  view_axes, gaps) -> tuple:
    return (to_warp(poses, wp.mat44), to_warp(heads, wp.vec3), to_warp(rotation, wp.vec3),
            to_warp(translation, wp.vec3), to_warp(target_rotation, wp.vec3), to_warp(target_translation, wp.vec3),
            to_warp(target_pivots, wp.vec3), to_warp(view_axes, wp.vec3), to_warp(gaps))


def pose_priors(poses: torch.Tensor, heads: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor, *,
                target_rotation: torch.Tensor, target_translation: torch.Tensor, target_pivots: torch.Tensor,
                view_axes: torch.Tensor, gaps: torch.Tensor, scale: float, depth_window: int) -> torch.Tensor:
    """The three priors of a refined motion of T frames and J joints, as [3] (prior, depth, smooth), in one launch
    forward and one backward (``kernels/poses.py`` gives the formulas):

    * prior: ``mean |rotation - target_rotation|^2`` over frames and joints plus
      ``mean |scale (translation - target_translation)|^2`` over frames;
    * depth: the mean square, over frames and joints, of the scaled pivots' moves from ``target_pivots`` along
      each frame's camera axis, each averaged over the ``depth_window`` frames around it (fewer at the ends; not
      averaged when T < ``depth_window``);
    * smooth: the mean square, over the inner frames and joints, of the second differences per video frame
      squared of the scaled pivots plus those of the rotation matrices (Frobenius); 0 when T < 3.

    Args:
        poses: float32 [T,J,4,4] the refined poses; differentiable.
        heads: float32 [J,3] rest-pose pivots [world units].
        rotation, target_rotation: float32 [T,J,3] the axis-angle corrections (differentiable) and their
            target [rad].
        translation, target_translation: float32 [T,3] the root offsets (differentiable) and their target
            [world units].
        target_pivots: float32 [T,J,3] the target's pivots times ``scale``.
        view_axes: float32 [T,3] each frame's unit camera axis in the world.
        gaps: float32 [T-1] video frames between consecutive frames (> 0).
        scale: the factor of every length (1 / the canonical extent).
        depth_window: odd number of frames the depth moves are averaged over.

    Returns:
        float32 [3]: (prior, depth, smooth).
    """
    check_tensor("poses", poses, (None, None, 4, 4), dtype_kind="float32")
    frames, joints = poses.shape[:2]
    device = poses.device
    if frames == 0 or joints == 0:
        raise ValueError(f"pose_priors needs at least one frame and joint, got poses of shape {list(poses.shape)}")
    check_tensor("heads", heads, (joints, 3), dtype_kind="float32", device=device)
    for name, tensor in (("rotation", rotation), ("target_rotation", target_rotation),
                         ("target_pivots", target_pivots)):
        check_tensor(name, tensor, (frames, joints, 3), dtype_kind="float32", device=device)
    for name, tensor in (("translation", translation), ("target_translation", target_translation),
                         ("view_axes", view_axes)):
        check_tensor(name, tensor, (frames, 3), dtype_kind="float32", device=device)
    check_tensor("gaps", gaps, (frames - 1,), dtype_kind="float32", device=device)
    if depth_window < 1 or depth_window % 2 == 0:
        raise ValueError(f"depth_window must be a positive odd number of frames, got {depth_window}")
    half = depth_window // 2 if frames >= depth_window else 0
    if frames < 3:  # the kernels read no gap then; Warp wants one element
        gaps = torch.ones(1, dtype=torch.float32, device=device)
    return _PosePriors.apply(*(t.contiguous() for t in (poses, heads, rotation, translation, target_rotation,
                                                         target_translation, target_pivots, view_axes, gaps)),
                             float(scale), int(half))
