"""Pose-conditioned correction of canonical Gaussians (in the spirit of ToMiE's Phi_d), applied before skinning.

A small MLP maps (canonical position, pose) to a position offset, a rotation and a log-scale change of each
canonical Gaussian. It captures what linear blend skinning of a fixed shape cannot: garments and soft parts
whose shape follows the pose (a skirt that swings with the legs, a sleeve that folds). The pose is read from
the bone transforms as each joint's rotation relative to its parent (6D: two matrix columns, minus the
identity's), so it does not depend on where the subject stands or faces. The last layer starts at zero: the
correction begins as the identity and grows only as far as the images ask for (and its regularizer allows).

Cloth also depends on its history (a skirt still swinging after the legs stopped), which no function of the
current pose can tell. For the instants seen in training, each training frame therefore also has a small
learned code (as per-frame latent codes in dynamic NeRFs): a pose equal to a training frame's (a novel view of
a training instant) uses that frame's code, any other pose uses the zero code, i.e. the pose-only correction.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch

from warpavatar._src.cuda_graph import adam_options
from warpavatar._src.precision import mlp_matmuls
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.geometry import Linear, linear_rows, match_pose, mlp, quat_from_vector, quat_multiply
from warpavatar.model.parts import AvatarPart
from warpavatar.model.skinning_field import box_encoding

__all__ = ["PoseCorrection", "relative_rotations_6d", "PoseCorrectionOptions", "PoseCorrectionExtension"]


def relative_rotations_6d(bone_transforms: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
    """Each joint's rotation relative to its parent's, as 6 numbers (first two columns minus the identity's).

    Args:
        bone_transforms: [J,4,4] rest-to-posed transforms.
        parents: [J] parent index, -1 for roots; roots contribute zeros, so the global heading is ignored.

    Returns:
        [J*6] pose feature.
    """
    rotations = bone_transforms[:, :3, :3]
    has_parent = parents >= 0
    parent_rotations = torch.where(has_parent[:, None, None], rotations[parents.clamp_min(0)], rotations)
    relative = parent_rotations.transpose(1, 2) @ rotations
    identity = torch.eye(3, device=rotations.device, dtype=rotations.dtype)
    six = (relative - identity)[:, :, :2].reshape(-1, 6)
    return six.reshape(-1)


class PoseCorrection(AvatarPart):
    """MLP(canonical position, pose) -> (offset [N,3], rotation (3 numbers: the vector part of an unnormalized
    quaternion with w = 1), log-scale change [N,3]).

    Args:
        bbox_min: [3] canonical box corner (positions are encoded relative to the box).
        bbox_max: [3] opposite corner.
        parents: [J] parent index of each joint.
        hidden: MLP width.
        layers: hidden layers.
        frequencies: positional-encoding octaves of the position.
        pose_width: the pose feature [J*6] is first compressed to this many numbers.
        frame_count: number of training frames that get a code (0: none).
        code_width: length of each frame code.
    """

    name = "pose_correction"

    def __init__(self, bbox_min: torch.Tensor, bbox_max: torch.Tensor, parents: torch.Tensor, *, hidden: int = 128,
                 layers: int = 3, frequencies: int = 4, pose_width: int = 32, frame_count: int = 0,
                 code_width: int = 16):
        super().__init__()
        self.register_buffer("bbox_min", bbox_min.float().clone())
        self.register_buffer("bbox_max", bbox_max.float().clone())
        self.register_buffer("parents", torch.as_tensor(parents).long().clone())
        self.frequencies = frequencies
        self.hyper = dict(hidden=hidden, layers=layers, frequencies=frequencies, pose_width=pose_width,
                          frame_count=frame_count, code_width=code_width)
        joint_count = self.parents.shape[0]
        self.pose_encoder = torch.nn.Linear(joint_count * 6, pose_width)
        self.frame_codes = torch.nn.Parameter(torch.zeros(frame_count, code_width))
        # the training frames' poses, to recognise a training instant (filled by set_frame_poses)
        self.register_buffer("frame_poses", torch.zeros(frame_count, joint_count, 4, 4))
        width_in = 3 + 6 * frequencies + pose_width + (code_width if frame_count else 0)
        self.trunk = mlp(width_in, hidden, layers, activation=torch.nn.SiLU)
        self.head = Linear(hidden, 3 + 3 + 3)
        torch.nn.init.zeros_(self.head.weight)
        torch.nn.init.zeros_(self.head.bias)
        self.last_outputs: torch.Tensor | None = None
        #: (key, encoding [N,E]) of the frozen canonical means in playback (prepare_playback)
        self._playback: tuple[tuple, torch.Tensor] | None = None

    def _encode(self, points: torch.Tensor) -> torch.Tensor:
        return box_encoding(points, self.bbox_min, self.bbox_max, self.frequencies)

    def forward(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, bone_transforms: torch.Tensor,
                *, key_pose: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Corrected canonical (means [N,3], unit quats [N,4], scales [N,3]) for this pose; ``key_pose`` [J,4,4]
        says which training instant's code applies (default: the pose itself)."""
        code = None
        if self.frame_codes.shape[0]:
            code = self.frame_code(bone_transforms if key_pose is None else key_pose)
        outputs = self._outputs(means, bone_transforms, code)
        if torch.is_grad_enabled():  # a pose without gradients (a refresh, a preview) keeps the training one's
            self.last_outputs = outputs
        offset = outputs[:, :3] * self._offset_scale()
        rotated = quat_multiply(quat_from_vector(outputs[:, 3:6]), quats)
        return means + offset, rotated, scales * torch.exp(outputs[:, 6:9].clamp(-3.0, 3.0))

    def deform_canonical(self, canonical, bones, frame):
        """The corrected canonical Gaussians for this pose (read from the skeleton's transforms in ``bones``)."""
        means, quats, scales = self(canonical.means, canonical.quats, canonical.scales,
                                    bones[: self.parents.shape[0]], key_pose=frame.bone_transforms)
        return canonical.replace(means=means, quats=quats, scales=scales)

    def _offset_scale(self) -> torch.Tensor:
        """World length of a unit position output: a tenth of the canonical box's diagonal."""
        return 0.1 * (self.bbox_max - self.bbox_min).norm()

    @property
    def position_width(self) -> int:
        """Width of the position encoding: the first columns of the trunk's first layer (the pose's follow)."""
        return 3 + 6 * self.frequencies

    def _outputs(self, means: torch.Tensor, bone_transforms: torch.Tensor, code: torch.Tensor | None
                 ) -> torch.Tensor:
        """Raw network outputs [N,9] for a pose and a frame code (None without codes).

        The trunk's first layer reads ``[encoding(mean), pose, code]``; the pose and the code are the same for
        every Gaussian, so their columns make a bias of this frame, ``b + W[:, E:] @ [pose, code]``, and only
        the encoding's E columns multiply per Gaussian (no [N, E + pose + code] input is built). Playback reuses
        the encoding when the means are the frozen ones (:meth:`prepare_playback`)."""
        rotations = relative_rotations_6d(bone_transforms, self.parents)  # posing maths: float32 products
        with mlp_matmuls(means.device):
            pose = self.pose_encoder(rotations)
            if code is not None:
                pose = torch.cat([pose, code])
            first, width = self.trunk[0], self.position_width
            bias = torch.addmv(first.bias, first.weight[:, width:], pose)
            encoded = self._cached_encoding(means)
            if encoded is None:
                encoded = self._encode(means.detach())
            hidden = linear_rows(encoded, first.weight[:, :width], bias)
            for layer in itertools.islice(self.trunk, 1, None):
                hidden = layer(hidden)
            return self.head(hidden)

    def _encoding_key(self, means: torch.Tensor) -> tuple:
        """What the encoding of ``means`` depends on beyond values: the tensors themselves (held, so that no other
        tensor takes their identity), their storage and version counters (bumped by every in-place change:
        optimizer steps, ``load_state_dict``)."""
        tensors = (means, self.bbox_min, self.bbox_max)
        return tensors, tuple((t.data_ptr(), t._version, tuple(t.shape)) for t in tensors)

    def _cached_encoding(self, means: torch.Tensor) -> torch.Tensor | None:
        """The encoding [N,E] of ``means`` from the playback cache when it was made from these very means,
        unchanged (and no gradient is asked for), else None."""
        cache = self._playback
        if cache is None or torch.is_grad_enabled():
            return None
        (tensors, versions), encoded = cache
        now_tensors, now_versions = self._encoding_key(means)
        if any(a is not b for a, b in zip(tensors, now_tensors)) or versions != now_versions:
            return None
        return encoded

    @torch.no_grad()
    def prepare_playback(self, rest_means: torch.Tensor) -> tuple:
        """Cache the positional encoding [N,E] of the stored canonical centres [N,3] (every frame of a frozen
        avatar computes it again: a dozen small kernels), in a buffer refilled in place while its shape holds;
        returns that buffer's storage (a captured frame reads it). Used by :meth:`_outputs` only for these very
        means, unchanged, without gradients.

        The first layer's product with it still runs every frame: the product [N,hidden] is the size of the
        layer's output, so a cached product would cost a pass over that size to add the frame's bias, more
        memory traffic than the product of E = 27 columns with the bias added in the GEMM."""
        if self._cached_encoding(rest_means) is None:
            encoded = self._encode(rest_means)
            old = None if self._playback is None else self._playback[1]
            if old is not None and old.shape == encoded.shape and old.device == encoded.device:
                encoded = old.copy_(encoded)
            self._playback = (self._encoding_key(rest_means), encoded)
        encoded = self._playback[1]
        return (encoded.data_ptr(), tuple(encoded.shape))

    def history_offsets(self, means: torch.Tensor, frame: int) -> torch.Tensor:
        """Position offsets [N,3] [world units] that training frame ``frame``'s code adds to the pose-only
        correction of canonical points [N,3]: the part of the frame's shape no function of the pose explains
        (cloth that lags or swings). Zeros without frame codes."""
        if not self.frame_codes.shape[0]:
            return torch.zeros_like(means)
        pose = self.frame_poses[frame]
        with_code = self._outputs(means, pose, self.frame_codes[frame])[:, :3]
        without = self._outputs(means, pose, torch.zeros_like(self.frame_codes[frame]))[:, :3]
        return (with_code - without) * self._offset_scale()

    def set_frame_poses(self, bone_transforms: torch.Tensor) -> None:
        """Record the training frames' poses [T,J,4,4] (T = frame_count), in the order of the codes."""
        self.frame_poses.copy_(bone_transforms)

    def frame_code(self, bone_transforms: torch.Tensor, *, tolerance: float = 1e-4) -> torch.Tensor:
        """The code of the training frame whose pose equals ``bone_transforms`` (within ``tolerance``), else zeros.

        Runs on the device without a host synchronization.
        """
        best, matched = match_pose(self.frame_poses, bone_transforms, tolerance=tolerance)
        return self.frame_codes.index_select(0, best.reshape(1))[0] * matched

    def regularization(self) -> torch.Tensor:
        """Mean squared raw output of the last forward with gradients (keeps the correction small where images
        do not need it)."""
        if self.last_outputs is None:
            return torch.zeros((), device=self.bbox_min.device)
        codes = (self.frame_codes**2).sum(-1).mean() if self.frame_codes.shape[0] else 0.0
        return (self.last_outputs**2).sum(-1).mean() + codes

    def state_for_file(self) -> dict:
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}, "hyper": dict(self.hyper)}

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "PoseCorrection":
        weights = state["state_dict"]
        part = cls(weights["bbox_min"], weights["bbox_max"], weights["parents"], **state["hyper"])
        part.load_state_dict(weights)
        return part.to(device)


@dataclass
class PoseCorrectionOptions:
    frame_codes: bool = option(True, "give each training frame a learned code in the pose correction (cloth "
                               "dynamics of the training instants; other poses use the pose-only correction)")
    pose_correction_hidden: int = option(128, "hidden width of the pose-correction MLP")
    lambda_pose_correction: float = option(0.01, "weight of the pose correction's size regularizer")


class PoseCorrectionExtension(Extension):
    """Trains :class:`PoseCorrection` with the skinning field (from the joint stage on, same learning rate)."""

    name = "pose_correction"
    title = "pose correction (--pose-correction)"
    summary = "learn a pose-conditioned correction of canonical Gaussians (garments)"
    options_type = PoseCorrectionOptions
    enabled_by_default = True
    presets = {"quick": {"pose_correction": False}}

    def attach(self) -> None:
        fit, options = self.fit, self.options
        field = fit.skinning.field
        frame_count = fit.frames.count if options.frame_codes else 0
        part = PoseCorrection(field.bbox_min, field.bbox_max, torch.as_tensor(fit.frames.skeleton.parents),
                              hidden=options.pose_correction_hidden, frame_count=frame_count).to(fit.device)
        if options.frame_codes:
            part.set_frame_poses(fit.frames.bone_transforms)
        self.part = fit.avatar.add_part(part)
        self.optimizer = torch.optim.Adam(part.parameters(), lr=fit.config.field_lr, **adam_options(fit.device))

    def step_capturable(self, step) -> bool:
        return True  # device work only; what changes (train_field) changes the step's graph key too

    def begin_step(self, step) -> None:
        self.part.requires_grad_(step.train_field)  # trains with the field, from the joint stage on

    def losses(self, step) -> dict[str, LossTerm]:
        if not step.train_field:
            return {}
        return {"pose_correction": LossTerm(self.options.lambda_pose_correction, self.part.regularization())}

    def optimizers(self, step) -> list[torch.optim.Optimizer]:
        return [self.optimizer] if step.train_field else []

    def state_dict(self) -> dict:
        return {"part": self.part.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.part.load_state_dict(state["part"])
        self.optimizer.load_state_dict(state["optimizer"])
