"""ToMiE's modular skeleton growth (paper 003, Sec. 4.1-4.4): extra joints where garments do not follow the body.

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
add (see :meth:`warpavatar.pose_correction.PoseCorrection.history_offsets`), or parents named by the user.

Each grown joint starts at its parent's head with the identity rotation (:class:`ExtraJoints`, the "extra
joint book"): a shallow MLP decodes its canonical position offset from its index (Eq. 10), another its rotation
in the parent's rest frame from its index and the frame's time (Eq. 11), both with positional encodings and
last layers initialised small. The skinning field gains one output per grown joint
(:meth:`warpavatar.skinning_field.VoxelSkinningField.add_joints`) that starts as a copy of its parent's with
the parent's weight shared half and half, so growing changes no render, and the field then learns where the
child takes over.

Rotations are known for the training instants. A pose equal to a training frame's (a novel view of a training
instant) gets that frame's rotations; any other pose gets the identity (the grown joint follows its parent
rigidly) unless rotations are given explicitly (animating the garment by hand).
"""

from __future__ import annotations

import math

import torch

from warpavatar.secondary_motion import match_pose

__all__ = ["motion_kernel", "assignment_weights", "joint_gradients", "joint_gradient_sums", "locate_parents", "rotation_from_vector",
           "quaternion_to_matrix", "ExtraJoints"]


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


def quaternion_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [...,3,3] of unit quaternions [...,4] (w, x, y, z)."""
    w, x, y, z = quats.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


def rotation_from_vector(vector: torch.Tensor) -> torch.Tensor:
    """Unit quaternion [...,4] (w, x, y, z) of ``(1, v) / |(1, v)|`` for v [...,3]: the identity at v = 0,
    smooth everywhere, any rotation below 180 degrees."""
    quats = torch.cat([torch.ones_like(vector[..., :1]), vector], dim=-1)
    return quats / quats.norm(dim=-1, keepdim=True)


def _encode(values: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF positional encoding [K, 1 + 2*frequencies] of scalars [K] in [0, 1]."""
    values = values[:, None]
    bands = [values]
    for octave in range(frequencies):
        scaled = values * (math.pi * 2.0**octave)
        bands += [torch.sin(scaled), torch.cos(scaled)]
    return torch.cat(bands, dim=-1)


def _mlp(width_in: int, hidden: int, layers: int, width_out: int, *, last_scale: float) -> torch.nn.Sequential:
    modules: list[torch.nn.Module] = []
    for _ in range(layers - 1):
        modules += [torch.nn.Linear(width_in, hidden), torch.nn.ReLU()]
        width_in = hidden
    last = torch.nn.Linear(width_in, width_out)
    with torch.no_grad():  # ToMiE A.5: the decoders' last layers start tiny (1e-2)
        last.weight.uniform_(-last_scale, last_scale)
        last.bias.zero_()
    modules.append(last)
    return torch.nn.Sequential(*modules)


class ExtraJoints(torch.nn.Module):
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
        self.position_mlp = _mlp(index_width, hidden_position, layers, 3, last_scale=1e-2)
        self.rotation_mlp = _mlp(index_width + time_width, hidden_rotation, layers, 3, last_scale=1e-2)

    @property
    def count(self) -> int:
        return int(self.parents.numel())

    def _index_encoding(self) -> torch.Tensor:
        index = torch.arange(self.count, device=self.parents.device, dtype=torch.float32)
        return _encode(index / max(1, self.count), self.hyper["index_frequencies"])

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
        features = torch.cat([self._index_encoding(), _encode(times, self.hyper["time_frequencies"])], dim=-1)
        return rotation_from_vector(self.rotation_mlp(features))

    def rotations_for_pose(self, bone_transforms: torch.Tensor) -> torch.Tensor:
        """Rotations [E,4] for a pose [J,4,4]: the training frame's if the pose is one, else the identity.

        Runs on the device without a host synchronization.
        """
        best, matched = match_pose(self.frame_poses, bone_transforms)
        rotations = self.frame_rotations(best)
        identity = torch.zeros_like(rotations)
        identity[:, 0] = 1.0
        return torch.where(matched > 0, rotations, identity)

    def transforms(self, bone_transforms: torch.Tensor, rotations: torch.Tensor | None = None) -> torch.Tensor:
        """Skinning transforms [E,4,4] of the grown joints for a pose.

        Args:
            bone_transforms: [J,4,4] the skeleton's rest-to-posed transforms.
            rotations: [E,4] (w, x, y, z) rotations to use instead of the decoded ones (explicit animation).
        """
        if rotations is None:
            rotations = self.rotations_for_pose(bone_transforms)
        elif rotations.shape != (self.count, 4):
            raise ValueError(f"rotations must have shape [{self.count}, 4] (w, x, y, z), got {list(rotations.shape)}")
        else:
            rotations = rotations.to(bone_transforms) / rotations.to(bone_transforms).norm(dim=-1, keepdim=True)
        rotation = quaternion_to_matrix(rotations)  # [E,3,3]
        centre = self.positions()
        local = torch.zeros(self.count, 4, 4, device=bone_transforms.device, dtype=bone_transforms.dtype)
        local[:, :3, :3] = rotation
        local[:, :3, 3] = centre - (rotation @ centre[:, :, None])[:, :, 0]
        local[:, 3, 3] = 1.0
        return bone_transforms[self.parents] @ local

    def group_matrix(self) -> torch.Tensor:
        """[J+E, J] 0/1 matrix mapping each skinning output (skeleton joints, then grown joints) to the skeleton
        joint it belongs to: itself, or a grown joint's parent."""
        joint_count = self.frame_poses.shape[1]
        groups = torch.cat([torch.arange(joint_count, device=self.parents.device), self.parents])
        return torch.nn.functional.one_hot(groups, joint_count).float()

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
