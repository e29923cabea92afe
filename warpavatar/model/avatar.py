"""The animatable avatar: canonical Gaussians + voxel skinning field + skeleton, posed by linear blend skinning,
plus optional parts (:mod:`warpavatar.model.parts`).

Data flows one way: a pose (bone transforms [J,4,4], rest -> posed world, as poses.npz stores them) becomes the
skinning transforms (the parts may append some: joints grown on the skeleton), the parts reshape the canonical
Gaussians, the skinning field gives each its weights (read at the reshaped canonical position),
:func:`warpavatar.ops.lbs` moves positions and rotations, the parts may change the posed Gaussians, and the
colours seen from the camera (which the parts may change too) go to the rasterizer.

Colours are spherical harmonics in each Gaussian's canonical frame. Under ``shading="world"`` (the default of
a fit) they are evaluated for the direction from a fixed world point (the training camera's centre) rather
than from the rendering camera: with a fixed camera and a subject that turns, what varies in the training
images is how the body faces the scene's lights, not the viewing direction, so a novel camera must see the
shading the body has at that orientation. ``shading="view"`` is the usual view-dependent 3DGS colour.

An avatar file (``avatar.pt``) holds everything needed to render it: the skeleton, the Gaussians, the field's
weights and box, every part, and the config it was fitted with.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import torch

from warpavatar import ops
from warpavatar._src.precision import check_matmul_precision
from warpavatar._src.tensor_files import read_tensor_file
from warpavatar.geometry import camera_centre
from warpavatar.io.output_files import atomic_open
from warpavatar.model.frozen import FrozenCanonical
from warpavatar.model.gaussians import GaussianModel
from warpavatar.model.parts import (AvatarPart, CanonicalGaussians, PoseFrame, frame_intervals, part_class_path,
                                    part_from_file_state)
from warpavatar.model.skinning_field import VoxelSkinningField

__all__ = ["PosedGaussians", "Avatar", "AVATAR_FORMAT"]

AVATAR_FORMAT = "warpavatar-avatar/2"
_LEGACY_FORMAT = "warpavatar-avatar/1"
# where the parts of a format-1 file (one key each) live now: key -> (part name, class path)
_LEGACY_PARTS = {
    "extra_joints": ("joint_growth", "warpavatar.extensions.joint_growth:ExtraJoints"),
    "pose_correction": ("pose_correction", "warpavatar.extensions.pose_correction:PoseCorrection"),
    "secondary_motion": ("secondary_motion", "warpavatar.extensions.secondary_motion:SecondaryMotion"),
    "dynamics": ("dynamics", "warpavatar.extensions.dynamics:SecondaryDynamics"),
    "lighting": ("lighting", "warpavatar.extensions.lighting:WorldLighting"),
}


class PosedGaussians(dict):
    """Posed Gaussians ready for :func:`warpavatar.ops.rasterize_gaussians`.

    Keys: ``means`` [N,3], ``quats`` [N,4] (w,x,y,z), ``scales`` [N,3], ``opacities`` [N],
    ``colors`` [N,(d+1)^2,3] SH coefficients, ``sh_degree`` (int), ``weights`` [N,J+E] skinning weights,
    ``canonical_quats`` [N,4] and ``canonical_means`` [N,3]: the rest-pose orientations and centres as the
    parts reshaped them, before any displacement; ``canonical_offsets`` [N,3] or None: the displacement the parts
    added to those centres before skinning (secondary motion); ``bone_transforms`` [J+E,4,4]: the skinning
    transforms used (the skeleton's, then those the parts appended, :meth:`Avatar.pose_bones`); ``frame``: the
    :class:`~warpavatar.model.parts.PoseFrame` they were posed for; ``sheet_vertices`` (only where a part places
    Gaussians on a triangle sheet): the frame's sheet vertices [V,3] by part name, detached.
    """


class Avatar(torch.nn.Module):
    """Canonical Gaussians driven by a skeleton through a voxel skinning field, with optional parts.

    Args:
        skeleton: the rest-pose skeleton (:class:`warpavatar.data.Skeleton`).
        gaussians: canonical Gaussians (rest pose, world units).
        field: the voxel skinning field over the canonical box.
    """

    def __init__(self, skeleton, gaussians: GaussianModel, field: VoxelSkinningField):
        super().__init__()
        self.skeleton = skeleton
        self.gaussians = gaussians
        self.field = field
        #: the optional parts by name, in the order their hooks run within a stage
        self.parts = torch.nn.ModuleDict()
        #: world point [3] the SH colours are evaluated from (``shading="world"``); None: the render camera
        self.shading_origin: torch.Tensor | None = None
        #: precision of the MLPs' float32 GEMMs in playback (``tf32`` or ``fp32``, on CUDA): the fit's
        #: ``--matmul-precision``, read back from the avatar file's config
        self.matmul_precision = "tf32"

    # ------------------------------------------------------------------------------------------------ parts
    def add_part(self, part: AvatarPart, *, first: bool = False) -> AvatarPart:
        """Attach a part under its name (replacing one of the same name), after the others or, with ``first``,
        before them (a part that refines the skeleton's pose must act before the parts that build on it)."""
        if not part.name:
            raise ValueError(f"{type(part).__name__} has no name")
        if first:
            others = [(name, other) for name, other in self.parts.items() if name != part.name]
            self.parts = torch.nn.ModuleDict([(part.name, part), *others])
        else:
            self.parts[part.name] = part
        return part

    def part(self, name: str) -> AvatarPart | None:
        """The part called ``name``, or None."""
        return self.parts[name] if name in self.parts else None

    @property
    def joint_count(self) -> int:
        """Joints J of the skeleton."""
        return len(self.skeleton.names)

    def _added_joint_parents(self) -> list[torch.Tensor]:
        return [parents for part in self.parts.values() if (parents := part.added_joint_parents()) is not None]

    @property
    def grown_joint_count(self) -> int:
        """Skinning transforms the parts append to the skeleton's (joints grown on it), 0 without."""
        return sum(int(parents.numel()) for parents in self._added_joint_parents())

    def skinning_groups(self) -> torch.Tensor | None:
        """[J+E, J] 0/1 matrix mapping each skinning output to the skeleton joint it belongs to (itself, or the
        parent of a grown joint), or None when no part appends joints."""
        added = self._added_joint_parents()
        if not added:
            return None
        device = self.gaussians.means.device
        groups = torch.cat([torch.arange(self.joint_count, device=device), *(p.to(device) for p in added)])
        return torch.nn.functional.one_hot(groups, self.joint_count).float()

    def pose_bones(self, bone_transforms: torch.Tensor, *, inputs: Mapping[str, Any] | None = None) -> torch.Tensor:
        """Every skinning transform [J+E,4,4] for the skeleton's [J,4,4]: the skeleton's, then those the parts
        append (E = 0 without).

        Args:
            bone_transforms: [J,4,4] rest-to-posed transforms.
            inputs: explicit inputs of parts by part name (see :meth:`pose`), e.g. ``{"joint_growth": [E,4]}``
                rotations of grown joints.
        """
        return self._skinning_transforms(self._frame(bone_transforms, None, inputs))

    def _frame(self, bone_transforms: torch.Tensor, frame_index: int | None, inputs: Mapping[str, Any] | None,
               skeleton_pose: torch.Tensor | None = None) -> PoseFrame:
        for name, pose in (("bone_transforms", bone_transforms), ("skeleton_pose", skeleton_pose)):
            if pose is not None and pose.shape != (self.joint_count, 4, 4):
                raise ValueError(f"{name} must have shape [{self.joint_count}, 4, 4] for this avatar's skeleton, "
                                 f"got {list(pose.shape)}")
        if inputs and not set(inputs) <= set(self.parts.keys()):
            raise ValueError(f"inputs for parts this avatar does not have: {sorted(set(inputs) - set(self.parts))} "
                             f"(its parts: {', '.join(self.parts) or 'none'})")
        return PoseFrame(bone_transforms, frame_index, inputs or {}, skeleton_pose)

    def _skinning_transforms(self, frame: PoseFrame) -> torch.Tensor:
        bones = frame.bone_transforms if frame.skeleton_pose is None else frame.skeleton_pose
        for part in self.parts.values():
            bones = part.skinning_transforms(bones, frame)
        return bones

    def rig(self):
        """The skeleton with the joints the parts append (for exports: UsdSkel)."""
        skeleton = self.skeleton
        for part in self.parts.values():
            skeleton = part.extend_rig(skeleton)
        return skeleton

    def prepare_sequence(self, bone_transforms, *, frame_ids=None, fps: float = 30.0,
                         progress: bool = False) -> None:
        """Get ready to pose the frames of a motion (parts with state over time roll it out once, so that
        :meth:`pose` of any of its frames gets that frame's state; others need nothing).

        Args:
            bone_transforms: [T,J,4,4] consecutive frames of the motion (numpy or torch).
            frame_ids: [T] frame numbers of the rows (default ``0..T-1``); with ``fps`` they give the time steps.
            fps: frames per second of the frame numbers.
            progress: show a progress bar over the frames.
        """
        stateful = [part for part in self.parts.values()
                    if type(part).prepare_sequence is not AvatarPart.prepare_sequence]
        if not stateful or len(bone_transforms) == 0:
            return
        device = self.gaussians.means.device
        bones = torch.stack([self.pose_bones(b) for b in
                             torch.as_tensor(bone_transforms, dtype=torch.float32, device=device)])
        intervals = frame_intervals(range(bones.shape[0]) if frame_ids is None else frame_ids, fps).to(device)
        for part in stateful:
            part.prepare_sequence(bones, intervals, progress=progress)

    # ----------------------------------------------------------------------------------------------- posing
    def pose(self, bone_transforms: torch.Tensor, *, sh_degree: int | None = None, frame_index: int | None = None,
             grid: torch.Tensor | None = None, inputs: Mapping[str, Any] | None = None,
             skeleton_pose: torch.Tensor | None = None, frozen: FrozenCanonical | None = None) -> PosedGaussians:
        """Pose the canonical Gaussians.

        Args:
            bone_transforms: [J,4,4] rest-to-posed transforms of this frame (float32, the avatar's device).
            sh_degree: SH degree to render with (default: all the avatar has).
            frame_index: index of the frame in its prepared sequence, for parts that keep state over time.
            grid: precomputed skinning grid (:meth:`VoxelSkinningField.grid_weights`), to share across calls.
            inputs: explicit inputs of parts by part name (see :class:`~warpavatar.model.parts.PoseFrame`).
            skeleton_pose: [J,4,4] the skeleton's transforms to skin with, while ``bone_transforms`` still says
                which instant this is (test-time pose refinement).
            frozen: the activated Gaussians and their weights at the stored centres, kept for a frozen avatar
                (playback: :class:`~warpavatar.model.frozen.FrozenCanonical`, refreshed with ``grid`` and
                this degree), used instead of computing them (no gradients reach the parameters through them).
        """
        gaussians = self.gaussians
        degree = gaussians.sh_degree if sh_degree is None else min(sh_degree, gaussians.sh_degree)
        frame = self._frame(bone_transforms, frame_index, inputs, skeleton_pose)
        bones = self._skinning_transforms(frame)
        if frozen is None:
            quats, scales, opacities, colors = (gaussians.normalized_quats, gaussians.scales, gaussians.opacities,
                                                gaussians.sh_coefficients(degree))
        elif frozen.sh_degree != degree:
            raise ValueError(f"the frozen tensors keep SH degree {frozen.sh_degree}, posing asks for {degree}")
        else:
            quats, scales, opacities, colors = frozen.quats, frozen.scales, frozen.opacities, frozen.colors
        canonical = CanonicalGaussians(means=gaussians.means, quats=quats, scales=scales, offset=None,
                                       rest_means=gaussians.means)
        for part in self.parts.values():
            canonical = part.deform_canonical(canonical, bones, frame)
        if frozen is not None and canonical.means is gaussians.means:  # read where the kept weights were
            weights = frozen.weights
        else:
            weights = self.field.weights(canonical.means, grid)
        moved = canonical.means if canonical.offset is None else canonical.means + canonical.offset
        means, quats = ops.lbs(moved.contiguous(), weights, bones, quats=canonical.quats)
        posed = PosedGaussians(means=means, quats=quats, scales=canonical.scales, opacities=opacities,
                               colors=colors, sh_degree=degree, weights=weights,
                               canonical_quats=canonical.quats, canonical_means=canonical.means,
                               canonical_offsets=canonical.offset,
                               bone_transforms=bones, frame=frame)
        for part in self.parts.values():
            posed = part.deform_posed(posed, frame)
        return posed

    def render(self, camera, bone_transforms: torch.Tensor, *, background: torch.Tensor | None = None,
               sh_degree: int | None = None, frame_index: int | None = None, grid: torch.Tensor | None = None,
               densify_grad_out: torch.Tensor | None = None, return_info: bool = False,
               inputs: Mapping[str, Any] | None = None, skeleton_pose: torch.Tensor | None = None):
        """Render the avatar in a pose through a camera (:meth:`pose`, then :meth:`rasterize`).

        Args:
            camera: object with ``K`` [3,3], ``world_to_camera`` [4,4] (numpy or torch), ``width``, ``height``.
            bone_transforms: [J,4,4] pose.
            background: [3] colour in 0..1 (default black).
            inputs, skeleton_pose: see :meth:`pose`.

        Returns:
            ``(image [H,W,3], alpha [H,W], depth [H,W])``, plus the rasterizer's info dict when ``return_info``.
        """
        posed = self.pose(bone_transforms, sh_degree=sh_degree, frame_index=frame_index, grid=grid, inputs=inputs,
                          skeleton_pose=skeleton_pose)
        return self.rasterize(posed, camera, background=background, densify_grad_out=densify_grad_out,
                              return_info=return_info)

    def rasterize(self, posed: PosedGaussians, camera, *, background: torch.Tensor | None = None,
                  densify_grad_out: torch.Tensor | None = None, return_info: bool = False,
                  intersection_capacity: int | None = None):
        """Shade posed Gaussians for a camera (:meth:`view_colors`, then the parts) and rasterize them; returns
        what :meth:`render` returns (``intersection_capacity``: see :func:`warpavatar.ops.rasterize_gaussians`)."""
        device = self.gaussians.means.device
        K = torch.as_tensor(camera.K, dtype=torch.float32, device=device)
        world_to_camera = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device)
        colors = self.view_colors(posed, world_to_camera, origin=self.shading_origin)
        for part in self.parts.values():
            colors = part.shade(colors, posed, posed["frame"])
        return ops.rasterize_gaussians(
            posed["means"], posed["quats"], posed["scales"], posed["opacities"], colors, K, world_to_camera,
            int(camera.width), int(camera.height), background=background,
            densify_grad_out=densify_grad_out, return_info=return_info, intersection_capacity=intersection_capacity)

    @staticmethod
    def view_colors(posed: PosedGaussians, world_to_camera: torch.Tensor, *, origin: torch.Tensor | None = None
                    ) -> torch.Tensor:
        """RGB [N,3] of posed Gaussians seen from a camera, with SH evaluated in each Gaussian's canonical frame.

        The direction (from ``origin`` [3] when given, else from the camera centre, to each Gaussian) is
        rotated back by the Gaussian's skinning rotation, so colour stays attached to the body as it turns (a
        world-frame evaluation would tie colours to where the subject faced during training).
        """
        means = posed["means"]
        if origin is None:
            origin = camera_centre(world_to_camera)
        # one fused Warp kernel forward and one backward (the op-by-op torch code is _torch_impl.view_colors)
        return ops.view_colors(means, posed["quats"], posed["canonical_quats"], posed["colors"], origin.to(means),
                               sh_degree=posed["sh_degree"])

    # ------------------------------------------------------------------------------------------------ files
    def state_for_file(self, config: dict | None = None) -> dict:
        return {
            "format": AVATAR_FORMAT,
            "skeleton": self.skeleton.to_json_dict(),
            "gaussians": self.gaussians.state_for_checkpoint(),
            "field": {
                "state_dict": {k: v.detach().cpu() for k, v in self.field.state_dict().items()},
                "joint_count": self.field.joint_count,
                "grid_shape": list(self.field.grid_shape),
                "hyper": dict(self.field.hyper),
            },
            "parts": {name: {"type": part_class_path(part), "state": part.state_for_file()}
                      for name, part in self.parts.items()},
            "shading_origin": None if self.shading_origin is None else self.shading_origin.detach().cpu(),
            "config": config or {},
        }

    def save(self, path: str | os.PathLike, *, config: dict | None = None) -> Path:
        """Write the avatar file atomically (a temporary name of its own, synced, then renamed; a full disk is one
        :class:`~warpavatar.io.output_files.DiskFullError` and leaves no file behind)."""
        path = Path(path)
        with atomic_open(path) as stream:
            torch.save(self.state_for_file(config), stream)
        return path

    @classmethod
    def from_state(cls, state: dict, *, device="cpu") -> "Avatar":
        from warpavatar.data import Skeleton

        if state.get("format") == _LEGACY_FORMAT:
            state = _upgrade_legacy_state(state)
        if state.get("format") != AVATAR_FORMAT:
            raise ValueError(f"not a warpavatar avatar this version reads (format {state.get('format')!r}; it "
                             f"reads {AVATAR_FORMAT!r} and {_LEGACY_FORMAT!r})")
        skeleton = Skeleton.from_json_dict(state["skeleton"], source="avatar file")
        gaussians = GaussianModel.from_checkpoint(state["gaussians"], device=device)
        field_state = state["field"]
        field = VoxelSkinningField(field_state["state_dict"]["bbox_min"], field_state["state_dict"]["bbox_max"],
                                   field_state["joint_count"], **field_state["hyper"])
        field.load_state_dict(field_state["state_dict"])
        avatar = cls(skeleton, gaussians, field.to(device))
        for name, entry in state["parts"].items():
            part = part_from_file_state(name, entry, device=device)
            if part.name != name:
                raise ValueError(f"avatar file: part {name!r} rebuilt as a {part.name!r} part")
            avatar.add_part(part)
        if avatar.field.joint_count != avatar.joint_count + avatar.grown_joint_count:
            raise ValueError(f"avatar file: the skinning field has {avatar.field.joint_count} outputs but the "
                             f"skeleton {avatar.joint_count} joints and {avatar.grown_joint_count} grown ones")
        if state.get("shading_origin") is not None:
            avatar.shading_origin = state["shading_origin"].to(device=device, dtype=torch.float32)
        config = state.get("config") or {}
        avatar.matmul_precision = check_matmul_precision(config.get("matmul_precision", avatar.matmul_precision))
        return avatar

    @classmethod
    def load(cls, path: str | os.PathLike, *, device="cpu") -> "Avatar":
        """Load an avatar file written by :meth:`save` (or an output folder containing ``avatar.pt``) with torch's
        weights-only unpickler: nothing in the file runs.

        Raises:
            FileNotFoundError: no such file.
            ValueError: a file holding objects other than tensors and plain containers (not loaded), one that
                cannot be read, holds no dict, misses entries or is of another format; one line naming it.
        """
        path = Path(path)
        if path.is_dir():
            path = path / "avatar.pt"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no avatar file here (run warpavatar-fit first)")
        state = read_tensor_file(path, what="avatar file")  # tensors and plain containers only: nothing runs
        try:
            return cls.from_state(state, device=device)
        except KeyError as error:
            raise ValueError(f"{path}: a damaged or incomplete avatar file (missing {error})") from None
        except (TypeError, AttributeError, IndexError) as error:  # an entry of the wrong kind
            raise ValueError(f"{path}: a damaged or incomplete avatar file ({error})") from None
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None


def _upgrade_legacy_state(state: dict) -> dict:
    """A format-1 avatar state (one key per optional part) in the layout of format 2 (``parts`` by name)."""
    parts = {}
    for key in ("extra_joints", "pose_correction", "secondary_motion", "lighting"):
        saved = state.get(key)
        if saved is None:
            continue
        if key == "secondary_motion" and saved.get("kind") == "dynamics":
            key = "dynamics"
        if key == "lighting":  # format 1 kept the lighting's state dict itself
            saved = {"state_dict": saved}
        name, path = _LEGACY_PARTS[key]
        parts[name] = {"type": path, "state": saved}
    upgraded = {k: v for k, v in state.items() if k not in _LEGACY_PARTS}
    upgraded.update(format=AVATAR_FORMAT, parts=parts)
    return upgraded
