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

from warpavatar import ops
from warpavatar._src.precision import current_mlp_dtype, float32_sums, mlp_matmuls
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.geometry import Linear, linear_rows, match_pose, mlp, quat_from_vector, quat_multiply
from warpavatar.model.frozen import tensor_versions
from warpavatar.model.parts import AvatarPart
from warpavatar.optim import Adam, Optimizer
from warpavatar.model.skinning_field import box_encoding

__all__ = ["PoseCorrection", "relative_rotations_6d", "corrected_gaussians", "PoseCorrectionOptions",
           "PoseCorrectionExtension"]


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


def corrected_gaussians(outputs: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                        offset_scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The canonical Gaussians a pose correction's outputs [N,9] make of centres [N,3], unit orientations [N,4]
    and scales [N,3]: ``means + offset_scale * o[:, :3]``, ``quat_from_vector(o[:, 3:6]) * quats``,
    ``scales * exp(clamp(o[:, 6:9], -3, 3))`` (differentiable; playback runs the one-kernel
    :func:`warpavatar.ops.apply_correction`)."""
    offset = outputs[:, :3] * offset_scale
    rotated = quat_multiply(quat_from_vector(outputs[:, 3:6]), quats)
    return means + offset, rotated, scales * torch.exp(outputs[:, 6:9].clamp(-3.0, 3.0))


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
        #: what playback keeps of the network for those means (prepare_playback)
        self._network: _PlaybackNetwork | None = None

    def _encode(self, points: torch.Tensor) -> torch.Tensor:
        return box_encoding(points, self.bbox_min, self.bbox_max, self.frequencies)

    def forward(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, bone_transforms: torch.Tensor,
                *, key_pose: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Corrected canonical (means [N,3], unit quats [N,4], scales [N,3]) for this pose; ``key_pose`` [J,4,4]
        says which training instant's code applies (default: the pose itself)."""
        network = self._playback_network(means)
        code = None
        if self.frame_codes.shape[0]:
            key_pose = bone_transforms if key_pose is None else key_pose
            code = self.frame_code(key_pose) if network is None else \
                ops.match_frame_code(self.frame_poses, key_pose, self.frame_codes)  # the same values
        outputs = self._outputs(means, bone_transforms, code, network=network)
        if network is not None:  # playback: one kernel (float32 rounding apart, the same maths)
            return ops.apply_correction(outputs, means, quats, scales, network.offset_scale)
        if torch.is_grad_enabled():  # a pose without gradients (a refresh, a preview) keeps the training one's
            self.last_outputs = outputs
        return corrected_gaussians(outputs, means, quats, scales, self._offset_scale())

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

    def _outputs(self, means: torch.Tensor, bone_transforms: torch.Tensor, code: torch.Tensor | None, *,
                 network: "_PlaybackNetwork | None" = None) -> torch.Tensor:
        """Raw network outputs [N,9] for a pose and a frame code (None without codes); ``network``: what playback
        kept for these means (:meth:`_playback_network`), or None.

        The trunk's first layer reads ``[encoding(mean), pose, code]``; the pose and the code are the same for
        every Gaussian, so their columns make a bias of this frame, ``b + W[:, E:] @ [pose, code]``, and only
        the encoding's E columns multiply per Gaussian (no [N, E + pose + code] input is built). Playback reuses
        the encoding when the means are the frozen ones (:meth:`prepare_playback`), and there the parts of the
        network that depend only on the parameters (in float16 when the player asks for it); its frame bias
        comes from :func:`warpavatar.ops.frame_bias` (float32 rounding apart, the same values)."""
        first, width = self.trunk[0], self.position_width
        if network is not None:  # playback: the frame's bias in two kernels, the network's rest from the caches
            half = network.half is not None and current_mlp_dtype() == torch.float16
            low, high = network.half.bias_bounds if half else network.unbounded
            bias = ops.frame_bias(bone_transforms, network.parent_index, self.pose_encoder.weight,
                                  self.pose_encoder.bias, code, network.pose_columns, first.bias, low=low, high=high,
                                  dtype=torch.float16 if half else torch.float32)
            if half:
                return network.half.outputs(bias)
            encoded = network.encoding
        else:
            rotations = relative_rotations_6d(bone_transforms, self.parents)  # posing maths: float32 products
        with mlp_matmuls(means.device):
            if network is None:
                pose = self.pose_encoder(rotations)
                if code is not None:
                    pose = torch.cat([pose, code])
                bias = torch.addmv(first.bias, first.weight[:, width:], pose)
                encoded = self._encode(means.detach())
            hidden = linear_rows(encoded, first.weight[:, :width], bias)
            for layer in itertools.islice(self.trunk, 1, None):
                hidden = layer(hidden)
            return self.head(hidden)

    def _encoding_key(self, means: torch.Tensor) -> tuple:
        """What the encoding of ``means`` depends on beyond values: the tensors themselves (held, so that no other
        tensor takes their identity), their storage and version counters (bumped by every in-place change:
        optimizer steps, ``load_state_dict``)."""
        return _versions((means, self.bbox_min, self.bbox_max))

    def _cached_encoding(self, means: torch.Tensor) -> torch.Tensor | None:
        """The encoding [N,E] of ``means`` from the playback cache when it was made from these very means,
        unchanged (and no gradient is asked for), else None."""
        cache = self._playback
        if cache is None or torch.is_grad_enabled() or not _same_versions(cache[0], self._encoding_key(means)):
            return None
        return cache[1]

    def _playback_network(self, means: torch.Tensor) -> "_PlaybackNetwork | None":
        """What :meth:`prepare_playback` kept of the network, inside a player's frame
        (:func:`~warpavatar._src.precision.mlp_dtype`), when it serves these means (the cached encoding's,
        without gradients) and the parameters it was made from are unchanged; else None."""
        network = self._network
        if network is None or current_mlp_dtype() is None or self._cached_encoding(means) is None:
            return None
        if not _same_versions(network.key, self._network_key()):
            return None
        return network

    def _network_key(self) -> tuple:
        return _versions((*self.parameters(), *self.buffers()))

    @torch.no_grad()
    def prepare_playback(self, rest_means: torch.Tensor, *, mlp_dtype: torch.dtype = torch.float32) -> tuple:
        """Cache what a frame of a frozen avatar computes from the parameters alone: the positional encoding
        [N,E] of the stored canonical centres [N,3] (a dozen small kernels a frame), the parents' index and
        the first layer's pose columns (read by :func:`warpavatar.ops.frame_bias`), the offsets' world scale and, with ``mlp_dtype`` float16, the
        network's weights and that encoding in float16 (:class:`_HalfNetwork`; float32 is kept when the
        activations could leave float16's range). Buffers are refilled in place while their shapes hold;
        returns their storage (a captured frame reads it). Used by :meth:`_outputs` only for these very means,
        unchanged, without gradients.

        The first layer's product with the encoding still runs every frame: the product [N,hidden] is the size
        of the layer's output, so a cached product would cost a pass over that size to add the frame's bias,
        more memory traffic than the product of E = 27 columns with the bias added in the GEMM."""
        encoded_again = self._cached_encoding(rest_means) is None
        if encoded_again:
            encoded = self._encode(rest_means)
            old = None if self._playback is None else self._playback[1]
            if old is not None and old.shape == encoded.shape and old.device == encoded.device:
                encoded = old.copy_(encoded)
            self._playback = (self._encoding_key(rest_means), encoded)
        key = self._network_key()
        network = self._network
        half = mlp_dtype == torch.float16 or (network is not None and network.half_asked)  # kept once asked for
        if encoded_again or network is None or network.half_asked != half or not _same_versions(network.key, key):
            self._network = network = _PlaybackNetwork(self, self._playback[1], key, half=half, old=network)
        return network.storage()

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


def _versions(tensors) -> tuple:
    """(the tensors, held so that no other tensor takes their identity; their storage, version counters and
    shapes): what a cache made from them depends on beyond their values."""
    tensors = tuple(tensors)
    return tensors, tensor_versions(tensors)


def _same_versions(a: tuple, b: tuple) -> bool:
    """Whether two :func:`_versions` keys name the same tensors, unchanged."""
    return len(a[0]) == len(b[0]) and all(x is y for x, y in zip(a[0], b[0])) and a[1] == b[1]


_FLOAT16_MARGIN = 16.0
"""How many times the largest value seen in the rest and training poses must fit in float16's range (65504)."""


class _HalfNetwork:
    """The pose correction's per-Gaussian network in float16 for playback: the float16 encoding and weights,
    GEMMs summing in float32 (:func:`~warpavatar._src.precision.float32_sums`), activations and outputs stored
    in float16 (:func:`warpavatar.ops.apply_correction` reads them as they are).

    Built only when the values it stores stay well inside float16's range (6e-5 .. 65504): the largest value of the
    network (:meth:`peak`, over the rest pose and the training poses) times :data:`_FLOAT16_MARGIN` must be below
    65504. The frame's first-layer bias is also clamped to its bound over every rigid pose (:meth:`bias_bound`: a
    no-op for rigid poses), so no bone transform can push it out of range. Values below 6e-5 lose relative
    precision, not absolute: their error stays below 6e-8.
    """

    def __init__(self, part: "PoseCorrection", encoding: torch.Tensor, old: "_HalfNetwork | None"):
        half = torch.float16
        first, width = part.trunk[0], part.position_width
        bias_bound = _HalfNetwork.bias_bound(part)
        bounds = (-bias_bound, bias_bound)
        if old is not None and old.bias_bounds[0].shape == bias_bound.shape:
            bounds = tuple(k.copy_(v) for k, v in zip(old.bias_bounds, bounds))
        self.bias_bounds = bounds  # (low, high) of the frame's bias
        # the encoding's columns and the head's outputs padded with zeros to multiples of 8 (16-byte rows, as
        # float16 tensor-core GEMMs want them): the same sums, and apply_correction reads the first 9 outputs
        pad_in, pad_out = -width % 8, -part.head.out_features % 8
        pad = torch.nn.functional.pad
        layers = [(pad(first.weight[:, :width], (0, pad_in)), None)]
        layers += [(layer.weight, layer.bias) for layer in itertools.islice(part.trunk, 2, None, 2)]
        layers.append((pad(part.head.weight, (0, 0, 0, pad_out)), pad(part.head.bias, (0, pad_out))))
        values = [pad(encoding, (0, pad_in)), *(t for layer in layers for t in layer if t is not None)]
        kept = [] if old is None else old._tensors
        if [tuple(t.shape) for t in kept] == [tuple(t.shape) for t in values]:
            values = [k.copy_(v) for k, v in zip(kept, values)]  # in place: a captured frame reads them
        else:
            values = [v.to(half).contiguous() for v in values]
        self._tensors = values
        self.encoding = values[0]
        rest = iter(values[1:])
        self.layers = [(next(rest), None if bias is None else next(rest)) for _, bias in layers]

    @staticmethod
    def usable(part: "PoseCorrection") -> bool:
        """Whether the trunk is the (Linear, SiLU) pairs this class runs."""
        trunk = list(part.trunk)
        return len(trunk) >= 2 and len(trunk) % 2 == 0 and all(
            isinstance(m, torch.nn.Linear) if i % 2 == 0 else isinstance(m, torch.nn.SiLU) for i, m in enumerate(trunk))

    @staticmethod
    def bias_bound(part: "PoseCorrection") -> torch.Tensor:
        """[hidden] bound of |the first layer's bias of a frame| over rigid poses and the frame codes."""
        encoder = part.pose_encoder
        pose = encoder.bias.abs() + encoder.weight.abs().sum(1) * 2.0  # |R_parent^T R - I| <= 2 entry by entry
        if part.frame_codes.shape[0]:
            pose = torch.cat([pose, part.frame_codes.abs().amax(0)])
        first, width = part.trunk[0], part.position_width
        return first.bias.abs() + first.weight[:, width:].abs() @ pose

    @staticmethod
    def peak(part: "PoseCorrection", encoding: torch.Tensor, *, poses: int = 16) -> float:
        """The largest magnitude a float16 value of the network takes (the encoding, weights and biases, and every
        layer's outputs, computed in float32) at the rest pose and at up to ``poses`` of the training frames'
        poses with their codes (one host read)."""
        first, width = part.trunk[0], part.position_width
        layers = [*itertools.islice(part.trunk, 2, None, 2), part.head]
        largest = [encoding.abs().max(), first.weight.abs().max()]
        largest += [t.abs().max() for layer in layers for t in (layer.weight, layer.bias)]
        joint_count, frame_count = part.parents.shape[0], part.frame_codes.shape[0]
        rest = torch.eye(4, device=encoding.device).expand(joint_count, 4, 4)
        frames = torch.linspace(0, frame_count - 1, min(poses, frame_count)).round().long().tolist()
        cases = [(rest, None)] + [(part.frame_poses[f], part.frame_codes[f]) for f in frames]
        for pose, code in cases:
            feature = part.pose_encoder(relative_rotations_6d(pose, part.parents))
            if frame_count:
                feature = torch.cat([feature, torch.zeros_like(part.frame_codes[0]) if code is None else code])
            bias = torch.addmv(first.bias, first.weight[:, width:], feature)
            hidden = torch.addmm(bias, encoding, first.weight[:, :width].t())
            largest += [bias.abs().max(), hidden.abs().max()]
            for layer in layers:
                hidden = torch.nn.functional.linear(torch.nn.functional.silu(hidden), layer.weight, layer.bias)
                largest.append(hidden.abs().max())
        return float(torch.stack(largest).max())

    def outputs(self, bias: torch.Tensor) -> torch.Tensor:
        """Raw outputs [N,16] (float16; the first 9 are the network's, then zeros) for the first layer's bias of
        this frame [hidden] (float16, clamped to :attr:`bias_bounds`: :func:`warpavatar.ops.frame_bias`)."""
        with float32_sums(bias.device):
            (weight, _), *middle, (head_weight, head_bias) = self.layers
            hidden = torch.nn.functional.silu(torch.addmm(bias, self.encoding, weight.t()), inplace=True)
            for weight, layer_bias in middle:
                hidden = torch.nn.functional.silu(torch.addmm(layer_bias, hidden, weight.t()), inplace=True)
            return torch.addmm(head_bias, hidden, head_weight.t())

    def storage(self) -> tuple:
        return tuple(t.data_ptr() for t in (*self._tensors, *self.bias_bounds))


class _PlaybackNetwork:
    """What a playback frame of :class:`PoseCorrection` reads that depends on its parameters alone
    (:meth:`PoseCorrection.prepare_playback`): the encoding of the stored centres, the index of each joint's
    parent (itself for roots), the first layer's pose columns, the offsets' world scale and, once a player asked
    for float16 and when it fits, the :class:`_HalfNetwork`.

    Attributes:
        key: the :func:`_versions` of the part's parameters and buffers it was made from.
        half_asked: whether a player asked for float16 (``half`` is None when none did or float16 does not fit;
            frames run it only inside :func:`~warpavatar._src.precision.mlp_dtype` float16 blocks).
    """

    def __init__(self, part: "PoseCorrection", encoding: torch.Tensor, key: tuple, *, half: bool,
                 old: "_PlaybackNetwork | None"):
        self.key, self.half_asked, self.encoding = key, half, encoding
        parents = part.parents
        hidden = part.trunk[0].out_features
        infinity = torch.full((hidden,), float("inf"), device=parents.device)
        values = [torch.where(parents >= 0, parents, torch.arange(parents.shape[0], device=parents.device)).int(),
                  part.trunk[0].weight[:, part.position_width:].contiguous(), part._offset_scale(), -infinity,
                  infinity]
        kept = None if old is None else old._tensors
        if kept is not None and [t.shape for t in kept] == [t.shape for t in values]:
            values = [k.copy_(v) for k, v in zip(kept, values)]  # in place: a captured frame reads them
        self._tensors = values
        #: each joint's parent (itself for roots) [J] int32, the first layer's pose and code columns [H, P+C],
        #: the offsets' world scale [], and no bound on the frame bias (-inf, inf) [H] each
        self.parent_index, self.pose_columns, self.offset_scale, *unbounded = values
        self.unbounded = tuple(unbounded)
        self.half = None
        #: the largest value the network takes in float32 (:meth:`_HalfNetwork.peak`; None unless float16 asked)
        self.peak = _HalfNetwork.peak(part, encoding) if half and _HalfNetwork.usable(part) else None
        if self.peak is not None and self.peak * _FLOAT16_MARGIN <= 65504.0:
            self.half = _HalfNetwork(part, encoding, None if old is None else old.half)

    def storage(self) -> tuple:
        own = tuple(t.data_ptr() for t in (self.encoding, *self._tensors))
        return own + (() if self.half is None else self.half.storage())


@dataclass
class PoseCorrectionOptions:
    # off by default: default fits with the codes spiked late on an H200 (BENCHMARKS.md, "Avatar quality")
    frame_codes: bool = option(False, "give each training frame a learned code in the pose correction (cloth "
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
        self.optimizer = Adam(part.parameters(), lr=fit.config.field_lr)

    def step_capturable(self, step) -> bool:
        return True  # device work only; what changes (train_field) changes the step's graph key too

    def begin_step(self, step) -> None:
        self.part.requires_grad_(step.train_field)  # trains with the field, from the joint stage on

    def losses(self, step) -> dict[str, LossTerm]:
        if not step.train_field:
            return {}
        return {"pose_correction": LossTerm(self.options.lambda_pose_correction, self.part.regularization())}

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [self.optimizer] if step.train_field else []

    def state_dict(self) -> dict:
        return {"part": self.part.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.part.load_state_dict(state["part"])
        self.optimizer.load_state_dict(state["optimizer"])
