"""Evaluating a fitted avatar on a held-out video folder (novel views or novel poses).

Each frame is rendered with the folder's camera and pose over the folder's background and compared with the
ground truth: PSNR and SSIM over the full frame, and inside the ground-truth mask (the figure that counts:
the subjects cover a small part of the frame, so full-frame PSNR is dominated by the background).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch
import tqdm

from warpavatar import metrics

__all__ = ["evaluate_avatar", "write_json_atomic"]


def write_json_atomic(path: str | os.PathLike, value) -> Path:
    """Write ``value`` as JSON to ``path`` through a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=2))
    os.replace(tmp, path)
    return path


@torch.no_grad()
def evaluate_avatar(avatar, video, *, save_renders: str | os.PathLike | None = None, progress: bool = True) -> dict:
    """Render ``avatar`` for every frame of ``video`` and measure it.

    Args:
        avatar: a fitted :class:`~warpavatar.model.Avatar` (its device is used).
        video: a :class:`~warpavatar.data.VideoFolder` of the same skeleton.
        save_renders: folder for side-by-side images (render | ground truth | error x4), or None.
        progress: show a progress bar.

    Returns:
        dict with mean ``psnr``, ``ssim``, ``psnr_masked``, ``ssim_masked`` (and ``lpips`` when weights exist
        locally, else None), ``frame_count``, ``seconds_per_frame``, and ``frames``: one dict per frame.
    """
    import cv2

    if video.skeleton.joint_count != avatar.joint_count:
        raise ValueError(f"{video.root}: its skeleton has {video.skeleton.joint_count} joints but the avatar's has "
                         f"{avatar.joint_count}")
    device = avatar.gaussians.means.device
    background = torch.as_tensor(video.background, dtype=torch.float32, device=device)
    grid = avatar.field.grid_weights()
    # learned secondary dynamics roll the folder's motion out first (frames equal to training instants keep
    # the training rollout's state)
    avatar.prepare_sequence(video.bone_transforms, frame_ids=video.frame_ids, fps=video.fps)
    if save_renders is not None:
        save_renders = Path(save_renders)
        save_renders.mkdir(parents=True, exist_ok=True)
    frames = []
    render_seconds = 0.0
    lpips_available = True
    for t in tqdm.trange(video.frame_count, disable=not progress, desc=f"eval {Path(video.root).name}"):
        bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32, device=device)
        start = time.perf_counter()
        image, _, _ = avatar.render(video.cameras[t], bones, background=background, grid=grid)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        render_seconds += time.perf_counter() - start
        # metrics run where the render is (on a GPU, CPU-side SSIM of every frame would dominate the time)
        pred = image.clamp(0, 1)
        gt = torch.as_tensor(video.images[t], device=device).float() / 255.0
        mask = None
        if video.masks is not None:
            mask = torch.as_tensor(video.masks[t], device=device).float() / 255.0
        record = {
            "frame_id": int(video.frame_ids[t]),
            "psnr": metrics.psnr(pred, gt),
            "ssim": metrics.ssim(pred, gt),
            "psnr_masked": metrics.psnr(pred, gt, mask=mask) if mask is not None else None,
            "ssim_masked": metrics.ssim(pred, gt, mask=mask) if mask is not None else None,
        }
        if lpips_available:
            value = metrics.lpips(pred, gt)
            lpips_available = value is not None
            record["lpips"] = value
        frames.append(record)
        if save_renders is not None:
            error = ((pred - gt).abs() * 4).clamp(0, 1)
            row = torch.cat([pred, gt, error], dim=1).cpu().numpy()
            cv2.imwrite(str(save_renders / f"{record['frame_id']:06d}.png"),
                        cv2.cvtColor((row * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))

    def mean(key):
        values = [f[key] for f in frames if f.get(key) is not None]
        return float(np.mean(values)) if values else None

    return {
        "folder": str(video.root),
        "frame_count": len(frames),
        "psnr": mean("psnr"),
        "ssim": mean("ssim"),
        "psnr_masked": mean("psnr_masked"),
        "ssim_masked": mean("ssim_masked"),
        "lpips": mean("lpips") if lpips_available else None,
        "seconds_per_frame": render_seconds / max(1, len(frames)),
        "gaussians": avatar.gaussians.count,
        "frames": frames,
    }
