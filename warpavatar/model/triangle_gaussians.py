"""Gaussians bound to the triangles of a mesh (a garment sheet): the texture lives on the mesh's surface.

Each Gaussian belongs to one triangle and holds, in that triangle's terms (``kernels/triangle_binding.py``):
barycentric coordinates (stored as logits, ``softmax`` of them, so the point never leaves its triangle), an offset
along the normal [world units], a rotation in the triangle's frame (w, x, y, z) and log-scales at rest. Posed by
the mesh's vertices (:meth:`TriangleGaussians.posed`, :func:`warpavatar.ops.pose_triangle_gaussians`), it follows
the surface's material point, turns with its frame and stretches with its area, in every view and pose, as in
"GaussianAvatars: Photorealistic Head Avatars with Rigged 3D Gaussians" and "SplattingAvatar: Realistic Real-Time
Human Avatars with Mesh-Embedded Gaussian Splatting".

Binding (:meth:`TriangleGaussians.bind`): each existing Gaussian goes to the triangle of its closest surface point
(:func:`warpavatar.ops.closest_triangles`), at that point's barycentric coordinates (floored at
:data:`BARYCENTRIC_FLOOR` so their logits are finite) and at its signed distance along that triangle's normal; its
rotation and scales are expressed in the triangle's rest frame. Posed at rest, a Gaussian comes back where it was,
but for the tangential part of its distance when its closest point lies on an edge or corner of the triangle (a
point beyond a convex crease: at most the distance times the sine of half the crease's angle).

Density control per triangle (the caller decides *which* Gaussians, e.g. by screen-space gradient and size, as
3DGS does; these methods decide *how*, triangle by triangle, and return, for every Gaussian afterwards, the index
it came from, so the caller can gather the other per-Gaussian attributes and optimizer moments):

* :meth:`~TriangleGaussians.densify`: a triangle holds at most ``max_per_triangle`` Gaussians. Each selected
  Gaussian adds one: a *clone* is an exact copy on the same triangle (the two separate under later gradients); a
  *split* replaces the Gaussian by two on the same triangle, at its barycentric point moved by plus and minus its
  largest in-plane standard deviation (the longest of its three axes projected onto the triangle's rest plane),
  with log-scales lowered by ``log(1.6)`` (3DGS's factor) and the same offset and rotation; deterministic, so no
  random generator is needed. Where a triangle has room for fewer than its selected Gaussians, those of highest
  ``priority`` (by default the lowest index) go first; the others are left as they are.
* :meth:`~TriangleGaussians.prune`: removes the Gaussians not kept, but (``keep_last_per_triangle``) never the last
  one of a triangle: of a triangle's Gaussians all marked for removal, the one of highest ``priority`` stays, so
  every triangle keeps something to show and to receive gradients.

Both replace the parameters (new ``torch.nn.Parameter`` objects): an optimizer built on the old ones must be
rebuilt, or its state gathered with the returned index.
"""

from __future__ import annotations

import math

import torch

from warpavatar import ops
from warpavatar._src.triangle_binding import triangle_frames
from warpavatar.geometry import quat_conjugate, quat_from_matrix, quat_multiply, quat_to_matrix

__all__ = ["BARYCENTRIC_FLOOR", "SPLIT_SCALE_DIVISOR", "TriangleGaussians", "triangle_areas"]

BARYCENTRIC_FLOOR = 1.0e-4
"""Smallest barycentric weight a binding stores (its logit is ``log`` of it)."""

SPLIT_SCALE_DIVISOR = 1.6
"""A split Gaussian's children have its scales divided by this (as 3DGS)."""

_PARAMETER_NAMES = ("barycentric_logits", "offsets", "local_quats", "local_log_scales")


def triangle_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area [world units^2] ``[F]`` of each triangle ``faces`` ``[F, 3]`` of ``vertices`` ``[V, 3]``."""
    corners = vertices[faces.long()]
    return 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1).norm(dim=-1)


def _mesh_arrays(mesh, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(vertices float32 [V, 3], faces int64 [F, 3]) of a ``(vertices, faces)`` pair or an object with
    ``.vertices`` and ``.faces`` (a ``trimesh.Trimesh``, a garment sheet)."""
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        vertices, faces = mesh
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        vertices, faces = mesh.vertices, mesh.faces
    else:
        raise TypeError("mesh must be a (vertices, faces) pair or have .vertices and .faces (a trimesh.Trimesh)")
    vertices = torch.as_tensor(vertices).to(device=device, dtype=torch.float32)
    faces = torch.as_tensor(faces).to(device=device)
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"mesh vertices must have shape [V, 3], got {list(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point() or faces.shape[0] == 0:
        raise ValueError(f"mesh faces must be integer vertex ids of shape [F, 3], F >= 1, got {faces.dtype} "
                         f"{list(faces.shape)}")
    faces = faces.long()
    if int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]:
        raise ValueError(f"mesh faces must hold vertex ids in [0, {vertices.shape[0]})")
    return vertices.contiguous(), faces.contiguous()


class TriangleGaussians(torch.nn.Module):
    """Gaussians bound to the triangles of a mesh (module docstring).

    Args:
        rest_vertices: float ``[V, 3]`` the mesh's rest shape [world units] (the frames and areas of binding).
        faces: integer ``[F, 3]`` vertex ids of each triangle.
        triangle_ids: integer ``[N]`` each Gaussian's triangle.
        barycentric_logits: float ``[N, 3]``; the weights are their softmax.
        offsets: float ``[N]`` along the triangle's unit normal [world units].
        local_quats: float ``[N, 4]`` (w, x, y, z) in the triangle's frame.
        local_log_scales: float ``[N, 3]`` at the rest shape.

    Raises:
        ValueError: shapes that do not agree, ids out of range, a degenerate rest triangle.
    """

    def __init__(self, rest_vertices: torch.Tensor, faces: torch.Tensor, triangle_ids: torch.Tensor,
                 barycentric_logits: torch.Tensor, offsets: torch.Tensor, local_quats: torch.Tensor,
                 local_log_scales: torch.Tensor):
        super().__init__()
        rest_vertices, faces = _mesh_arrays((rest_vertices, faces), torch.as_tensor(rest_vertices).device)
        device = rest_vertices.device
        triangle_ids = torch.as_tensor(triangle_ids).to(device=device)
        if triangle_ids.dim() != 1 or triangle_ids.is_floating_point():
            raise ValueError(f"triangle_ids must be integer ids of shape [N], got {triangle_ids.dtype} "
                             f"{list(triangle_ids.shape)}")
        count = triangle_ids.shape[0]
        if count and (int(triangle_ids.min()) < 0 or int(triangle_ids.max()) >= faces.shape[0]):
            raise ValueError(f"triangle_ids must hold triangle ids in [0, {faces.shape[0]})")
        for name, value, width in (("barycentric_logits", barycentric_logits, 3), ("offsets", offsets, None),
                                   ("local_quats", local_quats, 4), ("local_log_scales", local_log_scales, 3)):
            expected = [count] if width is None else [count, width]
            if list(value.shape) != expected:
                raise ValueError(f"{name} must have shape {expected}, got {list(value.shape)}")
        rest_area = triangle_areas(rest_vertices.double(), faces)
        longest = (rest_vertices[faces] - rest_vertices[faces].roll(1, dims=1)).double().norm(dim=-1).amax(dim=1)
        if bool((rest_area <= 1e-9 * longest.square().clamp_min(1e-30)).any()):
            raise ValueError("the rest mesh has degenerate triangles (zero area): clean it first")
        self.register_buffer("rest_vertices", rest_vertices)
        self.register_buffer("faces", faces)
        self.register_buffer("rest_area", rest_area.float())
        self.register_buffer("triangle_ids", triangle_ids.long())
        self.barycentric_logits = torch.nn.Parameter(barycentric_logits.detach().to(device, torch.float32).clone())
        self.offsets = torch.nn.Parameter(offsets.detach().to(device, torch.float32).clone())
        self.local_quats = torch.nn.Parameter(local_quats.detach().to(device, torch.float32).clone())
        self.local_log_scales = torch.nn.Parameter(local_log_scales.detach().to(device, torch.float32).clone())

    # ------------------------------------------------------------------------------------------------ binding
    @classmethod
    def bind(cls, points: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, mesh, *,
             max_distance: float = 1.0e6) -> "TriangleGaussians":
        """Bind existing Gaussians to their closest triangles of ``mesh`` in its rest shape (module docstring).

        Args:
            points: float ``[N, 3]`` the Gaussians' centres [world units].
            quats: float ``[N, 4]`` their (w, x, y, z) rotations (normalized here).
            scales: float ``[N, 3]`` their scales [world units] (> 0).
            mesh: the rest mesh, a ``(vertices [V, 3], faces [F, 3])`` pair or an object with ``.vertices`` and
                ``.faces`` (a ``trimesh.Trimesh``, a garment sheet); on any device (moved to the points').
            max_distance: farthest a Gaussian may lie from the mesh [world units].

        Raises:
            ValueError: bad shapes, a Gaussian farther than ``max_distance`` from every triangle.
        """
        device = points.device
        vertices, faces = _mesh_arrays(mesh, device)
        count = points.shape[0]
        for name, value, width in (("points", points, 3), ("quats", quats, 4), ("scales", scales, 3)):
            if value.dim() != 2 or list(value.shape) != [count, width]:
                raise ValueError(f"{name} must have shape [{count}, {width}], got {list(value.shape)}")
        points = points.detach().float()
        triangle_ids, barycentrics = ops.closest_triangles(points, vertices, faces, max_distance=max_distance)
        if bool((triangle_ids < 0).any()):
            raise ValueError(f"{int((triangle_ids < 0).sum())} Gaussians lie farther than max_distance="
                             f"{max_distance} from the mesh")
        corners = vertices[faces[triangle_ids]]
        frame, normal, _ = triangle_frames(corners.double())
        barycentrics = barycentrics.double().clamp_min(BARYCENTRIC_FLOOR)
        barycentrics = barycentrics / barycentrics.sum(dim=1, keepdim=True)
        foot = (barycentrics[:, :, None] * corners.double()).sum(1)
        offsets = ((points.double() - foot) * normal).sum(1)
        unit = quats.detach().double()
        unit = unit / unit.norm(dim=1, keepdim=True).clamp_min(1e-12)
        local_quats = quat_multiply(quat_conjugate(quat_from_matrix(frame)), unit)
        local_log_scales = scales.detach().double().clamp_min(1e-12).log()
        return cls(vertices, faces, triangle_ids, barycentrics.log().float(), offsets.float(), local_quats.float(),
                   local_log_scales.float())

    # -------------------------------------------------------------------------------------------------- views
    @property
    def count(self) -> int:
        """Number of Gaussians."""
        return self.triangle_ids.shape[0]

    @property
    def triangle_count(self) -> int:
        return self.faces.shape[0]

    def barycentrics(self) -> torch.Tensor:
        """Barycentric weights ``[N, 3]`` (softmax of the logits: positive, summing to 1)."""
        return torch.softmax(self.barycentric_logits, dim=1)

    def gaussians_per_triangle(self) -> torch.Tensor:
        """How many Gaussians each triangle holds, int64 ``[F]``."""
        return torch.bincount(self.triangle_ids, minlength=self.triangle_count)

    def posed(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The Gaussians on the mesh posed at ``vertices`` (float ``[V, 3]``, differentiable).

        Returns:
            ``(means [N, 3], quats [N, 4], scales [N, 3])`` float32: world centres [world units], (w, x, y, z)
            rotations (unnormalized: the local rotations' norms), scales [world units].
        """
        if list(vertices.shape) != list(self.rest_vertices.shape):
            raise ValueError(f"vertices must have shape {list(self.rest_vertices.shape)}, got {list(vertices.shape)}")
        means, quats, log_scales = ops.pose_triangle_gaussians(
            vertices.to(torch.float32), self.faces, self.rest_area, self.triangle_ids, self.barycentrics(),
            self.offsets, self.local_quats, self.local_log_scales)
        return means, quats, log_scales.exp()

    # ---------------------------------------------------------------------------------------- density control
    def _replace(self, index: torch.Tensor, **overrides: torch.Tensor) -> None:
        """Keep the Gaussians ``index`` (repeats allowed), then overwrite the rows given in ``overrides``: each a
        ``(rows, values)`` pair."""
        self.triangle_ids = self.triangle_ids[index]
        for name in _PARAMETER_NAMES:
            values = getattr(self, name).detach()[index].clone()
            if name in overrides:
                rows, new = overrides[name]
                values[rows] = new.to(values.dtype)
            setattr(self, name, torch.nn.Parameter(values))

    def _admitted(self, selected: torch.Tensor, priority: torch.Tensor | None, max_per_triangle: int
                  ) -> torch.Tensor:
        """Ids of the selected Gaussians that fit under the cap, each triangle's highest priority first."""
        candidates = torch.nonzero(selected).squeeze(1)
        if candidates.numel() == 0:
            return candidates
        order_key = (-priority[candidates].double() if priority is not None
                     else candidates.double())
        order = torch.argsort(order_key, stable=True)
        candidates = candidates[order]
        triangles = self.triangle_ids[candidates]
        # rank of each candidate among its triangle's candidates (a stable sort by triangle keeps the priority order)
        by_triangle = torch.argsort(triangles, stable=True)
        sorted_triangles = triangles[by_triangle]
        first = torch.searchsorted(sorted_triangles, sorted_triangles, right=False)
        rank = torch.empty_like(by_triangle)
        rank[by_triangle] = torch.arange(by_triangle.numel(), device=by_triangle.device) - first
        room = (max_per_triangle - self.gaussians_per_triangle())[triangles]
        return torch.sort(candidates[rank < room]).values

    def _split_children(self, ids: torch.Tensor) -> torch.Tensor:
        """Barycentric logits ``[2, M, 3]`` of the two children of each split Gaussian ``ids`` (module doc)."""
        corners = self.rest_vertices[self.faces[self.triangle_ids[ids]]].double()  # [M, 3, 3]
        frame, normal, _ = triangle_frames(corners)
        weights = torch.softmax(self.barycentric_logits.detach()[ids].double(), dim=1)
        quats = self.local_quats.detach()[ids].double()
        rotation = frame @ quat_to_matrix(quats / quats.norm(dim=1, keepdim=True).clamp_min(1e-12))
        axes = rotation * self.local_log_scales.detach()[ids].double().exp()[:, None, :]  # columns: sigma_k axis_k
        in_plane = axes - normal[:, :, None] * (normal[:, :, None] * axes).sum(1, keepdim=True)
        longest = in_plane.norm(dim=1).argmax(dim=1)
        step = in_plane[torch.arange(ids.numel(), device=ids.device), :, longest]  # [M, 3]
        a, b, c = corners.unbind(1)
        edges = torch.stack([b - a, c - a], dim=2)  # [M, 3, 2]
        gram = edges.transpose(1, 2) @ edges
        # the move in barycentric terms: d(v, w) solving edges @ (dv, dw) = step (in-plane), du = -(dv + dw)
        dvw = torch.linalg.solve(gram, (edges.transpose(1, 2) @ step[:, :, None]))[:, :, 0]
        delta = torch.stack([-(dvw[:, 0] + dvw[:, 1]), dvw[:, 0], dvw[:, 1]], dim=1)
        children = []
        for sign in (1.0, -1.0):
            moved = (weights + sign * delta).clamp_min(BARYCENTRIC_FLOOR)
            children.append((moved / moved.sum(dim=1, keepdim=True)).log())
        return torch.stack(children)

    def densify(self, selected: torch.Tensor, *, split: torch.Tensor | None = None, max_per_triangle: int,
                priority: torch.Tensor | None = None) -> torch.Tensor:
        """Clone or split the ``selected`` Gaussians, at most ``max_per_triangle`` a triangle (module docstring).

        Args:
            selected: bool ``[N]`` the Gaussians to densify.
            split: bool ``[N]`` which of them are split (the others are cloned); default none.
            max_per_triangle: cap of Gaussians a triangle may hold afterwards (>= 1).
            priority: float ``[N]``, higher first where a triangle has too little room (e.g. the gradient).

        Returns:
            int64 ``[N']`` for each Gaussian afterwards, the index (before) of the one it is, was cloned or split
            from: the old ones first (a split Gaussian's place holds its first child), then the new ones.
        """
        count = self.count
        split = torch.zeros_like(selected) if split is None else split
        for name, mask in (("selected", selected), ("split", split)):
            if mask.dtype != torch.bool or list(mask.shape) != [count]:
                raise ValueError(f"{name} must be a bool mask of shape [{count}], got {mask.dtype} "
                                 f"{list(mask.shape)}")
        if priority is not None and list(priority.shape) != [count]:
            raise ValueError(f"priority must have shape [{count}], got {list(priority.shape)}")
        if isinstance(max_per_triangle, bool) or not isinstance(max_per_triangle, int) or max_per_triangle < 1:
            raise ValueError(f"max_per_triangle must be a positive int, got {max_per_triangle!r}")
        device = self.triangle_ids.device
        admitted = self._admitted(selected.to(device), None if priority is None else priority.to(device),
                                  max_per_triangle)
        splits = admitted[split.to(device)[admitted]]
        source = torch.cat([torch.arange(count, device=device), admitted])
        overrides = {}
        if splits.numel():
            children = self._split_children(splits)
            new_rows = count + torch.nonzero(split.to(device)[admitted]).squeeze(1)
            rows = torch.cat([splits, new_rows])
            overrides["barycentric_logits"] = (rows, torch.cat([children[0], children[1]]))
            smaller = self.local_log_scales.detach()[splits] - math.log(SPLIT_SCALE_DIVISOR)
            overrides["local_log_scales"] = (rows, torch.cat([smaller, smaller]))
        self._replace(source, **overrides)
        return source

    def prune(self, keep: torch.Tensor, *, keep_last_per_triangle: bool = True,
              priority: torch.Tensor | None = None) -> torch.Tensor:
        """Remove the Gaussians where ``keep`` (bool ``[N]``) is False, but never a triangle's last one when
        ``keep_last_per_triangle`` (the one of highest ``priority``, float ``[N]``, stays; default the first).

        Returns:
            int64 ``[N']`` the indices (before) of the Gaussians kept, in order.
        """
        count = self.count
        if keep.dtype != torch.bool or list(keep.shape) != [count]:
            raise ValueError(f"keep must be a bool mask of shape [{count}], got {keep.dtype} {list(keep.shape)}")
        if priority is not None and list(priority.shape) != [count]:
            raise ValueError(f"priority must have shape [{count}], got {list(priority.shape)}")
        device = self.triangle_ids.device
        keep = keep.to(device).clone()
        if keep_last_per_triangle and count:
            held = torch.bincount(self.triangle_ids[keep], minlength=self.triangle_count)
            orphaned = (held == 0)[self.triangle_ids]  # Gaussians of triangles that would be left empty
            if bool(orphaned.any()):
                key = (priority.to(device).double() if priority is not None
                       else -torch.arange(count, device=device, dtype=torch.float64))
                key = torch.where(orphaned, key, torch.full_like(key, -math.inf))
                best = torch.full((self.triangle_count,), -math.inf, dtype=torch.float64, device=device)
                best = best.scatter_reduce(0, self.triangle_ids, key, reduce="amax")
                chosen = orphaned & (key == best[self.triangle_ids])
                # ties: the first of them
                first = torch.full((self.triangle_count,), count, dtype=torch.int64, device=device)
                ids = torch.arange(count, device=device)
                first = first.scatter_reduce(0, self.triangle_ids[chosen], ids[chosen], reduce="amin")
                keep[first[first < count]] = True
        index = torch.nonzero(keep).squeeze(1)
        self._replace(index)
        return index
