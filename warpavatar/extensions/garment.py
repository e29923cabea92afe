"""A loose garment as simulated cloth: detected in the fit, fitted by differentiable simulation, rolled out by
every consumer.

The part (:class:`GarmentPart`). The garment's Gaussians (``gaussian_ids`` into the avatar's) are
voxel-downsampled into cloth *nodes* in canonical space; a :class:`~warpavatar.sim.ClothModel` joins them by
stretch and bend springs with learnable rest lengths, stiffness, damping, drag and mass scale. Some nodes are
*attached*: they follow their canonical rest position skinned by the body (a waistband on the hips); the others
are free particles under gravity, pushed out of the body's capsules (fitted once to the non-garment Gaussians,
:func:`~warpavatar.sim.fit_body_capsules`). After skinning (:meth:`GarmentPart.deform_posed`), each garment
Gaussian rides on its nearest node: centre ``x_node + R_node offset``, rotation ``q_node * q_canonical``, where
``offset`` is its canonical centre minus the node's rest position (plus any displacement other parts gave it
before skinning, such as ``--secondary-motion``'s per-frame one) and ``R_node`` the rotation of the node's
neighbourhood from rest (:func:`~warpavatar.sim.node_rotations`, warm-started by the node's skinning rotation):
appearance stays on the cloth, whatever the body does.

Where a frame's cloth state comes from, in this order:

1. an explicit input (a fit's window of simulated frames, with gradients);
2. the table of the training rollout when the pose is a training frame's (novel views of training instants
   see the cloth as the whole training motion, rolled out from a settled rest at frame 0, left it);
3. the sequence prepared by :meth:`GarmentPart.prepare_sequence` when the pose is one of its frames (a new
   motion: settled at its first pose, then simulated frame by frame);
4. otherwise the cloth settled at that pose (one pose on its own: it hangs at rest, never an unsimulated
   smear). This case reads the device once to know it is in it.

The fit (:class:`GarmentExtension`) detects garments at ``--garment-from`` (:mod:`.garment_detection`; while
none is found, again every ``--garment-retry-every`` steps up to ``--garment-until``: the field keeps training,
and on cesium_skirt the detection at one step found the skirt or nothing on small numerical differences), builds
the part, and from then on trains it by truncated backpropagation through time, in the manner of the
dynamics extension: a no-grad rollout of the whole training sequence (refreshed every
``--garment-refresh-every`` steps) caches every frame's state; a step simulates the ``--garment-window`` frames
before its training frame from the cached state, with gradients, so the image loss reaches the cloth's
parameters through those substeps. The cloth's rest shape is learned too (``--garment-rest-bound``): the cache
holds each frame's displacement from the skinned rest shape, so a window starts at ``skinned(P) + d`` and the
image loss of every step reaches the rest positions ``P`` (and, through the simulated frames, the rest lengths
they define); each refresh rolls the motion out again from the settled new rest shape. By default nothing is learned per
training frame: novel poses use the same physics and rest shape.

Fitted frame states (``--garment-frame-states on``). Every training frame ``t`` gets its own cloth state: node
displacements ``y_t`` from the skinned rest shape (attached nodes: none), started at the first refresh's rollout.
A step draws its frame at ``x_i = skinned_i(P) + y_i`` (the image loss moves ``y_i`` directly) and simulates the
``--garment-window`` frames before it from the fitted state at ``s = i - W`` (moving at ``(x_s - x_{s-1}) / dt``);
the squared distance of each simulated frame to its fitted state, over the node spacing squared, is the dynamics
residual (``--lambda-garment-dynamics``): the physics is fitted to predict the fitted motion one window ahead
(multiple shooting) and the states are held to what it can predict. Three more terms guide the states: their
stretch against the rest shape's edge lengths, a silhouette term (nodes drawn outside the mask, mask cells the
render leaves uncovered) and an optical-flow term (the nodes the render shows, carried by the video's flow to the
neighbouring frames, which must draw them there). The states are drawn only at their own instants (the training
frames and novel views of them, through the table); a new motion or pose is simulated from the physics alone.

The sheet (``--garment-surface sheet``; default ``nodes``, all of the above). Detection is the same; the garment is
then a triangle sheet of its surface pinned at its waistband, its Gaussians bound to the sheet's triangles, every
training frame's sheet fitted with the physics as a soft prior: :mod:`.garment_sheet_part` (its part and its fit,
which the hooks below hand over to when a sheet exists).

A training step's window is device work only (:meth:`GarmentExtension.step_input`), so on CUDA it is captured
with the rest of the step and replayed: the frame comes from the step's buffers as a device index, which
gathers the cached start displacement and velocity and the window's transforms, and scatters the simulated
frames' displacements back into the cache; the window always runs ``W`` frame steps (a frame before the first
is a step whose result is discarded by a device-side select, so frame ``i < W`` simulates frames ``1..i`` from
the cached frame 0), each the length of the training frames' interval. It reads the rest shape from the cloth's
parameters every time (the optimizers update them in place, so a replayed step sees the current shape). The
refresh runs between steps, outside the graph, and writes the cache in place. Training frames at irregular
intervals (an evenly spaced subset, ``--max-train-frames``) get windows of their own frames' lengths instead,
and those steps run eagerly, through the same device work.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.extensions.garment_detection import detect_garments, related_joints
from warpavatar.extensions.garment_sheet_part import SheetFit, cell_centres, project_points
from warpavatar.extensions.graph import voxel_downsample
from warpavatar.geometry import match_pose
from warpavatar.model.parts import AvatarPart
from warpavatar.optim import Adam, Optimizer
from warpavatar.sim import (Capsules, ClothGraph, ClothModel, ClothState, capsules_near, cloth_graph,
                            fit_body_capsules, nearest_nodes, node_rotations, pose_capsules, ride_on_nodes)
from warpavatar.sim.capsules import select

__all__ = ["GarmentPart", "GarmentOptions", "GarmentExtension", "body_detection_options", "training_flows"]


class GarmentPart(AvatarPart):
    """A simulated garment: its Gaussians ride on the nodes of a mass-spring cloth hung from the body.

    Args:
        gaussian_ids: int64 ``[G]`` the garment's Gaussians among the avatar's.
        nodes: canonical rest positions of the cloth nodes [world units], ``[M, 3]``.
        node_weights: skinning weights of the nodes ``[M, J+E]`` (what the attached nodes and the warm start of
            the node rotations are skinned with).
        attached: int64 ``[A]`` ids of the nodes held by the body.
        joint: the joint the garment hangs from (skeleton index; reported, and the attachment's reference).
        capsules: canonical body capsules, one per skeleton joint; ``capsule_ids`` int64 ``[C]``: the ones the
            garment can meet (posed by those joints' transforms).
        voxel_size: node spacing [world units].
        max_substep: longest simulation substep [s].
        up: the world's up direction (gravity is ``-9.81 up``).
        joint_count: joints J of the skeleton (the leading transforms that name a pose); default ``J+E``.
        graph: the cloth's edges (None: :func:`~warpavatar.sim.cloth_graph` of ``nodes``).
        settle_frames: at most this many frames of settling before a sequence or a lone pose.
        rest_bound: how far the learned rest shape may move a free node from ``nodes`` [world units]; 0: the
            rest shape stays ``nodes`` (see :class:`~warpavatar.sim.ClothModel`).
        strain_limit: the longest a stretch edge may get, as a multiple of its rest length (strain limiting
            after every substep, see :class:`~warpavatar.sim.ClothModel`); 0: none.

    The rest shape (``cloth.rest_positions()``) is what posing starts from: a pose's skinned cloth, the settled
    start of every rollout, and the frame states of the training rollout, cached as displacements from the
    skinned rest shape (:meth:`displacements`). ``nodes`` stay the frame the Gaussians are bound in: a Gaussian's
    offset from its node and the nodes' rotations are measured from them, so the Gaussians move with the rest
    shape.
    """

    name = "garment"

    def __init__(self, gaussian_ids: torch.Tensor, nodes: torch.Tensor, node_weights: torch.Tensor,
                 attached: torch.Tensor, *, joint: int, capsules: Capsules, capsule_ids: torch.Tensor,
                 voxel_size: float, max_substep: float = 1.0 / 240.0, up=(0.0, 0.0, 1.0),
                 joint_count: int | None = None, graph: ClothGraph | None = None, settle_frames: int = 300,
                 rest_bound: float = 0.0, strain_limit: float = 0.0):
        super().__init__()
        nodes = nodes.detach().float().contiguous()
        device = nodes.device
        if nodes.shape[0] < 2:
            raise ValueError(f"a garment needs at least 2 cloth nodes, got {nodes.shape[0]}")
        if graph is None:
            graph = cloth_graph(nodes, neighbours=min(8, nodes.shape[0] - 1))
        joint_count = int(node_weights.shape[1] if joint_count is None else joint_count)
        self.hyper = dict(joint=int(joint), joint_count=joint_count, voxel_size=float(voxel_size),
                          max_substep=float(max_substep), up=tuple(float(u) for u in up),
                          settle_frames=int(settle_frames), rest_bound=float(rest_bound),
                          strain_limit=float(strain_limit))
        self.register_buffer("gaussian_ids", torch.as_tensor(gaussian_ids, device=device).long().clone())
        self.register_buffer("nodes", nodes.clone())
        self.register_buffer("node_weights", node_weights.detach().float().to(device).clone())
        self.register_buffer("stretch", graph.stretch.to(device).long().clone())
        self.register_buffer("bend", graph.bend.to(device).long().clone())
        self.register_buffer("capsule_start", capsules.segment_start.detach().float().to(device).clone())
        self.register_buffer("capsule_end", capsules.segment_end.detach().float().to(device).clone())
        self.register_buffer("capsule_radius", capsules.radius.detach().float().to(device).clone())
        self.register_buffer("capsule_ids", torch.as_tensor(capsule_ids, device=device).long().clone())
        self.register_buffer("anchor", torch.zeros(0, dtype=torch.int64, device=device))
        self.cloth = ClothModel(nodes, graph, torch.as_tensor(attached, device=device).long(), max_substep=max_substep,
                                up=self.hyper["up"], rest_offset_bound=self.hyper["rest_bound"],
                                strain_limit=self.hyper["strain_limit"])
        # the table of the training rollout: poses [T,J,4,4], node positions [T,M,3], node rotations [T,M,4]
        self.register_buffer("frame_poses", torch.zeros(0, 1, 4, 4, device=device))
        self.register_buffer("frame_positions", torch.zeros(0, nodes.shape[0], 3, device=device))
        self.register_buffer("frame_quats", torch.zeros(0, nodes.shape[0], 4, device=device))
        #: the training frames' cloth states fitted to their images [T,M,3]: each frame's node displacements from
        #: the skinned rest shape (zero on attached nodes); empty when the fit learns none (``--garment-frame-states
        #: off``). Used for the training frames' own instants only, never for another pose.
        self.frame_states = torch.nn.Parameter(torch.zeros(0, nodes.shape[0], 3, device=device))
        free = torch.ones(nodes.shape[0], 1, device=device)
        free[torch.as_tensor(attached, device=device).long()] = 0.0
        self.register_buffer("free_mask", free, persistent=False)
        self._sequence: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self._lone: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # last settled lone pose

    @property
    def node_count(self) -> int:
        return self.nodes.shape[0]

    @property
    def attached(self) -> torch.Tensor:
        return self.cloth.attached

    # ------------------------------------------------------------------------------------------ binding
    @torch.no_grad()
    def bind(self, canonical_means: torch.Tensor) -> None:
        """Anchor each garment Gaussian on its nearest node: ``canonical_means`` [N,3] of all the avatar's."""
        self.anchor = nearest_nodes(canonical_means.detach()[self.gaussian_ids], self.nodes)

    @torch.no_grad()
    def renumber(self, source_index: torch.Tensor, canonical_means: torch.Tensor) -> None:
        """Follow density control: new Gaussian ``i`` comes from old ``source_index[i]`` (a clone or a split of a
        garment Gaussian is one too); then re-anchor on the new canonical means [N,3]."""
        old_count = int(source_index.max()) + 1 if source_index.numel() else 0
        old_count = max(old_count, int(self.gaussian_ids.max()) + 1 if self.gaussian_ids.numel() else 0)
        member = torch.zeros(old_count, dtype=torch.bool, device=source_index.device)
        member[self.gaussian_ids] = True
        self.gaussian_ids = torch.nonzero(member[source_index]).reshape(-1)
        self.bind(canonical_means)

    @torch.no_grad()
    def set_node_weights(self, node_weights: torch.Tensor) -> None:
        """Replace the nodes' skinning weights ``[M, J+E]`` (the field trained; joints grew): in place while the
        shape holds (a captured training step reads this tensor)."""
        self.node_weights = _keep_storage(self.node_weights, node_weights.detach().float())

    # ------------------------------------------------------------------------------------ the body's part
    def _bones(self, bones: torch.Tensor) -> torch.Tensor:
        return bones[: self.node_weights.shape[1]]

    def skinned_nodes(self, bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Node positions [M,3] and rotations [M,4] as skinning alone would pose the rest shape (``bones``
        [J+E,4,4]); the positions are differentiable with respect to the rest shape."""
        identity = self.nodes.new_zeros(self.node_count, 4)
        identity[:, 0].fill_(1.0)  # (a fill, not values from the host: a training step is captured on CUDA)
        return ops.lbs(self.cloth.rest_positions(), self.node_weights, self._bones(bones).contiguous(),
                       quats=identity)

    def skinned_rest(self, bones: torch.Tensor) -> torch.Tensor:
        """Node positions [M,3] of the rest shape skinned into a pose (``bones`` [J+E,4,4]), differentiable with
        respect to the rest shape (:meth:`skinned_nodes` without the rotations)."""
        return ops.lbs(self.cloth.rest_positions(), self.node_weights, self._bones(bones).contiguous())[0]

    def attachment_targets(self, bones: torch.Tensor) -> torch.Tensor:
        """Where the attached nodes are in a pose [A,3]: their rest positions skinned by the body (the rest
        shape never moves them)."""
        attached = self.attached
        points, _ = ops.lbs(self.nodes[attached].contiguous(), self.node_weights[attached].contiguous(),
                            self._bones(bones).contiguous())
        return points

    def posed_capsules(self, bones: torch.Tensor) -> Capsules:
        """The garment's candidate capsules in a pose (``bones``: the skeleton's transforms first)."""
        ids = self.capsule_ids
        canonical = select(Capsules(self.capsule_start, self.capsule_end, self.capsule_radius), ids)
        return pose_capsules(canonical, bones[ids])

    # ------------------------------------------------------------------------------------------ simulation
    @torch.no_grad()
    def settled(self, bones: torch.Tensor, frame_interval: float) -> ClothState:
        """The cloth at rest in one pose: skinned there, then settled (extra drag) under gravity."""
        positions, _ = self.skinned_nodes(bones)
        state = self.cloth.rest_state(positions)
        state, _ = self.cloth.settle(state, self.attachment_targets(bones), capsules=self.posed_capsules(bones),
                                     frame_interval=float(frame_interval), max_frames=self.hyper["settle_frames"])
        return state

    def step(self, state: ClothState, previous_bones: torch.Tensor, bones: torch.Tensor, seconds: float
             ) -> ClothState:
        """One frame of ``seconds`` from the pose ``previous_bones`` to ``bones`` (differentiable)."""
        return self.cloth.step(state, self.attachment_targets(bones), float(seconds),
                               capsules=self.posed_capsules(bones),
                               previous_capsules=self.posed_capsules(previous_bones))

    @torch.no_grad()
    def displacements(self, bones: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """Node positions ``[T,M,3]`` of the frames with skinning transforms ``bones`` [T,J+E,4,4] as displacements
        from the skinned rest shape, ``x_t - skinned_t(P)`` (what a training window starts from,
        :meth:`GarmentExtension.step_input`)."""
        return torch.stack([x - self.skinned_rest(b) for b, x in zip(bones, positions)])

    def state_positions(self, bones: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
        """Node positions [K,M,3] of fitted frame states ``states`` [K,M,3] in poses ``bones`` [K,J+E,4,4]: the
        skinned rest shape plus the states' displacements, attached nodes where the body holds them
        (differentiable with respect to the states and the rest shape)."""
        return torch.stack([self.skinned_rest(b) for b in bones]) + states * self.free_mask

    @torch.no_grad()
    def rollout(self, bones: torch.Tensor, seconds: list[float], *, progress: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Simulate a motion (no gradients): settled at its first pose, then frame by frame.

        Args:
            bones: [T,J+E,4,4] every skinning transform of each frame.
            seconds: [T] seconds from each frame to the one before (the first: the settling frame's length).

        Returns:
            ``(positions, velocities)`` of the nodes, ``[T, M, 3]`` each.
        """
        state = self.settled(bones[0], seconds[0])
        positions, velocities = [state.positions], [state.velocities]
        frames = range(1, bones.shape[0])
        if progress:
            import tqdm

            frames = tqdm.tqdm(frames, desc="garment", unit="frame")
        for frame in frames:
            state = self.step(state, bones[frame - 1], bones[frame], seconds[frame])
            positions.append(state.positions)
            velocities.append(state.velocities)
        return torch.stack(positions), torch.stack(velocities)

    def node_quats(self, positions: torch.Tensor, bones: torch.Tensor) -> torch.Tensor:
        """Rotation [M,4] of every node's neighbourhood from rest to ``positions`` [M,3], warm-started by skinning."""
        with torch.no_grad():
            _, initial = self.skinned_nodes(bones)
        return node_rotations(self.nodes, positions, self.cloth.edges, initial=initial, iterations=4)

    @torch.no_grad()
    def _table(self, bones: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """Node rotations [T,M,4] of every frame of a sequence (``bones`` [T,J+E,4,4], ``positions`` [T,M,3]):
        the frames' neighbourhoods solved as one graph of ``T`` disjoint copies, in one call."""
        frames, count = positions.shape[0], self.node_count
        if frames == 0:
            return positions.new_zeros(0, count, 4)
        initial = torch.cat([self.skinned_nodes(b)[1] for b in bones])
        edges = self.cloth.edges
        copies = (torch.arange(frames, device=edges.device) * count)[:, None, None]
        quats = node_rotations(self.nodes.repeat(frames, 1), positions.reshape(-1, 3),
                               (edges[None] + copies).reshape(-1, 2), initial=initial, iterations=4)
        return quats.reshape(frames, count, 4)

    @torch.no_grad()
    def set_training_rollout(self, poses: torch.Tensor, bones: torch.Tensor, positions: torch.Tensor) -> None:
        """Keep the training sequence's poses [T,J,4,4] (as given) and its rolled-out node positions [T,M,3]."""
        self.frame_poses = poses.detach().float().clone()
        self.frame_positions = positions.detach().float().clone()
        self.frame_quats = self._table(bones, positions)

    @torch.no_grad()
    def prepare_sequence(self, bones: torch.Tensor, intervals: torch.Tensor, *, progress: bool = False) -> None:
        """Roll a new motion out (settled at its first pose) so its frames get their simulated cloth."""
        positions, _ = self.rollout(bones, intervals.tolist(), progress=progress)
        self._sequence = (bones[:, :self.hyper["joint_count"]].detach().float().clone(), positions,
                          self._table(bones, positions))

    def _lookup(self, frame, bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pose = frame.bone_transforms
        tables = [(self.frame_poses, self.frame_positions, self.frame_quats)]
        if self._sequence is not None:
            tables.append(self._sequence)
        positions = torch.zeros_like(self.nodes)
        quats = torch.zeros(self.node_count, 4, device=self.nodes.device)
        found = torch.zeros((), device=self.nodes.device)
        for poses, table_positions, table_quats in tables:
            if poses.shape[0] == 0:
                continue
            best, matched = match_pose(poses, pose)
            use = matched * (1.0 - found)
            positions = positions + use * table_positions[best]
            quats = quats + use * table_quats[best]
            found = found + use
        if float(found) < 0.5:  # a lone pose: hang the cloth at rest there
            key = self._lone
            if key is None or key[0].shape != pose.shape or not torch.equal(key[0], pose):
                state = self.settled(bones, 1.0 / 30.0)
                self._lone = (pose.detach().clone(), state.positions, self.node_quats(state.positions, bones))
            return self._lone[1], self._lone[2]
        return positions, quats

    # ------------------------------------------------------------------------------------------ posing
    def deform_posed(self, posed, frame):
        """Replace the garment Gaussians' skinned centres and rotations by the cloth's (see the module docstring).
        A displacement other parts gave a garment Gaussian before skinning (``posed["canonical_offsets"]``, e.g.
        ``--secondary-motion``'s per-frame one) is kept as part of its offset from its node, turned with the node."""
        ids = self.gaussian_ids
        if ids.numel() == 0:
            return posed
        bones = posed["bone_transforms"]
        explicit = frame.input(self.name)
        if explicit is not None:
            positions = explicit
            quats = self.node_quats(positions, bones)
        else:
            positions, quats = self._lookup(frame, bones)
        if self.anchor.shape[0] != ids.shape[0]:
            self.bind(posed["canonical_means"])
        anchor = self.anchor
        offset = posed["canonical_means"].index_select(0, ids) - self.nodes.index_select(0, anchor)
        displaced = posed.get("canonical_offsets")
        if displaced is not None:  # what other parts added before skinning rides along, in the node's frame
            offset = offset + displaced.index_select(0, ids)
        means, rotations = ride_on_nodes(positions, quats, anchor, offset,
                                         posed["canonical_quats"].index_select(0, ids))
        posed = type(posed)(posed)
        posed["means"] = posed["means"].index_copy(0, ids, means.to(posed["means"].dtype))
        posed["quats"] = posed["quats"].index_copy(0, ids, rotations.to(posed["quats"].dtype))
        return posed

    # ------------------------------------------------------------------------------------------- files
    def state_for_file(self) -> dict:
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}, "hyper": dict(self.hyper)}

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "GarmentPart":
        weights = {k: v.to(device) for k, v in state["state_dict"].items()}
        hyper = state["hyper"]
        part = cls(weights["gaussian_ids"], weights["nodes"], weights["node_weights"], weights["cloth.attached"],
                   joint=hyper["joint"], capsules=Capsules(weights["capsule_start"], weights["capsule_end"],
                                                           weights["capsule_radius"]),
                   capsule_ids=weights["capsule_ids"], voxel_size=hyper["voxel_size"],
                   max_substep=hyper["max_substep"], up=hyper["up"], joint_count=hyper["joint_count"],
                   graph=ClothGraph(weights["stretch"], weights["bend"]), settle_frames=hyper["settle_frames"],
                   rest_bound=hyper.get("rest_bound", 0.0), strain_limit=hyper.get("strain_limit", 0.0))
        for name in ("anchor", "frame_poses", "frame_positions", "frame_quats"):
            setattr(part, name, weights[name])
        if "frame_states" in weights:
            part.frame_states = torch.nn.Parameter(weights["frame_states"].float())
        for name, value in part.state_dict().items():  # (files older than the learned rest shape lack its buffer)
            weights.setdefault(name, value)
        part.load_state_dict(weights)
        return part


FLOW_SIDE = 192
"""Longer side [px] of the stored optical flows (computed at up to 512 px, stored coarser: a fit keeps one pair of
fields per training frame on its device)."""


def training_flows(images, *, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Dense optical flow between consecutive frames (OpenCV's DIS, medium preset, on grey levels).

    Args:
        images: uint8 ``[T, H, W, 3]`` (T >= 2), the training frames in order.

    Returns:
        ``(forward, backward)``, float16 ``[T, h, w, 2]`` each on ``device`` (``h, w``: the frame scaled to a
        longer side of :data:`FLOW_SIDE` at most): ``forward[t]`` moves a pixel of frame ``t`` to frame ``t + 1``,
        ``backward[t]`` to frame ``t - 1``, as ``(dx, dy)`` in pixels of the full frame (``forward[T-1]`` and
        ``backward[0]`` are zero: no such frame).
    """
    import cv2
    import numpy as np

    count, height, width = images.shape[:3]
    work = min(1.0, 512.0 / max(height, width))
    keep = min(1.0, FLOW_SIDE / max(height, width))
    work_size = (max(1, round(width * work)), max(1, round(height * work)))
    keep_size = (max(1, round(width * keep)), max(1, round(height * keep)))
    grey = [cv2.resize(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY), work_size,
                       interpolation=cv2.INTER_AREA) for image in images]
    solver = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    forward = np.zeros((count, keep_size[1], keep_size[0], 2), np.float16)
    backward = np.zeros_like(forward)

    def stored(flow):
        return cv2.resize(flow, keep_size, interpolation=cv2.INTER_AREA) / work

    for t in range(count - 1):
        forward[t] = stored(solver.calc(grey[t], grey[t + 1], None))
        backward[t + 1] = stored(solver.calc(grey[t + 1], grey[t], None))
    return torch.from_numpy(forward).to(device), torch.from_numpy(backward).to(device)


def _sample_image(image: torch.Tensor, pixels: torch.Tensor, *, mode: str = "bilinear") -> torch.Tensor:
    """Values [M,C] of ``image`` [h,w,C] at points [M,2] given as :func:`_normalized` coordinates of the frame it
    covers (any resolution of it; outside: zeros)."""
    grid = pixels[None, None].to(image.dtype)
    values = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None], grid, mode=mode, padding_mode="zeros",
                                             align_corners=True)
    return values[0, :, 0].T


def _normalized(pixels: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Frame pixels [M,2] as grid_sample coordinates (-1 and 1 at the first and last pixel centres)."""
    # (two column scalings, not a tensor made from host values: no upload inside a captured step)
    return torch.stack([pixels[:, 0] * (2.0 / max(width - 1, 1)), pixels[:, 1] * (2.0 / max(height - 1, 1))],
                       dim=1) - 1.0


def _common_interval(seconds: list[float]) -> float | None:
    """The interval [s] of evenly timed frames (the largest, where they differ by less than 1e-5 of it), or None.
    The first frame's interval is no step of a window and is left out."""
    later = seconds[1:] or seconds
    longest = max(later)
    return longest if longest - min(later) <= 1e-5 * longest else None


def _keep_storage(old: torch.Tensor | None, new: torch.Tensor) -> torch.Tensor:
    """``new``'s values in ``old``'s storage when shape, dtype and device agree (what a captured CUDA graph
    reads stays where it was), else a copy of ``new``."""
    if old is not None and old.shape == new.shape and old.dtype == new.dtype and old.device == new.device:
        return old.copy_(new)
    return new.clone()


def _split_groups(saved: dict) -> tuple[dict, dict]:
    """The state of an optimizer with two parameter groups as the states of two optimizers of one group each
    (checkpoints that kept the rest offsets as a group of the cloth's optimizer)."""
    def one(group: dict) -> dict:
        ids = group["params"]
        return {"state": {new: saved["state"][old] for new, old in enumerate(ids) if old in saved["state"]},
                "param_groups": [{**group, "params": list(range(len(ids)))}]}

    return one(saved["param_groups"][0]), one(saved["param_groups"][1])


def body_detection_options(skeleton, field) -> dict:
    """The arguments of :func:`detect_garments` that come from the body: the skeleton's bones and up axis (rules
    1, 5 and 6 of :mod:`.garment_detection`) and the skinning field's largest voxel side [world units], the
    finest detail its weights can hold."""
    cells = torch.tensor(field.grid_shape[::-1], dtype=torch.float32) - 1.0  # (x, y, z) intervals
    voxel = float(((field.bbox_max - field.bbox_min).float().cpu() / cells.clamp_min(1.0)).max())
    return dict(heads=torch.as_tensor(skeleton.heads, dtype=torch.float32),
                tails=torch.as_tensor(skeleton.tails, dtype=torch.float32),
                up=torch.as_tensor(skeleton.up, dtype=torch.float32), resolution=voxel)


@dataclass
class GarmentOptions:
    """Options of the garment extension."""

    garment: str = option("off", "detect loose garments and simulate them as cloth ('auto'), or not ('off')",
                          product=True, choices=("auto", "off"))
    garment_attach: str = option("", "name of the joint the garment hangs from, overriding the detected one "
                                 "(default: detected)", product=True)
    garment_from: int = option(3000, "step at which garments are detected and their cloth starts to train (after "
                               "the skinning field has trained for a while)")
    garment_retry_every: int = option(500, "steps between further detection attempts while none has found a "
                                      "garment (the skinning field keeps training, and a blend that was just "
                                      "under the thresholds may pass later); 0: one attempt")
    garment_until: int = option(5000, "last step of a detection attempt (a garment found later has too few steps "
                                "left to fit its cloth)")
    garment_threshold: float = option(0.005, "garment seeds: Gaussians whose skinning weights blend limbs that "
                                      "move apart (weight x weight x distance apart over the training motion) by "
                                      "at least this fraction of the body's longest side (0-1)")
    garment_min_fraction: float = option(0.03, "smallest garment, as a fraction of all Gaussians (0-1)")
    garment_residual: float = option(0.02, "a found garment counts only when its pixels' mean absolute image "
                                     "error on the training frames (0-1 intensity, each pixel weighted by the "
                                     "garment's share of it) exceeds the rest of the avatar's by at least this: "
                                     "cloth that skinning cannot follow leaves its texture misplaced, while a "
                                     "body part the field merely blends is fitted as well as the rest (0: no "
                                     "check; a named --garment-attach skips it too)")
    garment_voxel: float = option(0.03, "cloth node spacing as a fraction of the canonical box's longest side")
    garment_window: int = option(1, "frames simulated with gradients before each training frame (truncated "
                                 "backpropagation through time; each costs the frame's substeps forward and "
                                 "backward; every step runs this many, those before the first frame discarded, so "
                                 "that one CUDA graph serves every frame of evenly timed training frames)")
    garment_refresh_every: int = option(100, "steps between no-grad rollouts of the whole training motion "
                                        "(the cached states the windows start from)")
    garment_substep: float = option(1.0 / 240.0, "longest simulation substep [s]; the cloth's stiffness bound "
                                    "scales with its inverse square")
    garment_strain_limit: float = option(0.0, "strain limiting: after every substep, stretch edges longer than this "
                                         "multiple of their rest length are pulled back to it (Jacobi passes; "
                                         "cloth barely stretches, springs of an explicit step do); 0: off, else "
                                         "> 1 (e.g. 1.1)")
    lr_garment: float = option(0.02, "Adam learning rate of the cloth's parameters (logits of rest lengths, "
                               "stiffness, damping, drag, mass scale)")
    garment_rest_bound: float = option(0.3, "how far the cloth's learned rest shape may move a free node from where "
                                       "detection put it, as a fraction of the garment's longest canonical side "
                                       "(0: the rest shape stays as detected)")
    lr_garment_rest: float = option(0.005, "Adam learning rate of the rest shape's offsets (unitless: a step moves "
                                    "a node by at most about this times the bound)")
    lambda_garment_rest_smooth: float = option(0.01, "weight of the rest shape's roughness: mean over nodes of "
                                               "|offset - mean of its neighbours' offsets|^2 / node spacing^2 "
                                               "(dimensionless; a smooth flare of a ring scores too, so keep it "
                                               "small: it mostly decides where the images say little)")
    garment_frame_states: str = option("off", "fit every training frame's cloth state to its images ('on'): each "
                                       "frame's node positions are learned, held to the simulation by "
                                       "--lambda-garment-dynamics and guided by the silhouette and optical-flow "
                                       "terms, and drawn for that frame's instant only (its novel views); the "
                                       "physics learns from them, and novel poses use the physics alone. 'off' "
                                       "(default until it measurably helps: README, 'Not done yet'): every frame "
                                       "is the simulation's",
                                       choices=("on", "off"))
    lr_garment_states: float = option(0.1, "Adam learning rate of the training frames' cloth states, as a fraction "
                                      "of the node spacing per step")
    lambda_garment_dynamics: float = option(0.01, "weight of the dynamics residual: mean over free nodes of "
                                            "|simulated - fitted|^2 / node spacing^2, the simulated state stepped "
                                            "through the --garment-window frames from the fitted state (and its "
                                            "velocity, from the two fitted frames before) to the step's frame")
    lambda_garment_stretch: float = option(0.2, "weight of the fitted states' stretch: mean over stretch edges of "
                                           "(length / rest-shape length - 1)^2 in the step's frame (cloth does "
                                           "not stretch much: what one camera cannot see follows what it sees)")
    lambda_garment_silhouette: float = option(1.0, "weight of the fitted states' silhouette terms (on a grid of "
                                              "about 96 cells a side): free nodes drawn outside the frame's mask are "
                                              "pulled to its nearest cell, and mask cells the render leaves "
                                              "uncovered pull the nearest drawn node within 15 % of the image; "
                                              "squared distances beyond one cell over the image's longer side "
                                              "squared, each term a mean. Image gradients only reach cloth that "
                                              "already covers a pixel: these reach a swing the cloth has not "
                                              "followed yet (0: off; no effect without masks)")
    lambda_garment_flow: float = option(10.0, "weight of the fitted states' optical-flow term: the free nodes the "
                                        "step's render shows (in the mask, at the rendered depth within two node "
                                        "spacings) are carried by the video's optical flow (OpenCV's DIS, between "
                                        "consecutive training frames) to where the neighbouring frames must draw "
                                        "them; mean squared miss over the image's longer side squared. It makes "
                                        "the nodes follow the cloth's material, so its texture stays put on it "
                                        "(0: off)")
    lambda_garment_rest_collapse: float = option(1.0, "weight of the penalty on rest-shape edges shorter than "
                                                 "half their detected length: mean of max(0, 0.5 - ratio)^2 "
                                                 "(dimensionless)")
    garment_surface: str = option("nodes", "how the garment is simulated: 'nodes' (a mass-spring graph of "
                                  "voxel-downsampled nodes the Gaussians ride on) or 'sheet' (a triangle sheet of "
                                  "the garment's surface, pinned at its waistband, the Gaussians bound to its "
                                  "triangles; every training frame's sheet is fitted, the physics a soft prior: "
                                  "docs/extensions/garment_sheet.md)", choices=("nodes", "sheet"))
    garment_sheet_rings: int = option(16, "sheet: rings of vertices from the waistband to the hem (>= 2)")
    garment_sheet_segments: int = option(32, "sheet: vertices a ring around the axis (>= 3)")
    garment_sheet_substep: float = option(1.0 / 600.0, "sheet: longest simulation substep [s]; the stiffness "
                                          "bound scales with its inverse square")
    garment_settle_substeps: int = option(600, "sheet: substeps of settling (the ring held at the first pose, the "
                                          "velocities damped hard) before a new motion or a lone pose (>= 1)")
    garment_sheet_frames: int = option(4, "sheet: frames whose physics residual each step trains (cycling over "
                                       "the sequence, >= 1)")
    lambda_garment_sheet_dynamics: float = option(0.1, "sheet: weight of the physics residual: mean over free "
                                                  "vertices of |x_t - step(x_{t-1}, (x_{t-1} - x_{t-2}) / dt)|^2 "
                                                  "over the mean edge length squared, over the step's frames")
    lr_garment_sheet_states: float = option(0.02, "sheet: Adam learning rate of the training frames' sheet states, "
                                            "as a fraction of the mean edge length per step")
    garment_sheet_track_iterations: int = option(300, "sheet tracking: Adam iterations of the batched fit of "
                                                 "every training frame's sheet state to its mask, without rendering "
                                                 "(free vertices and triangle centres inside the mask, the garment's "
                                                 "cells covered by the projected sheet, the physics residual, edge "
                                                 "lengths near rest), run right after the sheet's rollout and every "
                                                 "--garment-sheet-track-every steps after (>= 0; 0: off; needs masks)")
    garment_sheet_track_every: int = option(2000, "sheet tracking: steps between later runs, each at the first "
                                            "refresh (--garment-refresh-every) that many steps after the last "
                                            "(>= 0; 0: only when the sheet is built)")
    lr_garment_sheet_track: float = option(0.1, "sheet tracking: Adam learning rate of the states, as a fraction of "
                                           "the mean edge length per iteration, decaying to a tenth of it along a "
                                           "cosine over a run")
    lambda_garment_sheet_track_dynamics: float = option(0.1, "sheet tracking: weight of the physics residual "
                                                        "(edge lengths squared, as --lambda-garment-sheet-dynamics "
                                                        "measures it) against the silhouette terms (weight 1, "
                                                        "their misses in projected edge lengths, squared)")
    lambda_garment_sheet_track_edges: float = option(1.0, "sheet tracking: weight of the edges' strain, mean of "
                                                     "(length / rest length - 1)^2 (dimensionless)")
    garment_sheet_track_frames: int = option(16, "sheet tracking: frames whose physics residual an iteration fits "
                                             "(cycling over the sequence; >= 0; 0: every frame)")
    garment_sheet_track_region: str = option("body", "sheet tracking: the garment's cells each frame's sheet must "
                                             "cover: 'body' (the mask where a render of the avatar without the "
                                             "garment has alpha under one half) or 'share' (the mask where the "
                                             "garment Gaussians, on the sheet as it is, make over half of the "
                                             "render's alpha)", choices=("body", "share"))


class GarmentExtension(Extension):
    """Detect a loose garment, simulate it as cloth and fit its physics through the simulation (see the module
    docstring)."""

    name = "garment"
    switch_modes = ("auto", "off")
    default_mode = "off"  # until GPU fits confirm the detection on subjects with and without loose cloth
    title = "simulated garments (--garment)"
    summary = ("detect loose garments (Gaussians whose skinning weights split between independent limbs) at "
               "--garment-from and simulate each as a mass-spring cloth hung from the body; its physics is fitted "
               "through the simulation and every consumer rolls the cloth out ('auto'), or never ('off')")
    options_type = GarmentOptions
    presets = {"quick": {"garment_from": 1200}}

    @classmethod
    def check(cls, options, config) -> None:
        for name, least in (("garment_from", 0), ("garment_retry_every", 0), ("garment_until", 0),
                            ("garment_window", 1), ("garment_refresh_every", 1), ("garment_sheet_rings", 2),
                            ("garment_sheet_segments", 3), ("garment_settle_substeps", 1), ("garment_sheet_frames", 1),
                            ("garment_sheet_track_iterations", 0), ("garment_sheet_track_every", 0),
                            ("garment_sheet_track_frames", 0)):
            if getattr(options, name) < least:
                raise ValueError(f"--{name.replace('_', '-')} must be >= {least}, got {getattr(options, name)}")
        for name in ("garment_threshold", "garment_min_fraction"):
            if not 0.0 < getattr(options, name) < 1.0:
                raise ValueError(f"--{name.replace('_', '-')} must be in (0, 1), got {getattr(options, name)}")
        if options.garment_surface not in ("nodes", "sheet"):
            raise ValueError(f"--garment-surface must be 'nodes' or 'sheet', got {options.garment_surface!r}")
        for name in ("garment_sheet_substep", "lr_garment_sheet_states", "lr_garment_sheet_track"):
            if not 0.0 < getattr(options, name) < math.inf:
                raise ValueError(f"--{name.replace('_', '-')} must be > 0, got {getattr(options, name)}")
        if options.garment_sheet_track_region not in ("body", "share"):
            raise ValueError("--garment-sheet-track-region must be 'body' or 'share', got "
                             f"{options.garment_sheet_track_region!r}")
        if options.garment_frame_states not in ("on", "off"):
            raise ValueError(f"--garment-frame-states must be 'on' or 'off', got {options.garment_frame_states!r}")
        if not (options.garment_strain_limit == 0.0 or 1.0 < options.garment_strain_limit < math.inf):
            raise ValueError(f"--garment-strain-limit must be 0 (off) or > 1, got {options.garment_strain_limit}")
        if not 0.0 <= options.garment_residual < 1.0:
            raise ValueError(f"--garment-residual must be in [0, 1), got {options.garment_residual}")
        for name in ("garment_voxel", "garment_substep", "lr_garment", "lr_garment_rest", "lr_garment_states"):
            if not getattr(options, name) > 0.0:
                raise ValueError(f"--{name.replace('_', '-')} must be > 0, got {getattr(options, name)}")
        for name in ("garment_rest_bound", "lambda_garment_rest_smooth", "lambda_garment_rest_collapse",
                     "lambda_garment_dynamics", "lambda_garment_stretch", "lambda_garment_silhouette",
                     "lambda_garment_flow", "lambda_garment_sheet_dynamics", "lambda_garment_sheet_track_dynamics",
                     "lambda_garment_sheet_track_edges"):
            if not 0.0 <= getattr(options, name) < math.inf:
                raise ValueError(f"--{name.replace('_', '-')} must be a number >= 0, got {getattr(options, name)}")

    def attach(self) -> None:
        names = self.fit.frames.skeleton.names
        if self.options.garment_attach and self.options.garment_attach not in names:
            raise ValueError(f"--garment-attach {self.options.garment_attach!r}: no such joint; the skeleton's "
                             f"joints are {', '.join(names)}")
        self.part: GarmentPart | None = None
        #: the sheet's fit (``--garment-surface sheet``, a garment found), or None
        self.sheet: SheetFit | None = None
        self.decided = False  # detection is over (a garment found, or no attempt left)
        self.next_attempt = self.options.garment_from  # step of the next detection attempt
        self.report: dict = {}
        #: every training frame's displacement from the skinned rest shape and velocity, [T,M,3] each
        self.cache: tuple[torch.Tensor, torch.Tensor] | None = None
        self.bones: torch.Tensor | None = None  # the training frames' skinning transforms [T,J+E,4,4]
        self.refreshed = -1
        self.step = 0
        self.optimizer: Adam | None = None  # the cloth's physics
        self.rest_optimizer: Adam | None = None  # its rest shape's offsets, while learned
        self.states_optimizer: Adam | None = None  # the training frames' fitted cloth states
        #: the training frames' optical flows to the next and to the previous frame [T,h,w,2] each (float16, in
        #: pixels of the frames), made with the states (:func:`training_flows`)
        self.flows: tuple[torch.Tensor, torch.Tensor] | None = None
        #: this step's dynamics residual and fitted positions (the states' losses), set by :meth:`step_input`
        self.residual: torch.Tensor | None = None
        self.fitted: torch.Tensor | None = None
        self.start_seconds = 1.0  # [s] from the frame before a window's start to its start (the start velocity)
        self.training = False  # this step simulates a window (a garment exists)
        window = self.options.garment_window
        #: window slot offsets -W..0 from the training frame (the start state's frame, then each simulated one)
        self.window_offsets = torch.arange(-window, 1, device=self.fit.device)
        #: the training frames' common interval [s] (the largest, when they differ by < 1e-5 of it), or None
        self.uniform_seconds = _common_interval(self.fit.frames.seconds)
        self.window_seconds: tuple[float, ...] = ()  # the lengths [s] of this step's window frames
        #: the training frames' intrinsics [T,3,3] and world-to-camera transforms [T,4,4], made with the states (their
        #: silhouette and flow terms read the step's by its device index)
        self.intrinsics: torch.Tensor | None = None
        self.world_to_cameras: torch.Tensor | None = None
        #: 1.0 when the step's frame is the first (no window, no gradient to the physics: its Adam skips its update)
        self.skip_update = torch.zeros((), device=self.fit.device)

    # ------------------------------------------------------------------------------------------ detection
    def _skeleton_weights(self, weights: torch.Tensor) -> torch.Tensor:
        groups = self.fit.avatar.skinning_groups()
        return weights if groups is None else weights @ groups

    @torch.no_grad()
    def detect(self, grid: torch.Tensor) -> None:
        """Find the garment and build its part (or decide there is none)."""
        fit, options = self.fit, self.options
        skeleton = fit.frames.skeleton
        means = fit.avatar.gaussians.means.detach()
        weights = self._skeleton_weights(fit.skinning.field.weights(means, grid))
        regions = detect_garments(means, weights, skeleton.parents, fit.frames.bone_transforms,
                                  threshold=options.garment_threshold,
                                  min_fraction=options.garment_min_fraction,
                                  # a named attachment overrides the rules that cloth hangs below the found
                                  # one and lies between the bones it blends, with a weight of each (the user
                                  # says there is a garment)
                                  **(dict(min_weight=0.0) if options.garment_attach else
                                     body_detection_options(skeleton, fit.skinning.field)))
        # rule 8 (the images): a region the avatar already draws as well as the rest of itself is body
        checked = not options.garment_attach and options.garment_residual > 0
        excess = [self.residual_excess(region.gaussian_ids, grid) if checked else math.inf for region in regions]
        rejected = [{"gaussians": int(region.gaussian_ids.numel()), "residual_excess": round(value, 4)}
                    for region, value in zip(regions, excess) if value < options.garment_residual]
        excess, regions = ([value for value in excess if value >= options.garment_residual],
                           [region for region, value in zip(regions, excess) if value >= options.garment_residual])
        retry = options.garment_retry_every
        self.next_attempt = self.step + retry if not regions and retry > 0 else -1
        self.decided = not 0 <= self.next_attempt <= options.garment_until
        up = torch.as_tensor(skeleton.up, dtype=torch.float32, device=means.device)
        height = means @ up
        low, high = float(height.min()), float(height.max())
        self.report = {"garments": len(regions), "gaussians": int(means.shape[0])}
        if not regions:
            fit.log({"step": self.step, "garment": "none", **({"rejected": rejected} if rejected else {}),
                     **({} if self.decided else {"next_attempt": self.next_attempt})})
            return
        region = regions[0]
        joint = region.joint
        if options.garment_attach:
            joint = skeleton.names.index(options.garment_attach)
        ids = region.gaussian_ids
        garment_height = height[ids]
        span = max(high - low, 1e-9)
        if checked:
            self.report["residual_excess"] = round(excess[0], 4)
        self.report.update(garment_gaussians=int(ids.numel()), joint=skeleton.names[joint],
                           split=[skeleton.names[j] for j in region.split_joints],
                           height_range=[round((float(garment_height.min()) - low) / span, 3),
                                         round((float(garment_height.max()) - low) / span, 3)])
        part = self._build(means, weights, grid, ids, joint)
        self.report.update(nodes=part.node_count, attached=int(part.attached.numel()),
                           capsules=int(part.capsule_ids.numel()))
        fit.log({"step": self.step, "garment": dict(self.report)})

    @torch.no_grad()
    def residual_excess(self, ids: torch.Tensor, grid: torch.Tensor, *, frames: int = 25) -> float:
        """How much worse the avatar draws the Gaussians ``ids`` [G] than the rest of itself: the mean absolute
        image error [0-1 intensity] inside the training frames' masks, each pixel weighted by the region's share
        of its opacity (the region rendered in white, the rest in black), minus the same mean weighted by the
        rest's share; over up to ``frames`` evenly spaced training frames (given poses, this grid)."""
        fit = self.fit
        training = fit.frames
        count = fit.avatar.gaussians.count
        white = torch.zeros(count, 3, device=fit.device)
        white[ids.to(fit.device)] = 1.0
        sums = torch.zeros(4, device=fit.device, dtype=torch.float64)
        total = len(training.cameras)
        for index in range(0, total, max(1, -(-total // frames))):
            camera = training.cameras[index]
            posed = fit.avatar.pose(training.bone_transforms[index], frame_index=index, grid=grid)
            image, alpha, _ = fit.avatar.rasterize(posed, camera, background=training.background)
            share = ops.rasterize_gaussians(
                posed["means"][:count], posed["quats"][:count], posed["scales"][:count],
                posed["opacities"][:count], white, torch.as_tensor(camera.K, dtype=torch.float32, device=fit.device),
                torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=fit.device),
                int(camera.width), int(camera.height))[0][..., 0]
            target, mask = training.target_of(training.images[index], None if training.masks is None
                                              else training.masks[index])
            error = (image - target).abs().mean(-1) * (1.0 if mask is None else mask)
            rest = (alpha - share).clamp_min(0.0)
            sums += torch.stack([(error * share).sum(), share.sum(), (error * rest).sum(), rest.sum()]).double()
        region_error, region_weight, rest_error, rest_weight = sums.tolist()
        return region_error / max(region_weight, 1e-9) - rest_error / max(rest_weight, 1e-9)

    def _build(self, means, weights, grid, ids: torch.Tensor, joint: int) -> GarmentPart:
        fit, options = self.fit, self.options
        if options.garment_surface == "sheet":
            self.sheet = SheetFit.build(self, means, weights, grid, ids, joint)
            self.part = self.sheet.part
            return self.part
        skeleton = fit.frames.skeleton
        field = fit.skinning.field
        voxel = options.garment_voxel * float((field.bbox_max - field.bbox_min).max())
        nodes = voxel_downsample(means[ids], voxel)
        node_weights = field.weights(nodes, grid)
        skeleton_weights = self._skeleton_weights(node_weights)
        garment = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        garment[ids] = True
        attached = self._attached(means, weights, garment, nodes, skeleton_weights, skeleton.parents, joint, voxel,
                                  up=torch.as_tensor(skeleton.up, dtype=torch.float32, device=means.device))
        device = means.device
        heads = torch.as_tensor(skeleton.heads, dtype=torch.float32, device=device)
        tails = torch.as_tensor(skeleton.tails, dtype=torch.float32, device=device)
        capsules = fit_body_capsules(heads, tails, means, weights, exclude=garment)
        radius = capsules.radius
        if bool((radius > 0).any()):  # a bone the garment hides entirely (thighs under a skirt) gets a typical radius
            radius = torch.where(radius > 0, radius, radius[radius > 0].median())
        capsules = Capsules(capsules.segment_start, capsules.segment_end, radius)
        sides = nodes.max(0).values - nodes.min(0).values
        capsule_ids = capsules_near(capsules, nodes, margin=0.5 * float(sides.norm()))
        part = GarmentPart(ids, nodes, node_weights, attached, joint=joint, capsules=capsules,
                           capsule_ids=capsule_ids, voxel_size=voxel, max_substep=options.garment_substep,
                           up=tuple(float(u) for u in skeleton.up), joint_count=len(skeleton.names),
                           rest_bound=options.garment_rest_bound * float(sides.max()),
                           strain_limit=options.garment_strain_limit)
        part.bind(means)
        self._use(part)
        return part

    @staticmethod
    def _attached(means, weights, garment, nodes, node_weights, parents, joint: int, voxel: float, *,
                  up: torch.Tensor | None = None) -> torch.Tensor:
        """The nodes the body holds: those within 1.5 node spacings of the body Gaussians that move with the
        attachment joint's side of the skeleton. That side is the joint, its ancestors, and the branches below
        it that carry less than a quarter of the garment's skinning weight (a skirt is held by the hips and the
        torso above them, not by the legs it hangs between). A node touching that body hangs from it; the band
        is 1.5 spacings wide so that it is a closed ring of nodes rather than isolated points. With ``up``, only
        nodes within 3 spacings of the garment's top are held: cloth hangs from its upper edge (a skirt from its
        waistband), and the hips it covers below that (body Gaussians under the skirt) hold nothing."""
        related = related_joints(parents).to(means.device)
        joint_count = weights.shape[1]
        chains = [[j] for j in range(joint_count)]
        for j in range(joint_count):  # the child of `joint` whose branch holds j (or -1)
            current = j
            while current >= 0 and int(parents[current]) != joint and current != joint:
                current = int(parents[current])
            chains[j] = current if current >= 0 and current != joint else -1
        mass = node_weights.sum(dim=0)
        branch_mass = torch.zeros(joint_count, device=means.device)
        for j, child in enumerate(chains):
            if child >= 0:
                branch_mass[child] += mass[j]
        holds = torch.zeros(joint_count, dtype=torch.bool, device=means.device)
        for j in range(joint_count):
            if not bool(related[joint, j]):
                continue
            child = chains[j]
            holds[j] = child < 0 or bool(branch_mass[child] < 0.25 * mass.sum())
        dominant = weights.argmax(dim=1)
        body = means[~garment & holds[dominant]]
        if body.shape[0] == 0:
            body = means[~garment]
        if body.shape[0] == 0:
            distance = torch.zeros(nodes.shape[0], device=nodes.device)  # nothing else: the nearest half below
        else:
            distance = torch.cat([torch.cdist(chunk, body).min(dim=1).values for chunk in torch.split(nodes, 4096)])
        if up is not None:
            height = nodes @ (up / up.norm().clamp_min(1e-12))
            distance = torch.where(height >= height.max() - 3.0 * voxel, distance, torch.full_like(distance, math.inf))
        attached = torch.nonzero(distance <= distance.min() + 1.5 * voxel).reshape(-1)
        if attached.numel() > nodes.shape[0] // 2:  # keep the cloth mostly free: hold the nearest half at most
            attached = distance.argsort()[: max(1, nodes.shape[0] // 2)].sort().values
        return attached

    def _use(self, part: GarmentPart) -> None:
        self.part = self.fit.avatar.add_part(part)
        # its step takes a device flag that skips the update (``found_inf``, the flag a gradient scaler sets),
        # which a step at the first frame raises without a host branch
        cloth = part.cloth
        physics = [p for name, p in cloth.named_parameters() if name != "rest_offset_logit"]
        self.optimizer = Adam(physics, lr=self.options.lr_garment)
        self.optimizer.found_inf = self.skip_update
        # the rest shape's offsets have an optimizer of their own, which the first frame does not skip: its window
        # starts at the skinned rest shape, so the image loss reaches them there too
        self.rest_optimizer = (None if cloth.rest_offset_logit is None else
                               Adam([cloth.rest_offset_logit], lr=self.options.lr_garment_rest))
        self.states_optimizer = None  # made once the states exist (the first refresh)
        self.cache = None
        self.bones = None

    @property
    def fits_states(self) -> bool:
        """The training frames' cloth states are fitted (``--garment-frame-states on``, a garment exists)."""
        return self.part is not None and self.options.garment_frame_states == "on"

    def _start_states(self, displacements: torch.Tensor) -> None:
        """Start the fitted states at the simulated rollout's displacements [T,M,3] (once, at the first refresh),
        with an Adam of their own."""
        part = self.part
        part.frame_states = torch.nn.Parameter(displacements.detach().clone() * part.free_mask)
        lr = self.options.lr_garment_states * part.hyper["voxel_size"]
        self.states_optimizer = Adam([part.frame_states], lr=lr)
        cameras = self.fit.frames.cameras
        self.intrinsics = torch.stack([camera.K for camera in cameras])
        self.world_to_cameras = torch.stack([camera.world_to_camera for camera in cameras])
        if self.options.lambda_garment_flow > 0 and self.flows is None and self.fit.frames.count >= 2:
            frames = self.fit.frames
            self.flows = training_flows(frames.video.images[frames.indices], device=self.fit.device)

    # ------------------------------------------------------------------------------------------ training
    def begin_step(self, step) -> None:
        self.step = step.step
        if not self.decided and step.step >= self.next_attempt:
            self.detect(step.grid)

    def after_backward(self, step) -> None:
        if self.sheet is not None:
            self.sheet.after_backward(step)

    def after_step(self, step) -> None:
        if self.sheet is not None:
            self.sheet.after_step(step)

    def _training_bones(self) -> torch.Tensor:
        frames = self.fit.frames
        return torch.stack([self.fit.avatar.pose_bones(b) for b in frames.bone_transforms])

    @torch.no_grad()
    def refresh(self) -> None:
        """Re-read the nodes' skinning weights and roll the whole training motion out (no gradients): the cached
        states the windows start from and the table novel views of training instants use. The cache and the
        transforms keep their storage while their shapes hold (a captured step reads and writes them)."""
        part, frames = self.part, self.fit.frames
        field = self.fit.skinning.field
        # (a grid of its own: the step's grid is evaluated by the step's work, inside a captured graph)
        part.set_node_weights(field.weights(part.nodes, field.grid_weights()))
        # the fused Adam and a replayed CUDA graph change the cloth's parameters (the rest offsets among them)
        # without bumping their version counters, which the fused rollout frame keys its coefficients on: say
        # they changed
        torch.autograd.graph.increment_version(list(part.cloth.parameters()))
        bones = self._training_bones()
        self.bones = _keep_storage(self.bones, bones)
        if not (self.fits_states and part.frame_states.shape[0] == bones.shape[0] and self.cache is not None):
            positions, velocities = part.rollout(bones, frames.seconds)
            cache = self.cache or (None, None)
            self.cache = (_keep_storage(cache[0], part.displacements(bones, positions)),
                          _keep_storage(cache[1], velocities))
            if self.fits_states and part.frame_states.shape[0] != bones.shape[0]:
                self._start_states(self.cache[0])
        if self.fits_states:  # the fitted states are what the training instants show (the rollout only began them)
            positions = part.state_positions(bones, part.frame_states.detach())
        part.set_training_rollout(frames.bone_transforms, bones, positions)
        self.refreshed = self.step

    def frame_input(self, step) -> None:
        """The host side of the step's window (the window itself is :meth:`step_input`'s): a refresh of the cached
        rollout when due, and the lengths of the window's frames. No explicit input: None."""
        self.training = self.part is not None
        if self.sheet is not None:
            self.training = False  # (no node window: the sheet's state is this step's explicit input)
            return self.sheet.frame_input(step)
        if not self.training:
            return None
        if self.cache is None or self.bones is None or \
                step.step - self.refreshed >= self.options.garment_refresh_every:
            self.refresh()
        self.window_seconds = self._window_seconds(step.index)
        if self.fits_states:
            seconds = self.fit.frames.seconds
            self.start_seconds = (self.uniform_seconds if self.uniform_seconds is not None else
                                  seconds[max(1, step.index - self.options.garment_window)])
        return None

    def _window_seconds(self, index: int) -> tuple[float, ...]:
        """Lengths [s] of the ``W`` frames of the window that ends at training frame ``index``: the common
        interval for every window when the training frames are evenly timed (one captured step serves all),
        else each frame's own (a slot before frame 1 is discarded: any length)."""
        window = self.options.garment_window
        if self.uniform_seconds is not None:
            return (self.uniform_seconds,) * window
        seconds = self.fit.frames.seconds
        return tuple(seconds[max(1, index - window + slot)] for slot in range(1, window + 1))

    def step_input(self, step) -> torch.Tensor | None:
        """Node positions [M,3] of training frame ``step.frame`` (a device index), as device work: a fixed
        sequence of kernels for every frame (see the module docstring). The start state, ``skinned_s(P) + d_s``,
        carries the cached displacement ``d_s`` by the current rest shape ``P``, so the window depends on the rest
        shape as well as on the physics although the cache holds no gradients. The
        ``--garment-window`` frames before it are simulated with gradients from the skinned rest shape plus the
        cached displacement at frame ``max(0, i - W)``, and their displacements from the skinned rest shape are
        written back into the cache. At the first frame nothing is simulated and the cloth's physics optimizer
        skips its step, as when no gradient reaches it (the rest offsets still get one)."""
        if not self.training:
            return None
        if self.fits_states:
            return self._fitted_window(step)
        part = self.part
        displacements, velocities = self.cache
        self.skip_update.copy_(step.frame == 0)
        rows = step.frame + self.window_offsets  # [W+1]: frames i-W .. i
        simulated = rows[1:] >= 1  # [W]: a slot whose frame follows frame 0 (else the state stays)
        rows = rows.clamp_min(0)
        bones = self.bones.index_select(0, rows)
        start = displacements.index_select(0, rows[:1])[0]
        state = ClothState(part.skinned_rest(bones[0]) + start, velocities.index_select(0, rows[:1])[0])
        written = []
        for slot, seconds in enumerate(self.window_seconds):
            stepped = part.step(state, bones[slot], bones[slot + 1], seconds)
            state = ClothState(torch.where(simulated[slot], stepped.positions, state.positions),
                               torch.where(simulated[slot], stepped.velocities, state.velocities))
            with torch.no_grad():  # (a discarded slot writes frame 0's own values back where they were read)
                written.append((torch.where(simulated[slot], state.positions - part.skinned_rest(bones[slot + 1]),
                                            start), state.velocities.detach()))
        with torch.no_grad():
            displacements.index_copy_(0, rows[1:], torch.stack([moved for moved, _ in written]))
            velocities.index_copy_(0, rows[1:], torch.stack([velocity for _, velocity in written]))
        return state.positions

    def _fitted_window(self, step) -> torch.Tensor:
        """The step's frame drawn from its fitted state, and the dynamics residual of the window before it (device
        work from the step's frame index, like the simulated window; see the module docstring).

        For training frame ``i`` and window ``W``: the fitted positions ``x_k = skinned_k(P) + y_k`` of frames
        ``s - 1 .. i`` (``s = i - W``, indices clamped at 0) give the start state, ``x_s`` moving at
        ``(x_s - x_{s-1}) / dt`` (the rollout's settled velocity when ``s`` is frame 0); the simulation steps it
        through the window with gradients, and each simulated frame's distance to that frame's fitted positions,
        squared, over the node spacing squared and averaged over the free nodes, is the residual (mean over the
        window's frames after frame 0). Gradients reach the states of every frame in the window, the physics and
        the rest shape. Returns ``x_i`` [M,3]."""
        part = self.part
        _, velocities = self.cache
        self.skip_update.copy_(step.frame == 0)
        rows = step.frame + self.window_offsets  # [W+1]: frames i-W .. i
        simulated = rows[1:] >= 1  # [W]: a slot whose frame follows frame 0
        rows = rows.clamp_min(0)
        frames = torch.cat([(rows[:1] - 1).clamp_min(0), rows])  # [W+2]: the start's previous frame first
        bones = self.bones.index_select(0, frames)
        fitted = part.state_positions(bones, part.frame_states.index_select(0, frames))
        moving = rows[0] >= 1
        velocity = torch.where(moving, (fitted[1] - fitted[0]) / self.start_seconds, velocities[0])
        state = ClothState(fitted[1], velocity)
        free = part.free_mask
        spacing = part.hyper["voxel_size"]
        scale = 1.0 / (spacing * spacing * free.sum().clamp_min(1.0))
        residual = fitted.new_zeros(())
        for slot, seconds in enumerate(self.window_seconds):
            stepped = part.step(state, bones[slot + 1], bones[slot + 2], seconds)
            error = (((stepped.positions - fitted[slot + 2]) ** 2) * free).sum() * scale
            residual = residual + torch.where(simulated[slot], error, torch.zeros_like(error))
            state = ClothState(torch.where(simulated[slot], stepped.positions, state.positions),
                               torch.where(simulated[slot], stepped.velocities, state.velocities))
        self.residual = residual / len(self.window_seconds)
        self.fitted = fitted[-1]
        return self.fitted

    def _stretch(self, positions: torch.Tensor) -> torch.Tensor:
        """Mean over stretch edges of ``(length / rest-shape length - 1)^2`` at node positions [M,3]."""
        cloth = self.part.cloth
        pairs = cloth.pairs[: cloth.stretch_count]
        lengths = (positions.index_select(0, pairs[:, 0]) - positions.index_select(0, pairs[:, 1])).norm(dim=1)
        rest = cloth.rest_shape_lengths()[: cloth.stretch_count].clamp_min(1e-9)
        return ((lengths / rest - 1.0) ** 2).mean()

    def _step_projection(self, step) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixels [M,2] and camera-space depths [M] of the step frame's fitted nodes (differentiable), by that
        frame's camera, gathered by its device index."""
        frame = step.frame.reshape(1)
        return project_points(self.fitted, self.intrinsics.index_select(0, frame)[0],
                        self.world_to_cameras.index_select(0, frame)[0])

    def _silhouette(self, step, pixels: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The fitted state's silhouette terms (``--lambda-garment-silhouette``): device work from the step's mask
        and render. On a grid of cells ``c`` pixels wide (the frame pooled to about 96 cells a side; a cell is in
        the mask, or uncovered, when over half its pixels are), with the free nodes at ``pixels`` [M,2] and
        ``depth`` [M] (:meth:`_step_projection`; nodes behind the camera left out), and ``S`` the image's longer
        side [px]:

        * ``outside``: mean over the free nodes of ``max(0, d - c)^2 / S^2``, ``d`` the distance to the nearest
          mask cell's centre;
        * ``uncovered``: mean over the uncovered mask cells (mask, and the render's alpha under one half) whose
          nearest node lies within ``0.15 S`` of ``max(0, d - c)^2 / S^2``, ``d`` that node's distance.

        Returns ``(outside, uncovered)``, 0-dim each (zero where nothing counts)."""
        part = self.part
        mask = step.mask
        height, width = mask.shape
        cell = max(1, round(max(height, width) / 96))
        pooled = torch.nn.functional.avg_pool2d(torch.stack([mask, step.alpha.detach()])[None], cell,
                                                ceil_mode=True)[0]
        rows, columns = pooled.shape[1:]
        centres = cell_centres(rows, columns, cell, device=mask.device)  # [P,2] (OpenCV pixels)
        inside = pooled[0].reshape(-1) > 0.5
        uncovered = inside & (pooled[1].reshape(-1) < 0.5)
        front = (depth > 1e-6) & (part.free_mask[:, 0] > 0)
        squared = ((pixels[:, None, :] - centres[None, :, :]) ** 2).sum(-1)  # [M,P]
        size = float(max(height, width))
        # (a finite stand-in for "none": an infinity would turn the masked-out entries' zero gradients into NaN)
        none = 1e4 * size * size
        far = torch.full_like(squared, none)
        to_mask = torch.where(inside[None, :], squared, far).min(dim=1).values  # [M]
        counted_nodes = (front & (to_mask < 0.5 * none)).float()  # (no mask cell at all: nothing counts)
        outside_each = torch.relu(torch.sqrt(to_mask + 1e-12) - cell) ** 2 / size**2
        outside = (outside_each * counted_nodes).sum() / counted_nodes.sum().clamp_min(1.0)
        to_node = torch.where(front[:, None], squared, far).min(dim=0).values  # [P]
        distance = torch.sqrt(to_node + 1e-12)
        counted = (uncovered & (distance < 0.15 * size)).float()
        uncovered_each = torch.where(counted > 0, torch.relu(distance - cell) ** 2 / size**2, torch.zeros_like(distance))
        return outside, uncovered_each.sum() / counted.sum().clamp_min(1.0)

    def _flow(self, step, pixels: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """The fitted states' optical-flow term (``--lambda-garment-flow``): device work from the step's render and
        the step frame's fitted nodes at ``pixels`` [M,2] and ``depth`` [M] (:meth:`_step_projection`).

        The free nodes of frame ``i``'s fitted state that its render shows (projected inside the image, in front of
        the camera, on a mask pixel, at the rendered depth within two node spacings: the cloth's near side) are
        moved by the video's flow from frame ``i`` to frame ``i + 1`` and to frame ``i - 1``; each neighbouring
        frame's fitted state must draw them there. Returns the mean over those nodes and neighbours of the squared
        miss [px^2] over the frame's longer side squared (0-dim; the targets carry no gradient)."""
        part = self.part
        forward, backward = self.flows
        frame = step.frame.reshape(1)
        count = forward.shape[0]
        height, width = step.alpha.shape
        pixels, depth = pixels.detach(), depth.detach()  # (the neighbours' states are what this term moves)
        with torch.no_grad():
            grid = _normalized(pixels, width, height)
            inside = (grid.abs() <= 1.0).all(dim=1) & (depth > 1e-6) & (part.free_mask[:, 0] > 0)
            rendered = torch.stack([step.depth, step.alpha] + ([] if step.mask is None else [step.mask]), dim=-1)
            seen = _sample_image(rendered, grid, mode="nearest")  # [M, 2 or 3]
            surface = seen[:, 0] / seen[:, 1].clamp_min(1e-6)
            visible = inside & (seen[:, 1] > 0.5) & ((depth - surface).abs() < 2.0 * part.hyper["voxel_size"])
            if step.mask is not None:
                visible = visible & (seen[:, 2] > 0.5)
        total = pixels.new_zeros(())
        weight = pixels.new_zeros(())
        for offset, flows in ((1, forward), (-1, backward)):
            neighbour = (frame + offset).clamp(0, count - 1)
            valid = ((frame + offset >= 0) & (frame + offset < count)).float()
            with torch.no_grad():
                target = pixels + _sample_image(flows.index_select(0, frame)[0], grid).float()
            bones = self.bones.index_select(0, neighbour)
            positions = part.state_positions(bones, part.frame_states.index_select(0, neighbour))[0]
            drawn, _ = project_points(positions, self.intrinsics.index_select(0, neighbour)[0],
                               self.world_to_cameras.index_select(0, neighbour)[0])
            miss = ((drawn - target) ** 2).sum(dim=1) * visible.float()
            total = total + valid * miss.sum()
            weight = weight + valid * visible.float().sum()
        return total / (weight.clamp_min(1.0) * float(max(height, width)) ** 2)

    def losses(self, step) -> dict[str, LossTerm]:
        """The rest shape's penalties (roughness, collapsed edges), while it is learned, and the fitted states'
        (the dynamics residual, stretch, optical flow, silhouette): device work, captured with the step."""
        if self.part is None:
            return {}
        if self.sheet is not None:
            return self.sheet.losses(step)
        cloth, options = self.part.cloth, self.options
        terms = {}
        if cloth.rest_offset_logit is not None:
            terms.update(garment_rest_smooth=LossTerm(options.lambda_garment_rest_smooth, cloth.rest_shape_roughness()),
                         garment_rest_collapse=LossTerm(options.lambda_garment_rest_collapse,
                                                        cloth.rest_shape_collapse()))
        if self.training and self.fits_states:
            terms.update(garment_dynamics=LossTerm(options.lambda_garment_dynamics, self.residual),
                         garment_stretch=LossTerm(options.lambda_garment_stretch, self._stretch(self.fitted)))
            flow = self.flows is not None and options.lambda_garment_flow > 0
            silhouette = step.mask is not None and options.lambda_garment_silhouette > 0
            if flow or silhouette:
                pixels, depth = self._step_projection(step)
            if flow:
                terms["garment_flow"] = LossTerm(options.lambda_garment_flow, self._flow(step, pixels, depth))
            if silhouette:
                outside, uncovered = self._silhouette(step, pixels, depth)
                terms.update(garment_outside=LossTerm(options.lambda_garment_silhouette, outside),
                             garment_uncovered=LossTerm(options.lambda_garment_silhouette, uncovered))
        return terms

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        if self.sheet is not None:
            return self.sheet.optimizers()
        if not self.training:
            return []
        optimizers = [self.optimizer] if self.rest_optimizer is None else [self.optimizer, self.rest_optimizer]
        return optimizers + ([self.states_optimizer] if self.fits_states else [])

    def step_capturable(self, step) -> bool:
        """Without a garment (none found, or detection not reached) this extension has no device work in a step;
        with one, the window is device work from the step's buffers, captured when every window has the same
        frame length (evenly timed training frames)."""
        return self.part is None or (self.sheet is None and self.uniform_seconds is not None)

    def graph_key(self, step) -> tuple:
        """The window's frame lengths and the storage and shape of what it reads and writes in place: the cache,
        the transforms, the part's buffers (a new garment, a renumbering or a refresh that changes a shape
        means capturing again)."""
        if not self.training:
            return ()
        part = self.part
        tensors = (*self.cache, self.bones, self.skip_update, *part.cloth.buffers(), *part.cloth.parameters(),
                   part.frame_states, part.free_mask,
                   *(tensor for tensor in (self.intrinsics, self.world_to_cameras) if tensor is not None),
                   *(self.flows or ()),
                   *(getattr(part, name) for name in ("nodes", "node_weights", "gaussian_ids", "anchor",
                                                      "capsule_start", "capsule_end", "capsule_radius",
                                                      "capsule_ids")))
        return self.window_seconds, tuple((tensor.data_ptr(), tuple(tensor.shape)) for tensor in tensors)

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        if self.part is not None:  # (either surface)
            self.part.renumber(source_index, self.fit.avatar.gaussians.means)

    def log_values(self) -> dict[str, float]:
        if self.part is None:
            return {}
        if self.sheet is not None:
            return self.sheet.log_values()
        cloth = self.part.cloth
        return {"garment_stiffness": float(torch.sigmoid(cloth.stiffness_logit.detach()).mean()),
                "garment_damping": float(torch.sigmoid(cloth.damping_logit.detach())),
                "garment_drag": float(torch.sigmoid(cloth.drag_logit.detach())),
                "garment_mass_scale": float(cloth.masses().detach().mean() / cloth.base_mass.mean()),
                "garment_rest_offset": float((cloth.rest_positions() - cloth.initial_rest_positions).detach()
                                             .norm(dim=1).mean())}

    def finish(self) -> None:
        if self.sheet is not None:
            self.sheet.finish(self.step)
        elif self.part is not None:
            self.refresh()

    def write_outputs(self, folder) -> None:
        if self.sheet is not None:
            self.sheet.write_outputs(folder)

    def summary_lines(self) -> list[str]:
        if not self.report:
            return []  # the fit ended before --garment-from
        report = self.report
        if self.part is None:
            return [f"garment: none detected among {report['gaussians']} Gaussians"]
        lines = [f"garment: {report['garment_gaussians']} of {report['gaussians']} Gaussians (heights "
                 f"{report['height_range'][0]:.2f}-{report['height_range'][1]:.2f} of the body), split between "
                 f"{' and '.join(report['split'])}, hung from {report['joint']}: {report['nodes']} "
                 f"{'sheet vertices' if self.sheet is not None else 'cloth nodes'}, {report['attached']} attached, "
                 f"{report['capsules']} body capsules"]
        if self.sheet is not None:
            return lines + self.sheet.summary_lines()
        cloth = self.part.cloth
        if cloth.rest_offset_logit is not None:
            moved = (cloth.rest_positions() - cloth.initial_rest_positions).detach().norm(dim=1)
            lines.append(f"garment rest shape: nodes moved {float(moved.mean()):.3g} on average, at most "
                         f"{float(moved.max()):.3g} (bound {cloth.rest_offset_bound:.3g}, world units)")
        return lines

    def state_dict(self) -> dict:
        state = {"decided": self.decided, "next_attempt": self.next_attempt, "report": dict(self.report),
                 "refreshed": self.refreshed}
        if self.sheet is not None:
            state.update(sheet=self.sheet.state_dict())
        elif self.part is not None:
            state.update(part=self.part.state_for_file(), optimizer=self.optimizer.state_dict(),
                         rest_optimizer=None if self.rest_optimizer is None else self.rest_optimizer.state_dict(),
                         states_optimizer=(None if self.states_optimizer is None else
                                           self.states_optimizer.state_dict()),
                         cache=None if self.cache is None else [tensor.cpu() for tensor in self.cache],
                         cache_holds="displacements")
        return state

    def load_state_dict(self, state: dict) -> None:
        if not state:
            return
        self.decided = bool(state["decided"])
        self.next_attempt = int(state.get("next_attempt", self.options.garment_from))
        self.report = dict(state["report"])
        self.refreshed = int(state["refreshed"])
        if "sheet" in state:
            self.sheet = SheetFit.from_state(self, state["sheet"])
            self.part = self.sheet.part
        if "part" in state:
            self._use(GarmentPart.from_file_state(state["part"], device=self.fit.device))
            saved, saved_rest = state["optimizer"], state.get("rest_optimizer")
            if saved_rest is None and len(saved["param_groups"]) == 2:  # one optimizer with the offsets' group
                saved, saved_rest = _split_groups(saved)
            self.optimizer.load_state_dict(saved)
            if self.rest_optimizer is not None and saved_rest is not None:
                self.rest_optimizer.load_state_dict(saved_rest)
            if self.fits_states and self.part.frame_states.shape[0]:  # (states fitted before the checkpoint)
                states = self.part.frame_states.detach().clone()
                self._start_states(states)
                if state.get("states_optimizer") is not None:
                    self.states_optimizer.load_state_dict(state["states_optimizer"])
            if state["cache"] is not None:
                self.cache = tuple(tensor.to(self.fit.device) for tensor in state["cache"])
                self.bones = self._training_bones()
                if state.get("cache_holds") != "displacements":  # a checkpoint that cached node positions
                    self.cache = (self.part.displacements(self.bones, self.cache[0]), self.cache[1])

