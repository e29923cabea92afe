"""What a finished fit writes besides the avatar: the canonical Gaussians as a 3DGS .ply, the training motion and
preview images; each file through a temporary name of its own and checked (:mod:`warpavatar.io.output_files`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from warpavatar.data import write_poses
from warpavatar.io.images import write_image
from warpavatar.io.ply import write_gaussian_ply

__all__ = ["TRAINING_MOTION_NAME", "write_canonical_ply", "write_training_motion", "write_previews"]

TRAINING_MOTION_NAME = "training_poses.npz"
"""The file in a fit's output folder that holds the poses it was fitted on (``warpavatar-view`` plays it)."""


def write_canonical_ply(gaussians, path: str | Path) -> None:
    """The canonical Gaussians with the 3DGS attribute names (opens in common splat viewers)."""
    write_gaussian_ply(path, means=gaussians.means.detach().cpu().numpy(),
                       quats=gaussians.normalized_quats.detach().cpu().numpy(),
                       scales=gaussians.scales.detach().cpu().numpy(),
                       opacities=gaussians.opacities.detach().cpu().numpy(),
                       sh_coeffs=gaussians.sh_coefficients().detach().cpu().numpy())


def write_training_motion(frames, path: str | Path) -> None:
    """The training frames' poses as a ``poses.npz`` (docs/FORMAT.md, plus ``fps``); any ``--motion`` option reads
    it, and replaying it gives each training instant what the fit learned for it."""
    write_poses(path, frames.bone_transforms.detach().cpu().numpy(), frames.frame_ids,
                fps=np.float64(frames.video.fps))


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
