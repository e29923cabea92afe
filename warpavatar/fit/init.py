"""Template-free initialization of a fit's Gaussians (TAGA Sec. 3.1: no body template): points around the bone
midpoints, and points carved out of the canonical box by the training masks, coloured by what they see; and the
avatar a fit starts from, those Gaussians with a skinning field over their box."""

from __future__ import annotations

import numpy as np
import torch

from warpavatar.fit.training_frames import evenly_spaced
from warpavatar.model import Avatar, GaussianModel, VoxelSkinningField
from warpavatar.model.skinning_field import bone_distance_prior

__all__ = ["initial_avatar", "initial_gaussians"]


def _project(points: torch.Tensor, K: torch.Tensor, world_to_camera: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels [N,2] and depths [N] of world points [N,3] through a pinhole camera."""
    camera = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = camera[:, 2]
    focal, centre = torch.stack([K[0, 0], K[1, 1]]), torch.stack([K[0, 2], K[1, 2]])
    return camera[:, :2] / z.clamp_min(1e-6)[:, None] * focal + centre, z


def initial_avatar(video, frames, config, *, generator: torch.Generator, device) -> tuple[Avatar, float]:
    """The avatar a fit starts from: :func:`initial_gaussians` as isotropic Gaussians of 1% of the extent, and a
    skinning field over their canonical box, with the config's shading and matmul precision.

    Args:
        video: the training video folder (its ``skeleton``, images and masks).
        frames: its :class:`~warpavatar.fit.training_frames.TrainingFrames` (the camera centre of world shading).
        config: the fit configuration.
        generator: the fit's random generator (the initial points draw from it).
        device: torch device of the avatar.

    Returns:
        (avatar, extent): the extent is half the diagonal of the canonical box [world units].
    """
    skeleton = video.skeleton
    positions, colours, bbox_min, bbox_max = initial_gaussians(skeleton, video, config, generator=generator,
                                                               device=device)
    extent = float((bbox_max - bbox_min).norm()) * 0.5
    gaussians = GaussianModel(positions, colours, torch.full_like(positions, 0.01 * extent),
                              sh_degree=config.sh_degree)
    field = VoxelSkinningField(bbox_min, bbox_max, skeleton.joint_count, cells=config.grid_cells,
                               min_cells=config.grid_min_cells, hidden=config.field_hidden,
                               layers=config.field_layers, frequencies=config.field_frequencies).to(device)
    avatar = Avatar(skeleton, gaussians, field)
    avatar.matmul_precision = config.matmul_precision
    if config.shading == "world":
        avatar.shading_origin = frames.camera_centre()
    return avatar, extent


def initial_gaussians(skeleton, video, config, *, generator: torch.Generator, device
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Template-free initialization: points around bone midpoints, refined by carving with the masks.

    Returns:
        (positions [N,3], colours [N,3], bbox_min [3], bbox_max [3]) in the canonical (rest) world frame.
    """
    heads = torch.as_tensor(skeleton.heads, dtype=torch.float32)
    tails = torch.as_tensor(skeleton.tails, dtype=torch.float32)
    lengths = (tails - heads).norm(dim=-1)
    skeleton_min = torch.minimum(heads.min(0).values, tails.min(0).values)
    skeleton_max = torch.maximum(heads.max(0).values, tails.max(0).values)
    height = float((skeleton_max - skeleton_min).max())
    # Bone-length-aware spread: long bones get elongated clouds along themselves; short (distal) ones small.
    midpoints = (heads + tails) * 0.5
    spread = (0.25 * lengths).clamp(0.02 * height, 0.12 * height)
    per_bone = config.init_points_per_bone
    samples = (midpoints[:, None, :] + torch.randn(len(heads), per_bone, 3, generator=generator)
               * spread[:, None, None])
    points = [samples.reshape(-1, 3)]

    margin = 0.25 * height
    box_min, box_max = skeleton_min - margin, skeleton_max + margin
    temperature = config.skinning_prior_temperature * height
    if config.init_carve and video.masks is not None:
        candidates = box_min + torch.rand(config.init_carve_candidates, 3, generator=generator) * (box_max - box_min)
        carved = _carve(candidates, heads, tails, video, temperature=temperature)
        if carved.shape[0] > config.init_carve_points:
            pick = torch.randperm(carved.shape[0], generator=generator)[: config.init_carve_points]
            carved = carved[pick]
        if carved.shape[0]:
            points.append(carved)
    positions = torch.cat(points)
    # The canonical box: skeleton and carved body, with a margin for Gaussians that move outwards.
    lo = torch.minimum(skeleton_min, positions.min(0).values)
    hi = torch.maximum(skeleton_max, positions.max(0).values)
    pad = 0.08 * float((hi - lo).max())
    bbox_min, bbox_max = lo - pad, hi + pad
    positions = torch.maximum(torch.minimum(positions, bbox_max), bbox_min)
    if positions.shape[0] > config.max_gaussians:  # the cap holds from the start (the box keeps every seed)
        kept = torch.randperm(positions.shape[0], generator=generator)[:config.max_gaussians].sort().values
        positions = positions[kept]
    colours = _initial_colours(positions, heads, tails, video, temperature=temperature)
    return positions.to(device), colours.to(device), bbox_min.to(device), bbox_max.to(device)


def _frames_for_init(video, count: int = 24) -> np.ndarray:
    return evenly_spaced(video.frame_count, count)


def _rigid_pixels(points: torch.Tensor, weights: torch.Tensor, video, t: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose canonical points [N,3] with skinning weights [N,J] to frame ``t`` and find their pixels.

    Returns:
        (row [N], column [N], valid [N]: in front of the camera and inside the image).
    """
    transforms = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32)
    blended = torch.einsum("nj,jab->nab", weights, transforms[:, :3, :])
    posed = torch.einsum("nab,nb->na", blended[:, :, :3], points) + blended[:, :, 3]
    camera = video.cameras[t]
    pixels, z = _project(posed, torch.as_tensor(camera.K, dtype=torch.float32),
                         torch.as_tensor(camera.world_to_camera, dtype=torch.float32))
    column, row = pixels[:, 0].round().long(), pixels[:, 1].round().long()
    valid = (z > 0) & (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
    return row, column, valid


def _mask_hits(video, t: int, row: torch.Tensor, column: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    hit = torch.zeros_like(valid)
    hit[valid] = torch.as_tensor(video.masks[t] > 127)[row[valid], column[valid]]
    return hit


def _carve(candidates: torch.Tensor, heads, tails, video, *, temperature: float) -> torch.Tensor:
    """Keep canonical points that, posed rigidly by the bone prior, fall inside the mask in nearly every frame."""
    weights = bone_distance_prior(candidates, heads, tails, temperature=temperature)
    inside_votes = torch.zeros(candidates.shape[0])
    seen_votes = torch.zeros(candidates.shape[0])
    for t in _frames_for_init(video):
        row, column, valid = _rigid_pixels(candidates, weights, video, t)
        seen_votes += valid.float()
        inside_votes += _mask_hits(video, t, row, column, valid).float()
    keep = (seen_votes >= 3) & (inside_votes >= 0.9 * seen_votes)
    return candidates[keep]


def _initial_colours(positions, heads, tails, video, *, temperature: float) -> torch.Tensor:
    """Mean colour each point sees where it projects inside the mask (grey where never seen)."""
    weights = bone_distance_prior(positions, heads, tails, temperature=temperature)
    total = torch.zeros(positions.shape[0], 3)
    count = torch.zeros(positions.shape[0])
    for t in _frames_for_init(video, 12):
        row, column, valid = _rigid_pixels(positions, weights, video, t)
        if video.masks is not None:
            valid = _mask_hits(video, t, row, column, valid)
        image = torch.as_tensor(video.images[t], dtype=torch.float32) / 255.0
        total[valid] += image[row[valid], column[valid]]
        count[valid] += 1
    return torch.where(count[:, None] > 0, total / count.clamp_min(1)[:, None], torch.full_like(total, 0.5))
