"""Reading and validating video folders and subjects (``docs/FORMAT.md``, ``docs/data.md``).

Everything read is checked; a problem raises :class:`~warpavatar.data.checks.VideoFolderError` whose message
starts with the path of the offending file and says what is wrong with it.
"""

from __future__ import annotations

import concurrent.futures
import math
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path

import cv2
import numpy as np

from warpavatar.data.checks import (VideoFolderError, check_fps, check_frame_ids, check_intrinsics,
                                    check_mask_coverage, check_rigid, check_subject_in_view, float_array, listed,
                                    positive_int, read_json, read_npz, require_mapping, warn_unusual)
from warpavatar.data.types import DEFAULT_FPS, POSE_SOURCES, Camera, Skeleton, Subject, VideoFolder
from warpavatar.io.images import ImageFileError, check_opencv_path, decode_image

__all__ = ["FRAME_EXTENSIONS", "load_video_folder", "load_subject", "LazyVideoFolders", "demo_subject_path",
           "read_poses", "read_skeleton", "read_image"]

FRAME_EXTENSIONS = (".png", ".jpg", ".jpeg")
"""File extensions of frame and mask images."""

_VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi")
_FRAME_NAME = re.compile(r"^(\d{6,})\.(png|jpg|jpeg)$", re.IGNORECASE)
_MAX_IMAGE_SIDE = 65536  # pixels; larger sizes in cameras.json are mistakes (16K video is 15360 wide)
_MASK_THRESHOLD = 128  # a resized mask pixel is subject (255) when its area average reaches this value
_MASK_SOFT_MARGIN = 0.1  # a mask value within this share of its scale from 0 or the scale counts as two-valued
_MASK_SOFT_SHARE = 0.05  # masks with more pixels than this share between those margins are warned about


def _list_frame_files(folder: Path) -> dict[int, Path]:
    """Map frame id -> file for the images named ``<6-digit id>.png|jpg|jpeg`` in ``folder``."""
    files: dict[int, Path] = {}
    badly_named = []
    for entry in sorted(os.scandir(folder), key=lambda item: item.name):
        if not entry.is_file() or not entry.name.lower().endswith(FRAME_EXTENSIONS):
            continue
        match = _FRAME_NAME.match(entry.name)
        if match is None:
            badly_named.append(entry.name)
            continue
        frame_id = int(match.group(1))
        if frame_id in files:
            raise VideoFolderError(folder / entry.name,
                                   f"frame id {frame_id} has two files ({files[frame_id].name} and {entry.name})")
        files[frame_id] = Path(entry.path)
    if badly_named:
        raise VideoFolderError(folder, f"image files must be named by their 6-digit frame id (000042.png); "
                                       f"found {listed(badly_named)}")
    return files


def _check_frame_files(files: dict[int, Path], frame_ids: np.ndarray, folder: Path, poses_path: Path,
                       what: str) -> None:
    """Every pose row needs a file, and every file a pose row."""
    missing = [int(frame_id) for frame_id in frame_ids if int(frame_id) not in files]
    if missing:
        names = [f"{frame_id:06d}" for frame_id in missing]
        raise VideoFolderError(folder, f"{len(missing)} {what} missing for frame ids listed in {poses_path.name} "
                                       f"(ids {listed(names)})")
    if len(files) != len(frame_ids):
        extra = sorted(set(files) - {int(frame_id) for frame_id in frame_ids})
        raise VideoFolderError(
            poses_path, f"frame count mismatch: {poses_path.name} has {len(frame_ids)} frames but {folder} holds "
                        f"{len(files)} {what} (ids without a pose: {listed(f'{i:06d}' for i in extra)})")


def _find_video_file(root: Path) -> Path | None:
    preferred = root / "video.mp4"
    if preferred.is_file():
        return preferred
    candidates = sorted(path for path in root.iterdir()
                        if path.is_file() and path.suffix.lower() in _VIDEO_EXTENSIONS)
    if len(candidates) > 1:
        names = listed(candidate.name for candidate in candidates)
        raise VideoFolderError(root, f"several video files and no video.mp4 to choose: {names}")
    return candidates[0] if candidates else None


def read_poses(path: str | os.PathLike, *, joint_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read and validate a ``poses.npz`` (docs/FORMAT.md) of a skeleton with ``joint_count`` joints.

    Returns:
        ``(bone_transforms [T,J,4,4] float32, frame_ids [T] int32, joint_positions [T,J,3] float32 or None)``.

    Raises:
        VideoFolderError: the file is missing or does not hold valid poses (the message names it).
    """
    path = Path(path)
    arrays = read_npz(path)
    for key in ("bone_transforms", "frame_ids"):
        if key not in arrays:
            raise VideoFolderError(path, f"has no {key!r} array (keys: {sorted(arrays)})")
    bone_transforms = arrays["bone_transforms"]
    if bone_transforms.ndim != 4 or bone_transforms.shape[2:] != (4, 4):
        raise VideoFolderError(
            path, f"'bone_transforms' must have shape [T, J, 4, 4], got {list(bone_transforms.shape)}")
    if not np.issubdtype(bone_transforms.dtype, np.floating):
        raise VideoFolderError(path, f"'bone_transforms' must be floating point, got {bone_transforms.dtype}")
    frame_count = bone_transforms.shape[0]
    if frame_count == 0:
        raise VideoFolderError(path, "'bone_transforms' has no frames (T = 0)")
    if bone_transforms.shape[1] != joint_count:
        raise VideoFolderError(path, f"joint count mismatch: 'bone_transforms' has {bone_transforms.shape[1]} "
                                     f"joints but skeleton.json has {joint_count}")
    check_rigid(bone_transforms, path, "'bone_transforms'", ("frame row", "joint"))
    frame_ids = arrays["frame_ids"]
    if not np.issubdtype(frame_ids.dtype, np.integer):
        raise VideoFolderError(path, f"'frame_ids' must be integers, got {frame_ids.dtype}")
    if frame_ids.shape != (frame_count,):
        raise VideoFolderError(path, f"frame count mismatch: 'frame_ids' has shape {list(frame_ids.shape)} but "
                                     f"'bone_transforms' has {frame_count} frames")
    frame_ids = check_frame_ids(frame_ids, path, increasing=True)
    joint_positions = arrays.get("joint_positions")
    if joint_positions is not None:
        if joint_positions.shape != (frame_count, joint_count, 3):
            raise VideoFolderError(path, f"'joint_positions' must have shape [{frame_count}, {joint_count}, 3], "
                                         f"got {list(joint_positions.shape)}")
        if not np.issubdtype(joint_positions.dtype, np.floating):
            raise VideoFolderError(path, f"'joint_positions' must be floating point, got {joint_positions.dtype}")
        if not np.all(np.isfinite(joint_positions)):
            raise VideoFolderError(path, "'joint_positions' holds non-finite values (nan or inf)")
        joint_positions = joint_positions.astype(np.float32)
    return bone_transforms.astype(np.float32), frame_ids.astype(np.int32), joint_positions


def _camera_from_json(entry: Mapping, width: int, height: int, fallback: Mapping, path: Path, what: str) -> Camera:
    if "K" not in entry and "K" not in fallback:
        raise VideoFolderError(path, f"{what} has no 'K'")
    if "world_to_camera" not in entry and "world_to_camera" not in fallback:
        raise VideoFolderError(path, f"{what} has no 'world_to_camera'")
    K = float_array(entry.get("K", fallback.get("K")), (3, 3), path, f"{what} 'K'")
    check_intrinsics(K, path, f"{what} 'K'", width=width, height=height)
    world_to_camera = float_array(entry.get("world_to_camera", fallback.get("world_to_camera")), (4, 4), path,
                                   f"{what} 'world_to_camera'")
    check_rigid(world_to_camera, path, f"{what} 'world_to_camera'")
    return Camera(K=K, world_to_camera=world_to_camera, width=width, height=height)


def _read_cameras(path: Path, frame_count: int) -> list[Camera]:
    """Cameras of all T pose rows: one object repeated for a fixed camera."""
    data = require_mapping(read_json(path), path, "cameras.json")
    for key in ("width", "height"):
        if key not in data:
            raise VideoFolderError(path, f"has no {key!r}")
    width = positive_int(data["width"], path, "'width'", at_most=_MAX_IMAGE_SIDE)
    height = positive_int(data["height"], path, "'height'", at_most=_MAX_IMAGE_SIDE)
    frames = data.get("frames")
    if frames is None:
        camera = _camera_from_json(data, width, height, {}, path, "the camera")
        return [camera] * frame_count
    if not isinstance(frames, list):
        raise VideoFolderError(path, f"'frames' must be null or a list, got {type(frames).__name__}")
    if len(frames) != frame_count:
        raise VideoFolderError(path, f"per-frame camera count mismatch: 'frames' has {len(frames)} entries but "
                                     f"poses.npz has {frame_count} frames")
    return [_camera_from_json(require_mapping(entry, path, f"frames[{index}]"), width, height, data, path,
                              f"frames[{index}]")
            for index, entry in enumerate(frames)]


def _read_meta(path: Path) -> tuple[dict, np.ndarray, float]:
    if not path.exists():
        return {}, np.zeros(3, dtype=np.float32), DEFAULT_FPS
    meta = dict(require_mapping(read_json(path), path, "meta.json"))
    fps = check_fps(meta.get("fps", DEFAULT_FPS), path)
    if meta.get("poses", POSE_SOURCES[0]) not in POSE_SOURCES:
        raise VideoFolderError(path, f"'poses' must be one of {', '.join(map(repr, POSE_SOURCES))}, "
                                     f"got {meta['poses']!r}")
    background = meta.get("background")
    if background is None:
        background = np.zeros(3)
    else:
        background = float_array(background, (3,), path, "'background'")
        if np.any(background < 0.0) or np.any(background > 1.0):
            raise VideoFolderError(path, f"'background' must be RGB in 0..1, got {background.tolist()}")
    return meta, background.astype(np.float32), float(fps)


def read_skeleton(path: Path) -> Skeleton:
    """The skeleton of a skeleton.json file, validated."""
    return Skeleton.from_json_dict(read_json(path), source=path)


def _resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    shrinking = width <= image.shape[1] and height <= image.shape[0]
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def _resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    if mask.shape[1] == width and mask.shape[0] == height:
        return mask
    averaged = _resize_image(mask, width, height)
    return np.where(averaged >= _MASK_THRESHOLD, 255, 0).astype(np.uint8)


def _decode_image(path: Path) -> np.ndarray:
    """An image file as 8-bit BGR [H,W,3] or BGRA [H,W,4]: grey is replicated, 16-bit is rounded to 8-bit."""
    try:
        image = decode_image(path)  # byte-safe paths, header size checked, codec warnings silenced
    except ImageFileError as error:
        raise VideoFolderError(path, error.problem) from None
    if image.dtype == np.uint16:
        image = np.round(image / 257.0).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise VideoFolderError(path, f"frames must be 8- or 16-bit images, got {image.dtype}")
    if image.ndim == 2 or image.shape[2] == 1:
        image = cv2.cvtColor(image.reshape(image.shape[:2]), cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 2:  # grey and alpha
        image = np.concatenate([np.repeat(image[..., :1], 3, axis=2), image[..., 1:]], axis=2)
    elif image.shape[2] not in (3, 4):
        raise VideoFolderError(path, f"frames must have 1 to 4 channels, got {image.shape[2]}")
    return image


def _check_size(image: np.ndarray, path: Path, width: int, height: int, sized_by: str) -> None:
    if image.shape[:2] != (height, width):
        raise VideoFolderError(path, f"image size mismatch: the image is {image.shape[1]}x{image.shape[0]} "
                                     f"but {sized_by} says {width}x{height}")


def read_image(path: Path, *, width: int, height: int, sized_by: str = "cameras.json") -> np.ndarray:
    """A colour image file as BGR uint8 [H,W,3], checked to be ``width`` x ``height`` (as ``sized_by`` says).

    Grey images are replicated to three channels, 16-bit ones rounded to 8 bits and an alpha channel is
    dropped (:func:`load_video_folder` composites RGBA frames instead).
    """
    image = _decode_image(path)
    _check_size(image, path, width, height, sized_by)
    return np.ascontiguousarray(image[..., :3])


def _read_frames(paths: list[Path], width: int, height: int, out_width: int, out_height: int,
                 background: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The frames as RGB uint8 [T,h,w,3] and, where they have an alpha channel, their alpha masks [T,h,w].

    An RGBA frame is composited over ``background`` (RGB in 0..1) and its alpha, thresholded at 128, is its
    mask; either every frame has alpha or none (the error names the first that differs from the first frame).
    """
    images = np.empty((len(paths), out_height, out_width, 3), np.uint8)
    alphas: list[np.ndarray | None] = [None] * len(paths)  # only RGBA folders pay for these
    background_bgr = np.asarray(background, dtype=np.float32)[::-1] * 255.0

    def read(index: int, path: Path) -> None:
        image = _decode_image(path)
        _check_size(image, path, width, height, "cameras.json")
        if image.shape[2] == 4:
            alpha = image[..., 3:].astype(np.float32) / 255.0
            image = np.round(image[..., :3] * alpha + background_bgr * (1.0 - alpha)).astype(np.uint8)
            alphas[index] = _resize_mask(np.where(alpha[..., 0] >= 0.5, 255, 0).astype(np.uint8), out_width,
                                         out_height)
        images[index] = _resize_image(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), out_width, out_height)

    _read_into(read, paths)
    has_alpha = np.array([alpha is not None for alpha in alphas])
    if not has_alpha.any():
        return images, None
    odd = int(np.argmax(has_alpha != has_alpha[0]))
    if has_alpha[odd] != has_alpha[0]:
        have = "has no alpha channel" if has_alpha[0] else "has an alpha channel"
        raise VideoFolderError(paths[odd], f"{have} but {paths[0].name} {'has' if has_alpha[0] else 'has not'}: "
                                           "frames are either all RGBA (their alpha is the mask) or none")
    return images, np.stack(alphas)


def _mask_scale(mask: np.ndarray) -> int:
    """The value that marks the subject in a mask: 1 when every value is 0 or 1, else 255 (an 8-bit mask, or a
    16-bit one whose values stay below 256), else 65535."""
    largest = int(mask.max()) if mask.size else 0
    return 1 if largest <= 1 else 255 if largest <= 255 else 65535


def _read_mask_file(path: Path, width: int, height: int, out_width: int,
                    out_height: int) -> tuple[np.ndarray, float]:
    """A mask file as 0/255 uint8 [out_height, out_width], and the share of its pixels that are not close to two
    values (farther than :data:`_MASK_SOFT_MARGIN` of its scale from both 0 and the scale).

    Whatever its scale (:func:`_mask_scale`: 0/1, 0/255, 0/65535), a pixel is the subject where its value reaches
    half the scale.
    """
    try:
        mask = decode_image(path, flags=cv2.IMREAD_UNCHANGED)
    except ImageFileError as error:
        raise VideoFolderError(path, error.problem) from None
    if mask.dtype not in (np.uint8, np.uint16):
        raise VideoFolderError(path, f"masks must be 8- or 16-bit, got {mask.dtype}")
    if mask.ndim == 3:
        if mask.shape[2] in (3, 4) and np.array_equal(mask[..., 0], mask[..., 1]) \
                and np.array_equal(mask[..., 0], mask[..., 2]):
            mask = mask[..., 0]  # a grey mask saved as colour
        else:
            raise VideoFolderError(path, f"masks must be single-channel, got {mask.shape[2]} channels")
    if mask.shape != (height, width):
        raise VideoFolderError(path, f"image size mismatch: the mask is {mask.shape[1]}x{mask.shape[0]} "
                                     f"but the frames are {width}x{height}")
    scale = _mask_scale(mask)
    values = mask.astype(np.float32) / scale
    soft = float(np.mean((values > _MASK_SOFT_MARGIN) & (values < 1.0 - _MASK_SOFT_MARGIN))) if scale > 1 else 0.0
    subject = np.where(values >= 0.5, 255, 0).astype(np.uint8)
    return _resize_mask(subject, out_width, out_height), soft


def _read_into(read, paths: list[Path]) -> None:
    """``read(i, paths[i])`` for every path, on a few threads (OpenCV releases the GIL); the first error (in
    the order of ``paths``) is raised."""
    if len(paths) < 4:
        for index, path in enumerate(paths):
            read(index, path)
        return
    workers = min(8, os.cpu_count() or 1, len(paths))
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
        for _ in pool.map(read, range(len(paths)), paths):  # re-raises the first error
            pass


def _read_video_frames(path: Path, frame_ids: np.ndarray, width: int, height: int, out_width: int,
                       out_height: int) -> np.ndarray:
    try:
        check_opencv_path(path)
    except ValueError:
        raise VideoFolderError(path, "the path is not valid UTF-8, which OpenCV needs to open a video; rename "
                                     "the file or its folders") from None
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise VideoFolderError(path, "cannot be opened as a video")
    images = np.empty((len(frame_ids), out_height, out_width, 3), dtype=np.uint8)
    try:
        wanted = {int(frame_id): row for row, frame_id in enumerate(frame_ids)}
        last = int(frame_ids[-1]) if len(frame_ids) else -1
        for index in range(last + 1):
            if not capture.grab():
                raise VideoFolderError(path, f"frame count mismatch: the video has only {index} frames but "
                                             f"poses.npz asks for frame id {last}")
            if index not in wanted:
                continue
            ok, image = capture.retrieve()
            if not ok or image is None:
                raise VideoFolderError(path, f"frame {index} cannot be decoded")
            if image.shape[:2] != (height, width):
                raise VideoFolderError(path, f"image size mismatch: the video is {image.shape[1]}x{image.shape[0]} "
                                             f"but cameras.json says {width}x{height}")
            images[wanted[index]] = _resize_image(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), out_width, out_height)
    finally:
        capture.release()
    return images


def _warn_about_soft_masks(paths: list[Path], soft_shares: np.ndarray) -> None:
    soft = soft_shares > _MASK_SOFT_SHARE
    if soft.any():
        first = int(np.argmax(soft))
        others = f" (and {int(soft.sum()) - 1} more masks)" if soft.sum() > 1 else ""
        warn_unusual(paths[first], f"not a two-valued mask: {soft_shares[first]:.0%} of its pixels lie between 0 "
                                   f"and full scale{others}; read as subject where at least half of full scale")


def _check_subject_in_view(cameras: list[Camera], skeleton: Skeleton, bone_transforms: np.ndarray,
                           frame_ids: np.ndarray, path: Path) -> None:
    """Every pose row's camera must see its posed joints (:func:`~warpavatar.data.checks.check_subject_in_view`)."""
    joints = np.einsum("tjab,jb->tja", bone_transforms[..., :3, :3].astype(np.float64),
                       skeleton.heads.astype(np.float64)) + bone_transforms[..., :3, 3]
    check_subject_in_view(np.stack([camera.world_to_camera for camera in cameras]),
                          np.stack([camera.K for camera in cameras]), joints, width=cameras[0].width,
                          height=cameras[0].height, frame_ids=frame_ids, path=path)


def _check_selection(max_frames, frame_stride, scale) -> None:
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, int)):
        raise TypeError(f"max_frames must be an int or None, got {type(max_frames).__name__}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    if isinstance(frame_stride, bool) or not isinstance(frame_stride, int):
        raise TypeError(f"frame_stride must be an int, got {type(frame_stride).__name__}")
    if frame_stride < 1:
        raise ValueError(f"frame_stride must be at least 1, got {frame_stride}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise TypeError(f"scale must be a number, got {type(scale).__name__}")
    if not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be positive and finite, got {scale}")


def _check_is_video_folder(root: Path) -> None:
    """A clear error for what is not a video folder at all: nothing there, a file, an empty folder."""
    if root.is_file():
        if root.suffix.lower() in _VIDEO_EXTENSIONS:
            raise VideoFolderError(root, "a video file, not a video folder: put it in a folder as video.mp4 with "
                                         "cameras.json, skeleton.json and poses.npz (docs/FORMAT.md), or let "
                                         "warpavatar-prepare make the folder from footage")
        raise VideoFolderError(root, "a file, not a video folder (docs/FORMAT.md)")
    if not root.is_dir():
        raise VideoFolderError(root, "no such video folder")
    try:
        empty = next(os.scandir(root), None) is None
    except OSError as error:
        raise VideoFolderError(root, f"cannot be listed ({error.strerror})") from None
    if empty:
        raise VideoFolderError(root, "the folder is empty: a video folder holds frames/ (or video.mp4), "
                                     "cameras.json, skeleton.json and poses.npz (docs/FORMAT.md)")


def load_video_folder(path: str | os.PathLike, *, max_frames: int | None = None, frame_stride: int = 1,
                      scale: float = 1.0) -> VideoFolder:
    """Read and validate one video folder (``docs/data.md``).

    The frames come from ``frames/<id>.png|jpg`` or, when there is no ``frames/`` folder, from a video file
    (``video.mp4``, else the single ``*.mp4|*.mov|*.avi`` in the folder) read with OpenCV, where frame id k
    is the video's k-th frame (0-based; frames after the last id are ignored).

    Args:
        path: the video folder.
        max_frames: keep at most this many frames (after ``frame_stride``); None keeps all.
        frame_stride: keep every ``frame_stride``-th pose row (1 keeps all).
        scale: resize images, masks and intrinsics by this factor: the new size is
            ``round(W * scale) x round(H * scale)``, images are resampled by area averaging (bilinear when
            enlarging), masks by area averaging then thresholded at 128 (so they stay 0/255), and ``K`` follows
            the integer-pixel-centre convention (:meth:`Camera.resized`).

    Returns:
        The folder's contents; the whole folder's listing, cameras and poses are validated even when only some
        frames are kept, but only the kept frames are decoded.

    Raises:
        VideoFolderError: a missing or invalid file (the message names it), see ``docs/data.md``, or data that
            cannot show the subject (``docs/FORMAT.md``, "Checks on load": implausible focal lengths, the subject
            behind the camera or outside the image, empty masks in most frames).
        TypeError, ValueError: bad ``max_frames``, ``frame_stride`` or ``scale``.

    Warns:
        VideoFolderWarning: a few frames without the subject, or masks that are not two-valued.
    """
    _check_selection(max_frames, frame_stride, scale)
    root = Path(path)
    _check_is_video_folder(root)
    skeleton = read_skeleton(root / "skeleton.json")
    poses_path = root / "poses.npz"
    bone_transforms, frame_ids, joint_positions = read_poses(poses_path, joint_count=skeleton.joint_count)
    cameras = _read_cameras(root / "cameras.json", len(frame_ids))
    _check_subject_in_view(cameras, skeleton, bone_transforms, frame_ids, root / "cameras.json")
    meta, background, fps = _read_meta(root / "meta.json")

    frames_dir = root / "frames"
    video_path = None
    if frames_dir.is_dir():
        frame_files = _list_frame_files(frames_dir)
        if not frame_files:
            videos = sorted(p.name for p in frames_dir.iterdir() if p.suffix.lower() in _VIDEO_EXTENSIONS)
            found = (f"it holds the video {listed(videos)}: a video file goes beside frames/ as video.mp4, "
                     "without a frames/ folder" if videos else "no <6-digit id>.png|jpg files")
            raise VideoFolderError(frames_dir, f"no frame images: {found}")
        _check_frame_files(frame_files, frame_ids, frames_dir, poses_path, "frames")
    else:
        video_path = _find_video_file(root)
        if video_path is None:
            raise VideoFolderError(frames_dir, "missing: the folder has neither frames/ nor a video file "
                                               "(video.mp4, *.mp4, *.mov, *.avi)")
    masks_dir = root / "masks"
    mask_files = None
    if masks_dir.is_dir():
        mask_files = _list_frame_files(masks_dir)
        _check_frame_files(mask_files, frame_ids, masks_dir, poses_path, "masks")

    rows = np.arange(len(frame_ids))[::frame_stride]
    if max_frames is not None:
        rows = rows[:max_frames]
    frame_ids = frame_ids[rows]
    bone_transforms = bone_transforms[rows]
    joint_positions = joint_positions[rows] if joint_positions is not None else None

    width, height = cameras[0].width, cameras[0].height
    out_width, out_height = width, height
    if scale != 1.0:
        out_width, out_height = max(1, round(width * scale)), max(1, round(height * scale))
    resized_cameras: dict[int, Camera] = {}
    kept_cameras = []
    for row in rows:
        camera = cameras[row]
        if id(camera) not in resized_cameras:
            resized_cameras[id(camera)] = camera if scale == 1.0 else camera.resized(out_width, out_height)
        kept_cameras.append(resized_cameras[id(camera)])

    if video_path is None:
        paths = [frame_files[int(frame_id)] for frame_id in frame_ids]
        images, alpha_masks = _read_frames(paths, width, height, out_width, out_height, background)
    else:
        images = _read_video_frames(video_path, frame_ids, width, height, out_width, out_height)
        alpha_masks = None
    masks = alpha_masks
    if mask_files is not None:
        paths = [mask_files[int(frame_id)] for frame_id in frame_ids]
        masks = np.empty((len(paths), out_height, out_width), np.uint8)
        soft_shares = np.zeros(len(paths))

        def read_mask(index: int, path: Path) -> None:
            masks[index], soft_shares[index] = _read_mask_file(path, width, height, out_width, out_height)

        _read_into(read_mask, paths)
        _warn_about_soft_masks(paths, soft_shares)
    if masks is not None:
        check_mask_coverage(masks, frame_ids, masks_dir if mask_files is not None else frames_dir,
                            "masks" if mask_files is not None else "alpha masks")

    return VideoFolder(root=root, frame_ids=frame_ids, images=images, masks=masks, cameras=kept_cameras,
                       skeleton=skeleton, bone_transforms=bone_transforms, joint_positions=joint_positions,
                       background=background, fps=fps, meta=meta)


class LazyVideoFolders(Mapping):
    """A read-only mapping name -> :class:`VideoFolder` that reads each folder the first time it is asked for.

    Listing names (``keys()``, ``len``, ``in``) reads nothing; ``folders[name]`` reads and validates that
    folder once and caches it. ``paths`` maps each name to its folder.
    """

    def __init__(self, paths: Mapping[str, Path], *, skeleton: Skeleton | None = None, scale: float = 1.0):
        self.paths = dict(paths)
        self._skeleton = skeleton
        self._scale = scale
        self._loaded: dict[str, VideoFolder] = {}

    def __getitem__(self, name: str) -> VideoFolder:
        if name not in self._loaded:
            folder = load_video_folder(self.paths[name], scale=self._scale)
            if self._skeleton is not None:
                _check_same_skeleton(folder.skeleton, self._skeleton, folder.root / "skeleton.json")
            self._loaded[name] = folder
        return self._loaded[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.paths)

    def __len__(self) -> int:
        return len(self.paths)

    def __repr__(self) -> str:
        return f"LazyVideoFolders({sorted(self.paths)}, loaded={sorted(self._loaded)})"


def _check_same_skeleton(skeleton: Skeleton, reference: Skeleton, path: Path) -> None:
    if skeleton.names != reference.names or not np.array_equal(skeleton.parents, reference.parents):
        raise VideoFolderError(path, "the skeleton differs from the training folder's (joint names or parents)")
    if not (np.allclose(skeleton.heads, reference.heads, atol=1e-5)
            and np.allclose(skeleton.tails, reference.tails, atol=1e-5)):
        raise VideoFolderError(path, "the skeleton's rest pose differs from the training folder's")



def load_subject(path: str | os.PathLike, *, scale: float = 1.0) -> Subject:
    """Read a subject folder: ``train/``, optional ``novel_view/<camera>/`` and ``novel_pose/<name>/``.

    The training folder is read and validated at once; the held-out folders are listed now and read (and
    checked to share the training skeleton) the first time they are indexed (:class:`LazyVideoFolders`).

    Args:
        path: the subject folder.
        scale: image scale applied to every folder (see :func:`load_video_folder`).

    Raises:
        VideoFolderError: a missing ``train/`` folder or any problem :func:`load_video_folder` reports.
    """
    root = Path(path)
    if not root.is_dir():
        raise VideoFolderError(root, "no such subject folder")
    train_dir = root / "train"
    if not train_dir.is_dir():
        raise VideoFolderError(train_dir, "missing: a subject needs a train/ video folder")
    train = load_video_folder(train_dir, scale=scale)

    def held_out(kind: str) -> LazyVideoFolders:
        folder = root / kind
        paths = {}
        if folder.is_dir():
            paths = {entry.name: Path(entry.path)
                     for entry in sorted(os.scandir(folder), key=lambda item: item.name) if entry.is_dir()}
        return LazyVideoFolders(paths, skeleton=train.skeleton, scale=scale)

    license_path = root / "LICENSE.txt"
    license_text = license_path.read_text(encoding="utf-8") if license_path.is_file() else None
    return Subject(root=root, train=train, novel_view=held_out("novel_view"), novel_pose=held_out("novel_pose"),
                   license_text=license_text)


def demo_subject_path() -> Path:
    """The small demo subject shipped inside the package (``warpavatar/data/demo/robot``).

    A reduced copy of the ``robot`` benchmark subject (CC0): its ``train/``, one ``novel_view/`` and one
    ``novel_pose/`` folder at 128x128 pixels; its LICENSE.txt says what was reduced.
    """
    return Path(__file__).resolve().parent / "demo" / "robot"


# ----------------------------------------------------------------------------------------------------------
