"""Reading, validating and writing warpavatar's input: video folders and subjects (``docs/data.md``).

A *video folder* holds the frames of one camera, their masks, the camera, the skeleton and the per-frame bone
transforms (the layout is in ``/work/shared/FORMAT.md`` and ``docs/data.md``). A *subject* groups a training
video folder with held-out ``novel_view/`` and ``novel_pose/`` folders that share its skeleton and world frame.

Everything read is checked; a problem raises :class:`VideoFolderError` whose message starts with the path of
the offending file and says what is wrong with it. Conventions: cameras follow OpenCV (x right, y down,
z forward; ``K`` puts the centre of pixel (column i, row j) at image coordinates (i, j)); lengths are in world
units (metres in the supplied data); images are RGB ``uint8``; masks ``uint8`` with 255 = subject.

Everything written here (:func:`write_video_folder`, :func:`import_instantavatar`) goes to a temporary name
first and is renamed into place once complete, so an interrupted run never leaves a half-written folder.
"""

from __future__ import annotations

import concurrent.futures
import json
import math
import os
import re
import shutil
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "SKELETON_FORMAT",
    "RIGID_TOLERANCE",
    "VideoFolderError",
    "Skeleton",
    "Camera",
    "VideoFolder",
    "Subject",
    "LazyVideoFolders",
    "load_video_folder",
    "load_subject",
    "write_video_folder",
    "import_instantavatar",
    "demo_subject_path",
]

SKELETON_FORMAT = "warpavatar-skeleton/1"
"""The ``format`` string that skeleton.json must carry."""

RIGID_TOLERANCE = 1e-3
"""Largest entry of ``|R^T R - I|`` accepted for the rotation part of a rigid 4x4 transform."""

_LAST_ROW_TOLERANCE = 1e-5  # how far the last row of a rigid transform may be from [0, 0, 0, 1]
_FRAME_EXTENSIONS = (".png", ".jpg", ".jpeg")
_VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi")
_FRAME_NAME = re.compile(r"^(\d{6,})\.(png|jpg|jpeg)$", re.IGNORECASE)
_MASK_THRESHOLD = 128  # a resized mask pixel is subject (255) when its area average reaches this value
_DEFAULT_FPS = 30.0
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


# ----------------------------------------------------------------------------------------------------------
# Small validation helpers: each raises VideoFolderError naming ``path``.


def _float_array(value, shape: tuple[int, ...], path: Path, what: str) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise VideoFolderError(path, f"{what} must be numbers of shape {list(shape)}, got {value!r:.80}") from None
    if array.shape != shape:
        raise VideoFolderError(path, f"{what} must have shape {list(shape)}, got {list(array.shape)}")
    if not np.all(np.isfinite(array)):
        raise VideoFolderError(path, f"{what} holds non-finite values (nan or inf)")
    return array


def _index_text(index: tuple[int, ...], names: tuple[str, ...]) -> str:
    return ", ".join(f"{name} {value}" for name, value in zip(names, index))


def _check_rigid(matrices: np.ndarray, path: Path, what: str, index_names: tuple[str, ...] = ()) -> None:
    """Check that ``matrices[..., 4, 4]`` are finite rigid transforms (rotation + translation)."""
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
    if np.any(orthonormal_error > RIGID_TOLERANCE):
        bad = tuple(np.argwhere(orthonormal_error > RIGID_TOLERANCE)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)}: |R^T R - I| = {orthonormal_error[bad]:.3g})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part is not orthonormal within {RIGID_TOLERANCE}{where}")
    if np.any(determinant <= 0.0):
        bad = tuple(np.argwhere(determinant <= 0.0)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part has determinant -1, a reflection{where}")


def _check_intrinsics(K: np.ndarray, path: Path, what: str) -> None:
    if np.abs(K[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-6:
        raise VideoFolderError(path, f"{what} must have the last row [0, 0, 1], got {K[2].tolist()}")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise VideoFolderError(path, f"{what} must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")


def _read_json(path: Path):
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with open(path, encoding="utf-8") as stream:
            return json.load(stream)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise VideoFolderError(path, f"cannot be read as JSON ({error})") from None


def _require_mapping(value, path: Path, what: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise VideoFolderError(path, f"{what} must be a JSON object, got {type(value).__name__}")
    return value


def _positive_int(value, path: Path, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) or value <= 0:
        raise VideoFolderError(path, f"{what} must be a positive integer, got {value!r}")
    return int(value)


def _listed(items) -> str:
    items = list(items)
    text = ", ".join(str(item) for item in items[:_MAX_LISTED])
    return text + (f" and {len(items) - _MAX_LISTED} more" if len(items) > _MAX_LISTED else "")


# ----------------------------------------------------------------------------------------------------------
# Skeleton


@dataclass
class Skeleton:
    """A skeleton in its rest (canonical) pose, in world coordinates.

    Attributes:
        names: joint names, unique, length ``joint_count``.
        parents: parent joint of each joint, shape [joint_count], int32; -1 marks a root.
        heads: rest-pose pivot of each joint [world units], shape [joint_count, 3], float32.
        tails: rest-pose end of each joint's bone [world units], shape [joint_count, 3], float32.
        up: the world's up direction, shape [3], float32 (``[0, 0, 1]`` in the supplied data).
    """

    names: list[str]
    parents: np.ndarray
    heads: np.ndarray
    tails: np.ndarray
    up: np.ndarray

    def __post_init__(self):
        self.names = [str(name) for name in self.names]
        self.parents = np.asarray(self.parents, dtype=np.int32).reshape(-1)
        self.heads = np.asarray(self.heads, dtype=np.float32)
        self.tails = np.asarray(self.tails, dtype=np.float32)
        self.up = np.asarray(self.up, dtype=np.float32).reshape(-1)
        joint_count = len(self.names)
        if self.parents.shape != (joint_count,):
            raise ValueError(f"Skeleton: parents must have shape [{joint_count}], got {list(self.parents.shape)}")
        for label, array in (("heads", self.heads), ("tails", self.tails)):
            if array.shape != (joint_count, 3):
                raise ValueError(f"Skeleton: {label} must have shape [{joint_count}, 3], got {list(array.shape)}")
        if self.up.shape != (3,):
            raise ValueError(f"Skeleton: up must have shape [3], got {list(self.up.shape)}")

    @property
    def joint_count(self) -> int:
        """Number of joints J."""
        return len(self.names)

    def to_json_dict(self) -> dict:
        """The skeleton as the JSON object of skeleton.json (``format`` warpavatar-skeleton/1)."""
        return {
            "format": SKELETON_FORMAT,
            "up": [float(value) for value in self.up],
            "joints": [
                {
                    "name": name,
                    "parent": int(parent),
                    "head": [float(value) for value in head],
                    "tail": [float(value) for value in tail],
                }
                for name, parent, head, tail in zip(self.names, self.parents, self.heads, self.tails)
            ],
        }

    @classmethod
    def from_json_dict(cls, d: Mapping, *, source: str | os.PathLike = "<skeleton.json>") -> Skeleton:
        """Build and validate a skeleton from the JSON object of skeleton.json.

        Args:
            d: the parsed JSON object.
            source: the file it came from, named in error messages.

        Raises:
            VideoFolderError: wrong ``format`` string, missing or malformed joints, duplicate names, non-finite
                values, or parents that do not form a forest (an index out of range, a cycle, no root).
        """
        path = Path(source)
        d = _require_mapping(d, path, "the skeleton")
        if d.get("format") != SKELETON_FORMAT:
            raise VideoFolderError(path, f"'format' must be {SKELETON_FORMAT!r}, got {d.get('format')!r}")
        joints = d.get("joints")
        if not isinstance(joints, list) or not joints:
            raise VideoFolderError(path, "'joints' must be a non-empty list")
        up = _float_array(d.get("up", [0.0, 0.0, 1.0]), (3,), path, "'up'")
        if np.linalg.norm(up) == 0.0:
            raise VideoFolderError(path, "'up' must not be the zero vector")
        names, parents, heads, tails = [], [], [], []
        for index, joint in enumerate(joints):
            joint = _require_mapping(joint, path, f"joint {index}")
            for key in ("name", "parent", "head", "tail"):
                if key not in joint:
                    raise VideoFolderError(path, f"joint {index} has no {key!r}")
            if not isinstance(joint["name"], str) or not joint["name"]:
                raise VideoFolderError(path, f"joint {index}: 'name' must be a non-empty string")
            parent = joint["parent"]
            if isinstance(parent, bool) or not isinstance(parent, int):
                raise VideoFolderError(path, f"joint {index} ({joint['name']}): 'parent' must be an integer")
            names.append(joint["name"])
            parents.append(parent)
            heads.append(_float_array(joint["head"], (3,), path, f"joint {index} ({joint['name']}) 'head'"))
            tails.append(_float_array(joint["tail"], (3,), path, f"joint {index} ({joint['name']}) 'tail'"))
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise VideoFolderError(path, f"joint names must be unique; repeated: {_listed(duplicates)}")
        _check_parents(np.asarray(parents, dtype=np.int64), names, path)
        return cls(names=names, parents=np.asarray(parents, dtype=np.int32), heads=np.stack(heads),
                   tails=np.stack(tails), up=up)


def _check_parents(parents: np.ndarray, names: list[str], path: Path) -> None:
    """Parents must index existing joints (-1 for a root) and form a forest with at least one root."""
    joint_count = len(parents)
    for index, parent in enumerate(parents):
        if parent < -1 or parent >= joint_count:
            raise VideoFolderError(
                path, f"joint {index} ({names[index]}) has parent {parent}, outside -1..{joint_count - 1}: not a tree")
    if not np.any(parents == -1):
        raise VideoFolderError(path, "no joint has parent -1: the skeleton has no root (parents form a cycle)")
    # Follow each joint's chain of parents up to a joint already known to reach a root; meeting a joint of
    # the current chain again means the chain loops.
    settled = parents == -1
    for start in range(joint_count):
        chain, on_chain, joint = [], set(), start
        while not settled[joint]:
            if joint in on_chain:
                cycle = chain[chain.index(joint):]
                raise VideoFolderError(path, f"the parents of joint {start} ({names[start]}) form a cycle through "
                                             f"{_listed(names[j] for j in cycle)}: not a tree")
            chain.append(joint)
            on_chain.add(joint)
            joint = int(parents[joint])
        settled[chain] = True


# ----------------------------------------------------------------------------------------------------------
# Camera


@dataclass
class Camera:
    """A pinhole camera in OpenCV convention (x right, y down, z forward).

    Attributes:
        K: intrinsics [pixels], shape [3, 3], float32; the centre of pixel (column i, row j) is at image
            coordinates (i, j), so the image centre is ((width - 1) / 2, (height - 1) / 2).
        world_to_camera: rigid transform from world to camera coordinates [world units], shape [4, 4], float32.
        width: image width [pixels].
        height: image height [pixels].
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float32)
        self.world_to_camera = np.asarray(self.world_to_camera, dtype=np.float32)
        if self.K.shape != (3, 3):
            raise ValueError(f"Camera: K must have shape [3, 3], got {list(self.K.shape)}")
        if self.world_to_camera.shape != (4, 4):
            raise ValueError(
                f"Camera: world_to_camera must have shape [4, 4], got {list(self.world_to_camera.shape)}")
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera: width and height must be positive, got {self.width}x{self.height}")

    @property
    def camera_to_world(self) -> np.ndarray:
        """Inverse of ``world_to_camera``, shape [4, 4], float32 (its last column is the camera centre)."""
        rotation = self.world_to_camera[:3, :3].astype(np.float64)
        translation = self.world_to_camera[:3, 3].astype(np.float64)
        inverse = np.eye(4)
        inverse[:3, :3] = rotation.T
        inverse[:3, 3] = -rotation.T @ translation
        return inverse.astype(np.float32)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points into the image.

        Args:
            points: world positions [world units], shape [..., 3].

        Returns:
            ``(pixels, depth)``: image coordinates (column, row) [pixels], shape [..., 2], float64, with pixel
            centres at integers; and camera-space depth z [world units], shape [...], float64.
        """
        points = np.asarray(points, dtype=np.float64)
        world_to_camera = self.world_to_camera.astype(np.float64)
        camera_points = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        depth = camera_points[..., 2]
        homogeneous = camera_points @ self.K.astype(np.float64).T
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = homogeneous[..., :2] / homogeneous[..., 2:3]
        return pixels, depth

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for the image resampled to ``width`` x ``height`` pixels.

        The image is stretched by ``sx = width / self.width`` and ``sy = height / self.height``; with pixel
        centres at integer coordinates a point at column u moves to ``(u + 0.5) * sx - 0.5`` (likewise rows),
        so ``fx' = fx sx``, ``cx' = (cx + 0.5) sx - 0.5``.
        """
        scale_x = width / self.width
        scale_y = height / self.height
        resample = np.array([[scale_x, 0.0, 0.5 * scale_x - 0.5],
                             [0.0, scale_y, 0.5 * scale_y - 0.5],
                             [0.0, 0.0, 1.0]])
        return Camera(K=resample @ self.K.astype(np.float64), world_to_camera=self.world_to_camera.copy(),
                      width=width, height=height)

    def cropped(self, left: int, top: int, width: int, height: int) -> Camera:
        """The same camera for the crop of ``width`` x ``height`` pixels whose top-left pixel is (left, top)."""
        K = self.K.astype(np.float64).copy()
        K[0, 2] -= left
        K[1, 2] -= top
        return Camera(K=K, world_to_camera=self.world_to_camera.copy(), width=width, height=height)

    def to_json_dict(self) -> dict:
        """``{"width", "height", "K", "world_to_camera"}`` as in cameras.json."""
        return {"width": self.width, "height": self.height, "K": self.K.astype(np.float64).tolist(),
                "world_to_camera": self.world_to_camera.astype(np.float64).tolist()}


# ----------------------------------------------------------------------------------------------------------
# Video folder


@dataclass
class VideoFolder:
    """One camera's frames of a subject, with everything needed to pose its skeleton in them.

    Attributes:
        root: the folder it was read from.
        frame_ids: the frame id of each frame, shape [T], int32, strictly increasing.
        images: RGB frames, shape [T, H, W, 3], uint8.
        masks: foreground masks (255 = subject, 0 = background), shape [T, H, W], uint8, or None.
        cameras: the camera of each frame, length T; a fixed camera is one object repeated.
        skeleton: the rest-pose skeleton (J joints).
        bone_transforms: per-frame rest-to-posed rigid transform of each joint, shape [T, J, 4, 4], float32;
            a point x attached to joint j in the rest pose is at ``bone_transforms[t, j] @ [x, 1]`` in frame t.
        joint_positions: posed joint heads [world units], shape [T, J, 3], float32, or None.
        background: colour the frames were rendered over, RGB in 0..1, shape [3], float32 (black by default).
        fps: frames per second of the original video (the time between rows t and t+1 is
            ``(frame_ids[t+1] - frame_ids[t]) / fps`` seconds).
        meta: the whole meta.json object ({} when the folder has none).
    """

    root: Path
    frame_ids: np.ndarray
    images: np.ndarray
    masks: np.ndarray | None
    cameras: list[Camera]
    skeleton: Skeleton
    bone_transforms: np.ndarray
    joint_positions: np.ndarray | None
    background: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.float32))
    fps: float = _DEFAULT_FPS
    meta: dict = field(default_factory=dict)

    @property
    def frame_count(self) -> int:
        """Number of frames T."""
        return int(self.frame_ids.shape[0])

    @property
    def height(self) -> int:
        """Image height H [pixels]."""
        return int(self.images.shape[1]) if self.images.ndim == 4 else int(self.cameras[0].height)

    @property
    def width(self) -> int:
        """Image width W [pixels]."""
        return int(self.images.shape[2]) if self.images.ndim == 4 else int(self.cameras[0].width)

    @property
    def fixed_camera(self) -> bool:
        """True when every frame is seen by the same camera object."""
        return all(camera is self.cameras[0] for camera in self.cameras)

    @property
    def intrinsics(self) -> np.ndarray:
        """``K`` of every frame, shape [T, 3, 3], float32."""
        return np.stack([camera.K for camera in self.cameras]) if self.cameras else np.zeros((0, 3, 3), np.float32)

    @property
    def world_to_cameras(self) -> np.ndarray:
        """``world_to_camera`` of every frame, shape [T, 4, 4], float32."""
        if not self.cameras:
            return np.zeros((0, 4, 4), np.float32)
        return np.stack([camera.world_to_camera for camera in self.cameras])


def _list_frame_files(folder: Path) -> dict[int, Path]:
    """Map frame id -> file for the images named ``<6-digit id>.png|jpg|jpeg`` in ``folder``."""
    files: dict[int, Path] = {}
    badly_named = []
    for entry in sorted(os.scandir(folder), key=lambda item: item.name):
        if not entry.is_file() or not entry.name.lower().endswith(_FRAME_EXTENSIONS):
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
                                       f"found {_listed(badly_named)}")
    return files


def _check_frame_files(files: dict[int, Path], frame_ids: np.ndarray, folder: Path, poses_path: Path,
                       what: str) -> None:
    """Every pose row needs a file, and every file a pose row."""
    missing = [int(frame_id) for frame_id in frame_ids if int(frame_id) not in files]
    if missing:
        names = [f"{frame_id:06d}" for frame_id in missing]
        raise VideoFolderError(folder, f"{len(missing)} {what} missing for frame ids listed in {poses_path.name} "
                                       f"(ids {_listed(names)})")
    if len(files) != len(frame_ids):
        extra = sorted(set(files) - {int(frame_id) for frame_id in frame_ids})
        raise VideoFolderError(
            poses_path, f"frame count mismatch: {poses_path.name} has {len(frame_ids)} frames but {folder} holds "
                        f"{len(files)} {what} (ids without a pose: {_listed(f'{i:06d}' for i in extra)})")


def _find_video_file(root: Path) -> Path | None:
    preferred = root / "video.mp4"
    if preferred.is_file():
        return preferred
    candidates = sorted(path for path in root.iterdir()
                        if path.is_file() and path.suffix.lower() in _VIDEO_EXTENSIONS)
    if len(candidates) > 1:
        names = _listed(candidate.name for candidate in candidates)
        raise VideoFolderError(root, f"several video files and no video.mp4 to choose: {names}")
    return candidates[0] if candidates else None


def _read_poses(path: Path, joint_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise VideoFolderError(path, f"cannot be read as an .npz archive ({error})") from None
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
    _check_rigid(bone_transforms, path, "'bone_transforms'", ("frame row", "joint"))
    frame_ids = arrays["frame_ids"]
    if not np.issubdtype(frame_ids.dtype, np.integer):
        raise VideoFolderError(path, f"'frame_ids' must be integers, got {frame_ids.dtype}")
    if frame_ids.shape != (frame_count,):
        raise VideoFolderError(path, f"frame count mismatch: 'frame_ids' has shape {list(frame_ids.shape)} but "
                                     f"'bone_transforms' has {frame_count} frames")
    if np.any(frame_ids < 0) or np.any(frame_ids > np.iinfo(np.int32).max):
        raise VideoFolderError(path, "'frame_ids' must be non-negative int32 values")
    if np.any(np.diff(frame_ids) <= 0):
        raise VideoFolderError(path, "'frame_ids' must be strictly increasing (unique, in time order)")
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
    K = _float_array(entry.get("K", fallback.get("K")), (3, 3), path, f"{what} 'K'")
    _check_intrinsics(K, path, f"{what} 'K'")
    world_to_camera = _float_array(entry.get("world_to_camera", fallback.get("world_to_camera")), (4, 4), path,
                                   f"{what} 'world_to_camera'")
    _check_rigid(world_to_camera, path, f"{what} 'world_to_camera'")
    return Camera(K=K, world_to_camera=world_to_camera, width=width, height=height)


def _read_cameras(path: Path, frame_count: int) -> list[Camera]:
    """Cameras of all T pose rows: one object repeated for a fixed camera."""
    data = _require_mapping(_read_json(path), path, "cameras.json")
    for key in ("width", "height"):
        if key not in data:
            raise VideoFolderError(path, f"has no {key!r}")
    width = _positive_int(data["width"], path, "'width'")
    height = _positive_int(data["height"], path, "'height'")
    frames = data.get("frames")
    if frames is None:
        camera = _camera_from_json(data, width, height, {}, path, "the camera")
        return [camera] * frame_count
    if not isinstance(frames, list):
        raise VideoFolderError(path, f"'frames' must be null or a list, got {type(frames).__name__}")
    if len(frames) != frame_count:
        raise VideoFolderError(path, f"per-frame camera count mismatch: 'frames' has {len(frames)} entries but "
                                     f"poses.npz has {frame_count} frames")
    return [_camera_from_json(_require_mapping(entry, path, f"frames[{index}]"), width, height, data, path,
                              f"frames[{index}]")
            for index, entry in enumerate(frames)]


def _read_meta(path: Path) -> tuple[dict, np.ndarray, float]:
    if not path.exists():
        return {}, np.zeros(3, dtype=np.float32), _DEFAULT_FPS
    meta = dict(_require_mapping(_read_json(path), path, "meta.json"))
    fps = meta.get("fps", _DEFAULT_FPS)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise VideoFolderError(path, f"'fps' must be a positive finite number, got {fps!r}")
    background = meta.get("background")
    if background is None:
        background = np.zeros(3)
    else:
        background = _float_array(background, (3,), path, "'background'")
        if np.any(background < 0.0) or np.any(background > 1.0):
            raise VideoFolderError(path, f"'background' must be RGB in 0..1, got {background.tolist()}")
    return meta, background.astype(np.float32), float(fps)


def _read_skeleton(path: Path) -> Skeleton:
    return Skeleton.from_json_dict(_read_json(path), source=path)


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


def _read_frame_file(path: Path, width: int, height: int, out_width: int, out_height: int) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise VideoFolderError(path, "cannot be read as an image (unreadable or corrupt)")
    if image.shape[:2] != (height, width):
        raise VideoFolderError(path, f"image size mismatch: the frame is {image.shape[1]}x{image.shape[0]} "
                                     f"but cameras.json says {width}x{height}")
    return _resize_image(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), out_width, out_height)


def _read_mask_file(path: Path, width: int, height: int, out_width: int, out_height: int) -> np.ndarray:
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise VideoFolderError(path, "cannot be read as an image (unreadable or corrupt)")
    if mask.dtype != np.uint8:
        raise VideoFolderError(path, f"masks must be 8-bit, got {mask.dtype}")
    if mask.ndim == 3:
        if mask.shape[2] in (3, 4) and np.array_equal(mask[..., 0], mask[..., 1]) \
                and np.array_equal(mask[..., 0], mask[..., 2]):
            mask = mask[..., 0]  # a grey mask saved as colour
        else:
            raise VideoFolderError(path, f"masks must be single-channel, got {mask.shape[2]} channels")
    if mask.shape != (height, width):
        raise VideoFolderError(path, f"image size mismatch: the mask is {mask.shape[1]}x{mask.shape[0]} "
                                     f"but the frames are {width}x{height}")
    return _resize_mask(mask, out_width, out_height)


def _read_into(output: np.ndarray, function, paths: list[Path], *args) -> np.ndarray:
    """``output[i] = function(paths[i], *args)``, decoded on a few threads (OpenCV releases the GIL)."""
    def read(index: int) -> None:
        output[index] = function(paths[index], *args)

    if len(paths) < 4:
        for index in range(len(paths)):
            read(index)
        return output
    workers = min(8, os.cpu_count() or 1, len(paths))
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
        for _ in pool.map(read, range(len(paths))):  # re-raises the first error
            pass
    return output


def _read_video_frames(path: Path, frame_ids: np.ndarray, width: int, height: int, out_width: int,
                       out_height: int) -> np.ndarray:
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
        VideoFolderError: a missing or invalid file (the message names it), see ``docs/data.md``.
        TypeError, ValueError: bad ``max_frames``, ``frame_stride`` or ``scale``.
    """
    _check_selection(max_frames, frame_stride, scale)
    root = Path(path)
    if not root.is_dir():
        raise VideoFolderError(root, "no such video folder")
    skeleton = _read_skeleton(root / "skeleton.json")
    poses_path = root / "poses.npz"
    bone_transforms, frame_ids, joint_positions = _read_poses(poses_path, skeleton.joint_count)
    cameras = _read_cameras(root / "cameras.json", len(frame_ids))
    meta, background, fps = _read_meta(root / "meta.json")

    frames_dir = root / "frames"
    video_path = None
    if frames_dir.is_dir():
        frame_files = _list_frame_files(frames_dir)
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
        images = _read_into(np.empty((len(paths), out_height, out_width, 3), np.uint8), _read_frame_file, paths,
                            width, height, out_width, out_height)
    else:
        images = _read_video_frames(video_path, frame_ids, width, height, out_width, out_height)
    masks = None
    if mask_files is not None:
        paths = [mask_files[int(frame_id)] for frame_id in frame_ids]
        masks = _read_into(np.empty((len(paths), out_height, out_width), np.uint8), _read_mask_file, paths,
                           width, height, out_width, out_height)

    return VideoFolder(root=root, frame_ids=frame_ids, images=images, masks=masks, cameras=kept_cameras,
                       skeleton=skeleton, bone_transforms=bone_transforms, joint_positions=joint_positions,
                       background=background, fps=fps, meta=meta)


# ----------------------------------------------------------------------------------------------------------
# Subject


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


@dataclass
class Subject:
    """A benchmark subject: a training video and held-out video folders sharing one skeleton and world frame.

    Attributes:
        root: the subject folder.
        train: the training video folder (read eagerly).
        novel_view: held-out folders of other cameras, by folder name; read lazily on first access.
        novel_pose: held-out folders of other motions, by folder name; read lazily on first access.
        license_text: contents of LICENSE.txt, or None when there is none.
    """

    root: Path
    train: VideoFolder
    novel_view: Mapping[str, VideoFolder]
    novel_pose: Mapping[str, VideoFolder]
    license_text: str | None


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
    return Path(__file__).resolve().parent / "data" / "demo" / "robot"


# ----------------------------------------------------------------------------------------------------------
# Writing


def _json_text(value) -> str:
    return json.dumps(value, indent=1) + "\n"


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f"{path}: cannot be written")


def _cameras_json(cameras: list[Camera]) -> dict:
    first = cameras[0]
    fixed = all(camera is first or (np.array_equal(camera.K, first.K) and
                                    np.array_equal(camera.world_to_camera, first.world_to_camera))
                for camera in cameras)
    data = first.to_json_dict()
    data["frames"] = None if fixed else [
        {"K": camera.K.astype(np.float64).tolist(),
         "world_to_camera": camera.world_to_camera.astype(np.float64).tolist()} for camera in cameras]
    return data


def _save_npz(path: Path, **arrays) -> None:
    with open(path, "wb") as stream:
        np.savez_compressed(stream, **arrays)


def _commit_folder(tmp: Path, destination: Path) -> None:
    """Rename the finished ``tmp`` folder to ``destination`` (replacing it when ``overwrite``)."""
    if destination.exists():
        old = destination.with_name(destination.name + ".old")
        if old.exists():
            shutil.rmtree(old)
        destination.rename(old)
        tmp.rename(destination)
        shutil.rmtree(old)
    else:
        tmp.rename(destination)


def _fresh_tmp(destination: Path, overwrite: bool) -> Path:
    if destination.exists() and not overwrite:
        raise FileExistsError(f"{destination} already exists (pass overwrite=True to replace it)")
    tmp = destination.with_name(destination.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)  # left over from an interrupted run
    destination.parent.mkdir(parents=True, exist_ok=True)
    tmp.mkdir()
    return tmp


def write_video_folder(video: VideoFolder, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write ``video`` as a video folder (PNG frames and masks, JSON and .npz files).

    The folder is written under ``<path>.tmp`` and renamed to ``path`` once complete. ``meta.json`` receives
    ``video.meta`` with ``fps`` and ``background`` updated from the fields.

    Args:
        video: what to write; its ``cameras`` become a fixed camera when they are all equal.
        path: the folder to create.
        overwrite: replace an existing folder instead of raising FileExistsError.

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
    tmp = _fresh_tmp(destination, overwrite)
    try:
        (tmp / "frames").mkdir()
        for frame_id, image in zip(video.frame_ids, video.images):
            _write_png(tmp / "frames" / f"{int(frame_id):06d}.png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        if video.masks is not None:
            (tmp / "masks").mkdir()
            for frame_id, mask in zip(video.frame_ids, video.masks):
                _write_png(tmp / "masks" / f"{int(frame_id):06d}.png", mask)
        (tmp / "cameras.json").write_text(_json_text(_cameras_json(video.cameras)), encoding="utf-8")
        (tmp / "skeleton.json").write_text(_json_text(video.skeleton.to_json_dict()), encoding="utf-8")
        arrays = {"bone_transforms": video.bone_transforms.astype(np.float32),
                  "frame_ids": video.frame_ids.astype(np.int32)}
        if video.joint_positions is not None:
            arrays["joint_positions"] = video.joint_positions.astype(np.float32)
        _save_npz(tmp / "poses.npz", **arrays)
        meta = dict(video.meta)
        meta["fps"] = float(video.fps)
        meta["background"] = [float(value) for value in video.background]
        (tmp / "meta.json").write_text(_json_text(meta), encoding="utf-8")
        _commit_folder(tmp, destination)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return destination


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
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise VideoFolderError(path, "cannot be read as an image (unreadable or corrupt)")
    if mask.ndim == 3:
        mask = mask[..., 0]
    if mask.dtype != np.uint8:
        raise VideoFolderError(path, f"masks must be 8-bit, got {mask.dtype}")
    return mask


def import_instantavatar(src_folder: str | os.PathLike, dst_folder: str | os.PathLike, *,
                         skeleton_json: str | os.PathLike, bone_transforms_npz: str | os.PathLike,
                         fps: float = _DEFAULT_FPS, overwrite: bool = False) -> Path:
    """Convert an InstantAvatar / GART-style sequence into a warpavatar video folder.

    Source layout: ``images/*.png|jpg`` (frames in sorted file-name order), optional ``masks/*.png|npy``
    (same count and order), and ``cameras.npz`` with ``intrinsic`` [3, 3], ``extrinsic`` [4, 4]
    (world-to-camera, OpenCV), ``height`` and ``width``. SMPL parameters are not used: the poses come from
    ``bone_transforms_npz`` (``bone_transforms`` [T, J, 4, 4], optional ``frame_ids`` [T] and
    ``joint_positions`` [T, J, 3]; row t belongs to the t-th image; without ``frame_ids`` the frames are
    numbered 0..T-1) for the skeleton in ``skeleton_json`` (warpavatar-skeleton/1).

    The folder is written under ``<dst_folder>.tmp``, validated with :func:`load_video_folder` and renamed.

    Args:
        src_folder: the InstantAvatar-style folder.
        dst_folder: the video folder to create.
        skeleton_json: the skeleton.json to copy (validated).
        bone_transforms_npz: the per-frame bone transforms.
        fps: frame rate written to meta.json.
        overwrite: replace an existing ``dst_folder`` instead of raising FileExistsError.

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
    image_paths = _sorted_files(images_dir, _FRAME_EXTENSIONS)
    if not image_paths:
        raise VideoFolderError(images_dir, "holds no .png or .jpg images")
    mask_paths = None
    if (src / "masks").is_dir():
        mask_paths = _sorted_files(src / "masks", (".png", ".npy"))
        if len(mask_paths) != len(image_paths):
            raise VideoFolderError(src / "masks", f"mask count mismatch: {len(mask_paths)} masks for "
                                                  f"{len(image_paths)} images in {images_dir}")

    cameras_path = src / "cameras.npz"
    if not cameras_path.is_file():
        raise VideoFolderError(cameras_path, "file is missing")
    try:
        with np.load(cameras_path, allow_pickle=False) as archive:
            camera_arrays = {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise VideoFolderError(cameras_path, f"cannot be read as an .npz archive ({error})") from None
    for key in ("intrinsic", "extrinsic", "height", "width"):
        if key not in camera_arrays:
            raise VideoFolderError(cameras_path, f"has no {key!r} array (keys: {sorted(camera_arrays)})")
    K = _float_array(camera_arrays["intrinsic"], (3, 3), cameras_path, "'intrinsic'")
    _check_intrinsics(K, cameras_path, "'intrinsic'")
    world_to_camera = _float_array(camera_arrays["extrinsic"], (4, 4), cameras_path, "'extrinsic'")
    _check_rigid(world_to_camera, cameras_path, "'extrinsic'")
    width = _positive_int(np.asarray(camera_arrays["width"]).reshape(-1)[0].item(), cameras_path, "'width'")
    height = _positive_int(np.asarray(camera_arrays["height"]).reshape(-1)[0].item(), cameras_path, "'height'")

    skeleton = _read_skeleton(skeleton_path)
    if not poses_path.is_file():
        raise VideoFolderError(poses_path, "file is missing")
    try:
        with np.load(poses_path, allow_pickle=False) as archive:
            pose_arrays = {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise VideoFolderError(poses_path, f"cannot be read as an .npz archive ({error})") from None
    if "bone_transforms" not in pose_arrays:
        raise VideoFolderError(poses_path, f"has no 'bone_transforms' array (keys: {sorted(pose_arrays)})")
    frame_count = pose_arrays["bone_transforms"].shape[0] if pose_arrays["bone_transforms"].ndim else 0
    if frame_count != len(image_paths):
        raise VideoFolderError(poses_path, f"frame count mismatch: {frame_count} pose rows for "
                                           f"{len(image_paths)} images in {images_dir}")
    pose_arrays.setdefault("frame_ids", np.arange(frame_count, dtype=np.int32))

    tmp = _fresh_tmp(destination, overwrite)
    try:
        (tmp / "frames").mkdir()
        for frame_id, image_path in zip(pose_arrays["frame_ids"], image_paths):
            image = cv2.imread(str(image_path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            if image is None:
                raise VideoFolderError(image_path, "cannot be read as an image (unreadable or corrupt)")
            if image.shape[:2] != (height, width):
                raise VideoFolderError(image_path, f"image size mismatch: the image is {image.shape[1]}x"
                                                   f"{image.shape[0]} but cameras.npz says {width}x{height}")
            _write_png(tmp / "frames" / f"{int(frame_id):06d}.png", image)
        if mask_paths is not None:
            (tmp / "masks").mkdir()
            for frame_id, mask_path in zip(pose_arrays["frame_ids"], mask_paths):
                mask = _instantavatar_mask(mask_path)
                if mask.shape != (height, width):
                    raise VideoFolderError(mask_path, f"image size mismatch: the mask is {mask.shape[1]}x"
                                                      f"{mask.shape[0]} but the images are {width}x{height}")
                _write_png(tmp / "masks" / f"{int(frame_id):06d}.png", mask)
        camera = Camera(K=K, world_to_camera=world_to_camera, width=width, height=height)
        (tmp / "cameras.json").write_text(_json_text(_cameras_json([camera])), encoding="utf-8")
        (tmp / "skeleton.json").write_text(_json_text(skeleton.to_json_dict()), encoding="utf-8")
        keep = {key: pose_arrays[key] for key in ("bone_transforms", "frame_ids", "joint_positions")
                if key in pose_arrays}
        _save_npz(tmp / "poses.npz", **keep)
        meta = {"fps": float(fps), "source": f"imported from the InstantAvatar-style folder {src.name}"}
        (tmp / "meta.json").write_text(_json_text(meta), encoding="utf-8")
        try:
            load_video_folder(tmp, max_frames=1)  # checks poses, skeleton, cameras and the file listing
        except VideoFolderError as error:
            # Name the user's file rather than the temporary copy.
            source = {"poses.npz": poses_path, "skeleton.json": skeleton_path}.get(error.path.name, error.path)
            raise VideoFolderError(source, error.problem) from None
        _commit_folder(tmp, destination)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return destination
