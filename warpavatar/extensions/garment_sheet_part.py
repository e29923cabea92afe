"""A loose garment as a simulated cloth sheet (``--garment-surface sheet``): the part and its fit over the whole video.

The part (:class:`GarmentSheetPart`). Detection (:mod:`.garment_detection`) finds the garment's Gaussians; their
canonical centres give a template-free triangle sheet (:func:`~warpavatar.sim.garment_sheet.build_garment_sheet`,
a surface of revolution about the attachment joint's axis, from its head down along minus the skeleton's up). The
sheet is a :class:`~warpavatar.sim.SheetCloth` (membrane, bending, gravity, damping, drag, the body's capsules)
whose waistband ring is pinned: its rest positions skinned by the body in every frame. Each garment Gaussian is
bound to its sheet triangle (the closest one, :meth:`~warpavatar.model.triangle_gaussians.TriangleGaussians.bind`)
and posed from the sheet's vertices by :func:`warpavatar.ops.pose_triangle_gaussians` (what
:meth:`TriangleGaussians.posed` runs): centre ``u a + v b + w c + d n``, rotation turned with the triangle's frame,
scales grown with its area. The Gaussians stay the avatar's own (trained by the fit's optimizer, renumbered by its
density control, stored in its file): every frame their canonical centre, rotation and scales are expressed in
their triangle's *rest* frame (barycentric coordinates of the centre's projection on the triangle's plane, its
distance along the normal, the rotation relative to the frame), so posed at the rest sheet each comes back exactly
where it is, and the image gradients reach the canonical parameters through that expression.

Where a frame's sheet comes from, in this order: an explicit input (the fit's fitted state of a training frame,
with gradients); the table of the training frames' fitted states, when the pose is a training frame's (novel
views of a training instant); the sequence prepared by :meth:`GarmentSheetPart.prepare_sequence` (a new motion:
settled at its first pose, then simulated frame by frame with the learned physics); otherwise the sheet settled
at that pose. Settling holds the ring at the pose for ``settle_substeps`` substeps while the velocities are
damped hard (scaled by :data:`SETTLE_VELOCITY_KEEP` after every frame).

The fit (:class:`SheetFit`, driven by :class:`~warpavatar.extensions.garment.GarmentExtension`). Every training
frame ``t`` has a state ``x_t = skinned_t(S) + y_t``: the rest sheet ``S`` skinned into the frame plus learned
displacements ``y_t`` (``[T, V, 3]``, zero on the ring), started from a rollout of the training motion. A step
draws its frame from its state (the image loss reaches ``y_i``), pulls free vertices drawn outside the mask back
to it and uncovered mask cells to the nearest vertex (the silhouette terms of the node model), and adds the physics
as a soft prior: for a batch of frames ``t >= 2`` the residual ``|x_t - step(x_{t-1}, (x_{t-1} - x_{t-2}) / dt)|^2``
over the free vertices, in units of the sheet's mean edge length squared. The residual's gradients reach the three
states and the material parameters (stretch, shear, bending, damping, drag), which are learned from it alone.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from warpavatar import ops
from warpavatar._src.triangle_binding import triangle_frames
from warpavatar.extensions.base import LossTerm
from warpavatar.geometry import match_pose, quat_conjugate, quat_from_matrix, quat_multiply
from warpavatar.io.output_files import write_bytes_atomic, write_text_atomic
from warpavatar.model.parts import AvatarPart
from warpavatar.model.triangle_gaussians import TriangleGaussians
from warpavatar.optim import Adam
from warpavatar.sim import Capsules, SheetCloth, SheetState, capsules_near, fit_body_capsules, pose_capsules
from warpavatar.sim.capsules import select
from warpavatar.sim.garment_sheet import build_garment_sheet

__all__ = ["GarmentSheetPart", "SheetFit", "SETTLE_VELOCITY_KEEP"]

SETTLE_VELOCITY_KEEP = 0.7
"""While settling, the velocities are scaled by this after every frame (strong damping: the sheet comes to rest)."""


class GarmentSheetPart(AvatarPart):
    """A simulated garment sheet: its Gaussians are bound to the triangles of a pinned triangle-mesh cloth.

    Args:
        gaussian_ids: int64 ``[G]`` the garment's Gaussians among the avatar's.
        vertices: the sheet's canonical rest vertices [world units], ``[V, 3]``.
        faces: int64 ``[F, 3]`` its triangles.
        pinned: int64 ``[P]`` the waistband ring's vertex ids (skinned by the body every frame).
        vertex_weights: skinning weights of the vertices ``[V, J+E]``.
        joint: the joint the garment hangs from (skeleton index).
        capsules: canonical body capsules, one per skeleton joint; ``capsule_ids`` int64 ``[C]`` those it can meet.
        max_substep: longest simulation substep [s].
        up: the world's up direction (gravity is ``-9.81 up``).
        joint_count: joints J of the skeleton (the leading transforms that name a pose).
        settle_substeps: substeps of settling before a sequence or a lone pose.
        areal_density: the cloth's mass per area [kg / world unit^2].
    """

    name = "garment"

    def __init__(self, gaussian_ids: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, pinned: torch.Tensor,
                 vertex_weights: torch.Tensor, *, joint: int, capsules: Capsules, capsule_ids: torch.Tensor,
                 max_substep: float = 1.0 / 600.0, up=(0.0, 0.0, 1.0), joint_count: int | None = None,
                 settle_substeps: int = 600, areal_density: float = 0.2):
        super().__init__()
        vertices = vertices.detach().float().contiguous()
        device = vertices.device
        joint_count = int(vertex_weights.shape[1] if joint_count is None else joint_count)
        self.hyper = dict(surface="sheet", joint=int(joint), joint_count=joint_count, max_substep=float(max_substep),
                          up=tuple(float(u) for u in up), settle_substeps=int(settle_substeps),
                          areal_density=float(areal_density))
        faces = torch.as_tensor(faces, device=device).long()
        pinned = torch.as_tensor(pinned, device=device).long()
        self.cloth = SheetCloth(vertices, faces, pinned, areal_density=areal_density, max_substep=max_substep,
                                up=self.hyper["up"])
        self.register_buffer("gaussian_ids", torch.as_tensor(gaussian_ids, device=device).long().clone())
        self.register_buffer("vertex_weights", vertex_weights.detach().float().to(device).clone())
        self.register_buffer("capsule_start", capsules.segment_start.detach().float().to(device).clone())
        self.register_buffer("capsule_end", capsules.segment_end.detach().float().to(device).clone())
        self.register_buffer("capsule_radius", capsules.radius.detach().float().to(device).clone())
        self.register_buffer("capsule_ids", torch.as_tensor(capsule_ids, device=device).long().clone())
        #: each garment Gaussian's triangle [G] (:meth:`bind`)
        self.register_buffer("triangle_ids", torch.zeros(0, dtype=torch.int64, device=device))
        #: the table of the training frames: poses [T,J,4,4] (as given) and their sheets' vertices [T,V,3]
        self.register_buffer("frame_poses", torch.zeros(0, 1, 4, 4, device=device))
        self.register_buffer("frame_vertices", torch.zeros(0, vertices.shape[0], 3, device=device))
        #: the training frames' fitted states [T,V,3]: displacements from the skinned rest sheet (zero on the ring)
        self.frame_states = torch.nn.Parameter(torch.zeros(0, vertices.shape[0], 3, device=device))
        free = torch.ones(vertices.shape[0], 1, device=device)
        free[pinned] = 0.0
        self.register_buffer("free_mask", free, persistent=False)
        self.free_count = max(1, vertices.shape[0] - int(pinned.unique().numel()))
        _, _, area = triangle_frames(vertices[faces].double())
        self.register_buffer("rest_area", area.float(), persistent=False)
        edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        #: mean rest edge length [world units]: the length scale of the residual and the states' step size
        self.edge_length = float((vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1).mean())
        self._binding: tuple[torch.Tensor, ...] | None = None
        self._sequence: tuple[torch.Tensor, torch.Tensor] | None = None
        self._lone: tuple[torch.Tensor, torch.Tensor] | None = None

    # -------------------------------------------------------------------------------------------- views
    @property
    def rest_vertices(self) -> torch.Tensor:
        return self.cloth.rest_positions

    @property
    def faces(self) -> torch.Tensor:
        return self.cloth.faces

    @property
    def node_count(self) -> int:
        """Vertices of the sheet (the node model's name for its simulated points)."""
        return self.rest_vertices.shape[0]

    @property
    def attached(self) -> torch.Tensor:
        """The pinned ring's vertex ids."""
        return self.cloth.pinned_ids

    # ------------------------------------------------------------------------------------------ binding
    @torch.no_grad()
    def bind(self, canonical_means: torch.Tensor, quats: torch.Tensor | None = None,
             scales: torch.Tensor | None = None) -> None:
        """Bind each garment Gaussian to its closest sheet triangle (``canonical_means`` [N,3] of all the avatar's;
        rotations and scales only shape :meth:`TriangleGaussians.bind`'s local values, re-expressed every frame)."""
        points = canonical_means.detach()[self.gaussian_ids].float()
        count = points.shape[0]
        quats = points.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(count, 4) if quats is None else \
            quats.detach()[self.gaussian_ids].float()
        scales = points.new_ones(count, 3) if scales is None else scales.detach()[self.gaussian_ids].float()
        binding = TriangleGaussians.bind(points, quats, scales, (self.rest_vertices, self.faces))
        self.triangle_ids = binding.triangle_ids.clone()
        self._binding = None

    def _rest_frames(self) -> tuple[torch.Tensor, ...]:
        """Per bound Gaussian: corner ``a`` [G,3], edges [G,3,2], inverse Gram matrix [G,2,2], unit normal [G,3]
        and the conjugate of the frame's rotation [G,4] of its triangle at rest (cached until rebound)."""
        if self._binding is None or self._binding[0].shape[0] != self.triangle_ids.shape[0]:
            corners = self.rest_vertices[self.faces[self.triangle_ids]].double()  # [G,3,3]
            frame, normal, _ = triangle_frames(corners)
            a, b, c = corners.unbind(1)
            edges = torch.stack([b - a, c - a], dim=2)
            gram_inverse = torch.linalg.inv(edges.transpose(1, 2) @ edges)
            self._binding = (a.float(), edges.float(), gram_inverse.float(), normal.float(),
                             quat_conjugate(quat_from_matrix(frame)).float())
        return self._binding

    def local_values(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The garment Gaussians' canonical centres [G,3], rotations [G,4] and scales [G,3] in their triangles'
        rest frames, differentiable: ``(barycentrics [G,3], offsets [G], local_quats [G,4], local_log_scales
        [G,3])`` for :func:`warpavatar.ops.pose_triangle_gaussians` (posed at the rest sheet: the same Gaussians)."""
        a, edges, gram_inverse, normal, frame_conjugate = self._rest_frames()
        relative = means - a
        offsets = (relative * normal).sum(1)
        vw = (gram_inverse @ (edges.transpose(1, 2) @ relative[:, :, None]))[:, :, 0]
        barycentrics = torch.cat([1.0 - vw.sum(1, keepdim=True), vw], dim=1)
        local_quats = quat_multiply(frame_conjugate, quats)
        return barycentrics, offsets, local_quats, scales.clamp_min(1e-12).log()

    @torch.no_grad()
    def renumber(self, source_index: torch.Tensor, canonical_means: torch.Tensor) -> None:
        """Follow density control: new Gaussian ``i`` comes from old ``source_index[i]``; then bind again."""
        old_count = int(source_index.max()) + 1 if source_index.numel() else 0
        old_count = max(old_count, int(self.gaussian_ids.max()) + 1 if self.gaussian_ids.numel() else 0)
        member = torch.zeros(old_count, dtype=torch.bool, device=source_index.device)
        member[self.gaussian_ids] = True
        self.gaussian_ids = torch.nonzero(member[source_index]).reshape(-1)
        self.bind(canonical_means)

    @torch.no_grad()
    def set_vertex_weights(self, vertex_weights: torch.Tensor) -> None:
        """Replace the vertices' skinning weights ``[V, J+E]`` (the field trained)."""
        self.vertex_weights = vertex_weights.detach().float().to(self.vertex_weights.device).clone()

    # ------------------------------------------------------------------------------------ the body's part
    def skinned_rest(self, bones: torch.Tensor) -> torch.Tensor:
        """The rest sheet skinned into a pose (``bones`` [J+E,4,4]): vertices [V,3]."""
        return ops.lbs(self.rest_vertices, self.vertex_weights,
                       bones[: self.vertex_weights.shape[1]].contiguous())[0]

    def pinned_targets(self, bones: torch.Tensor) -> torch.Tensor:
        """Where the ring is in a pose [P,3]: its rest positions skinned by the body."""
        return self.skinned_rest(bones).index_select(0, self.attached)

    def posed_capsules(self, bones: torch.Tensor) -> Capsules:
        canonical = select(Capsules(self.capsule_start, self.capsule_end, self.capsule_radius), self.capsule_ids)
        return pose_capsules(canonical, bones[self.capsule_ids])

    def state_vertices(self, bones: torch.Tensor, states: torch.Tensor) -> torch.Tensor:
        """Vertices [K,V,3] of states [K,V,3] in poses ``bones`` [K,J+E,4,4] (differentiable in the states)."""
        return torch.stack([self.skinned_rest(b) for b in bones]) + states * self.free_mask

    # ------------------------------------------------------------------------------------------ simulation
    def step(self, state: SheetState, previous_bones: torch.Tensor, bones: torch.Tensor, seconds: float
             ) -> SheetState:
        """One frame of ``seconds`` from the pose ``previous_bones`` to ``bones`` (differentiable)."""
        return self.cloth.step(state, self.pinned_targets(bones), float(seconds), capsules=self.posed_capsules(bones),
                               previous_capsules=self.posed_capsules(previous_bones))

    @torch.no_grad()
    def settled(self, bones: torch.Tensor, frame_interval: float) -> SheetState:
        """The sheet at rest in one pose: skinned there, then ``settle_substeps`` substeps with the ring held and
        the velocities damped hard."""
        interval = float(frame_interval)
        positions = self.skinned_rest(bones)
        state = SheetState(positions, torch.zeros_like(positions))
        frames = max(1, math.ceil(self.hyper["settle_substeps"] / self.cloth.substeps(interval)))
        for _ in range(frames):
            state = self.step(state, bones, bones, interval)
            state = SheetState(state.positions, state.velocities * SETTLE_VELOCITY_KEEP)
        return state

    @torch.no_grad()
    def rollout(self, bones: torch.Tensor, seconds: list[float], *, progress: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Simulate a motion (no gradients): settled at its first pose, then frame by frame. ``bones``
        [T,J+E,4,4], ``seconds`` [T] (the first: the settling frames' length). Returns vertex positions and
        velocities, ``[T,V,3]`` each."""
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

    @torch.no_grad()
    def set_training_table(self, poses: torch.Tensor, vertices: torch.Tensor) -> None:
        """Keep the training frames' poses [T,J,4,4] (as given) and their sheets' vertices [T,V,3]."""
        self.frame_poses = poses.detach().float().clone()
        self.frame_vertices = vertices.detach().float().clone()

    @torch.no_grad()
    def prepare_sequence(self, bones: torch.Tensor, intervals: torch.Tensor, *, progress: bool = False) -> None:
        """Roll a new motion out with the learned physics, from a settle at its first pose."""
        positions, _ = self.rollout(bones, intervals.tolist(), progress=progress)
        self._sequence = (bones[:, :self.hyper["joint_count"]].detach().float().clone(), positions)

    def _lookup(self, frame, bones: torch.Tensor) -> torch.Tensor:
        pose = frame.bone_transforms
        tables = [(self.frame_poses, self.frame_vertices)]
        if self._sequence is not None:
            tables.append(self._sequence)
        vertices = torch.zeros_like(self.rest_vertices)
        found = torch.zeros((), device=vertices.device)
        for poses, table in tables:
            if poses.shape[0] == 0:
                continue
            best, matched = match_pose(poses, pose)
            use = matched * (1.0 - found)
            vertices = vertices + use * table[best]
            found = found + use
        if float(found) < 0.5:  # a lone pose: the sheet hangs at rest there
            key = self._lone
            if key is None or key[0].shape != pose.shape or not torch.equal(key[0], pose):
                self._lone = (pose.detach().clone(), self.settled(bones, 1.0 / 30.0).positions)
            return self._lone[1]
        return vertices

    # ------------------------------------------------------------------------------------------ posing
    def deform_posed(self, posed, frame):
        """Place the garment Gaussians on the frame's sheet (module docstring); a displacement other parts gave
        them before skinning (``posed["canonical_offsets"]``) moves them in their triangle's rest frame."""
        ids = self.gaussian_ids
        if ids.numel() == 0:
            return posed
        if self.triangle_ids.shape[0] != ids.shape[0]:
            self.bind(posed["canonical_means"])
        bones = posed["bone_transforms"]
        explicit = frame.input(self.name)
        vertices = explicit if explicit is not None else self._lookup(frame, bones)
        means = posed["canonical_means"].index_select(0, ids)
        displaced = posed.get("canonical_offsets")
        if displaced is not None:
            means = means + displaced.index_select(0, ids)
        local = self.local_values(means.float(), posed["canonical_quats"].index_select(0, ids).float(),
                                  posed["scales"].index_select(0, ids).float())
        means, quats, log_scales = ops.pose_triangle_gaussians(vertices.float().contiguous(), self.faces,
                                                               self.rest_area, self.triangle_ids, *local)
        posed = type(posed)(posed)
        posed["means"] = posed["means"].index_copy(0, ids, means.to(posed["means"].dtype))
        posed["quats"] = posed["quats"].index_copy(0, ids, quats.to(posed["quats"].dtype))
        posed["scales"] = posed["scales"].index_copy(0, ids, log_scales.exp().to(posed["scales"].dtype))
        return posed

    # ------------------------------------------------------------------------------------------- files
    def state_for_file(self) -> dict:
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}, "hyper": dict(self.hyper)}

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "GarmentSheetPart":
        weights = {k: v.to(device) for k, v in state["state_dict"].items()}
        hyper = state["hyper"]
        part = cls(weights["gaussian_ids"], weights["cloth.rest_positions"], weights["cloth.faces"],
                   weights["cloth.pinned_ids"], weights["vertex_weights"], joint=hyper["joint"],
                   capsules=Capsules(weights["capsule_start"], weights["capsule_end"], weights["capsule_radius"]),
                   capsule_ids=weights["capsule_ids"], max_substep=hyper["max_substep"], up=hyper["up"],
                   joint_count=hyper["joint_count"], settle_substeps=hyper["settle_substeps"],
                   areal_density=hyper["areal_density"])
        for name in ("triangle_ids", "frame_poses", "frame_vertices"):
            setattr(part, name, weights[name])
        part.frame_states = torch.nn.Parameter(weights["frame_states"].float())
        part.load_state_dict(weights)
        return part

    @torch.no_grad()
    def write_sheet(self, path: Path) -> Path:
        """Write the canonical rest sheet as a ``.ply`` for inspection (atomically)."""
        import trimesh

        mesh = trimesh.Trimesh(self.rest_vertices.cpu().numpy(), self.faces.cpu().numpy(), process=False)
        return write_bytes_atomic(path, mesh.export(file_type="ply"))


class SheetFit:
    """The sheet's fit over the whole video, for :class:`~warpavatar.extensions.garment.GarmentExtension` (module
    docstring): per-frame states with an Adam of their own, the physics residual, the silhouette terms.

    Args:
        extension: the garment extension (its options, fit context and silhouette term).
        part: the sheet part (added to the avatar by :meth:`build` or a checkpoint).
    """

    def __init__(self, extension, part: GarmentSheetPart):
        self.extension = extension
        self.fit = extension.fit
        self.options = extension.options
        self.part = part
        self.optimizer = Adam(list(part.cloth.parameters()), lr=self.options.lr_garment)
        self.states_optimizer: Adam | None = None
        self.bones: torch.Tensor | None = None
        self.refreshed = -1
        #: image-loss steps each training frame's state has had [T] (host ints)
        self.image_steps: list[int] = []
        self.residual_steps = 0  # steps that trained the residual
        self.initial_residual: float | None = None  # over the whole sequence, at the rollout the states began from
        self.final_residual: float | None = None
        self.residual: torch.Tensor | None = None  # this step's (batch) residual
        self.fitted: torch.Tensor | None = None  # this step's frame's vertices [V,3]
        cameras = self.fit.frames.cameras
        self.intrinsics = torch.stack([torch.as_tensor(c.K, dtype=torch.float32) for c in cameras]).to(self.fit.device)
        self.world_to_cameras = torch.stack([torch.as_tensor(c.world_to_camera, dtype=torch.float32)
                                             for c in cameras]).to(self.fit.device)

    # ------------------------------------------------------------------------------------------ building
    @classmethod
    @torch.no_grad()
    def build(cls, extension, means, weights, grid, ids: torch.Tensor, joint: int) -> "SheetFit":
        """The sheet of the detected garment ``ids`` hung from ``joint``, its part added to the avatar."""
        fit, options = extension.fit, extension.options
        skeleton = fit.frames.skeleton
        field = fit.skinning.field
        device = means.device
        up = torch.as_tensor(skeleton.up, dtype=torch.float32)
        heads = torch.as_tensor(skeleton.heads, dtype=torch.float32)
        sheet = build_garment_sheet(means[ids].cpu(), axis_origin=heads[joint].numpy(),
                                    axis_direction=(-up).numpy(), rings=options.garment_sheet_rings,
                                    segments=options.garment_sheet_segments)
        vertices = torch.as_tensor(sheet.vertices, dtype=torch.float32, device=device)
        faces = torch.as_tensor(sheet.faces, dtype=torch.int64, device=device)
        vertex_weights = field.weights(vertices, grid)
        garment = torch.zeros(means.shape[0], dtype=torch.bool, device=device)
        garment[ids] = True
        capsules = fit_body_capsules(heads.to(device), torch.as_tensor(skeleton.tails, dtype=torch.float32,
                                                                       device=device), means, weights, exclude=garment)
        radius = capsules.radius
        if bool((radius > 0).any()):  # a bone the garment hides entirely gets a typical radius
            radius = torch.where(radius > 0, radius, radius[radius > 0].median())
        capsules = Capsules(capsules.segment_start, capsules.segment_end, radius)
        sides = vertices.max(0).values - vertices.min(0).values
        capsule_ids = capsules_near(capsules, vertices, margin=0.5 * float(sides.norm()))
        part = GarmentSheetPart(ids, vertices, faces, torch.as_tensor(sheet.pinned, device=device), vertex_weights,
                                joint=joint, capsules=capsules, capsule_ids=capsule_ids,
                                max_substep=options.garment_sheet_substep, up=tuple(float(u) for u in skeleton.up),
                                joint_count=len(skeleton.names), settle_substeps=options.garment_settle_substeps)
        gaussians = fit.avatar.gaussians
        part.bind(means, gaussians.normalized_quats, gaussians.scales)
        return cls(extension, fit.avatar.add_part(part))

    # ------------------------------------------------------------------------------------------ training
    def _training_bones(self) -> torch.Tensor:
        return torch.stack([self.fit.avatar.pose_bones(b) for b in self.fit.frames.bone_transforms])

    @torch.no_grad()
    def refresh(self, step: int) -> None:
        """Re-read the vertices' skinning weights, start the states from a rollout (once) and refill the table
        novel views of training instants use."""
        part, frames = self.part, self.fit.frames
        field = self.fit.skinning.field
        part.set_vertex_weights(field.weights(part.rest_vertices, field.grid_weights()))
        self.bones = self._training_bones()
        if part.frame_states.shape[0] != frames.count:
            positions, _ = part.rollout(self.bones, frames.seconds)
            skinned = torch.stack([part.skinned_rest(b) for b in self.bones])
            part.frame_states = torch.nn.Parameter((positions - skinned) * part.free_mask)
            self.states_optimizer = Adam([part.frame_states],
                                         lr=self.options.lr_garment_sheet_states * part.edge_length)
            self.image_steps = [0] * frames.count
            self.initial_residual = self.whole_residual()
        part.set_training_table(frames.bone_transforms, part.state_vertices(self.bones, part.frame_states.detach()))
        self.refreshed = step

    def frame_input(self, step) -> torch.Tensor:
        """The step frame's sheet from its state (with gradients): the part's explicit input."""
        if self.bones is None or step.step - self.refreshed >= self.options.garment_refresh_every:
            self.refresh(step.step)
        index = step.index
        self.image_steps[index] += 1
        self.fitted = self.part.state_vertices(self.bones[index:index + 1], self.part.frame_states[index:index + 1])[0]
        return self.fitted

    def _residual(self, frames: list[int]) -> torch.Tensor:
        """Mean over ``frames`` (each >= 2) of the physics residual of each: mean over free vertices of
        ``|x_t - step(x_{t-1}, (x_{t-1} - x_{t-2}) / dt_{t-1})|^2`` over the mean edge length squared."""
        part, seconds = self.part, self.fit.frames.seconds
        scale = 1.0 / (part.edge_length ** 2 * part.free_count)
        total = part.frame_states.new_zeros(())
        for t in frames:
            rows = torch.arange(t - 2, t + 1, device=part.frame_states.device)
            x = part.state_vertices(self.bones[t - 2:t + 1], part.frame_states.index_select(0, rows))
            state = SheetState(x[1], (x[1] - x[0]) / seconds[t - 1])
            predicted = part.step(state, self.bones[t - 1], self.bones[t], seconds[t]).positions
            total = total + (((predicted - x[2]) ** 2) * part.free_mask).sum() * scale
        return total / max(1, len(frames))

    @torch.no_grad()
    def whole_residual(self) -> float:
        """The residual over every frame ``t >= 2`` of the sequence (no gradients)."""
        count = self.fit.frames.count
        return float(self._residual(list(range(2, count)))) if count >= 3 else 0.0

    def _batch(self, step: int) -> list[int]:
        """This step's residual frames: ``--garment-sheet-frames`` of ``2 .. T-1``, cycling deterministically."""
        count = self.fit.frames.count
        if count < 3:
            return []
        span = count - 2
        size = min(self.options.garment_sheet_frames, span)
        stride = 7 if span % 7 else 1  # (a stride coprime with the span visits every frame)
        return [2 + ((step * size + k) * stride) % span for k in range(size)]

    def losses(self, step) -> dict[str, LossTerm]:
        options, extension = self.options, self.extension
        terms = {}
        frames = self._batch(step.step)
        if frames:
            self.residual = self._residual(frames)
            self.residual_steps += 1
            terms["garment_sheet_dynamics"] = LossTerm(options.lambda_garment_sheet_dynamics, self.residual)
        if step.mask is not None and options.lambda_garment_silhouette > 0:
            frame = step.index
            pixels, depth = _project(self.fitted, self.intrinsics[frame], self.world_to_cameras[frame])
            outside, uncovered = extension._silhouette(step, pixels, depth)
            terms.update(garment_outside=LossTerm(options.lambda_garment_silhouette, outside),
                         garment_uncovered=LossTerm(options.lambda_garment_silhouette, uncovered))
        return terms

    def optimizers(self) -> list:
        return [self.optimizer] + ([self.states_optimizer] if self.states_optimizer is not None else [])

    def log_values(self) -> dict[str, float]:
        cloth = self.part.cloth
        values = {"garment_sheet_stretch": float(cloth.stretch_stiffness().detach()),
                  "garment_sheet_bend": float(cloth.bend_stiffness().detach()),
                  "garment_sheet_damping": float(cloth.damping().detach()),
                  "garment_sheet_drag": float(cloth.drag().detach())}
        if self.image_steps:
            values["garment_sheet_steps_per_frame"] = sum(self.image_steps) / len(self.image_steps)
        return values

    # ------------------------------------------------------------------------------------------ the end
    def finish(self, step: int) -> None:
        self.refresh(step)
        self.final_residual = self.whole_residual()
        self.fit.log({"step": step, "garment_sheet": self.report()})

    def report(self) -> dict:
        """What ``garment_sheet.json`` and the fit's log say about the fit."""
        part, cloth = self.part, self.part.cloth
        steps = self.image_steps or [0]
        return {"vertices": part.node_count, "triangles": int(part.faces.shape[0]),
                "pinned": int(part.attached.numel()), "garment_gaussians": int(part.gaussian_ids.numel()),
                "edge_length": part.edge_length, "training_frames": len(self.image_steps),
                "image_steps_per_frame": {"mean": sum(steps) / len(steps), "min": min(steps), "max": max(steps)},
                "residual_steps": self.residual_steps, "residual_frames_per_step": self.options.garment_sheet_frames,
                "initial_residual": self.initial_residual, "final_residual": self.final_residual,
                "material": {"stretch_stiffness": float(cloth.stretch_stiffness().detach()),
                             "shear_stiffness": float(cloth.shear_stiffness().detach()),
                             "bend_stiffness": float(cloth.bend_stiffness().detach()),
                             "damping": float(cloth.damping().detach()), "drag": float(cloth.drag().detach())}}

    def write_outputs(self, folder: Path) -> None:
        folder = Path(folder)
        write_text_atomic(folder / "garment_sheet.json", json.dumps(self.report(), indent=2) + "\n")
        self.part.write_sheet(folder / "garment_sheet.ply")

    def summary_lines(self) -> list[str]:
        report = self.report()
        steps = report["image_steps_per_frame"]
        final = report["final_residual"]
        return [f"garment sheet: {report['vertices']} vertices, {report['triangles']} triangles, "
                f"{report['pinned']} pinned; states fitted {steps['mean']:.1f} image steps a frame "
                f"(min {steps['min']}),"
                f" physics residual {report['initial_residual'] or 0.0:.3g} at the rollout, "
                f"{'not measured' if final is None else f'{final:.3g}'} at the end"]

    def state_dict(self) -> dict:
        return {"surface": "sheet", "part": self.part.state_for_file(), "optimizer": self.optimizer.state_dict(),
                "states_optimizer": None if self.states_optimizer is None else self.states_optimizer.state_dict(),
                "image_steps": list(self.image_steps), "residual_steps": self.residual_steps,
                "initial_residual": self.initial_residual, "refreshed": self.refreshed}

    @classmethod
    def from_state(cls, extension, state: dict) -> "SheetFit":
        part = GarmentSheetPart.from_file_state(state["part"], device=extension.fit.device)
        sheet = cls(extension, extension.fit.avatar.add_part(part))
        sheet.optimizer.load_state_dict(state["optimizer"])
        if state.get("states_optimizer") is not None and part.frame_states.shape[0]:
            sheet.states_optimizer = Adam([part.frame_states],
                                          lr=extension.options.lr_garment_sheet_states * part.edge_length)
            sheet.states_optimizer.load_state_dict(state["states_optimizer"])
        sheet.image_steps = list(state.get("image_steps", []))
        sheet.residual_steps = int(state.get("residual_steps", 0))
        sheet.initial_residual = state.get("initial_residual")
        if part.frame_states.shape[0]:
            sheet.bones = sheet._training_bones()
            sheet.refreshed = int(state.get("refreshed", -1))
        return sheet


def _project(points: torch.Tensor, K: torch.Tensor, world_to_camera: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels [M,2] (OpenCV: pixel centres at integers) and camera-space depths [M] of world points [M,3]; points
    behind the camera get depth <= 0 and a pixel computed at depth 1 (finite, for the caller to mask)."""
    camera = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    depth = camera[:, 2]
    safe = torch.where(depth > 1e-6, depth, torch.ones_like(depth))
    return (camera[:, :2] / safe[:, None]) @ K[:2, :2].T + K[:2, 2], depth
