"""What a finished fit writes: the avatar file, the canonical Gaussians as a 3DGS .ply, the training motion, each
extension's own files and preview images; each file through a temporary name of its own and checked
(:mod:`warpavatar.io.output_files`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from warpavatar.data import write_poses
from warpavatar.io.images import write_image
from warpavatar.io.ply import write_gaussian_ply

__all__ = ["TRAINING_MOTION_NAME", "PIXEL_SIZE_KEY", "FLOATER_MARGIN", "FLOATER_LINK", "FLOATER_NEIGHBOURS",
           "FLOATER_OPACITY", "write_fitted_avatar", "canonical_floaters", "write_canonical_ply", "training_pixel_size",
           "write_training_motion", "write_previews"]

TRAINING_MOTION_NAME = "training_poses.npz"
"""The file in a fit's output folder that holds the poses it was fitted on (``warpavatar-view`` plays it)."""

PIXEL_SIZE_KEY = "pixel_size"
"""The array of :data:`TRAINING_MOTION_NAME` that holds the training frames' pixel width at the subject [m]
(:func:`training_pixel_size`; the mesh export blurs its renders by it, :func:`warpavatar.mesh.views.training_blur`)."""


def write_fitted_avatar(avatar, frames, extensions, folder: str | Path, *, config) -> None:
    """End a fit and write its avatar: each extension's ``finish()``, then ``avatar.pt`` (with ``config``), the
    canonical .ply, the training motion and each extension's own files into ``folder``.

    Args:
        avatar: the fitted :class:`~warpavatar.model.avatar.Avatar`.
        frames: its :class:`~warpavatar.fit.training_frames.TrainingFrames`.
        extensions: the enabled extensions, in the registry's order.
        folder: the fit's output folder.
        config: the fit's :class:`~warpavatar.fit.config.FitConfig` (saved in the avatar file).
    """
    folder = Path(folder)
    for extension in extensions:
        extension.finish()
    avatar.save(folder / "avatar.pt", config=config.to_dict())
    write_canonical_ply(avatar.gaussians, folder / "canonical.ply", skeleton=avatar.skeleton)
    cameras = [frames.video.cameras[int(index)] for index in frames.indices]  # (the host copies)
    write_training_motion(frames, folder / TRAINING_MOTION_NAME,
                          pixel_size=training_pixel_size(cameras, frames.bone_transforms.detach().cpu().numpy(),
                                                         frames.video.skeleton))
    for extension in extensions:
        extension.write_outputs(folder)


FLOATER_MARGIN = 0.25
"""A Gaussian whose centre lies farther than this fraction of the skeleton's height from every bone segment is a
floater (:func:`canonical_floaters`)."""

FLOATER_LINK = 0.03
"""A Gaussian beyond :data:`FLOATER_MARGIN` is kept when a chain of Gaussians, each closer than this fraction of the
skeleton's height to the next, joins it to one within the margin: a big head, a hat or a long coat reaches farther
from its bones than the margin, and stays; a cloud apart from the body does not."""

FLOATER_NEIGHBOURS = 16
"""Nearest Gaussians each one is linked to when chains are followed (:data:`FLOATER_LINK`)."""

FLOATER_OPACITY = 1.0 / 255.0
"""A Gaussian less opaque than this (it changes no 8-bit pixel on its own) is a floater."""


def canonical_floaters(means: torch.Tensor, opacities: torch.Tensor, skeleton, *,
                       scales: torch.Tensor | None = None) -> torch.Tensor:
    """Which canonical Gaussians are floaters, left out of ``canonical.ply``: those whose centre lies farther than
    :data:`FLOATER_MARGIN` times the skeleton's height (its bones' extent along ``skeleton.up``) from every bone
    segment head -> tail unless a chain of close Gaussians joins them to the body (:data:`FLOATER_LINK`), and those
    with an opacity below :data:`FLOATER_OPACITY`.

    Args:
        means: [N,3] canonical centres [m].
        opacities: [N] opacities in 0..1.
        skeleton: the :class:`~warpavatar.data.Skeleton` (rest pose ``heads``, ``tails`` [J,3], ``up`` [3]).
        scales: [N,3] standard deviations [m]; with them two Gaussians are also linked when their centres are
            closer than three times the sum of their largest scales (their bodies touch).

    Returns:
        [N] bool, True for a floater.
    """
    from warpavatar.model.skinning_field import closest_on_segments

    device = means.device  # (the k-NN graph below runs where the Gaussians live: a CUDA-only Warp has no CPU)
    means = means.detach().to("cpu", torch.float64)
    heads = torch.as_tensor(np.asarray(skeleton.heads), dtype=torch.float64)
    tails = torch.as_tensor(np.asarray(skeleton.tails), dtype=torch.float64)
    up = torch.as_tensor(np.asarray(skeleton.up), dtype=torch.float64)
    up = up / up.norm()
    heights = torch.cat([heads, tails]) @ up
    margin = FLOATER_MARGIN * float(heights.max() - heights.min())
    nearest = torch.empty(means.shape[0], dtype=torch.float64)
    for start in range(0, means.shape[0], 16384):  # [chunk, J, 3] at a time
        chunk = means[start:start + 16384]
        nearest[start:start + 16384] = (chunk[:, None] - closest_on_segments(chunk, heads, tails)).norm(dim=-1).amin(1)
    visible = opacities.detach().cpu() >= FLOATER_OPACITY
    reached = (nearest <= margin) & visible
    beyond = visible & ~reached
    if beyond.any() and reached.any():  # join what a chain of close Gaussians links to the body
        from warpavatar.ops import knn_graph

        points = means[visible].float()
        index, distance = knn_graph(points.to(device), min(FLOATER_NEIGHBOURS, points.shape[0] - 1))
        index, distance = index.cpu(), distance.cpu()
        reach = torch.full_like(distance, FLOATER_LINK * float(heights.max() - heights.min()))
        index = index.clamp_min(0)
        if scales is not None:  # Gaussians whose 3-sigma bodies touch
            extent = 3.0 * scales.detach().to("cpu", torch.float32)[visible].amax(dim=1)
            reach = torch.maximum(reach, extent[:, None] + extent[index])
        linked = distance <= reach
        joined = reached[visible]
        while True:  # one link further each pass; ends when a pass joins nothing more
            grown = joined | (joined[index] & linked).any(dim=1)
            if torch.equal(grown, joined):
                break
            joined = grown
        reached[visible] = joined
    return ~reached


def write_canonical_ply(gaussians, path: str | Path, *, skeleton=None, keep_floaters: bool = False) -> int:
    """The canonical Gaussians with the 3DGS attribute names (opens in common splat viewers), floaters left out.

    Args:
        gaussians: the avatar's :class:`~warpavatar.model.GaussianModel` (not changed).
        path: the ``.ply`` to write (atomically).
        skeleton: the avatar's skeleton; with it, the :func:`canonical_floaters` are left out unless
            ``keep_floaters``; None writes every Gaussian (there are no bones to measure from).
        keep_floaters: write every Gaussian even so.

    Returns:
        the number of Gaussians written.
    """
    keep = slice(None)
    if skeleton is not None and not keep_floaters:
        keep = ~canonical_floaters(gaussians.means, gaussians.opacities, skeleton, scales=gaussians.scales)
    means = gaussians.means.detach().cpu()[keep].numpy()
    write_gaussian_ply(path, means=means,
                       quats=gaussians.normalized_quats.detach().cpu()[keep].numpy(),
                       scales=gaussians.scales.detach().cpu()[keep].numpy(),
                       opacities=gaussians.opacities.detach().cpu()[keep].numpy(),
                       sh_coeffs=gaussians.sh_coefficients().detach().cpu()[keep].numpy())
    return int(means.shape[0])


def training_pixel_size(cameras, bone_transforms, skeleton) -> float:
    """The width [m] one pixel of a fit's frames covers at the subject: over the frames, the median of the posed
    joints' median camera depth over the focal length, ``z / sqrt(fx fy)``.

    Args:
        cameras: the frames' cameras (``K`` [3,3], ``world_to_camera`` [4,4]), one a frame.
        bone_transforms: [T,J,4,4] the frames' rest-to-posed bone transforms.
        skeleton: the :class:`~warpavatar.data.Skeleton` (its ``heads`` [J,3] are posed).

    Raises:
        ValueError: no frames, cameras and poses of different counts, or the subject behind every camera.
    """
    bones = np.asarray(bone_transforms, dtype=np.float64)
    if bones.ndim != 4 or bones.shape[2:] != (4, 4) or bones.shape[0] == 0 or len(cameras) != bones.shape[0]:
        raise ValueError(f"training_pixel_size: needs one camera a pose, got {len(cameras)} cameras and bone "
                         f"transforms of shape {list(bones.shape)}")
    heads = np.asarray(skeleton.heads, dtype=np.float64)
    widths = []
    for camera, pose in zip(cameras, bones):
        posed = np.einsum("jab,jb->ja", pose[:, :3, :3], heads) + pose[:, :3, 3]
        matrix = np.asarray(camera.world_to_camera, dtype=np.float64)
        depth = float(np.median(posed @ matrix[2, :3] + matrix[2, 3]))
        K = np.asarray(camera.K, dtype=np.float64)
        if depth > 0.0:
            widths.append(depth / math.sqrt(K[0, 0] * K[1, 1]))
    if not widths:
        raise ValueError("training_pixel_size: the subject is behind every camera")
    return float(np.median(widths))


def write_training_motion(frames, path: str | Path, *, pixel_size: float | None = None) -> None:
    """The training frames' poses as a ``poses.npz`` (docs/FORMAT.md, plus ``fps`` and, when given, ``pixel_size``
    [m] as :data:`PIXEL_SIZE_KEY`: the frames' pixel width at the subject, :func:`training_pixel_size`); any
    ``--motion`` option reads it, and replaying it gives each training instant what the fit learned for it."""
    extra = {} if pixel_size is None else {PIXEL_SIZE_KEY: np.float64(pixel_size)}
    write_poses(path, frames.bone_transforms.detach().cpu().numpy(), frames.frame_ids,
                fps=np.float64(frames.video.fps), **extra)


@torch.no_grad()
def write_previews(avatar, frames, folder: str | Path, *, count: int) -> None:
    """``render | ground truth`` PNGs of ``count`` evenly spaced training frames, named by frame number."""
    folder = Path(folder)
    folder.mkdir(exist_ok=True)
    for index in frames.spread(count):
        image, _, _ = avatar.render(frames.cameras[index], frames.bone_transforms[index],
                                    background=frames.background)
        target, _ = frames.target(index)
        row = torch.cat([image, target], dim=1).clamp(0, 1).cpu().numpy()
        path = folder / f"{frames.frame_id(index):06d}.png"
        write_image(path, (row * 255).round().astype(np.uint8))
