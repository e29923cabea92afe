"""Fit checkpoints: one file, written atomically, holding the core's state and each extension's by name, and
what the fit was made on (its video folder and skeleton), so that a resume can refuse what it cannot continue.

A checkpoint holds only tensors and plain containers and is read with torch's weights-only unpickler
(:func:`~warpavatar._src.tensor_files.read_tensor_file`): nothing in it runs.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import torch

from warpavatar._src.tensor_files import read_tensor_file
from warpavatar.fit.config import FitConfig, changed_options
from warpavatar.fit.schedule import make_gaussian_optimizer
from warpavatar.io.output_files import atomic_open
from warpavatar.model import GaussianModel

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "save_checkpoint", "read_checkpoint", "training_record",
           "check_resume", "trainer_state", "restore_trainer_state"]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "warpavatar-checkpoint/3"

_CORE_KEYS = ("step", "config", "gaussians", "gaussian_optimizer", "skinning", "density", "generator",
              "frame_order", "extensions")
#: the formats this version resumes -> the entries each must hold (format 3 added ``training``)
_READABLE = {CHECKPOINT_FORMAT: (*_CORE_KEYS, "training"), "warpavatar-checkpoint/2": _CORE_KEYS}
_START_OVER = "start over with --overwrite or in a new output folder"


def save_checkpoint(path: str | os.PathLike, state: dict) -> Path:
    """Write ``state`` (with the format tag) to ``path`` through a temporary file of its own, synced and renamed
    (:func:`~warpavatar.io.output_files.atomic_open`): an interrupted or failed write leaves the previous
    checkpoint as it was and no temporary file.

    Raises:
        DiskFullError: the disk filled up (one line naming ``path`` and the free space).
    """
    path = Path(path)
    with atomic_open(path) as stream:
        torch.save({"format": CHECKPOINT_FORMAT, **state}, stream)
    return path


def read_checkpoint(path: str | os.PathLike, *, mmap: bool = False) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: the file.
        mmap: map the tensors' storage from the file instead of reading it (for a look at the small entries,
            such as ``step``, of a checkpoint that may hold hundreds of MB).

    Raises:
        ValueError: a file holding objects other than tensors and plain containers (not loaded), an unreadable
            file, one holding no dict, one of another format or one missing entries; one line naming ``path``.
    """
    path = Path(path)
    state = read_tensor_file(path, what="checkpoint", mmap=mmap)
    found = state.get("format", "warpavatar-checkpoint/1")
    if found not in _READABLE:
        raise ValueError(f"{path}: checkpoint format {found!r} was written by an earlier warpavatar (this one resumes "
                         f"{' and '.join(map(repr, _READABLE))}); start the fit again in a new output folder (a "
                         "finished fit's avatar.pt still loads)")
    missing = [key for key in _READABLE[found] if key not in state]
    if missing:
        raise ValueError(f"{path}: a damaged or incomplete checkpoint (missing {', '.join(map(repr, missing))})")
    return state


def training_record(video) -> dict:
    """What a checkpoint records of the data it was fitted on: the video folder's resolved path (``folder``),
    ``frame_count``, ``image_size`` [W, H] and digests of its ``frame_ids``, ``poses`` and ``cameras`` (as read, at
    the fit's image scale), and its ``skeleton``: joint ``names``, ``parents`` (indices, -1 for a root) and a
    digest of the ``rest_pose``. Plain values only; cheap (no image is read)."""
    skeleton = video.skeleton
    return {"folder": str(Path(video.root).resolve()), "frame_count": int(video.frame_count),
            "image_size": [int(video.width), int(video.height)], "frame_ids": _digest(video.frame_ids),
            "poses": _digest(video.bone_transforms), "cameras": _digest(video.intrinsics, video.world_to_cameras),
            "skeleton": {"names": [str(name) for name in skeleton.names],
                         "parents": [int(parent) for parent in skeleton.parents],
                         "rest_pose": _digest(skeleton.heads, skeleton.tails, skeleton.up)}}


def trainer_state(trainer) -> dict:
    """What a checkpoint holds of a :class:`~warpavatar.fit.trainer.Trainer`: the steps done, the config, the
    Gaussians and their optimizer, the skinning stage, density control, the random generator and the frames left
    in this epoch's order, each extension's state by name and the :func:`training_record` of its video folder."""
    return {
        "step": trainer.step,
        "config": trainer.config.to_dict(),
        "gaussians": trainer.gaussians.state_for_checkpoint(),
        "gaussian_optimizer": trainer.gaussians.optimizer.state_dict(),
        "skinning": trainer.skinning.state_dict(),
        "density": trainer.density.state_dict(),
        "generator": trainer.generator.get_state(),
        "frame_order": list(trainer.frame_order),
        "extensions": {extension.name: extension.state_dict() for extension in trainer.extensions},
        "training": training_record(trainer.frames.video),
    }


def restore_trainer_state(trainer, state: dict) -> None:
    """Put a checkpoint's :func:`trainer_state` back into ``trainer`` (made with the same options on the same
    folder: :func:`check_resume`): new Gaussians with their optimizer's state, then each extension (one may give
    the field outputs, grown joints, that the saved skinning state has), the skinning stage, density control, the
    generator, the frame order and the step."""
    trainer.avatar.gaussians = GaussianModel.from_checkpoint(state["gaussians"], device=trainer.device)
    make_gaussian_optimizer(trainer.gaussians, trainer.config, extent=trainer.extent)
    trainer.gaussians.optimizer.load_state_dict(state["gaussian_optimizer"])
    for extension in trainer.extensions:
        extension.load_state_dict(state["extensions"][extension.name])
    trainer.skinning.load_state_dict(state["skinning"])
    trainer.density.load_state_dict(state["density"], device=trainer.device)
    trainer.generator.set_state(state["generator"])
    trainer.frame_order = list(state["frame_order"])
    trainer.step = int(state["step"])


def check_resume(path: str | os.PathLike, state: dict, *, config: FitConfig, video) -> None:
    """Refuse to continue the checkpoint ``state`` (read from ``path``) with a fit of ``config`` on ``video``.

    Refused, in this order: other options (a finished fit too, whose resume would otherwise just rewrite its
    outputs), another skeleton (joint names, parents, rest pose), another video folder or one changed since
    (frame count, image size, frame ids, poses or cameras; the same content at another path is the same folder).
    A checkpoint of format 2 recorded neither folder nor skeleton: only its options are checked.

    Raises:
        ValueError: one line naming ``path`` and what differs.
    """
    path = Path(path)
    try:
        saved_config = FitConfig.from_dict(state["config"])
    except (ValueError, TypeError, AttributeError) as error:
        raise ValueError(f"{path}: the checkpoint's config cannot be read ({' '.join(str(error).split())})") from None
    changed = [f"--{name.replace('_', '-')}: {'(off)' if saved is None else saved} in the checkpoint vs "
               f"{'(off)' if given is None else given} given"
               for name, saved, given in changed_options(saved_config, config)]
    if changed:
        step = int(state["step"])
        made = (f"the fit there is finished (step {step} of {saved_config.iterations}) and was made with other "
                "options" if step >= saved_config.iterations else "the checkpoint was made with other options")
        raise ValueError(f"{path}: {made} ({'; '.join(changed)}); resume with the checkpoint's options, or "
                         f"{_START_OVER}")
    saved = state.get("training")
    if saved is None:
        return
    given = training_record(video)
    try:
        problem = _skeleton_difference(saved["skeleton"], given["skeleton"])
        differences = [f"another skeleton: {problem}"] if problem else _folder_differences(saved, given)
    except (KeyError, TypeError, IndexError) as error:
        raise ValueError(f"{path}: a damaged or incomplete checkpoint (its record of the training data lacks "
                         f"{error})") from None
    if differences and saved["folder"] == given["folder"]:
        raise ValueError(f"{path}: the video folder {given['folder']} changed since the checkpoint was made "
                         f"({'; '.join(differences)}); {_START_OVER}")
    if differences:
        raise ValueError(f"{path}: the checkpoint was made on another video folder, {saved['folder']} "
                         f"({'; '.join(differences)}), not {given['folder']}; resume on that folder, or {_START_OVER}")


def _digest(*arrays) -> str:
    """A short hex digest of arrays' dtypes, shapes and values."""
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(np.asarray(array))
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def _skeleton_difference(saved: dict, given: dict) -> str | None:
    """How the skeleton ``given`` (:func:`training_record`'s entry) differs from ``saved``, in a few words."""
    names, given_names = saved["names"], given["names"]
    if len(names) != len(given_names):
        return f"{len(names)} joints in the checkpoint vs {len(given_names)} given"
    for index, (name, given_name) in enumerate(zip(names, given_names)):
        if name != given_name:
            return f"joint {index} is {name!r} in the checkpoint vs {given_name!r} given"
    for name, parent, given_parent in zip(names, saved["parents"], given["parents"]):
        if parent != given_parent:
            parent, given_parent = (names[j] if j >= 0 else "none" for j in (parent, given_parent))
            return f"the parent of joint {name!r} is {parent!r} in the checkpoint vs {given_parent!r} given"
    if saved["rest_pose"] != given["rest_pose"]:
        return "the same joints in another rest pose"
    return None


def _folder_differences(saved: dict, given: dict) -> list[str]:
    """What differs between two :func:`training_record` entries' video folders (their paths aside)."""
    differences = []
    if saved["frame_count"] != given["frame_count"]:
        differences.append(f"{saved['frame_count']} frames in the checkpoint vs {given['frame_count']} given")
    if list(saved["image_size"]) != given["image_size"]:
        differences.append("images of {}x{} in the checkpoint vs {}x{} given".format(*saved["image_size"],
                                                                                      *given["image_size"]))
    if saved["frame_count"] == given["frame_count"]:  # another count of frames differs in all of these anyway
        differences += [f"other {name.replace('_', ' ')}" for name in ("frame_ids", "poses", "cameras")
                        if saved[name] != given[name]]
    return differences
