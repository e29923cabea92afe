"""The animatable avatar: canonical Gaussians + voxel skinning field + skeleton, posed by linear blend skinning.

Data flows one way: a pose (bone transforms [J,4,4], rest -> posed world, as poses.npz stores them) goes
through :meth:`Avatar.pose_bones` (which appends the transforms of joints grown by ToMiE's skeleton growth,
:class:`~warpavatar.joint_growth.ExtraJoints`), the skinning field gives each canonical
Gaussian its weights (read at the pose-corrected canonical position), a secondary-motion model on SMAD's graph
(per-training-frame displacements, :class:`~warpavatar.secondary_motion.SecondaryMotion`, or learned dynamics,
:class:`~warpavatar.dynamics.SecondaryDynamics`, after :meth:`Avatar.prepare_sequence`) displaces the canonical
Gaussians, :func:`warpavatar.ops.lbs` moves positions and rotations, and each deformer in ``Avatar.deformers``
may then add further per-frame non-rigid offsets before rendering.

Colours are spherical harmonics in each Gaussian's canonical frame. Under ``shading="world"`` (the default of
a fit) they are evaluated for the direction from a fixed world point (the training camera's centre) rather
than from the rendering camera: with a fixed camera and a subject that turns, what varies in the training
images is how the body faces the scene's lights, not the viewing direction, so a novel camera must see the
shading the body has at that orientation. ``shading="view"`` is the usual view-dependent 3DGS colour.

An avatar file (``avatar.pt``) holds everything needed to render it: the skeleton, the Gaussians, the field's
weights and box, and the config it was fitted with.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from warpavatar import ops
from warpavatar._torch_impl.splat import sh_basis
from warpavatar.gaussians import SH_C0, GaussianModel
from warpavatar.joint_growth import ExtraJoints
from warpavatar.pose_correction import PoseCorrection
from warpavatar.dynamics import SecondaryDynamics, frame_intervals
from warpavatar.secondary_motion import SecondaryMotion
from warpavatar.skinning_field import VoxelSkinningField

__all__ = ["Deformer", "PosedGaussians", "Avatar", "AVATAR_FORMAT", "quat_rotate", "camera_centre",
           "secondary_from_file_state"]

AVATAR_FORMAT = "warpavatar-avatar/1"


def camera_centre(world_to_camera: torch.Tensor) -> torch.Tensor:
    """World position [3] of a camera's centre from its [4,4] ``world_to_camera`` (``-R^T t``)."""
    return -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]


def secondary_from_file_state(state: dict, *, device="cpu"):
    """Rebuild a secondary-motion model (per-frame displacements, or learned dynamics) from its saved state."""
    if state.get("kind") == "dynamics":
        return SecondaryDynamics.from_file_state(state, device=device)
    return SecondaryMotion.from_file_state(state, device=device)


def quat_rotate(quats: torch.Tensor, vectors: torch.Tensor, *, inverse: bool = False) -> torch.Tensor:
    """Rotate vectors [N,3] by unit quaternions [N,4] (w, x, y, z), or by their inverses."""
    w, axis = quats[:, :1], quats[:, 1:]
    if inverse:
        axis = -axis
    t = 2.0 * torch.cross(axis, vectors, dim=-1)
    return vectors + w * t + torch.cross(axis, t, dim=-1)


class PosedGaussians(dict):
    """Posed Gaussians ready for :func:`warpavatar.ops.rasterize_gaussians`.

    Keys: ``means`` [N,3], ``quats`` [N,4] (w,x,y,z), ``scales`` [N,3], ``opacities`` [N],
    ``colors`` [N,(d+1)^2,3] SH coefficients, ``sh_degree`` (int), ``weights`` [N,J+E] skinning weights,
    ``canonical_quats`` [N,4] and ``canonical_means`` [N,3]: the (pose-corrected) rest-pose orientations and
    centres, before secondary motion; ``bone_transforms`` [J+E,4,4]: the skinning transforms used (the
    skeleton's, then any grown joints', :meth:`Avatar.pose_bones`).
    """


class Deformer(Protocol):
    """A per-frame non-rigid correction applied after skinning (e.g. a secondary-motion model)."""

    def __call__(self, posed: PosedGaussians, *, frame_index: int | None) -> PosedGaussians: ...


class Avatar(torch.nn.Module):
    """Canonical Gaussians driven by a skeleton through a voxel skinning field.

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
        self.deformers: list[Deformer] = []
        self.pose_correction: PoseCorrection | None = None
        self.secondary_motion: SecondaryMotion | None = None
        #: joints grown on the skeleton (ToMiE); the skinning field has one output per skeleton and grown joint
        self.extra_joints: ExtraJoints | None = None
        #: optional global world-frame irradiance (:class:`warpavatar.lighting.WorldLighting`)
        self.lighting: torch.nn.Module | None = None
        #: world point [3] the SH colours are evaluated from (``shading="world"``); None: the render camera
        self.shading_origin: torch.Tensor | None = None

    @property
    def joint_count(self) -> int:
        return len(self.skeleton.names)

    @property
    def grown_joint_count(self) -> int:
        """Number of joints grown on the skeleton (ToMiE), 0 without growth."""
        return 0 if self.extra_joints is None else self.extra_joints.count

    def pose_bones(self, bone_transforms: torch.Tensor, *, extra_rotations: torch.Tensor | None = None
                   ) -> torch.Tensor:
        """Full set of skinning transforms [J+E,4,4] for the skeleton's [J,4,4]: the skeleton's, then those of
        the E grown joints (E = 0 without growth).

        Args:
            bone_transforms: [J,4,4] rest-to-posed transforms.
            extra_rotations: [E,4] (w, x, y, z) rotations of the grown joints in their parents' rest frames, to
                animate them explicitly; by default a training instant's pose gets its learned rotations and any
                other pose the identity (see :class:`~warpavatar.joint_growth.ExtraJoints`).
        """
        if bone_transforms.shape != (self.joint_count, 4, 4):
            raise ValueError(f"bone_transforms must have shape [{self.joint_count}, 4, 4] for this avatar's "
                             f"skeleton, got {list(bone_transforms.shape)}")
        if self.extra_joints is None:
            if extra_rotations is not None:
                raise ValueError("extra_rotations given but this avatar has no grown joints")
            return bone_transforms
        return torch.cat([bone_transforms, self.extra_joints.transforms(bone_transforms, extra_rotations)])

    def rig(self):
        """The skeleton with the grown joints appended (names ``grown_<parent>_<k>``, heads at their canonical
        positions, tails 10 % of the parent's length further along the parent), for exports (UsdSkel)."""
        from warpavatar.data import Skeleton

        skeleton = self.skeleton
        if self.extra_joints is None:
            return skeleton
        extra = self.extra_joints
        parents = extra.parents.cpu().numpy()
        heads = extra.positions().detach().cpu().numpy().astype(np.float32)
        direction = skeleton.tails[parents] - skeleton.heads[parents]
        names = list(skeleton.names)
        for k, parent in enumerate(parents):
            names.append(f"grown_{skeleton.names[parent]}_{k}")
        return Skeleton(names=names, parents=np.concatenate([skeleton.parents, parents]).astype(np.int32),
                        heads=np.concatenate([skeleton.heads, heads]).astype(np.float32),
                        tails=np.concatenate([skeleton.tails, heads + 0.1 * direction]).astype(np.float32),
                        up=skeleton.up)

    def prepare_sequence(self, bone_transforms, *, frame_ids=None, fps: float = 30.0,
                         progress: bool = False) -> None:
        """Get ready to pose the frames of a motion in which secondary dynamics matter.

        With learned dynamics (:class:`~warpavatar.dynamics.SecondaryDynamics`) this rolls the motion out
        once, so that :meth:`pose` of any of its frames gets that frame's cloth state; other avatars need
        nothing and this does nothing.

        Args:
            bone_transforms: [T,J,4,4] consecutive frames of the motion (numpy or torch).
            frame_ids: [T] frame numbers of the rows (default ``0..T-1``); with ``fps`` they give the time steps.
            fps: frames per second of the frame numbers.
            progress: show a progress bar over the frames.
        """
        if not isinstance(self.secondary_motion, SecondaryDynamics) or len(bone_transforms) == 0:
            return
        device = self.gaussians.means.device
        bones = torch.stack([self.pose_bones(b) for b in
                             torch.as_tensor(bone_transforms, dtype=torch.float32, device=device)])
        if frame_ids is None:
            frame_ids = range(bones.shape[0])
        intervals = frame_intervals(frame_ids, fps).to(device)
        self.secondary_motion.prepare_sequence(bones, intervals, progress=progress)

    def pose(self, bone_transforms: torch.Tensor, *, sh_degree: int | None = None, frame_index: int | None = None,
             grid: torch.Tensor | None = None, node_displacement: torch.Tensor | None = None,
             extra_rotations: torch.Tensor | None = None) -> PosedGaussians:
        """Pose the canonical Gaussians.

        Args:
            bone_transforms: [J,4,4] rest-to-posed transforms of this frame (float32, the avatar's device).
            sh_degree: SH degree to render with (default: all the avatar has).
            frame_index: index of the frame in its sequence, passed to deformers that keep state over time.
            grid: precomputed skinning grid (:meth:`VoxelSkinningField.grid_weights`), to share across calls.
            node_displacement: [M,3] secondary displacement of the graph nodes to use instead of the one the
                secondary-motion model looks up for this pose (a fit passes the state it is training).
            extra_rotations: see :meth:`pose_bones`.
        """
        gaussians = self.gaussians
        degree = gaussians.sh_degree if sh_degree is None else min(sh_degree, gaussians.sh_degree)
        bones = self.pose_bones(bone_transforms, extra_rotations=extra_rotations)
        skeleton_bones = bones[: self.joint_count]
        canonical_means, canonical_quats, scales = gaussians.means, gaussians.normalized_quats, gaussians.scales
        if self.pose_correction is not None:
            canonical_means, canonical_quats, scales = self.pose_correction(
                canonical_means, canonical_quats, scales, skeleton_bones)
        weights = self.field.weights(canonical_means, grid)
        displaced_means = canonical_means
        if self.secondary_motion is not None:
            if node_displacement is None:
                node_displacement = self.secondary_motion.node_displacement(bones)
            displaced_means = canonical_means + self.secondary_motion.gaussian_displacement(
                gaussians.means, node_displacement)
        means, quats = ops.lbs(displaced_means.contiguous(), weights, bones, quats=canonical_quats)
        posed = PosedGaussians(means=means, quats=quats, scales=scales, opacities=gaussians.opacities,
                               colors=gaussians.sh_coefficients(degree), sh_degree=degree, weights=weights,
                               canonical_quats=canonical_quats, canonical_means=canonical_means,
                               bone_transforms=bones)
        for deformer in self.deformers:
            posed = deformer(posed, frame_index=frame_index)
        return posed

    def render(self, camera, bone_transforms: torch.Tensor, *, background: torch.Tensor | None = None,
               sh_degree: int | None = None, frame_index: int | None = None, grid: torch.Tensor | None = None,
               densify_grad_out: torch.Tensor | None = None, return_info: bool = False,
               node_displacement: torch.Tensor | None = None, extra_rotations: torch.Tensor | None = None):
        """Render the avatar in a pose through a camera.

        Args:
            camera: object with ``K`` [3,3], ``world_to_camera`` [4,4] (numpy or torch), ``width``, ``height``.
            bone_transforms: [J,4,4] pose.
            background: [3] colour in 0..1 (default black).
            node_displacement: see :meth:`pose`.
            extra_rotations: see :meth:`pose_bones`.

        Returns:
            ``(image [H,W,3], alpha [H,W], depth [H,W])``, plus the rasterizer's info dict when ``return_info``.
        """
        device = self.gaussians.means.device
        posed = self.pose(bone_transforms, sh_degree=sh_degree, frame_index=frame_index, grid=grid,
                          node_displacement=node_displacement, extra_rotations=extra_rotations)
        K = torch.as_tensor(camera.K, dtype=torch.float32, device=device)
        world_to_camera = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device)
        colors = self.view_colors(posed, world_to_camera, origin=self.shading_origin)
        if self.lighting is not None:
            colors = self.lighting(colors, posed)
        return ops.rasterize_gaussians(
            posed["means"], posed["quats"], posed["scales"], posed["opacities"], colors, K, world_to_camera,
            int(camera.width), int(camera.height), background=background,
            densify_grad_out=densify_grad_out, return_info=return_info)

    @staticmethod
    def view_colors(posed: PosedGaussians, world_to_camera: torch.Tensor, *, origin: torch.Tensor | None = None
                    ) -> torch.Tensor:
        """RGB [N,3] of posed Gaussians seen from a camera, with SH evaluated in each Gaussian's canonical frame.

        The direction (from ``origin`` [3] when given, else from the camera centre, to each Gaussian) is
        rotated back by the Gaussian's skinning rotation, so colour stays attached to the body as it turns (a
        world-frame evaluation would tie colours to where the subject faced during training).
        """
        coefficients = posed["colors"]
        if posed["sh_degree"] == 0:
            return torch.clamp_min(coefficients[:, 0] * SH_C0 + 0.5, 0.0)
        if origin is None:
            origin = camera_centre(world_to_camera)
        directions = posed["means"] - origin.to(posed["means"])
        directions = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        # skinning rotation R_i = R(q_posed) R(q_canonical)^T, so R_i^T d = R(q_canonical) R(q_posed)^T d
        directions = quat_rotate(posed["canonical_quats"], quat_rotate(posed["quats"], directions, inverse=True))
        basis = sh_basis(posed["sh_degree"], directions)  # [N,(d+1)^2]
        return torch.clamp_min((basis[:, :, None] * coefficients).sum(dim=1) + 0.5, 0.0)

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
            "pose_correction": None if self.pose_correction is None else {
                "state_dict": {k: v.detach().cpu() for k, v in self.pose_correction.state_dict().items()},
                "hyper": dict(self.pose_correction.hyper),
            },
            "secondary_motion": None if self.secondary_motion is None else self.secondary_motion.state_for_file(),
            "extra_joints": None if self.extra_joints is None else self.extra_joints.state_for_file(),
            "shading_origin": None if self.shading_origin is None else self.shading_origin.detach().cpu(),
            "lighting": None if self.lighting is None else {
                k: v.detach().cpu() for k, v in self.lighting.state_dict().items()},
            "config": config or {},
        }

    def save(self, path: str | os.PathLike, *, config: dict | None = None) -> Path:
        """Write the avatar file atomically (temporary name, then rename)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state_for_file(config), tmp)
        os.replace(tmp, path)
        return path

    @classmethod
    def from_state(cls, state: dict, *, device="cpu") -> "Avatar":
        from warpavatar.data import Skeleton

        if state.get("format") != AVATAR_FORMAT:
            raise ValueError(f"not a warpavatar avatar (format {state.get('format')!r}, expected {AVATAR_FORMAT!r})")
        skeleton = Skeleton.from_json_dict(state["skeleton"], source="avatar file")
        gaussians = GaussianModel.from_checkpoint(state["gaussians"], device=device)
        field_state = state["field"]
        hyper = field_state["hyper"]
        field = VoxelSkinningField(field_state["state_dict"]["bbox_min"], field_state["state_dict"]["bbox_max"],
                                   field_state["joint_count"], **hyper)
        field.load_state_dict(field_state["state_dict"])
        avatar = cls(skeleton, gaussians, field.to(device))
        correction_state = state.get("pose_correction")
        if correction_state is not None:
            weights = correction_state["state_dict"]
            correction = PoseCorrection(weights["bbox_min"], weights["bbox_max"], weights["parents"],
                                        **correction_state["hyper"])
            correction.load_state_dict(weights)
            avatar.pose_correction = correction.to(device)
        if state.get("secondary_motion") is not None:
            avatar.secondary_motion = secondary_from_file_state(state["secondary_motion"], device=device)
        if state.get("extra_joints") is not None:
            avatar.extra_joints = ExtraJoints.from_file_state(state["extra_joints"], device=device)
            if avatar.field.joint_count != avatar.joint_count + avatar.grown_joint_count:
                raise ValueError(f"avatar file: the skinning field has {avatar.field.joint_count} outputs but the "
                                 f"skeleton {avatar.joint_count} joints and {avatar.grown_joint_count} grown ones")
        if state.get("lighting") is not None:
            from warpavatar.lighting import WorldLighting

            lighting = WorldLighting(state["lighting"]["heads"], state["lighting"]["tails"])
            lighting.load_state_dict(state["lighting"])
            avatar.lighting = lighting.to(device)
        if state.get("shading_origin") is not None:
            avatar.shading_origin = state["shading_origin"].to(device=device, dtype=torch.float32)
        return avatar

    @classmethod
    def load(cls, path: str | os.PathLike, *, device="cpu") -> "Avatar":
        """Load an avatar file written by :meth:`save` (or an output folder containing ``avatar.pt``)."""
        path = Path(path)
        if path.is_dir():
            path = path / "avatar.pt"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no avatar file here (run warpavatar-fit first)")
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as error:  # noqa: BLE001 - any unreadable file gets the same clear message
            raise ValueError(f"{path}: cannot read the avatar file ({error})") from error
        return cls.from_state(state, device=device)
