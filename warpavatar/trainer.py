"""Fitting an avatar to a video folder (TAGA's forward path): initialization, staged training, checkpoints.

Stages (TAGA appendix C): (1) warm-up: the skinning field alone distils a rigid bone-distance prior;
(2) Gaussian-only: the Gaussians train under that frozen field; (3) joint: the field trains too, with the bone
regularization; from ``secondary_from`` on, a secondary-motion model on SMAD's graph (built then from the
canonical Gaussians) trains with it: per-frame displacements, or learned dynamics rolled out over the training
sequence (truncated backpropagation through ``dynamics_window`` frames from cached states); between
``backward_from`` and ``backward_until``, TAGA's backward mapping (when enabled) adds its cycle losses; at
``grow_at``, ToMiE's skeleton growth (when enabled) adds joints where the position gradients stay large.
Adaptive density control (3DGS) runs with a Gaussian budget (ToMiE appendix A.4).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
import tqdm

from warpavatar import ops
from warpavatar.avatar import Avatar, camera_centre
from warpavatar.backward_mapping import BackwardMapping
from warpavatar.config import FitConfig
from warpavatar.dynamics import DynamicsState, SecondaryDynamics, frame_intervals
from warpavatar.gaussians import GaussianModel
from warpavatar.joint_growth import (ExtraJoints, assignment_weights, joint_gradient_sums, joint_gradients,
                                     locate_parents, motion_kernel)
from warpavatar.metrics import psnr, ssim_map
from warpavatar.pose_correction import PoseCorrection
from warpavatar.secondary_motion import SecondaryMotion, voxel_downsample
from warpavatar.skinning_field import VoxelSkinningField, bone_distance_prior, bone_sample_points

__all__ = ["Trainer", "initial_gaussians", "CHECKPOINT_NAME"]

CHECKPOINT_NAME = "checkpoint.pt"


def _project(points: torch.Tensor, K: torch.Tensor, world_to_camera: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    camera = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = camera[:, 2]
    pixels = camera[:, :2] / z.clamp_min(1e-6)[:, None] * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])
    return pixels, z


def initial_gaussians(skeleton, video, config: FitConfig, *, generator: torch.Generator, device
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Template-free initialization: points around bone midpoints, refined by carving with the masks.

    Returns:
        (positions [N,3], colours [N,3], bbox_min [3], bbox_max [3]) in the canonical (rest) world frame.
    """
    heads = torch.as_tensor(skeleton.heads, dtype=torch.float32)
    tails = torch.as_tensor(skeleton.tails, dtype=torch.float32)
    lengths = (tails - heads).norm(dim=-1)
    skeleton_min = torch.minimum(heads.min(0).values, tails.min(0).values)
    skeleton_max = torch.maximum(heads.max(0).values, tails.max(0).values)
    height = float((skeleton_max - skeleton_min).max())
    # Bone-length-aware spread: long bones get elongated clouds along themselves; short (distal) ones small.
    midpoints = (heads + tails) * 0.5
    spread = (0.25 * lengths).clamp(0.02 * height, 0.12 * height)
    per_bone = config.init_points_per_bone
    samples = (midpoints[:, None, :] + torch.randn(len(heads), per_bone, 3, generator=generator)
               * spread[:, None, None])
    points = [samples.reshape(-1, 3)]

    margin = 0.25 * height
    box_min, box_max = skeleton_min - margin, skeleton_max + margin
    temperature = config.skinning_prior_temperature * height
    if config.init_carve and video.masks is not None:
        candidates = box_min + torch.rand(config.init_carve_candidates, 3, generator=generator) * (box_max - box_min)
        carved = _carve(candidates, heads, tails, video, temperature=temperature)
        if carved.shape[0] > config.init_carve_points:
            pick = torch.randperm(carved.shape[0], generator=generator)[: config.init_carve_points]
            carved = carved[pick]
        if carved.shape[0]:
            points.append(carved)
    positions = torch.cat(points)
    # The canonical box: skeleton and carved body, with a margin for Gaussians that move outwards.
    lo = torch.minimum(skeleton_min, positions.min(0).values)
    hi = torch.maximum(skeleton_max, positions.max(0).values)
    pad = 0.08 * float((hi - lo).max())
    bbox_min, bbox_max = lo - pad, hi + pad
    positions = torch.maximum(torch.minimum(positions, bbox_max), bbox_min)
    colours = _initial_colours(positions, heads, tails, video, temperature=temperature)
    return positions.to(device), colours.to(device), bbox_min.to(device), bbox_max.to(device)


def _evenly_spaced(total: int, count: int) -> np.ndarray:
    """At most ``count`` distinct indices spread evenly over ``0..total-1`` (first and last included)."""
    return np.unique(np.linspace(0, total - 1, min(count, total)).round().astype(int))


def _frames_for_init(video, count: int = 24) -> np.ndarray:
    return _evenly_spaced(video.frame_count, count)


def _rigid_pixels(points: torch.Tensor, weights: torch.Tensor, video, t: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose canonical points [N,3] with skinning weights [N,J] to frame ``t`` and find their pixels.

    Returns:
        (row [N], column [N], valid [N]: in front of the camera and inside the image).
    """
    transforms = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32)
    blended = torch.einsum("nj,jab->nab", weights, transforms[:, :3, :])
    posed = torch.einsum("nab,nb->na", blended[:, :, :3], points) + blended[:, :, 3]
    camera = video.cameras[t]
    pixels, z = _project(posed, torch.as_tensor(camera.K, dtype=torch.float32),
                         torch.as_tensor(camera.world_to_camera, dtype=torch.float32))
    column, row = pixels[:, 0].round().long(), pixels[:, 1].round().long()
    valid = (z > 0) & (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
    return row, column, valid


def _mask_hits(video, t: int, row: torch.Tensor, column: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    hit = torch.zeros_like(valid)
    hit[valid] = torch.as_tensor(video.masks[t] > 127)[row[valid], column[valid]]
    return hit


def _carve(candidates: torch.Tensor, heads, tails, video, *, temperature: float) -> torch.Tensor:
    """Keep canonical points that, posed rigidly by the bone prior, fall inside the mask in nearly every frame."""
    weights = bone_distance_prior(candidates, heads, tails, temperature=temperature)
    inside_votes = torch.zeros(candidates.shape[0])
    seen_votes = torch.zeros(candidates.shape[0])
    for t in _frames_for_init(video):
        row, column, valid = _rigid_pixels(candidates, weights, video, t)
        seen_votes += valid.float()
        inside_votes += _mask_hits(video, t, row, column, valid).float()
    keep = (seen_votes >= 3) & (inside_votes >= 0.9 * seen_votes)
    return candidates[keep]


def _initial_colours(positions, heads, tails, video, *, temperature: float) -> torch.Tensor:
    """Mean colour each point sees where it projects inside the mask (grey where never seen)."""
    weights = bone_distance_prior(positions, heads, tails, temperature=temperature)
    total = torch.zeros(positions.shape[0], 3)
    count = torch.zeros(positions.shape[0])
    for t in _frames_for_init(video, 12):
        row, column, valid = _rigid_pixels(positions, weights, video, t)
        if video.masks is not None:
            valid = _mask_hits(video, t, row, column, valid)
        image = torch.as_tensor(video.images[t], dtype=torch.float32) / 255.0
        total[valid] += image[row[valid], column[valid]]
        count[valid] += 1
    return torch.where(count[:, None] > 0, total / count.clamp_min(1)[:, None], torch.full_like(total, 0.5))


class Trainer:
    """Fits an :class:`~warpavatar.avatar.Avatar` to one video folder.

    Args:
        video: the training :class:`~warpavatar.data.VideoFolder` (already loaded, possibly rescaled).
        config: the fit configuration.
        output_dir: where checkpoints, the avatar file, the log and previews go.
        device: torch device to train on.
    """

    def __init__(self, video, config: FitConfig, output_dir: str | os.PathLike, *, device="cpu"):
        self.video = video
        self.config = config
        self.output_dir = Path(output_dir)
        self.device = torch.device(device)
        self.output_dir.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)

        frame_count = video.frame_count
        self.train_indices = np.arange(frame_count)
        if config.max_train_frames and config.max_train_frames < frame_count:
            self.train_indices = _evenly_spaced(frame_count, config.max_train_frames)
        self.images = torch.as_tensor(video.images[self.train_indices], device=self.device)  # uint8 [T,H,W,3]
        self.masks = (torch.as_tensor(video.masks[self.train_indices], device=self.device)
                      if video.masks is not None else None)
        self.bone_transforms = torch.as_tensor(video.bone_transforms[self.train_indices], dtype=torch.float32,
                                               device=self.device)
        # seconds from each training frame to the one before it (the secondary dynamics' time steps)
        self.frame_intervals = frame_intervals(video.frame_ids[self.train_indices], video.fps).to(self.device)
        self.frame_seconds = self.frame_intervals.tolist()  # the same on the host
        # cameras with their matrices already on the device (no host-to-device copy per step)
        self.cameras = [
            SimpleNamespace(K=torch.as_tensor(c.K, dtype=torch.float32, device=self.device),
                            world_to_camera=torch.as_tensor(c.world_to_camera, dtype=torch.float32, device=self.device),
                            width=c.width, height=c.height)
            for c in (video.cameras[i] for i in self.train_indices)]
        self.background = torch.as_tensor(video.background, dtype=torch.float32, device=self.device)
        # frames rendered over a declared flat background are their own target (their edge pixels mix the
        # subject with that colour, as a render does); otherwise the mask cuts the foreground out
        self.composite_target = self.masks is not None and (
            config.target == "masked" or (config.target == "auto" and "background" not in video.meta))

        skeleton = video.skeleton
        positions, colours, bbox_min, bbox_max = initial_gaussians(skeleton, video, config, generator=self.generator,
                                                                   device=self.device)
        self.extent = float((bbox_max - bbox_min).norm()) * 0.5
        typical = torch.full_like(positions, 0.01 * self.extent)
        gaussians = GaussianModel(positions, colours, typical, sh_degree=config.sh_degree)
        field = VoxelSkinningField(bbox_min, bbox_max, skeleton.joint_count, cells=config.grid_cells,
                                   min_cells=config.grid_min_cells, hidden=config.field_hidden,
                                   layers=config.field_layers, frequencies=config.field_frequencies).to(self.device)
        self.avatar = Avatar(skeleton, gaussians, field)
        if config.shading == "world":
            self.avatar.shading_origin = torch.stack([camera_centre(c.world_to_camera) for c in self.cameras]).mean(0)
        self.secondary_optimizer: torch.optim.Optimizer | None = None
        self.dynamics_optimizer: torch.optim.Optimizer | None = None
        self.dynamics_drive: dict | None = None  # SecondaryDynamics.drive of the training sequence
        self.dynamics_cache: tuple[torch.Tensor, torch.Tensor] | None = None  # states [T,M,3] (d, u), no grad
        self._dynamics_refreshed = -1
        self.lighting_optimizer: torch.optim.Optimizer | None = None
        if config.lighting:
            from warpavatar.lighting import WorldLighting

            self.avatar.lighting = WorldLighting(torch.as_tensor(skeleton.heads), torch.as_tensor(skeleton.tails)
                                                 ).to(self.device)
            self.lighting_optimizer = torch.optim.Adam(self.avatar.lighting.parameters(), lr=config.lr_lighting)
        self.gaussians = gaussians
        self.field = field
        self.extra_joints_optimizer: torch.optim.Optimizer | None = None
        self.grown = False  # ToMiE's growth has run (whether or not any joint grew)
        self.growth_report: dict | None = None
        if config.pose_correction:
            self.avatar.pose_correction = PoseCorrection(
                bbox_min, bbox_max, torch.as_tensor(skeleton.parents), hidden=config.pose_correction_hidden,
                frame_count=len(self.train_indices) if config.frame_codes else 0
            ).to(self.device)
            if config.frame_codes:
                self.avatar.pose_correction.set_frame_poses(self.bone_transforms)
        gaussians.make_optimizer(lr_position=config.lr_position * self.extent, lr_scale=config.lr_scale,
                                 lr_rotation=config.lr_rotation, lr_opacity=config.lr_opacity, lr_color=config.lr_color)
        # the networks (skinning field, pose correction) train together from the joint stage on
        self.field_optimizer = torch.optim.Adam(self._network_parameters(), lr=config.field_lr)
        heads = torch.as_tensor(skeleton.heads, dtype=torch.float32, device=self.device)
        tails = torch.as_tensor(skeleton.tails, dtype=torch.float32, device=self.device)
        parents = torch.as_tensor(skeleton.parents, device=self.device)
        self.bone_samples, self.bone_sample_index = bone_sample_points(heads, tails, parents)
        self.bone_groups: torch.Tensor | None = None  # [J+E, J] once joints have grown
        # ToMiE's per-joint gradient statistics (Eq. 4), pooled over the densification rounds before growth
        self.joint_grad_sum = torch.zeros(skeleton.joint_count, device=self.device)
        self.joint_grad_seen = torch.zeros(skeleton.joint_count, device=self.device)
        if config.grow_joints:
            self._named_parents()  # a misspelt --grow-parents fails now, not thousands of steps in
        self.backward: BackwardMapping | None = None
        if config.backward_mapping:
            self.backward = BackwardMapping(heads, tails, parents, threshold=config.backward_threshold,
                                            neighbours=config.backward_neighbours,
                                            min_semi_axis=0.005 * self.extent,
                                            max_move=config.backward_max_move * self.extent)
        self._backward_refreshed = -1
        self.field_prior = bone_distance_prior(field.grid_points.reshape(-1, 3), heads, tails,
                                               temperature=config.skinning_prior_temperature * self.extent)
        self.step = 0
        self._frozen_grid: torch.Tensor | None = None
        self.frame_order: list[int] = []
        self._reset_densify_stats()
        self.log_path = self.output_dir / "train_log.jsonl"

    # ---------------------------------------------------------------------------------------------- helpers
    def _network_parameters(self) -> list[torch.nn.Parameter]:
        """The parameters the network optimizer trains: the skinning field's, then the pose correction's."""
        parameters = list(self.field.parameters())
        if self.avatar.pose_correction is not None:
            parameters += list(self.avatar.pose_correction.parameters())
        return parameters

    def _reset_densify_stats(self) -> None:
        count = self.gaussians.count
        self.grad_accum = torch.zeros(count, 2, device=self.device)
        self.visible_count = torch.zeros(count, device=self.device)
        # canonical position-gradient norms, for ToMiE's parent-joint localization
        self.position_grad_accum = torch.zeros(count, device=self.device)

    def _next_frame(self) -> int:
        if not self.frame_order:
            self.frame_order = torch.randperm(len(self.train_indices), generator=self.generator).tolist()
        return self.frame_order.pop()

    def _position_lr(self, step: int) -> float:
        config = self.config
        fraction = min(1.0, step / max(1, config.iterations))
        start = config.lr_position * self.extent
        end = config.lr_position_final * self.extent
        return math.exp(math.log(start) * (1 - fraction) + math.log(end) * fraction)

    def _active_sh_degree(self, step: int) -> int:
        return min(self.config.sh_degree, step // max(1, self.config.sh_increase_every))

    def target(self, index: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Ground truth of training frame ``index`` and its mask (None without masks).

        The image is the frame itself, or (``composite_target``) its masked foreground over the background
        colour (see ``FitConfig.target``).
        """
        image = self.images[index].float() / 255.0
        if self.masks is None:
            return image, None
        mask = (self.masks[index].float() / 255.0)
        if not self.composite_target:
            return image, mask
        return image * mask[..., None] + self.background * (1 - mask[..., None]), mask

    # -------------------------------------------------------------------------------------------- the stages
    def warmup_field(self) -> float:
        """Stage 1: distil the rigid bone-distance prior into the field (and the bone regularization)."""
        loss = torch.zeros(())
        for _ in range(self.config.field_warmup_steps):
            self.field_optimizer.zero_grad(set_to_none=True)
            loss = self.field.distillation_loss(self.field_prior)
            loss.backward()
            self.field_optimizer.step()
        self._frozen_grid = None
        return float(loss.detach())

    def train_step(self) -> dict:
        """One optimizer step on one training frame."""
        config = self.config
        step = self.step
        train_field = step >= config.gaussian_only_steps
        if config.grow_joints and not self.grown and step >= config.grow_at:
            self.grow_joints()
        index = self._next_frame()
        gt, mask = self.target(index)
        camera = self.cameras[index]
        self.gaussians.set_position_lr(self._position_lr(step))

        if train_field:
            grid = self.field.grid_weights()
        else:  # the field is frozen in this stage: evaluate its grid once
            if self._frozen_grid is None:
                with torch.no_grad():
                    self._frozen_grid = self.field.grid_weights()
            grid = self._frozen_grid
        correction = self.avatar.pose_correction
        if correction is not None:
            correction.requires_grad_(train_field)  # trains with the field, from the joint stage on
        if (config.secondary_motion or config.dynamics) and step >= config.secondary_from \
                and self.avatar.secondary_motion is None:
            if config.dynamics:
                self._build_dynamics(grid=grid)
            else:
                self._build_secondary_motion()
        secondary = self.avatar.secondary_motion
        dynamics_state = self._dynamics_state(index, grid) if config.dynamics and secondary is not None else None
        grad_out = torch.zeros(self.gaussians.count, 2, device=self.device)
        image, alpha, _, info = self.avatar.render(
            camera, self.bone_transforms[index], background=self.background,
            sh_degree=self._active_sh_degree(step), grid=grid, densify_grad_out=grad_out, return_info=True,
            node_displacement=None if dynamics_state is None else dynamics_state.displacement)
        l1 = (image - gt).abs().mean()
        ssim_value = ssim_map(image, gt).mean()
        loss = (1.0 - config.lambda_ssim) * l1 + config.lambda_ssim * (1.0 - ssim_value)
        if mask is not None and config.lambda_mask > 0:
            loss = loss + config.lambda_mask * (alpha - mask).abs().mean()
        if config.lambda_scale > 0:
            loss = loss + config.lambda_scale * torch.relu(self.gaussians.scales - 0.05 * self.extent).mean()
        bone = torch.zeros((), device=self.device)
        geo = skin = torch.zeros((), device=self.device)
        if train_field:
            bone = self.field.bone_loss(self.bone_samples, self.bone_sample_index, grid, groups=self.bone_groups)
            loss = loss + config.lambda_bone * bone
            if self.backward is not None and config.backward_from <= step <= config.backward_until:
                self._refresh_backward(step, index, grid)
                geo, skin = self.backward.losses(self.gaussians.means, self.field, grid)
                loss = loss + config.lambda_geo * geo + config.lambda_skin * skin
            if correction is not None:
                loss = loss + config.lambda_pose_correction * correction.regularization()
            self.field_optimizer.zero_grad(set_to_none=True)
        isometry = torch.zeros((), device=self.device)
        if dynamics_state is not None:
            isometry = secondary.isometry(dynamics_state.displacement)
            loss = (loss + config.lambda_isometry * isometry
                    + config.lambda_damping * secondary.damping(dynamics_state)
                    + config.lambda_displacement * secondary.magnitude(dynamics_state))
            self.dynamics_optimizer.zero_grad(set_to_none=True)
        elif secondary is not None:
            isometry = secondary.isometry(secondary.displacement[index])
            loss = (loss + config.lambda_isometry * isometry + config.lambda_damping * secondary.damping(index)
                    + config.lambda_displacement * secondary.magnitude(index))
            self.secondary_optimizer.zero_grad(set_to_none=True)
        self.gaussians.optimizer.zero_grad(set_to_none=True)
        if self.lighting_optimizer is not None:
            self.lighting_optimizer.zero_grad(set_to_none=True)
        if self.extra_joints_optimizer is not None:
            self.extra_joints_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self._pooling_gradients() and self.gaussians.means.grad is not None:
            with torch.no_grad():
                self.position_grad_accum += self.gaussians.means.grad.norm(dim=-1)
        self.gaussians.optimizer.step()
        if self.lighting_optimizer is not None:
            self.lighting_optimizer.step()
        if self.extra_joints_optimizer is not None:
            self.extra_joints_optimizer.step()
        if train_field:
            self.field_optimizer.step()
        if dynamics_state is not None:
            self.dynamics_optimizer.step()
        elif secondary is not None:
            secondary.sparsify_gradient()
            self.secondary_optimizer.step()

        with torch.no_grad():
            visible = (info["radii"] > 0).any(dim=-1)
            # absolute screen gradient in NDC units (pixels -> [-1, 1]) as 3DGS thresholds it
            scale = torch.tensor([camera.width * 0.5, camera.height * 0.5], device=self.device)
            self.grad_accum += grad_out * scale
            self.visible_count += visible.float()
            self._density_control(step)
        self.step += 1
        return {"loss": float(loss.detach()), "l1": float(l1.detach()), "ssim": float(ssim_value.detach()),
                "bone": float(bone.detach()), "isometry": float(isometry.detach()),
                "geo": float(geo.detach()), "skin": float(skin.detach()),
                # ambiguous Gaussians the backward mapping has corrected (its cached constraints)
                "ambiguous": (int(self.backward.index.numel()) if self.backward is not None and self.backward.ready
                              else 0),
                "psnr": psnr(image.detach(), gt), "gaussians": self.gaussians.count}

    def _density_control(self, step: int) -> None:
        config = self.config
        in_window = config.densify_from <= step <= config.densify_until
        if in_window and step > 0 and step % config.densify_every == 0:
            count = self.gaussians.count
            threshold = config.densify_grad_threshold
            budget = config.max_gaussians
            if count > budget:  # ToMiE A.4: raise the threshold as the count passes the budget
                threshold *= 2.0 + (count - budget) / (budget / 6.0)
            grad_norm = (self.grad_accum / self.visible_count.clamp_min(1)[:, None]).norm(dim=-1)
            if self._pooling_gradients():  # before cloning and pruning renumber the Gaussians
                self._fold_growth_statistics()
            if count < 1.5 * budget:
                self.gaussians.densify(grad_norm, threshold=threshold,
                                       size_split=config.densify_percent_dense * self.extent,
                                       generator=self.generator)
            self._prune()
            self._reset_densify_stats()
            if self.backward is not None:  # its cached indices no longer name the same Gaussians
                self.backward.clear()
            if self.avatar.secondary_motion is not None:
                self.avatar.secondary_motion.bind(self.gaussians.means)
        if (config.opacity_reset_every and step > 0 and step % config.opacity_reset_every == 0
                and step <= config.densify_until):
            self.gaussians.reset_opacity()

    def _prune(self) -> None:
        opacities = self.gaussians.opacities.detach()
        max_scale = self.gaussians.scales.detach().max(dim=1).values
        keep = (opacities > self.config.prune_opacity) & (max_scale < self.config.prune_max_scale * self.extent)
        if not bool(keep.all()):
            self.gaussians.prune(keep)

    # ------------------------------------------------------------------------------------- skeleton growth
    @torch.no_grad()
    def _growth_assignment(self) -> torch.Tensor:
        """ToMiE's assignment [N,J] of the current Gaussians to the skeleton's joints (Eq. 6-8)."""
        config = self.config
        means = self.gaussians.means.detach()
        weights = self.field.weights(means)[:, : self.avatar.joint_count]
        frames = self._kernel_frames()
        heads = torch.as_tensor(self.video.skeleton.heads, dtype=torch.float32, device=self.device)
        posed_means = torch.stack([ops.lbs(means, weights, self.bone_transforms[t])[0] for t in frames])
        bones = self.bone_transforms[frames]
        posed_joints = torch.einsum("tjab,jb->tja", bones[:, :, :3, :3], heads) + bones[:, :, :3, 3]
        kernel = motion_kernel(posed_means, posed_joints)
        return assignment_weights(kernel, weights, mix=config.grow_motion_mix, floor=(0.01 * self.extent) ** 2)

    def _pooling_gradients(self) -> bool:
        """Whether position gradients are being pooled for ToMiE's gradient criterion (until growth)."""
        return self.config.grow_joints and not self.grown and self.config.grow_criterion == "gradient"

    @torch.no_grad()
    def _fold_growth_statistics(self) -> None:
        """Add this densification round's per-Gaussian gradient sums to the per-joint sums (before the
        Gaussians are renumbered)."""
        numerator, denominator = joint_gradient_sums(self.position_grad_accum, self.visible_count,
                                                     self._growth_assignment())
        self.joint_grad_sum += numerator
        self.joint_grad_seen += denominator

    @torch.no_grad()
    def joint_growth_statistics(self) -> dict:
        """ToMiE's parent-joint localization on the current model (Sec. 4.1-4.2), without growing anything.

        Returns:
            dict with ``joint_gradient`` [J] (Eq. 4: mean position-gradient norm per step a Gaussian was seen,
            pooled since the start of the fit), ``parents`` [P] (the joints that would grow, largest gradient
            first) and ``threshold``.
        """
        config = self.config
        assignment = self._growth_assignment()
        if config.grow_criterion == "history":
            gradient = joint_gradients(self._history_offsets(), assignment)
        else:
            numerator, denominator = joint_gradient_sums(self.position_grad_accum, self.visible_count, assignment)
            gradient = (self.joint_grad_sum + numerator) / (self.joint_grad_seen + denominator).clamp_min(1e-12)
        parents = locate_parents(gradient, ratio=config.grow_threshold, max_count=config.grow_max_joints)
        return {"joint_gradient": gradient, "parents": parents,
                "threshold": float(config.grow_threshold * gradient.median())}

    @torch.no_grad()
    def _history_offsets(self) -> torch.Tensor:
        """RMS over the kernel frames [N] of the offsets the pose correction's frame codes add to the current
        Gaussians (the ``history`` growth criterion) [world units]."""
        correction = self.avatar.pose_correction
        means = self.gaussians.means.detach()
        frames = self._kernel_frames()
        total = torch.zeros(means.shape[0], device=self.device)
        for frame in frames:
            total += correction.history_offsets(means, int(frame)).square().sum(-1)
        return (total / len(frames)).sqrt()

    def _kernel_frames(self) -> np.ndarray:
        """Training-frame indices (evenly spaced, at most ``grow_kernel_frames``) the growth statistics use."""
        return _evenly_spaced(len(self.train_indices), self.config.grow_kernel_frames)

    def grow_joints(self) -> None:
        """Run ToMiE's growth once: locate the parent joints and give each a child (see
        :mod:`warpavatar.joint_growth`); the field gains the children's outputs and the optimizers their
        parameters. Logged to the training log either way."""
        statistics = self.joint_growth_statistics()
        parents = statistics["parents"]
        names = self.video.skeleton.names
        if self.config.grow_parents:
            parents = torch.as_tensor([names.index(name) for name in self._named_parents()], device=self.device)
        self.growth_report = {
            "stage": "grow_joints", "step": self.step,
            "joint_gradient": {names[j]: float(g) for j, g in enumerate(statistics["joint_gradient"].tolist())},
            "threshold": statistics["threshold"], "grown_parents": [names[j] for j in parents.tolist()]}
        self._log(self.growth_report)
        self.grown = True
        if parents.numel():
            self._add_extra_joints(parents)

    def _named_parents(self) -> list[str]:
        """The joint names of ``--grow-parents``, checked against the skeleton."""
        names = self.video.skeleton.names
        requested = [name.strip() for name in self.config.grow_parents.split(",") if name.strip()]
        unknown = [name for name in requested if name not in names]
        if unknown:
            raise ValueError(f"--grow-parents names joints the skeleton does not have: {', '.join(unknown)} "
                             f"(its joints: {', '.join(names)})")
        return requested

    def _add_extra_joints(self, parents: torch.Tensor, state: dict | None = None) -> None:
        """Attach grown joints (``parents`` [E]) to the avatar, or the saved ones from ``state``."""
        config = self.config
        heads = torch.as_tensor(self.video.skeleton.heads, dtype=torch.float32, device=self.device)
        if state is None:
            frame_times = torch.as_tensor(self.video.frame_ids[self.train_indices], dtype=torch.float32,
                                          device=self.device) / float(self.video.fps)
            # the decoders' initial weights depend on the seed only, not on how many random numbers the fit
            # drew before (a fit resumed before the growth grows the same joints)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(config.seed)
                extra = ExtraJoints(parents, heads[parents], self.bone_transforms, frame_times,
                                    extent=self.extent).to(self.device)
        else:
            extra = ExtraJoints.from_file_state(state, device=self.device)
        old_parameters = self._network_parameters()
        self.field.add_joints(extra.parents)
        self.avatar.extra_joints = extra
        self.bone_groups = extra.group_matrix()
        self._frozen_grid = None
        # the network optimizer keeps its moments for every parameter but the field's replaced last layer
        parameters = self._network_parameters()
        optimizer = torch.optim.Adam(parameters, lr=config.field_lr)
        kept = {id(parameter) for parameter in parameters}
        for parameter in old_parameters:
            if id(parameter) in kept and parameter in self.field_optimizer.state:
                optimizer.state[parameter] = self.field_optimizer.state[parameter]
        self.field_optimizer = optimizer
        self.extra_joints_optimizer = torch.optim.Adam(extra.parameters(), lr=config.lr_extra_joints)

    def _refresh_backward(self, step: int, index: int, grid: torch.Tensor) -> None:
        """Re-detect and correct ambiguous Gaussians on training frame ``index`` when the cache is stale."""
        backward = self.backward
        if backward.ready and step - self._backward_refreshed < self.config.backward_every:
            return
        with torch.no_grad():
            posed = self.avatar.pose(self.bone_transforms[index], grid=grid)
            backward.refresh(self.gaussians.means.detach(), posed["means"], posed["weights"],
                             self.avatar.pose_bones(self.bone_transforms[index]))
        self._backward_refreshed = step

    def _build_secondary_motion(self, state: dict | None = None) -> None:
        """SMAD's graph from the current canonical Gaussians (or from a checkpoint's ``state``), and its optimizer."""
        config = self.config
        if state is None:
            field = self.field
            voxel = config.secondary_voxel * float((field.bbox_max - field.bbox_min).max())
            nodes = voxel_downsample(self.gaussians.means.detach(), voxel)
            secondary = SecondaryMotion(nodes, self.bone_transforms, voxel_size=voxel)
            secondary.bind(self.gaussians.means)
        else:
            secondary = SecondaryMotion.from_file_state(state, device=self.device)
        self.avatar.secondary_motion = secondary
        # row-sparse Adam: a frame's displacements move only in the steps that see that frame
        self.secondary_optimizer = torch.optim.SparseAdam([secondary.displacement],
                                                          lr=config.lr_secondary * self.extent)

    def _build_dynamics(self, *, grid: torch.Tensor | None = None, state: dict | None = None) -> None:
        """SMAD's learned dynamics on a graph of the current canonical Gaussians (or from a checkpoint's
        ``state``), and its optimizer."""
        config = self.config
        if state is None:
            field = self.field
            voxel = config.secondary_voxel * float((field.bbox_max - field.bbox_min).max())
            nodes = voxel_downsample(self.gaussians.means.detach(), voxel)
            with torch.no_grad():
                node_weights = field.weights(nodes, grid)
            dynamics = SecondaryDynamics(
                nodes, node_weights, self.video.skeleton.parents, voxel_size=voxel,
                frame_interval=float(self.frame_intervals.median()),
                hidden=config.dynamics_hidden, velocity_history=config.dynamics_velocity_history,
                pose_window=config.dynamics_pose_window, substeps=config.dynamics_substeps)
            dynamics.bind(self.gaussians.means)
        else:
            dynamics = SecondaryDynamics.from_file_state(state, device=self.device)
        self.avatar.secondary_motion = dynamics
        springs = [dynamics.stiffness_raw, dynamics.anchor_raw, dynamics.damping_raw]
        network = [p for p in dynamics.parameters() if all(p is not q for q in springs)]
        self.dynamics_optimizer = torch.optim.Adam([{"params": network, "lr": config.lr_dynamics},
                                                    {"params": springs, "lr": config.lr_dynamics_springs}])
        self.dynamics_drive = None  # computed with the cache (refresh) or, after a resume, on first use
        self.dynamics_cache = None

    @torch.no_grad()
    def refresh_dynamics(self, grid: torch.Tensor | None = None) -> None:
        """Re-read the nodes' skinning weights and roll the whole training sequence out (no gradients): the
        cached states the training windows start from, and the table novel views of training instants use."""
        dynamics = self.avatar.secondary_motion
        if grid is None:
            grid = self.field.grid_weights()
        dynamics.set_node_weights(self.field.weights(dynamics.nodes, grid))
        self.dynamics_drive = dynamics.drive(self.bone_transforms, self.frame_intervals)
        displacement, velocity = dynamics.rollout(self.bone_transforms, self.frame_intervals,
                                                  drive=self.dynamics_drive)
        self.dynamics_cache = (displacement, velocity)
        dynamics.set_training_rollout(self.bone_transforms, displacement)
        self._dynamics_refreshed = self.step

    def _dynamics_state(self, index: int, grid: torch.Tensor) -> DynamicsState:
        """The dynamics' state at training frame ``index``, rolled with gradients over the last
        ``dynamics_window`` frames from the cached state before them (which it then updates)."""
        dynamics = self.avatar.secondary_motion
        if self.dynamics_cache is None or self.step - self._dynamics_refreshed >= self.config.dynamics_refresh_every:
            self.refresh_dynamics(grid)
        elif self.dynamics_drive is None:  # resumed with a cache: the drive of the saved node weights
            self.dynamics_drive = dynamics.drive(self.bone_transforms, self.frame_intervals)
        cached_displacement, cached_velocity = self.dynamics_cache
        start = max(0, index - self.config.dynamics_window)
        # clones: the cache rows are overwritten below, and autograd may hold on to the start state
        state = DynamicsState(cached_displacement[start].clone(), cached_velocity[start].clone())
        for frame in range(start + 1, index + 1):
            state = dynamics.step(state, self.dynamics_drive, frame, self.frame_seconds[frame])
            cached_displacement[frame] = state.displacement.detach()
            cached_velocity[frame] = state.velocity.detach()
        return state

    # ------------------------------------------------------------------------------------------- checkpoints
    def checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "config": self.config.to_dict(),
            "gaussians": self.gaussians.state_for_checkpoint(),
            "gaussian_optimizer": self.gaussians.optimizer.state_dict(),
            "field": self.field.state_dict(),
            "pose_correction": (self.avatar.pose_correction.state_dict()
                                if self.avatar.pose_correction is not None else None),
            "field_optimizer": self.field_optimizer.state_dict(),
            "secondary_motion": (self.avatar.secondary_motion.state_for_file()
                                 if self.avatar.secondary_motion is not None else None),
            "secondary_optimizer": (self.secondary_optimizer.state_dict()
                                    if self.secondary_optimizer is not None else None),
            "dynamics_optimizer": (self.dynamics_optimizer.state_dict()
                                   if self.dynamics_optimizer is not None else None),
            "dynamics_cache": (None if self.dynamics_cache is None
                               else [tensor.cpu() for tensor in self.dynamics_cache]),
            "dynamics_refreshed": self._dynamics_refreshed,
            "lighting": (self.avatar.lighting.state_dict() if self.avatar.lighting is not None else None),
            "grown": self.grown,
            "extra_joints": (self.avatar.extra_joints.state_for_file() if self.avatar.extra_joints is not None
                             else None),
            "extra_joints_optimizer": (self.extra_joints_optimizer.state_dict()
                                       if self.extra_joints_optimizer is not None else None),
            "position_grad_accum": self.position_grad_accum.cpu(),
            "joint_grad_sum": self.joint_grad_sum.cpu(),
            "joint_grad_seen": self.joint_grad_seen.cpu(),
            "lighting_optimizer": (self.lighting_optimizer.state_dict() if self.lighting_optimizer is not None
                                   else None),
            "backward": (dict(self.backward.state() or {}, refreshed=self._backward_refreshed)
                         if self.backward is not None and self.backward.ready else None),
            "generator": self.generator.get_state(),
            "frame_order": list(self.frame_order),
            "grad_accum": self.grad_accum.cpu(),
            "visible_count": self.visible_count.cpu(),
        }

    def save_checkpoint(self) -> Path:
        path = self.output_dir / CHECKPOINT_NAME
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.checkpoint_state(), tmp)
        os.replace(tmp, path)
        return path

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        state = torch.load(path, map_location="cpu", weights_only=False)
        saved = FitConfig.from_dict(state["config"])
        if saved.to_dict() != self.config.to_dict():
            changed = sorted(k for k, v in saved.to_dict().items() if self.config.to_dict()[k] != v)
            raise ValueError(f"{path}: the checkpoint was made with a different config ({', '.join(changed)}); "
                             "resume with the same options or start a new output folder")
        gaussians = GaussianModel.from_checkpoint(state["gaussians"], device=self.device)
        self.avatar.gaussians = gaussians
        self.gaussians = gaussians
        gaussians.make_optimizer(lr_position=self.config.lr_position * self.extent, lr_scale=self.config.lr_scale,
                                 lr_rotation=self.config.lr_rotation, lr_opacity=self.config.lr_opacity,
                                 lr_color=self.config.lr_color)
        gaussians.optimizer.load_state_dict(state["gaussian_optimizer"])
        self.grown = bool(state.get("grown", False))
        if state.get("extra_joints") is not None:
            self._add_extra_joints(None, state=state["extra_joints"])
            self.extra_joints_optimizer.load_state_dict(state["extra_joints_optimizer"])
        self.field.load_state_dict(state["field"])
        if self.avatar.pose_correction is not None:
            self.avatar.pose_correction.load_state_dict(state["pose_correction"])
        self._frozen_grid = None
        self.field_optimizer.load_state_dict(state["field_optimizer"])
        if state.get("secondary_motion") is not None:
            if state["secondary_motion"].get("kind") == "dynamics":
                self._build_dynamics(state=state["secondary_motion"])
                self.dynamics_optimizer.load_state_dict(state["dynamics_optimizer"])
                if state.get("dynamics_cache") is not None:
                    self.dynamics_cache = tuple(tensor.to(self.device) for tensor in state["dynamics_cache"])
                self._dynamics_refreshed = int(state.get("dynamics_refreshed", -1))
            else:
                self._build_secondary_motion(state["secondary_motion"])
                self.secondary_optimizer.load_state_dict(state["secondary_optimizer"])
        if self.avatar.lighting is not None:
            self.avatar.lighting.load_state_dict(state["lighting"])
            self.lighting_optimizer.load_state_dict(state["lighting_optimizer"])
        if self.backward is not None:
            saved_backward = state.get("backward")
            self.backward.load_state(saved_backward, device=self.device)
            self._backward_refreshed = int(saved_backward["refreshed"]) if saved_backward else -1
        self.generator.set_state(state["generator"])
        self.frame_order = list(state["frame_order"])
        self.grad_accum = state["grad_accum"].to(self.device)
        self.visible_count = state["visible_count"].to(self.device)
        # checkpoints written before skeleton growth existed have no growth statistics: start them empty
        if "position_grad_accum" in state:
            self.position_grad_accum = state["position_grad_accum"].to(self.device)
            self.joint_grad_sum = state["joint_grad_sum"].to(self.device)
            self.joint_grad_seen = state["joint_grad_seen"].to(self.device)
        else:
            self.position_grad_accum = torch.zeros(self.gaussians.count, device=self.device)
        self.step = int(state["step"])

    # ------------------------------------------------------------------------------------------------ run
    def fit(self, *, resume: bool = False, progress: bool = True, stop_at: int | None = None) -> Avatar:
        """Run (or continue) the fit and write the outputs.

        Args:
            resume: continue from ``checkpoint.pt`` in the output folder when it exists.
            progress: show a tqdm progress bar.
            stop_at: stop after this step (as an interruption would), without writing final outputs.
        """
        config = self.config
        checkpoint = self.output_dir / CHECKPOINT_NAME
        if resume and checkpoint.is_file():
            self.load_checkpoint(checkpoint)
        else:
            self.log_path.unlink(missing_ok=True)
            (self.output_dir / "config.json").write_text(config.to_json())
            warm = self.warmup_field()
            self._log({"stage": "warmup", "distillation_loss": warm, "gaussians": self.gaussians.count})
        start_time = time.time()
        end = config.iterations if stop_at is None else min(stop_at, config.iterations)
        bar = tqdm.tqdm(total=config.iterations, initial=self.step, disable=not progress, desc="fit", unit="step")
        while self.step < end:
            stats = self.train_step()
            bar.update(1)
            if self.step % config.log_every == 0 or self.step == config.iterations:
                stats["step"] = self.step
                stats["seconds"] = round(time.time() - start_time, 2)
                self._log(stats)
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", n=stats["gaussians"])
            if self.step % config.checkpoint_every == 0 and self.step < config.iterations:
                self.save_checkpoint()
        bar.close()
        if self.step >= config.iterations:
            self.write_outputs()
        else:
            self.save_checkpoint()
        return self.avatar

    def _log(self, record: dict) -> None:
        with open(self.log_path, "a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")

    def write_outputs(self) -> None:
        """Avatar file, canonical .ply, previews of a few training frames; the last checkpoint stays."""
        from warpavatar.io.ply import write_gaussian_ply

        if isinstance(self.avatar.secondary_motion, SecondaryDynamics):
            self.refresh_dynamics()  # the saved table of the training instants comes from the final model
        self.avatar.save(self.output_dir / "avatar.pt", config=self.config.to_dict())
        g = self.gaussians
        write_gaussian_ply(self.output_dir / "canonical.ply", means=g.means.detach().cpu().numpy(),
                           quats=g.normalized_quats.detach().cpu().numpy(), scales=g.scales.detach().cpu().numpy(),
                           opacities=g.opacities.detach().cpu().numpy(),
                           sh_coeffs=g.sh_coefficients().detach().cpu().numpy())
        self.save_checkpoint()
        self.write_previews()

    @torch.no_grad()
    def write_previews(self) -> None:
        import cv2

        preview_dir = self.output_dir / "previews"
        preview_dir.mkdir(exist_ok=True)
        picks = _evenly_spaced(len(self.train_indices), self.config.preview_frames)
        for index in picks:
            image, _, _ = self.avatar.render(self.cameras[index], self.bone_transforms[index],
                                             background=self.background)
            gt, _ = self.target(index)
            row = torch.cat([image, gt], dim=1).clamp(0, 1).cpu().numpy()
            frame_id = int(self.video.frame_ids[self.train_indices[index]])
            path = preview_dir / f"{frame_id:06d}.png"
            cv2.imwrite(str(path), cv2.cvtColor((row * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
