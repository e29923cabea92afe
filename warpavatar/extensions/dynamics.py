"""SMAD's secondary dynamics (SMAD, Sec. 3.1-3.2 and appendix B): a velocity-encoded Gaussian graph whose
nodes move by a mass-spring-damper system, stepped by explicit (semi-implicit) Euler, under forces a
message-passing network predicts from the body's motion.

Where :class:`~warpavatar.extensions.secondary_motion.SecondaryMotion` learns one free displacement per
training frame (so it replays the training instants and gives nothing for a new motion), this model is a
function of the motion: any pose sequence can be rolled out, so cloth responds to a dance it never saw (as far
as the fit loosened its springs).

State and frames. Each graph node ``i`` has a canonical (rest) position ``x_i`` and a secondary state, its
displacement ``d_i`` and velocity ``u_i`` [world units, world units / s], both in the node's canonical frame.
The posed node sits at ``T_i(t) (x_i + d_i)``, where ``T_i(t)`` blends the bone transforms by the node's
skinning weights, so the displacement turns with the body. Between frames ``t - 1`` and ``t`` (``dt`` seconds):

* **Velocity encoding** (SMAD Sec. 3.1): the node's skinned velocity at the last ``velocity_history`` frames,
  and its skinned acceleration, both rotated into the node's frame at ``t``; a pose-window embedding (an MLP
  of each bone's rotation relative to the root over the last ``pose_window`` frames, SMAD's table G), shared by
  every node; the node's canonical position and its current ``d``, ``u``.
* **Message passing** (SMAD appendix B.2): a node projection, then ``message_passes`` iterations that share
  an edge MLP on ``[h_i, h_j, x_j + d_j - x_i - d_i, u_j - u_i, |.|, 1]``, mean aggregation over the node's k-NN
  edges and a GRU cell; a decoder MLP and a linear head give a force per node.
* **Mass-spring-damper step** (SMAD Eq. 2-4): unit masses; the external force is the network's (bounded) force
  plus the inertial force of the accelerating body frame (``-R_i^T a_i``: cloth that is not held stays behind)
  and a learnable anchor spring ``-k^a_i d_i`` towards the skinned shape; learnable stiffness ``k_ij`` on the
  k-NN pairs (both directions of an undirected pair share it) with their canonical rest offsets, and
  learnable damping ``gamma_i``.
  :func:`warpavatar.ops.spring_step` (Warp kernels with a hand-written backward) integrates ``substeps``
  semi-implicit Euler steps.

Stiffness, anchor and damping are squashed into ranges that keep the explicit step stable for any parameter
values (Gershgorin bound of the symmetric spring system with its largest node degree), frames farther apart than the
training ones take more substeps, and the network's force is bounded: the rollout cannot blow up.
SMAD's decoder also predicts colour, covariance and a velocity refinement; here the dynamics move positions
only (the Gaussians' own colours and shapes stay the avatar's).

Rollouts: :meth:`SecondaryDynamics.rollout` runs a pose sequence from rest. The table of the training sequence
(:meth:`set_training_rollout`) answers poses equal to a training frame (novel views of training instants); a
sequence prepared with :meth:`prepare_sequence` answers its own poses (novel motions, exports); other poses get
no displacement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.extensions.graph import GRAPH_PRESETS, GraphMotionOptions, NodeGraph, graph_nodes
from warpavatar.geometry import match_pose, mlp
from warpavatar.optim import Adam, Optimizer

__all__ = ["SecondaryDynamics", "DynamicsState", "DynamicsOptions", "DynamicsExtension"]


class DynamicsState:
    """Secondary state of every node: displacement ``d`` and velocity ``u``, [M,3] each, canonical frame."""

    __slots__ = ("displacement", "velocity")

    def __init__(self, displacement: torch.Tensor, velocity: torch.Tensor):
        self.displacement = displacement
        self.velocity = velocity


def _bounded(raw: torch.Tensor, upper: float) -> torch.Tensor:
    return upper * torch.sigmoid(raw)


def _bounded_inverse(value: float, upper: float) -> float:
    fraction = min(max(value / upper, 1e-4), 1.0 - 1e-4)
    return math.log(fraction / (1.0 - fraction))


class SecondaryDynamics(NodeGraph):
    """SMAD's graph dynamics: a GNN force model on a mass-spring-damper node graph.

    Args:
        node_positions: [M,3] canonical node positions [world units] (see
            :func:`~warpavatar.extensions.graph.voxel_downsample`).
        node_weights: [M,J] skinning weights of the nodes (rows sum to 1); refresh them with
            :meth:`set_node_weights` while the skinning field trains.
        parents: [J] parent index of each bone (-1 for roots); the first root is the pose embedding's frame.
        voxel_size: the voxel edge of the nodes [world units]; the unit of lengths in the network's inputs.
        frame_interval: typical seconds between frames; with ``voxel_size`` it sets the velocity and
            acceleration units of the inputs and the stability bounds of the springs.
        neighbors: k of the k-NN edges (SMAD: 16).
        bind_count: nearest nodes each Gaussian blends.
        hidden: width of node features, messages and the GRU (SMAD: 256 / 128).
        embedding: width of the pose-window embedding (SMAD: 128).
        velocity_history: past skinned velocities in a node's encoding (SMAD: tau_v = 11).
        pose_window: frames of the pose-window embedding.
        message_passes: shared message-passing iterations (SMAD: 3).
        substeps: semi-implicit Euler steps per frame of the typical interval (longer intervals take
            proportionally more, so every substep stays within the stability bounds).
        force_limit: bound of the network's force, in voxels per typical frame interval squared.
    """

    name = "dynamics"

    def __init__(self, node_positions: torch.Tensor, node_weights: torch.Tensor, parents, *, voxel_size: float,
                 frame_interval: float, neighbors: int = 16, bind_count: int = 4, hidden: int = 64,
                 embedding: int = 32, velocity_history: int = 11, pose_window: int = 4, message_passes: int = 3,
                 substeps: int = 2, force_limit: float = 4.0):
        super().__init__(node_positions, voxel_size=voxel_size, neighbors=neighbors, bind_count=bind_count)
        node_count = self.node_count
        parents = torch.as_tensor(parents, dtype=torch.long).reshape(-1)
        joint_count = int(parents.numel())
        if node_weights.shape != (node_count, joint_count):
            raise ValueError(f"node_weights must have shape [{node_count}, {joint_count}], "
                             f"got {list(node_weights.shape)}")
        if not (math.isfinite(frame_interval) and frame_interval > 0):
            raise ValueError(f"frame_interval must be a positive number of seconds, got {frame_interval}")
        for name, value in (("hidden", hidden), ("embedding", embedding), ("velocity_history", velocity_history),
                            ("pose_window", pose_window), ("message_passes", message_passes),
                            ("substeps", substeps)):
            if int(value) < 1:
                raise ValueError(f"{name} must be at least 1, got {value}")
        if not (math.isfinite(force_limit) and force_limit > 0):
            raise ValueError(f"force_limit must be a positive number, got {force_limit}")
        roots = torch.nonzero(parents < 0).flatten()
        if roots.numel() == 0:
            raise ValueError("parents has no root bone (-1)")
        self.hyper.update(frame_interval=float(frame_interval), hidden=int(hidden), embedding=int(embedding),
                          velocity_history=int(velocity_history), pose_window=int(pose_window),
                          message_passes=int(message_passes), substeps=int(substeps), joint_count=joint_count,
                          force_limit=float(force_limit), root=int(roots[0]))
        self.register_buffer("node_weights", node_weights.detach().float().clone())
        self.register_buffer("parents", parents.clone())
        device = self.nodes.device
        centre = 0.5 * (self.nodes.min(0).values + self.nodes.max(0).values)
        self.register_buffer("centre", centre)
        self.register_buffer("extent", (self.nodes.max(0).values - self.nodes.min(0).values).max().clamp_min(1e-6))

        # SMAD's graph is undirected: both directions of every k-NN pair, sharing one stiffness, so the spring
        # system is symmetric (real eigenvalues, for which the bounds below make the explicit step stable)
        directed = self.edges.long()
        pairs = torch.unique(torch.sort(directed, dim=1).values, dim=0)  # [P,2], i < j
        both = torch.cat([pairs, pairs.flip(1)])
        pair_index = torch.arange(pairs.shape[0], device=device).repeat(2)
        order = torch.argsort(both[:, 0] * node_count + both[:, 1])  # sorted by receiver (cheapest for the kernel)
        edges = both[order].to(torch.int32).contiguous()
        self.edges = edges
        self.rest_offset = self.nodes[edges[:, 0].long()] - self.nodes[edges[:, 1].long()]
        self.register_buffer("edge_pair", pair_index[order].contiguous())
        in_degree = torch.bincount(edges[:, 0].long(), minlength=node_count)
        degree = int(in_degree.max())
        # 1 / edges per receiver [M,1], for the mean aggregation of messages
        self.register_buffer("inverse_degree", 1.0 / in_degree.clamp_min(1).float()[:, None])

        # stability bounds of the explicit step (unit masses), for the substep interval: by Gershgorin, the
        # spring matrix's eigenvalues lie below 2 * degree * max_stiffness + max_anchor = 2 / step^2
        step = float(frame_interval) / int(substeps)
        self.hyper.update(max_stiffness=0.5 / (degree * step * step), max_anchor=1.0 / (step * step),
                          max_damping=0.5 / step, max_degree=degree)
        self.stiffness_raw = torch.nn.Parameter(torch.full(
            (pairs.shape[0],), _bounded_inverse(0.2 * self.hyper["max_stiffness"], self.hyper["max_stiffness"]),
            device=device))
        self.anchor_raw = torch.nn.Parameter(torch.full(
            (node_count,), _bounded_inverse(0.45 * self.hyper["max_anchor"], self.hyper["max_anchor"]),
            device=device))
        self.damping_raw = torch.nn.Parameter(torch.full(
            (node_count,), _bounded_inverse(0.1 * self.hyper["max_damping"], self.hyper["max_damping"]),
            device=device))

        pose_inputs = pose_window * joint_count * 6
        self.pose_embedding = mlp(pose_inputs, 2 * hidden, 2, embedding, layer_norm=True).to(device)
        node_inputs = 3 + 3 * velocity_history + 3 + 3 + 3 + embedding
        self.node_projection = mlp(node_inputs, hidden, 1).to(device)
        self.edge_mlp = mlp(2 * hidden + 8, hidden, 1, hidden).to(device)
        self.node_update = torch.nn.GRUCell(hidden, hidden).to(device)
        self.decoder = mlp(hidden, hidden, 1, hidden).to(device)
        self.force_head = torch.nn.Linear(hidden, 3).to(device)
        # Start close to the spring-damper response to the body's motion, held stiffly to the skinned shape
        # (an anchor frequency of about 1.3 / frame): the photometric loss loosens the nodes that swing.
        with torch.no_grad():
            self.force_head.weight.mul_(0.01)
            self.force_head.bias.zero_()

        self.register_buffer("frame_poses", torch.zeros(0, joint_count, 4, 4, device=device))
        self.register_buffer("frame_displacement", torch.zeros(0, node_count, 3, device=device))
        self._sequence: tuple[torch.Tensor, torch.Tensor] | None = None  # prepared (poses, displacement)

    # ------------------------------------------------------------------------------------- parameters
    @property
    def stiffness(self) -> torch.Tensor:
        """Stiffness k_ij [1/s^2] (unit masses) of every directed edge, [E] (both directions of a pair share it)."""
        return _bounded(self.stiffness_raw, self.hyper["max_stiffness"]).index_select(0, self.edge_pair)

    @property
    def anchor(self) -> torch.Tensor:
        """Anchor stiffness towards the skinned shape [1/s^2], [M]."""
        return _bounded(self.anchor_raw, self.hyper["max_anchor"])

    @property
    def damping_coefficient(self) -> torch.Tensor:
        """Damping gamma_i [1/s], [M]."""
        return _bounded(self.damping_raw, self.hyper["max_damping"])

    @property
    def speed_unit(self) -> float:
        """Velocity unit of the network inputs: one voxel per typical frame interval [world units / s]."""
        return self.hyper["voxel_size"] / self.hyper["frame_interval"]

    @torch.no_grad()
    def set_node_weights(self, node_weights: torch.Tensor) -> None:
        """Replace the nodes' skinning weights [M,J] (as the skinning field trains)."""
        if node_weights.shape != self.node_weights.shape:
            raise ValueError(f"node_weights must have shape {list(self.node_weights.shape)}, "
                             f"got {list(node_weights.shape)}")
        self.node_weights.copy_(node_weights.detach())

    # ---------------------------------------------------------------------------------------- drive
    def drive(self, bone_transforms: torch.Tensor, intervals: torch.Tensor) -> dict:
        """What the body's motion tells each node, for every frame of a sequence (no learned parameters).

        Args:
            bone_transforms: [T,J,4,4] rest-to-posed bone transforms of consecutive frames.
            intervals: [T] seconds since the previous frame (the first entry is not used).

        Returns:
            dict with ``velocities`` [T,M,3*velocity_history] (skinned velocities of the last frames in the
            node's current frame, in speed units), ``acceleration`` [T,M,3] (skinned acceleration in the
            node's frame [world units / s^2]) and ``pose_features`` [T, pose_window*J*6].
        """
        frame_count = bone_transforms.shape[0]
        if bone_transforms.dim() != 4 or bone_transforms.shape[1:] != (self.hyper["joint_count"], 4, 4):
            raise ValueError(f"bone_transforms must have shape [T, {self.hyper['joint_count']}, 4, 4], "
                             f"got {list(bone_transforms.shape)}")
        if intervals.shape != (frame_count,):
            raise ValueError(f"intervals must have shape [{frame_count}], got {list(intervals.shape)}")
        bones = bone_transforms.float()
        intervals = intervals.to(bones)
        blended = torch.einsum("mj,tjab->tmab", self.node_weights, bones)  # [T,M,4,4]
        rotation = blended[..., :3, :3]
        positions = torch.einsum("tmab,mb->tma", rotation, self.nodes) + blended[..., :3, 3]
        velocity = torch.zeros_like(positions)
        if frame_count > 1:
            velocity[1:] = (positions[1:] - positions[:-1]) / intervals[1:, None, None]
        acceleration = torch.zeros_like(positions)
        if frame_count > 2:
            acceleration[2:] = (velocity[2:] - velocity[1:-1]) / intervals[2:, None, None]
        inverse = rotation.transpose(-1, -2)  # R^T of the blended transform, the node frame's inverse rotation
        history = []
        for lag in range(self.hyper["velocity_history"]):
            lagged = torch.zeros_like(velocity)
            if lag < frame_count:
                lagged[lag:] = velocity[: frame_count - lag]
            history.append(torch.einsum("tmab,tmb->tma", inverse, lagged))
        local_acceleration = torch.einsum("tmab,tmb->tma", inverse, acceleration)
        root = bones[:, self.hyper["root"]]
        relative = torch.linalg.solve(root[:, None], bones)[..., :3, :2]  # [T,J,3,2]: two rotation columns
        relative = relative.reshape(frame_count, -1)
        window = []
        for lag in range(self.hyper["pose_window"]):
            rows = torch.clamp(torch.arange(frame_count, device=bones.device) - lag, min=0)
            window.append(relative[rows])
        return {"velocities": torch.cat(history, dim=-1) / self.speed_unit,
                "acceleration": local_acceleration, "pose_features": torch.cat(window, dim=-1)}

    def rest_state(self) -> DynamicsState:
        zeros = torch.zeros_like(self.nodes)
        return DynamicsState(zeros, zeros.clone())

    # ----------------------------------------------------------------------------------------- step
    def step(self, state: DynamicsState, drive: dict, frame: int, interval: float) -> DynamicsState:
        """Advance the secondary state to frame ``frame`` of a sequence whose :meth:`drive` is ``drive``.

        Args:
            state: the state at frame ``frame - 1``.
            drive: :meth:`drive` of the sequence.
            frame: index of the frame being reached.
            interval: seconds from frame ``frame - 1`` to ``frame`` (a Python number: a device scalar would
                cost a host synchronization per call).
        """
        voxel = self.hyper["voxel_size"]
        speed = self.speed_unit
        acceleration_unit = speed / self.hyper["frame_interval"]
        displacement, velocity = state.displacement, state.velocity
        embedding = self.pose_embedding(drive["pose_features"][frame][None])  # [1,E]
        inertial = drive["acceleration"][frame]
        features = torch.cat([
            (self.nodes - self.centre) / self.extent,
            drive["velocities"][frame],
            inertial / acceleration_unit,
            displacement / voxel,
            velocity / speed,
            embedding.expand(self.node_count, -1),
        ], dim=-1)
        hidden = self.node_projection(features)
        receivers = self.edges[:, 0].long()
        senders = self.edges[:, 1].long()
        # index_select rather than indexing: its backward (index_add) is deterministic on the CPU, so fits
        # with dynamics stay reproducible there
        positions = self.nodes + displacement
        offset = (positions.index_select(0, senders) - positions.index_select(0, receivers)) / voxel
        relative_velocity = (velocity.index_select(0, senders) - velocity.index_select(0, receivers)) / speed
        geometry = torch.cat([offset, relative_velocity, offset.norm(dim=-1, keepdim=True),
                              torch.ones_like(offset[:, :1])], dim=-1)
        # The edge MLP's first layer on [h_i, h_j, geometry] is split by columns: the two node blocks act on
        # the M node features before the gather (not on E = k M gathered rows), the geometry block once per
        # step. Same function and parameters as applying the layer to the concatenation, ~k times fewer FLOPs.
        first, rest = self.edge_mlp[0], self.edge_mlp[1:]
        width = self.hyper["hidden"]
        receiver_block, sender_block = first.weight[:, :width], first.weight[:, width: 2 * width]
        geometry_term = torch.nn.functional.linear(geometry, first.weight[:, 2 * width:], first.bias)
        for _ in range(self.hyper["message_passes"]):
            pre_activation = (hidden.matmul(receiver_block.t()).index_select(0, receivers)
                              + hidden.matmul(sender_block.t()).index_select(0, senders) + geometry_term)
            messages = rest(pre_activation)
            aggregated = torch.zeros_like(hidden).index_add_(0, receivers, messages) * self.inverse_degree
            hidden = self.node_update(aggregated, hidden)
        # bounded (tanh): a learned force that feeds back on the state cannot drive the stable spring-damper
        # system beyond a bounded response
        limit = self.hyper["force_limit"] * acceleration_unit
        network_force = limit * torch.tanh(self.force_head(self.decoder(hidden)) / self.hyper["force_limit"])
        external = network_force - inertial  # unit masses: force = acceleration
        stiffness, anchor, damping = self.stiffness, self.anchor, self.damping_coefficient
        mass = torch.ones_like(anchor)
        # substeps no longer than the training ones, for which the stability bounds hold (a sparser sequence,
        # such as every 5th frame, takes more of them)
        interval = float(interval)
        longest = self.hyper["frame_interval"] / self.hyper["substeps"]
        substeps = max(self.hyper["substeps"], math.ceil(interval / longest - 1e-6))
        dt = interval / substeps
        for _ in range(substeps):
            force = (external - anchor[:, None] * displacement).contiguous()
            positions, velocity = ops.spring_step((self.nodes + displacement).contiguous(), velocity.contiguous(),
                                                  self.edges, self.rest_offset, stiffness, damping, mass, force, dt)
            displacement = positions - self.nodes
        return DynamicsState(displacement, velocity)

    @torch.no_grad()
    def rollout(self, bone_transforms: torch.Tensor, intervals: torch.Tensor, *, drive: dict | None = None,
                progress: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll a pose sequence out from rest (no gradients).

        Args:
            bone_transforms: [T,J,4,4] consecutive frames.
            intervals: [T] seconds since the previous frame (see :func:`warpavatar.model.parts.frame_intervals`).
            drive: :meth:`drive` of the sequence, when the caller has it already.

        Returns:
            ``(displacement, velocity)``, [T,M,3] each; frame 0 is at rest.
        """
        if drive is None:
            drive = self.drive(bone_transforms, intervals)
        state = self.rest_state()
        displacements = [state.displacement]
        velocities = [state.velocity]
        seconds = intervals.tolist()  # one host copy, not a device sync per frame
        frames = range(1, bone_transforms.shape[0])
        if progress:
            import tqdm

            frames = tqdm.tqdm(frames, desc="dynamics", unit="frame")
        for frame in frames:
            state = self.step(state, drive, frame, seconds[frame])
            displacements.append(state.displacement)
            velocities.append(state.velocity)
        return torch.stack(displacements), torch.stack(velocities)

    # ------------------------------------------------------------------------------------------ tables
    @torch.no_grad()
    def set_training_rollout(self, bone_transforms: torch.Tensor, displacement: torch.Tensor) -> None:
        """Keep the training sequence's poses [T,J,4,4] and rolled-out displacements [T,M,3] for lookup."""
        self.frame_poses = bone_transforms.detach().float().clone()
        self.frame_displacement = displacement.detach().float().clone()

    @torch.no_grad()
    def prepare_sequence(self, bone_transforms: torch.Tensor, intervals: torch.Tensor, *,
                         progress: bool = False) -> None:
        """Roll out a new motion so that :meth:`node_displacement` answers its poses (replaces the last one)."""
        displacement, _ = self.rollout(bone_transforms, intervals, progress=progress)
        self._sequence = (bone_transforms.detach().float().clone(), displacement)

    def _match(self, poses: torch.Tensor, displacement: torch.Tensor, bone_transforms: torch.Tensor,
               tolerance: float) -> tuple[torch.Tensor, torch.Tensor]:
        if poses.shape[0] == 0:
            return torch.zeros_like(self.nodes), torch.zeros((), device=self.nodes.device)
        best, matched = match_pose(poses, bone_transforms, tolerance=tolerance)
        return displacement[best], matched

    def node_displacement(self, bone_transforms: torch.Tensor, *, tolerance: float = 1e-4) -> torch.Tensor:
        """Canonical displacement [M,3] of every node for this pose: the training rollout's when the pose is a
        training frame's, else the prepared sequence's when it is one of its frames, else zeros."""
        displacement, matched = self._match(self.frame_poses, self.frame_displacement, bone_transforms, tolerance)
        if self._sequence is not None:
            other, other_matched = self._match(*self._sequence, bone_transforms, tolerance)
            use_other = other_matched * (1.0 - matched)
            return displacement * matched + other * use_other
        return displacement * matched

    # ------------------------------------------------------------------------------------------ losses
    def damping(self, state: DynamicsState) -> torch.Tensor:
        """SMAD's damping term on the nodes' secondary velocities, in voxels per typical frame interval."""
        return ops.damping_loss((state.velocity / self.speed_unit).contiguous())

    def magnitude(self, state: DynamicsState) -> torch.Tensor:
        """Mean squared node displacement, in voxels."""
        return (state.displacement / self.hyper["voxel_size"]).square().sum(-1).mean()

    # ------------------------------------------------------------------------------------------- files
    def state_for_file(self) -> dict:
        state = super().state_for_file()
        state["kind"] = "dynamics"
        state["parents"] = self.parents.cpu()
        return state

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "SecondaryDynamics":
        weights = state["state_dict"]
        hyper = dict(state["hyper"])
        module = cls(weights["nodes"].to(device), weights["node_weights"].to(device), state["parents"],
                     voxel_size=hyper["voxel_size"],
                     frame_interval=hyper["frame_interval"], neighbors=hyper["neighbors"],
                     bind_count=hyper["bind_count"], hidden=hyper["hidden"], embedding=hyper["embedding"],
                     velocity_history=hyper["velocity_history"], pose_window=hyper["pose_window"],
                     message_passes=hyper["message_passes"], substeps=hyper["substeps"],
                     force_limit=hyper["force_limit"])
        # the saved graph, whatever order a k-NN search on another device would give its ties
        module.hyper = hyper
        for name in ("edges", "rest_offset", "edge_pair", "inverse_degree", "frame_poses", "frame_displacement"):
            setattr(module, name, weights[name].clone())
        module.stiffness_raw = torch.nn.Parameter(weights["stiffness_raw"].clone())
        module.load_state_dict(weights)
        module = module.to(device)
        module.restore_binding(state.get("binding"), device=device)
        return module

    def extra_repr(self) -> str:
        return (f"nodes={self.node_count}, edges={self.edges.shape[0]}, hidden={self.hyper['hidden']}, "
                f"voxel_size={self.hyper['voxel_size']:.4g}, trained_frames={self.frame_poses.shape[0]}")


@dataclass
class DynamicsOptions(GraphMotionOptions):
    dynamics_hidden: int = option(64, "width of the dynamics network's node features and messages")
    dynamics_window: int = option(4, "frames each step rolls forward with gradients, from a cached state "
                                  "(truncated backpropagation through time)")
    dynamics_refresh_every: int = option(100, "steps between full no-gradient rollouts of the training sequence "
                                         "that refresh the cached states")
    dynamics_substeps: int = option(2, "semi-implicit Euler steps per frame")
    dynamics_velocity_history: int = option(11, "past skinned velocities in each node's encoding (SMAD: 11)")
    dynamics_pose_window: int = option(4, "frames of bone rotations in the pose-window embedding")
    lr_dynamics: float = option(1e-3, "Adam learning rate of the dynamics network")
    lr_dynamics_springs: float = option(1e-2, "Adam learning rate of the dynamics' stiffness, anchor and damping "
                                        "(logits of their bounded ranges)")

    def __post_init__(self):
        for name in ("dynamics_hidden", "dynamics_window", "dynamics_refresh_every", "dynamics_substeps",
                     "dynamics_velocity_history", "dynamics_pose_window"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


class DynamicsExtension(Extension):
    """Fits :class:`SecondaryDynamics` from ``secondary_from`` on: each step rolls the last ``dynamics_window``
    frames forward with gradients from a cached state of the training sequence (truncated backpropagation
    through time), and every ``dynamics_refresh_every`` steps the whole sequence is rolled out again without
    gradients to refresh that cache (and the table of the training instants)."""

    name = "dynamics"
    title = "learned secondary dynamics (--dynamics)"
    summary = ("learn SMAD's secondary dynamics on the graph (the alternative to --secondary-motion): a "
               "message-passing network predicts forces from the body's motion and a mass-spring-damper step with "
               "learned stiffness and damping moves the nodes, so any motion can be rolled out (novel poses, "
               "exports); starts at --secondary-from")
    options_type = DynamicsOptions
    presets = GRAPH_PRESETS
    part: SecondaryDynamics | None = None

    def attach(self) -> None:
        self.drive: dict | None = None  # SecondaryDynamics.drive of the training sequence
        self.cache: tuple[torch.Tensor, torch.Tensor] | None = None  # states [T,M,3] (d, u), no grad
        self.refreshed = -1  # step of the last refresh
        self.step = 0
        self.state: DynamicsState | None = None  # this step's state, with gradients over the window

    def _build(self, part: SecondaryDynamics) -> None:
        self.part = self.fit.avatar.add_part(part)
        springs = [part.stiffness_raw, part.anchor_raw, part.damping_raw]
        network = [p for p in part.parameters() if all(p is not q for q in springs)]
        self.optimizer = Adam([{"params": network, "lr": self.options.lr_dynamics},
                               {"params": springs, "lr": self.options.lr_dynamics_springs}])
        self.drive = None  # computed with the cache (refresh) or, after a resume, on first use
        self.cache = None

    def begin_step(self, step) -> None:
        self.step = step.step
        if self.part is None and step.step >= self.options.secondary_from:
            fit, options = self.fit, self.options
            nodes, voxel = graph_nodes(fit, options)
            with torch.no_grad():
                node_weights = fit.skinning.field.weights(nodes, step.grid)
            part = SecondaryDynamics(
                nodes, node_weights, fit.frames.skeleton.parents, voxel_size=voxel,
                frame_interval=float(fit.frames.intervals.median()), hidden=options.dynamics_hidden,
                velocity_history=options.dynamics_velocity_history, pose_window=options.dynamics_pose_window,
                substeps=options.dynamics_substeps)
            part.bind(fit.avatar.gaussians.means)
            self._build(part)

    @torch.no_grad()
    def refresh(self, grid: torch.Tensor | None = None) -> None:
        """Re-read the nodes' skinning weights and roll the whole training sequence out (no gradients): the
        cached states the training windows start from, and the table novel views of training instants use."""
        part, frames = self.part, self.fit.frames
        field = self.fit.skinning.field
        part.set_node_weights(field.weights(part.nodes, field.grid_weights() if grid is None else grid))
        self.drive = part.drive(frames.bone_transforms, frames.intervals)
        displacement, velocity = part.rollout(frames.bone_transforms, frames.intervals, drive=self.drive)
        self.cache = (displacement, velocity)
        part.set_training_rollout(frames.bone_transforms, displacement)
        self.refreshed = self.step

    def frame_input(self, step) -> torch.Tensor | None:
        """The state of training frame ``step.index``, rolled with gradients over the last ``dynamics_window``
        frames from the cached state before them (which it then updates): its node displacement."""
        self.state = None
        if self.part is None:
            return None
        part, frames = self.part, self.fit.frames
        if self.cache is None or step.step - self.refreshed >= self.options.dynamics_refresh_every:
            self.refresh(step.grid)
        elif self.drive is None:  # resumed with a cache: the drive of the saved node weights
            self.drive = part.drive(frames.bone_transforms, frames.intervals)
        cached_displacement, cached_velocity = self.cache
        start = max(0, step.index - self.options.dynamics_window)
        # clones: the cache rows are overwritten below, and autograd may hold on to the start state
        state = DynamicsState(cached_displacement[start].clone(), cached_velocity[start].clone())
        for frame in range(start + 1, step.index + 1):
            state = part.step(state, self.drive, frame, frames.seconds[frame])
            cached_displacement[frame] = state.displacement.detach()
            cached_velocity[frame] = state.velocity.detach()
        self.state = state
        return state.displacement

    def losses(self, step) -> dict[str, LossTerm]:
        if self.state is None:
            return {}
        options, part, state = self.options, self.part, self.state
        return {"isometry": LossTerm(options.lambda_isometry, part.isometry(state.displacement)),
                "damping": LossTerm(options.lambda_damping, part.damping(state)),
                "displacement": LossTerm(options.lambda_displacement, part.magnitude(state))}

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [] if self.state is None else [self.optimizer]

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        if self.part is not None:
            self.part.bind(self.fit.avatar.gaussians.means)

    def finish(self) -> None:
        if self.part is not None:
            self.refresh()  # the saved table of the training instants comes from the final model

    def state_dict(self) -> dict:
        if self.part is None:
            return {}
        return {"part": self.part.state_for_file(), "optimizer": self.optimizer.state_dict(),
                "cache": None if self.cache is None else [tensor.cpu() for tensor in self.cache],
                "refreshed": self.refreshed}

    def load_state_dict(self, state: dict) -> None:
        if not state:
            return
        self._build(SecondaryDynamics.from_file_state(state["part"], device=self.fit.device))
        self.optimizer.load_state_dict(state["optimizer"])
        if state["cache"] is not None:
            self.cache = tuple(tensor.to(self.fit.device) for tensor in state["cache"])
        self.refreshed = int(state["refreshed"])
