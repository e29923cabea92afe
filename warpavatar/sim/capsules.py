"""Collision capsules of the body, fitted to the avatar's own Gaussians around each bone.

A capsule per bone lies along the bone's segment (skeleton.json's ``head`` to ``tail``, rest pose). Its radius
is a quantile of the distances to that segment of the body Gaussians that the skinning weights give mostly to
the bone (garment Gaussians excluded): a robust radius that ignores the few Gaussians of a neighbouring part
that a bone also holds. Capsules are fitted once in canonical space and posed per frame by the bones' rigid
transforms (poses.npz's ``bone_transforms``), as the Gaussians they were fitted to are.
"""

from __future__ import annotations

import torch

from warpavatar.sim.mass_spring_cloth import Capsules

__all__ = ["fit_body_capsules", "pose_capsules", "capsules_near", "select", "distance_to_segments"]


def distance_to_segments(points: torch.Tensor, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """Distance of each point to its own segment: ``points, start, end [N, 3]`` -> ``[N]`` [world units].

    A segment shorter than 1e-6 counts as its start point.
    """
    direction = end - start
    length_sq = (direction * direction).sum(-1)
    short = length_sq <= 1e-12
    t = ((points - start) * direction).sum(-1) / torch.where(short, torch.ones_like(length_sq), length_sq)
    t = torch.where(short, torch.zeros_like(t), t.clamp(0.0, 1.0))
    return (points - start - t[:, None] * direction).norm(dim=-1)


def fit_body_capsules(
    heads: torch.Tensor,
    tails: torch.Tensor,
    means: torch.Tensor,
    skinning_weights: torch.Tensor,
    *,
    exclude: torch.Tensor | None = None,
    dominance: float = 0.5,
    quantile: float = 0.75,
    min_points: int = 8,
) -> Capsules:
    """One capsule per bone, in canonical space, from the body's Gaussians.

    Args:
        heads: rest-pose joint pivots (skeleton.json ``head``) [world units], float ``[J, 3]``.
        tails: rest-pose bone ends (``tail``) [world units], float ``[J, 3]``.
        means: canonical Gaussian centres [world units], float ``[N, 3]``.
        skinning_weights: each Gaussian's skinning weights, float ``[N, J]`` (rows summing to 1).
        exclude: Gaussians to leave out (the garment's own), bool ``[N]``; None keeps all.
        dominance: a Gaussian belongs to its heaviest bone when that weight is at least this, ``(0, 1]``.
        quantile: the radius is this quantile of the bone's Gaussians' distances to its segment, ``(0, 1]``.
        min_points: a bone with fewer Gaussians gets radius 0 (a capsule that holds nothing).

    Returns:
        :class:`Capsules` with ``J`` capsules (bone order) on the device of ``means``, float32, detached.

    Raises:
        ValueError: inconsistent shapes or options out of range.
    """
    joint_count = heads.shape[0]
    if heads.shape != (joint_count, 3) or tails.shape != (joint_count, 3):
        raise ValueError(f"heads and tails must have shape [J, 3], got {list(heads.shape)} and {list(tails.shape)}")
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape [N, 3], got {list(means.shape)}")
    if skinning_weights.shape != (means.shape[0], joint_count):
        raise ValueError(f"skinning_weights must have shape [{means.shape[0]}, {joint_count}], "
                         f"got {list(skinning_weights.shape)}")
    if exclude is not None and exclude.shape != (means.shape[0],):
        raise ValueError(f"exclude must have shape [{means.shape[0]}], got {list(exclude.shape)}")
    if not 0.0 < dominance <= 1.0 or not 0.0 < quantile <= 1.0:
        raise ValueError(f"dominance and quantile must be in (0, 1], got {dominance} and {quantile}")
    device = means.device
    heads = torch.as_tensor(heads, dtype=torch.float32, device=device)
    tails = torch.as_tensor(tails, dtype=torch.float32, device=device)
    means = means.detach().float()
    weight, bone = skinning_weights.detach().max(dim=1)
    keep = weight >= dominance
    if exclude is not None:
        keep &= ~exclude.to(device=device, dtype=torch.bool)
    bone, means = bone[keep], means[keep]
    distance = distance_to_segments(means, heads[bone], tails[bone])
    radius = torch.zeros(joint_count, device=device)
    for joint in range(joint_count):
        mine = distance[bone == joint]
        if mine.numel() >= min_points:
            radius[joint] = torch.quantile(mine, quantile)
    return Capsules(heads.clone(), tails.clone(), radius)


def capsules_near(capsules: Capsules, points: torch.Tensor, *, margin: float, chunk: int = 8192) -> torch.Tensor:
    """Ids of the capsules whose surface comes within ``margin`` of any point: the candidates of a garment.

    Collision costs one test per node and capsule; a garment only ever meets the bones near it (a shirt never
    the shins). Choose once, in canonical space, with a margin as large as the garment can move away from its
    rest shape, then pose only those: ``pose_capsules(select(capsules, ids), bone_transforms[ids])``.

    Args:
        capsules: canonical capsules ``[C]``.
        points: the garment's rest nodes [world units], ``[N, 3]``.
        margin: distance [world units] >= 0 from a capsule's surface within which a point makes it a candidate.
        chunk: points per batch of the ``[chunk, C]`` distance table.

    Returns:
        int64 ``[K]``, ascending.
    """
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    capsule_count = capsules.radius.shape[0]
    near = torch.zeros(capsule_count, dtype=torch.bool, device=capsules.radius.device)
    start, end = capsules.segment_start.float(), capsules.segment_end.float()
    for first in range(0, points.shape[0], chunk):
        block = points[first:first + chunk].detach().float()
        count = block.shape[0]
        distance = distance_to_segments(
            block.repeat_interleave(capsule_count, dim=0), start.repeat(count, 1), end.repeat(count, 1)
        ).reshape(count, capsule_count)
        near |= ((distance - capsules.radius.float()[None]) <= margin).any(dim=0)
    return torch.nonzero(near).reshape(-1)


def select(capsules: Capsules, ids: torch.Tensor) -> Capsules:
    """The capsules ``ids`` of ``capsules``."""
    return Capsules(capsules.segment_start[ids], capsules.segment_end[ids], capsules.radius[ids])


def pose_capsules(capsules: Capsules, bone_transforms: torch.Tensor) -> Capsules:
    """Canonical capsules moved rigidly by their bones: ``T_j @ [point, 1]`` for both endpoints.

    Args:
        capsules: canonical capsules, one per bone (:func:`fit_body_capsules`).
        bone_transforms: rest-to-posed rigid transforms of the bones, float ``[J, 4, 4]`` (one frame of
            poses.npz's ``bone_transforms``). Differentiable.

    Returns:
        The posed :class:`Capsules` (same radii).
    """
    if bone_transforms.shape != (capsules.radius.shape[0], 4, 4):
        raise ValueError(f"bone_transforms must have shape [{capsules.radius.shape[0]}, 4, 4], "
                         f"got {list(bone_transforms.shape)}")
    rotation, translation = bone_transforms[:, :3, :3], bone_transforms[:, :3, 3]

    def move(points):
        return (rotation @ points.to(rotation.dtype)[:, :, None])[:, :, 0] + translation

    return Capsules(move(capsules.segment_start), move(capsules.segment_end), capsules.radius.to(rotation.dtype))
