"""ToMiE's modular skeleton growth (ToMiE, Sec. 4.1-4.4): extra joints where garments do not follow the body.

Where LBS on the given skeleton cannot follow a part of the subject (a skirt swinging off the legs, an object
in the hand), the Gaussians there keep large position gradients. Growth happens once, at step ``grow_at`` of a
fit:

1. **Motion kernels** (Eq. 6-7). Over the training frames, the variance of the distance between each posed
   Gaussian and each posed joint: small when the Gaussian moves rigidly with that joint.
2. **Assignment** (Eq. 8). Each Gaussian is assigned to joints by ``lambda * Normalize(1 / MK) +
   (1 - lambda) * w_lbs`` (lambda = 0.4).
3. **Joint gradients** (Eq. 4). Each joint's gradient is the assignment-weighted mean of its Gaussians'
   position-gradient norms, pooled over every step from the start of the fit to ``grow_at`` (each
   densification round folds its per-Gaussian sums into per-joint sums, as cloning and pruning renumber the
   Gaussians).
4. **Parent localization** (Eq. 9). The joints whose gradient passes a threshold grow one child each. ToMiE's
   threshold is absolute (3.5e-6 for its loss); here it is relative to the median joint gradient, as the
   scale of a position gradient depends on the loss, the image size and the units.

On the supplied subjects this criterion separates the joints weakly (largest over median 1.1-1.4 for the
skirted subject, 1.4-1.9 for the garment-free one) and often picks extremities. Two alternatives exist: the
trainer's ``history`` criterion, which ranks joints by the offsets that the pose correction's per-frame codes
add (see :meth:`warpavatar.extensions.pose_correction.PoseCorrection.history_offsets`), or parents named by the user.

Each grown joint starts at its parent's head with the identity rotation (:class:`ExtraJoints`, the "extra
joint book"): a shallow MLP decodes its canonical position offset from its index (Eq. 10), another its rotation
in the parent's rest frame from its index and the frame's time (Eq. 11), both with positional encodings and
last layers initialised small. The skinning field gains one output per grown joint
(:meth:`warpavatar.model.skinning_field.VoxelSkinningField.add_joints`) that starts as a copy of its parent's with
the parent's weight shared half and half, so growing changes no render, and the field then learns where the
child takes over.

Rotations are known for the training instants. A pose equal to a training frame's (a novel view of a training
instant) gets that frame's rotations; any other pose gets the identity (the grown joint follows its parent
rigidly) unless rotations are given explicitly (animating the garment by hand).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from warpavatar import ops
from warpavatar.extensions.base import Extension, option
from warpavatar.geometry import fourier_features, match_pose, mlp, quat_from_vector, quat_to_matrix
from warpavatar.model.parts import AvatarPart
from warpavatar.optim import Adam, Optimizer

__all__ = ["motion_kernel", "assignment_weights", "joint_gradients", "joint_gradient_sums", "locate_parents",
           "ExtraJoints", "JointGrowthOptions", "JointGrowthExtension"]


def motion_kernel(posed_means: torch.Tensor, posed_joints: torch.Tensor) -> torch.Tensor:
    """ToMiE's motion kernel (Eq. 6-7): variance over frames of the distance from each point to each joint.

    Args:
        posed_means: [T,N,3] point positions in each frame [world units].
        posed_joints: [T,J,3] joint positions in each frame [world units].

    Returns:
        [N,J] variance [world units^2]; small where a point moves rigidly with a joint.
    """
    if posed_means.dim() != 3 or posed_means.shape[-1] != 3:
        raise ValueError(f"posed_means must have shape [T, N, 3], got {list(posed_means.shape)}")
    if posed_joints.dim() != 3 or posed_joints.shape[-1] != 3 or posed_joints.shape[0] != posed_means.shape[0]:
        raise ValueError(f"posed_joints must have shape [{posed_means.shape[0]}, J, 3], "
                         f"got {list(posed_joints.shape)}")
    frame_count = posed_means.shape[0]
    if frame_count < 2:
        raise ValueError(f"a motion kernel needs at least 2 frames, got {frame_count}")
    # two passes (mean, then squared deviations) in float64: no cancellation for near-rigid pairs
    total = torch.zeros(posed_means.shape[1], posed_joints.shape[1], dtype=torch.float64, device=posed_means.device)
    for t in range(frame_count):
        total += torch.cdist(posed_means[t].double(), posed_joints[t].double())
    mean = total / frame_count
    spread = torch.zeros_like(total)
    for t in range(frame_count):
        spread += (torch.cdist(posed_means[t].double(), posed_joints[t].double()) - mean).square()
    return (spread / frame_count).to(posed_means.dtype)


def assignment_weights(kernel: torch.Tensor, lbs_weights: torch.Tensor, *, mix: float = 0.4, floor: float
                       ) -> torch.Tensor:
    """ToMiE's assignment of points to joints (Eq. 8): ``mix * Normalize(1 / MK) + (1 - mix) * w_lbs``.

    Args:
        kernel: [N,J] motion kernel (:func:`motion_kernel`) [world units^2].
        lbs_weights: [N,J] skinning weights (rows sum to one).
        mix: lambda, the share of the motion-kernel term (ToMiE: 0.4).
        floor: added to the kernel before inverting [world units^2], so a perfectly rigid pair stays finite.

    Returns:
        [N,J] non-negative weights, rows summing to one.
    """
    if kernel.shape != lbs_weights.shape:
        raise ValueError(f"kernel {list(kernel.shape)} and lbs_weights {list(lbs_weights.shape)} must match")
    if not 0.0 <= mix <= 1.0:
        raise ValueError(f"mix must lie in [0, 1], got {mix}")
    if floor <= 0:
        raise ValueError(f"floor must be positive, got {floor}")
    inverse = 1.0 / (kernel + floor)
    return mix * inverse / inverse.sum(dim=-1, keepdim=True) + (1.0 - mix) * lbs_weights


def joint_gradients(gradient_norm: torch.Tensor, assignment: torch.Tensor) -> torch.Tensor:
    """Each joint's assignment-weighted mean of the points' position-gradient norms (ToMiE Eq. 4).

    Args:
        gradient_norm: [N] accumulated gradient norm of each point.
        assignment: [N,J] assignment weights (:func:`assignment_weights`).

    Returns:
        [J]; zero for a joint no point is assigned to.
    """
    if gradient_norm.dim() != 1 or assignment.dim() != 2 or assignment.shape[0] != gradient_norm.shape[0]:
        raise ValueError(f"gradient_norm [N] and assignment [N,J] must agree, got {list(gradient_norm.shape)} and "
                         f"{list(assignment.shape)}")
    mass = assignment.sum(dim=0)
    return (assignment * gradient_norm[:, None]).sum(dim=0) / mass.clamp_min(1e-12)


def joint_gradient_sums(gradient_sum: torch.Tensor, seen_count: torch.Tensor, assignment: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4 pooled over (point, step) pairs, for statistics gathered across densification rounds.

    ``numerator / denominator`` is each joint's assignment-weighted mean position-gradient norm per step in
    which a point was seen; sums from several rounds (whose points differ after cloning and pruning) add up.
    With equal ``seen_count`` for every point it equals :func:`joint_gradients` of the per-point means.

    Args:
        gradient_sum: [N] summed position-gradient norm of each point over the steps of a round.
        seen_count: [N] steps of the round in which each point was visible.
        assignment: [N,J] assignment weights (:func:`assignment_weights`).

    Returns:
        (numerator [J], denominator [J]).
    """
    if gradient_sum.shape != seen_count.shape or assignment.shape[0] != gradient_sum.shape[0]:
        raise ValueError(f"gradient_sum {list(gradient_sum.shape)}, seen_count {list(seen_count.shape)} and "
                         f"assignment {list(assignment.shape)} must agree on N")
    return assignment.T @ gradient_sum, assignment.T @ seen_count.to(assignment)


def locate_parents(joint_gradient: torch.Tensor, *, ratio: float, max_count: int) -> torch.Tensor:
    """The joints that grow a child (ToMiE Eq. 9): gradient at least ``ratio`` times the median joint's.

    Args:
        joint_gradient: [J] per-joint gradient (:func:`joint_gradients`).
        ratio: threshold relative to the median of ``joint_gradient``.
        max_count: at most this many joints, the largest gradients first.

    Returns:
        [P] int64 joint indices in descending order of gradient (possibly empty).
    """
    if ratio <= 0:
        raise ValueError(f"ratio must be positive, got {ratio}")
    if max_count < 0:
        raise ValueError(f"max_count must be non-negative, got {max_count}")
    threshold = ratio * joint_gradient.median()
    order = torch.argsort(joint_gradient, descending=True)
    selected = order[joint_gradient[order] >= threshold]
    return selected[:max_count]


def _decoder(width_in: int, hidden: int, layers: int, width_out: int) -> torch.nn.Sequential:
    """An MLP of ``layers`` layers whose last starts tiny (ToMiE A.5: 1e-2)."""
    network = mlp(width_in, hidden, layers - 1, width_out)
    with torch.no_grad():
        network[-1].weight.uniform_(-1e-2, 1e-2)
        network[-1].bias.zero_()
    return network


class ExtraJoints(AvatarPart):
    """ToMiE's extra joint book: grown joints, their canonical positions and per-frame rotations, decoded by MLPs.

    A grown joint ``e`` with parent ``p`` has canonical position ``c_e`` = its parent's head plus an offset
    ``Phi_p(PE(e))`` and, in training frame ``t``, a rotation ``R_e(t)`` = ``Phi_r(PE(e), PE(t))`` about
    ``c_e`` in the parent's rest frame; its skinning transform is ``T_p(t) [R_e(t) | c_e - R_e(t) c_e]``, so it
    equals the parent's when the rotation is the identity.

    Args:
        parents: [E] index of each grown joint's parent in the skeleton.
        base_positions: [E,3] canonical start positions (the parents' heads) [world units].
        frame_poses: [T,J,4,4] the training frames' bone transforms, to recognise a training instant.
        frame_times: [T] their times [s].
        extent: a length that scales the position offsets [world units] (the canonical box's half-diagonal).
        hidden_position: width of ``Phi_p`` (ToMiE: 256).
        hidden_rotation: width of ``Phi_r`` (ToMiE: 128).
        layers: layers of each MLP (ToMiE: 4).
        index_frequencies: positional-encoding octaves of the joint index.
        time_frequencies: positional-encoding octaves of the time.
    """

    name = "joint_growth"

    def __init__(self, parents: torch.Tensor, base_positions: torch.Tensor, frame_poses: torch.Tensor,
                 frame_times: torch.Tensor, *, extent: float, hidden_position: int = 256, hidden_rotation: int = 128,
                 layers: int = 4, index_frequencies: int = 4, time_frequencies: int = 10):
        super().__init__()
        parents = torch.as_tensor(parents).long().reshape(-1)
        joint_count = int(parents.numel())
        if joint_count == 0:
            raise ValueError("ExtraJoints needs at least one grown joint")
        if base_positions.shape != (joint_count, 3):
            raise ValueError(f"base_positions must have shape [{joint_count}, 3], got {list(base_positions.shape)}")
        if frame_poses.dim() != 4 or frame_poses.shape[2:] != (4, 4) or frame_poses.shape[0] < 1:
            raise ValueError(f"frame_poses must have shape [T, J, 4, 4] with T >= 1, got {list(frame_poses.shape)}")
        if frame_times.shape != (frame_poses.shape[0],):
            raise ValueError(f"frame_times must have shape [{frame_poses.shape[0]}], got {list(frame_times.shape)}")
        if int(parents.min()) < 0 or int(parents.max()) >= frame_poses.shape[1]:
            raise ValueError(f"parents must index the skeleton's {frame_poses.shape[1]} joints, got {parents.tolist()}")
        if layers < 1:
            raise ValueError(f"layers must be at least 1, got {layers}")
        self.hyper = dict(extent=float(extent), hidden_position=int(hidden_position),
                          hidden_rotation=int(hidden_rotation), layers=int(layers),
                          index_frequencies=int(index_frequencies), time_frequencies=int(time_frequencies))
        self.register_buffer("parents", parents.clone())
        self.register_buffer("base_positions", base_positions.detach().float().clone())
        self.register_buffer("frame_poses", frame_poses.detach().float().clone())
        self.register_buffer("frame_times", frame_times.detach().float().clone())
        index_width = 1 + 2 * index_frequencies
        time_width = 1 + 2 * time_frequencies
        self.position_mlp = _decoder(index_width, hidden_position, layers, 3)
        self.rotation_mlp = _decoder(index_width + time_width, hidden_rotation, layers, 3)

    @property
    def count(self) -> int:
        return int(self.parents.numel())

    def _index_encoding(self) -> torch.Tensor:
        index = torch.arange(self.count, device=self.parents.device, dtype=torch.float32)
        return fourier_features((index / max(1, self.count))[:, None], self.hyper["index_frequencies"])

    def positions(self) -> torch.Tensor:
        """Canonical positions [E,3] of the grown joints [world units] (Eq. 10)."""
        offset = self.position_mlp(self._index_encoding())
        return self.base_positions + offset * (0.1 * self.hyper["extent"])

    def normalized_time(self, frame: torch.Tensor) -> torch.Tensor:
        """Time of training frame(s) ``frame`` mapped to [0, 1] over the training sequence."""
        start, end = self.frame_times[0], self.frame_times[-1]
        return (self.frame_times[frame] - start) / (end - start).clamp_min(1e-6)

    def frame_rotations(self, frame: torch.Tensor) -> torch.Tensor:
        """Rotations [E,4] (w, x, y, z) of the grown joints in training frame ``frame`` (a 0-d index tensor)."""
        times = self.normalized_time(frame).reshape(1).expand(self.count)
        features = torch.cat([self._index_encoding(), fourier_features(times[:, None], self.hyper["time_frequencies"])],
                             dim=-1)
        return quat_from_vector(self.rotation_mlp(features))

    def rotations_for_pose(self, bone_transforms: torch.Tensor) -> torch.Tensor:
        """Rotations [E,4] for a pose [J,4,4]: the training frame's if the pose is one, else the identity.

        Runs on the device without a host synchronization.
        """
        best, matched = match_pose(self.frame_poses, bone_transforms)
        rotations = self.frame_rotations(best)
        identity = torch.zeros_like(rotations)
        identity[:, 0] = 1.0
        return torch.where(matched > 0, rotations, identity)

    def transforms(self, bone_transforms: torch.Tensor, rotations: torch.Tensor | None = None, *,
                   key_pose: torch.Tensor | None = None) -> torch.Tensor:
        """Skinning transforms [E,4,4] of the grown joints for a pose.

        Args:
            bone_transforms: [J,4,4] the skeleton's rest-to-posed transforms (the grown joints follow them).
            rotations: [E,4] (w, x, y, z) rotations to use instead of the decoded ones (explicit animation).
            key_pose: [J,4,4] the pose that says which training instant this is (default ``bone_transforms``;
                the given pose when another part refined it).
        """
        if rotations is None:
            rotations = self.rotations_for_pose(bone_transforms if key_pose is None else key_pose)
        elif rotations.shape != (self.count, 4):
            raise ValueError(f"rotations must have shape [{self.count}, 4] (w, x, y, z), got {list(rotations.shape)}")
        else:
            rotations = rotations.to(bone_transforms) / rotations.to(bone_transforms).norm(dim=-1, keepdim=True)
        rotation = quat_to_matrix(rotations)  # [E,3,3]
        centre = self.positions()
        local = torch.zeros(self.count, 4, 4, device=bone_transforms.device, dtype=bone_transforms.dtype)
        local[:, :3, :3] = rotation
        local[:, :3, 3] = centre - (rotation @ centre[:, :, None])[:, :, 0]
        local[:, 3, 3] = 1.0
        return bone_transforms[self.parents] @ local

    # ---------------------------------------------------------------------------------------- part hooks
    def skinning_transforms(self, bones: torch.Tensor, frame) -> torch.Tensor:
        """Append the grown joints' transforms; the frame's explicit input, if any, is their rotations [E,4]; without
        one, the given pose says which training instant's rotations to replay."""
        return torch.cat([bones, self.transforms(bones, frame.input(self.name), key_pose=frame.bone_transforms)])

    def added_joint_parents(self) -> torch.Tensor:
        return self.parents

    def extend_rig(self, skeleton):
        """The skeleton with the grown joints appended (names ``grown_<parent>_<k>``, heads at their canonical
        positions, tails 10 % of the parent's length further along the parent)."""
        from warpavatar.data import Skeleton

        parents = self.parents.cpu().numpy()
        heads = self.positions().detach().cpu().numpy().astype(np.float32)
        direction = skeleton.tails[parents] - skeleton.heads[parents]
        names = list(skeleton.names) + [f"grown_{skeleton.names[parent]}_{k}" for k, parent in enumerate(parents)]
        return Skeleton(names=names, parents=np.concatenate([skeleton.parents, parents]).astype(np.int32),
                        heads=np.concatenate([skeleton.heads, heads]).astype(np.float32),
                        tails=np.concatenate([skeleton.tails, heads + 0.1 * direction]).astype(np.float32),
                        up=skeleton.up)

    # ------------------------------------------------------------------------------------------------ files
    def state_for_file(self) -> dict:
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}, "hyper": dict(self.hyper)}

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "ExtraJoints":
        weights = state["state_dict"]
        hyper = dict(state["hyper"])
        extent = hyper.pop("extent")
        module = cls(weights["parents"], weights["base_positions"], weights["frame_poses"], weights["frame_times"],
                     extent=extent, **hyper)
        module.load_state_dict(weights)
        return module.to(device)


@dataclass
class JointGrowthOptions:
    grow_parents: str = option("", "comma-separated skeleton joint names that grow a child at --grow-at instead of "
                               "those the gradients locate (e.g. the hips a skirt hangs from; a name given twice "
                               "grows two children); the gradients are still logged", product=True)
    grow_at: int = option(1500, "step at which joints grow (the position gradients of every step before it are "
                          "pooled); growing when the field starts to train (as here) measured better than at step "
                          "3000 on cesium_skirt with named parents")
    grow_threshold: float = option(1.1, "a joint grows a child when its gradient is at least this many times the "
                                   "median joint's (ToMiE thresholds an absolute value, which depends on the loss "
                                   "scale)")
    grow_max_joints: int = option(4, "at most this many located joints grow a child")
    grow_criterion: str = option("gradient", "what locates the parent joints: 'gradient' (ToMiE: each joint's "
                                 "assigned Gaussians' mean position-gradient norm) or 'history' (their RMS offset, "
                                 "over the training frames, that the pose correction's per-frame codes add to its "
                                 "pose-only correction: shape no function of the pose explains, as cloth that "
                                 "lags; needs --pose-correction and --frame-codes, and --grow-at after "
                                 "--gaussian-only-steps so that the correction has trained)",
                                 choices=("gradient", "history"))
    grow_motion_mix: float = option(0.4, "share of the motion kernel in the assignment of Gaussians to joints "
                                    "(ToMiE's lambda)")
    grow_kernel_frames: int = option(64, "training frames (evenly spaced) the motion kernels are computed over")
    lr_extra_joints: float = option(1e-3, "Adam learning rate of the grown joints' position and rotation MLPs")

    def __post_init__(self):
        if self.grow_threshold <= 0 or not 0.0 <= self.grow_motion_mix <= 1.0:
            raise ValueError(f"grow_threshold must be positive and grow_motion_mix lie in [0, 1], got "
                             f"{self.grow_threshold} and {self.grow_motion_mix}")
        if self.grow_kernel_frames < 2 or self.grow_max_joints < 1:
            raise ValueError(f"grow_kernel_frames must be at least 2 and grow_max_joints at least 1, got "
                             f"{self.grow_kernel_frames} and {self.grow_max_joints}")


class JointGrowthExtension(Extension):
    """ToMiE's growth in a fit: position gradients are pooled per joint until ``grow_at``, when the located (or
    named) joints each grow a child (:class:`ExtraJoints`); the skinning field gains the children's outputs and
    the grown joints' decoders train from then on."""

    name = "joint_growth"
    switch = "grow_joints"
    title = "ToMiE's skeleton growth (--grow-joints)"
    summary = ("grow extra joints on the skeleton where garments or held objects do not follow the body (ToMiE): "
               "at --grow-at, joints whose Gaussians carry the largest position gradients (assigned by skinning "
               "weights and motion kernels) each grow a child whose per-frame rotation is learned; novel views of "
               "training instants replay it, other poses keep it at rest unless animated explicitly")
    options_type = JointGrowthOptions
    presets = {"quick": {"grow_at": 600}}
    conflicts = {name: "--grow-joints cannot yet be combined with --dynamics or --backward-mapping (both read the "
                       "skeleton's bones only); use --secondary-motion for per-frame cloth displacements"
                 for name in ("dynamics", "backward_mapping")}
    part: ExtraJoints | None = None

    @classmethod
    def check(cls, options: JointGrowthOptions, config) -> None:
        correction = config.extensions.get("pose_correction")
        if options.grow_criterion == "history" and not (
                correction is not None and correction.frame_codes and options.grow_at > config.gaussian_only_steps):
            raise ValueError("--grow-criterion history reads the pose correction's per-frame codes: it needs "
                             "--pose-correction, --frame-codes and --grow-at later than --gaussian-only-steps")

    def attach(self) -> None:
        fit = self.fit
        self.names = list(fit.frames.skeleton.names)
        self.named_parents = self._named_parents()  # a misspelt --grow-parents fails now, not thousands of steps in
        self.grown = False  # the growth has run (whether or not any joint grew)
        self.report: dict | None = None
        count = len(self.names)
        # ToMiE's per-joint gradient statistics (Eq. 4), pooled over the densification rounds before growth
        self.joint_grad_sum = torch.zeros(count, device=fit.device)
        self.joint_grad_seen = torch.zeros(count, device=fit.device)
        # canonical position-gradient norms of the current Gaussians in this densification round
        self.position_grad_accum = torch.zeros(fit.avatar.gaussians.count, device=fit.device)

    def _named_parents(self) -> list[str]:
        requested = [name.strip() for name in self.options.grow_parents.split(",") if name.strip()]
        unknown = [name for name in requested if name not in self.names]
        if unknown:
            raise ValueError(f"--grow-parents names joints the skeleton does not have: {', '.join(unknown)} "
                             f"(its joints: {', '.join(self.names)})")
        return requested

    # ---------------------------------------------------------------------------------------- statistics
    def _pooling(self) -> bool:
        """Whether position gradients are being pooled for the gradient criterion (until growth)."""
        return not self.grown and self.options.grow_criterion == "gradient"

    def _kernel_frames(self) -> np.ndarray:
        """Training frames (evenly spaced, at most ``grow_kernel_frames``) the growth statistics use."""
        return self.fit.frames.spread(self.options.grow_kernel_frames)

    @torch.no_grad()
    def _assignment(self) -> torch.Tensor:
        """ToMiE's assignment [N,J] of the current Gaussians to the skeleton's joints (Eq. 6-8)."""
        fit = self.fit
        means = fit.avatar.gaussians.means.detach()
        weights = fit.skinning.field.weights(means)[:, : len(self.names)]
        frames = self._kernel_frames()
        all_bones = fit.frames.bone_transforms
        heads = torch.as_tensor(fit.frames.skeleton.heads, dtype=torch.float32, device=fit.device)
        posed_means = torch.stack([ops.lbs(means, weights, all_bones[t])[0] for t in frames])
        bones = all_bones[frames]
        posed_joints = torch.einsum("tjab,jb->tja", bones[:, :, :3, :3], heads) + bones[:, :, :3, 3]
        kernel = motion_kernel(posed_means, posed_joints)
        return assignment_weights(kernel, weights, mix=self.options.grow_motion_mix, floor=(0.01 * fit.extent) ** 2)

    @torch.no_grad()
    def _history_offsets(self) -> torch.Tensor:
        """RMS over the kernel frames [N] of the offsets the pose correction's frame codes add to the current
        Gaussians (the ``history`` criterion) [world units]."""
        correction = self.fit.avatar.part("pose_correction")
        means = self.fit.avatar.gaussians.means.detach()
        frames = self._kernel_frames()
        total = torch.zeros(means.shape[0], device=means.device)
        for frame in frames:
            total += correction.history_offsets(means, int(frame)).square().sum(-1)
        return (total / len(frames)).sqrt()

    @torch.no_grad()
    def statistics(self) -> dict:
        """ToMiE's parent-joint localization on the current model (Sec. 4.1-4.2), without growing anything.

        Returns:
            dict with ``joint_gradient`` [J] (Eq. 4: mean position-gradient norm per step a Gaussian was seen,
            pooled since the start of the fit; or the history offsets), ``parents`` [P] (the joints that would
            grow, largest first) and ``threshold``.
        """
        options = self.options
        assignment = self._assignment()
        if options.grow_criterion == "history":
            gradient = joint_gradients(self._history_offsets(), assignment)
        else:
            numerator, denominator = joint_gradient_sums(self.position_grad_accum, self.fit.density.visible_count,
                                                         assignment)
            gradient = (self.joint_grad_sum + numerator) / (self.joint_grad_seen + denominator).clamp_min(1e-12)
        parents = locate_parents(gradient, ratio=options.grow_threshold, max_count=options.grow_max_joints)
        return {"joint_gradient": gradient, "parents": parents,
                "threshold": float(options.grow_threshold * gradient.median())}

    # --------------------------------------------------------------------------------------------- growth
    def _grow(self, step: int) -> None:
        statistics = self.statistics()
        parents = statistics["parents"]
        if self.named_parents:
            parents = torch.as_tensor([self.names.index(name) for name in self.named_parents], device=self.fit.device)
        self.report = {
            "stage": "grow_joints", "step": step,
            "joint_gradient": {self.names[j]: float(g) for j, g in enumerate(statistics["joint_gradient"].tolist())},
            "threshold": statistics["threshold"], "grown_parents": [self.names[j] for j in parents.tolist()]}
        self.fit.log(self.report)
        self.grown = True
        if parents.numel():
            self._attach_joints(parents)

    def _attach_joints(self, parents: torch.Tensor | None, state: dict | None = None) -> None:
        """Attach grown joints (``parents`` [E]) to the avatar, or the saved ones from ``state``."""
        fit = self.fit
        if state is None:
            heads = torch.as_tensor(fit.frames.skeleton.heads, dtype=torch.float32, device=fit.device)
            # the decoders' initial weights depend on the seed only, not on how many random numbers the fit
            # drew before (a fit resumed before the growth grows the same joints)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(fit.config.seed)
                part = ExtraJoints(parents, heads[parents], fit.frames.bone_transforms, fit.frames.times,
                                   extent=fit.extent).to(fit.device)
        else:
            part = ExtraJoints.from_file_state(state, device=fit.device)
        fit.skinning.add_joints(part.parents)
        self.part = fit.avatar.add_part(part)
        self.optimizer = Adam(part.parameters(), lr=self.options.lr_extra_joints)

    # ---------------------------------------------------------------------------------------------- hooks
    def begin_step(self, step) -> None:
        if not self.grown and step.step >= self.options.grow_at:
            self._grow(step.step)

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [] if self.part is None else [self.optimizer]

    def after_backward(self, step) -> None:
        gradient = self.fit.avatar.gaussians.means.grad
        if self._pooling() and gradient is not None:
            with torch.no_grad():
                self.position_grad_accum += gradient.norm(dim=-1)

    def before_densify(self, visible_count: torch.Tensor) -> None:
        if self._pooling():  # fold this round's per-Gaussian sums into per-joint sums before the renumbering
            numerator, denominator = joint_gradient_sums(self.position_grad_accum, visible_count, self._assignment())
            self.joint_grad_sum += numerator
            self.joint_grad_seen += denominator

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        self.position_grad_accum = torch.zeros(source_index.shape[0], device=self.fit.device)

    def summary_lines(self) -> list[str]:
        if self.part is not None:
            grown = self.fit.avatar.rig().names[len(self.names):]
            return [f"grown joints ({len(grown)}): {', '.join(grown)} (per-joint statistics in train_log.jsonl)"]
        if self.grown:
            return ["no joint grew: none passed --grow-threshold (per-joint statistics in train_log.jsonl)"]
        return []

    def state_dict(self) -> dict:
        return {"grown": self.grown, "part": None if self.part is None else self.part.state_for_file(),
                "optimizer": None if self.part is None else self.optimizer.state_dict(),
                "position_grad_accum": self.position_grad_accum.cpu(), "joint_grad_sum": self.joint_grad_sum.cpu(),
                "joint_grad_seen": self.joint_grad_seen.cpu()}

    def load_state_dict(self, state: dict) -> None:
        self.grown = bool(state["grown"])
        if state["part"] is not None:
            self._attach_joints(None, state=state["part"])
            self.optimizer.load_state_dict(state["optimizer"])
        self.position_grad_accum = state["position_grad_accum"].to(self.fit.device)
        self.joint_grad_sum = state["joint_grad_sum"].to(self.fit.device)
        self.joint_grad_seen = state["joint_grad_seen"].to(self.fit.device)
