"""Writing video folders atomically: everything goes to a temporary sibling folder that is renamed into place
once complete, so an interrupted or failed write never leaves a half-written folder under the final name.

:func:`staged_folder` (:mod:`warpavatar.io.output_files`, re-exported here) is that mechanism for any writer
(``write_video_folder``, the InstantAvatar importer, ``warpavatar-prepare``); it marks the folder as a
``video-folder`` output, and replaces an existing folder only when it is such an output. :func:`write_json`,
:func:`write_png` and :func:`save_npz` write the files of a video folder as docs/FORMAT.md lays them out, each
through a temporary name, checked (a full disk is one clear error).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from warpavatar.data.types import Camera, VideoFolder
from warpavatar.io.images import write_image
from warpavatar.io.output_files import atomic_open, staged_folder, write_text_atomic

__all__ = ["staged_folder", "write_json", "write_png", "save_npz", "write_poses", "cameras_json", "write_video_folder"]


def write_json(path: Path, value) -> None:
    """``value`` as indented JSON text (UTF-8, final newline)."""
    write_text_atomic(path, json.dumps(value, indent=1) + "\n", fsync=False)


def write_png(path: Path, image: np.ndarray, *, compression: int = 9) -> None:
    """An 8-bit image (BGR or single channel) as a PNG (``compression`` 0-9: zlib level, 9 the smallest), through
    a temporary name (a file of a staged folder: not synced)."""
    rgb = image[..., ::-1] if image.ndim == 3 else image
    write_image(path, rgb, params=[cv2.IMWRITE_PNG_COMPRESSION, compression], fsync=False)


def save_npz(path: Path, **arrays) -> None:
    """Arrays as a compressed .npz archive."""
    with atomic_open(path, fsync=False) as stream:
        np.savez_compressed(stream, **arrays)


def write_poses(path: str | os.PathLike, bone_transforms, frame_ids, *, joint_positions=None, **extra) -> Path:
    """A ``poses.npz`` of docs/FORMAT.md (``bone_transforms`` [T,J,4,4] float32, ``frame_ids`` [T] int32, optional
    ``joint_positions`` [T,J,3] float32, and any ``extra`` arrays such as ``fps``), written to a temporary name,
    synced and renamed."""
    path = Path(path)
    arrays = {"bone_transforms": np.asarray(bone_transforms, dtype=np.float32),
              "frame_ids": np.asarray(frame_ids, dtype=np.int32), **extra}
    if joint_positions is not None:
        arrays["joint_positions"] = np.asarray(joint_positions, dtype=np.float32)
    with atomic_open(path) as stream:
        np.savez_compressed(stream, **arrays)
    return path


def cameras_json(cameras: list[Camera]) -> dict:
    """The cameras.json object of a folder's cameras: one fixed camera when they are all equal."""
    first = cameras[0]
    fixed = all(camera is first or (np.array_equal(camera.K, first.K) and
                                    np.array_equal(camera.world_to_camera, first.world_to_camera))
                for camera in cameras)
    data = first.to_json_dict()
    data["frames"] = None if fixed else [
        {"K": camera.K.astype(np.float64).tolist(),
         "world_to_camera": camera.world_to_camera.astype(np.float64).tolist()} for camera in cameras]
    return data


def write_video_folder(video: VideoFolder, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write ``video`` as a video folder (PNG frames and masks, JSON and .npz files), atomically.

    ``meta.json`` receives ``video.meta`` with ``fps`` and ``background`` updated from the fields (``background``
    only where the folder declares one or the field is not black: real footage declares none).

    Args:
        video: what to write; its ``cameras`` become a fixed camera when they are all equal.
        path: the folder to create.
        overwrite: replace an earlier video folder this project wrote (its marker says so) instead of raising
            FileExistsError; any other non-empty folder is refused (:func:`staged_folder`).

    Returns:
        ``path`` as a Path.
    """
    destination = Path(path)
    frame_count = video.frame_count
    if frame_count == 0:
        raise ValueError("write_video_folder: the video has no frames")
    if video.images.shape != (frame_count, video.height, video.width, 3) or video.images.dtype != np.uint8:
        raise ValueError(f"write_video_folder: images must be uint8 [T, H, W, 3] with T={frame_count}, got "
                         f"{video.images.dtype} {list(video.images.shape)}")
    if video.masks is not None and (video.masks.shape != video.images.shape[:3] or video.masks.dtype != np.uint8):
        raise ValueError(f"write_video_folder: masks must be uint8 {list(video.images.shape[:3])}, got "
                         f"{video.masks.dtype} {list(video.masks.shape)}")
    if len(video.cameras) != frame_count:
        raise ValueError(f"write_video_folder: {len(video.cameras)} cameras for {frame_count} frames")
    with staged_folder(destination, overwrite=overwrite) as tmp:
        (tmp / "frames").mkdir()
        for frame_id, image in zip(video.frame_ids, video.images):
            write_png(tmp / "frames" / f"{int(frame_id):06d}.png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        if video.masks is not None:
            (tmp / "masks").mkdir()
            for frame_id, mask in zip(video.frame_ids, video.masks):
                write_png(tmp / "masks" / f"{int(frame_id):06d}.png", mask)
        write_json(tmp / "cameras.json", cameras_json(video.cameras))
        write_json(tmp / "skeleton.json", video.skeleton.to_json_dict())
        write_poses(tmp / "poses.npz", video.bone_transforms, video.frame_ids, joint_positions=video.joint_positions)
        meta = dict(video.meta)
        meta["fps"] = float(video.fps)
        if video.declares_background or np.any(np.asarray(video.background) != 0):
            # only a folder whose frames were rendered over a flat colour declares one: declaring black for real
            # footage (the field's default) would make its frames, room and all, the fit's target
            meta["background"] = [float(value) for value in video.background]
        write_json(tmp / "meta.json", meta)
    return destination
