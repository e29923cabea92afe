"""Refining the given poses while fitting (``--refine-poses``): a learned correction of every training frame's pose.

Poses estimated from a real video (``warpavatar-prepare``) are off by several degrees per joint and centimetres
at the root; a fit that trusts them exactly blurs the avatar to cover the disagreement. As the avatar methods
that work on real monocular video do (InstantAvatar, GART, 3DGS-Avatar), each training frame ``t`` gets a
learned correction, starting where the given motion smoothed in time puts it (zero with ``--pose-prior-window
0``):

* a rotation ``exp([d_tj])`` (axis-angle ``d_tj`` [rad]) of every joint ``j`` in its own posed frame, composed
  after its given rotation relative to its parent, so the joints below it follow;
* a translation ``u_t`` [world units] of the root(s).

Each step's images move the corrections of the step's frame; every step also pulls all frames' corrections
towards the given motion smoothed in time and penalizes the refined motion's acceleration per video frame
(estimation noise is rough in time, motion mostly is not), which is what constrains what one camera cannot see (a
limb turned towards or away from it); a third prior holds the joints' slow drift along each frame's camera axis,
which no image of that camera sees, to that smoothed motion. After each step the corrections' mean over all frames
is removed: a correction shared by every frame is one the canonical shape can take up just as well, so only frame-to-frame
errors are corrected.

The prior's target (``--pose-prior-window``, up to 0.45 s): a pose estimator's jitter is mostly independent from
frame to frame, while a body's motion is smooth over a few frames, so the given motion smoothed in time
(:func:`warpavatar.model.kinematics.smoothing_corrections`: a robust local quadratic fit of every joint's rotation,
on the rotation manifold, and of the root's position, over the video folder's frames within a window either
side) is closer to the true motion than the given poses are. The corrections start at that target (the Gaussians
are fitted on the smoothed poses from the first step) and the prior holds them near it where the images do not say
otherwise: a turn one camera cannot see keeps the smoothed value, not the frame's noise. Each frame and joint
takes the widest of six windows, from 0.075 to 0.45 s either side, that agrees with the narrower ones: a quadratic
fit over +-0.075 s keeps 97 % of a component varying at 4 Hz (the gain at frequency ``f`` is that of
Savitzky-Golay's filter), over +-0.45 s it keeps 70 % at 1.2 Hz and averages independent noise over 27 frames at
30 fps (about 0.3 of it left, against 0.5 at +-0.15 s). Where a move is too fast for the wide windows (a kick
stopped within a few frames) and the noise does not hide it, the narrower windows disagree with them and the
frame keeps a narrow one, so exact poses stay nearly as given. With the
window at 0 the target is the given motion and the corrections start at zero.

The corrected skinning transforms are rebuilt down the skeleton (:func:`warpavatar.ops.corrected_poses`): a joint
keeps its pivot's offset from its parent's, expressed in the parent's frame, so the skeleton stays rigid. Every
training frame's refined pose and the three priors are computed by Warp kernels each refining step, three launches
forward and four backward (:func:`warpavatar.ops.pose_priors`; in torch they were some 450 small kernels a step). A
pose equal to a training frame's (a novel view of a training instant, the training motion replayed or exported)
gets that frame's refined pose; any other pose is used as given.

Adam moves each frame's correction by about ten times its learning rate at every visit of that frame, whether
the image's gradient is signal or noise, so the poses would jitter by a fraction of a pixel until the end and
the Gaussians never lock in: the learning rates decay to ``--lr-pose-final`` (1 %) of their value, and the
refinement stops three quarters of the way through the fit (``--refine-poses-until``), after which the Gaussians
fit fixed poses.

``--refine-poses auto`` (the default) refines the poses of folders whose ``meta.json`` says they are estimated
(``"poses": "estimated"``, written by ``warpavatar-prepare``) and trusts the others; ``on`` and ``off`` force it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from warpavatar import ops
from warpavatar.data import write_poses
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.geometry import match_pose
from warpavatar.model.kinematics import posed_pivots, rigid_poses, smoothing_corrections
from warpavatar.model.parts import AvatarPart
from warpavatar.optim import Adam, Optimizer

__all__ = ["PoseRefinement", "PoseRefinementOptions", "PoseRefinementExtension", "VectorAdam",
           "refinement_last_step"]


class VectorAdam(Optimizer):
    """Adam whose second moment is shared by the components of each vector (the last dimension of a parameter):
    a joint's axis-angle correction, a root's offset.

    Plain Adam divides every component by its own gradient scale, so a direction the images barely constrain (a
    joint turning towards the camera, whose gradient is a small fraction of the in-plane ones) moves as far per
    step as the best-seen one, and its noise drifts. Sharing the scale across the vector keeps the gradient's
    direction: an unconstrained component moves in proportion to its share of the gradient. The step length per
    vector stays about the learning rate, as with Adam.

    Its step reads nothing from the host beyond the betas and eps: the step count is a tensor on the parameters'
    device and the learning rate may be one (changed in place), so a training step that runs it can be captured
    as a CUDA graph and replayed.

    Args:
        params: parameters (or groups) whose last dimension holds the vectors.
        lr: learning rate (the step length of a vector whose gradient is steady, in its units): a number or a
            0-dim tensor.
        betas: decay rates of the first and second moments.
        eps: added to the square root of the second moment.
    """

    def __init__(self, params, lr: float | torch.Tensor = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        if not float(lr) > 0:
            raise ValueError(f"lr must be > 0, got {float(lr)}")
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for parameter in group["params"]:
                if parameter.grad is None:
                    continue
                gradient = parameter.grad
                state = self.state[parameter]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float64, device=parameter.device)
                    state["exp_avg"] = torch.zeros_like(parameter)
                    state["exp_avg_sq"] = torch.zeros_like(parameter[..., :1])
                elif not isinstance(state["step"], torch.Tensor) or state["step"].device != parameter.device:
                    # a count saved by an older version (a number), or a state loaded onto another device
                    state["step"] = torch.as_tensor(state["step"], dtype=torch.float64).to(parameter.device)
                count = state["step"].add_(1.0)
                state["exp_avg"].mul_(beta1).add_(gradient, alpha=1.0 - beta1)
                state["exp_avg_sq"].mul_(beta2).add_(gradient.square().mean(-1, keepdim=True), alpha=1.0 - beta2)
                corrected_first = 1.0 - torch.pow(beta1, count)
                corrected_second = 1.0 - torch.pow(beta2, count)
                scale = (state["exp_avg_sq"] / corrected_second).sqrt().add_(group["eps"])
                parameter.sub_(state["exp_avg"] / scale * (group["lr"] / corrected_first))
        return None


_DEPTH_WINDOW = 5
"""Training frames over which the depth prior averages the pivots' moves along the camera axis (odd)."""


class PoseRefinement(AvatarPart):
    """Per-training-frame corrections of the given poses (see the module docstring).

    Args:
        frame_poses: [T,J,4,4] the training frames' given poses, in the order of the corrections.
        heads: [J,3] rest-pose pivots [world units].
        parents: [J] parent index of each joint.
        frame_ids: [T] the frames' numbers (for the exported poses).
    """

    name = "pose_refinement"

    def __init__(self, frame_poses: torch.Tensor, heads: torch.Tensor, parents: torch.Tensor,
                 frame_ids: torch.Tensor):
        super().__init__()
        frame_count, joint_count = frame_poses.shape[:2]
        self.register_buffer("frame_poses", frame_poses.detach().float().clone())
        self.register_buffer("heads", torch.as_tensor(heads, dtype=torch.float32).clone())
        self.register_buffer("parents", torch.as_tensor(parents).long().clone())
        self.register_buffer("frame_ids", torch.as_tensor(frame_ids).long().clone())
        self.rotation = torch.nn.Parameter(torch.zeros(frame_count, joint_count, 3, device=self.frame_poses.device))
        self.translation = torch.nn.Parameter(torch.zeros(frame_count, 3, device=self.frame_poses.device))
        self._parent_list = tuple(int(p) for p in torch.as_tensor(parents).tolist())  # host data for the kernels
        self._table: tuple[tuple[int, int, torch.device], torch.Tensor] | None = None

    @property
    def joint_count(self) -> int:
        return int(self.parents.shape[0])

    def _apply(self, fn, recurse=True):  # a move or cast makes the table again
        module = super()._apply(fn, recurse)
        self.forget_table()
        return module

    def refined(self, index: int | torch.Tensor | slice) -> torch.Tensor:
        """The refined pose [J,4,4] of training frame ``index`` ([K,J,4,4] for a slice), differentiable
        (:func:`warpavatar.ops.corrected_poses`)."""
        if isinstance(index, int):
            return self.refined(slice(index, index + 1))[0]
        if index == slice(None):  # every frame: the parameters themselves (a slice's backward costs two kernels)
            return ops.corrected_poses(self.frame_poses, self.heads, self._parent_list, self.rotation,
                                       self.translation)
        return ops.corrected_poses(self.frame_poses[index], self.heads, self._parent_list, self.rotation[index],
                                   self.translation[index])

    @torch.no_grad()
    def refined_poses(self) -> torch.Tensor:
        """Every training frame's refined pose [T,J,4,4], computed once per change of the corrections (an in-place
        change made on the host; a replayed CUDA graph changes them unseen: :meth:`forget_table`)."""
        key = (self.rotation._version, self.translation._version, self.rotation.device)
        if self._table is None or self._table[0] != key:
            self._table = (key, self.refined(slice(None)))
        return self._table[1]

    def forget_table(self) -> None:
        """Make :meth:`refined_poses` compute the table again: the corrections may change where their versions do
        not show it (a step replayed from a CUDA graph)."""
        self._table = None

    def skinning_transforms(self, bones: torch.Tensor, frame) -> torch.Tensor:
        """The skeleton's transforms refined: the frame's explicit input is a training frame's index, or the
        refined pose [J,4,4] itself (a fit); without one, a training instant's refined pose is looked up. A frame
        posed with an explicit skeleton pose (``PoseFrame.skeleton_pose``, test-time refinement) keeps it."""
        if frame.skeleton_pose is not None:
            return bones
        choice = frame.input(self.name)
        joints = self.joint_count
        if isinstance(choice, torch.Tensor):  # a fit passes the refined pose it is training
            skeleton = choice
        elif choice is not None:
            skeleton = self.refined(int(choice)) if torch.is_grad_enabled() else self.refined_poses()[int(choice)]
        else:
            best, matched = match_pose(self.frame_poses, frame.bone_transforms)
            skeleton = torch.where(matched > 0, self.refined_poses()[best], bones[:joints])
        return torch.cat([skeleton, bones[joints:]])

    def corrections(self) -> dict[str, torch.Tensor]:
        """Per training frame [T]: mean correction angle over the joints [deg] and root offset [world units]."""
        with torch.no_grad():
            angles = torch.rad2deg(self.rotation.norm(dim=-1)).mean(-1)
            return {"angle_deg": angles, "root_offset": self.translation.norm(dim=-1)}

    def write_poses(self, path: str | Path) -> None:
        """The refined training poses as a poses.npz of docs/FORMAT.md (bone_transforms, frame_ids,
        joint_positions: the posed pivots)."""
        poses = rigid_poses(self.refined_poses().cpu(), self.heads.cpu())
        write_poses(path, poses.numpy(), self.frame_ids.cpu().numpy(),
                    joint_positions=posed_pivots(poses, self.heads.cpu()).numpy())

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "PoseRefinement":
        weights = state["state_dict"]
        part = cls(weights["frame_poses"], weights["heads"], weights["parents"], weights["frame_ids"])
        part.load_state_dict(weights)
        return part.to(device)


@dataclass
class PoseRefinementOptions:
    refine_poses: str = option("auto", "when to refine the training poses (see --refine-poses)",
                               choices=("auto", "on", "off"))
    refine_poses_from: int = option(1000, "first step that refines the poses (the Gaussians take shape before: "
                                    "pose gradients of a blurred avatar mislead)")
    refine_poses_until: int = option(0, "last step that refines the poses; the Gaussians finish on them fixed "
                                     "after it, so that they lock in (0: three quarters of the way from "
                                     "--refine-poses-from to the fit's last step; give the last step to refine "
                                     "until the end)")
    lr_pose_rotation: float = option(2e-3, "Adam learning rate of the joints' correction angles [rad]")
    lr_pose_translation: float = option(1e-3, "Adam learning rate of the root's correction, times the canonical "
                                        "extent")
    pose_moments: str = option("vector", "Adam's gradient scale for the pose corrections: one per vector (a "
                               "joint's rotation, a root's offset: a direction the images barely see moves in "
                               "proportion to its share of the gradient) or one per component (plain Adam: every "
                               "direction moves as far per step)", choices=("vector", "component"))
    lr_pose_final: float = option(0.01, "fraction of the pose learning rates left at the last refining step (they "
                                  "decay exponentially from --refine-poses-from on): Adam moves every frame's "
                                  "pose by about ten times its rate at each of its visits, signal or noise, so "
                                  "what is left at the end is the poses' final jitter")
    lambda_pose_prior: float = option(10.0, "weight of the mean squared difference between the corrections and the "
                                      "prior's target over all frames and joints (angles in rad, the root's "
                                      "offset in units of the canonical extent): keeps the poses near the given "
                                      "motion smoothed in time (--pose-prior-window) where the images do not "
                                      "need otherwise")
    pose_prior_window: float = option(0.45, "widest half-width [s] of the time window over which the given "
                                      "motion is smoothed into the prior's target and the corrections' start (a "
                                      "robust local quadratic fit over the folder's frames within it either "
                                      "side, from meta.json's fps and the frame numbers; per frame and joint the "
                                      "widest of six windows down to a sixth of this that agrees with the "
                                      "narrower ones, so fast moves keep a narrow one): removes per-frame "
                                      "jitter of the pose estimate; 0: the given poses themselves")
    lambda_pose_smooth: float = option(1.0, "weight of the refined motion's mean squared acceleration over all "
                                       "frames (joints' positions in units of the canonical extent, and "
                                       "rotation matrices, per video frame squared, from the frame numbers of the "
                                       "neighbouring training frames): estimation noise is not smooth in time, "
                                       "motion mostly is; the prior fades where training frames lie far apart")
    lambda_pose_depth: float = option(30.0, "weight of the mean squared move of the joints' pivots along each "
                                      "frame's camera axis, averaged over 5 consecutive training frames (units of "
                                      "the canonical extent): one camera does not see depth, so a slow drift along "
                                      "its axis is held to the given pose while frame-to-frame corrections (noise "
                                      "the smoothness prior removes) stay free")

    def __post_init__(self):
        for name in ("lr_pose_rotation", "lr_pose_translation", "lambda_pose_prior", "lambda_pose_smooth",
                     "lambda_pose_depth", "pose_prior_window"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)}")
        if not 0 < self.lr_pose_final <= 1:
            raise ValueError(f"lr_pose_final must lie in (0, 1], got {self.lr_pose_final}")
        if self.refine_poses_from < 0:
            raise ValueError(f"refine_poses_from must be non-negative, got {self.refine_poses_from}")
        if self.refine_poses_until < 0:
            raise ValueError(f"refine_poses_until must be non-negative (0: the last step), got "
                             f"{self.refine_poses_until}")


def refinement_last_step(options: PoseRefinementOptions, iterations: int) -> int:
    """The last step that refines the poses: ``refine_poses_until``, or by default three quarters of the way from
    ``refine_poses_from`` to the fit's last step ``iterations`` (the Gaussians then lock in on fixed poses)."""
    if options.refine_poses_until:
        return options.refine_poses_until
    start = min(options.refine_poses_from, iterations)
    return start + (3 * (iterations - start)) // 4


class PoseRefinementExtension(Extension):
    """Refines each training frame's pose with the avatar: Adam on the corrections from ``refine_poses_from`` to
    :func:`refinement_last_step` (learning rates decaying to ``lr_pose_final`` of their value there; the
    Gaussians then finish on fixed poses), the step's frame pulled by its images, every frame
    pulled towards its given pose smoothed in time (where the corrections start) and towards a motion smooth in
    time."""

    name = "pose_refinement"
    switch = "refine_poses"
    switch_modes = ("auto", "on", "off")
    default_mode = "auto"
    title = "pose refinement (--refine-poses)"
    summary = ("refine every training frame's pose (each joint's rotation, the root's position) with the avatar: "
               "'auto' does it when meta.json says the poses are estimated (warpavatar-prepare writes so), 'on' "
               "and 'off' force it; the refined poses are saved (poses_refined.npz) and novel views and replays "
               "of training instants use them")
    options_type = PoseRefinementOptions
    presets = {"quick": {"refine_poses_from": 400}}
    part: PoseRefinement | None = None
    refined: torch.Tensor | None = None  # while refining: every training frame's refined pose [T,J,4,4] this step

    @classmethod
    def check(cls, options, config) -> None:
        until = options.refine_poses_until
        if until and not options.refine_poses_from <= until <= config.iterations:
            raise ValueError(f"refine_poses_until ({until}) must lie between refine_poses_from "
                             f"({options.refine_poses_from}) and the last step ({config.iterations}), or be 0")

    def attach(self) -> None:
        fit = self.fit
        if self.options.refine_poses == "auto" and not fit.frames.video.poses_estimated:
            return  # exact poses (a rendered subject): nothing to refine
        skeleton = fit.frames.skeleton
        part = PoseRefinement(fit.frames.bone_transforms, torch.as_tensor(skeleton.heads, dtype=torch.float32),
                              torch.as_tensor(skeleton.parents), torch.as_tensor(fit.frames.frame_ids))
        self.part = fit.avatar.add_part(part.to(fit.device), first=True)
        self.target_rotation, self.target_translation = self._prior_target()
        with torch.no_grad():  # start at the target: the Gaussians are fitted on the smoothed motion from step 0
            part.rotation.copy_(self.target_rotation)
            part.translation.copy_(self.target_translation)
        ids = torch.as_tensor(np.asarray(fit.frames.frame_ids, dtype=np.float32), device=fit.device)
        # video frames between consecutive training frames (1 where none was skipped) [T-1]: the acceleration
        # is measured per video frame, so the smoothness prior fades where training frames lie far apart in time
        self.gaps = (ids[1:] - ids[:-1]).abs().clamp(min=1.0)
        with torch.no_grad():  # the target's pivots [T,J,3] (extent units) and each frame's camera axis in the world
            self.target_pivots = posed_pivots(part.refined(slice(None)), part.heads) / fit.extent
            self.view_axes = torch.stack([camera.world_to_camera[2, :3] for camera in fit.frames.cameras]).float()
        self.base_lr = (self.options.lr_pose_rotation, self.options.lr_pose_translation * fit.extent)
        # learning rates as device tensors, changed in place every step: a captured step reads them
        groups = [{"params": [part.rotation], "lr": torch.tensor(self.base_lr[0], device=fit.device)},
                  {"params": [part.translation], "lr": torch.tensor(self.base_lr[1], device=fit.device)}]
        if self.options.pose_moments == "vector":
            self.optimizer = VectorAdam(groups)
        else:
            self.optimizer = Adam(groups)

    def _prior_target(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrections [T,J,3], [T,3] that bring the training frames to the given motion smoothed in time (every
        frame of the video folder within ``pose_prior_window`` seconds taken), less their mean over the training
        frames: a correction shared by every frame is the fit's gauge (see :meth:`after_step`)."""
        video, frames = self.fit.frames.video, self.fit.frames
        rotation, translation = smoothing_corrections(
            torch.as_tensor(video.bone_transforms), torch.as_tensor(frames.skeleton.heads), frames.skeleton.parents,
            torch.as_tensor(np.asarray(video.frame_ids, dtype=np.float64) / float(video.fps)),
            window=self.options.pose_prior_window)
        rows = torch.as_tensor(frames.indices, dtype=torch.long)
        rotation, translation = rotation[rows], translation[rows]
        rotation, translation = rotation - rotation.mean(0), translation - translation.mean(0)
        return rotation.float().to(self.fit.device), translation.float().to(self.fit.device)

    def _last_step(self) -> int:
        return refinement_last_step(self.options, self.fit.config.iterations)

    def _training(self, step) -> bool:
        return self.part is not None and self.options.refine_poses_from <= step.step <= self._last_step()

    def step_capturable(self, step) -> bool:
        # the frame comes from step.frame, the learning rates are tensors changed in place; plain Adam's steps
        # (--pose-moments component) stay eager: one capture in five of them was invalidated on the H100
        return self.part is None or self.options.pose_moments == "vector"

    def graph_key(self, step) -> tuple:
        if self.part is None:
            return ()
        if not self._training(step):  # the poses are fixed: a step reads their table (made here, off the capture)
            return (False, self.part.refined_poses().data_ptr())
        return (True, tuple(group["lr"].data_ptr() for group in self.optimizer.param_groups))

    def begin_step(self, step) -> None:
        if self.part is None:
            return
        training = self._training(step)
        self.part.requires_grad_(training)
        if training:  # decays exponentially to lr_pose_final by the last step: large moves first, then settle
            self.part.forget_table()  # this step changes the corrections, replayed or not
            span = max(1, self._last_step() - self.options.refine_poses_from)
            decay = self.options.lr_pose_final ** (min(step.step - self.options.refine_poses_from, span) / span)
            for group, base in zip(self.optimizer.param_groups, self.base_lr):
                if isinstance(group["lr"], torch.Tensor) and group["lr"].device == self.fit.device:
                    group["lr"].fill_(base * decay)
                else:  # a number again (a loaded optimizer state)
                    group["lr"] = torch.tensor(base * decay, device=self.fit.device)

    def step_input(self, step) -> torch.Tensor | None:
        """The step frame's refined pose [J,4,4], gathered at ``step.frame`` (on the device, so a replayed step
        reads its own frame). While refining, every training frame's refined pose is computed (one batched pass
        down the skeleton) for the priors, and the frame's is taken from them with gradients; once the poses are
        fixed, from their table (:meth:`PoseRefinement.refined_poses`, computed once)."""
        self.refined = None
        if self.part is None:
            return None
        frame = step.frame.reshape(1)
        if not self._training(step):
            return self.part.refined_poses().index_select(0, frame)[0]
        self.refined = self.part.refined(slice(None))  # [T,J,4,4]
        return self.refined.index_select(0, frame)[0]

    def losses(self, step) -> dict[str, LossTerm]:
        """The priors, each averaged over every training frame: the corrections' mean squared difference from the
        target (the given motion smoothed in time), the joints' slow drift from it along each frame's camera axis,
        and the refined motion's mean squared acceleration. Each step sees one frame's images but moves every
        frame's pose towards the priors, so information spreads along the motion at every step."""
        if self.refined is None:
            return {}
        part = self.part
        prior, depth, smooth = ops.pose_priors(
            self.refined, part.heads, part.rotation, part.translation, target_rotation=self.target_rotation,
            target_translation=self.target_translation, target_pivots=self.target_pivots, view_axes=self.view_axes,
            gaps=self.gaps, scale=1.0 / self.fit.extent, depth_window=_DEPTH_WINDOW).unbind()
        terms = {"pose_prior": LossTerm(self.options.lambda_pose_prior, prior)}
        if self.options.lambda_pose_depth > 0:  # what each frame's camera cannot see: moves along its axis
            terms["pose_depth"] = LossTerm(self.options.lambda_pose_depth, depth)
        if self.refined.shape[0] >= 3:  # the refined motion's acceleration: noise is not smooth
            terms["pose_smooth"] = LossTerm(self.options.lambda_pose_smooth, smooth)
        return terms

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [self.optimizer] if self._training(step) else []

    @torch.no_grad()
    def after_step(self, step) -> None:
        """Keep the corrections' mean over the training frames at zero: a correction shared by every frame is
        one the canonical shape can take up just as well (the fit's gauge), so only frame-to-frame errors are
        corrected and the avatar keeps the given poses' average."""
        if self._training(step):
            self.part.rotation.sub_(self.part.rotation.mean(dim=0, keepdim=True))
            self.part.translation.sub_(self.part.translation.mean(dim=0, keepdim=True))

    def log_values(self) -> dict[str, float]:
        if self.part is None:
            return {}
        corrections = self.part.corrections()
        return {"pose_correction_deg": float(corrections["angle_deg"].mean()),
                "pose_root_offset": float(corrections["root_offset"].mean())}

    def write_outputs(self, folder: Path) -> None:
        if self.part is not None:
            self.part.write_poses(folder / "poses_refined.npz")

    def summary_lines(self) -> list[str]:
        if self.part is None:  # poses used as given: nothing to report
            return []
        corrections = self.part.corrections()
        return [f"poses refined: {float(corrections['angle_deg'].mean()):.2f} deg per joint and "
                f"{float(corrections['root_offset'].mean()) * 1000:.1f} mm at the root on average "
                "(poses_refined.npz)"]

    def state_dict(self) -> dict:
        if self.part is None:
            return {}
        return {"part": self.part.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if self.part is not None:
            self.part.load_state_dict(state["part"])
            self.optimizer.load_state_dict(state["optimizer"])
