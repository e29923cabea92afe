"""Motion sources that drive a fitted avatar: a video folder, a ``poses.npz`` or a BVH file.

:func:`load_motion` turns any of them into per-frame bone transforms of *our* skeleton (rest pose ->
posed world, the linear-blend-skinning matrices of ``poses.npz``; see ``docs/FORMAT.md``), checked for shape,
finiteness and rigidity, with errors that name the file.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from warpavatar.data.checks import VideoFolderError, check_fps, check_frame_ids, read_json
from warpavatar.io.bvh import BvhError, match_joint_names, parse_bvh, retarget_bvh

__all__ = ["Motion", "MotionError", "load_motion", "check_bone_transforms"]

DEFAULT_FPS = 30.0
"""Frame rate assumed when a source does not state one."""

_RIGID_TOLERANCE = 1e-3


class MotionError(ValueError):
    """A motion source that cannot be read or does not fit the skeleton; the message names the file."""


@dataclasses.dataclass
class Motion:
    """Bone transforms of a skeleton over time.

    Attributes:
        bone_transforms: [T,J,4,4] float32 rigid transforms (rest pose -> posed world) per frame and joint.
        fps: frames per second.
        frame_ids: [T] int32 frame ids (file names of a video folder's frames; 0..T-1 for a BVH).
        undriven_joints: names of the skeleton's joints the source has no joint for (BVH only).
    """

    bone_transforms: np.ndarray
    fps: float
    frame_ids: np.ndarray
    #: the skeleton's joints that the source does not drive (a BVH without them); they keep their rest pose
    #: relative to their parent
    undriven_joints: list = dataclasses.field(default_factory=list)

    @property
    def frame_count(self) -> int:
        return int(self.bone_transforms.shape[0])


def check_bone_transforms(bone_transforms, *, joint_count: int, source: str = "bone_transforms") -> np.ndarray:
    """Check per-frame bone transforms and return them as a float32 array.

    Args:
        bone_transforms: [T,J,4,4] array.
        joint_count: J expected (the skeleton's joint count).
        source: what to name in messages (a file path).

    Returns:
        the [T,J,4,4] float32 array.

    Raises:
        MotionError: wrong shape or joint count, non-finite values, or a transform that is not a rotation
            plus a translation (|R^T R - I| > 1e-3, det R < 0, or a last row other than [0, 0, 0, 1]).
    """
    array = np.asarray(bone_transforms)
    if array.dtype.kind not in "fiu":
        raise MotionError(f"{source}: bone_transforms must be numeric, got dtype {array.dtype}")
    if array.ndim != 4 or array.shape[2:] != (4, 4):
        raise MotionError(f"{source}: bone_transforms must have shape [T, J, 4, 4], got {list(array.shape)}")
    if array.shape[1] != joint_count:
        raise MotionError(f"{source}: bone_transforms have {array.shape[1]} joints but the skeleton has "
                          f"{joint_count}")
    array = np.ascontiguousarray(array, dtype=np.float32)
    finite = np.isfinite(array).all(axis=(2, 3))
    if not finite.all():
        frame, joint = np.argwhere(~finite)[0]
        raise MotionError(f"{source}: bone_transforms hold non-finite values (first at frame {frame}, "
                          f"joint {joint})")
    if array.size:
        matrices = array.astype(np.float64)
        rotations = matrices[..., :3, :3]
        orthogonality = np.abs(np.swapaxes(rotations, -1, -2) @ rotations - np.eye(3)).max(axis=(-1, -2))
        last_row = np.abs(matrices[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1)
        bad = (orthogonality > _RIGID_TOLERANCE) | (np.linalg.det(rotations) < 0) | (last_row > 1e-5)
        if bad.any():
            frame, joint = np.argwhere(bad)[0]
            raise MotionError(f"{source}: bone transform of frame {frame}, joint {joint} is not rigid "
                              f"(|R^T R - I| = {orthogonality[frame, joint]:.2e}, det R = "
                              f"{np.linalg.det(rotations[frame, joint]):.4f}, last row "
                              f"{matrices[frame, joint, 3].tolist()})")
    return array


def _read_npz(path: str) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """(bone_transforms, frame_ids or None, fps or None) from a poses.npz-like file."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            if "bone_transforms" not in archive.files:
                raise MotionError(f"{path}: no 'bone_transforms' array (found {archive.files})")
            bone_transforms = archive["bone_transforms"]
            frame_ids = archive["frame_ids"] if "frame_ids" in archive.files else None
            fps = archive["fps"] if "fps" in archive.files else None
            if fps is not None and fps.shape not in ((), (1,)):
                raise MotionError(f"{path}: 'fps' must be one number, got an array of shape {list(fps.shape)}")
            fps = None if fps is None else fps.reshape(-1)[0]
    except MotionError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, zlib.error, EOFError, TypeError) as error:
        raise MotionError(f"{path}: cannot read as .npz: {error}") from None
    return bone_transforms, frame_ids, fps


def _read_fps(meta_path: str) -> float | None:
    if not os.path.exists(meta_path):
        return None
    try:
        meta = read_json(Path(meta_path))
    except VideoFolderError as error:
        raise MotionError(str(error)) from None
    fps = meta.get("fps") if isinstance(meta, dict) else None
    return None if fps is None else fps


def load_motion(source: str | os.PathLike, skeleton, *, name_map: dict | None = None, frames: slice | None = None,
                bvh_scale: float | None = None, bvh_up=None) -> Motion:
    """Load a motion for ``skeleton`` from a video folder, a ``.npz`` or a ``.bvh``.

    Args:
        source: a video folder (its ``poses.npz``, and ``meta.json``'s ``fps`` when present), a ``.npz``
            with ``bone_transforms`` [T,J,4,4] (optional ``frame_ids`` [T], ``fps``), or a ``.bvh`` file
            retargeted with :func:`warpavatar.io.bvh.retarget_bvh`.
        skeleton: our skeleton (``warpavatar.data.Skeleton`` or any object with ``names``, ``parents``,
            ``heads``, ``tails``, ``up``); folders and ``.npz`` files must have its joint count.
        name_map: BVH only: {our joint name: BVH joint name}; default matches names.
        frames: a slice of the frames to keep (e.g. ``slice(0, 100, 2)``); default all.
        bvh_scale: BVH only: skeleton units per BVH unit; default from the ratio of rest heights.
        bvh_up: BVH only: the BVH up axis ('Y' default, 'Z', '-Y', ... or a 3-vector).

    Returns:
        a :class:`Motion` with float32 ``bone_transforms`` [T,J,4,4], ``fps`` and int32 ``frame_ids`` [T]
        (default ``0..T-1`` where the source has none).

    Raises:
        MotionError: missing or unreadable files, an unknown source type, wrong joint count, non-finite
            or non-rigid transforms, an fps outside 0.01..1000 (``FPS_RANGE``), frame ids outside 0..2**31 - 1,
            an empty selection, BVH errors; the message names the file.
        TypeError: ``frames`` is not a slice.
    """
    if frames is not None and not isinstance(frames, slice):
        raise TypeError(f"frames must be a slice or None, got {type(frames).__name__}")
    source = os.fspath(source)
    undriven = []
    try:
        joint_count = len(skeleton.names)
    except (AttributeError, TypeError):
        raise TypeError("skeleton must have a 'names' list (warpavatar.data.Skeleton or alike)") from None
    fps_source = source
    if os.path.isdir(source):
        poses_path = os.path.join(source, "poses.npz")
        if not os.path.isfile(poses_path):
            raise MotionError(f"{source}: video folder has no poses.npz")
        _check_folder_skeleton(os.path.join(source, "skeleton.json"), skeleton)
        bone_transforms, frame_ids, fps = _read_npz(poses_path)
        meta_path = os.path.join(source, "meta.json")
        meta_fps = _read_fps(meta_path)
        if meta_fps is not None:
            fps, fps_source = meta_fps, meta_path
        described = poses_path
    elif not os.path.exists(source):
        raise MotionError(f"{source}: no such file or folder")
    elif source.lower().endswith(".npz"):
        bone_transforms, frame_ids, fps = _read_npz(source)
        described = source
    elif source.lower().endswith(".bvh"):
        try:
            bvh = parse_bvh(source)
            bone_transforms = retarget_bvh(bvh, skeleton, name_map=name_map, scale=bvh_scale, up=bvh_up)
            driven = match_joint_names(list(skeleton.names), bvh.names, name_map)
            undriven = [name for index, name in enumerate(skeleton.names) if index not in driven]
        except BvhError as error:
            message = str(error)
            raise MotionError(message if source in message else f"{source}: {message}") from None
        except OSError as error:
            raise MotionError(f"{source}: cannot read: {error}") from None
        frame_ids, fps = None, bvh.fps
        described = source
    else:
        raise MotionError(f"{source}: unknown motion source (expected a video folder, a .npz or a .bvh)")

    if fps is None:
        fps = DEFAULT_FPS
    try:
        fps = check_fps(fps, fps_source, "fps")
    except VideoFolderError as error:
        raise MotionError(str(error)) from None

    bone_transforms = check_bone_transforms(bone_transforms, joint_count=joint_count, source=described)
    frame_count = bone_transforms.shape[0]
    if frame_ids is None:
        frame_ids = np.arange(frame_count, dtype=np.int32)
    frame_ids = np.asarray(frame_ids)
    if frame_ids.shape != (frame_count,) or frame_ids.dtype.kind not in "iu":
        raise MotionError(f"{described}: frame_ids must be {frame_count} integers, got shape "
                          f"{list(frame_ids.shape)} dtype {frame_ids.dtype}")
    try:  # a motion's rows may come in any order (motion_time_codes), but ids outside int32 would wrap
        frame_ids = check_frame_ids(frame_ids, described, increasing=False)
    except VideoFolderError as error:
        raise MotionError(str(error)) from None
    if frames is not None:
        bone_transforms = bone_transforms[frames]
        frame_ids = frame_ids[frames]
    if bone_transforms.shape[0] == 0:
        raise MotionError(f"{described}: no frames" + (f" selected by {frames}" if frames is not None else ""))
    return Motion(bone_transforms=np.ascontiguousarray(bone_transforms), fps=fps,
                  frame_ids=np.ascontiguousarray(frame_ids, dtype=np.int32), undriven_joints=undriven)


def _check_folder_skeleton(path: str, skeleton) -> None:
    """A video folder's motion drives its own skeleton: it must be ``skeleton`` (same joint names, same
    order), or the message says which joints differ."""
    if not os.path.isfile(path):
        return
    from warpavatar.data import VideoFolderError
    from warpavatar.data.reader import read_skeleton
    from warpavatar.data.checks import listed

    try:
        names = read_skeleton(Path(path)).names
    except VideoFolderError as error:
        raise MotionError(str(error)) from None
    ours = [str(name) for name in skeleton.names]
    if names == ours:
        return
    extra = [name for name in names if name not in ours]
    missing = [name for name in ours if name not in names]
    if extra or missing:
        differences = "; ".join(part for part in (
            f"joints the avatar lacks: {listed(extra)}" if extra else "",
            f"avatar joints it lacks: {listed(missing)}" if missing else "") if part)
        raise MotionError(f"{path}: the motion is of another skeleton ({differences})")
    first = next(index for index, (a, b) in enumerate(zip(names, ours)) if a != b)
    raise MotionError(f"{path}: the motion's skeleton orders its joints differently (joint {first} is "
                      f"{names[first]!r}, the avatar's {ours[first]!r})")

