"""Build the small demo subject shipped inside the package from a full benchmark subject.

``python tools/make_demo_data.py path/to/robot -o warpavatar/data/demo --size 128``

Keeps a subset of the training frames (every k-th, over the whole video), one ``novel_view/`` folder (all of
its frames) and one ``novel_pose/`` folder (every k-th frame). Each folder is cropped to a square around the
union of its masks' bounding boxes (plus a margin), then resized; the intrinsics are adjusted for both steps
(crop: ``cx -= left``; resize: ``cx' = (cx + 0.5) s - 0.5``), so poses and cameras stay exact. Skeleton,
bone transforms (the kept rows), masks and meta.json are kept; LICENSE.txt is copied with a note of what was
reduced. The subject is written under ``<output>/<name>.tmp`` and renamed when complete, then read back with
:func:`warpavatar.data.load_subject` as a check.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from warpavatar.data import Camera, VideoFolder, load_subject, load_video_folder, write_video_folder

__all__ = ["square_crop_box", "crop_and_resize", "make_demo_subject", "main"]


def square_crop_box(masks: np.ndarray, *, margin: float) -> tuple[int, int, int]:
    """A square around the union of the masks' bounding boxes, inside the image.

    Args:
        masks: foreground masks, shape [T, H, W], uint8 (non-zero = subject).
        margin: extra space on each side, as a fraction of the box's longer side.

    Returns:
        ``(left, top, side)`` in pixels; the square is as large as the image's shorter side at most and is
        shifted, not shrunk, to stay inside the image.
    """
    union = np.any(masks > 0, axis=0)
    if not union.any():
        raise ValueError("the masks are empty: cannot find the subject to crop around")
    rows = np.flatnonzero(union.any(axis=1))
    columns = np.flatnonzero(union.any(axis=0))
    height, width = union.shape
    box_side = max(rows[-1] - rows[0] + 1, columns[-1] - columns[0] + 1)
    side = min(int(math.ceil(box_side * (1.0 + 2.0 * margin))), height, width)
    centre_row = 0.5 * (rows[0] + rows[-1])
    centre_column = 0.5 * (columns[0] + columns[-1])
    top = int(round(centre_row - 0.5 * (side - 1)))
    left = int(round(centre_column - 0.5 * (side - 1)))
    top = min(max(top, 0), height - side)
    left = min(max(left, 0), width - side)
    return left, top, side


def crop_and_resize(video: VideoFolder, *, left: int, top: int, side: int, size: int) -> VideoFolder:
    """Crop every frame (and mask) to the square (left, top, side) and resize it to ``size`` x ``size``.

    Images are resampled by area averaging; masks by area averaging thresholded at 128; each camera's ``K``
    follows (:meth:`Camera.cropped`, then :meth:`Camera.resized`).
    """
    window = (slice(top, top + side), slice(left, left + side))
    images = np.stack([cv2.resize(np.ascontiguousarray(image[window]), (size, size), interpolation=cv2.INTER_AREA)
                       for image in video.images])
    masks = None
    if video.masks is not None:
        masks = np.stack([
            np.where(cv2.resize(np.ascontiguousarray(mask[window]), (size, size),
                                interpolation=cv2.INTER_AREA) >= 128, 255, 0).astype(np.uint8)
            for mask in video.masks])
    converted: dict[int, Camera] = {}
    cameras = []
    for camera in video.cameras:
        if id(camera) not in converted:
            converted[id(camera)] = camera.cropped(left, top, side, side).resized(size, size)
        cameras.append(converted[id(camera)])
    return replace(video, images=images, masks=masks, cameras=cameras)


def _reduce_folder(source: Path, destination: Path, *, stride: int, size: int, margin: float, note: str) -> dict:
    video = load_video_folder(source, frame_stride=stride)
    if video.masks is None:
        raise ValueError(f"{source}: the demo needs masks to crop around the subject")
    left, top, side = square_crop_box(video.masks, margin=margin)
    reduced = crop_and_resize(video, left=left, top=top, side=side, size=size)
    meta = dict(video.meta)
    meta["frame_ids_step"] = int(meta.get("frame_ids_step", 1)) * stride
    meta["demo_reduction"] = (f"{note}: one pose row in {stride}, cropped to the {side}x{side} square at "
                              f"(left {left}, top {top}) of the {video.width}x{video.height} frames, resized to "
                              f"{size}x{size}; K adjusted accordingly")
    reduced = replace(reduced, meta=meta)
    write_video_folder(reduced, destination)
    coverage = float(np.mean(reduced.masks > 0))
    return {"folder": str(destination), "frames": reduced.frame_count, "crop": (left, top, side),
            "mask_coverage": coverage}


def make_demo_subject(subject_dir: Path, output_dir: Path, *, size: int, train_frames: int, novel_view: str,
                      novel_pose: str, novel_pose_frames: int, margin: float, overwrite: bool) -> Path:
    """Write the reduced copy of ``subject_dir`` to ``output_dir/<subject name>`` and return its path."""
    subject = load_subject(subject_dir)
    if novel_view not in subject.novel_view:
        raise ValueError(f"{subject_dir}: no novel_view/{novel_view} (have {sorted(subject.novel_view)})")
    if novel_pose not in subject.novel_pose:
        raise ValueError(f"{subject_dir}: no novel_pose/{novel_pose} (have {sorted(subject.novel_pose)})")
    destination = output_dir / subject_dir.name
    if destination.exists() and not overwrite:
        raise FileExistsError(f"{destination} exists (pass --overwrite to replace it)")
    tmp = output_dir / (subject_dir.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        train_stride = max(1, math.ceil(subject.train.frame_count / train_frames))
        pose_count = len(np.load(subject.novel_pose.paths[novel_pose] / "poses.npz")["frame_ids"])
        pose_stride = max(1, math.ceil(pose_count / novel_pose_frames))
        reports = [
            _reduce_folder(subject_dir / "train", tmp / "train", stride=train_stride, size=size, margin=margin,
                           note="warpavatar demo"),
            _reduce_folder(subject.novel_view.paths[novel_view], tmp / "novel_view" / novel_view, stride=1,
                           size=size, margin=margin, note="warpavatar demo"),
            _reduce_folder(subject.novel_pose.paths[novel_pose], tmp / "novel_pose" / novel_pose,
                           stride=pose_stride, size=size, margin=margin, note="warpavatar demo"),
        ]
        license_text = (subject.license_text or "").rstrip("\n")
        lines = [f"  {Path(report['folder']).relative_to(tmp)}: {report['frames']} frames, crop "
                 f"(left, top, side) = {report['crop']}" for report in reports]
        summary = textwrap.fill(
            "Reduced for warpavatar's demo by tools/make_demo_data.py from the full subject: one training frame "
            f"in {train_stride}, novel_view/{novel_view} whole, one frame in {pose_stride} of "
            f"novel_pose/{novel_pose}; the other held-out folders were dropped. Each folder was cropped to a "
            f"square around its subject and resized to {size}x{size} pixels, with the camera intrinsics "
            "adjusted to match; skeleton, bone transforms and masks are the original ones (masks resampled). "
            "The reduced data keeps the licence above (CC0 1.0).", width=110)
        license_text += "\n\n" + summary + "\n" + "\n".join(lines) + "\n"
        (tmp / "LICENSE.txt").write_text(license_text, encoding="utf-8")
        if destination.exists():
            shutil.rmtree(destination)
        tmp.rename(destination)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for report in reports:
        folder = destination / Path(report["folder"]).relative_to(tmp)
        print(f"{folder}: {report['frames']} frames, mask covers {100 * report['mask_coverage']:.1f} %")
    return destination


def _folder_bytes(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("subject_dir", type=Path, help="the full subject folder (train/, novel_view/, novel_pose/)")
    parser.add_argument("-o", "--output", type=Path, default=Path("warpavatar/data/demo"),
                        help="folder that receives <subject name>/ (default: warpavatar/data/demo)")
    parser.add_argument("--size", type=int, default=128, help="side of the square output frames [pixels]")
    parser.add_argument("--train-frames", type=int, default=50,
                        help="at most this many training frames, every k-th over the whole video")
    parser.add_argument("--novel-view", default="cam_090", help="the novel_view/ folder to keep (all its frames)")
    parser.add_argument("--novel-pose", default="dance_cam000", help="the novel_pose/ folder to keep")
    parser.add_argument("--novel-pose-frames", type=int, default=17,
                        help="at most this many frames of the novel_pose/ folder, every k-th")
    parser.add_argument("--margin", type=float, default=0.06,
                        help="space around the subject's bounding box, as a fraction of its longer side")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output subject")
    args = parser.parse_args(argv)
    for name in ("size", "train_frames", "novel_pose_frames"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.margin < 0:
        parser.error("--margin must not be negative")
    destination = make_demo_subject(args.subject_dir, args.output, size=args.size, train_frames=args.train_frames,
                                    novel_view=args.novel_view, novel_pose=args.novel_pose,
                                    novel_pose_frames=args.novel_pose_frames, margin=args.margin,
                                    overwrite=args.overwrite)
    subject = load_subject(destination)
    for folders in (subject.novel_view, subject.novel_pose):
        for name in folders:
            folders[name]  # read and validate every held-out folder
    print(f"{destination}: {_folder_bytes(destination) / 1e6:.2f} MB, load_subject accepts it")
    return 0


if __name__ == "__main__":
    sys.exit(main())
