"""The types of warpavatar's input: a skeleton, a camera, a video folder and a subject.

Conventions: cameras follow OpenCV (x right, y down, z forward; ``K`` puts the centre of pixel (column i, row j)
at image coordinates (i, j)); lengths are in world units (metres in the supplied data); images are RGB
``uint8``; masks ``uint8`` with 255 = subject.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from warpavatar.data.checks import VideoFolderError, float_array, listed, require_mapping

__all__ = ["SKELETON_FORMAT", "MAX_JOINT_DEPTH", "DEFAULT_FPS", "ESTIMATED_POSES", "POSE_SOURCES", "Skeleton", "Camera", "VideoFolder",
           "Subject"]


SKELETON_FORMAT = "warpavatar-skeleton/1"
"""The ``format`` string that skeleton.json must carry."""

MAX_JOINT_DEPTH = 128
"""The most joints on a path from a root to a leaf that skeleton.json and BVH files may have: a body with its
fingers is about a dozen deep, so a deeper chain is a broken hierarchy (every joint the child of the last)."""

DEFAULT_FPS = 30.0
"""Frames per second of a folder whose meta.json does not say."""

ESTIMATED_POSES = "estimated"
"""meta.json's ``"poses"`` of a folder whose poses were estimated from its images (``warpavatar-prepare``): not
exact, so a fit refines them (``--refine-poses auto``)."""

POSE_SOURCES = ("exact", ESTIMATED_POSES)
"""The values meta.json's ``"poses"`` may take; a folder that does not say has exact poses (rendered, captured)."""


@dataclass
class Skeleton:
    """A skeleton in its rest (canonical) pose, in world coordinates.

    Attributes:
        names: joint names, unique, length ``joint_count``.
        parents: parent joint of each joint, shape [joint_count], int32; -1 marks a root.
        heads: rest-pose pivot of each joint [world units], shape [joint_count, 3], of ``dtype``.
        tails: rest-pose end of each joint's bone [world units], shape [joint_count, 3], of ``dtype``.
        up: the world's up direction, shape [3], of ``dtype`` (``[0, 0, 1]``, the default, in the supplied data).
        dtype: the precision of the coordinates: float32 (as files are read), or float64 where a computation
            needs it (``warpavatar-prepare``'s skeleton fit).
    """

    names: list[str]
    parents: np.ndarray
    heads: np.ndarray
    tails: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    dtype: type = field(default=np.float32, repr=False, compare=False)

    def __post_init__(self):
        if self.dtype not in (np.float32, np.float64):
            raise ValueError(f"Skeleton: dtype must be numpy.float32 or numpy.float64, got {self.dtype!r}")
        self.names = [str(name) for name in self.names]
        self.parents = np.asarray(self.parents, dtype=np.int32).reshape(-1)
        self.heads = np.asarray(self.heads, dtype=self.dtype)
        self.tails = np.asarray(self.tails, dtype=self.dtype)
        self.up = np.asarray(self.up, dtype=self.dtype).reshape(-1)
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

    def to_json_dict(self, *, decimals: int | None = None) -> dict:
        """The skeleton as the JSON object of skeleton.json (``format`` warpavatar-skeleton/1).

        Args:
            decimals: round coordinates to this many decimals (None: as stored).
        """

        def numbers(values) -> list[float]:
            return [float(value) if decimals is None else round(float(value), decimals) for value in values]

        return {
            "format": SKELETON_FORMAT,
            "up": [float(value) for value in self.up],
            "joints": [
                {"name": name, "parent": int(parent), "head": numbers(head), "tail": numbers(tail)}
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
        d = require_mapping(d, path, "the skeleton")
        if d.get("format") != SKELETON_FORMAT:
            raise VideoFolderError(path, f"'format' must be {SKELETON_FORMAT!r}, got {d.get('format')!r}")
        joints = d.get("joints")
        if not isinstance(joints, list) or not joints:
            raise VideoFolderError(path, "'joints' must be a non-empty list")
        up = float_array(d.get("up", [0.0, 0.0, 1.0]), (3,), path, "'up'")
        if np.linalg.norm(up) == 0.0:
            raise VideoFolderError(path, "'up' must not be the zero vector")
        names, parents, heads, tails = [], [], [], []
        for index, joint in enumerate(joints):
            joint = require_mapping(joint, path, f"joint {index}")
            for key in ("name", "parent", "head", "tail"):
                if key not in joint:
                    raise VideoFolderError(path, f"joint {index} has no {key!r}")
            if not isinstance(joint["name"], str) or not joint["name"]:
                raise VideoFolderError(path, f"joint {index}: 'name' must be a non-empty string")
            parent = joint["parent"]
            if isinstance(parent, bool) or not isinstance(parent, int) or not -2**31 <= parent < 2**31:
                raise VideoFolderError(path, f"joint {index} ({joint['name']}): 'parent' must be an integer joint "
                                             f"index, got {parent!r:.40}")
            names.append(joint["name"])
            parents.append(parent)
            heads.append(joint["head"])
            tails.append(joint["tail"])
        heads, tails = _joint_points(heads, names, path, "head"), _joint_points(tails, names, path, "tail")
        if len(set(names)) < len(names):  # a set, not names.count per name: linear in the joint count
            seen: set[str] = set()
            duplicates = sorted({name for name in names if name in seen or seen.add(name)})
            raise VideoFolderError(path, f"joint names must be unique; repeated: {listed(duplicates)}")
        _check_parents(np.asarray(parents, dtype=np.int64), names, path)
        ends = np.concatenate([heads, tails])
        if not np.any(ends.max(axis=0) > ends.min(axis=0)):
            point = [round(float(value), 6) for value in heads[0]]
            raise VideoFolderError(path, f"every joint's head and tail lie at one point {point}: the skeleton has "
                                         "no size (its rest pose needs joints apart)")
        return cls(names=names, parents=np.asarray(parents, dtype=np.int32), heads=heads, tails=tails, up=up)


def _joint_points(values: list, names: list[str], path: Path, key: str) -> np.ndarray:
    """The joints' ``key`` points ('head' or 'tail') as float64 [J, 3]: checked all at once, and joint by joint
    only to name the first bad one."""
    try:
        return float_array(values, (len(values), 3), path, f"'{key}'")
    except VideoFolderError:
        for index, value in enumerate(values):
            float_array(value, (3,), path, f"joint {index} ({names[index]}) '{key}'")
        raise


def _check_parents(parents: np.ndarray, names: list[str], path: Path) -> None:
    """Parents must index existing joints (-1 for a root) and form a forest with at least one root; linear in the
    joint count (each joint's chain is followed only up to a joint already settled)."""
    joint_count = len(parents)
    outside = np.flatnonzero((parents < -1) | (parents >= joint_count))
    if outside.size:
        index = int(outside[0])
        raise VideoFolderError(path, f"joint {index} ({names[index]}) has parent {parents[index]}, outside "
                                     f"-1..{joint_count - 1}: not a tree")
    if not np.any(parents == -1):
        raise VideoFolderError(path, "no joint has parent -1: the skeleton has no root (parents form a cycle)")
    # Follow each joint's chain of parents up to a joint already known to reach a root; meeting a joint of
    # the current chain again means the chain loops.
    settled = parents == -1
    depth = np.where(settled, 1, 0)  # joints from the root down to each joint, the root included
    for start in range(joint_count):
        chain, on_chain, joint = [], set(), start
        while not settled[joint]:
            if joint in on_chain:
                cycle = chain[chain.index(joint):]
                raise VideoFolderError(path, f"the parents of joint {start} ({names[start]}) form a cycle through "
                                             f"{listed(names[j] for j in cycle)}: not a tree")
            chain.append(joint)
            on_chain.add(joint)
            joint = int(parents[joint])
        base = depth[joint]
        for offset, member in enumerate(reversed(chain)):
            depth[member] = base + 1 + offset
        settled[chain] = True
    deepest = int(np.argmax(depth > MAX_JOINT_DEPTH))  # the first joint too deep, if any
    if depth[deepest] > MAX_JOINT_DEPTH:
        raise VideoFolderError(path, f"joint {deepest} ({names[deepest]}) is {depth[deepest]} joints deep "
                                     f"(its root counted), more than the {MAX_JOINT_DEPTH} expected of a skeleton: "
                                     "check the 'parent' indices")


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
    fps: float = DEFAULT_FPS
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
    def declares_background(self) -> bool:
        """True when meta.json declares the flat colour the frames were rendered over (then each frame, edge pixels
        and all, is its own ground truth); real footage declares none."""
        return "background" in self.meta

    @property
    def poses_estimated(self) -> bool:
        """True when meta.json says the poses were estimated from the images (:data:`ESTIMATED_POSES`)."""
        return self.meta.get("poses") == ESTIMATED_POSES

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


