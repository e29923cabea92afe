"""Evaluating a fitted avatar on a held-out video folder (novel views or novel poses).

Each frame is rendered with the folder's camera and pose over the folder's background and compared with the
ground truth: PSNR and SSIM over the full frame, and inside the ground-truth mask (the figure that counts:
the subjects cover a small part of the frame, so full-frame PSNR is dominated by the background), and beside
them the floater share: the share of the rendered opacity outside the mask dilated by 3 pixels
(:func:`~warpavatar.metrics.floater_share`), which a blur or a misplaced figure raises while the masked
scores may not notice.

With test-time pose refinement (``refine_steps``, the protocol of the PeopleSnapshot papers for estimated
poses) each frame's pose is also optimized against its ground truth with the avatar frozen
(:func:`refine_frame_pose`), and the metrics are reported both ways.

One rule for the resolution of every score a command reports (``warpavatar-fit --demo``, ``warpavatar-fit-many
--eval``, and ``warpavatar-eval`` by default): the fit's training resolution, each held-out folder read with the
fit's ``image_scale`` as the fit read its training folder (:func:`evaluate_held_out`). Each result names its
resolution (``"resolution": "64x64"``), and :func:`score_line` prints it with the scores.

Timing: each result gives the render time and the metric time per frame apart (``render_seconds_per_frame``,
``metric_seconds_per_frame``; ``refine_seconds_per_frame`` with refinement).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch
import tqdm

from warpavatar import metrics, ops
from warpavatar.io.images import write_image
from warpavatar.io.output_files import write_json_atomic
from warpavatar.optim import Adam

__all__ = ["evaluate_avatar", "evaluate_held_out", "refine_frame_pose", "score_line", "held_out_resolution",
           "write_json_atomic"]


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
def evaluate_held_out(avatar, subject_root: str | os.PathLike, *, image_scale: float,
                      progress: bool = True) -> dict[str, dict]:
    """Measure ``avatar`` on every held-out folder of the subject folder ``subject_root`` at the fit's training
    resolution: every folder is read with ``image_scale`` (the fit's ``FitConfig.image_scale``), as the fit read
    its training folder. ``warpavatar-fit --demo`` and ``warpavatar-fit-many --eval`` report these scores.

    Returns:
        ``{"novel_view/<name>" or "novel_pose/<name>": the means of :func:`evaluate_avatar` (without the
        per-frame list)}``, novel views first, each kind in name order; empty for a subject without held-out
        folders.
    """
    from warpavatar import data

    subject = data.load_subject(subject_root, scale=image_scale)
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
        save_renders: folder for side-by-side images (render | ground truth | error x4), or None; each image is
            written through a temporary name and checked (``warpavatar-eval`` passes a staged folder).
        progress: show a progress bar.
        refine_steps: test-time pose refinement steps per frame (0: none); the images saved are then the
            refined renders.

    Returns:
        dict with mean ``psnr``, ``ssim``, ``psnr_masked``, ``ssim_masked``, ``floater_share`` (the share of the
        rendered opacity outside the mask dilated by 3 pixels, :func:`~warpavatar.metrics.floater_share`; None
        without masks, as the masked scores) (and ``lpips`` when weights exist
        locally, else None, with ``lpips_unavailable`` saying why), ``frame_count``, ``resolution`` (the frames'
        ``"<width>x<height>"``), ``render_seconds_per_frame`` (the render alone, synchronized on CUDA),
        ``metric_seconds_per_frame`` (PSNR, SSIM, LPIPS and their inputs), ``refine_seconds_per_frame`` (with
        ``refine_steps``: the refinement and the refined render), and ``frames``: one dict per frame; with
        ``refine_steps`` also ``refined``: the same means after test-time refinement (and ``refined_*`` per
        frame).

    Raises:
        ValueError: a skeleton other than the avatar's, or frames smaller than SSIM's window (named with their
            size).
    """
    if video.skeleton.joint_count != avatar.joint_count:
        raise ValueError(f"{video.root}: its skeleton has {video.skeleton.joint_count} joints but the avatar's has "
                         f"{avatar.joint_count}")
    window = metrics.SSIM_WINDOW_SIZE
    if video.width < window or video.height < window:
        raise ValueError(f"{video.root}: its frames are {video.width}x{video.height} pixels at this scale, smaller "
                         f"than SSIM's {window}x{window}-pixel window; evaluate at a larger image scale")
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
    seconds = {"render": 0.0, "metric": 0.0, "refine": 0.0}
    lpips_unavailable = metrics.lpips_unavailable_reason()
    for t in tqdm.trange(video.frame_count, disable=not progress, desc=f"eval {Path(video.root).name}"):
        bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32, device=device)
        start = time.perf_counter()
        image, alpha, _ = avatar.render(video.cameras[t], bones, background=background, grid=grid)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds["render"] += time.perf_counter() - start
        start = time.perf_counter()
        # metrics run where the render is (on a GPU, CPU-side SSIM of every frame would dominate the time)
        pred = image.clamp(0, 1)
        gt = torch.as_tensor(video.images[t], device=device).float() / 255.0
        mask = None
        if video.masks is not None:
            mask = torch.as_tensor(video.masks[t], device=device).float() / 255.0
        record = {"frame_id": int(video.frame_ids[t]), **metrics.image_scores(pred, gt, mask=mask),
                  "floater_share": None if mask is None else metrics.floater_share(alpha, mask)}
        if lpips_unavailable is None:
            record["lpips"] = metrics.lpips(pred, gt)
        seconds["metric"] += time.perf_counter() - start
        if refine_steps:
            start = time.perf_counter()
            target = gt
            if mask is not None and not video.declares_background:  # real footage: the subject cut out, as a fit
                target = gt * mask[..., None] + background * (1.0 - mask[..., None])  # compares (not the room)
            pose = refine_frame_pose(avatar, video.cameras[t], bones, target, mask=mask, background=background,
                                     steps=refine_steps, grid=grid)
            refined, refined_alpha, _ = avatar.render(video.cameras[t], bones, background=background, grid=grid,
                                                      skeleton_pose=pose)
            pred = refined.clamp(0, 1)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds["refine"] += time.perf_counter() - start
            start = time.perf_counter()
            record.update({f"refined_{key}": value
                           for key, value in metrics.image_scores(pred, gt, mask=mask).items()})
            record["refined_floater_share"] = None if mask is None else metrics.floater_share(refined_alpha, mask)
            seconds["metric"] += time.perf_counter() - start
        frames.append(record)
        if save_renders is not None:
            error = ((pred - gt).abs() * 4).clamp(0, 1)
            row = torch.cat([pred, gt, error], dim=1).cpu().numpy()
            write_image(save_renders / f"{record['frame_id']:06d}.png", (row * 255).round().astype(np.uint8),
                        fsync=False)

    def mean(key):
        values = [f[key] for f in frames if f.get(key) is not None]
        return float(np.mean(values)) if values else None

    count = max(1, len(frames))
    result = {
        "folder": str(video.root),
        "frame_count": len(frames),
        "resolution": f"{video.width}x{video.height}",
        **{key: mean(key) for key in _METRICS},
        "lpips": mean("lpips") if lpips_unavailable is None else None,
        "render_seconds_per_frame": seconds["render"] / count,
        "metric_seconds_per_frame": seconds["metric"] / count,
        "gaussians": avatar.gaussians.count,
        "frames": frames,
    }
    if lpips_unavailable is not None:
        result["lpips_unavailable"] = lpips_unavailable
    if refine_steps:
        result["refine_seconds_per_frame"] = seconds["refine"] / count
    if refine_steps:
        result["refined"] = {"steps": refine_steps, **{key: mean(f"refined_{key}") for key in _METRICS}}
    return result


_METRICS = ("psnr", "ssim", "psnr_masked", "ssim_masked", "floater_share")


def score_line(label: str, result: dict) -> str:
    """One folder's scores as every command prints them, the resolution they were computed at included:
    ``"<label>: masked PSNR 22.08 dB, masked SSIM 0.9512, floaters 1.25%, PSNR 30.10 dB, SSIM 0.9801 at 64x64"``
    (the masked scores and the floater share, in percent of the rendered opacity, only with a mask; LPIPS when
    computed). ``result``: :func:`evaluate_avatar`'s (or its ``refined``
    means, with the resolution of the result they belong to)."""
    parts = []
    if result.get("psnr_masked") is not None:
        parts += [f"masked PSNR {result['psnr_masked']:.2f} dB", f"masked SSIM {result['ssim_masked']:.4f}"]
    if result.get("floater_share") is not None:
        parts.append(f"floaters {100 * result['floater_share']:.2f}%")
    parts += [f"PSNR {result['psnr']:.2f} dB", f"SSIM {result['ssim']:.4f}"]
    if result.get("lpips") is not None:
        parts.append(f"LPIPS {result['lpips']:.4f}")
    return f"{label}: {', '.join(parts)} at {result['resolution']}"


def held_out_resolution(results: dict[str, dict]) -> str:
    """The resolution label of :func:`evaluate_held_out`'s results: ``"64x64"`` when every folder shares it, else
    each folder's (``"novel_view/cam 64x64, novel_pose/walk 48x64"``); empty without results (or for results
    written before they named their resolution)."""
    resolutions = {label: result["resolution"] for label, result in results.items() if result.get("resolution")}
    if len(set(resolutions.values())) <= 1:
        return next(iter(resolutions.values()), "")
    return ", ".join(f"{label} {resolution}" for label, resolution in resolutions.items())
