"""Small validators of video-folder files: each raises :class:`VideoFolderError` naming the offending file, or,
for data that are valid but unusual, issues a :class:`VideoFolderWarning` naming it (docs/FORMAT.md, "Checks on
load")."""

from __future__ import annotations

import json
import math
import os
import warnings
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["VideoFolderError", "VideoFolderWarning", "RIGID_TOLERANCE", "FOCAL_RANGE", "FPS_RANGE", "MAX_FRAME_ID",
           "UNUSABLE_SHARE", "float_array", "check_rigid", "check_intrinsics", "check_fps", "check_frame_ids",
           "check_subject_in_view", "check_mask_coverage", "warn_unusual", "read_json", "read_npz", "require_mapping",
           "positive_int", "listed"]

RIGID_TOLERANCE = 1e-3
"""Largest entry of ``|R^T R - I|`` accepted for the rotation part of a rigid 4x4 transform."""

FOCAL_RANGE = (0.05, 50.0)
"""Focal lengths fx, fy accepted, in multiples of the image's larger side: 0.05x is a field of view of about 169
degrees across that side, 50x about 1.1 degrees; beyond either a number is a mistake (a focal length in mm, a
normalised K) rather than a lens."""

FPS_RANGE = (0.01, 1000.0)
"""Frame rates accepted [frames per second], both ends included: from a frame every 100 s to 1000 a second."""

MAX_FRAME_ID = 2**31 - 1
"""The largest frame id: ids are stored as int32."""

UNUSABLE_SHARE = 0.5
"""A folder where more than this share of the frames show no subject (behind the camera, outside the image, an
empty mask) is refused; fewer such frames, but at least one, give a :class:`VideoFolderWarning`."""

_LAST_ROW_TOLERANCE = 1e-5  # how far the last row of a rigid transform may be from [0, 0, 0, 1]
_LARGEST = float(np.finfo(np.float32).max)  # values are used as float32
_MAX_LISTED = 5  # at most this many offending ids or files are named in an error message


class VideoFolderError(ValueError):
    """A video folder, or one of its files, is missing or invalid.

    Attributes:
        path: the offending file or folder.
        problem: what is wrong with it, in words.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.problem))


class VideoFolderWarning(UserWarning):
    """A video folder whose data are valid but unusual (a few frames without the subject, soft masks); the message
    starts with the file or folder concerned."""


def warn_unusual(path: str | os.PathLike, problem: str) -> None:
    """Issue a :class:`VideoFolderWarning` ``"<path>: <problem>"``."""
    warnings.warn(f"{Path(path)}: {problem}", VideoFolderWarning, stacklevel=3)


def float_array(value, shape: tuple[int, ...], path: Path, what: str) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise VideoFolderError(path, f"{what} must be numbers of shape {list(shape)}, got {value!r:.80}") from None
    if array.shape != shape:
        raise VideoFolderError(path, f"{what} must have shape {list(shape)}, got {list(array.shape)}")
    if not np.all(np.isfinite(array)):
        raise VideoFolderError(path, f"{what} holds non-finite values (nan or inf)")
    if array.size and np.abs(array).max() > _LARGEST:
        raise VideoFolderError(path, f"{what} holds a value beyond float32's range ({np.abs(array).max():.3g})")
    return array


def _index_text(index: tuple[int, ...], names: tuple[str, ...]) -> str:
    return ", ".join(f"{name} {value}" for name, value in zip(names, index))


def check_rigid(matrices: np.ndarray, path: Path, what: str, index_names: tuple[str, ...] = (), *,
                tolerance: float = RIGID_TOLERANCE) -> None:
    """Check that ``matrices[..., 4, 4]`` are finite rigid transforms (rotation + translation).

    Args:
        matrices: the transforms, shape [..., 4, 4].
        path: the file named in the error; what: what the matrices are, in words.
        index_names: the names of the leading axes, to say where the first bad matrix is.
        tolerance: the largest entry of ``|R^T R - I|`` accepted (the determinant must be positive).
    """
    if not np.all(np.isfinite(matrices)):
        where = ""
        if index_names:
            bad = tuple(np.argwhere(~np.isfinite(matrices).all(axis=(-2, -1)))[0])
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(path, f"{what} holds non-finite values (nan or inf){where}")
    matrices = matrices.astype(np.float64, copy=False)
    last_row_error = np.abs(matrices[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    rotation = matrices[..., :3, :3]
    gram = np.einsum("...ki,...kj->...ij", rotation, rotation)
    orthonormal_error = np.abs(gram - np.eye(3)).max(axis=(-2, -1))
    determinant = np.linalg.det(rotation)
    where = ""
    if np.any(last_row_error > _LAST_ROW_TOLERANCE):
        bad = tuple(np.argwhere(last_row_error > _LAST_ROW_TOLERANCE)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(path, f"{what} is not rigid: its last row is not [0, 0, 0, 1]{where}")
    if np.any(orthonormal_error > tolerance):
        bad = tuple(np.argwhere(orthonormal_error > tolerance)[0])
        where = f" (|R^T R - I| = {orthonormal_error[bad]:.3g})"
        if index_names:
            where = f" (first at {_index_text(bad, index_names)}: |R^T R - I| = {orthonormal_error[bad]:.3g})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part is not orthonormal within {tolerance:g}{where}")
    if np.any(determinant <= 0.0):
        bad = tuple(np.argwhere(determinant <= 0.0)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part has determinant -1, a reflection{where}")


def check_intrinsics(K: np.ndarray, path: Path, what: str, *, width: int | None = None,
                     height: int | None = None) -> None:
    """Check a [3, 3] intrinsic matrix: last row [0, 0, 1], positive focal lengths and, given the image size
    [pixels], focal lengths within :data:`FOCAL_RANGE` times its larger side."""
    if np.abs(K[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-6:
        raise VideoFolderError(path, f"{what} must have the last row [0, 0, 1], got {K[2].tolist()}")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise VideoFolderError(path, f"{what} must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    if width is None or height is None:
        return
    side = max(width, height)
    low, high = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    if not (low <= K[0, 0] <= high and low <= K[1, 1] <= high):
        raise VideoFolderError(
            path, f"{what} has implausible focal lengths fx={K[0, 0]:.6g}, fy={K[1, 1]:.6g} pixels: they must lie "
                  f"within {FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} times the image's larger side ({side} pixels), "
                  f"{low:g} to {high:g}")


def check_fps(value, path: str | os.PathLike, what: str = "'fps'") -> float:
    """``value`` as a frame rate [frames per second]: a number (not a bool) within :data:`FPS_RANGE`."""
    low, high = FPS_RANGE
    if isinstance(value, (np.integer, np.floating)):
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not low <= value <= high:
        raise VideoFolderError(path, f"{what} must be a number of frames per second from {low:g} to {high:g}, "
                                     f"got {value!r:.40}")
    return float(value)


def check_frame_ids(frame_ids: np.ndarray, path: str | os.PathLike, *, increasing: bool) -> np.ndarray:
    """Check frame ids [T]: integers from 0 to :data:`MAX_FRAME_ID` and, with ``increasing``, strictly
    increasing; returns them as int32 (never wrapped)."""
    if not np.issubdtype(frame_ids.dtype, np.integer):
        raise VideoFolderError(path, f"'frame_ids' must be integers, got {frame_ids.dtype}")
    out_of_range = (frame_ids < 0) | (frame_ids > MAX_FRAME_ID)
    if np.any(out_of_range):
        row = int(np.argmax(out_of_range))
        raise VideoFolderError(path, f"'frame_ids' must be integers from 0 to {MAX_FRAME_ID} (int32), got "
                                     f"{int(frame_ids[row])} at row {row}")
    if increasing and np.any(np.diff(frame_ids.astype(np.int64)) <= 0):
        row = int(np.argmax(np.diff(frame_ids.astype(np.int64)) <= 0)) + 1
        raise VideoFolderError(path, f"'frame_ids' must be strictly increasing (unique, in time order); row {row} "
                                     f"has {int(frame_ids[row])} after {int(frame_ids[row - 1])}")
    return frame_ids.astype(np.int32)


def _judge_frames(bad: np.ndarray, frame_ids: np.ndarray, path: Path, problem: str, remedy: str) -> None:
    """Refuse when more than :data:`UNUSABLE_SHARE` of the frames are ``bad`` [T] bool, warn when some are."""
    count, total = int(bad.sum()), len(bad)
    if count == 0:
        return
    text = f"{problem} in {count} of {total} frames (frame ids {listed(f'{int(i):06d}' for i in frame_ids[bad])})"
    if count > UNUSABLE_SHARE * total:
        raise VideoFolderError(path, f"{text}: {remedy}")
    warn_unusual(path, f"{text}; those frames show no subject")


def check_subject_in_view(world_to_cameras: np.ndarray, intrinsics: np.ndarray, joints: np.ndarray, *, width: int,
                          height: int, frame_ids: np.ndarray, path: Path) -> None:
    """Check that each frame's camera sees the subject.

    A frame's subject is *behind* the camera when more than half of its joints have camera-space depth z <= 0,
    and *out of view* when no joint in front of the camera projects inside the image (pixel centres at
    integers, so the image spans -0.5 to W - 0.5). Either, in more than :data:`UNUSABLE_SHARE` of the frames, is
    an error; in fewer, a warning.

    Args:
        world_to_cameras: [T, 4, 4] each frame's extrinsics; intrinsics: [T, 3, 3] its K [pixels].
        joints: [T, J, 3] the posed joints [world units].
        width, height: the image size [pixels].
        frame_ids: [T] the frames' ids, named in the messages.
        path: cameras.json, named in the messages.
    """
    world_to_cameras = np.asarray(world_to_cameras, dtype=np.float64)
    camera_points = np.einsum("tab,tjb->tja", world_to_cameras[:, :3, :3], np.asarray(joints, np.float64)) \
        + world_to_cameras[:, None, :3, 3]
    depth = camera_points[..., 2]
    in_front = depth > 0.0
    behind = (~in_front).sum(axis=1) * 2 > depth.shape[1]
    _judge_frames(behind, frame_ids, path, "the subject is behind the camera (most joints at depth <= 0)",
                  "is 'world_to_camera' a camera-to-world matrix, or the camera turned away from the subject?")
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        pixels = np.einsum("tab,tjb->tja", np.asarray(intrinsics, np.float64), camera_points)
        columns, rows = pixels[..., 0] / pixels[..., 2], pixels[..., 1] / pixels[..., 2]
    inside = in_front & (columns >= -0.5) & (columns <= width - 0.5) & (rows >= -0.5) & (rows <= height - 0.5)
    outside = ~inside.any(axis=1) & ~behind
    _judge_frames(outside, frame_ids, path, f"the subject projects outside the {width}x{height} image (no joint "
                                            "inside it)",
                  "check 'K' (focal lengths, cx, cy) and the translation of 'world_to_camera'")


def check_mask_coverage(masks: np.ndarray, frame_ids: np.ndarray, path: Path, what: str = "masks") -> None:
    """Refuse masks [T, H, W] (0 = background) without foreground in every frame or in more than
    :data:`UNUSABLE_SHARE` of them; warn, naming them, when some frames have none."""
    empty = ~masks.reshape(len(masks), -1).any(axis=1)
    if empty.all():
        raise VideoFolderError(path, f"every one of the {len(masks)} {what} is empty (no foreground pixel): the "
                                     "subject is 255 in 0/255 masks, 1 in 0/1 masks, 65535 in 16-bit ones")
    _judge_frames(empty, frame_ids, path, f"the {what} are empty (no foreground pixel)",
                  "a fit needs the subject's silhouette in most frames")


def read_json(path: Path):
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with open(path, encoding="utf-8") as stream:
            return json.load(stream)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise VideoFolderError(path, f"cannot be read as JSON ({error})") from None
    except RecursionError:
        raise VideoFolderError(path, "cannot be read as JSON (nested too deeply)") from None


def require_mapping(value, path: Path, what: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise VideoFolderError(path, f"{what} must be a JSON object, got {type(value).__name__}")
    return value


def positive_int(value, path: Path, what: str, *, at_most: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value != int(value) or value <= 0:
        raise VideoFolderError(path, f"{what} must be a positive integer, got {value!r}")
    if at_most is not None and value > at_most:
        raise VideoFolderError(path, f"{what} must be at most {at_most}, got {value!r}")
    return int(value)


def listed(items) -> str:
    items = list(items)
    text = ", ".join(str(item) for item in items[:_MAX_LISTED])
    return text + (f" and {len(items) - _MAX_LISTED} more" if len(items) > _MAX_LISTED else "")



def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz archive (no pickles)."""
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, zlib.error, EOFError) as error:
        raise VideoFolderError(path, f"cannot be read as an .npz archive ({error})") from None
