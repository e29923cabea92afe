"""Where a fitted avatar's masked error comes from: overall colour, silhouette edges, a body region, or the rest.

    python tools/error_breakdown.py AVATAR_DIR VIDEO_FOLDER [VIDEO_FOLDER ...] [--device cuda] [--stride N]
        [--height-band LOW HIGH]
    python tools/error_breakdown.py --reference blur|mean|shift VIDEO_FOLDER [...] [--height-band LOW HIGH]

For every folder, the mean over frames of four masked PSNRs (dB):

* ``masked``: as ``warpavatar-eval`` reports it (inside the ground-truth mask);
* ``gain``: after the render is multiplied by the per-channel gain that best fits the ground truth inside the
  mask (least squares, one gain per frame): what a perfect global colour/brightness correction would give;
* ``inner``: inside the mask eroded by 2 pixels (the silhouette band left out): what perfect edges would give;
* ``gain+inner``: both.

With ``--height-band LOW HIGH`` (world units along the skeleton's up axis) the masked error is also split in
two regions, pooled over the folder's frames: ``band``, the mask pixels whose camera ray passes between the
two heights where it crosses the depth of the root joint (on the supplied subjects, a horizontal slab such as
the one a skirt occupies), and ``outside``, the other mask pixels. It also prints ``band share`` (the band's
fraction of the mask pixels) and two ``needed`` columns: the band PSNR that would bring the pooled masked
PSNR to ``--target`` dB with a perfect outside region (``needed, outside perfect``) or with the outside as
measured (``needed, outside as is``; ``-`` when the outside alone already misses the target).

``--reference blur`` or ``--reference mean`` scores the ground truth itself instead of an avatar: blurred by a
Gaussian of ``--blur-sigma`` pixels (2), or its mask filled with the frame's mean colour inside it. These are
the baselines a benchmark's data README quotes. ``--reference shift`` scores the ground truth moved by
``--shift-px`` pixels (2), each frame's error the mean of four moves (right, left, down, up; what comes in from
beyond the frame is the folder's background colour): how precisely a prediction must place the subject's texture
and silhouette to reach a score (a moved image is an exact texture in a slightly wrong place).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from warpavatar import data

__all__ = ["breakdown", "height_band_mask", "masked_psnr", "reference_image", "reference_images", "shifted_image",
           "band_needed"]


def masked_psnr(prediction: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """PSNR [dB] of ``prediction`` against ``truth`` ([H,W,3] in 0..1) over the pixels weighted by ``mask`` [H,W]."""
    mse = float((((prediction - truth) ** 2) * mask[..., None]).sum() / max(1.0, mask.sum() * 3))
    return -10.0 * np.log10(max(mse, 1e-12))


def height_band_mask(camera: data.Camera, root_position: np.ndarray, up: np.ndarray, *, low: float, high: float
                     ) -> np.ndarray:
    """Pixels [H,W] (bool) whose ray crosses the root joint's camera depth between heights ``low`` and ``high``.

    Args:
        camera: the frame's camera (OpenCV convention, pixel centres at integers).
        root_position: [3] posed root joint [world units].
        up: [3] the world's up direction (normalized here).
        low: lower height along ``up`` [world units].
        high: upper height.
    """
    world_to_camera = np.asarray(camera.world_to_camera, dtype=np.float64)
    intrinsics = np.asarray(camera.K, dtype=np.float64)
    depth = float((world_to_camera[:3, :3] @ root_position + world_to_camera[:3, 3])[2])
    rows, columns = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    camera_points = np.stack([(columns - intrinsics[0, 2]) / intrinsics[0, 0] * depth,
                              (rows - intrinsics[1, 2]) / intrinsics[1, 1] * depth,
                              np.full_like(rows, depth)], axis=-1)
    camera_to_world = np.linalg.inv(world_to_camera)
    world = camera_points @ camera_to_world[:3, :3].T + camera_to_world[:3, 3]
    height = world @ (np.asarray(up, dtype=np.float64) / np.linalg.norm(up))
    return (height > low) & (height < high)


SHIFT_DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))  # (columns, rows) of the four moves of ``shift``


def shifted_image(image: np.ndarray, columns: int, rows: int, fill: np.ndarray) -> np.ndarray:
    """``image`` [H,W,C] moved right by ``columns`` and down by ``rows`` pixels (negative: left, up); the pixels
    that come in from beyond the frame take the colour ``fill`` [C]."""
    height, width = image.shape[:2]
    moved = np.empty_like(image)
    moved[...] = np.asarray(fill, dtype=image.dtype)
    source_rows = slice(max(0, -rows), min(height, height - rows))
    source_columns = slice(max(0, -columns), min(width, width - columns))
    target_rows = slice(max(0, rows), min(height, height + rows))
    target_columns = slice(max(0, columns), min(width, width + columns))
    if source_rows.start < source_rows.stop and source_columns.start < source_columns.stop:
        moved[target_rows, target_columns] = image[source_rows, source_columns]
    return moved


def reference_images(truth: np.ndarray, mask: np.ndarray, kind: str, *, blur_sigma: float = 2.0,
                     shift_px: int = 2, background=(0.0, 0.0, 0.0)) -> list[np.ndarray]:
    """The baseline images of ``--reference kind`` for one frame: ``shift`` gives the four moved ground truths,
    the others the one :func:`reference_image`."""
    if kind == "shift":
        fill = np.asarray(background, dtype=truth.dtype)
        return [shifted_image(truth, shift_px * dx, shift_px * dy, fill) for dx, dy in SHIFT_DIRECTIONS]
    return [reference_image(truth, mask, kind, blur_sigma=blur_sigma)]


def reference_image(truth: np.ndarray, mask: np.ndarray, kind: str, *, blur_sigma: float = 2.0) -> np.ndarray:
    """A baseline built from the ground truth [H,W,3] in 0..1: ``blur`` (Gaussian blur of ``blur_sigma`` pixels)
    or ``mean`` (the mask [H,W] filled with the mean colour inside it, zero elsewhere)."""
    import cv2

    if kind == "blur":
        return cv2.GaussianBlur(truth, (0, 0), blur_sigma)
    if kind == "mean":
        weight = mask[..., None]
        mean = (truth * weight).sum((0, 1)) / max(float(weight.sum()), 1.0)
        return np.where(weight > 0.5, mean, 0.0)
    raise ValueError(f"unknown reference {kind!r} (expected 'blur' or 'mean')")


def band_needed(band_share: float, target_db: float, *, outside_db: float = math.inf) -> float:
    """PSNR [dB] a region covering ``band_share`` of the mask pixels must reach for the pooled masked PSNR to
    reach ``target_db`` when the rest scores ``outside_db`` (infinite: no error there); NaN when no band PSNR
    can (the rest alone already misses the target, or the share is zero)."""
    if band_share <= 0.0:
        return math.nan
    budget = 10.0 ** (-target_db / 10.0) - (1.0 - band_share) * 10.0 ** (-outside_db / 10.0)
    if budget <= 0.0:
        return math.nan
    return -10.0 * math.log10(budget / band_share)


def _psnr_of_mean(predictions: list[np.ndarray], truth: np.ndarray, mask: np.ndarray) -> float:
    """Masked PSNR [dB] of the mean squared error of several predictions (:func:`masked_psnr` for one)."""
    if len(predictions) == 1:
        return masked_psnr(predictions[0], truth, mask)
    mse = np.mean([10.0 ** (-masked_psnr(prediction, truth, mask) / 10.0) for prediction in predictions])
    return -10.0 * np.log10(max(float(mse), 1e-12))


def breakdown(avatar, video, *, stride: int = 1, band: tuple[float, float] | None = None,
              reference: str | None = None, blur_sigma: float = 2.0, shift_px: int = 2) -> dict:
    """The mean masked PSNRs of the module docstring for ``avatar`` (or, with ``reference``, a ground-truth
    baseline) on ``video``; with ``band``, also the pooled ``band``, ``outside`` and ``band share`` values."""
    import cv2

    rows = {"masked": [], "gain": [], "inner": [], "gain+inner": []}
    pooled = {"band": [0.0, 0.0], "outside": [0.0, 0.0]}
    kernel = np.ones((5, 5), np.uint8)
    if avatar is not None:
        device = avatar.gaussians.means.device
        background = torch.as_tensor(video.background, dtype=torch.float32, device=device)
        grid = avatar.field.grid_weights()
        avatar.prepare_sequence(video.bone_transforms, frame_ids=video.frame_ids, fps=video.fps)
    for t in range(0, video.frame_count, stride):
        truth = video.images[t].astype(np.float64) / 255.0
        mask = video.masks[t].astype(np.float64) / 255.0
        if avatar is None:
            predictions = reference_images(truth, mask, reference, blur_sigma=blur_sigma, shift_px=shift_px,
                                           background=video.background)
        else:
            with torch.no_grad():
                bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32, device=device)
                image, _, _ = avatar.render(video.cameras[t], bones, background=background, grid=grid)
            predictions = [image.clamp(0, 1).cpu().numpy().astype(np.float64)]
        weight = mask[..., None]
        corrected = []
        for prediction in predictions:
            gain = (prediction * truth * weight).sum((0, 1)) / np.maximum((prediction**2 * weight).sum((0, 1)), 1e-12)
            corrected.append(np.clip(prediction * gain, 0.0, 1.0))
        inner = cv2.erode((mask > 0.5).astype(np.uint8), kernel).astype(np.float64)
        rows["masked"].append(_psnr_of_mean(predictions, truth, mask))
        rows["gain"].append(_psnr_of_mean(corrected, truth, mask))
        rows["inner"].append(_psnr_of_mean(predictions, truth, inner))
        rows["gain+inner"].append(_psnr_of_mean(corrected, truth, inner))
        if band is not None:
            root = video.bone_transforms[t][0].astype(np.float64) @ np.append(video.skeleton.heads[0], 1.0)
            inside = height_band_mask(video.cameras[t], root[:3], video.skeleton.up, low=band[0], high=band[1])
            error = np.mean([((prediction - truth) ** 2).sum(-1) for prediction in predictions], axis=0) * mask
            for name, region in (("band", inside), ("outside", ~inside)):
                pooled[name][0] += float(error[region].sum())
                pooled[name][1] += float(mask[region].sum()) * 3
    result = {key: float(np.mean(values)) for key, values in rows.items()}
    if band is not None:
        for name, (total, count) in pooled.items():
            result[name] = -10.0 * math.log10(max(total / max(count, 1.0), 1e-12))
        result["band share"] = pooled["band"][1] / max(pooled["band"][1] + pooled["outside"][1], 1.0)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="fit output folder (or avatar.pt) followed by video folders with masks; with "
                             "--reference, video folders only")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--stride", type=int, default=1, help="use every N-th frame of each folder")
    parser.add_argument("--height-band", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                        help="also split the masked error into the pixels whose ray passes between these world "
                             "heights at the root joint's depth, and the rest (see above)")
    parser.add_argument("--target", type=float, default=23.0,
                        help="masked PSNR [dB] the 'needed' columns are computed for (default 23)")
    parser.add_argument("--reference", choices=("blur", "mean", "shift"), default=None,
                        help="score a baseline made from the ground truth instead of an avatar (see above)")
    parser.add_argument("--blur-sigma", type=float, default=2.0, help="blur of --reference blur [pixels] "
                        "(default 2)")
    parser.add_argument("--shift-px", type=int, default=2, help="move of --reference shift [pixels] (default 2)")
    args = parser.parse_args(argv)
    if args.stride < 1:
        parser.error("--stride must be at least 1")
    if args.shift_px < 1:
        parser.error("--shift-px must be at least 1")
    if args.height_band is not None and not args.height_band[0] < args.height_band[1]:
        parser.error("--height-band LOW HIGH needs LOW < HIGH")
    avatar = None
    folders = args.paths
    if args.reference is None:
        if len(args.paths) < 2:
            parser.error("give an avatar and at least one video folder (or --reference)")
        from warpavatar.model import Avatar

        avatar = Avatar.load(args.paths[0], device=args.device)
        folders = args.paths[1:]
    columns = ["masked", "gain", "inner", "gain+inner"]
    if args.height_band is not None:
        columns += ["band", "outside", "band share", "needed, outside perfect", "needed, outside as is"]
    print("| folder | " + " | ".join(columns) + " |\n|" + "---|" * (len(columns) + 1))
    for folder in folders:
        video = data.load_video_folder(folder)
        if video.masks is None:
            raise SystemExit(f"{folder}: has no masks/, so no masked PSNR can be measured")
        values = breakdown(avatar, video, stride=args.stride,
                           band=tuple(args.height_band) if args.height_band is not None else None,
                           reference=args.reference, blur_sigma=args.blur_sigma, shift_px=args.shift_px)
        cells = [f"{values[k]:.2f}" for k in ("masked", "gain", "inner", "gain+inner")]
        if args.height_band is not None:
            needed = [band_needed(values["band share"], args.target),
                      band_needed(values["band share"], args.target, outside_db=values["outside"])]
            cells += [f"{values['band']:.2f}", f"{values['outside']:.2f}", f"{values['band share']:.2f}"]
            cells += [f"{value:.2f}" if math.isfinite(value) else "-" for value in needed]
        print(f"| {folder} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
