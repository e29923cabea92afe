"""Where a fitted avatar's masked error comes from: overall colour, silhouette edges, or the rest.

    python tools/error_breakdown.py AVATAR_DIR VIDEO_FOLDER [VIDEO_FOLDER ...] [--device cuda] [--stride N]

For every folder, the mean over frames of four masked PSNRs (dB):

* ``masked``: as ``warpavatar-eval`` reports it (inside the ground-truth mask);
* ``gain``: after the render is multiplied by the per-channel gain that best fits the ground truth inside the
  mask (least squares, one gain per frame): what a perfect global colour/brightness correction would give;
* ``inner``: inside the mask eroded by 2 pixels (the silhouette band left out): what perfect edges would give;
* ``gain+inner``: both.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from warpavatar import data
from warpavatar.avatar import Avatar


def _masked_psnr(prediction: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    mse = float((((prediction - truth) ** 2) * mask[..., None]).sum() / max(1.0, mask.sum() * 3))
    return -10.0 * np.log10(max(mse, 1e-12))


def breakdown(avatar: Avatar, video, *, stride: int = 1) -> dict:
    """The four mean masked PSNRs (see the module docstring) of ``avatar`` on ``video``."""
    import cv2

    device = avatar.gaussians.means.device
    background = torch.as_tensor(video.background, dtype=torch.float32, device=device)
    grid = avatar.field.grid_weights()
    avatar.prepare_sequence(video.bone_transforms, frame_ids=video.frame_ids, fps=video.fps)
    rows = {"masked": [], "gain": [], "inner": [], "gain+inner": []}
    kernel = np.ones((5, 5), np.uint8)
    for t in range(0, video.frame_count, stride):
        with torch.no_grad():
            image, _, _ = avatar.render(video.cameras[t],
                                        torch.as_tensor(video.bone_transforms[t], dtype=torch.float32, device=device),
                                        background=background, grid=grid)
        prediction = image.clamp(0, 1).cpu().numpy().astype(np.float64)
        truth = video.images[t].astype(np.float64) / 255.0
        mask = video.masks[t].astype(np.float64) / 255.0
        weight = mask[..., None]
        gain = (prediction * truth * weight).sum((0, 1)) / np.maximum((prediction**2 * weight).sum((0, 1)), 1e-12)
        corrected = np.clip(prediction * gain, 0.0, 1.0)
        inner = cv2.erode((mask > 0.5).astype(np.uint8), kernel).astype(np.float64)
        rows["masked"].append(_masked_psnr(prediction, truth, mask))
        rows["gain"].append(_masked_psnr(corrected, truth, mask))
        rows["inner"].append(_masked_psnr(prediction, truth, inner))
        rows["gain+inner"].append(_masked_psnr(corrected, truth, inner))
    return {key: float(np.mean(values)) for key, values in rows.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("avatar", help="fit output folder (or avatar.pt)")
    parser.add_argument("folders", nargs="+", help="video folders with masks (novel views, novel poses, train)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--stride", type=int, default=1, help="use every N-th frame of each folder")
    args = parser.parse_args(argv)
    avatar = Avatar.load(args.avatar, device=args.device)
    print("| folder | masked | gain | inner | gain+inner |\n|---|---|---|---|---|")
    for folder in args.folders:
        video = data.load_video_folder(folder)
        if video.masks is None:
            raise SystemExit(f"{folder}: has no masks/, so no masked PSNR can be measured")
        values = breakdown(avatar, video, stride=args.stride)
        print(f"| {folder} | " + " | ".join(f"{values[k]:.2f}" for k in ("masked", "gain", "inner", "gain+inner"))
              + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
