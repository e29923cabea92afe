"""Driving a fitted avatar with a motion, frame by frame, on the avatar's device.

Used by ``warpavatar-animate`` (USD export) and ``warpavatar-render`` (video): both pose the avatar with the
same code path as fitting and evaluation (:meth:`warpavatar.model.Avatar.pose`), every part of the avatar
included.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np
import torch

from warpavatar.data.checks import check_intrinsics, check_rigid
from warpavatar.io.images import MAX_IMAGE_SIDE

__all__ = ["OrbitCamera", "orbit_cameras", "camera_looking_at_skeleton", "read_cameras_json",
           "RENDER_ROTATION_TOLERANCE", "posed_frames", "parse_frame_range", "read_grown_rotations",
           "motion_time_codes"]


@dataclass
class OrbitCamera:
    """A pinhole camera in the OpenCV convention (same attributes as :class:`warpavatar.data.Camera`)."""

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int


def parse_frame_range(text: str | None) -> slice | None:
    """``"A:B"`` (either side optional) as a slice of motion frames; None for all."""
    if not text:
        return None
    parts = text.split(":")
    if len(parts) != 2:
        raise ValueError(f"--frames must look like A:B (e.g. 0:120 or 30:), got {text!r}")
    try:
        start, stop = (int(p) if p.strip() else None for p in parts)
    except ValueError:
        raise ValueError(f"--frames must hold integers, got {text!r}") from None
    return slice(start, stop)


def motion_time_codes(frame_ids: np.ndarray) -> np.ndarray:
    """The time code of each motion row: its frame id less the first, in frames of the motion's clock.

    A motion's ``fps`` counts its frame ids, so rows of a folder that keeps every k-th frame lie k time codes
    apart and the animation plays at the speed it was captured (USD interpolates between the rows). Rows whose
    ids do not increase (a ``.npz`` may hold any) are numbered 0, 1, 2, ... instead.

    Args:
        frame_ids: [T] int frame ids of the rows.

    Returns:
        [T] int64 time codes, increasing, starting at 0.
    """
    frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    if frame_ids.size > 1 and not (np.diff(frame_ids) > 0).all():
        return np.arange(frame_ids.size, dtype=np.int64)
    return frame_ids - frame_ids[:1].sum()


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:  # looking along the up axis
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera x (right), y (down), z (forward) in world
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ eye
    return matrix.astype(np.float32)


def _skeleton_frame(skeleton) -> tuple[np.ndarray, np.ndarray, float]:
    """(unit up [3], centre of the rest-pose bones' bounding box [3], its diagonal [m]) of a skeleton."""
    up = np.asarray(skeleton.up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    points = np.concatenate([skeleton.heads, skeleton.tails]).astype(np.float64)
    centre = 0.5 * (points.min(0) + points.max(0))
    return up, centre, float(np.linalg.norm(points.max(0) - points.min(0)))


def _orbit_intrinsics(width: int, height: int, field_of_view_degrees: float) -> np.ndarray:
    focal = 0.5 * height / math.tan(math.radians(field_of_view_degrees) * 0.5)
    return np.array([[focal, 0, (width - 1) * 0.5], [0, focal, (height - 1) * 0.5], [0, 0, 1]], dtype=np.float32)


def camera_looking_at_skeleton(skeleton, eye: np.ndarray, *, width: int = 512, height: int = 512,
                               field_of_view_degrees: float = 40.0) -> OrbitCamera:
    """A camera at ``eye`` [3] (world, metres) looking at the centre of the skeleton's rest-pose bones, upright
    along ``skeleton.up``, with the orbit's intrinsics."""
    up, centre, _ = _skeleton_frame(skeleton)
    return OrbitCamera(_orbit_intrinsics(width, height, field_of_view_degrees),
                       _look_at(np.asarray(eye, dtype=np.float64), centre, up), width, height)


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """The 3x3 rotation by ``angle`` [rad] about the unit ``axis`` (right-handed)."""
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def orbit_cameras(skeleton, frame_count: int, *, width: int = 512, height: int = 512, turns: float = 1.0,
                  elevation_degrees: float = 10.0, field_of_view_degrees: float = 40.0,
                  start=None) -> list[OrbitCamera]:
    """Cameras circling the skeleton's rest-pose centre ``turns`` times over ``frame_count`` frames.

    Args:
        skeleton: the avatar's skeleton (rest ``heads``, ``tails`` [J,3] and ``up`` [3]).
        frame_count: the number of cameras, one per frame; camera t is turned by ``turns * 360 * t / frame_count``
            degrees about ``up`` (right-handed).
        width, height: image size [pixels] (without ``start``).
        turns: full circles over the frames.
        elevation_degrees: height of the circle above the centre, as an angle [degrees] (without ``start``).
        field_of_view_degrees: vertical field of view [degrees] (without ``start``).
        start: a camera (``K`` [3,3], ``world_to_camera`` [4,4], ``width``, ``height``) to start from: camera 0
            is that camera, and the others turn it about the up axis through the centre (its distance, height,
            intrinsics and image size kept). None: a circle framing the skeleton's whole height, starting on a
            fixed side.
    """
    up, centre, size = _skeleton_frame(skeleton)
    if start is not None:
        first = np.asarray(start.world_to_camera, dtype=np.float64)
        K = np.asarray(start.K, dtype=np.float32)
        cameras = []
        for t in range(frame_count):
            angle = 2 * math.pi * turns * t / max(1, frame_count)
            turn = np.eye(4)  # camera_to_world turned about the axis: world_to_camera @ T(centre) R^T T(-centre)
            turn[:3, :3] = _rotation_about(up, angle).T
            turn[:3, 3] = centre - turn[:3, :3] @ centre
            cameras.append(OrbitCamera(K, (first @ turn).astype(np.float32), int(start.width), int(start.height)))
        return cameras
    distance = 0.75 * size / math.tan(math.radians(field_of_view_degrees) * 0.5)
    # two axes orthogonal to up
    side = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    K = _orbit_intrinsics(width, height, field_of_view_degrees)
    cameras = []
    elevation = math.radians(elevation_degrees)
    for t in range(frame_count):
        angle = 2 * math.pi * turns * t / max(1, frame_count)
        direction = math.cos(elevation) * (math.cos(angle) * side + math.sin(angle) * other) + math.sin(elevation) * up
        eye = centre + distance * direction
        cameras.append(OrbitCamera(K, _look_at(eye, centre, up), width, height))
    return cameras


RENDER_ROTATION_TOLERANCE = 1e-4
"""The largest entry of ``|R^T R - I|`` accepted for the rotation part of a ``--camera`` extrinsic."""


def _check_render_camera(camera: OrbitCamera, path: Path, what: str) -> None:
    """A camera to render from must be plausible: focal lengths within ``FOCAL_RANGE`` times the larger image side
    and an extrinsic whose rotation part is a rotation (docs/FORMAT.md, "Checks on load")."""
    check_intrinsics(camera.K.astype(np.float64), path, f"{what} 'K'", width=camera.width, height=camera.height)
    check_rigid(camera.world_to_camera.astype(np.float64), path, f"{what} 'world_to_camera'",
                tolerance=RENDER_ROTATION_TOLERANCE)


def read_cameras_json(path: str | Path, frame_count: int) -> list[OrbitCamera]:
    """Cameras from a docs/FORMAT.md ``cameras.json`` (fixed, or one per frame), one per motion frame.

    Raises:
        ValueError: the file is unreadable or malformed, too few per-frame cameras, focal lengths outside
            ``FOCAL_RANGE`` times the larger image side, or an extrinsic whose rotation part is not a rotation within
            :data:`RENDER_ROTATION_TOLERANCE` (the message names the file).
    """
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
        width, height = int(spec["width"]), int(spec["height"])
        entries = spec.get("frames") or [spec]
        cameras = []
        for entry in entries:
            K = np.asarray(entry["K"], dtype=np.float32)
            w2c = np.asarray(entry["world_to_camera"], dtype=np.float32)
            if K.shape != (3, 3) or w2c.shape != (4, 4):
                raise ValueError(f"K must be 3x3 and world_to_camera 4x4, got {K.shape} and {w2c.shape}")
            if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
                raise ValueError("non-finite camera values")
            cameras.append(OrbitCamera(K, w2c, width, height))
    except (OSError, KeyError, TypeError, json.JSONDecodeError, ValueError, OverflowError, RecursionError) as error:
        raise ValueError(f"{path}: not a usable cameras.json ({error})") from error
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise ValueError(f"{path}: the camera's 'width' and 'height' must be 1 to {MAX_IMAGE_SIDE} pixels, got "
                         f"{width}x{height}")
    for index, camera in enumerate(cameras):
        _check_render_camera(camera, path, "the camera" if len(cameras) == 1 else f"frames[{index}]")
    if len(cameras) == 1:
        return cameras * frame_count
    if len(cameras) < frame_count:
        raise ValueError(f"{path}: {len(cameras)} per-frame cameras for {frame_count} motion frames")
    return cameras[:frame_count]


def read_grown_rotations(path: str | Path, *, frame_count: int, joint_count: int) -> np.ndarray:
    """Rotations of an avatar's grown joints for every motion frame, from a ``.npy`` array or a ``.npz`` with
    a ``rotations`` array: float [T,E,4], (w, x, y, z) in each grown joint's parent rest frame (normalized here).

    Raises:
        ValueError: an unreadable file, or one whose shape or values do not fit (named in the message).
    """
    path = Path(path)
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            if "rotations" not in loaded:
                raise ValueError(f"has no 'rotations' array (it has {', '.join(loaded.files) or 'none'})")
            loaded = loaded["rotations"]
        rotations = np.asarray(loaded, dtype=np.float64)
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: not a usable grown-joint rotation file ({error})") from error
    if joint_count == 0:
        raise ValueError(f"{path}: rotations given but the avatar has no grown joints")
    if rotations.shape != (frame_count, joint_count, 4):
        raise ValueError(f"{path}: rotations must have shape [{frame_count}, {joint_count}, 4] (frames, grown "
                         f"joints, w x y z), got {list(rotations.shape)}")
    norms = np.linalg.norm(rotations, axis=-1)
    if not np.isfinite(rotations).all() or (norms < 1e-8).any():
        raise ValueError(f"{path}: rotations must be finite, non-zero quaternions")
    return (rotations / norms[..., None]).astype(np.float32)


@torch.no_grad()
def posed_frames(avatar, bone_transforms: np.ndarray, *, frame_ids: np.ndarray | None = None, fps: float = 30.0,
                 part_inputs: Mapping[str, np.ndarray] | None = None) -> Iterator[dict]:
    """Yield the posed Gaussians of each frame (torch tensors on the avatar's device).

    Args:
        avatar: the avatar.
        bone_transforms: [T,J,4,4] consecutive frames of the motion.
        frame_ids: [T] frame numbers of the rows (default ``0..T-1``).
        fps: frames per second of the frame numbers (with them, the time steps of parts with state over time).
        part_inputs: explicit per-frame inputs of the avatar's parts by part name, arrays with the frame first
            (e.g. the grown joints' rotations [T,E,4], :func:`read_grown_rotations`); by default each part
            decides (a training instant replays what was learned for it).
    """
    device = avatar.gaussians.means.device
    grid = avatar.field.grid_weights()
    avatar.prepare_sequence(bone_transforms, frame_ids=frame_ids, fps=fps)
    for t in range(bone_transforms.shape[0]):
        bones = torch.as_tensor(bone_transforms[t], dtype=torch.float32, device=device)
        inputs = {name: torch.as_tensor(values[t], device=device) for name, values in (part_inputs or {}).items()}
        yield avatar.pose(bones, frame_index=t, grid=grid, inputs=inputs)
