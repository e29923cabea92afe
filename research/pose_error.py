"""How far estimated or refined poses lie from exact ones, split by what the training camera can see.

    python -m research.pose_error EXACT POSES [POSES ...] [--per-joint N]

EXACT is a video folder whose poses are exact (a rendered subject's ``train/``; a subject folder stands for its
``train/``). Each POSES is a ``poses.npz`` of docs/FORMAT.md for the same skeleton, a fit's output folder (its
``poses_refined.npz``, what ``--refine-poses`` wrote) or a video folder (its ``poses.npz``, e.g. a copy made by
``research/perturb_poses.py``). Over the frames a file shares with EXACT (matched by frame id) and every joint it
prints the mean of:

* ``pivots``: the distance between a joint's pivot and its exact place (world units; mm for metres);
* ``along axis`` and ``across``: that error split along the frame camera's optical axis (depth, which one camera
  barely sees) and across it (in the image plane), and ``px``: the pivots' distance in that camera's image;
* ``bias``: per joint, the length of the error vector averaged over the frames (an error shared by every frame,
  which a fitted canonical shape can take up without a visible cost);
* ``rotation``: the angle between each joint's rotation relative to its parent and the exact one (degrees).

``--per-joint N`` also lists the N joints of the largest image-plane error for every file. A file that does not
fit the folder (another skeleton, no shared frame) is reported in one line and the tool exits with status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from warpavatar import data
from warpavatar.data import VideoFolderError

__all__ = ["pose_errors", "poses_path"]


def poses_path(path: Path) -> Path:
    """The poses.npz a POSES argument names: the file itself, a fit folder's ``poses_refined.npz`` or a video
    folder's ``poses.npz``."""
    path = Path(path)
    if path.is_dir():
        for name in ("poses_refined.npz", "poses.npz"):
            if (path / name).is_file():
                return path / name
        raise VideoFolderError(path, "holds neither poses_refined.npz (a fit) nor poses.npz (a video folder)")
    return path


def _relative_rotations(bone_transforms: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Each joint's rotation relative to its parent's [T,J,3,3] (a root's own rotation)."""
    rotations = bone_transforms[..., :3, :3]
    parent_rotations = rotations[:, np.where(parents >= 0, parents, np.arange(parents.shape[0]))]
    relative = np.swapaxes(parent_rotations, -1, -2) @ rotations
    roots = parents < 0
    relative[:, roots] = rotations[:, roots]
    return relative


def pose_errors(exact: np.ndarray, estimate: np.ndarray, heads: np.ndarray, parents: np.ndarray,
                cameras) -> dict[str, np.ndarray]:
    """Per frame and joint errors of ``estimate`` against ``exact`` (both [T,J,4,4] rest-to-posed transforms of
    the same frames).

    Args:
        heads: [J,3] rest pivots [world units]; parents: [J] parent index (-1 for roots).
        cameras: the T frames' :class:`~warpavatar.data.Camera` (OpenCV convention).

    Returns:
        ``pivots``, ``along_axis``, ``across``, ``pixels`` and ``rotation_deg``, each [T,J], and ``bias`` [J].
    """
    exact = np.asarray(exact, dtype=np.float64)
    estimate = np.asarray(estimate, dtype=np.float64)
    heads = np.asarray(heads, dtype=np.float64)
    parents = np.asarray(parents)
    intrinsics = np.stack([np.asarray(camera.K, dtype=np.float64) for camera in cameras])
    world_to_camera = np.stack([np.asarray(camera.world_to_camera, dtype=np.float64) for camera in cameras])

    def pivots(transforms):
        return np.einsum("tjab,jb->tja", transforms[..., :3, :3], heads) + transforms[..., :3, 3]

    truth, guess = pivots(exact), pivots(estimate)
    error = guess - truth  # [T,J,3] world
    rotation = world_to_camera[:, None, :3, :3]
    error_camera = (rotation @ error[..., None])[..., 0]

    def project(points):
        camera = (rotation @ points[..., None])[..., 0] + world_to_camera[:, None, :3, 3]
        image = (intrinsics[:, None] @ camera[..., None])[..., 0]
        return image[..., :2] / image[..., 2:3]

    # the angle between two rotations from their chordal distance, |A - B|_F = 2 sqrt(2) sin(angle / 2): unlike
    # the trace's arccos it stays accurate near zero, where float32 poses' rounding would read as tenths of a degree
    chord = np.linalg.norm(_relative_rotations(estimate, parents) - _relative_rotations(exact, parents), axis=(-2, -1))
    angle = 2.0 * np.arcsin(np.clip(chord / (2.0 * math.sqrt(2.0)), 0.0, 1.0))
    return {"pivots": np.linalg.norm(error, axis=-1), "along_axis": np.abs(error_camera[..., 2]),
            "across": np.linalg.norm(error_camera[..., :2], axis=-1),
            "pixels": np.linalg.norm(project(guess) - project(truth), axis=-1),
            "rotation_deg": np.degrees(angle), "bias": np.linalg.norm(error.mean(axis=0), axis=-1)}


def _report(video, path: Path, per_joint: int) -> list[str]:
    transforms, frame_ids, _ = data.read_poses(path, joint_count=video.skeleton.joint_count)
    rows = {int(frame): row for row, frame in enumerate(video.frame_ids)}
    shared = [(row, rows[int(frame)]) for row, frame in enumerate(frame_ids) if int(frame) in rows]
    if not shared:
        raise VideoFolderError(path, f"shares no frame id with {video.root}")
    mine, theirs = (np.asarray(index) for index in zip(*shared))
    errors = pose_errors(np.asarray(video.bone_transforms)[theirs], transforms[mine], video.skeleton.heads,
                         video.skeleton.parents, [video.cameras[t] for t in theirs])
    lines = [f"| {path} | {len(shared)} | {1000 * errors['pivots'].mean():.1f} | "
             f"{1000 * errors['along_axis'].mean():.1f} | {1000 * errors['across'].mean():.1f} | "
             f"{errors['pixels'].mean():.2f} | {1000 * errors['bias'].mean():.1f} | "
             f"{errors['rotation_deg'].mean():.2f} |"]
    for joint in np.argsort(-errors["pixels"].mean(axis=0))[:per_joint]:
        lines.append(f"|   {video.skeleton.names[joint]} | | {1000 * errors['pivots'][:, joint].mean():.1f} | "
                     f"{1000 * errors['along_axis'][:, joint].mean():.1f} | "
                     f"{1000 * errors['across'][:, joint].mean():.1f} | {errors['pixels'][:, joint].mean():.2f} | "
                     f"{1000 * errors['bias'][joint]:.1f} | {errors['rotation_deg'][:, joint].mean():.2f} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("exact", type=Path, help="video folder (or subject folder) whose poses are exact")
    parser.add_argument("poses", type=Path, nargs="+", help="poses.npz files, fit folders or video folders")
    parser.add_argument("--per-joint", type=int, default=0, metavar="N",
                        help="also list the N joints of the largest image-plane error (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.per_joint < 0:
        parser.error(f"--per-joint must be >= 0, got {args.per_joint}")
    try:
        root = args.exact / "train" if (args.exact / "train").is_dir() else args.exact
        video = data.load_video_folder(root)
        print("| poses | frames | pivots (mm) | along axis (mm) | across (mm) | px | bias (mm) | rotation (deg) |")
        print("|---|---|---|---|---|---|---|---|")
        for path in args.poses:
            print("\n".join(_report(video, poses_path(path), args.per_joint)))
    except (VideoFolderError, OSError) as error:
        print(f"pose_error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
