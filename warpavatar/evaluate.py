"""Evaluating a fitted avatar on a held-out video folder (novel views or novel poses).

Each frame is rendered with the folder's camera and pose over the folder's background and compared with the
ground truth: PSNR and SSIM over the full frame, and inside the ground-truth mask (the figure that counts:
the subjects cover a small part of the frame, so full-frame PSNR is dominated by the background).

With test-time pose refinement (``refine_steps``, the protocol of the PeopleSnapshot papers for estimated
poses) each frame's pose is also optimized against its ground truth with the avatar frozen
(:func:`refine_frame_pose`), and the metrics are reported both ways.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch
import tqdm

from warpavatar import metrics, ops
from warpavatar.optim import Adam

__all__ = ["evaluate_avatar", "evaluate_held_out", "refine_frame_pose", "write_json_atomic"]


def write_json_atomic(path: str | os.PathLike, value) -> Path:
    """Write ``value`` as JSON to ``path`` through a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=2))
    os.replace(tmp, path)
    return path


def refine_frame_pose(avatar, camera, bone_transforms: torch.Tensor, image: torch.Tensor, *,
                      mask: torch.Tensor | None = None, background: torch.Tensor | None = None, steps: int = 100,
                      lr_rotation: float = 5e-3, lr_translation: float = 2e-3, lambda_ssim: float = 0.2,
                      lambda_mask: float = 0.1, grid: torch.Tensor | None = None) -> torch.Tensor:
    """Optimize one frame's skeleton pose against its image with the avatar frozen.

    Starts from the pose the avatar uses for the frame (a training instant's refined pose, else the given one)
    and learns a correction of every joint's rotation and of the root's position
    (:func:`warpavatar.ops.corrected_poses`, the kernels pose refinement trains with) by Adam on a fit's image loss
    (:func:`~warpavatar.metrics.image_loss_terms`; the weights default to the fit's defaults).

    Args:
        avatar: the fitted avatar (its parameters are not changed).
        camera: the frame's camera; image: [H,W,3] its ground truth in 0..1; mask: [H,W] in 0..1 or None.
        bone_transforms: [J,4,4] the frame's pose as given (it still names the instant for the avatar's parts).
        steps: optimizer steps; lr_rotation [rad] and lr_translation [world units] their Adam learning rates.
        lambda_ssim, lambda_mask: weights of D-SSIM and of the mask term in the image loss.
        grid: the avatar's skinning grid (computed when None).

    Returns:
        [J,4,4] the refined skeleton pose (pass it as ``skeleton_pose`` to :meth:`Avatar.render`).
    """
    device = bone_transforms.device
    skeleton = avatar.skeleton
    heads = torch.as_tensor(skeleton.heads, dtype=torch.float32, device=device)
    parents = [int(p) for p in skeleton.parents]
    with torch.no_grad():
        start = avatar.pose_bones(bone_transforms)[None, : avatar.joint_count].contiguous()
        grid = avatar.field.grid_weights() if grid is None else grid
    rotation = torch.zeros(1, avatar.joint_count, 3, device=device, requires_grad=True)
    translation = torch.zeros(1, 3, device=device, requires_grad=True)
    optimizer = Adam([{"params": [rotation], "lr": lr_rotation}, {"params": [translation], "lr": lr_translation}])
    frozen = [parameter for parameter in avatar.parameters() if parameter.requires_grad]
    for parameter in frozen:
        parameter.requires_grad_(False)
    try:
        with torch.enable_grad():
            for _ in range(steps):
                pose = ops.corrected_poses(start, heads, parents, rotation, translation)[0]
                render, alpha, _ = avatar.render(camera, bone_transforms, background=background, grid=grid,
                                                 skeleton_pose=pose)
                terms = metrics.image_loss_terms(render, image, lambda_ssim=lambda_ssim, alpha=alpha, mask=mask,
                                                 lambda_mask=lambda_mask)
                loss = sum(weight * value for weight, value in terms.values())
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
    finally:
        for parameter in frozen:
            parameter.requires_grad_(True)
    with torch.no_grad():
        return ops.corrected_poses(start, heads, parents, rotation, translation)[0]


@torch.no_grad()
def evaluate_held_out(avatar, subject, *, progress: bool = True) -> dict[str, dict]:
    """Measure ``avatar`` on every held-out folder of a :class:`~warpavatar.data.Subject`.

    Returns:
        ``{"novel_view/<name>" or "novel_pose/<name>": the means of :func:`evaluate_avatar` (without the
        per-frame list)}``, novel views first, each kind in name order; empty for a subject without held-out
        folders.
    """
    results = {}
    for kind, folders in (("novel_view", subject.novel_view), ("novel_pose", subject.novel_pose)):
        for name in folders:
            result = evaluate_avatar(avatar, folders[name], progress=progress)
            results[f"{kind}/{name}"] = {key: value for key, value in result.items() if key != "frames"}
    return results


@torch.no_grad()
def evaluate_avatar(avatar, video, *, save_renders: str | os.PathLike | None = None, progress: bool = True,
                    refine_steps: int = 0) -> dict:
    """Render ``avatar`` for every frame of ``video`` and measure it.

    Args:
        avatar: a fitted :class:`~warpavatar.model.Avatar` (its device is used).
        video: a :class:`~warpavatar.data.VideoFolder` of the same skeleton.
        save_renders: folder for side-by-side images (render | ground truth | error x4), or None.
        progress: show a progress bar.
        refine_steps: test-time pose refinement steps per frame (0: none); the images saved are then the
            refined renders.

    Returns:
        dict with mean ``psnr``, ``ssim``, ``psnr_masked``, ``ssim_masked`` (and ``lpips`` when weights exist
        locally, else None), ``frame_count``, ``seconds_per_frame``, and ``frames``: one dict per frame; with
        ``refine_steps`` also ``refined``: the same means after test-time refinement (and ``refined_*`` per
        frame).
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
        record = {"frame_id": int(video.frame_ids[t]), **_frame_metrics(pred, gt, mask)}
        if lpips_available:
            value = metrics.lpips(pred, gt)
            lpips_available = value is not None
            record["lpips"] = value
        if refine_steps:
            target = gt
            if mask is not None and not video.declares_background:  # real footage: the subject cut out, as a fit
                target = gt * mask[..., None] + background * (1.0 - mask[..., None])  # compares (not the room)
            pose = refine_frame_pose(avatar, video.cameras[t], bones, target, mask=mask, background=background,
                                     steps=refine_steps, grid=grid)
            refined, _, _ = avatar.render(video.cameras[t], bones, background=background, grid=grid,
                                          skeleton_pose=pose)
            pred = refined.clamp(0, 1)
            record.update({f"refined_{key}": value for key, value in _frame_metrics(pred, gt, mask).items()})
        frames.append(record)
        if save_renders is not None:
            error = ((pred - gt).abs() * 4).clamp(0, 1)
            row = torch.cat([pred, gt, error], dim=1).cpu().numpy()
            cv2.imwrite(str(save_renders / f"{record['frame_id']:06d}.png"),
                        cv2.cvtColor((row * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))

    def mean(key):
        values = [f[key] for f in frames if f.get(key) is not None]
        return float(np.mean(values)) if values else None

    result = {
        "folder": str(video.root),
        "frame_count": len(frames),
        **{key: mean(key) for key in _METRICS},
        "lpips": mean("lpips") if lpips_available else None,
        "seconds_per_frame": render_seconds / max(1, len(frames)),
        "gaussians": avatar.gaussians.count,
        "frames": frames,
    }
    if refine_steps:
        result["refined"] = {"steps": refine_steps, **{key: mean(f"refined_{key}") for key in _METRICS}}
    return result


_METRICS = ("psnr", "ssim", "psnr_masked", "ssim_masked")


def _frame_metrics(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> dict:
    """PSNR and SSIM of one frame, over the full frame and inside the mask (None without one)."""
    return {"psnr": metrics.psnr(pred, gt), "ssim": metrics.ssim(pred, gt),
            "psnr_masked": metrics.psnr(pred, gt, mask=mask) if mask is not None else None,
            "ssim_masked": metrics.ssim(pred, gt, mask=mask) if mask is not None else None}
