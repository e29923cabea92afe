"""Copy a video folder (or a subject's training folder) with its poses perturbed by a known, reproducible noise.

    python -m research.perturb_poses SOURCE -o OUT --rotation-deg 5 --translation-m 0.02 [--smooth-frames 5] [--seed 0]
        [--confine image-plane|depth]

The perturbation is what pose refinement has to undo, measured against poses known exactly (a rendered
subject): every joint's rotation relative to its parent is turned by a random axis-angle of
``--rotation-deg`` degrees (a uniformly random axis, the same angle for every joint: the noise's size is
exact), the root(s) move by a random offset of ``--translation-m`` world units, and the children follow
rigidly (``warpavatar.model.kinematics.corrected_transforms``). With ``--smooth-frames K`` the noise
varies slowly in time, as an estimator's does: each frame's noise vectors are a Gaussian-weighted average
(sigma K frames) of independent ones, rescaled to the requested size.

``--confine`` separates what one camera sees from what it does not, each frame's own camera deciding:
``image-plane`` turns every joint about the camera's optical axis (a random sense per joint and frame) and moves
the root across it, so every pivot moves in the image plane only; ``depth`` turns every joint about a random axis
in the image plane (a limb lying across the view swings towards or away from the camera) and moves the root along
the optical axis. The angles and the offset keep their sizes. (Not with ``--smooth-frames``: a sense of turn drawn
per frame does not vary smoothly.)

SOURCE may be a video folder or a subject folder. For a subject, ``train/`` is perturbed, and each
``novel_view/`` folder (other cameras at the training instants) gets the same noise as the training frame of
the same id: an estimator gives an instant one pose, whichever camera looks at it, so novel views are judged
with the poses the fit was given (and refined). ``novel_pose/`` folders are copied as they are. Each perturbed
folder's ``meta.json`` says ``"poses": "estimated"`` (so ``--refine-poses auto`` refines them) and records the
perturbation.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from warpavatar import data
from warpavatar.data.types import ESTIMATED_POSES
from warpavatar.model.kinematics import ancestor_jumps, corrected_transforms

__all__ = ["perturbation", "confined_perturbation", "perturb_poses", "perturb_folder", "perturb_subject"]

CONFINES = ("none", "image-plane", "depth")
"""What ``--confine`` accepts: no confinement, or the noise kept to the image plane or to depth-ward turns."""


def _unit_vectors(generator: np.random.Generator, shape) -> np.ndarray:
    vectors = generator.normal(size=(*shape, 3))
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def _smooth_in_time(vectors: np.ndarray, frames: float) -> np.ndarray:
    """Gaussian-weighted averages over the first axis (time), sigma ``frames``."""
    if frames <= 0:
        return vectors
    times = np.arange(vectors.shape[0])
    weights = np.exp(-0.5 * ((times[:, None] - times[None, :]) / frames) ** 2)
    weights /= weights.sum(axis=1, keepdims=True)
    return np.tensordot(weights, vectors, axes=(1, 0))


def perturbation(frame_count: int, joint_count: int, *, rotation_deg: float, translation: float,
                 smooth_frames: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Noise of exactly the requested size: axis-angle vectors [T,J,3] of norm ``rotation_deg`` (in radians) and
    root offsets [T,3] of norm ``translation``, independent per frame or smooth in time."""
    generator = np.random.default_rng(seed)
    rotations = _smooth_in_time(_unit_vectors(generator, (frame_count, joint_count)), smooth_frames)
    offsets = _smooth_in_time(_unit_vectors(generator, (frame_count,)), smooth_frames)
    rotations = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True) * math.radians(rotation_deg)
    offsets = offsets / np.linalg.norm(offsets, axis=-1, keepdims=True) * translation
    return rotations, offsets


def confined_perturbation(bone_transforms: np.ndarray, optical_axes: np.ndarray, *, rotation_deg: float,
                          translation: float, confine: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Noise confined to the image plane or to depth (see the module docstring), as :func:`perturbation` returns
    it: axis-angle vectors [T,J,3] of norm ``rotation_deg`` (in radians) in each joint's posed frame (what
    :func:`perturb_poses` turns by) and root offsets [T,3] of norm ``translation``.

    Args:
        bone_transforms: [T,J,4,4] the poses to perturb (the joints' posed frames).
        optical_axes: [T,3] each frame camera's optical axis in the world (``world_to_camera[2, :3]``).
        confine: ``image-plane`` or ``depth``.
    """
    if confine not in ("image-plane", "depth"):
        raise ValueError(f"confine must be 'image-plane' or 'depth', got {confine!r}")
    generator = np.random.default_rng(seed)
    frame_count, joint_count = bone_transforms.shape[:2]
    axes = np.asarray(optical_axes, dtype=np.float64)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    helper = np.where(np.abs(axes[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])  # not along the axis
    across = np.cross(axes, helper)
    across /= np.linalg.norm(across, axis=-1, keepdims=True)
    across_too = np.cross(axes, across)  # (across, across_too) span the image plane
    if confine == "image-plane":
        turn_axes = axes[:, None, :] * generator.choice([-1.0, 1.0], size=(frame_count, joint_count, 1))
        angle = generator.uniform(0.0, 2.0 * math.pi, size=(frame_count, 1))
        directions = np.cos(angle) * across + np.sin(angle) * across_too
    else:
        angle = generator.uniform(0.0, 2.0 * math.pi, size=(frame_count, joint_count, 1))
        turn_axes = np.cos(angle) * across[:, None] + np.sin(angle) * across_too[:, None]
        directions = axes * generator.choice([-1.0, 1.0], size=(frame_count, 1))
    # a joint's turn exp(d) in its posed frame is the world turn about R d (corrected_transforms): d = R^T a
    rotations = np.einsum("tjba,tjb->tja", np.asarray(bone_transforms, dtype=np.float64)[..., :3, :3], turn_axes)
    return rotations * math.radians(rotation_deg), directions * translation


def perturb_poses(bone_transforms: np.ndarray, skeleton, rotations: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Poses [T,J,4,4] with every joint's local rotation turned by ``rotations`` [T,J,3] and the roots moved by
    ``offsets`` [T,3] (children follow rigidly)."""
    heads = torch.as_tensor(skeleton.heads, dtype=torch.float64)
    poses = torch.as_tensor(bone_transforms, dtype=torch.float64)
    out = corrected_transforms(poses, heads, ancestor_jumps(skeleton.parents), torch.as_tensor(rotations),
                               torch.as_tensor(offsets))
    return out.numpy().astype(np.float32)


def perturb_folder(source: Path, output: Path, *, rotation_deg: float, translation: float,
                   smooth_frames: float = 0.0, seed: int = 0, overwrite: bool = False,
                   noise: dict | None = None, confine: str = "none") -> dict:
    """Copy the video folder ``source`` to ``output`` with perturbed poses (see the module docstring).

    Args:
        noise: ``{frame id: (rotations [J,3], offset [3])}`` to apply instead of drawing new noise (the noise of
            another folder showing the same instants); frames it lacks are drawn.
        confine: ``none``, or ``image-plane`` / ``depth`` (:func:`confined_perturbation`, this folder's cameras).

    Returns:
        The noise applied, by frame id.
    """
    if confine not in CONFINES:
        raise ValueError(f"confine must be one of {', '.join(CONFINES)}, got {confine!r}")
    if confine != "none" and smooth_frames > 0:
        raise ValueError("--confine does not combine with --smooth-frames (its sense of turn is drawn per frame)")
    video = data.load_video_folder(source)
    if confine == "none":
        rotations, offsets = perturbation(video.frame_count, video.skeleton.joint_count, rotation_deg=rotation_deg,
                                          translation=translation, smooth_frames=smooth_frames, seed=seed)
    else:
        optical_axes = np.stack([np.asarray(camera.world_to_camera)[2, :3] for camera in video.cameras])
        rotations, offsets = confined_perturbation(video.bone_transforms, optical_axes, rotation_deg=rotation_deg,
                                                   translation=translation, confine=confine, seed=seed)
    applied = {}
    for row, frame_id in enumerate(video.frame_ids.tolist()):
        if noise is not None and frame_id in noise:
            rotations[row], offsets[row] = noise[frame_id]
        applied[frame_id] = (rotations[row], offsets[row])
    video.bone_transforms = perturb_poses(video.bone_transforms, video.skeleton, rotations, offsets)
    video.joint_positions = None  # they would describe the exact poses
    video.meta = {**video.meta, "poses": ESTIMATED_POSES,
                  "perturbation": {"rotation_deg": rotation_deg, "translation": translation,
                                   "smooth_frames": smooth_frames, "seed": seed, "confine": confine,
                                   "source": str(source)}}
    data.write_video_folder(video, output, overwrite=overwrite)
    return applied


def perturb_subject(source: Path, output: Path, *, overwrite: bool = False, **options) -> None:
    """Copy a subject with ``train/`` and ``novel_view/*`` perturbed alike, ``novel_pose/*`` as they are."""
    if output.exists() and not overwrite:
        raise FileExistsError(f"{output} already exists (pass --overwrite to replace it)")
    with data.staged_folder(output, overwrite=overwrite) as staging:
        noise = perturb_folder(source / "train", staging / "train", **options)
        for entry in source.iterdir():
            if entry.name == "train":
                continue
            if entry.name == "novel_view" and entry.is_dir():
                for view in sorted(entry.iterdir()):
                    if view.is_dir():
                        perturb_folder(view, staging / "novel_view" / view.name, noise=noise, **options)
            else:
                (shutil.copytree if entry.is_dir() else shutil.copy2)(entry, staging / entry.name)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path, help="a video folder, or a subject folder (its train/ is perturbed)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the folder to write")
    parser.add_argument("--rotation-deg", type=float, default=5.0,
                        help="angle of every joint's local rotation noise [degrees] (default: 5)")
    parser.add_argument("--translation-m", type=float, default=0.02,
                        help="length of the root's offset [world units: metres in the supplied data] (default: 0.02)")
    parser.add_argument("--smooth-frames", type=float, default=0.0,
                        help="make the noise vary smoothly over this many frames (Gaussian sigma; 0: independent "
                             "per frame) (default: 0)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the noise (default: 0)")
    parser.add_argument("--confine", choices=CONFINES, default="none",
                        help="keep the noise to the image plane of each frame's camera (joints turned about its "
                             "optical axis, the root moved across it) or to depth (joints turned about axes in the "
                             "image plane, the root moved along the axis): what one camera sees against what it "
                             "does not (default: none)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    args = parser.parse_args(argv)
    if args.rotation_deg < 0 or args.translation_m < 0 or args.smooth_frames < 0:
        parser.error("--rotation-deg, --translation-m and --smooth-frames must be non-negative")
    options = dict(rotation_deg=args.rotation_deg, translation=args.translation_m, smooth_frames=args.smooth_frames,
                   seed=args.seed, overwrite=args.overwrite, confine=args.confine)
    try:
        if (args.source / "train").is_dir():
            perturb_subject(args.source, args.output, **options)
        else:
            perturb_folder(args.source, args.output, **options)
    except (ValueError, FileExistsError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    confined = "" if args.confine == "none" else f", confined to {args.confine}"
    print(f"wrote {args.output}: poses perturbed by {args.rotation_deg:g} deg per joint and {args.translation_m:g} "
          f"at the root (seed {args.seed}{confined})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
