"""Optional parts of an avatar: the hooks through which they take part in posing, shading and files.

An :class:`~warpavatar.model.avatar.Avatar` is canonical Gaussians, a skeleton and a skinning field, plus any
number of *parts* (:class:`AvatarPart`): a pose-dependent correction, secondary motion of cloth, joints grown
on the skeleton, a lighting model, a simulated garment. Posing one frame runs a fixed pipeline, and each part
joins the stages it needs by overriding their hooks (the defaults change nothing):

1. :meth:`AvatarPart.skinning_transforms`: the skinning transforms [J,4,4] of the skeleton may be extended
   (joints grown on the skeleton append theirs).
2. :meth:`AvatarPart.deform_canonical`: the canonical Gaussians are reshaped before skinning
   (:class:`CanonicalGaussians`); the skinning field is then read at their centres.
3. Linear blend skinning poses them.
4. :meth:`AvatarPart.deform_posed`: the posed Gaussians may be changed in the world (after skinning).
5. :meth:`AvatarPart.shade`: the colours seen from the camera may be changed.

Sequences: :meth:`AvatarPart.prepare_sequence` is called with every frame of a motion before its frames are
posed one by one (a part with state over time, as simulated cloth, rolls the motion out there).

Files: a part is saved in ``avatar.pt`` under its :attr:`AvatarPart.name` with the import path of its class,
and rebuilt by that class's :meth:`AvatarPart.from_file_state`, so parts defined outside this package load as
well as the built-in ones.

How a part is *fitted* (its losses, optimizers, schedule) is not the model's business: see
:mod:`warpavatar.extensions`.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import math
import sys
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Mapping

import torch

__all__ = ["AvatarPart", "PoseFrame", "CanonicalGaussians", "part_class_path", "part_from_file_state",
           "frame_intervals"]


def frame_intervals(frame_ids, fps: float) -> torch.Tensor:
    """Seconds from each frame of a sequence to the one before it, [T] float32 (the first is the median
    interval).

    Args:
        frame_ids: [T] strictly increasing frame numbers of the sequence.
        fps: frames per second of the numbering.
    """
    ids = torch.as_tensor(frame_ids, dtype=torch.float64).reshape(-1)
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive number, got {fps}")
    if ids.numel() == 0:
        return torch.zeros(0)
    steps = torch.diff(ids, prepend=ids[:1])
    if ids.numel() > 1:
        if bool((steps[1:] <= 0).any()):
            raise ValueError("frame ids must be strictly increasing")
        steps[0] = steps[1:].median()
    else:
        steps[0] = 1.0
    return (steps / fps).float()


@dataclass(frozen=True)
class PoseFrame:
    """What posing one frame is told.

    Attributes:
        bone_transforms: [J,4,4] the skeleton's rest-to-posed transforms as given: what says which instant this
            is (parts look up what they learned per training instant by it).
        frame_index: index of the frame in the prepared sequence (None outside one).
        inputs: explicit inputs of parts for this frame, by part name (e.g. the state a fit is training, or
            rotations a user gives grown joints); a part without one looks its state up itself.
        skeleton_pose: [J,4,4] the skeleton's transforms to skin with instead of ``bone_transforms`` (a pose
            refined for this frame at test time), or None.
    """

    bone_transforms: torch.Tensor
    frame_index: int | None = None
    inputs: Mapping[str, Any] = field(default_factory=dict)
    skeleton_pose: torch.Tensor | None = None

    def input(self, name: str) -> Any | None:
        """The explicit input for part ``name``, or None."""
        return self.inputs.get(name)


@dataclass(frozen=True)
class CanonicalGaussians:
    """The canonical Gaussians as the parts reshape them before skinning.

    Attributes:
        means: [N,3] centres [world units]: the skinning field is read here, and skinning poses them.
        quats: [N,4] unit orientations (w, x, y, z).
        scales: [N,3] scales [world units].
        offset: [N,3] displacement added before skinning that does not move where the skinning weights are
            read (secondary motion of cloth), or None.
        rest_means: [N,3] the stored canonical centres, before any part (what graphs bind to).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    offset: torch.Tensor | None
    rest_means: torch.Tensor

    def replace(self, **changes) -> "CanonicalGaussians":
        return replace(self, **changes)

    def displaced(self, offset: torch.Tensor) -> "CanonicalGaussians":
        """The same Gaussians with ``offset`` [N,3] added to the displacement before skinning."""
        return replace(self, offset=offset if self.offset is None else self.offset + offset)


class AvatarPart(torch.nn.Module):
    """Base of an avatar's optional parts. Subclasses set :attr:`name` and override the hooks they need.

    Every hook runs on the avatar's device and must not synchronize with the host (posing is on the hot path
    of fits and playback).
    """

    name: ClassVar[str] = ""
    """The part's key in :attr:`Avatar.parts` and in avatar files (an extension's name)."""

    # ---------------------------------------------------------------------------------------- posing
    def skinning_transforms(self, bones: torch.Tensor, frame: PoseFrame) -> torch.Tensor:
        """The skinning transforms [J+E',4,4] from those so far [J+E,4,4] (append, never reorder)."""
        return bones

    def added_joint_parents(self) -> torch.Tensor | None:
        """Skeleton joint [E'] each transform appended by :meth:`skinning_transforms` belongs to, or None."""
        return None

    def extend_rig(self, skeleton):
        """The skeleton with the joints this part appends (for exports: UsdSkel); unchanged by default."""
        return skeleton

    def deform_canonical(self, canonical: CanonicalGaussians, bones: torch.Tensor, frame: PoseFrame
                         ) -> CanonicalGaussians:
        """Reshape the canonical Gaussians for this frame (``bones``: every skinning transform [J+E,4,4])."""
        return canonical

    def deform_posed(self, posed, frame: PoseFrame):
        """Change the posed Gaussians (:class:`~warpavatar.model.avatar.PosedGaussians`) after skinning."""
        return posed

    def shade(self, colors: torch.Tensor, posed, frame: PoseFrame) -> torch.Tensor:
        """Change the RGB colours [N,3] the posed Gaussians show from the camera."""
        return colors

    def prepare_sequence(self, bones: torch.Tensor, intervals: torch.Tensor, *, progress: bool = False) -> None:
        """Get ready to pose the frames of a motion: every skinning transform [T,J+E,4,4], seconds [T] since the
        frame before (:func:`frame_intervals`)."""

    # -------------------------------------------------------------------------------------- playback
    def prepare_playback(self, rest_means: torch.Tensor, *, mlp_dtype: torch.dtype = torch.float32) -> tuple:
        """Called by :class:`~warpavatar.model.playback.Player` before every frame, outside any captured graph,
        with the stored canonical centres [N,3]: a part may cache what depends only on them and on its own
        parameters (the same for every frame of a frozen avatar), refilled in place when they change.
        ``mlp_dtype`` (``torch.float16`` or ``torch.float32``) is the dtype the player asks the part's
        per-Gaussian MLPs to run in (inputs, weights and activations; sums in float32); a part may keep float32
        where its values could leave float16's range. Host reads are allowed here, not in the frame.

        Returns:
            The storage a captured frame reads of those caches (data pointers, shapes); when it changes, the
            player captures again. Nothing by default.
        """
        return ()

    # ------------------------------------------------------------------------------------------ files
    def state_for_file(self) -> dict:
        """Everything :meth:`from_file_state` needs (tensors on the CPU)."""
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}}

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "AvatarPart":
        raise NotImplementedError(f"{cls.__name__} cannot be loaded from a file")


def part_class_path(part: AvatarPart) -> str:
    """``module:QualifiedName`` of a part's class, as avatar files record it."""
    return f"{type(part).__module__}:{type(part).__qualname__}"


def part_from_file_state(name: str, entry: dict, *, device="cpu") -> AvatarPart:
    """Rebuild part ``name`` of an avatar file from its entry ``{"type": class path, "state": ...}``."""
    path = entry.get("type", "")
    module_name, _, qualname = path.partition(":") if isinstance(path, str) else ("", "", "")
    if not _importable_part_module(module_name):
        raise ValueError(f"avatar file: part {name!r} names {path!r}, which is neither in warpavatar nor in a "
                         "package that registers warpavatar extensions; it was not imported")
    try:
        cls = importlib.import_module(module_name)
        for attribute in qualname.split("."):
            cls = getattr(cls, attribute)
    except (ImportError, AttributeError, ValueError) as error:
        raise ValueError(f"avatar file: part {name!r} needs {path!r}, which cannot be imported ({error})") from None
    if not (isinstance(cls, type) and issubclass(cls, AvatarPart)):
        raise ValueError(f"avatar file: part {name!r} names {path!r}, which is not an avatar part")
    return cls.from_file_state(entry["state"], device=device)


EXTENSION_ENTRY_POINT_GROUP = "warpavatar.extensions"
"""The entry-point group through which installed packages register extensions (and so the parts they save)."""


def _importable_part_module(module_name: str) -> bool:
    """Whether an avatar file may make ``module_name`` be imported: a module of this package, one that is
    imported already (importing it again runs nothing), or one of a top-level package that registers
    extensions through :data:`EXTENSION_ENTRY_POINT_GROUP`. Any other name in a file is refused, so a crafted
    file cannot run the top-level code of an arbitrary installed module."""
    if not module_name or any(not part.isidentifier() for part in module_name.split(".")):
        return False
    top = module_name.partition(".")[0]
    if top == "warpavatar" or module_name in sys.modules:
        return True
    try:
        entry_points = importlib.metadata.entry_points(group=EXTENSION_ENTRY_POINT_GROUP)
    except Exception:  # noqa: BLE001 - broken metadata of some distribution: trust none
        return False
    return any(entry.value.partition(":")[0].partition(".")[0] == top for entry in entry_points)
