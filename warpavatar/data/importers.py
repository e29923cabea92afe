"""Importers: other datasets' layouts converted into warpavatar video folders."""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from warpavatar.data.checks import (VideoFolderError, check_intrinsics, check_rigid, float_array, positive_int,
                                    read_npz)
from warpavatar.data.reader import FRAME_EXTENSIONS, load_video_folder, read_image, read_skeleton
from warpavatar.data.types import DEFAULT_FPS, Camera
from warpavatar.data.writer import cameras_json, save_npz, staged_folder, write_json, write_png
from warpavatar.io.images import ImageFileError, decode_image

__all__ = ["import_instantavatar"]


def _sorted_files(folder: Path, extensions: tuple[str, ...]) -> list[Path]:
    return sorted(path for path in folder.iterdir() if path.is_file() and path.suffix.lower() in extensions)


def _instantavatar_mask(path: Path) -> np.ndarray:
    """A mask of the InstantAvatar layout (.png, or .npy of bool / 0..1 floats / 0..255 integers) as 0/255."""
    if path.suffix.lower() == ".npy":
        try:
            mask = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise VideoFolderError(path, f"cannot be read as a .npy array ({error})") from None
        if mask.ndim == 3 and mask.shape[2] == 1:
            mask = mask[..., 0]
        if mask.ndim != 2:
            raise VideoFolderError(path, f"a mask must be [H, W], got shape {list(mask.shape)}")
        if mask.dtype == np.bool_:
            return np.where(mask, 255, 0).astype(np.uint8)
        if np.issubdtype(mask.dtype, np.floating):
            if not np.all(np.isfinite(mask)):
                raise VideoFolderError(path, "the mask holds non-finite values")
            return np.where(mask > 0.5, 255, 0).astype(np.uint8)
        return np.where(mask > (127 if mask.max(initial=0) > 1 else 0), 255, 0).astype(np.uint8)
    try:
        mask = decode_image(path, flags=cv2.IMREAD_UNCHANGED)
    except ImageFileError as error:
        raise VideoFolderError(path, error.problem) from None
    if mask.ndim == 3:
        mask = mask[..., 0]
    if mask.dtype != np.uint8:
        raise VideoFolderError(path, f"masks must be 8-bit, got {mask.dtype}")
    return mask


def import_instantavatar(src_folder: str | os.PathLike, dst_folder: str | os.PathLike, *,
                         skeleton_json: str | os.PathLike, bone_transforms_npz: str | os.PathLike,
                         fps: float = DEFAULT_FPS, overwrite: bool = False) -> Path:
    """Convert an InstantAvatar / GART-style sequence into a warpavatar video folder.

    Source layout: ``images/*.png|jpg`` (frames in sorted file-name order), optional ``masks/*.png|npy``
    (same count and order), and ``cameras.npz`` with ``intrinsic`` [3, 3], ``extrinsic`` [4, 4]
    (world-to-camera, OpenCV), ``height`` and ``width``. SMPL parameters are not used: the poses come from
    ``bone_transforms_npz`` (``bone_transforms`` [T, J, 4, 4], optional ``frame_ids`` [T] and
    ``joint_positions`` [T, J, 3]; row t belongs to the t-th image; without ``frame_ids`` the frames are
    numbered 0..T-1) for the skeleton in ``skeleton_json`` (warpavatar-skeleton/1).

    The folder is written under a temporary name beside it, validated with :func:`load_video_folder` and renamed.

    Args:
        src_folder: the InstantAvatar-style folder.
        dst_folder: the video folder to create.
        skeleton_json: the skeleton.json to copy (validated).
        bone_transforms_npz: the per-frame bone transforms.
        fps: frame rate written to meta.json.
        overwrite: replace an earlier video folder at ``dst_folder`` instead of raising FileExistsError (a folder
            this project did not write is always refused).

    Returns:
        ``dst_folder`` as a Path.

    Raises:
        VideoFolderError: a missing or invalid source file (named in the message).
    """
    src = Path(src_folder)
    destination = Path(dst_folder)
    skeleton_path = Path(skeleton_json)
    poses_path = Path(bone_transforms_npz)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive finite number, got {fps!r}")
    if not src.is_dir():
        raise VideoFolderError(src, "no such folder")
    images_dir = src / "images"
    if not images_dir.is_dir():
        raise VideoFolderError(images_dir, "missing: an InstantAvatar folder needs images/")
    image_paths = _sorted_files(images_dir, FRAME_EXTENSIONS)
    if not image_paths:
        raise VideoFolderError(images_dir, "holds no .png or .jpg images")
    mask_paths = None
    if (src / "masks").is_dir():
        mask_paths = _sorted_files(src / "masks", (".png", ".npy"))
        if len(mask_paths) != len(image_paths):
            raise VideoFolderError(src / "masks", f"mask count mismatch: {len(mask_paths)} masks for "
                                                  f"{len(image_paths)} images in {images_dir}")

    cameras_path = src / "cameras.npz"
    camera_arrays = read_npz(cameras_path)
    for key in ("intrinsic", "extrinsic", "height", "width"):
        if key not in camera_arrays:
            raise VideoFolderError(cameras_path, f"has no {key!r} array (keys: {sorted(camera_arrays)})")
    K = float_array(camera_arrays["intrinsic"], (3, 3), cameras_path, "'intrinsic'")
    check_intrinsics(K, cameras_path, "'intrinsic'")
    world_to_camera = float_array(camera_arrays["extrinsic"], (4, 4), cameras_path, "'extrinsic'")
    check_rigid(world_to_camera, cameras_path, "'extrinsic'")
    width = positive_int(np.asarray(camera_arrays["width"]).reshape(-1)[0].item(), cameras_path, "'width'")
    height = positive_int(np.asarray(camera_arrays["height"]).reshape(-1)[0].item(), cameras_path, "'height'")

    skeleton = read_skeleton(skeleton_path)
    pose_arrays = read_npz(poses_path)
    if "bone_transforms" not in pose_arrays:
        raise VideoFolderError(poses_path, f"has no 'bone_transforms' array (keys: {sorted(pose_arrays)})")
    frame_count = pose_arrays["bone_transforms"].shape[0] if pose_arrays["bone_transforms"].ndim else 0
    if frame_count != len(image_paths):
        raise VideoFolderError(poses_path, f"frame count mismatch: {frame_count} pose rows for "
                                           f"{len(image_paths)} images in {images_dir}")
    pose_arrays.setdefault("frame_ids", np.arange(frame_count, dtype=np.int32))

    with staged_folder(destination, overwrite=overwrite) as tmp:
        (tmp / "frames").mkdir()
        for frame_id, image_path in zip(pose_arrays["frame_ids"], image_paths):
            image = read_image(image_path, width=width, height=height, sized_by="cameras.npz")
            write_png(tmp / "frames" / f"{int(frame_id):06d}.png", image)
        if mask_paths is not None:
            (tmp / "masks").mkdir()
            for frame_id, mask_path in zip(pose_arrays["frame_ids"], mask_paths):
                mask = _instantavatar_mask(mask_path)
                if mask.shape != (height, width):
                    raise VideoFolderError(mask_path, f"image size mismatch: the mask is {mask.shape[1]}x"
                                                      f"{mask.shape[0]} but the images are {width}x{height}")
                write_png(tmp / "masks" / f"{int(frame_id):06d}.png", mask)
        camera = Camera(K=K, world_to_camera=world_to_camera, width=width, height=height)
        write_json(tmp / "cameras.json", cameras_json([camera]))
        write_json(tmp / "skeleton.json", skeleton.to_json_dict())
        keep = {key: pose_arrays[key] for key in ("bone_transforms", "frame_ids", "joint_positions")
                if key in pose_arrays}
        save_npz(tmp / "poses.npz", **keep)
        meta = {"fps": float(fps), "source": f"imported from the InstantAvatar-style folder {src.name}"}
        write_json(tmp / "meta.json", meta)
        try:
            load_video_folder(tmp, max_frames=1)  # checks poses, skeleton, cameras and the file listing
        except VideoFolderError as error:
            # Name the user's file rather than the temporary copy.
            source = {"poses.npz": poses_path, "skeleton.json": skeleton_path}.get(error.path.name, error.path)
            raise VideoFolderError(source, error.problem) from None
    return destination
