"""Skeleton kinematics: rotations from axis-angle vectors, the skeleton's joints by depth, and a pose corrected
joint by joint (what pose refinement learns and what test-time refinement and the pose-noise tool apply)."""

from __future__ import annotations

import torch

__all__ = ["axis_angle_to_matrix", "skeleton_levels", "ancestor_jumps", "posed_pivots", "corrected_transforms"]


def axis_angle_to_matrix(vectors: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [...,3,3] of axis-angle vectors [...,3] (angle = norm [rad]); smooth, with finite
    gradients, at zero."""
    angle_sq = (vectors * vectors).sum(-1, keepdim=True)[..., None]  # [...,1,1]
    small = angle_sq < 1e-8
    angle = torch.sqrt(torch.where(small, torch.ones_like(angle_sq), angle_sq))
    # sin(a)/a and (1 - cos(a))/a^2, by their Taylor series near zero
    first = torch.where(small, 1.0 - angle_sq / 6.0, torch.sin(angle) / angle)
    second = torch.where(small, 0.5 - angle_sq / 24.0, (1.0 - torch.cos(angle)) / torch.where(small, 1.0, angle_sq))
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*vectors.shape[:-1], 3, 3)
    identity = torch.eye(3, dtype=vectors.dtype, device=vectors.device).expand_as(cross)
    return identity + first * cross + second * (cross @ cross)


def skeleton_levels(parents) -> list[list[int]]:
    """The joints by depth below their root: roots first, every joint after its parent.

    Raises:
        ValueError: parents that do not form a forest.
    """
    parents = [int(p) for p in parents]
    depth = [-1] * len(parents)
    for start in range(len(parents)):
        chain, joint = [], start
        while joint >= 0 and depth[joint] < 0:
            if joint in chain:
                raise ValueError("the skeleton's parents form a cycle")
            chain.append(joint)
            joint = parents[joint]
        base = -1 if joint < 0 else depth[joint]
        for offset, member in enumerate(reversed(chain)):
            depth[member] = base + 1 + offset
    return [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]


def ancestor_jumps(parents, *, device=None) -> list[torch.Tensor]:
    """Ancestor tables for composing transforms down the skeleton in ``ceil(log2(depth))`` batched steps.

    Entry ``r`` [J] holds each joint's ``2**r``-th ancestor, or ``J`` (one past the last joint) where there is
    none; entry 0 is the parent. There is at least one entry.

    Raises:
        ValueError: parents that do not form a forest.
    """
    parents = [int(p) for p in parents]
    count = len(parents)
    depth = len(skeleton_levels(parents))  # also rejects cycles
    jumps = [[count if p < 0 else p for p in parents]]
    while 2 ** len(jumps) < depth:
        last = jumps[-1]
        jumps.append([count if last[j] == count else last[last[j]] for j in range(count)])
    return [torch.as_tensor(jump, dtype=torch.long, device=device) for jump in jumps]


def posed_pivots(bone_transforms: torch.Tensor, heads: torch.Tensor) -> torch.Tensor:
    """The joints' pivots [...,J,3] in a pose: the rest pivots ``heads`` [J,3] moved by ``bone_transforms``
    [...,J,4,4] (the ``joint_positions`` of a poses.npz)."""
    return (bone_transforms[..., :3, :3] @ heads[:, :, None])[..., 0] + bone_transforms[..., :3, 3]


def corrected_transforms(bone_transforms: torch.Tensor, heads: torch.Tensor, jumps: list[torch.Tensor],
                         rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Poses [...,J,4,4] (rest-to-posed transforms) with every joint turned by ``exp(rotation[..., j])`` in its own
    posed frame after its given rotation relative to its parent, and the roots moved by ``translation``; each
    child keeps its pivot's offset from its parent's pivot, in the parent's frame.

    Each joint's correction is a rigid motion of the world, a turn ``R_j exp(d_j) R_j^T`` about its given pivot;
    a joint moves by the composition of its ancestors' and its own, from the root down (then the root's shift),
    composed for all joints at once by pointer jumping over ``jumps`` (a few batched products, not one per level).

    Args:
        bone_transforms: [...,J,4,4] the given poses (any leading dimensions: several frames at once).
        heads: [J,3] rest-pose pivots [world units].
        jumps: :func:`ancestor_jumps` of the skeleton, on the device.
        rotation: [...,J,3] axis-angle corrections [rad].
        translation: [...,3] root offsets [world units].

    Returns:
        [...,J,4,4] the corrected poses (equal to the given ones where both corrections are zero).
    """
    count = bone_transforms.shape[-3]
    given_rotation = bone_transforms[..., :3, :3]
    pivots = posed_pivots(bone_transforms, heads)
    turn = given_rotation @ axis_angle_to_matrix(rotation) @ given_rotation.transpose(-1, -2)  # about the pivot
    is_root = (jumps[0] == count).to(bone_transforms.dtype)[:, None]
    shift = pivots - (turn @ pivots[..., None])[..., 0] + is_root * translation[..., None, :]
    eye = torch.eye(4, dtype=bone_transforms.dtype, device=bone_transforms.device)
    bottom = eye[3:4].expand(*shift.shape[:-1], 1, 4)
    motion = torch.cat([torch.cat([turn, shift[..., None]], dim=-1), bottom], dim=-2)  # [...,J,4,4] of the world
    identity = eye.expand(*motion.shape[:-3], 1, 4, 4)
    for jump in jumps:  # each joint's motion composed after its ancestors' (2**r more of them each round)
        motion = torch.cat([motion, identity], dim=-3)[..., jump, :, :] @ motion
    return motion @ bone_transforms

