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

Tracking (:class:`SheetTracker`, run by :meth:`SheetFit.track` right after the rollout and every
``--garment-sheet-track-every`` steps at a refresh). A frame's image steps are too few and too small to bring its
state from the rollout to the images, so every frame's state is also fitted at once, without rendering the
Gaussians, for ``--garment-sheet-track-iterations`` Adam iterations: free vertices and triangle centroids inside the
frame's mask (its distance transform, sampled bilinearly), the garment's cells of the mask covered by the projected
sheet (each uncovered one pulls its nearest free vertex), the physics residual and the edges' strain.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
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

__all__ = ["GarmentSheetPart", "SheetFit", "SheetTracker", "TrackingTargets", "tracking_targets", "tracking_cell",
           "covered_cells", "cell_centres", "project_frames", "project_points", "sheet_residual",
           "SETTLE_VELOCITY_KEEP", "TRACK_CELLS", "TRACK_REACH", "MIN_AREA_RATIO", "valid_sheet_frames"]

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
            index = frame.frame_index
            if index is not None and 0 <= int(index) < poses.shape[0]:
                # the frame's own row when its pose is that row's: a motion that comes back to a pose (a loop,
                # a hold) keeps its own sheet there instead of the first frame with that pose
                own = ((poses[int(index)] - pose[: poses.shape[1]]).abs().amax() <= 1e-4).to(matched.dtype)
                best = torch.where(own > 0, torch.full_like(best, int(index)), best)
                matched = torch.maximum(matched, own)
            use = matched * (1.0 - found)
            vertices = vertices + use * table[best]
            found = found + use
        if float(found) < 0.5:  # a lone pose: the sheet hangs at rest there
            key = self._lone
            if key is None or key[0].shape != pose.shape or not torch.equal(key[0], pose):
                self._lone = (pose.detach().clone(), self.settled(bones, 1.0 / 30.0).positions)
            return self._lone[1]
        return vertices

    @torch.no_grad()
    def posed_sheet(self, posed) -> tuple[torch.Tensor, torch.Tensor]:
        """The sheet :meth:`deform_posed` placed ``posed``'s garment Gaussians on (read-only; for exports):
        vertices [V,3] [world units] and faces int64 [F,3], on the avatar's device."""
        vertices = posed.get("sheet_vertices", {}).get(self.name)
        if vertices is None:  # (a part without Gaussians places none and keeps no sheet in ``posed``)
            frame = posed["frame"]
            explicit = frame.input(self.name)
            vertices = explicit if explicit is not None else self._lookup(frame, posed["bone_transforms"])
        return vertices.detach().float(), self.faces

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
        posed["sheet_vertices"] = {**posed.get("sheet_vertices", {}), self.name: vertices.detach()}
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


# ---------------------------------------------------------------------------------------------------------
# Sheet tracking: every training frame's state fitted to its mask at once, without rendering the Gaussians
# ---------------------------------------------------------------------------------------------------------

TRACK_CELLS = 96
"""The tracking stage's grid has about this many cells along the frames' longer side."""

TRACK_REACH = 0.15
"""Garment cells farther than this fraction of the frame's longer side from the skinned rest sheet's cells are left
out of the garment region (a mask part the avatar does not draw, far from the garment, pulls nothing)."""

_MAX_SPLAT_DIVISIONS = 16
"""At most this many divisions of a triangle's edges when its projection is splatted into the grid's cells."""


@dataclass
class TrackingTargets:
    """What the tracking stage fits the training frames' sheets to, on a grid of ``cell``-pixel cells.

    Attributes:
        distance: [T,rows,cols] float32: the mean distance [px] of each cell's pixels to the frame's mask (0 inside
            it; within half a cell of the centre's).
        region: [T,rows,cols] bool: the garment's cells (the mask where the rest of the avatar is not drawn).
        other: [T,rows,cols] bool: the mask's cells that are not the garment's (the body: a sheet drawn there may
            lie in front of it or behind it, so coverage there counts neither way).
        cell: the cell's side [px]; ``width``, ``height``: the frames' size [px].
    """

    distance: torch.Tensor
    region: torch.Tensor
    other: torch.Tensor
    cell: int
    width: int
    height: int

    def centres(self) -> torch.Tensor:
        """Pixel coordinates [rows*cols, 2] of the cells' centres (:func:`cell_centres`)."""
        rows, columns = self.region.shape[1:]
        return cell_centres(rows, columns, self.cell, device=self.region.device)


def cell_centres(rows: int, columns: int, cell: int, *, device=None) -> torch.Tensor:
    """Pixel coordinates [rows*cols, 2] (OpenCV: pixel centres at integers), row-major, of the centres of a grid of
    ``cell``-pixel cells laid from the image's corner."""
    y, x = torch.meshgrid(torch.arange(rows, device=device), torch.arange(columns, device=device), indexing="ij")
    return (torch.stack([x, y], dim=-1).reshape(-1, 2).float() + 0.5) * cell - 0.5


def tracking_cell(width: int, height: int, *, cells: int = TRACK_CELLS) -> int:
    """The side [px] of the tracking grid's cells for frames ``width x height``: about ``cells`` a longer side."""
    return max(1, round(max(width, height) / cells))


@torch.no_grad()
def tracking_targets(masks: torch.Tensor, not_garment: torch.Tensor | None = None, *, cells: int = TRACK_CELLS,
                     anchor: torch.Tensor | None = None, reach: float = TRACK_REACH,
                     distance: torch.Tensor | None = None) -> TrackingTargets:
    """The tracking stage's targets of frames' masks.

    Args:
        masks: [T,H,W] the frames' masks (uint8 0-255 or float 0-1; a pixel is in where over one half).
        not_garment: [T,H,W] bool, pixels of the mask that are not the garment's (None: the whole mask is).
        cells: about this many grid cells along the longer side.
        anchor: [T,rows,cols] bool, cells of a first guess at the garment (the skinned rest sheet); region cells
            farther than ``reach`` times the longer side from them are left out (None: none are).
        reach: see ``anchor`` (a fraction of the longer side).
        distance: the cells' distances to the masks from an earlier call with the same masks and ``cells`` (not
            computed again), or None.

    Returns:
        The :class:`TrackingTargets`, on the masks' device. A cell is in the mask, or the garment's, when over
        half its pixels are; its distance to the mask is the mean over its pixels of theirs (the exact Euclidean
        distance transform at full resolution, :func:`_distance_to`), within half a cell of the centre's.
    """
    masks = masks.float() / (255.0 if masks.dtype == torch.uint8 else 1.0)
    count, height, width = masks.shape
    cell = tracking_cell(width, height, cells=cells)
    inside = masks > 0.5
    garment = inside if not_garment is None else inside & ~not_garment.to(inside.device)
    pooled = torch.nn.functional.avg_pool2d(torch.stack([inside.float(), garment.float()], dim=1), cell,
                                            ceil_mode=True)
    if distance is None or distance.shape != pooled.shape[:1] + pooled.shape[2:]:
        full = _distance_to(inside).to(masks.device)
        distance = torch.nn.functional.avg_pool2d(full[:, None], cell, ceil_mode=True)[:, 0].contiguous()
    region = pooled[:, 1] > 0.5
    if anchor is not None:
        region &= _distance_to(anchor).to(region.device) * cell <= reach * max(width, height)
    return TrackingTargets(distance=distance, region=region, other=(pooled[:, 0] > 0.5) & ~region, cell=cell,
                           width=width, height=height)


def _distance_to(inside: torch.Tensor) -> torch.Tensor:
    """Each pixel's Euclidean distance [px] to the nearest ``True`` pixel of its frame, float32 ``[T,H,W]`` (on
    the CPU) for ``inside`` [T,H,W] bool; a frame with none gets its diagonal everywhere. SciPy's exact transform
    (it comes with scikit-image): OpenCV's precise one differs in its last bits from run to run, and a fit must
    reproduce exactly."""
    import numpy as np
    from scipy.ndimage import distance_transform_edt

    frames = inside.cpu().numpy()
    distance = np.empty(frames.shape, dtype=np.float32)
    for index, frame in enumerate(frames):
        distance[index] = distance_transform_edt(~frame) if frame.any() else math.hypot(*frame.shape)
    return torch.from_numpy(distance)


def project_frames(points: torch.Tensor, intrinsics: torch.Tensor, world_to_cameras: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels [K,M,2] (OpenCV) and camera depths [K,M] of world points [K,M,3] seen by cameras ``intrinsics``
    [K,3,3] and ``world_to_cameras`` [K,4,4]; a point behind its camera gets depth <= 0 and a finite pixel."""
    camera = points @ world_to_cameras[:, :3, :3].transpose(1, 2) + world_to_cameras[:, None, :3, 3]
    depth = camera[..., 2]
    safe = torch.where(depth > 1e-6, depth, torch.ones_like(depth))
    return (camera[..., :2] / safe[..., None]) @ intrinsics[:, :2, :2].transpose(1, 2) + intrinsics[:, None, :2, 2], \
        depth


@torch.no_grad()
def covered_cells(pixels: torch.Tensor, front: torch.Tensor, faces: torch.Tensor, *, cell: int, rows: int,
                  columns: int) -> torch.Tensor:
    """The grid cells whose centre a projected sheet covers: ``[K,rows,cols]`` bool for ``K`` frames' vertex
    pixels ``pixels`` [K,V,2] (``front`` [K,V]: in front of the camera; a triangle with a corner behind it covers
    nothing). Each triangle is sampled on a barycentric lattice of spacing at most half a cell (up to 16 divisions
    of an edge): a triangle holding a cell's centre has a sample in that cell, and each cell a triangle's samples fall
    in is tested exactly (its centre inside the triangle, edges included)."""
    count = pixels.shape[0]
    covered = torch.zeros(count * rows * columns, dtype=torch.bool, device=pixels.device)
    corners = pixels[:, faces]  # [K,F,3,2]
    usable = front[:, faces].all(dim=2)  # [K,F]
    if not bool(usable.any()):
        return covered.reshape(count, rows, columns)
    edges = (corners - corners.roll(1, dims=2)).norm(dim=3).amax(dim=2)  # [K,F] longest edge [px]
    longest = float(torch.where(usable, edges, torch.zeros_like(edges)).max())
    divisions = int(min(_MAX_SPLAT_DIVISIONS, max(1, math.ceil(2.0 * longest / cell))))
    i, j = torch.meshgrid(torch.arange(divisions + 1, device=pixels.device),
                          torch.arange(divisions + 1, device=pixels.device), indexing="ij")
    keep = (i + j) <= divisions
    lattice = torch.stack([i[keep], j[keep], divisions - i[keep] - j[keep]], dim=1).float() / divisions  # [S,3]
    samples = (lattice @ corners.reshape(-1, 3, 2)).reshape(count, -1, 2)  # [K,F*S,2]
    column = torch.floor((samples[..., 0] + 0.5) / cell).long()
    row = torch.floor((samples[..., 1] + 0.5) / cell).long()
    hit = usable.repeat_interleave(lattice.shape[0], dim=1) & (column >= 0) & (column < columns) & (row >= 0) & \
        (row < rows)
    frame, sample = hit.nonzero(as_tuple=True)  # (a cell may come more than once)
    cell_index = row[frame, sample] * columns + column[frame, sample]
    a, b, c = corners[frame, sample // lattice.shape[0]].unbind(1)
    centre = torch.stack([cell_index % columns, cell_index // columns], dim=1).float() * cell + 0.5 * cell - 0.5

    def side(u, v):
        return (v[:, 0] - u[:, 0]) * (centre[:, 1] - u[:, 1]) - (v[:, 1] - u[:, 1]) * (centre[:, 0] - u[:, 0])

    s0, s1, s2 = side(a, b), side(b, c), side(c, a)
    inside = ((s0 >= 0) & (s1 >= 0) & (s2 >= 0)) | ((s0 <= 0) & (s1 <= 0) & (s2 <= 0))
    cells = rows * columns
    covered[(frame * cells + cell_index)[inside]] = True
    return covered.reshape(count, rows, columns)


def sheet_residual(part: "GarmentSheetPart", bones: torch.Tensor, states: torch.Tensor, seconds: list[float],
                   frames: list[int], *, skinned: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over ``frames`` (each >= 2) of the physics residual of each: mean over free vertices of
    ``|x_t - step(x_{t-1}, (x_{t-1} - x_{t-2}) / dt_{t-1})|^2`` over the mean edge length squared, for the
    states [T,V,3] in the poses ``bones`` [T,J+E,4,4] (``seconds`` [T]: each frame's interval [s]; ``skinned``
    [T,V,3]: the rest sheet skinned into every frame, when the caller has it)."""
    scale = 1.0 / (part.edge_length ** 2 * part.free_count)
    total = states.new_zeros(())
    for t in frames:
        rows = torch.arange(t - 2, t + 1, device=states.device)
        if skinned is None:
            x = part.state_vertices(bones[t - 2:t + 1], states.index_select(0, rows))
        else:
            x = skinned[t - 2:t + 1] + states.index_select(0, rows) * part.free_mask
        state = SheetState(x[1], (x[1] - x[0]) / seconds[t - 1])
        predicted = part.step(state, bones[t - 1], bones[t], seconds[t]).positions
        total = total + (((predicted - x[2]) ** 2) * part.free_mask).sum() * scale
    return total / max(1, len(frames))


MIN_AREA_RATIO = 0.1
"""Least area of a tracked sheet's triangle, as a share of its rest area, for the tracked state to be kept
(:meth:`SheetTracker.valid_frames`)."""


@torch.no_grad()
def valid_sheet_frames(part: "GarmentSheetPart", reference: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """[T] bool: the frames whose sheet ``vertices`` [T,V,3] is still a sheet against a ``reference`` sheet
    [T,V,3] of the same frames: finite, every triangle at least :data:`MIN_AREA_RATIO` of the smaller of its rest
    area and its area in the reference (a skinned rest sheet can be squashed itself), and facing the way it faces
    in the reference (the Gaussians bound to a squashed or turned-over triangle have no frame to follow)."""
    faces = part.faces

    def normals(points):
        a, b, c = points[:, faces[:, 0]], points[:, faces[:, 1]], points[:, faces[:, 2]]
        return torch.cross(b - a, c - a, dim=2)  # [T,F,3], length twice the area

    posed, before = normals(vertices), normals(reference)
    area = 0.5 * posed.norm(dim=2)
    least = torch.minimum(part.rest_area.to(area)[None], 0.5 * before.norm(dim=2))
    facing = (posed * before).sum(dim=2) > 0.0
    finite = torch.isfinite(vertices).flatten(1).all(dim=1)
    return finite & ((area >= MIN_AREA_RATIO * least) & facing).all(dim=1)


class SheetTracker:
    """The sheet tracking stage: every training frame's state fitted to its mask at once, without rendering.

    The terms, each a 0-dim tensor in units of the sheet's mean edge length ``l`` (in pixels, ``l`` projected at
    the frame's median vertex depth, so a miss of one edge length costs 1 at any distance):

    * ``outside``: mean over the frames, and over the free vertices and the triangles' centroids in front of the
      camera, of ``(max(0, D(p) - c / 2) / l)^2``, ``D`` the distance to the frame's mask sampled bilinearly at
      the point's pixel ``p`` (plus its distance outside the frame), ``c`` the cell;
    * ``uncovered``: mean over the frames of the sum over the garment cells the projected sheet does not cover of
      ``(max(0, d - c / 2) / l)^2``, ``d`` the distance of the cell's centre to the nearest free vertex, over the
      garment's cell count (so it is the uncovered share times their mean squared miss);
    * ``dynamics``: :func:`sheet_residual` over the frames ``2 .. T-1`` (an iteration: ``dynamics_frames`` of them,
      cycling; 0: all);
    * ``edges``: mean over the frames and edges of ``(length / rest length - 1)^2`` (cloth barely stretches).

    Args:
        part: the sheet part.
        bones: [T,J+E,4,4] the training frames' skinning transforms; ``seconds`` [T] their intervals [s].
        intrinsics: [T,3,3]; ``world_to_cameras``: [T,4,4] the frames' cameras.
        targets: the frames' :class:`TrackingTargets`.
        lambda_dynamics, lambda_edges: the weights of ``dynamics`` and ``edges`` (the silhouette terms weigh 1).
        dynamics_frames: frames of an iteration's residual (0: every frame ``t >= 2``).
    """

    def __init__(self, part: "GarmentSheetPart", bones: torch.Tensor, seconds: list[float], intrinsics: torch.Tensor,
                 world_to_cameras: torch.Tensor, targets: TrackingTargets, *, lambda_dynamics: float,
                 lambda_edges: float, dynamics_frames: int = 0):
        self.part, self.bones, self.seconds = part, bones, list(seconds)
        self.dynamics_frame_count = int(dynamics_frames)
        self.intrinsics, self.world_to_cameras, self.targets = intrinsics, world_to_cameras, targets
        self.lambda_dynamics, self.lambda_edges = float(lambda_dynamics), float(lambda_edges)
        with torch.no_grad():
            self.skinned = torch.stack([part.skinned_rest(b) for b in bones])  # [T,V,3]
        faces = part.faces
        edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values.unique(dim=0)
        self.edges = edges
        rest = part.rest_vertices
        self.rest_lengths = (rest[edges[:, 0]] - rest[edges[:, 1]]).norm(dim=1).clamp_min(1e-9)
        self.free = part.free_mask[:, 0] > 0
        self.centres = targets.centres()
        self.focal = 0.5 * (intrinsics[:, 0, 0] + intrinsics[:, 1, 1])  # [T] [px]
        self.region_cells = targets.region.flatten(1).sum(dim=1)  # [T]

    def vertices(self, states: torch.Tensor) -> torch.Tensor:
        """The frames' sheets [T,V,3] of states [T,V,3]."""
        return self.skinned + states * self.part.free_mask

    def valid_frames(self, states: torch.Tensor) -> torch.Tensor:
        """[T] bool: :func:`valid_sheet_frames` of the frames' sheets at states [T,V,3], against their skinned rest
        sheets."""
        return valid_sheet_frames(self.part, self.skinned, self.vertices(states))

    def _projected(self, vertices: torch.Tensor):
        pixels, depth = project_frames(vertices, self.intrinsics, self.world_to_cameras)
        front = depth > 1e-6
        with torch.no_grad():
            free_depth = torch.where(front & self.free, depth, torch.full_like(depth, math.nan))
            median = free_depth.nanmedian(dim=1).values
            median = torch.where(torch.isfinite(median), median, torch.ones_like(median)).clamp_min(1e-6)
            edge_pixels = (self.focal * self.part.edge_length / median).clamp_min(1e-6)  # [T] [px]
        return pixels, depth, front, edge_pixels

    def _outside(self, vertices, edge_pixels) -> torch.Tensor:
        targets = self.targets
        faces = self.part.faces
        points = torch.cat([vertices, vertices[:, faces].mean(dim=2)], dim=1)  # [T,V+F,3]
        pixels, depth = project_frames(points, self.intrinsics, self.world_to_cameras)
        counted = (depth > 1e-6) & torch.cat([self.free, self.free.new_ones(faces.shape[0])])[None]
        rows, columns = targets.distance.shape[1:]
        cell = float(targets.cell)
        grid = (pixels + 0.5) / cell - 0.5  # [T,M,2] in cells (centres at integers)
        high = grid.new_tensor([columns - 1, rows - 1])
        clamped = torch.minimum(torch.maximum(grid, torch.zeros_like(grid)), high)
        beyond = (grid - clamped).norm(dim=2) * cell  # [px] outside the frame
        normalized = clamped / high.clamp_min(1.0) * 2.0 - 1.0
        sampled = torch.nn.functional.grid_sample(targets.distance[:, None], normalized[:, None], mode="bilinear",
                                                  align_corners=True)[:, 0, 0]  # [T,M] [px]
        miss = torch.relu(sampled + beyond - 0.5 * cell) / edge_pixels[:, None]
        each = (miss ** 2 * counted).sum(dim=1) / counted.sum(dim=1).clamp_min(1)
        return each.mean()

    def _uncovered(self, pixels, front, edge_pixels, *, covered: torch.Tensor | None = None) -> torch.Tensor:
        targets = self.targets
        count = pixels.shape[0]
        if covered is None:
            covered = covered_cells(pixels.detach(), front, self.part.faces, cell=targets.cell,
                                    rows=targets.region.shape[1], columns=targets.region.shape[2])
        missing = (targets.region & ~covered).flatten(1)
        frame, cell_index = missing.nonzero(as_tuple=True)
        centres = self.centres[cell_index]
        candidates = front & self.free  # [T,V]
        nearest = torch.zeros_like(frame)
        with torch.no_grad():
            detached = pixels.detach()
            for start in range(0, frame.shape[0], 8192):
                rows = slice(start, start + 8192)
                squared = ((detached[frame[rows]] - centres[rows, None]) ** 2).sum(dim=2)
                squared = torch.where(candidates[frame[rows]], squared, torch.full_like(squared, math.inf))
                nearest[rows] = squared.argmin(dim=1)
        usable = candidates[frame, nearest]
        miss = torch.relu((pixels[frame, nearest] - centres).norm(dim=1) - 0.5 * targets.cell) / edge_pixels[frame]
        sums = pixels.new_zeros(count).index_add(0, frame, miss ** 2 * usable)
        has_region = self.region_cells > 0
        each = sums / self.region_cells.clamp_min(1)
        return (each * has_region).sum() / has_region.sum().clamp_min(1)

    def _edges(self, vertices) -> torch.Tensor:
        lengths = (vertices[:, self.edges[:, 0]] - vertices[:, self.edges[:, 1]]).norm(dim=2)
        return ((lengths / self.rest_lengths - 1.0) ** 2).mean()

    def dynamics_frames(self, iteration: int | None = None) -> list[int]:
        """The frames ``t >= 2`` of an iteration's residual: ``dynamics_frames`` of them, cycling over the sequence
        (every one when that is 0 or ``iteration`` is None)."""
        span = len(self.seconds) - 2
        if span <= 0:
            return []
        size = self.dynamics_frame_count
        if iteration is None or size <= 0 or size >= span:
            return list(range(2, span + 2))
        stride = 7 if span % 7 else 1  # (a stride coprime with the span visits every frame)
        return [2 + ((iteration * size + k) * stride) % span for k in range(size)]

    def terms(self, states: torch.Tensor, *, dynamics: bool = True, iteration: int | None = None
              ) -> dict[str, torch.Tensor]:
        """The four terms (class docstring) at states [T,V,3], differentiable in them (the residual over
        :meth:`dynamics_frames` of ``iteration``; ``dynamics=False``: without it)."""
        vertices = self.vertices(states)
        pixels, _, front, edge_pixels = self._projected(vertices)
        terms = {"outside": self._outside(vertices, edge_pixels),
                 "uncovered": self._uncovered(pixels, front, edge_pixels),
                 "edges": self._edges(vertices)}
        if dynamics:
            frames = self.dynamics_frames(iteration)
            terms["dynamics"] = sheet_residual(self.part, self.bones, states, self.seconds, frames,
                                               skinned=self.skinned) if frames else states.new_zeros(())
        return terms

    def loss(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        return terms["outside"] + terms["uncovered"] + self.lambda_dynamics * terms["dynamics"] + \
            self.lambda_edges * terms["edges"]

    @torch.no_grad()
    def coverage_iou(self, states: torch.Tensor) -> torch.Tensor:
        """Per frame [T]: the projected sheet's covered cells against the garment's, ``|C & R| / |R | (C - O)|``
        (``O`` the mask's other cells, where the sheet may lie in front of the body or behind it); 1 where a frame
        has neither."""
        vertices = self.vertices(states)
        pixels, depth = project_frames(vertices, self.intrinsics, self.world_to_cameras)
        targets = self.targets
        covered = covered_cells(pixels, depth > 1e-6, self.part.faces, cell=targets.cell,
                                rows=targets.region.shape[1], columns=targets.region.shape[2])
        region = targets.region
        both = (covered & region).flatten(1).sum(dim=1).float()
        either = (region | (covered & ~targets.other)).flatten(1).sum(dim=1).float()
        return torch.where(either > 0, both / either.clamp_min(1.0), torch.ones_like(both))

    @torch.no_grad()
    def measure(self, states: torch.Tensor) -> dict:
        """The terms (floats) and the coverage IoU (mean, min, per frame) at states [T,V,3]."""
        values = {name: float(value) for name, value in self.terms(states).items()}
        iou = self.coverage_iou(states)
        values["coverage_iou"] = {"mean": float(iou.mean()), "min": float(iou.min()),
                                  "per_frame": [round(float(v), 3) for v in iou]}
        return values

    def run(self, states: torch.Tensor, *, iterations: int, lr: float) -> tuple[torch.Tensor, dict]:
        """Fit states [T,V,3] (a start; not changed) with Adam for ``iterations``, the step ``lr`` [world units]
        decaying to a tenth of it along a cosine. Returns the fitted states (detached, zero on the ring) and a
        record: iterations, seconds, the terms and the coverage IoU before and after."""
        started = time.perf_counter()
        before = self.measure(states)
        fitted = (states.detach().clone() * self.part.free_mask).requires_grad_(True)
        optimizer = Adam([fitted], lr=lr)
        material = [p for p in self.part.cloth.parameters() if p.requires_grad]
        for parameter in material:  # (the states alone are fitted: the fit's gradients stay its own)
            parameter.requires_grad_(False)
        try:
            for iteration in range(iterations):
                optimizer.param_groups[0]["lr"] = lr * (0.55 + 0.45 * math.cos(math.pi * iteration / iterations))
                optimizer.zero_grad(set_to_none=True)
                self.loss(self.terms(fitted, iteration=iteration)).backward()
                fitted.grad.mul_(self.part.free_mask)
                optimizer.step()
        finally:
            for parameter in material:
                parameter.requires_grad_(True)
        fitted = fitted.detach() * self.part.free_mask
        # a frame whose fitted sheet is not a sheet any more (a non-finite vertex, a triangle squashed below
        # MIN_AREA_RATIO of its rest area or turned over) keeps the state it started from: a silhouette cannot
        # tell a collapsed or folded-through panel from a valid one, and the Gaussians bound to it have no frame
        valid = self.valid_frames(fitted)
        fitted = torch.where(valid[:, None, None], fitted, states.detach() * self.part.free_mask)
        after = self.measure(fitted)
        record = {"iterations": int(iterations), "seconds": round(time.perf_counter() - started, 3),
                  "kept_frames": int((~valid).sum()),
                  "frames": int(states.shape[0]), "garment_cells_per_frame": float(self.region_cells.float().mean())}
        for name in ("outside", "uncovered", "dynamics", "edges"):
            record[name] = {"before": before[name], "after": after[name]}
        record["coverage_iou"] = {"before": {k: before["coverage_iou"][k] for k in ("mean", "min")},
                                  "after": after["coverage_iou"]}
        return fitted, record


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
        self.skinned: torch.Tensor | None = None  # the frames' skinned rest sheets [T,V,3] (at the last refresh)
        self._states_before: torch.Tensor | None = None  # the states before this step's optimizer step
        #: steps whose sheet gradients held a non-finite value (zeroed), and frame states put back because a step
        #: left their sheet invalid (:func:`valid_sheet_frames`): 0-dim counters on the device
        self.non_finite_steps = torch.zeros((), dtype=torch.int64, device=self.fit.device)
        self.reverted_states = torch.zeros((), dtype=torch.int64, device=self.fit.device)
        #: the tracking stage's runs (:meth:`track`): one record each, in order
        self.tracking: list[dict] = []
        self.tracked = -1  # step of the last tracking run
        #: what the fit's end measured of the final states (:meth:`silhouette_check`), or None
        self.final_silhouette: dict | None = None
        self._mask_distance: torch.Tensor | None = None  # [T,rows,cols] (tracking_targets, computed once)
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
    def refresh(self, step: int, *, track: bool = True) -> None:
        """Re-read the vertices' skinning weights, start the states from a rollout (once), track them to the masks
        when due (:meth:`track`: right after the rollout, then every ``--garment-sheet-track-every`` steps; never
        with ``track=False``) and refill the table novel views of training instants use."""
        part, frames, options = self.part, self.fit.frames, self.options
        field = self.fit.skinning.field
        part.set_vertex_weights(field.weights(part.rest_vertices, field.grid_weights()))
        self.bones = self._training_bones()
        self.skinned = torch.stack([part.skinned_rest(b) for b in self.bones])
        started = part.frame_states.shape[0] != frames.count
        if started:
            positions, _ = part.rollout(self.bones, frames.seconds)
            skinned = torch.stack([part.skinned_rest(b) for b in self.bones])
            part.frame_states = torch.nn.Parameter((positions - skinned) * part.free_mask)
            self.states_optimizer = Adam([part.frame_states],
                                         lr=self.options.lr_garment_sheet_states * part.edge_length)
            self.image_steps = [0] * frames.count
            self.initial_residual = self.whole_residual()
        every = options.garment_sheet_track_every
        if track and (started or (every > 0 and self.tracked >= 0 and step - self.tracked >= every)):
            self.track(step)
        part.set_training_table(frames.bone_transforms, part.state_vertices(self.bones, part.frame_states.detach()))
        self.refreshed = step

    # ------------------------------------------------------------------------------------------ tracking
    @property
    def tracks(self) -> bool:
        """The tracking stage runs: ``--garment-sheet-track-iterations`` > 0 and the training frames have masks."""
        return self.options.garment_sheet_track_iterations > 0 and self.fit.frames.masks is not None

    @torch.no_grad()
    def tracking_targets(self) -> TrackingTargets:
        """The training frames' tracking targets (:func:`tracking_targets`): their masks' distances (computed once),
        the garment's region (``--garment-sheet-track-region``: 'body', the mask where a render of the avatar
        without the garment has alpha under one half; 'share', the mask where the garment Gaussians' share of a
        render of the whole avatar, its sheet at the current states, is over one half of the alpha) within reach
        of the skinned rest sheet."""
        part, frames, fit = self.part, self.fit.frames, self.fit
        masks = frames.masks
        count, height, width = masks.shape
        grid = fit.skinning.field.grid_weights()
        vertices = part.state_vertices(self.bones, part.frame_states.detach())
        ids = part.gaussian_ids
        not_garment = torch.zeros(count, height, width, dtype=torch.bool, device=masks.device)
        share_mode = self.options.garment_sheet_track_region == "share"
        for index in range(count):
            camera = frames.cameras[index]
            posed = fit.avatar.pose(frames.bone_transforms[index], frame_index=index, grid=grid,
                                    inputs={part.name: vertices[index]})
            opacities = posed["opacities"].clone()
            colors = torch.zeros(opacities.shape[0], 3, device=opacities.device)
            if share_mode:
                colors[ids] = 1.0
            else:
                opacities[ids] = 0.0
            image, alpha = ops.rasterize_gaussians(
                posed["means"], posed["quats"], posed["scales"], opacities, colors, self.intrinsics[index],
                self.world_to_cameras[index], int(camera.width), int(camera.height))[:2]
            if share_mode:
                garment = (image[..., 0] >= 0.5 * alpha) & (alpha >= 0.05)
                not_garment[index] = ~garment
            else:
                not_garment[index] = alpha >= 0.5
        cell = tracking_cell(width, height)
        rows, columns = -(-height // cell), -(-width // cell)
        skinned = torch.stack([part.skinned_rest(b) for b in self.bones])
        pixels, depth = project_frames(skinned, self.intrinsics, self.world_to_cameras)
        anchor = covered_cells(pixels, depth > 1e-6, part.faces, cell=cell, rows=rows, columns=columns)
        targets = tracking_targets(masks, not_garment, anchor=anchor, distance=self._mask_distance)
        self._mask_distance = targets.distance
        return targets

    def tracker(self, targets: TrackingTargets | None = None) -> SheetTracker:
        """The tracking stage's :class:`SheetTracker` of the training frames (``targets``: default
        :meth:`tracking_targets`)."""
        options = self.options
        return SheetTracker(self.part, self.bones, self.fit.frames.seconds, self.intrinsics, self.world_to_cameras,
                            self.tracking_targets() if targets is None else targets,
                            lambda_dynamics=options.lambda_garment_sheet_track_dynamics,
                            lambda_edges=options.lambda_garment_sheet_track_edges,
                            dynamics_frames=options.garment_sheet_track_frames)

    def track(self, step: int) -> dict | None:
        """The tracking stage (:class:`SheetTracker`): fit every training frame's state to its mask at once, from
        the states as they are; its record (also logged as ``"garment_sheet_tracking"``), or None when it does not
        run (:attr:`tracks`)."""
        if not self.tracks:
            return None
        options, part = self.options, self.part
        with torch.enable_grad():
            fitted, record = self.tracker().run(part.frame_states.detach(),
                                                iterations=options.garment_sheet_track_iterations,
                                                lr=options.lr_garment_sheet_track * part.edge_length)
        with torch.no_grad():
            part.frame_states.copy_(fitted)
        record = {"step": int(step), "region": options.garment_sheet_track_region, **record}
        self.tracking.append(record)
        self.tracked = int(step)
        self.fit.log({"step": step, "garment_sheet_tracking": record})
        return record

    @torch.no_grad()
    def silhouette_check(self) -> dict | None:
        """The tracking terms and coverage IoU of the states as they are (:meth:`SheetTracker.measure`: whether the
        image loss kept what tracking reached), or None without masks."""
        if self.fit.frames.masks is None or self.bones is None:
            return None
        return self.tracker().measure(self.part.frame_states.detach())

    def frame_input(self, step) -> torch.Tensor:
        """The step frame's sheet from its state (with gradients): the part's explicit input."""
        if self.bones is None or step.step - self.refreshed >= self.options.garment_refresh_every:
            self.refresh(step.step)
        index = step.index
        self.image_steps[index] += 1
        self.fitted = self.part.state_vertices(self.bones[index:index + 1], self.part.frame_states[index:index + 1])[0]
        return self.fitted

    def _residual(self, frames: list[int]) -> torch.Tensor:
        """:func:`sheet_residual` of the fitted states over ``frames`` (each >= 2)."""
        return sheet_residual(self.part, self.bones, self.part.frame_states, self.fit.frames.seconds, frames)

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
            pixels, depth = project_points(self.fitted, self.intrinsics[frame], self.world_to_cameras[frame])
            outside, uncovered = extension._silhouette(step, pixels, depth)
            terms.update(garment_outside=LossTerm(options.lambda_garment_silhouette, outside),
                         garment_uncovered=LossTerm(options.lambda_garment_silhouette, uncovered))
        return terms

    def optimizers(self) -> list:
        return [self.optimizer] + ([self.states_optimizer] if self.states_optimizer is not None else [])

    @torch.no_grad()
    def after_backward(self, step) -> None:
        """Zero any non-finite gradient of the sheet's states and material (a near-degenerate triangle's frame has
        unbounded derivatives; one inf would make Adam's moments NaN for good), counting such steps, and keep the
        states as they are before the optimizer steps them (:meth:`after_step`)."""
        grads = [p.grad for p in self.part.cloth.parameters() if p.grad is not None]
        states = self.part.frame_states
        if states.grad is not None:
            grads.append(states.grad)
        if grads:
            bad = torch.stack([(~torch.isfinite(g)).any() for g in grads]).any()
            self.non_finite_steps += bad.to(torch.int64)
            for g in grads:
                torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        if self.states_optimizer is not None and states.shape[0]:
            if self._states_before is None or self._states_before.shape != states.shape:
                self._states_before = states.detach().clone()
            else:
                self._states_before.copy_(states.detach())

    @torch.no_grad()
    def after_step(self, step) -> None:
        """Put back the state of every frame whose sheet the step left invalid (:func:`valid_sheet_frames` against
        the sheet before the step: non-finite, a triangle squashed or turned over) and clear its Adam moments, so
        one bad step cannot end the fit in non-finite Gaussians (no host synchronization: the rows are selected on
        the device)."""
        states = self.part.frame_states
        if self._states_before is None or self.skinned is None or self._states_before.shape != states.shape \
                or self.skinned.shape != states.shape:
            return
        free = self.part.free_mask
        before = self._states_before
        changed = (states != before).flatten(1).any(dim=1)
        keep = (valid_sheet_frames(self.part, self.skinned + before * free, self.skinned + states * free)
                | ~changed)[:, None, None]
        states.copy_(torch.where(keep, states, before))
        moments = self.states_optimizer.state.get(states, {})
        for name in ("exp_avg", "exp_avg_sq"):
            if name in moments:
                moments[name].mul_(keep)
        self.reverted_states += (~keep).sum()

    def log_values(self) -> dict[str, float]:
        cloth = self.part.cloth
        values = {"garment_sheet_stretch": float(cloth.stretch_stiffness().detach()),
                  "garment_sheet_bend": float(cloth.bend_stiffness().detach()),
                  "garment_sheet_damping": float(cloth.damping().detach()),
                  "garment_sheet_drag": float(cloth.drag().detach())}
        if self.image_steps:
            values["garment_sheet_steps_per_frame"] = sum(self.image_steps) / len(self.image_steps)
        values["garment_sheet_reverted_states"] = int(self.reverted_states)
        values["garment_sheet_non_finite_steps"] = int(self.non_finite_steps)
        return values

    # ------------------------------------------------------------------------------------------ the end
    def finish(self, step: int) -> None:
        self.refresh(step, track=False)
        self.final_residual = self.whole_residual()
        self.final_silhouette = self.silhouette_check()
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
                "reverted_states": int(self.reverted_states), "non_finite_steps": int(self.non_finite_steps),
                "initial_residual": self.initial_residual, "final_residual": self.final_residual,
                "tracking": list(self.tracking), "final_silhouette": self.final_silhouette,
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
        lines = [f"garment sheet: {report['vertices']} vertices, {report['triangles']} triangles, "
                 f"{report['pinned']} pinned; states fitted {steps['mean']:.1f} image steps a frame "
                 f"(min {steps['min']}),"
                 f" physics residual {report['initial_residual'] or 0.0:.3g} at the rollout, "
                 f"{'not measured' if final is None else f'{final:.3g}'} at the end"]
        if self.tracking:
            first, last = self.tracking[0], self.tracking[-1]
            lines.append(f"garment sheet tracking: {len(self.tracking)} run(s) of {last['iterations']} iterations "
                         f"(last at step {last['step']}, {last['seconds']:.1f} s); sheet/garment IoU "
                         f"{first['coverage_iou']['before']['mean']:.3f} at the rollout, "
                         f"{last['coverage_iou']['before']['mean']:.3f} -> {last['coverage_iou']['after']['mean']:.3f} "
                         f"(min {last['coverage_iou']['after']['min']:.3f}) in the last run; outside "
                         f"{last['outside']['before']:.3g} -> {last['outside']['after']:.3g}, uncovered "
                         f"{last['uncovered']['before']:.3g} -> {last['uncovered']['after']:.3g}, residual "
                         f"{last['dynamics']['before']:.3g} -> {last['dynamics']['after']:.3g} (edge lengths^2)")
        check = report["final_silhouette"]
        if check is not None:
            lines.append(f"garment sheet at the end: sheet/garment IoU {check['coverage_iou']['mean']:.3f} "
                         f"(min {check['coverage_iou']['min']:.3f}), outside {check['outside']:.3g}, uncovered "
                         f"{check['uncovered']:.3g} (edge lengths^2)")
        return lines

    def state_dict(self) -> dict:
        return {"surface": "sheet", "part": self.part.state_for_file(), "optimizer": self.optimizer.state_dict(),
                "states_optimizer": None if self.states_optimizer is None else self.states_optimizer.state_dict(),
                "image_steps": list(self.image_steps), "residual_steps": self.residual_steps,
                "initial_residual": self.initial_residual, "refreshed": self.refreshed,
                "tracking": [dict(record) for record in self.tracking], "tracked": self.tracked,
                "reverted_states": int(self.reverted_states), "non_finite_steps": int(self.non_finite_steps)}

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
        sheet.tracking = [dict(record) for record in state.get("tracking", [])]
        sheet.tracked = int(state.get("tracked", -1))
        sheet.reverted_states.fill_(int(state.get("reverted_states", 0)))
        sheet.non_finite_steps.fill_(int(state.get("non_finite_steps", 0)))
        if part.frame_states.shape[0]:
            sheet.bones = sheet._training_bones()
            sheet.refreshed = int(state.get("refreshed", -1))
        return sheet


def project_points(points: torch.Tensor, K: torch.Tensor, world_to_camera: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`project_frames` for one frame: pixels [M,2] and camera depths [M] of world points [M,3] seen by a
    camera ``K`` [3,3], ``world_to_camera`` [4,4]."""
    pixels, depth = project_frames(points[None], K[None], world_to_camera[None])
    return pixels[0], depth[0]
